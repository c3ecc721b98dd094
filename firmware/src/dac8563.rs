//! Driver for the TI DAC8563: dual 16-bit voltage-output DAC with a 2.5 V internal reference,
//! on an [`embedded_hal::spi::SpiDevice`]. Channel A drives the piezo amplifier input.
//!
//! Followed (DAC8563 datasheet, TI SLAS719): section "Serial Interface" / "Input Shift
//! Register" — a 24-bit frame per SYNC low period, MSB first, data latched on SCLK falling edges
//! (SPI mode 1, CPOL = 0, CPHA = 1, up to 50 MHz):
//!
//! ```text
//! bit  23 22 | 21 20 19 | 18 17 16 | 15 ............ 0
//!      X  X  | C2 C1 C0 | A2 A1 A0 | D15 ......... D0
//! ```
//!
//! Command table ("Command Set" / "Commands for the DAC8563"):
//!
//! | C2..C0 | meaning                                        | A2..A0           | data        |
//! |--------|------------------------------------------------|------------------|-------------|
//! | 000    | write input register n (010: gain register)     | 000 A, 001 B     | code / gain |
//! | 011    | write input register n and update DAC n         | 000 A, 001 B, 111| code        |
//! | 101    | software reset                                  | 000              | DB0 = 1: all registers (power-on reset) |
//! | 110    | LDAC register: DB1 = B, DB0 = A, 1 = LDAC pin ignored | 000        | 0x0003      |
//! | 111    | internal reference: DB0 = 1 enable (sets gain = 2 on both) | 000   | 0x0001      |
//!
//! Gain register (command 000, address 010): DB1 = DAC-B, DB0 = DAC-A, 0 = gain 2, 1 = gain 1.
//!
//! Init sequence ([`Dac8563::init`]): reset all registers, enable the internal reference (gain 2,
//! so 0..5 V out), make the LDAC pin inactive for both channels (every write with command 011
//! updates its output at the end of its frame, so the LDAC pin may be tied low), write gain 2
//! explicitly, and set channel A to [`DacCode::SAFE`]. The DAC8563 resets to mid-scale, so
//! the last step matters: the amplifier input is 0 V before the loop starts.

use embedded_hal::spi::SpiDevice;

use crate::codes::DacCode;
use crate::converter::{DacWrite, DriverError, ErrorType};

/// DAC8563 output channel.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Dac8563Channel {
    /// DAC-A (address 000).
    A,
    /// DAC-B (address 001).
    B,
}

impl Dac8563Channel {
    fn address(self) -> u8 {
        match self {
            Dac8563Channel::A => 0b000,
            Dac8563Channel::B => 0b001,
        }
    }
}

/// Command bits C2..C0 (frame bits 21..19).
mod command {
    pub const WRITE_INPUT: u8 = 0b000;
    pub const WRITE_AND_UPDATE: u8 = 0b011;
    pub const SOFTWARE_RESET: u8 = 0b101;
    pub const LDAC_REGISTER: u8 = 0b110;
    pub const INTERNAL_REFERENCE: u8 = 0b111;
}

/// Address of the gain register (with command 000).
const GAIN_ADDRESS: u8 = 0b010;

/// One 24-bit frame, MSB first: `[XX C2 C1 C0 A2 A1 A0, D15..D8, D7..D0]`.
#[inline]
pub fn frame(command: u8, address: u8, data: u16) -> [u8; 3] {
    let [hi, lo] = data.to_be_bytes();
    [((command & 0b111) << 3) | (address & 0b111), hi, lo]
}

/// The frame that writes `code` to `channel` and updates its output (command 011): what
/// [`Dac8563::set`] sends, and what the board's DMA sends ([`crate::dac_dma`]).
#[inline]
pub fn update_frame(channel: Dac8563Channel, code: DacCode) -> [u8; 3] {
    frame(command::WRITE_AND_UPDATE, channel.address(), code.0)
}

/// TI DAC8563 on an SPI device (SYNC is the device's chip select).
#[derive(Debug)]
pub struct Dac8563<SPI> {
    spi: SPI,
}

impl<SPI: SpiDevice> Dac8563<SPI> {
    /// Wraps the SPI device; sends nothing. Call [`Dac8563::init`] before use.
    pub fn new(spi: SPI) -> Self {
        Self { spi }
    }

    /// Gives the SPI device back.
    pub fn release(self) -> SPI {
        self.spi
    }

    fn send(&mut self, command: u8, address: u8, data: u16) -> Result<(), DriverError<SPI::Error>> {
        self.spi
            .write(&frame(command, address, data))
            .map_err(DriverError::Spi)
    }

