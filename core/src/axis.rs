//! One axis of a stage as the firmware runs it, and every tool that builds, uploads or checks a
//! set for the firmware: the core's parameter structs of the axis (Bouc-Wen set, output map,
//! asymmetry, effects, servo), its output [`Limits`] (window, slew limit, envelope policy), and
//! its first loading from rest.
//!
//! This is the one definition: the firmware's built-in set (`firmware/build.rs` writes
//! [`AxisParams`] consts), the stage file's firmware view (`piezo_stage::FirmwareSet`), an
//! upload on the command link (`piezo_link::AxisModel` converts to and from it) and the
//! firmware's session all hold this type.
//!
//! The first loading from rest at the lower end of the window gives the rest output
//! `y_rest = y(u_min)` and the secant gain `g_lin = (y(u_max) − y_rest)/(u_max − u_min)`
//! ([`StaticModel::first_loading`]); the uncompensated baseline is
//! `u = u_min + (r − y_rest)/g_lin`, and the effects are validated over
//! `[y_rest, y_rest + g_lin·(u_max − u_min)]`.

use crate::effects::{EffectParams, Effects, OperatingRange};
use crate::{
    Asymmetry, BoucWen, BoucWenParams, Compensator, CompensatorSettings, Envelope, EnvelopeMonitor,
    EnvelopePolicy, IoChain, Limits, OnTarget, ParamError, Servo, ServoParams, StaticMap,
    StaticModel, STATE_LIMIT,
};

/// One axis: the model, its window and its servo (see the module doc).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AxisParams {
    /// Bouc-Wen parameters of the stack (h in the unit of A·u).
    pub bouc_wen: BoucWenParams,
    /// Output map y = k1·u + k2·h + y0.
    pub static_map: StaticMap,
    /// δ and φ of the asymmetric model (zero: the symmetric model).
    pub asymmetry: Asymmetry,
    /// The output window, the slew limit and the policy outside the envelope (the stage file's
    /// `[x.limits]`, [`crate::limits`]).
    pub limits: Limits,
    /// Secant gain of the first loading over the window \[m/V\]: the gain of the uncompensated
    /// (linear) baseline ([`AxisParams::with_first_loading`]).
    pub linear_gain_m_per_v: f32,
    /// Output at the window's lower end at rest \[m\].
    pub rest_output_m: f32,
    /// The effects around the hysteresis model (creep, even term, mode, delay, drift, coupling);
    /// all zero: none.
    pub effects: EffectParams,
    /// The feedback servo on the sensor (`None`: feed-forward only).
    pub servo: Option<ServoParams>,
    /// The identified envelope (`None`: not known, nothing checked; [`crate::envelope`]); the
    /// policy outside it is [`Limits::envelope_policy`].
    pub envelope: Option<Envelope>,
    /// The on-target band: |sensor − reference| ≤ tolerance for N ticks ([`crate::on_target`];
    /// the stage file's `[x.on_target]`, or [`OnTarget::default_for`] the chain).
    pub on_target: OnTarget,
}

impl AxisParams {
    /// This axis with its rest output and baseline gain computed from its quasi-static model's
    /// first loading over the window (what the stage file's validation computes, and what the
    /// firmware computes for an uploaded set, which does not carry them).
    pub fn with_first_loading(mut self, sample_period_s: f32) -> Result<Self, ParamError> {
        let (rest, gain) = self
            .quasi_static_model(sample_period_s)?
            .first_loading(self.limits.output_min_v, self.limits.output_max_v);
        self.rest_output_m = rest;
        self.linear_gain_m_per_v = gain;
        Ok(self)
    }

    /// The compensator's settings: this axis's limits with the loop period `sample_period_s`
    /// \[s\].
    pub fn settings(&self, sample_period_s: f32) -> CompensatorSettings {
        CompensatorSettings {
            limits: self.limits,
            sample_period_s,
        }
    }

