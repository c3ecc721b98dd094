//! The identified envelope of an axis: the input range and the largest input rate of the record
//! its model was fitted to. Inside it the model is known to hold; outside it extrapolates.
//!
//! A commanded voltage u\[k\] at the loop period T leaves the envelope when
//!
//! ```text
//! e_v[k] = max(u_min − u[k], u[k] − u_max) > 0                          voltage excursion [V]
//! e_r[k] = |u[k] − u[k−1]|/T − r_max > 0                                 rate excursion [V/s]
//! ```
//!
//! with `[u_min, u_max]` = [`Envelope::input_range_v`] and `r_max` =
//! [`Envelope::input_rate_max_v_per_s`] (both taken from the identification record: its smallest
//! and largest input, and its largest `|u[k] − u[k−1]|/T_record`). Both excursions are positive
//! outside, zero or negative inside. [`EnvelopeCounts`] counts the ticks with either excursion
//! positive and keeps the largest of each; [`EnvelopeMonitor::observe`] is the per-tick step (two
//! compares and two maxima: no division, no panic).
//!
//! What the loop does outside is the axis's [`EnvelopePolicy`], held by its limits
//! ([`crate::Limits::envelope_policy`], the stage file's `[x.limits] envelope_policy`) and given
//! to the monitor when it is built ([`Envelope::monitor`]): `warn` counts and flags only;
//! `feedback-only` hands the axis to its servo alone while outside (the feed-forward removed,
//! bumplessly) and back to the compensator inside, which needs a servo on the axis
//! ([`crate::AxisParams::envelope_monitor`] refuses it without one).

use crate::error::{finite, ParamError};
use crate::math::max;

/// What the loop does while an axis's command is outside its identified envelope.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "serde", serde(rename_all = "kebab-case"))]
pub enum EnvelopePolicy {
    /// Count and flag the ticks outside; the control mode runs unchanged.
    #[default]
    Warn,
    /// While outside, the servo alone drives the axis (feed-forward removed with a bumpless
    /// hand-over); inside again, the control mode's feed-forward resumes, bumplessly.
    FeedbackOnly,
}

impl EnvelopePolicy {
    /// Name as written in the stage file: `warn`, `feedback-only`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Warn => "warn",
            Self::FeedbackOnly => "feedback-only",
        }
    }
}

/// The identified envelope of one axis: what the identification record covered (see the module
/// doc).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Envelope {
    /// Smallest and largest input of the identification record \[V\].
    pub input_range_v: [f32; 2],
    /// Largest |du/dt| of the identification record \[V/s\] (`f32::MAX`: not known, no rate
    /// check).
    pub input_rate_max_v_per_s: f32,
}

/// Per-axis excursion counts (saturating), since the loop started or the monitor was reset.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct EnvelopeCounts {
    /// Ticks whose command was outside the envelope (voltage or rate).
    pub ticks_outside: u32,
    /// Largest voltage excursion `e_v` \[V\] (0: none).
    pub max_voltage_excursion_v: f32,
    /// Largest rate excursion `e_r` \[V/s\] (0: none).
    pub max_rate_excursion_v_per_s: f32,
}

/// An [`Envelope`] checked and set up for one loop period, with the axis's policy outside it:
/// the per-tick step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EnvelopeMonitor {
    envelope: Envelope,
    policy: EnvelopePolicy,
    /// r_max·T: the largest step per tick inside \[V\].
    max_step_v: f32,
    /// 1/T \[1/s\].
    rate_per_step: f32,
}

impl Envelope {
    /// The envelope checked for the loop period `sample_period_s` T, run under `policy` (the
    /// axis's [`crate::Limits::envelope_policy`]): a finite range with `u_min ≤ u_max` and a
    /// positive rate bound (`f32::MAX` allowed: no rate check).
    pub fn monitor(
        &self,
        policy: EnvelopePolicy,
        sample_period_s: f32,
    ) -> Result<EnvelopeMonitor, ParamError> {
        let [lo, hi] = self.input_range_v;
        finite("input_range_v", lo)?;
        finite("input_range_v", hi)?;
        if lo > hi {
            return Err(ParamError::OutOfRange {
                field: "input_range_v",
                value: lo,
                requirement: "[lo, hi] with lo <= hi",
            });
        }
        let rate = finite("input_rate_max_v_per_s", self.input_rate_max_v_per_s)?;
        if rate <= 0.0 {
            return Err(ParamError::OutOfRange {
                field: "input_rate_max_v_per_s",
                value: rate,
                requirement: "> 0",
            });
        }
        let period = finite("sample_period_s", sample_period_s)?;
        if period <= 0.0 {
            return Err(ParamError::OutOfRange {
                field: "sample_period_s",
                value: period,
                requirement: "> 0",
            });
        }
        Ok(EnvelopeMonitor {
            envelope: *self,
            policy,
            max_step_v: rate * period,
            rate_per_step: 1.0 / period,
        })
    }
}

