//! Driver for the TI ADS8681: 16-bit, 1 MSPS SAR ADC with a programmable bipolar input range
//! and a 4.096 V internal reference, on an [`embedded_hal::spi::SpiDevice`]. It reads the
//! displacement sensor.
//!
//! Followed (ADS8681 datasheet, TI SBAS633):
//! - section "Data Transfer Frame" / "Input Command Word": 32-bit frames, MSB first, SPI mode 0
//!   (the power-on protocol, SDI_CTL_REG = 0), up to 66.7 MHz. The CONVST/CS pin is both the
//!   chip select and the conversion start: its rising edge at the end of a frame starts a
//!   conversion (t_conv ≤ 665 ns), whose 16-bit result is clocked out MSB first at the start of
//!   the **next** frame.
//! - Input commands (bits 31..25 opcode, 24..16 register address, 15..0 data):
//!
//! | command    | bits 31..25 | first byte | meaning                                   |
//! |------------|-------------|------------|-------------------------------------------|
//! | NOP        | 000_0000    | 0x00       | no operation (read a conversion)          |
//! | WRITE      | 1101_000    | 0xD0       | write a 16-bit half-word                  |
//! | READ_HWORD | 1100_100    | 0xC8       | half-word appears in the next frame's bits 31..16 |
//!
//! - section "Register Maps": RANGE_SEL_REG at address 0x14, bits 3..0 RANGE_SEL, bit 6
//!   INTREF_DIS (0 = internal reference on).
//! - section "ADC Transfer Function": straight binary output; bipolar ranges have 0 V at 0x8000.
//!
//! Init ([`Ads8681::init`]): write RANGE_SEL, read it back (two frames, the value arrives in the
//! second) and compare, so a miswired or unpowered ADC fails at start-up with
//! [`DriverError::Readback`] instead of returning plausible codes.
//!
//! Timing: [`Ads8681::read_code`] is one 32-bit frame and returns the conversion started when CS
//! rose at the end of the previous frame (pipelined, as the datasheet describes). For a sample
//! taken "now", call [`Ads8681::start_conversion`] (a CS pulse) at least 1 µs before
//! [`Ads8681::read_code`]. Frames must be ≥ 1 µs apart (1 MSPS cycle time); at a 10 kHz loop
//! rate they are 50–100 µs apart.

use embedded_hal::spi::SpiDevice;

use crate::codes::AdcCode;
use crate::converter::{AdcRead, DriverError, ErrorType};

/// Register address of RANGE_SEL_REG.
pub const RANGE_SEL_REG: u16 = 0x14;

/// Opcodes (frame bits 31..25, placed in the first byte together with address bit 8).
mod opcode {
    pub const NOP: u8 = 0x00;
    pub const WRITE: u8 = 0xD0;
    pub const READ_HWORD: u8 = 0xC8;
}

/// Bits of RANGE_SEL_REG that this driver writes and checks: INTREF_DIS and RANGE_SEL.
const RANGE_SEL_MASK: u16 = 0x004F;

/// One 32-bit input command: `[opcode | addr8, addr7..0, data15..8, data7..0]`.
#[inline]
pub fn frame(opcode: u8, address: u16, data: u16) -> [u8; 4] {
    let [dhi, dlo] = data.to_be_bytes();
    [
        (opcode & 0xFE) | ((address >> 8) as u8 & 1),
        address as u8,
        dhi,
        dlo,
    ]
}

/// Analog input range (RANGE_SEL bits 3..0), with the internal 4.096 V reference.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum InputRange {
    /// ±3 · V_REF = ±12.288 V (code 0000).
    Bipolar3x,
    /// ±2.5 · V_REF = ±10.24 V (code 0001); the default, matching [`AdcCode::VOLTS_PER_LSB`].
    Bipolar2_5x,
    /// ±1.5 · V_REF = ±6.144 V (code 0010).
    Bipolar1_5x,
    /// ±1.25 · V_REF = ±5.12 V (code 0011).
    Bipolar1_25x,
    /// ±0.625 · V_REF = ±2.56 V (code 0100).
    Bipolar0_625x,
    /// 0 to 3 · V_REF = 12.288 V (code 1000).
    Unipolar3x,
    /// 0 to 2.5 · V_REF = 10.24 V (code 1001).
    Unipolar2_5x,
    /// 0 to 1.5 · V_REF = 6.144 V (code 1010).
    Unipolar1_5x,
    /// 0 to 1.25 · V_REF = 5.12 V (code 1011).
    Unipolar1_25x,
}

