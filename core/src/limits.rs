//! What one axis may be commanded: the output window `u_min ≤ u[k] ≤ u_max` of the stack voltage
//! and its largest rate of change, `|u[k] − u[k−1]| ≤ S_r · T` at the loop period T
//! (`S_r` = [`Limits::slew_limit_v_per_s`]), and what the loop does while a command leaves the
//! axis's identified envelope ([`EnvelopePolicy`]).
//!
//! The one definition: the stage file's `[x.limits]` (piezo-stage reads and writes this type),
//! an upload on the command link (`piezo_link::AxisModel`) and [`AxisParams`] (its flat window
//! fields and its envelope's policy, [`AxisParams::limits`]) hold it; the compensator, the servo
//! and the firmware's output guard enforce it. Validated where an axis is built
//! ([`crate::Compensator::new`], [`crate::IoChain::check_limits`]).
//!
//! With the `serde` feature: `deny_unknown_fields`, `envelope_policy` optional when read (`warn`);
//! a self-describing format (TOML, JSON) leaves it out when it is `warn`, a positional one
//! (postcard, the link) always carries it.

use crate::{AxisParams, EnvelopePolicy};

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

impl AxisParams {
    /// The axis's output limits: its window, its slew limit and its envelope's policy (`warn`
    /// without an envelope).
    pub fn limits(&self) -> Limits {
        Limits {
            output_min_v: self.output_min_v,
            output_max_v: self.output_max_v,
            slew_limit_v_per_s: self.slew_limit_v_per_s,
            envelope_policy: self.envelope.map_or(EnvelopePolicy::Warn, |e| e.policy),
        }
    }

    /// This axis with the output limits `limits`: its window and slew limit, and its envelope's
    /// policy if it has an envelope (nothing else changed; its rest output and baseline gain are
    /// those of the old window until [`AxisParams::with_first_loading`]).
    pub fn with_limits(mut self, limits: Limits) -> Self {
        self.output_min_v = limits.output_min_v;
        self.output_max_v = limits.output_max_v;
        self.slew_limit_v_per_s = limits.slew_limit_v_per_s;
        if let Some(envelope) = &mut self.envelope {
            envelope.policy = limits.envelope_policy;
        }
        self
    }
}