    /// Init sequence (see module docs): reset, internal reference on (gain 2), LDAC pin ignored,
    /// gain 2 on both channels, both outputs to [`DacCode::SAFE`].
    pub fn init(&mut self) -> Result<(), DriverError<SPI::Error>> {
        self.send(command::SOFTWARE_RESET, 0b000, 0x0001)?;
        self.send(command::INTERNAL_REFERENCE, 0b000, 0x0001)?;
        self.send(command::LDAC_REGISTER, 0b000, 0x0003)?;
        self.send(command::WRITE_INPUT, GAIN_ADDRESS, 0x0000)?;
        // Address 111: both channels, updated at once.
        self.send(command::WRITE_AND_UPDATE, 0b111, DacCode::SAFE.0)
    }

    /// Writes `code` to `channel` and updates its output (command 011).
    pub fn set(
        &mut self,
        channel: Dac8563Channel,
        code: DacCode,
    ) -> Result<(), DriverError<SPI::Error>> {
        self.spi
            .write(&update_frame(channel, code))
            .map_err(DriverError::Spi)
    }
}

impl<SPI: SpiDevice> ErrorType for Dac8563<SPI> {
    type Error = DriverError<SPI::Error>;
}

impl<SPI: SpiDevice> DacWrite for Dac8563<SPI> {
    type Channel = Dac8563Channel;

    fn write_code(&mut self, channel: Dac8563Channel, code: DacCode) -> Result<(), Self::Error> {
        self.set(channel, code)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::converter::{Error as _, ErrorKind};
    use crate::test_support::{write_frame, FailingSpi};
    use embedded_hal::spi::ErrorKind as SpiErrorKind;
    use embedded_hal_mock::eh1::spi::{Mock as SpiMock, Transaction};

    fn expect(frames: &[[u8; 3]]) -> Vec<Transaction<u8>> {
        frames.iter().flat_map(|f| write_frame(f)).collect()
    }

    #[test]
    fn frame_layout_matches_datasheet() {
        assert_eq!(frame(0b011, 0b000, 0xABCD), [0x18, 0xAB, 0xCD]);
        assert_eq!(frame(0b011, 0b001, 0x0001), [0x19, 0x00, 0x01]);
        assert_eq!(frame(0b101, 0b000, 0x0001), [0x28, 0x00, 0x01]);
        assert_eq!(frame(0b111, 0b000, 0x0001), [0x38, 0x00, 0x01]);
        assert_eq!(frame(0b110, 0b000, 0x0003), [0x30, 0x00, 0x03]);
        assert_eq!(frame(0b000, 0b010, 0x0000), [0x02, 0x00, 0x00]);
        // Out-of-range bits are masked, never shifted into the command field.
        assert_eq!(frame(0xFF, 0xFF, 0), [0x3F, 0x00, 0x00]);
    }

    #[test]
    fn init_sends_reset_reference_ldac_gain_and_safe_code() {
        let mut spi = SpiMock::new(&expect(&[
            [0x28, 0x00, 0x01],
            [0x38, 0x00, 0x01],
            [0x30, 0x00, 0x03],
            [0x02, 0x00, 0x00],
            [0x1F, 0x00, 0x00],
        ]));
        let mut dac = Dac8563::new(spi.clone());
        dac.init().unwrap();
        spi.done();
    }

    #[test]
    fn write_code_selects_channel_and_sends_big_endian_code() {
        let mut spi = SpiMock::new(&expect(&[[0x18, 0x80, 0x00], [0x19, 0xFF, 0xFF]]));
        let mut dac = Dac8563::new(spi.clone());
        dac.write_code(Dac8563Channel::A, DacCode(0x8000)).unwrap();
        dac.write_code(Dac8563Channel::B, DacCode::MAX).unwrap();
        spi.done();
    }

    #[test]
    fn spi_error_becomes_bus_error_kind() {
        let mut spi = SpiMock::new(&[]);
        let mut dac = Dac8563::new(FailingSpi::new(spi.clone(), 0, SpiErrorKind::ModeFault));
        let err = dac
            .write_code(Dac8563Channel::A, DacCode(0x1234))
            .unwrap_err();
        assert_eq!(err, DriverError::Spi(SpiErrorKind::ModeFault));
        assert_eq!(err.kind(), ErrorKind::Bus(SpiErrorKind::ModeFault));
        spi.done();
    }

    #[test]
    fn init_stops_at_first_failed_frame() {
        // Frame 0 (reset) goes out, frame 1 (reference) fails, nothing after it is sent.
        let mut spi = SpiMock::new(&expect(&[[0x28, 0x00, 0x01]]));
        let mut dac = Dac8563::new(FailingSpi::new(spi.clone(), 1, SpiErrorKind::Overrun));
        assert_eq!(
            dac.init().unwrap_err().kind(),
            ErrorKind::Bus(SpiErrorKind::Overrun)
        );
        spi.done();
    }

    #[test]
    #[should_panic(expected = "Not all expectations consumed")]
    fn mock_catches_a_missing_frame() {
        // The mock, not the driver, panics: a frame that was expected but never sent fails.
        let mut spi = SpiMock::new(&expect(&[[0x18, 0x00, 0x00]]));
        let _dac = Dac8563::new(spi.clone());
        spi.done();
    }
}