impl InputRange {
    /// Internal reference voltage.
    pub const V_REF: f32 = 4.096;

    /// RANGE_SEL field value.
    pub fn bits(self) -> u16 {
        match self {
            InputRange::Bipolar3x => 0b0000,
            InputRange::Bipolar2_5x => 0b0001,
            InputRange::Bipolar1_5x => 0b0010,
            InputRange::Bipolar1_25x => 0b0011,
            InputRange::Bipolar0_625x => 0b0100,
            InputRange::Unipolar3x => 0b1000,
            InputRange::Unipolar2_5x => 0b1001,
            InputRange::Unipolar1_5x => 0b1010,
            InputRange::Unipolar1_25x => 0b1011,
        }
    }

    fn is_bipolar(self) -> bool {
        self.bits() & 0b1000 == 0
    }

    /// The range whose input span is `range_v` \[V\] (the stage file's `io.adc_range_v`, checked
    /// by `build.rs` to be one of these); the default ±10.24 V for any other.
    pub fn from_range_v(range_v: [f32; 2]) -> Self {
        const ALL: [InputRange; 9] = [
            InputRange::Bipolar3x,
            InputRange::Bipolar2_5x,
            InputRange::Bipolar1_5x,
            InputRange::Bipolar1_25x,
            InputRange::Bipolar0_625x,
            InputRange::Unipolar3x,
            InputRange::Unipolar2_5x,
            InputRange::Unipolar1_5x,
            InputRange::Unipolar1_25x,
        ];
        let unipolar = range_v[0] >= 0.0;
        ALL.into_iter()
            .find(|r| {
                r.is_bipolar() != unipolar
                    && (r.span_volts() - (range_v[1] - range_v[0])).abs() < 1e-3
            })
            .unwrap_or(InputRange::Bipolar2_5x)
    }

    /// Input span in volts (full scale minus zero scale): the multiple of V_REF times V_REF.
    pub fn span_volts(self) -> f32 {
        match self {
            InputRange::Bipolar3x => 24.576,
            InputRange::Bipolar2_5x => 20.48,
            InputRange::Bipolar1_5x => 12.288,
            InputRange::Bipolar1_25x => 10.24,
            InputRange::Bipolar0_625x => 5.12,
            InputRange::Unipolar3x => 12.288,
            InputRange::Unipolar2_5x => 10.24,
            InputRange::Unipolar1_5x => 6.144,
            InputRange::Unipolar1_25x => 5.12,
        }
    }

    /// Volts per code step: span / 2^16.
    pub fn volts_per_lsb(self) -> f32 {
        self.span_volts() / 65_536.0
    }

    /// Input volts for `code` in this range.
    pub fn volts(self, code: AdcCode) -> f32 {
        let offset = if self.is_bipolar() { 0x8000 } else { 0 };
        (code.0 as i32 - offset) as f32 * self.volts_per_lsb()
    }
}

/// TI ADS8681 on an SPI device (CONVST/CS is the device's chip select).
#[derive(Debug)]
pub struct Ads8681<SPI> {
    spi: SPI,
    range: InputRange,
}

impl<SPI: SpiDevice> Ads8681<SPI> {
    /// Wraps the SPI device; sends nothing. Call [`Ads8681::init`] before use.
    pub fn new(spi: SPI, range: InputRange) -> Self {
        Self { spi, range }
    }

    /// The configured input range.
    pub fn range(&self) -> InputRange {
        self.range
    }

    /// Gives the SPI device back.
    pub fn release(self) -> SPI {
        self.spi
    }

    /// One full-duplex frame: sends `command`, returns the first 16 bits clocked out.
    fn exchange(&mut self, command: [u8; 4]) -> Result<u16, DriverError<SPI::Error>> {
        let mut buf = command;
        self.spi
            .transfer_in_place(&mut buf)
            .map_err(DriverError::Spi)?;
        Ok(u16::from_be_bytes([buf[0], buf[1]]))
    }

