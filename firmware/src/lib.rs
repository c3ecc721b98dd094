//! piezo-firmware: the hardware edge of the piezo hysteresis compensator.
//!
//! Hardware-independent, host-tested parts (this library builds for the host in the workspace's
//! `cargo test`, and `no_std` for the Cortex-M4F target):
//! - [`codes`]: converter codes `DacCode`/`AdcCode` and their SI conversions;
//! - [`converter`]: the project's DAC/ADC traits (`DacWrite`, `AdcRead`) and error kinds;
//! - [`dac8563`], [`ads8681`]: drivers for TI DAC8563 and ADS8681 over
//!   `embedded_hal::spi::SpiDevice`;
//! - [`concurrent_adc`], [`dac_dma`]: the board's converters without the tick waiting on them
//!   (both ADCs read at once on their two buses; the DAC frames sent by DMA), and
//!   [`converter_timing`], their timing budget from the datasheets;
//! - [`safety`]: output window, slew limit, NaN hold, fault counters;
//! - [`control`]: [`control::TrackingStats`], RMS and peak tracking error of a run;
//! - [`params`]: the parameter set built in by `build.rs` from `firmware/params/*.toml`;
//! - [`mod@reference`]: waveform generator (sine, triangle, steps, raster, streamed setpoints);
//! - [`xy_loop`]: the two-axis loop (reference → `piezo_core::Compensator` → guard → DAC, sensor
//!   every tick, fault detection and safe state, overrun count);
//! - [`frames`]: sample frames out, with sequence numbers and gap detection;
//! - [`session`]: the command link's endpoint ([`piezo_link`] requests in, responses and frames
//!   out) around the loop: programs, open-loop excitation, model upload, rearm, status;
//! - [`inverse_chain`]: the inverse of the effect chain (creep, even term, mode, delay, drift,
//!   coupling) the loop runs around the compensator when the parameter file has effects;
//! - [`servo_table`]: the four control modes on the simulated stage with creep, drift and noise;
//! - [`plant`], [`demo`]: a simulated two-axis stage (independent f32 Bouc-Wen + lag) and the
//!   fixed run the QEMU image checks itself with.
//!
//! Board code (STM32F407, `board` feature; or QEMU netduinoplus2, `board-emu`; target only) is
//! in `board`. The images are `src/bin/qemu.rs` (feature `qemu`), `src/bin/board.rs` (feature
//! `board`) and `src/bin/board_emu.rs` (feature `board-emu`, the board image's application
//! under QEMU); see `firmware/ci.sh`.
#![cfg_attr(not(test), no_std)]

pub mod ads8681;
pub mod codes;
pub mod concurrent_adc;
pub mod control;
pub mod converter;
pub mod converter_timing;
pub mod dac8563;
pub mod dac_dma;
pub mod demo;
pub mod frames;
pub mod inverse_chain;
pub mod params;
pub mod plant;
pub mod reference;
pub mod safety;
pub mod servo_table;
pub mod session;
pub mod xy_loop;

#[cfg(all(target_os = "none", any(feature = "board", feature = "board-emu")))]
pub mod board;
#[cfg(all(target_os = "none", feature = "qemu"))]
pub mod cmsdk_uart;
#[cfg(all(target_os = "none", any(feature = "qemu", feature = "board-emu")))]
pub mod semihosting_exit;

#[cfg(test)]
mod test_support;
