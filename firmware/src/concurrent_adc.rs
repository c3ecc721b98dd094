//! The two ADS8681 of the board read at once, one on each SPI bus: both chip selects low, the
//! two 32-bit NOP frames clocked on SPI1 and SPI3 together, both chip selects high. The tick
//! waits one frame (32 bits at 21 MHz = 1.52 µs, [`crate::converter_timing::ADC_FRAME_CYCLES`])
//! instead of two one after the other, and both conversions start on the same CONVST/CS rising
//! edge pair, two instructions apart.
//!
//! Each bus keeps two bytes in flight (one shifting, one in the transmit buffer) so its SCLK
//! does not stop between bytes: with `s` bytes sent and `r` received, a byte is written when
//! `s − r < 2` and the transmit buffer is free, a byte is read as soon as one has arrived (it
//! must be, within one byte time, 381 ns = 64 core cycles, or the bus reports an overrun). The
//! polling is bounded ([`POLL_LIMIT`] rounds over both buses): a bus that stops clocking
//! gives [`FrameError::Timeout`] for its axis, never a hang. Before a frame, a byte left
//! received by an aborted frame is discarded.
//!
//! Frames are the driver's ([`crate::ads8681::Ads8681::read`]: a NOP command, the conversion
//! started at the end of the previous frame in bits 31..16 out); the conversion to metres is
//! [`crate::xy_loop::AdcPair`]'s (`scale.metres(code.to_volts())`). The ADCs are initialised
//! with the blocking driver before the buses are handed over here.

use core::convert::Infallible;

use embedded_hal::digital::OutputPin;
use embedded_hal_nb::nb;
use embedded_hal_nb::spi::FullDuplex;

use crate::codes::{AdcCode, SensorScale};
use crate::converter::{Error, ErrorKind, ErrorType};
use crate::xy_loop::{Axis, PairError, PositionSensor};

/// Bytes of an ADS8681 frame.
pub const FRAME_BYTES: usize = 4;

/// Rounds of polling both buses before a frame that has not ended counts as timed out. A
/// healthy frame ends after about 1.52 µs (256 core cycles), a few dozen rounds; 512 rounds of
/// at least ~10 cycles each are several frame times.
pub const POLL_LIMIT: u32 = 512;

/// Why one axis's frame failed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FrameError<E> {
    /// The bus reported an error (overrun, mode fault, ...).
    Spi(E),
    /// The frame did not end within [`POLL_LIMIT`] rounds.
    Timeout,
}

impl<E: embedded_hal::spi::Error> Error for FrameError<E> {
    fn kind(&self) -> ErrorKind {
        match self {
            FrameError::Spi(e) => ErrorKind::Bus(e.kind()),
            FrameError::Timeout => ErrorKind::Timeout,
        }
    }
}

/// Error of one axis of a [`ConcurrentAdcPair`] on buses `BX` and `BY`.
pub type ExchangeError<BX, BY> = PairError<
    FrameError<<BX as embedded_hal::spi::ErrorType>::Error>,
    FrameError<<BY as embedded_hal::spi::ErrorType>::Error>,
>;

/// One bus's progress through its frame.
struct Lane<E> {
    sent: usize,
    received: usize,
    rx: [u8; FRAME_BYTES],
    error: Option<FrameError<E>>,
}

impl<E> Lane<E> {
    fn new() -> Self {
        Self {
            sent: 0,
            received: 0,
            rx: [0; FRAME_BYTES],
            error: None,
        }
    }

    fn done(&self) -> bool {
        self.received == FRAME_BYTES || self.error.is_some()
    }

    /// One round on `bus`: write if the transmit side has room, read if a byte has arrived.
    #[inline(always)]
    fn poll<B: FullDuplex<u8, Error = E>>(&mut self, bus: &mut B) {
        if self.done() {
            return;
        }
        if self.sent < FRAME_BYTES && self.sent - self.received < 2 {
            match bus.write(0) {
                Ok(()) => self.sent += 1,
                Err(nb::Error::WouldBlock) => {}
                Err(nb::Error::Other(e)) => {
                    self.error = Some(FrameError::Spi(e));
                    return;
                }
            }
        }
        if self.received < self.sent {
            match bus.read() {
                Ok(byte) => {
                    self.rx[self.received] = byte;
                    self.received += 1;
                }
                Err(nb::Error::WouldBlock) => {}
                Err(nb::Error::Other(e)) => self.error = Some(FrameError::Spi(e)),
            }
        }
    }