    /// Writes RANGE_SEL (internal reference on) and checks it by reading it back.
    pub fn init(&mut self) -> Result<(), DriverError<SPI::Error>> {
        let expected = self.range.bits();
        self.exchange(frame(opcode::WRITE, RANGE_SEL_REG, expected))?;
        self.exchange(frame(opcode::READ_HWORD, RANGE_SEL_REG, 0))?;
        let found = self.exchange(frame(opcode::NOP, 0, 0))? & RANGE_SEL_MASK;
        if found != expected {
            return Err(DriverError::Readback {
                register: RANGE_SEL_REG,
                expected,
                found,
            });
        }
        Ok(())
    }

    /// Pulses CONVST/CS (an empty transaction): starts a conversion now.
    pub fn start_conversion(&mut self) -> Result<(), DriverError<SPI::Error>> {
        self.spi.transaction(&mut []).map_err(DriverError::Spi)
    }

    /// Reads the conversion started at the end of the previous frame (one NOP frame); the end of
    /// this frame starts the next conversion.
    pub fn read(&mut self) -> Result<AdcCode, DriverError<SPI::Error>> {
        self.exchange(frame(opcode::NOP, 0, 0)).map(AdcCode)
    }

    /// Input volts for a code read from this ADC.
    pub fn volts(&self, code: AdcCode) -> f32 {
        self.range.volts(code)
    }
}

impl<SPI: SpiDevice> ErrorType for Ads8681<SPI> {
    type Error = DriverError<SPI::Error>;
}

impl<SPI: SpiDevice> AdcRead for Ads8681<SPI> {
    type Channel = ();

