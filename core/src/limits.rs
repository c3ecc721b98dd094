//! What one axis may be commanded: the output window `u_min ≤ u[k] ≤ u_max` of the stack voltage
//! and its largest rate of change, `|u[k] − u[k−1]| ≤ S_r · T` at the loop period T
//! (`S_r` = [`Limits::slew_limit_v_per_s`]), and what the loop does while a command leaves the
//! axis's identified envelope ([`EnvelopePolicy`]).
//!
//! [`Limits`] is the one type that carries these values, from the stage file to the output guard;
//! a slew limit written in the stage file reaches the guard through it unchanged:
//!
//! 1. **Stage file**: `[x.limits]` is this type (piezo-stage's `Axis::limits` reads and writes
//!    it, serde below).
//! 2. **Validate**: piezo-stage's `StageFile::validate` checks it with the core's rule
//!    ([`CompensatorSettings::check_slew`], by building the compensator) and against the drive
//!    ([`crate::IoChain::check_limits`]), and refuses `feedback-only` without an envelope or a
//!    servo.
//! 3. **Firmware set / upload**: the firmware's built-in set (`firmware/build.rs` writes it into
//!    the [`AxisParams`] consts) and an upload on the command link (`piezo_link::AxisModel`'s
//!    `limits`, validated again by the firmware) carry it as it is.
//! 4. **[`AxisParams::limits`]**: the axis holds it; [`AxisParams::settings`] pairs it with the
//!    loop period into [`CompensatorSettings`], and [`AxisParams::envelope_monitor`] gives its
//!    policy to the envelope's check ([`crate::Envelope::monitor`]).
//! 5. **Compensator and servo**: [`crate::Compensator::new`] and [`crate::Servo::new`] apply the
//!    one rule [`CompensatorSettings::check_slew`] and limit their outputs to the window and
//!    the slew limit (the firmware runs them a hair inside the guard,
//!    [`CompensatorSettings::inside_guard`]).
//! 6. **Output guard**: the firmware's `safety::SafetyLimits::from_limits` turns the window and
//!    `S_r · T` into the exact per-tick bound ([`CompensatorSettings::guard_step_v`]) that every
//!    written voltage passes.
//!
//! With the `serde` feature: `deny_unknown_fields`, `envelope_policy` optional when read (`warn`);
//! a self-describing format (TOML, JSON) leaves it out when it is `warn`, a positional one
//! (postcard, the link) always carries it.

use crate::EnvelopePolicy;
#[cfg(doc)]
use crate::{AxisParams, CompensatorSettings};

/// One axis's output limits (module doc).
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Deserialize))]
#[cfg_attr(feature = "serde", serde(deny_unknown_fields))]
pub struct Limits {
    /// Lowest stack voltage u_min \[V\] (the oscillator model's: lowest force \[N\]).
    pub output_min_v: f32,
    /// Highest stack voltage u_max \[V\].
    pub output_max_v: f32,
    /// Largest rate of change of the stack voltage S_r \[V/s\].
    pub slew_limit_v_per_s: f32,
    /// What the loop does while a command leaves the identified envelope (`warn` when absent;
    /// nothing is checked without an envelope).
    #[cfg_attr(feature = "serde", serde(default))]
    pub envelope_policy: EnvelopePolicy,
}

#[cfg(feature = "serde")]
impl serde::Serialize for Limits {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeStruct;
        let policy = !s.is_human_readable() || self.envelope_policy != EnvelopePolicy::Warn;
        let mut out = s.serialize_struct("Limits", 3 + usize::from(policy))?;
        out.serialize_field("output_min_v", &self.output_min_v)?;
        out.serialize_field("output_max_v", &self.output_max_v)?;
        out.serialize_field("slew_limit_v_per_s", &self.slew_limit_v_per_s)?;
        if policy {
            out.serialize_field("envelope_policy", &self.envelope_policy)?;
        } else {
            out.skip_field("envelope_policy")?;
        }
        out.end()
    }
}

impl Limits {
    /// The window `[output_min_v, output_max_v]` and the slew limit `slew_limit_v_per_s`, with
    /// the envelope policy `warn` (not checked here: where the axis is built, module doc).
    pub const fn new(output_min_v: f32, output_max_v: f32, slew_limit_v_per_s: f32) -> Self {
        Self {
            output_min_v,
            output_max_v,
            slew_limit_v_per_s,
            envelope_policy: EnvelopePolicy::Warn,
        }
    }
}