    fn result(self) -> Result<AdcCode, FrameError<E>> {
        match self.error {
            Some(e) => Err(e),
            None if self.received == FRAME_BYTES => {
                Ok(AdcCode(u16::from_be_bytes([self.rx[0], self.rx[1]])))
            }
            None => Err(FrameError::Timeout),
        }
    }
}

/// Two ADS8681, x on `BX` with chip select `CX`, y on `BY` with `CY`, read at once.
#[derive(Debug)]
pub struct ConcurrentAdcPair<BX, BY, CX, CY> {
    /// x-axis bus.
    pub bus_x: BX,
    /// y-axis bus.
    pub bus_y: BY,
    /// x-axis CONVST/CS.
    pub cs_x: CX,
    /// y-axis CONVST/CS.
    pub cs_y: CY,
    /// Metres per volt at the ADC input (both axes).
    pub scale: SensorScale,
}

impl<BX, BY, CX, CY> ConcurrentAdcPair<BX, BY, CX, CY>
where
    BX: FullDuplex<u8>,
    BY: FullDuplex<u8>,
    CX: OutputPin<Error = Infallible>,
    CY: OutputPin<Error = Infallible>,
{
    /// One frame on both buses at once (module docs); the codes of the conversions started at
    /// the end of the previous frames. Both chip selects are high again when this returns,
    /// whatever happened, which starts the next conversions.
    pub fn exchange(&mut self) -> [Result<AdcCode, ExchangeError<BX, BY>>; 2] {
        // A byte an aborted frame left behind (at most one arrives after the last read).
        let _ = self.bus_x.read();
        let _ = self.bus_y.read();
        let mut x = Lane::new();
        let mut y = Lane::new();
        let Ok(()) = self.cs_x.set_low();
        let Ok(()) = self.cs_y.set_low();
        for _ in 0..POLL_LIMIT {
            x.poll(&mut self.bus_x);
            y.poll(&mut self.bus_y);
            if x.done() && y.done() {
                break;
            }
        }
        let Ok(()) = self.cs_x.set_high();
        let Ok(()) = self.cs_y.set_high();
        [
            x.result().map_err(PairError::X),
            y.result().map_err(PairError::Y),
        ]
    }
}

impl<BX, BY, CX, CY> ErrorType for ConcurrentAdcPair<BX, BY, CX, CY>
where
    BX: FullDuplex<u8>,
    BY: FullDuplex<u8>,
{
    type Error = ExchangeError<BX, BY>;
}

