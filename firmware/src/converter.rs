//! Project traits for data converters: write one DAC channel's code, read one ADC channel's code.
//!
//! embedded-hal 1.0 has no DAC or ADC trait, so this module defines two small ones in its style:
//! every operation is fallible, and every error reports an [`ErrorKind`] so generic code (the
//! two-axis loop, [`crate::xy_loop::TwoAxisLoop::tick`]) can react without knowing the driver. Implemented by
//! the SPI drivers [`crate::dac8563::Dac8563`] and [`crate::ads8681::Ads8681`] and by the
//! simulated plant [`crate::plant`].

use crate::codes::{AdcCode, DacCode};

/// What went wrong in a converter operation, independent of the driver.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub enum ErrorKind {
    /// The bus transfer failed; carries the SPI error kind.
    Bus(embedded_hal::spi::ErrorKind),
    /// A register read back differs from what was written (wiring, mode or power problem).
    Readback,
    /// The channel does not exist on this converter.
    InvalidChannel,
    /// The previous transfer had not finished when the next one was asked for (a DAC written by
    /// DMA whose frames were still going out one loop period later).
    Busy,
    /// A transfer did not finish within its bound (a bus that stopped clocking), or was
    /// aborted by its DMA stream.
    Timeout,
    /// Anything else.
    Other,
}

/// An error from a converter; like `embedded_hal::spi::Error`, it reports a kind.
pub trait Error: core::fmt::Debug {
    /// The driver-independent kind of this error.
    fn kind(&self) -> ErrorKind;
}

impl Error for core::convert::Infallible {
    fn kind(&self) -> ErrorKind {
        match *self {}
    }
}

/// The error type of a converter.
pub trait ErrorType {
    /// Error returned by this converter's operations.
    type Error: Error;
}

/// A digital-to-analog converter: sets one channel's output code.
pub trait DacWrite: ErrorType {
    /// Channel selector (for example `Dac8563Channel::A`, or `()` for a single channel).
    type Channel: Copy;

    /// Sets `channel`'s output to `code`. The output changes when this returns `Ok`, or, for a
    /// DAC whose frames go out by DMA ([`crate::dac_dma`]), when its transfer ends, before
    /// the next tick (a transfer still running then makes the next write fail with
    /// [`ErrorKind::Busy`]).
    fn write_code(&mut self, channel: Self::Channel, code: DacCode) -> Result<(), Self::Error>;
}

/// An analog-to-digital converter: returns one channel's latest conversion.
pub trait AdcRead: ErrorType {
    /// Channel selector (`()` for a single-channel converter).
    type Channel: Copy;

    /// The latest conversion result of `channel`.
    fn read_code(&mut self, channel: Self::Channel) -> Result<AdcCode, Self::Error>;
}

impl<T: ErrorType + ?Sized> ErrorType for &mut T {
    type Error = T::Error;
}

impl<T: DacWrite + ?Sized> DacWrite for &mut T {
    type Channel = T::Channel;
    fn write_code(&mut self, channel: Self::Channel, code: DacCode) -> Result<(), Self::Error> {
        T::write_code(self, channel, code)
    }
}

impl<T: AdcRead + ?Sized> AdcRead for &mut T {
    type Channel = T::Channel;
    fn read_code(&mut self, channel: Self::Channel) -> Result<AdcCode, Self::Error> {
        T::read_code(self, channel)
    }
}

/// The one error type of both SPI converter drivers.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DriverError<E> {
    /// The SPI transaction failed.
    Spi(E),
    /// A configuration register read back a different value.
    Readback {
        /// Register address.
        register: u16,
        /// Value written.
        expected: u16,
        /// Value read back.
        found: u16,
    },
}

impl<E: embedded_hal::spi::Error> Error for DriverError<E> {
    fn kind(&self) -> ErrorKind {
        match self {
            DriverError::Spi(e) => ErrorKind::Bus(e.kind()),
            DriverError::Readback { .. } => ErrorKind::Readback,
        }
    }
}