    /// The core's quasi-static model over the output window (without the effects' input lag),
    /// at the loop period `sample_period_s` \[s\] (the asymmetric model's φ term is a rate).
    pub fn quasi_static_model(&self, sample_period_s: f32) -> Result<StaticModel, ParamError> {
        let hysteresis = BoucWen::with_input_range(
            self.bouc_wen,
            self.limits.output_min_v,
            self.limits.output_max_v,
            STATE_LIMIT,
        )?;
        StaticModel::with_asymmetry(hysteresis, self.static_map, self.asymmetry, sample_period_s)
    }

    /// The core's forward model the compensator inverts: the quasi-static one with the effects'
    /// input lag, if any ([`EffectParams::hysteresis_model`]).
    pub fn model(&self, sample_period_s: f32) -> Result<StaticModel, ParamError> {
        self.effects
            .hysteresis_model(self.quasi_static_model(sample_period_s)?, sample_period_s)
    }

    /// What the effects are validated against: the output window and the first loading's
    /// output over it, `[y_rest, y_rest + g_lin·(u_max − u_min)]`.
    pub fn operating_range(&self) -> OperatingRange {
        OperatingRange::first_loading(
            self.rest_output_m,
            self.linear_gain_m_per_v,
            (self.limits.output_min_v, self.limits.output_max_v),
        )
    }

    /// The core's effect chain of this axis at the loop period `sample_period_s` \[s\].
    pub fn effect_chain(&self, sample_period_s: f32) -> Result<Effects, ParamError> {
        Effects::new(self.effects, sample_period_s, self.operating_range())
    }

    /// The core's feedback servo of this axis at the loop period `sample_period_s` \[s\] (with
    /// the compensator's output window and slew limit, around the first-loading gain), if the
    /// axis has one.
    pub fn servo(&self, sample_period_s: f32) -> Result<Option<Servo>, ParamError> {
        self.servo
            .map(|p| Servo::new(p, self.settings(sample_period_s), self.linear_gain_m_per_v))
            .transpose()
    }

    /// The per-tick check of this axis's identified envelope at the loop period
    /// `sample_period_s` \[s\] ([`Envelope::monitor`]) under the policy of its limits
    /// ([`Limits::envelope_policy`]), if it has one. Refused ([`ParamError::NeedsServo`]) when
    /// the policy is `feedback-only` and the axis has no servo.
    pub fn envelope_monitor(
        &self,
        sample_period_s: f32,
    ) -> Result<Option<EnvelopeMonitor>, ParamError> {
        let Some(envelope) = self.envelope else {
            return Ok(None);
        };
        let policy = self.limits.envelope_policy;
        if policy == EnvelopePolicy::FeedbackOnly && self.servo.is_none() {
            return Err(ParamError::NeedsServo {
                field: "envelope_policy",
            });
        }
        envelope.monitor(policy, sample_period_s).map(Some)
    }

    /// This axis's window and slew limit against the chain `io` at the loop period
    /// `sample_period_s` \[s\] ([`IoChain::check_limits`]).
    pub fn check_chain(&self, io: &IoChain, sample_period_s: f32) -> Result<(), ParamError> {
        io.check_limits(&self.settings(sample_period_s))
    }

    /// The core's inverse compensator for this axis at the loop period `sample_period_s` \[s\].
    pub fn compensator(&self, sample_period_s: f32) -> Result<Compensator, ParamError> {
        Compensator::new(self.model(sample_period_s)?, self.settings(sample_period_s))
    }

    /// This axis with another Bouc-Wen exponent (for benches of the general-n path). β and γ are
    /// scaled by `H^(n₀ − n)` so that the saturation level `H = (A/(β + γ))^(1/n)` stays where it
    /// was and the loop keeps its shape.
    pub fn with_exponent(mut self, n: f32) -> Self {
        let bw = &mut self.bouc_wen;
        let level = libm::powf(
            bw.a.abs() / (bw.beta + bw.gamma * bw.a.signum()),
            1.0 / bw.n,
        );
        let scale = libm::powf(level, bw.n - n);
        bw.beta *= scale;
        bw.gamma *= scale;
        bw.n = n;
        self
    }
}
