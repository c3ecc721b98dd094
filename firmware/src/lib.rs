//! piezo-firmware: the hardware edge of the piezo hysteresis compensator.
//!
//! Hardware-independent, host-tested parts (this library builds for the host in the workspace's
//! `cargo test`, and `no_std` for the Cortex-M4F target):
//! - [`codes`]: converter codes `DacCode`/`AdcCode` and their SI conversions;
//! - [`converter`]: the project's DAC/ADC traits (`DacWrite`, `AdcRead`) and error kinds;
//! - [`dac8563`], [`ads8681`]: drivers for TI DAC8563 and ADS8681 over
//!   `embedded_hal::spi::SpiDevice`;
//! - [`safety`]: output window, slew limit, NaN hold, fault counters;
//! - [`control`]: the per-tick loop body [`control::tick`] with a pluggable feed-forward;
//! - [`plant`], [`demo`]: a simulated stage and the fixed run the QEMU image checks itself with.
//!
//! Board code (STM32F407, `board` feature, target only) is in `board`. The images are
//! `src/bin/qemu.rs` (feature `qemu`) and `src/bin/board.rs` (feature `board`); see
//! `firmware/ci.sh`.
#![cfg_attr(not(test), no_std)]

pub mod ads8681;
pub mod codes;
pub mod control;
pub mod converter;
pub mod dac8563;
pub mod demo;
pub mod plant;
pub mod safety;

#[cfg(all(target_os = "none", feature = "board"))]
pub mod board;

#[cfg(test)]
mod test_support;