impl<BX, BY, CX, CY> PositionSensor for ConcurrentAdcPair<BX, BY, CX, CY>
where
    BX: FullDuplex<u8>,
    BY: FullDuplex<u8>,
    CX: OutputPin<Error = Infallible>,
    CY: OutputPin<Error = Infallible>,
{
    /// One exchange on both buses; the other axis's reading is dropped (the loop reads both
    /// through [`PositionSensor::read_both_m`]).
    fn read_m(&mut self, axis: Axis) -> Result<f32, Self::Error> {
        let [x, y] = self.read_both_m();
        match axis {
            Axis::X => x,
            Axis::Y => y,
        }
    }

    #[inline]
    fn read_both_m(&mut self) -> [Result<f32, Self::Error>; 2] {
        let scale = self.scale;
        self.exchange()
            .map(|r| r.map(|code| scale.metres(code.to_volts())))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use embedded_hal::spi::ErrorKind as SpiErrorKind;
    use std::cell::Cell;
    use std::rc::Rc;

    /// Calls to either bus so far: the time of the test, one unit per register access.
    type Clock = Rc<Cell<u32>>;

    /// An STM32F4 SPI master, byte by byte: a one-byte transmit buffer (TXE), a shift register
    /// that takes `byte_time` clock units per byte, a one-byte receive buffer (RXNE) that
    /// overruns if a byte arrives while it is full. MISO returns `miso` bytes in turn.
    struct FakeSpi {
        clock: Clock,
        byte_time: u32,
        tx: Option<u8>,
        shifting: Option<(u8, u32)>,
        rx: Option<u8>,
        overrun: bool,
        miso: Vec<u8>,
        mosi: Vec<u8>,
        /// Clock when each byte started and ended shifting.
        spans: Vec<(u32, u32)>,
        /// The bus stops clocking after this many bytes.
        stall_after: Option<usize>,
        /// Chip select of the device on this bus, sampled when each byte starts.
        cs: Rc<Cell<bool>>,
        cs_low_at_start: Vec<bool>,
        fail_write: Option<SpiErrorKind>,
    }

    impl FakeSpi {
        fn new(clock: &Clock, cs: &Rc<Cell<bool>>, miso: &[u8]) -> Self {
            Self {
                clock: clock.clone(),
                byte_time: 8,
                tx: None,
                shifting: None,
                rx: None,
                overrun: false,
                miso: miso.to_vec(),
                mosi: Vec::new(),
                spans: Vec::new(),
                stall_after: None,
                cs: cs.clone(),
                cs_low_at_start: Vec::new(),
                fail_write: None,
            }
        }

        fn step(&mut self) {
            let now = self.clock.get() + 1;
            self.clock.set(now);
            if let Some((byte, end)) = self.shifting {
                if now >= end {
                    if self.rx.is_some() {
                        self.overrun = true;
                    }
                    let i = self.spans.len() - 1;
                    self.spans[i].1 = now;
                    self.rx = Some(self.miso.get(i).copied().unwrap_or(0xEE));
                    self.mosi.push(byte);
                    self.shifting = None;
                }
            }
            if self.shifting.is_none() && self.stall_after != Some(self.spans.len()) {
                if let Some(byte) = self.tx.take() {
                    self.shifting = Some((byte, now + self.byte_time));
                    self.spans.push((now, now));
                    self.cs_low_at_start.push(!self.cs.get());
                }
            }
        }
    }

    impl embedded_hal::spi::ErrorType for FakeSpi {
        type Error = SpiErrorKind;
    }

    impl FullDuplex<u8> for FakeSpi {
        fn read(&mut self) -> nb::Result<u8, SpiErrorKind> {
            self.step();
            if self.overrun {
                return Err(nb::Error::Other(SpiErrorKind::Overrun));
            }
            self.rx.take().ok_or(nb::Error::WouldBlock)
        }

        fn write(&mut self, byte: u8) -> nb::Result<(), SpiErrorKind> {
            self.step();
            if let Some(e) = self.fail_write {
                return Err(nb::Error::Other(e));
            }
            if core::mem::take(&mut self.overrun) {
                // The HAL reads DR and SR to clear OVR and reports it.
                self.rx = None;
                return Err(nb::Error::Other(SpiErrorKind::Overrun));
            }
            if self.tx.is_some() {
                return Err(nb::Error::WouldBlock);
            }
            self.tx = Some(byte);
            Ok(())
        }
    }

    /// A GPIO output; high is `true`.
    struct Pin(Rc<Cell<bool>>);

    impl embedded_hal::digital::ErrorType for Pin {
        type Error = Infallible;
    }

    impl OutputPin for Pin {
        fn set_low(&mut self) -> Result<(), Infallible> {
            self.0.set(false);
            Ok(())
        }
        fn set_high(&mut self) -> Result<(), Infallible> {
            self.0.set(true);
            Ok(())
        }
    }

    type FakePair = ConcurrentAdcPair<FakeSpi, FakeSpi, Pin, Pin>;

    fn pair(x_miso: &[u8], y_miso: &[u8]) -> (FakePair, [Rc<Cell<bool>>; 2]) {
        let clock = Clock::default();
        let cs = [Rc::new(Cell::new(true)), Rc::new(Cell::new(true))];
        let p = ConcurrentAdcPair {
            bus_x: FakeSpi::new(&clock, &cs[0], x_miso),
            bus_y: FakeSpi::new(&clock, &cs[1], y_miso),
            cs_x: Pin(cs[0].clone()),
            cs_y: Pin(cs[1].clone()),
            scale: SensorScale::new(1e-6).unwrap(),
        };
        (p, cs)
    }

    #[test]
    fn both_frames_are_nop_commands_returning_the_first_16_bits() {
        let (mut p, cs) = pair(&[0x80, 0x00, 0xAA, 0x55], &[0x12, 0x34, 0x56, 0x78]);
        let [x, y] = p.exchange();
        assert_eq!(x.unwrap(), AdcCode(0x8000));
        assert_eq!(y.unwrap(), AdcCode(0x1234));
        assert_eq!(p.bus_x.mosi, [0; 4]);
        assert_eq!(p.bus_y.mosi, [0; 4]);
        // Every byte went out with its chip select low; both are high afterwards (the
        // CONVST/CS rising edges that start the next conversions).
        assert!(p.bus_x.cs_low_at_start.iter().all(|&low| low));
        assert!(p.bus_y.cs_low_at_start.iter().all(|&low| low));
        assert!(cs[0].get() && cs[1].get());
    }

    #[test]
    fn the_two_frames_run_at_the_same_time_without_gaps() {
        let (mut p, _) = pair(&[0; 4], &[0; 4]);
        let [x, y] = p.exchange();
        assert!(x.is_ok() && y.is_ok());
        let (xs, xe) = (p.bus_x.spans[0].0, p.bus_x.spans[3].1);
        let (ys, ye) = (p.bus_y.spans[0].0, p.bus_y.spans[3].1);
        // y's frame starts before x's ends and the other way round: they overlap.
        assert!(ys < xe && xs < ye, "x {xs}..{xe}, y {ys}..{ye}");
        // Each bus shifts its four bytes back to back: the next byte starts when the one
        // before ends (two bytes in flight), so a frame lasts four byte times.
        for bus in [&p.bus_x, &p.bus_y] {
            for w in bus.spans.windows(2) {
                assert_eq!(w[1].0, w[0].1, "gap between bytes: {:?}", bus.spans);
            }
        }
        // Both frames end within about one frame time (4 bytes × 8 units per bus access, two
        // buses polled in turn), not two.
        let one_frame = 4 * p.bus_x.byte_time * 2;
        assert!(xe.max(ye) <= one_frame + 8, "ended at {}", xe.max(ye));
    }

    #[test]
    fn a_bus_that_stops_clocking_times_out_its_axis_only() {
        let (mut p, cs) = pair(&[0x40, 0x00, 0, 0], &[0; 4]);
        p.bus_y.stall_after = Some(2);
        let [x, y] = p.exchange();
        assert_eq!(x.unwrap(), AdcCode(0x4000));
        let e = y.unwrap_err();
        assert_eq!(e, PairError::Y(FrameError::Timeout));
        assert_eq!(e.kind(), ErrorKind::Timeout);
        // Bounded: about POLL_LIMIT rounds of two accesses each on the stalled bus.
        assert!(p.bus_y.clock.get() < 3 * POLL_LIMIT + 64);
        assert!(cs[0].get() && cs[1].get());
    }

    #[test]
    fn a_bus_error_fails_its_axis_and_the_other_reads() {
        let (mut p, _) = pair(&[0; 4], &[0x00, 0x01, 0, 0]);
        p.bus_x.fail_write = Some(SpiErrorKind::ModeFault);
        let [x, y] = p.exchange();
        assert_eq!(
            x.unwrap_err().kind(),
            ErrorKind::Bus(SpiErrorKind::ModeFault)
        );
        assert_eq!(y.unwrap(), AdcCode(1));
    }

    #[test]
    fn an_overrun_fails_one_exchange_and_the_next_one_reads() {
        // An overrun left on x's bus (a frame cut short by an earlier error): this exchange
        // reports it for x, as the HAL does (and clears it), and the next one reads.
        let (mut p, _) = pair(&[0; 4], &[0; 4]);
        p.bus_x.miso = vec![0x11, 0x11, 0, 0];
        p.bus_x.overrun = true;
        let [x, y] = p.exchange();
        assert_eq!(x.unwrap_err().kind(), ErrorKind::Bus(SpiErrorKind::Overrun));
        assert!(y.is_ok());
        let [x, _] = p.exchange();
        assert_eq!(x.unwrap(), AdcCode(0x1111));
    }

    #[test]
    fn the_loop_reads_both_axes_in_one_exchange() {
        let (mut p, _) = pair(&[0x80, 0x00, 0, 0, 0x90, 0x00], &[0x80, 0x00, 0, 0]);
        let [x, y] = p.read_both_m();
        assert_eq!(x.unwrap(), 0.0);
        assert_eq!(y.unwrap(), 0.0);
        assert_eq!(p.bus_x.spans.len(), 4);
        assert_eq!(p.bus_y.spans.len(), 4);
    }

    /// A DAC that takes every code.
    struct NullDac;

    impl ErrorType for NullDac {
        type Error = Infallible;
    }

    impl crate::converter::DacWrite for NullDac {
        type Channel = u8;
        fn write_code(&mut self, _: u8, _: crate::codes::DacCode) -> Result<(), Infallible> {
            Ok(())
        }
    }

    #[test]
    fn a_loop_tick_clocks_one_frame_on_each_bus() {
        use crate::xy_loop::XyIo;
        let (sensor, _) = pair(&[0x80, 0x00, 0, 0], &[0x80, 0x00, 0, 0]);
        let mut lp = crate::test_support::loop_holding([0.0; 2]);
        let mut io = XyIo {
            dac: NullDac,
            dac_channels: [0, 1],
            sensor,
        };
        let report = lp.tick(&mut io, false);
        assert_eq!(report.measured_m, [0.0; 2]);
        // One exchange: four bytes on each bus, not one frame per axis on both.
        assert_eq!(io.sensor.bus_x.spans.len(), 4);
        assert_eq!(io.sensor.bus_y.spans.len(), 4);
        assert_eq!(lp.counters().sensor_errors, 0);
    }
}
