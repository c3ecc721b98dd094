//! The emulated images' failure exit (QEMU): the reason on the host's stderr through
//! semihosting, then QEMU exits with failure. Shared by the panic and HardFault handlers of the
//! mps2 images `qemu` and `replay` and of `board-emu`.

use core::fmt::Write as _;

use cortex_m_semihosting::{debug, hio};

/// Prints `what` on the host's stderr (best effort: an error while printing must not stop the
/// exit) and exits QEMU with failure.
pub fn fail(what: core::fmt::Arguments<'_>) -> ! {
    if let Ok(mut err) = hio::hstderr() {
        let _ = err.write_fmt(what);
        let _ = err.write_str("\n");
    }
    debug::exit(debug::EXIT_FAILURE);
    #[allow(clippy::empty_loop)]
    loop {}
}
