//! The inverse of the effect chain around the compensator, for both axes: piezo-core's
//! [`piezo_core::inverse_chain::InverseChain`] (its doc has the equations), which
//! [`crate::xy_loop::TwoAxisLoop`] runs when the parameter file has effects, fed by the loop's
//! [`crate::reference::ReferenceGenerator`] and started at rest at each axis's initial voltage.
//!
//! # Latency
//! Because the generator is sampled L = [`InverseChain::lead_ticks`] ticks ahead, anything that
//! changes its output — a `set_program`, and **streamed setpoints**
//! ([`crate::reference::Program::Streamed`]) — takes effect L ticks (L·T: at most 6.5 ms at
//! 10 kHz for a 64-sample delay) later than without effects: a streamed setpoint dequeued at
//! tick k is the reference of tick k + L. The queue must be kept L setpoints fuller to have the
//! same slack. While the loop is safe the generator is paused (as without effects); the drift
//! clock is not, so the first ticks after [`crate::xy_loop::TwoAxisLoop::rearm`] see a step in
//! z\* of r_d times the safe time.

pub use piezo_core::inverse_chain::{InverseChain, REFERENCE_RING};