    fn read_code(&mut self, _channel: ()) -> Result<AdcCode, Self::Error> {
        self.read()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::converter::{Error as _, ErrorKind};
    use crate::test_support::{transfer_frame, FailingSpi};
    use embedded_hal::spi::ErrorKind as SpiErrorKind;
    use embedded_hal_mock::eh1::spi::{Mock as SpiMock, Transaction};

    fn init_frames(range_bits: u16, readback: u16) -> Vec<Transaction<u8>> {
        let [rh, rl] = readback.to_be_bytes();
        let mut t = Vec::new();
        t.extend(transfer_frame(
            &[0xD0, 0x14, 0x00, range_bits as u8],
            &[0x12, 0x34, 0, 0],
        ));
        t.extend(transfer_frame(
            &[0xC8, 0x14, 0x00, 0x00],
            &[0x80, 0x00, 0, 0],
        ));
        t.extend(transfer_frame(&[0x00, 0x00, 0x00, 0x00], &[rh, rl, 0, 0]));
        t
    }

    #[test]
    fn frame_layout_matches_datasheet() {
        assert_eq!(frame(opcode::WRITE, 0x14, 0x0001), [0xD0, 0x14, 0x00, 0x01]);
        assert_eq!(frame(opcode::READ_HWORD, 0x14, 0), [0xC8, 0x14, 0x00, 0x00]);
        assert_eq!(frame(opcode::NOP, 0, 0), [0; 4]);
        // Address bit 8 goes to bit 24 (first byte, LSB).
        assert_eq!(
            frame(opcode::WRITE, 0x114, 0xBEEF),
            [0xD1, 0x14, 0xBE, 0xEF]
        );
    }

    #[test]
    fn init_writes_range_and_checks_readback() {
        let mut spi = SpiMock::new(&init_frames(0x01, 0x0001));
        let mut adc = Ads8681::new(spi.clone(), InputRange::Bipolar2_5x);
        adc.init().unwrap();
        spi.done();
    }

    #[test]
    fn init_ignores_reserved_bits_in_readback() {
        let mut spi = SpiMock::new(&init_frames(0x09, 0xFF09 & !0x0040));
        let mut adc = Ads8681::new(spi.clone(), InputRange::Unipolar2_5x);
        adc.init().unwrap();
        spi.done();
    }

    #[test]
    fn init_readback_mismatch_is_readback_error() {
        // A floating MISO reads all ones.
        let mut spi = SpiMock::new(&init_frames(0x01, 0xFFFF));
        let mut adc = Ads8681::new(spi.clone(), InputRange::Bipolar2_5x);
        let err = adc.init().unwrap_err();
        assert_eq!(
            err,
            DriverError::Readback {
                register: RANGE_SEL_REG,
                expected: 0x0001,
                found: 0x004F
            }
        );
        assert_eq!(err.kind(), ErrorKind::Readback);
        spi.done();
    }

    #[test]
    fn read_code_is_one_nop_frame_returning_first_16_bits() {
        let mut t = Vec::new();
        t.extend(transfer_frame(&[0; 4], &[0x80, 0x00, 0xAA, 0x55]));
        t.extend(transfer_frame(&[0; 4], &[0xFF, 0xFF, 0x00, 0x00]));
        let mut spi = SpiMock::new(&t);
        let mut adc = Ads8681::new(spi.clone(), InputRange::Bipolar2_5x);
        let code = adc.read_code(()).unwrap();
        assert_eq!(code, AdcCode::MID_SCALE);
        assert_eq!(adc.volts(code), 0.0);
        assert_eq!(adc.read_code(()).unwrap(), AdcCode(0xFFFF));
        spi.done();
    }

    #[test]
    fn start_conversion_is_an_empty_chip_select_pulse() {
        let mut spi = SpiMock::new(&[
            Transaction::transaction_start(),
            Transaction::transaction_end(),
        ]);
        let mut adc = Ads8681::new(spi.clone(), InputRange::Bipolar2_5x);
        adc.start_conversion().unwrap();
        spi.done();
    }

    #[test]
    fn spi_error_on_read_becomes_bus_error_kind() {
        let mut spi = SpiMock::new(&[]);
        let mut adc = Ads8681::new(
            FailingSpi::new(spi.clone(), 0, SpiErrorKind::FrameFormat),
            InputRange::Bipolar2_5x,
        );
        let err = adc.read_code(()).unwrap_err();
        assert_eq!(err, DriverError::Spi(SpiErrorKind::FrameFormat));
        assert_eq!(err.kind(), ErrorKind::Bus(SpiErrorKind::FrameFormat));
        spi.done();
    }

    #[test]
    fn spi_error_during_init_readback_stops_init() {
        let mut t = Vec::new();
        t.extend(transfer_frame(&[0xD0, 0x14, 0x00, 0x01], &[0; 4]));
        let mut spi = SpiMock::new(&t);
        let mut adc = Ads8681::new(
            FailingSpi::new(spi.clone(), 1, SpiErrorKind::ChipSelectFault),
            InputRange::Bipolar2_5x,
        );
        assert_eq!(
            adc.init().unwrap_err().kind(),
            ErrorKind::Bus(SpiErrorKind::ChipSelectFault)
        );
        spi.done();
    }

    #[test]
    fn range_transfer_functions() {
        let r = InputRange::Bipolar2_5x;
        assert_eq!(r.volts_per_lsb(), AdcCode::VOLTS_PER_LSB);
        assert_eq!(r.volts(AdcCode(0)), -10.24);
        assert_eq!(r.volts(AdcCode(0x8000)), 0.0);
        assert_eq!(InputRange::Unipolar2_5x.volts(AdcCode(0)), 0.0);
        assert!(
            (InputRange::Bipolar3x.volts(AdcCode(0xFFFF)) - (12.288 - 24.576 / 65536.0)).abs()
                < 1e-6
        );
        for code in [0u16, 1, 0x7FFF, 0x8000, 0xFFFF] {
            assert_eq!(r.volts(AdcCode(code)), AdcCode(code).to_volts());
        }
    }

    #[test]
    #[should_panic(expected = "spi::transfer_in_place write data does not match expectation")]
    fn mock_catches_a_wrong_command_word() {
        let mut spi = SpiMock::new(&transfer_frame(&[0xC8, 0x14, 0, 0], &[0; 4]));
        let mut adc = Ads8681::new(spi.clone(), InputRange::Bipolar2_5x);
        let _ = adc.read_code(());
        spi.done();
    }
}
