//! Test helpers shared by the driver tests (host only).
//!
//! [`loop_holding`] builds the built-in stage's loop holding a constant reference, as the
//! converter drivers' loop tests run it.
//!
//! embedded-hal-mock 0.11's SPI mock cannot return errors, so [`FailingSpi`] wraps it and fails
//! one chosen transaction with a chosen `embedded_hal::spi::ErrorKind` before it reaches the
//! mock. The mock's expectation list then holds only the transactions that did go out, and its
//! `.done()` proves nothing was sent after the failure.

use embedded_hal::spi::{ErrorKind, ErrorType, Operation, SpiDevice};
use embedded_hal_mock::eh1::spi::{Mock, Transaction};

/// SPI device that fails transaction number `fail_at` (0-based) with `kind`.
pub struct FailingSpi {
    pub inner: Mock<u8>,
    pub fail_at: usize,
    pub kind: ErrorKind,
    count: usize,
}

impl FailingSpi {
    pub fn new(inner: Mock<u8>, fail_at: usize, kind: ErrorKind) -> Self {
        Self {
            inner,
            fail_at,
            kind,
            count: 0,
        }
    }
}

impl ErrorType for FailingSpi {
    type Error = ErrorKind;
}

impl SpiDevice for FailingSpi {
    fn transaction(&mut self, operations: &mut [Operation<'_, u8>]) -> Result<(), ErrorKind> {
        let n = self.count;
        self.count += 1;
        if n == self.fail_at {
            return Err(self.kind);
        }
        self.inner.transaction(operations)
    }
}

/// One chip-select-framed transaction that writes `bytes`.
pub fn write_frame(bytes: &[u8]) -> [Transaction<u8>; 3] {
    [
        Transaction::transaction_start(),
        Transaction::write_vec(bytes.to_vec()),
        Transaction::transaction_end(),
    ]
}

/// One chip-select-framed full-duplex transaction: sends `out`, receives `reply`.
pub fn transfer_frame(out: &[u8], reply: &[u8]) -> [Transaction<u8>; 3] {
    [
        Transaction::transaction_start(),
        Transaction::transfer_in_place(out.to_vec(), reply.to_vec()),
        Transaction::transaction_end(),
    ]
}

/// The built-in stage's loop ([`crate::demo::settings`], the compensator) holding a constant
/// reference `offsets_m` \[m\] per axis, its outputs starting at the window's lower edge.
pub fn loop_holding(offsets_m: [f32; 2]) -> crate::xy_loop::TwoAxisLoop {
    use crate::params;
    use crate::reference::{Program, ReferenceGenerator, Wave};
    use crate::xy_loop::{Feedforward, TwoAxisLoop};
    let reference = ReferenceGenerator::new(
        Program::PerAxis(offsets_m.map(|offset_m| Wave::Constant { offset: offset_m })),
        params::SAMPLE_PERIOD_S,
        [0.0; 2],
    );
    let initial = [
        params::AXES[0].limits.output_min_v,
        params::AXES[1].limits.output_min_v,
    ];
    TwoAxisLoop::new(
        crate::demo::settings().expect("the built-in stage's settings are valid"),
        Feedforward::Compensator,
        reference,
        initial,
    )
}