impl EnvelopeMonitor {
    /// The envelope it checks.
    pub fn envelope(&self) -> &Envelope {
        &self.envelope
    }

    /// The policy outside (the axis's limits').
    pub fn policy(&self) -> EnvelopePolicy {
        self.policy
    }

    /// One tick: the command `u_v` after the command `previous_v` of the tick before \[V\].
    /// Counts the tick in `counts` if it is outside (`e_v > 0` or `e_r > 0`, module doc) and
    /// returns whether it was. A non-finite command counts as outside with no excursion size.
    #[inline]
    pub fn observe(&self, counts: &mut EnvelopeCounts, u_v: f32, previous_v: f32) -> bool {
        let [lo, hi] = self.envelope.input_range_v;
        let voltage = max(lo - u_v, u_v - hi);
        let step = (u_v - previous_v).abs() - self.max_step_v;
        // `!(a <= 0)` is also true for NaN: a non-finite command is outside.
        let outside = !(voltage <= 0.0 && step <= 0.0);
        if outside {
            counts.ticks_outside = counts.ticks_outside.saturating_add(1);
            // A NaN excursion (non-finite command) leaves the largest as it was.
            if voltage > counts.max_voltage_excursion_v {
                counts.max_voltage_excursion_v = voltage;
            }
            let rate = step * self.rate_per_step;
            if rate > counts.max_rate_excursion_v_per_s {
                counts.max_rate_excursion_v_per_s = rate;
            }
        }
        outside
    }

    /// The counts of a whole sequence of commands `u` \[V\] at this monitor's period, the first
    /// one's rate taken from rest at `u[0]` (what `host-sim predict` and `compensate` report).
    pub fn count(&self, u: impl IntoIterator<Item = f32>) -> EnvelopeCounts {
        let mut counts = EnvelopeCounts::default();
        let mut previous = None;
        for v in u {
            self.observe(&mut counts, v, previous.unwrap_or(v));
            previous = Some(v);
        }
        counts
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn monitor() -> EnvelopeMonitor {
        Envelope {
            input_range_v: [10.0, 50.0],
            input_rate_max_v_per_s: 1000.0,
        }
        .monitor(EnvelopePolicy::Warn, 1e-3)
        .unwrap()
    }

    #[test]
    fn inside_is_not_counted() {
        let m = monitor();
        let counts = m.count([10.0, 10.5, 11.5, 12.5, 50.0 - 1.0, 50.0 - 1.0]);
        assert_eq!(counts.ticks_outside, 1, "one 36.5 V step: over the rate");
        let counts = m.count([10.0, 10.9, 11.8, 12.7, 12.7, 50.0]);
        assert_eq!(counts.ticks_outside, 1);
        let counts = m.count((0..40).map(|k| 10.0 + k as f32));
        assert_eq!(counts, EnvelopeCounts::default());
    }

    #[test]
    fn voltage_and_rate_excursions_are_measured() {
        let m = monitor();
        // 9 V (1 V below), then 51.5 V in 1 ms steps of 1 V: 2 V/ms over at the end.
        let mut c = EnvelopeCounts::default();
        assert!(m.observe(&mut c, 9.0, 9.0));
        assert!(!m.observe(&mut c, 10.0, 9.0));
        assert!(m.observe(&mut c, 13.0, 10.0));
        assert!(m.observe(&mut c, 51.5, 51.0));
        assert_eq!(c.ticks_outside, 3);
        assert!((c.max_voltage_excursion_v - 1.5).abs() < 1e-6);
        assert!((c.max_rate_excursion_v_per_s - 2000.0).abs() < 1e-2);
        // NaN: outside, sizes unchanged.
        assert!(m.observe(&mut c, f32::NAN, 20.0));
        assert_eq!(c.ticks_outside, 4);
        assert!((c.max_voltage_excursion_v - 1.5).abs() < 1e-6);
    }

    #[test]
    fn invalid_envelopes_are_refused() {
        let bad = |range: [f32; 2], rate: f32| Envelope {
            input_range_v: range,
            input_rate_max_v_per_s: rate,
        };
        assert!(bad([5.0, 1.0], 1.0)
            .monitor(EnvelopePolicy::Warn, 1e-4)
            .is_err());
        assert!(bad([0.0, f32::NAN], 1.0)
            .monitor(EnvelopePolicy::Warn, 1e-4)
            .is_err());
        assert!(bad([0.0, 1.0], 0.0)
            .monitor(EnvelopePolicy::Warn, 1e-4)
            .is_err());
        assert!(bad([0.0, 1.0], f32::INFINITY)
            .monitor(EnvelopePolicy::Warn, 1e-4)
            .is_err());
        assert!(bad([0.0, 1.0], f32::MAX)
            .monitor(EnvelopePolicy::Warn, 1e-4)
            .is_ok());
    }
}
