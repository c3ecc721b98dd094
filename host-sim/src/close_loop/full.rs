//! The model `close-loop` refits: piezo-core's static Bouc-Wen model followed by the core's effect chain
//! ([`piezo_core::effects`]), one per axis, and a Levenberg–Marquardt fit of all its parameters at once
//! on a chosen set of samples (the whole scored record, or all but one held-out block).
//!
//! Per axis and command sample j (the chain of `piezo_core::effects`):
//! w = k1·u + k2·h + y0 (h the Bouc-Wen state, A = 1), s = w + e·(u_{j−1} − u_c)² + c (creep: a
//! Kelvin–Voigt bank Σ g_i·x_i or the logarithmic bank g_log·½·Σ x_l with t₀ = one sample period),
//! z = M(s) (second-order mode), y(t_j) = z(j − D) + d(t_j) + κ·z_other(j − D) with the drift
//! d(t) = r·t (linear) or A·(1 − e^(−t/τ)) (settling). The coupling follows the core's convention:
//! the other axis's z delayed by *this* axis's D. The simulation is the core's f32 code, started at
//! rest at the first input (`ModelState::at_rest(u0)`, `EffectsState::at_rest(u0)`); only the
//! optimiser runs in f64.
//!
//! Parameter vector θ: (β, γ, n, k1, k2, y0), then per added effect: creep (g_i, ln τ_i) per element
//! or g_log, drift r or (A, ln τ), delay D \[s\], asymmetry e \[m/V²\] (u_c held), dynamics (ln f, ln ζ;
//! its form ρ = `mode_relative_damping` held, 0 or 1, chosen by fitting both),
//! coupling κ. Each entry is a named [`Param`] (its [`ParamSpec`]: range, log scale, effect).
//! Every effect parameter has a range that makes it that effect ([`EffectBounds`]);
//! [`AxisModel::decode`] holds θ inside it and writes each entry into its field
//! ([`Param::set`]), and [`AxisModel::effect_parameters`] names the parameters a fit
//! ran to. [`refit`] is the shared Levenberg–Marquardt ([`crate::optimise::Marquardt`]); its
//! Jacobian is by forward differences (one core simulation per column, in parallel),
//! steps Marquardt-scaled; a set the core refuses scores an infinite SSE and the step is rejected
//! (with `--invertible`, [`FitData::invertible_at_hz`], so does a set the compensator refuses: the
//! fit stays inside the sets `host-sim compensate` runs).
//! A column of a map or effect parameter leaves the Bouc-Wen set alone, so it runs on the base
//! point's hysteresis path ([`HysteresisPath`]: the operator's input and h per sample) instead of
//! integrating the operator again; the numbers are those of a whole simulation, bit for bit.
//! [`linearise`] takes the final fit's Jacobian in the parameters as reported (central
//! differences, the log-scale entries chained to their parameters) for its uncertainty.

// Small dense linear algebra reads best with index loops.
#![allow(clippy::needless_range_loop)]

use super::diagnose::{EffectInit, EffectKind};
use super::param::Param;
use crate::identify::model::bouc_wen;
use crate::optimise::{LeastSquares, Marquardt, NormalEquations};
use crate::uncertainty::{Linearised, Parameter};
use piezo_core::effects::{EffectParams, Effects, EffectsState};
use piezo_core::{BoucWen, BoucWenParams, ModelState, StaticMap, StaticModel};
use rayon::prelude::*;

/// The form of the creep term.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CreepForm {
    /// Kelvin–Voigt elements (gains and time constants fitted).
    KelvinVoigt,
    /// Logarithmic creep g_log·log₁₀(1 + t/t₀) per step, t₀ = one sample period (gain fitted).
    Logarithmic,
}

/// The form of the drift term.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DriftForm {
    /// r·t.
    Linear,
    /// A·(1 − e^(−t/τ)).
    Settling,
}

/// The form of the rate-dependent hysteresis.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RateForm {
    /// The Bouc-Wen operator driven by a first-order lag of the command (τ_v fitted; the core's
    /// `hysteresis_lag_s`).
    InputLag,
    /// A relaxation of the hysteretic part k2·h (gain g and τ_w fitted; the core's
    /// `relaxation_gain`, `relaxation_time_constant_s`).
    Relaxation,
    /// Both at once, two time constants: the operator driven by a lag of the command (τ_v) and
    /// its output k2·h relaxing, G(s) = 1 + g/(1 + s·τ_w) — a spread of dielectric relaxation
    /// times that one first-order lag cannot follow across rates (τ_v, g and τ_w fitted).
    LagAndRelaxation,
    /// The input lag and two relaxation elements, G(s) = 1 + Σᵢ gᵢ/(1 + s·τ_wᵢ) (i = 0, 1): three
    /// time constants (τ_v, both g and both τ_w fitted).
    LagAndTwoRelaxations,
    /// A relaxation of the whole output w = k1·u + k2·h (k_r = 0), G(s) = 1 + g/(1 + s·τ_w) on w
    /// (g and τ_w fitted): a stack whose whole polarisation, the linear strain with the switched
    /// domains, follows the voltage through a dielectric loss, so that its loops widen with rate
    /// where those of [`Self::Relaxation`] (the hysteretic part alone relaxing) narrow.
    WholeRelaxation,
    /// [`Self::Relaxation`] with its relaxation times spread log-uniformly over W decades around
    /// τ_w (the core's `relaxation_spread_decades`; g, τ_w and W fitted): a dielectric's spread
    /// of relaxation times, whose loop opening grows over W decades of rate.
    SpreadRelaxation,
    /// [`Self::WholeRelaxation`] with its relaxation times spread over W decades (g, τ_w, W).
    WholeSpreadRelaxation,
    /// The Bouc-Wen operator's gain rising with the command's speed, A·(1 + c·|u̇|) (c fitted;
    /// the core's `hysteresis_rate_gain_s_per_v`): loops that grow taller and wider with the rate
    /// and keep growing with it, where a lag's or a relaxation's effect levels off.
    RateGain,
}

impl RateForm {
    /// Name in reports.
    pub fn name(self) -> &'static str {
        match self {
            Self::InputLag => "input lag",
            Self::Relaxation => "relaxation",
            Self::LagAndRelaxation => "input lag and relaxation",
            Self::LagAndTwoRelaxations => "input lag and two relaxations",
            Self::WholeRelaxation => "relaxation of the whole output",
            Self::SpreadRelaxation => "spread relaxation",
            Self::WholeSpreadRelaxation => "spread relaxation of the whole output",
            Self::RateGain => "rate-dependent gain",
        }
    }
}

impl RateForm {
    /// Whether the operator is driven by a lag of the command (τ_v fitted).
    pub fn has_input_lag(self) -> bool {
        matches!(
            self,
            Self::InputLag | Self::LagAndRelaxation | Self::LagAndTwoRelaxations
        )
    }
    /// Whether the hysteretic output (or the whole output) relaxes (g and τ_w fitted).
    pub fn has_relaxation(self) -> bool {
        matches!(
            self,
            Self::Relaxation
                | Self::LagAndRelaxation
                | Self::LagAndTwoRelaxations
                | Self::WholeRelaxation
                | Self::SpreadRelaxation
                | Self::WholeSpreadRelaxation
        )
    }
    /// Whether the operator's gain rises with the command's speed (c fitted).
    pub fn has_rate_gain(self) -> bool {
        self == Self::RateGain
    }
    /// Whether the relaxation times are spread (W fitted).
    pub fn has_spread(self) -> bool {
        matches!(self, Self::SpreadRelaxation | Self::WholeSpreadRelaxation)
    }
    /// Whether the whole output relaxes (k_r = 0), not the hysteretic part alone (k_r = k1).
    pub fn relaxes_whole_output(self) -> bool {
        matches!(self, Self::WholeRelaxation | Self::WholeSpreadRelaxation)
    }
    /// Number of relaxation elements fitted.
    pub fn relaxation_elements(self) -> usize {
        match self {
            Self::InputLag | Self::RateGain => 0,
            Self::Relaxation
            | Self::LagAndRelaxation
            | Self::WholeRelaxation
            | Self::SpreadRelaxation
            | Self::WholeSpreadRelaxation => 1,
            Self::LagAndTwoRelaxations => 2,
        }
    }
}

impl CreepForm {
    /// Name in reports.
    pub fn name(self) -> &'static str {
        match self {
            Self::KelvinVoigt => "Kelvin-Voigt",
            Self::Logarithmic => "logarithmic",
        }
    }
}

impl DriftForm {
    /// Name in reports.
    pub fn name(self) -> &'static str {
        match self {
            Self::Linear => "linear",
            Self::Settling => "exponential settling",
        }
    }
}

/// The ranges that make each effect that effect (physical plausibility), from the record.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EffectBounds {
    /// Creep time constants: a few sample periods to a third of the scored record \[s\].
    pub creep_tau_s: (f64, f64),
    /// Largest total creep gain (Kelvin–Voigt), a share of the linear gain \[m/V\]; plausible gains
    /// are > 0.
    pub creep_max_gain_m_per_v: f64,
    /// Largest logarithmic creep per decade \[m/V\]; ≥ 0.
    pub log_creep_max_gain_m_per_v: f64,
    /// Settling drift time constants: several input periods to a few records \[s\].
    pub settling_tau_s: (f64, f64),
    /// Largest settling amplitude or linear drift over the record \[m\].
    pub drift_max_m: f64,
    /// Scored record duration \[s\].
    pub record_s: f64,
    /// Delay: 0 to a fraction of the input period (at most 64 samples) \[s\].
    pub delay_max_s: f64,
    /// Largest |e|: the even term may move the output by a quarter of the stroke \[m/V²\].
    pub even_max_m_per_v2: f64,
    /// Mode frequency: above the excitation band, below Nyquist \[Hz\].
    pub mode_frequency_hz: (f64, f64),
    /// Mode damping ratio.
    pub mode_damping: (f64, f64),
    /// Largest |κ|.
    pub coupling_max: f64,
    /// Rate-dependent hysteresis, every form (the relaxations' τ_w and the input lag's τ_v):
    /// time constants from one sample period to a tenth of the record or 50 ms \[s\] (0.1 ms to
    /// 50 ms for a 0.5 s record at 10 kHz).
    pub relaxation_tau_s: (f64, f64),
    /// Relaxation gain g of the hysteretic part, G(s) = 1 + g/(1 + s·τ): from 0.01 (less: no
    /// rate dependence) to 100 (its high-frequency response 1 % of its static one, a pure lag
    /// of k2·h). Fitted as ln g; the core's stable-inverse bound g·tanh(T/2τ) ≤ 0.5 is the
    /// fit's other limit (a set beyond it is refused), not this effect's.
    pub relaxation_gain: (f64, f64),
    /// Sample period \[s\].
    pub sample_period_s: f64,
    /// Sign of the stage's static gain dy/du (±1): a creep gain of this sign keeps the output moving
    /// the way a command change moved it.
    pub gain_sign: f64,
}

impl EffectBounds {
    /// The ranges for a record: sample period `ts`, scored duration `record_s`, dominant input
    /// frequency `f_dom`, output stroke `stroke_m`, linear gain `gain_m_per_v` (signed: the sign of
    /// dy/du), input span `span_v`.
    pub fn for_record(
        ts: f64,
        record_s: f64,
        f_dom: f64,
        stroke_m: f64,
        gain_m_per_v: f64,
        span_v: f64,
    ) -> Self {
        let gain = gain_m_per_v.abs().max(1e-30);
        let half = (0.5 * span_v).max(1e-9);
        let nyquist = 0.5 / ts;
        let settling_lo = (2.0 / f_dom).max(20.0 * ts);
        Self {
            creep_tau_s: (3.0 * ts, (record_s / 3.0).max(4.0 * ts)),
            creep_max_gain_m_per_v: 0.5 * gain,
            log_creep_max_gain_m_per_v: 0.1 * gain,
            settling_tau_s: (settling_lo, (3.0 * record_s).max(4.0 * settling_lo)),
            drift_max_m: 0.5 * stroke_m.max(1e-12),
            record_s,
            delay_max_s: (64.0 * ts).min(0.05 / f_dom).max(ts),
            even_max_m_per_v2: 0.25 * stroke_m.max(1e-12) / (half * half),
            mode_frequency_hz: ((10.0 * f_dom).min(0.2 * nyquist), 0.85 * nyquist),
            mode_damping: (0.005, 2.0),
            coupling_max: 0.3,
            relaxation_tau_s: (ts, (record_s / 10.0).clamp(4.0 * ts, 0.05)),
            relaxation_gain: (0.01, 100.0),
            sample_period_s: ts,
            gain_sign: if gain_m_per_v < 0.0 { -1.0 } else { 1.0 },
        }
    }
}

/// The rate-dependent gain c the [`RateForm::RateGain`] fit starts from \[s/V\]: the operator's
/// gain 5 % higher at 10 kV/s (a 0–120 V sine at 27 Hz).
pub const RATE_GAIN_START_S_PER_V: f64 = 5e-6;

/// The lowest rate-dependent gain c a fit may reach \[s/V\]: 0.1 % at 100 kV/s, the fastest
/// command a 10 kHz loop's slew limit usually allows; a fit that runs here has found none.
pub const MIN_RATE_GAIN_S_PER_V: f64 = 1e-8;

/// The relaxation gain g the two-time-constant form ([`RateForm::LagAndRelaxation`]) starts from.
pub const LAG_AND_RELAXATION_START_GAIN: f64 = 0.2;

/// One axis's complete model, in SI.
#[derive(Debug, Clone, PartialEq)]
pub struct AxisModel {
    /// Bouc-Wen parameters (A = 1).
    pub bouc_wen: BoucWenParams,
    /// y = k1·u + k2·h + y0.
    pub map: StaticMap,
    /// The effect chain's parameters (all zero: none).
    pub effects: EffectParams,
    /// Effects in the order they were added.
    pub added: Vec<EffectKind>,
    /// The creep's form (when added).
    pub creep_form: CreepForm,
    /// Number of Kelvin–Voigt elements (1 or 2).
    pub creep_elements: usize,
    /// The drift's form (when added).
    pub drift_form: DriftForm,
    /// The rate-dependent hysteresis's form (when added).
    pub rate_form: RateForm,
    /// Whether the form also carries the operator's rate-dependent gain A·(1 + c·|v̇|) (c fitted
    /// beside the form's own parameters; [`RateForm::RateGain`] is the gain alone).
    pub with_rate_gain: bool,
    /// Input range the Bouc-Wen set is validated over \[V\].
    pub input_range_v: (f32, f32),
    /// Range of the hysteresis output w (the measured range widened by a quarter each side) \[m\].
    pub w_range_m: (f32, f32),
    /// Sample period \[s\].
    pub sample_period_s: f32,
    /// The plausible ranges of the effect parameters.
    pub bounds: EffectBounds,
    /// The first sample of each record the model runs over (several records of one stage end to
    /// end): the simulation starts from rest at each; `[0]` for one record.
    pub segments: Vec<usize>,
    /// Each record's constant offset is re-estimated on its own samples (`--free-offset`); the
    /// map's y0 is then held in fits.
    pub free_offset: bool,
}

/// A simulation of the whole record.
#[derive(Debug, Clone, Default)]
pub struct Simulation {
    /// Prediction \[m\].
    pub y: Vec<f64>,
    /// Bouc-Wen state.
    pub h: Vec<f64>,
    /// The axis's z before delay, drift and coupling (what the other axis couples to) \[m\].
    pub z: Vec<f64>,
}

/// The hysteresis operator's path over a record (sanitised input and h per sample), for a Bouc-Wen
/// set and input range: models that differ only in their map or effects share it.
#[derive(Debug, Clone)]
pub struct HysteresisPath {
    /// The Bouc-Wen set it was integrated with.
    bouc_wen: BoucWenParams,
    /// The input range that set was validated over \[V\].
    input_range_v: (f32, f32),
    /// The operator's input lag τ_v \[s\] (0: none).
    lag_s: f32,
    /// The operator's rate-dependent gain c \[s/V\] (0: none).
    rate_gain_s_per_v: f32,
    /// The validated operator.
    operator: BoucWen,
    /// The operator's input per sample (the command clamped into its range) \[V\].
    input_v: Vec<f32>,
    /// h per sample.
    h: Vec<f32>,
}

impl HysteresisPath {
    /// Whether `model` has this path's operator.
    fn fits(&self, model: &AxisModel) -> bool {
        self.bouc_wen == model.bouc_wen
            && self.input_range_v == model.input_range_v
            && self.lag_s == model.effects.hysteresis_lag_s
            && self.rate_gain_s_per_v == model.effects.hysteresis_rate_gain_s_per_v
    }
}

/// One entry of θ: which parameter, its range (infinite: free) and whether it is a logarithm.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ParamSpec {
    /// The parameter (its name in reports: [`Param::name`]).
    pub param: Param,
    /// Lower end (in θ's coordinate).
    pub lo: f64,
    /// Upper end (in θ's coordinate).
    pub hi: f64,
    /// θ is the natural logarithm of the parameter.
    pub log: bool,
    /// The effect it belongs to (None: base model).
    pub effect: Option<EffectKind>,
}

impl ParamSpec {
    fn free(param: Param) -> Self {
        Self {
            param,
            lo: f64::NEG_INFINITY,
            hi: f64::INFINITY,
            log: false,
            effect: None,
        }
    }
    fn within(param: Param, effect: EffectKind, lo: f64, hi: f64) -> Self {
        Self {
            param,
            lo,
            hi,
            log: false,
            effect: Some(effect),
        }
    }
    fn log_within(param: Param, effect: EffectKind, lo: f64, hi: f64) -> Self {
        Self {
            param,
            lo: lo.max(1e-300).ln(),
            hi: hi.max(1e-300).ln(),
            log: true,
            effect: Some(effect),
        }
    }
    /// The parameter's value for θ entry `t`.
    pub fn value(&self, t: f64) -> f64 {
        if self.log {
            t.exp()
        } else {
            t
        }
    }
    /// The range in the parameter's own units.
    pub fn range(&self) -> (f64, f64) {
        (self.value(self.lo), self.value(self.hi))
    }
}

/// The range of the Bouc-Wen exponent n that piezo-core accepts.
const BOUC_WEN_EXPONENT_RANGE: (f64, f64) = (1.0, 16.0);

/// Share of a range within which a fitted value counts as having run to the bound.
pub const AT_BOUND_SHARE: f64 = 0.01;

impl AxisModel {
    /// Builds the core objects (validation).
    pub fn build(&self) -> crate::Result<(StaticModel, Effects)> {
        let h = bouc_wen(self.bouc_wen, self.input_range_v).map_err(|e| {
            crate::Error::Refused(format!("Bouc-Wen set refused by piezo-core: {e}"))
        })?;
        self.build_on(h)
    }

    /// The core's model (this map on the operator `h`) and effects, validated.
    fn build_on(&self, h: BoucWen) -> crate::Result<(StaticModel, Effects)> {
        let model = StaticModel::new(h, self.map)
            .map_err(|e| crate::Error::Refused(format!("static map refused by piezo-core: {e}")))?;
        let range = piezo_core::effects::OperatingRange {
            input_v: self.input_range_v,
            output_m: self.w_range_m,
        };
        let effects = Effects::new(self.effects, self.sample_period_s, range)
            .map_err(|e| crate::Error::Refused(format!("effects refused by piezo-core: {e}")))?;
        let model = effects.hysteresis_model(model).map_err(|e| {
            crate::Error::Refused(format!("hysteresis input lag refused by piezo-core: {e}"))
        })?;
        Ok((model, effects))
    }

    /// Simulates the record (the model sees only u, and the other axis's z for coupling).
    pub fn simulate(&self, u: &[f32], other_z: Option<&[f64]>) -> crate::Result<Simulation> {
        let mut out = Simulation {
            y: Vec::with_capacity(u.len()),
            h: Vec::with_capacity(u.len()),
            z: Vec::with_capacity(u.len()),
        };
        self.simulate_into(u, other_z, |_, y, h, z| {
            out.y.push(y);
            out.h.push(h);
            out.z.push(z);
        })?;
        Ok(out)
    }

    /// Simulates from rest at u\[0\] and calls `visit(k, y, h, z)` per sample, without allocating.
    /// `other_z`: the other axis's z (undelayed); it is delayed by this axis's D, as in the core.
    pub fn simulate_into(
        &self,
        u: &[f32],
        other_z: Option<&[f64]>,
        visit: impl FnMut(usize, f64, f64, f64),
    ) -> crate::Result<()> {
        let (model, effects) = self.build()?;
        let Some(&u0) = u.first() else {
            return Ok(());
        };
        let mut s = ModelState::at_rest(u0);
        let operator = |k: usize| {
            if self.starts_record(k) {
                s = ModelState::at_rest(u[k]);
            }
            model.step(&mut s, u[k]);
            (s.input_v, s.hysteresis.h)
        };
        self.run_chain(model.map(), &effects, u, other_z, operator, visit);
        Ok(())
    }

    /// Whether sample `k` > 0 is the first of a record (the state restarts from rest there).
    fn starts_record(&self, k: usize) -> bool {
        k > 0 && self.segments.binary_search(&k).is_ok()
    }

    /// The hysteresis operator's path over `u` from rest at u\[0\]: what every model with this
    /// model's Bouc-Wen set and input range shares, whatever its map and effects.
    pub fn hysteresis_path(&self, u: &[f32]) -> crate::Result<HysteresisPath> {
        let (model, _) = self.build()?;
        let mut path = HysteresisPath {
            bouc_wen: self.bouc_wen,
            input_range_v: self.input_range_v,
            lag_s: self.effects.hysteresis_lag_s,
            rate_gain_s_per_v: self.effects.hysteresis_rate_gain_s_per_v,
            operator: *model.hysteresis(),
            input_v: Vec::with_capacity(u.len()),
            h: Vec::with_capacity(u.len()),
        };
        if let Some(&u0) = u.first() {
            let mut s = ModelState::at_rest(u0);
            for (k, &v) in u.iter().enumerate() {
                if self.starts_record(k) {
                    s = ModelState::at_rest(v);
                }
                model.step(&mut s, v);
                path.input_v.push(s.input_v);
                path.h.push(s.hysteresis.h);
            }
        }
        Ok(path)
    }

    /// [`Self::simulate_into`] on a path of the hysteresis operator computed before
    /// ([`Self::hysteresis_path`]), which must be this model's (same Bouc-Wen set and input range):
    /// the same numbers, without integrating the operator again.
    pub fn simulate_on_path(
        &self,
        path: &HysteresisPath,
        u: &[f32],
        other_z: Option<&[f64]>,
        visit: impl FnMut(usize, f64, f64, f64),
    ) -> crate::Result<()> {
        if !path.fits(self) || path.h.len() != u.len() {
            return self.simulate_into(u, other_z, visit);
        }
        let (model, effects) = self.build_on(path.operator)?;
        let operator = |k: usize| (path.input_v[k], path.h[k]);
        self.run_chain(model.map(), &effects, u, other_z, operator, visit);
        Ok(())
    }

    /// The chain after the hysteresis operator: `operator(k)` gives the operator's (sanitised) input
    /// and h at sample k; w = k1·u + k2·h + y0, then the effects, the delay and the coupling.
    fn run_chain(
        &self,
        map: StaticMap,
        effects: &Effects,
        u: &[f32],
        other_z: Option<&[f64]>,
        mut operator: impl FnMut(usize) -> (f32, f32),
        mut visit: impl FnMut(usize, f64, f64, f64),
    ) {
        let Some(&u0) = u.first() else {
            return;
        };
        let mut es = EffectsState::at_rest(u0);
        let c = self.effects.coupling;
        let whole = effects.reference_index_offset();
        let frac = effects.delay_fraction();
        for k in 0..u.len() {
            if self.starts_record(k) {
                es = EffectsState::at_rest(u[k]);
            }
            let (input_v, h) = operator(k);
            let w = map.output(input_v, h);
            let z = effects.forward_z(&mut es, input_v, w);
            let mut y = effects.output_m(&es);
            if let (Some(o), true) = (other_z, c != 0.0) {
                // z_other(k − D), linear interpolation, z_other[0] before the start (the core's ring).
                let at = o[k.saturating_sub(whole)] as f32;
                let before = o[k.saturating_sub(whole + 1)] as f32;
                let delayed = if frac == 0.0 {
                    at
                } else {
                    at + frac * (before - at)
                };
                y += c * delayed;
            }
            visit(k, f64::from(y), f64::from(h), f64::from(z));
        }
    }

    /// Adds an effect with its screening values (the model keeps its other parameters); the values
    /// are held inside the plausible ranges.
    pub fn with_effect(&self, init: EffectInit) -> Self {
        let mut m = self.without_effect(init.kind());
        let b = self.bounds;
        let e = &mut m.effects;
        let clamp_log = |v: f64, (lo, hi): (f64, f64)| v.clamp(lo, hi) as f32;
        match init {
            EffectInit::Creep {
                gains_m_per_v,
                time_constants_s,
            } => {
                let n = if gains_m_per_v[1] != 0.0 { 2 } else { 1 };
                for i in 0..n {
                    e.creep_gain_m_per_v[i] = gains_m_per_v[i]
                        .clamp(-b.creep_max_gain_m_per_v, b.creep_max_gain_m_per_v)
                        as f32;
                    e.creep_time_constant_s[i] = clamp_log(time_constants_s[i], b.creep_tau_s);
                }
                m.creep_form = CreepForm::KelvinVoigt;
                m.creep_elements = n;
            }
            EffectInit::LogCreep { gain_m_per_v } => {
                e.log_creep_gain_m_per_v = gain_m_per_v
                    .clamp(-b.log_creep_max_gain_m_per_v, b.log_creep_max_gain_m_per_v)
                    as f32;
                e.log_creep_time_s = m.sample_period_s;
                m.creep_form = CreepForm::Logarithmic;
            }
            EffectInit::Drift { rate_m_per_s } => {
                let max = b.drift_max_m / b.record_s;
                e.drift_rate_m_per_s = rate_m_per_s.clamp(-max, max) as f32;
                m.drift_form = DriftForm::Linear;
            }
            EffectInit::Settling {
                amplitude_m,
                time_constant_s,
            } => {
                e.drift_settling_m = amplitude_m.clamp(-b.drift_max_m, b.drift_max_m) as f32;
                e.drift_settling_time_constant_s = clamp_log(time_constant_s, b.settling_tau_s);
                m.drift_form = DriftForm::Settling;
            }
            EffectInit::Delay { delay_s } => {
                e.delay_s = delay_s.clamp(0.0, b.delay_max_s) as f32;
            }
            EffectInit::Asymmetry {
                coefficient_m_per_v2,
                center_v,
            } => {
                e.even_coefficient_m_per_v2 =
                    coefficient_m_per_v2.clamp(-b.even_max_m_per_v2, b.even_max_m_per_v2) as f32;
                e.even_center_v = center_v as f32;
            }
            EffectInit::Dynamics {
                frequency_hz,
                damping,
            } => {
                e.mode_frequency_hz = clamp_log(frequency_hz, b.mode_frequency_hz);
                e.mode_damping = clamp_log(damping, b.mode_damping);
            }
            EffectInit::Coupling { coefficient } => {
                e.coupling = coefficient.clamp(-b.coupling_max, b.coupling_max) as f32;
            }
            EffectInit::RateDependent {
                time_constant_s, ..
            } if m.rate_form.has_input_lag() && m.rate_form.has_relaxation() => {
                // The lag's start as below, and a small relaxation slower than it
                // (k2·(1 + g) kept: the static hysteretic gain is the data's).
                let lag = time_constant_s.clamp(b.relaxation_tau_s.0, b.relaxation_tau_s.1);
                e.hysteresis_lag_s = lag as f32;
                let gain = LAG_AND_RELAXATION_START_GAIN;
                m.map.k2_m_per_h = (f64::from(m.map.k2_m_per_h) / (1.0 + gain)) as f32;
                e.relaxation_gain[0] = gain as f32;
                e.relaxation_time_constant_s[0] =
                    (4.0 * lag).clamp(b.relaxation_tau_s.0, b.relaxation_tau_s.1) as f32;
                e.relaxation_linear_m_per_v = m.map.k1_m_per_v;
            }
            EffectInit::RateDependent { .. } if m.rate_form == RateForm::RateGain => {
                // The operator's gain 5 % higher at 10 kV/s: the fit moves it from there
                // ([`RATE_GAIN_START_S_PER_V`]).
                e.hysteresis_rate_gain_s_per_v = RATE_GAIN_START_S_PER_V as f32;
            }
            EffectInit::RateDependent {
                time_constant_s, ..
            } if m.rate_form == RateForm::InputLag => {
                // A lag of h with τ and h driven by a lag of u with τ share their first-order
                // signature, −τ·ḣ.
                e.hysteresis_lag_s =
                    time_constant_s.clamp(b.relaxation_tau_s.0, b.relaxation_tau_s.1) as f32;
            }
            EffectInit::RateDependent {
                time_constant_s, ..
            } if m.rate_form.relaxes_whole_output() => {
                // A relaxation of the whole output at the screening's τ, its gain twice the
                // bound's lowest (the start is the current model, nearly: the gain and its split
                // from τ are the fit's and [`Self::relaxation_restart`]'s), the static gains
                // k1·(1 + g) and k2·(1 + g) kept (the static output is the data's); k_r = 0.
                let gain = 2.0 * b.relaxation_gain.0;
                m.map.k1_m_per_v = (f64::from(m.map.k1_m_per_v) / (1.0 + gain)) as f32;
                m.map.k2_m_per_h = (f64::from(m.map.k2_m_per_h) / (1.0 + gain)) as f32;
                let tau = time_constant_s.clamp(b.relaxation_tau_s.0, b.relaxation_tau_s.1);
                let stable = 0.4 / (0.5 * b.sample_period_s / tau).tanh();
                e.relaxation_gain[0] =
                    gain.clamp(b.relaxation_gain.0, b.relaxation_gain.1.min(stable)) as f32;
                e.relaxation_time_constant_s[0] = tau as f32;
                e.relaxation_linear_m_per_v = 0.0;
            }
            EffectInit::RateDependent {
                lag_coefficient_m,
                time_constant_s,
            } => {
                // The screening's y ≈ ŷ − c·h + c·lag(h) (its static part kept): k2 → k2 − c,
                // g = c / (k2 − c).
                let k2 = f64::from(m.map.k2_m_per_h) - lag_coefficient_m;
                let gain = if k2 != 0.0 {
                    lag_coefficient_m / k2
                } else {
                    0.0
                };
                if gain > 0.0 {
                    m.map.k2_m_per_h = k2 as f32;
                }
                let tau = time_constant_s.clamp(b.relaxation_tau_s.0, b.relaxation_tau_s.1);
                // Within the core's stable-inverse bound g·tanh(T/2τ) ≤ 0.5 (at 0.4).
                let stable = 0.4 / (0.5 * b.sample_period_s / tau).tanh();
                e.relaxation_gain[0] =
                    gain.clamp(b.relaxation_gain.0, b.relaxation_gain.1.min(stable)) as f32;
                e.relaxation_time_constant_s[0] = tau as f32;
                // The hysteretic part relaxes; the linear strain k1·u follows at once.
                e.relaxation_linear_m_per_v = m.map.k1_m_per_v;
            }
        }
        m.added.push(init.kind());
        m
    }

    /// The model with its rate-dependent hysteresis restarted at relaxation gain `gain`, its
    /// static hysteretic gain k2·(1 + g) and its first-order lag τ·g/(1 + g) kept: on records
    /// slow against τ (ω·τ ≪ 1) G(jω) ≈ (1 + g)·(1 − jω·τ·g/(1 + g)), so those two are what the
    /// data fix and the split into g and τ is left to the fit; `None` without the effect, or when
    /// the start lies outside the bounds or the core's stable-inverse bound (at 0.4).
    pub fn relaxation_restart(&self, gain: f64) -> Option<Self> {
        if !self.added.contains(&EffectKind::RateDependent)
            || !matches!(
                self.rate_form,
                RateForm::Relaxation | RateForm::WholeRelaxation
            )
        {
            return None;
        }
        let b = self.bounds;
        let g0 = f64::from(self.effects.relaxation_gain[0]);
        let tau0 = f64::from(self.effects.relaxation_time_constant_s[0]);
        let tau = tau0 * g0 / (1.0 + g0) * (1.0 + gain) / gain;
        let stable = 0.4 / (0.5 * b.sample_period_s / tau).tanh();
        let inside = |v: f64, (lo, hi): (f64, f64)| v > lo && v < hi;
        if !(inside(gain, b.relaxation_gain) && inside(tau, b.relaxation_tau_s) && gain <= stable) {
            return None;
        }
        let mut m = self.clone();
        m.map.k2_m_per_h = (f64::from(self.map.k2_m_per_h) * (1.0 + g0) / (1.0 + gain)) as f32;
        if self.rate_form == RateForm::WholeRelaxation {
            // The whole output relaxes: its linear gain k1·(1 + g) is kept too.
            m.map.k1_m_per_v = (f64::from(self.map.k1_m_per_v) * (1.0 + g0) / (1.0 + gain)) as f32;
        }
        m.effects.relaxation_gain[0] = gain as f32;
        m.effects.relaxation_time_constant_s[0] = tau as f32;
        Some(m)
    }

    /// The model without `kind` (its parameters zeroed; the rest kept).
    pub fn without_effect(&self, kind: EffectKind) -> Self {
        let mut m = self.clone();
        m.added.retain(|k| *k != kind);
        if kind == EffectKind::RateDependent {
            m.with_rate_gain = false;
        }
        let e = &mut m.effects;
        match kind {
            EffectKind::Creep => {
                e.creep_gain_m_per_v = Default::default();
                e.creep_time_constant_s = Default::default();
                e.log_creep_gain_m_per_v = 0.0;
                e.log_creep_time_s = 0.0;
            }
            EffectKind::Drift => {
                e.drift_rate_m_per_s = 0.0;
                e.drift_settling_m = 0.0;
                e.drift_settling_time_constant_s = 0.0;
            }
            EffectKind::Delay => e.delay_s = 0.0,
            EffectKind::Asymmetry => {
                e.even_coefficient_m_per_v2 = 0.0;
                e.even_center_v = 0.0;
            }
            EffectKind::Dynamics => {
                e.mode_frequency_hz = 0.0;
                e.mode_damping = 0.0;
                e.mode_relative_damping = 0.0;
            }
            EffectKind::Coupling => e.coupling = 0.0,
            EffectKind::RateDependent => {
                e.relaxation_gain = Default::default();
                e.relaxation_time_constant_s = Default::default();
                e.relaxation_linear_m_per_v = 0.0;
                e.relaxation_spread_decades = 0.0;
                e.hysteresis_lag_s = 0.0;
                e.hysteresis_rate_gain_s_per_v = 0.0;
            }
        }
        m
    }

    /// The form of an added effect, in words ("Kelvin-Voigt, 2 elements", "exponential settling").
    pub fn form(&self, kind: EffectKind) -> String {
        match kind {
            EffectKind::Creep if self.creep_form == CreepForm::KelvinVoigt => format!(
                "Kelvin-Voigt, {} element{}",
                self.creep_elements,
                if self.creep_elements > 1 { "s" } else { "" }
            ),
            EffectKind::Creep => self.creep_form.name().into(),
            EffectKind::Drift => self.drift_form.name().into(),
            EffectKind::RateDependent if self.with_rate_gain => {
                format!("{} and rate-dependent gain", self.rate_form.name())
            }
            EffectKind::RateDependent => self.rate_form.name().into(),
            EffectKind::Dynamics if self.effects.mode_relative_damping > 0.0 => {
                "stack-driven".into()
            }
            _ => String::new(),
        }
    }

    /// θ, the typical size of each entry (for difference steps) and what each entry is.
    pub fn encode(&self) -> (Vec<f64>, Vec<f64>, Vec<ParamSpec>) {
        let scales = self.scales();
        let mut theta = self.encode_base(scales);
        for &kind in &self.added {
            self.encode_effect(kind, scales, &mut theta);
        }
        (theta.th, theta.typ, theta.spec)
    }

    /// The sizes the typical sizes of θ's entries are taken from.
    fn scales(&self) -> Scales {
        let m = self.map;
        let k = f64::from(m.k1_m_per_v)
            .abs()
            .max(f64::from(m.k2_m_per_h).abs());
        let span = f64::from(self.input_range_v.1 - self.input_range_v.0).max(1e-9);
        Scales {
            k,
            span,
            stroke: (k * span).max(1e-12),
        }
    }

    /// The base model's entries of θ: (β, γ, n, k1, k2, y0).
    fn encode_base(&self, sc: Scales) -> Theta {
        let b = self.bouc_wen;
        let m = self.map;
        let (k, stroke) = (sc.k, sc.stroke);
        let bg = f64::from(b.beta.abs() + b.gamma.abs()).max(1e-12);
        Theta {
            th: vec![
                f64::from(b.beta),
                f64::from(b.gamma),
                f64::from(b.n),
                f64::from(m.k1_m_per_v),
                f64::from(m.k2_m_per_h),
                f64::from(m.offset_m),
            ],
            typ: vec![bg, bg, 1.0, k, k, stroke],
            spec: {
                let mut spec = [
                    Param::Beta,
                    Param::Gamma,
                    Param::Exponent,
                    Param::LinearGain,
                    Param::HysteresisGain,
                    Param::Offset,
                ]
                .map(ParamSpec::free)
                .to_vec();
                // The core's range of the exponent: a step beyond it would be refused, and a fit
                // whose gradient points there would stall on refusals instead of moving along it.
                (spec[2].lo, spec[2].hi) = (BOUC_WEN_EXPONENT_RANGE.0, BOUC_WEN_EXPONENT_RANGE.1);
                // With free offsets each record's offset is re-estimated on its samples, so y0 is
                // held (its column would be zero).
                if self.free_offset {
                    let y0 = f64::from(m.offset_m);
                    (spec[5].lo, spec[5].hi) = (y0, y0);
                }
                spec
            },
        }
    }

    /// The entries of θ of an added effect, appended to `theta`.
    fn encode_effect(&self, kind: EffectKind, sc: Scales, theta: &mut Theta) {
        let e = &self.effects;
        let bd = &self.bounds;
        let ts = f64::from(self.sample_period_s);
        match kind {
            EffectKind::Creep => self.encode_creep(sc, theta),
            EffectKind::Drift => self.encode_drift(sc, theta),
            EffectKind::Delay => theta.push(
                f64::from(e.delay_s),
                10.0 * ts,
                ParamSpec::within(Param::Delay, kind, 0.0, bd.delay_max_s),
            ),
            EffectKind::Asymmetry => theta.push(
                f64::from(e.even_coefficient_m_per_v2),
                0.01 * f64::from(self.map.k1_m_per_v).abs() / sc.span,
                ParamSpec::within(
                    Param::EvenCoefficient,
                    kind,
                    -bd.even_max_m_per_v2,
                    bd.even_max_m_per_v2,
                ),
            ),
            EffectKind::Dynamics => {
                theta.push(
                    f64::from(e.mode_frequency_hz).max(1e-9).ln(),
                    10.0,
                    ParamSpec::log_within(
                        Param::ModeFrequency,
                        kind,
                        bd.mode_frequency_hz.0,
                        bd.mode_frequency_hz.1,
                    ),
                );
                theta.push(
                    f64::from(e.mode_damping).max(1e-9).ln(),
                    10.0,
                    ParamSpec::log_within(
                        Param::ModeDamping,
                        kind,
                        bd.mode_damping.0,
                        bd.mode_damping.1,
                    ),
                );
            }
            EffectKind::Coupling => theta.push(
                f64::from(e.coupling),
                0.1,
                ParamSpec::within(Param::Coupling, kind, -bd.coupling_max, bd.coupling_max),
            ),
            EffectKind::RateDependent => {
                if self.rate_form.has_input_lag() {
                    theta.push(
                        f64::from(e.hysteresis_lag_s).max(1e-9).ln(),
                        10.0,
                        ParamSpec::log_within(
                            Param::HysteresisLag,
                            kind,
                            bd.relaxation_tau_s.0,
                            bd.relaxation_tau_s.1,
                        ),
                    );
                }
                if self.rate_form.has_rate_gain() || self.with_rate_gain {
                    theta.push(
                        f64::from(e.hysteresis_rate_gain_s_per_v).max(1e-12).ln(),
                        10.0,
                        ParamSpec::log_within(
                            Param::HysteresisRateGain,
                            kind,
                            MIN_RATE_GAIN_S_PER_V,
                            f64::from(piezo_core::static_model::MAX_RATE_GAIN_S_PER_V),
                        ),
                    );
                }
                if !self.rate_form.has_relaxation() {
                    return;
                }
                const G: [Param; 2] = [Param::RelaxationGain, Param::RelaxationGain1];
                const T: [Param; 2] = [
                    Param::RelaxationTimeConstant,
                    Param::RelaxationTimeConstant1,
                ];
                for i in 0..self.rate_form.relaxation_elements() {
                    theta.push(
                        f64::from(e.relaxation_gain[i]).max(1e-9).ln(),
                        10.0,
                        ParamSpec::log_within(
                            G[i],
                            kind,
                            bd.relaxation_gain.0,
                            bd.relaxation_gain.1,
                        ),
                    );
                    theta.push(
                        f64::from(e.relaxation_time_constant_s[i]).max(1e-9).ln(),
                        10.0,
                        ParamSpec::log_within(
                            T[i],
                            kind,
                            bd.relaxation_tau_s.0,
                            bd.relaxation_tau_s.1,
                        ),
                    );
                }
                if self.rate_form.has_spread() {
                    theta.push(
                        f64::from(e.relaxation_spread_decades),
                        1.0,
                        ParamSpec::within(
                            Param::RelaxationSpread,
                            kind,
                            0.0,
                            f64::from(piezo_core::effects::MAX_RELAXATION_SPREAD_DECADES),
                        ),
                    );
                }
            }
        }
    }

    /// The creep's entries of θ: g_log, or (g_i, ln τ_i) per Kelvin–Voigt element.
    fn encode_creep(&self, sc: Scales, theta: &mut Theta) {
        let kind = EffectKind::Creep;
        let e = &self.effects;
        let bd = &self.bounds;
        if self.creep_form == CreepForm::Logarithmic {
            theta.push(
                f64::from(e.log_creep_gain_m_per_v),
                0.01 * sc.k,
                ParamSpec::within(
                    Param::LogCreepGain,
                    kind,
                    -bd.log_creep_max_gain_m_per_v,
                    bd.log_creep_max_gain_m_per_v,
                ),
            );
            return;
        }
        const G: [Param; 2] = Param::CREEP_GAINS;
        const T: [Param; 2] = Param::CREEP_TIME_CONSTANTS;
        for i in 0..self.creep_elements {
            theta.push(
                f64::from(e.creep_gain_m_per_v[i]),
                0.01 * sc.k,
                ParamSpec::within(
                    G[i],
                    kind,
                    -bd.creep_max_gain_m_per_v,
                    bd.creep_max_gain_m_per_v,
                ),
            );
            theta.push(
                f64::from(e.creep_time_constant_s[i]).max(1e-9).ln(),
                10.0,
                ParamSpec::log_within(T[i], kind, bd.creep_tau_s.0, bd.creep_tau_s.1),
            );
        }
    }

    /// The drift's entries of θ: (A, ln τ) when settling, r when linear.
    fn encode_drift(&self, sc: Scales, theta: &mut Theta) {
        let kind = EffectKind::Drift;
        let e = &self.effects;
        let bd = &self.bounds;
        if self.drift_form == DriftForm::Settling {
            theta.push(
                f64::from(e.drift_settling_m),
                0.01 * sc.stroke,
                ParamSpec::within(Param::DriftSettling, kind, -bd.drift_max_m, bd.drift_max_m),
            );
            theta.push(
                f64::from(e.drift_settling_time_constant_s).max(1e-9).ln(),
                10.0,
                ParamSpec::log_within(
                    Param::DriftSettlingTimeConstant,
                    kind,
                    bd.settling_tau_s.0,
                    bd.settling_tau_s.1,
                ),
            );
        } else {
            let max = bd.drift_max_m / bd.record_s;
            theta.push(
                f64::from(e.drift_rate_m_per_s),
                0.01 * sc.stroke,
                ParamSpec::within(Param::DriftRate, kind, -max, max),
            );
        }
    }

    /// The model of θ (inverse of [`Self::encode`]); every entry is held inside its range.
    pub fn decode(&self, th: &[f64]) -> Self {
        let (_, _, spec) = self.encode();
        let th: Vec<f64> = th
            .iter()
            .zip(&spec)
            .map(|(t, s)| t.clamp(s.lo, s.hi))
            .collect();
        let mut m = self.clone();
        for (s, &t) in spec.iter().zip(&th) {
            s.param.set(&mut m, s.value(t));
        }
        if m.added.contains(&EffectKind::RateDependent) && m.rate_form.has_relaxation() {
            // Only the hysteretic part relaxes (k_r = k1), or the whole output (k_r = 0).
            m.effects.relaxation_linear_m_per_v = if m.rate_form.relaxes_whole_output() {
                0.0
            } else {
                m.map.k1_m_per_v
            };
        }
        m
    }

    /// The fitted parameters of `kind`: (parameter, value, plausible range, ran to a bound).
    pub fn effect_parameters(&self, kind: EffectKind) -> Vec<(Param, f64, (f64, f64), bool)> {
        let (th, _, spec) = self.encode();
        spec.iter()
            .zip(&th)
            .filter(|(s, _)| s.effect == Some(kind))
            .map(|(s, &t)| {
                let width = s.hi - s.lo;
                let at = width.is_finite()
                    && (t - s.lo <= AT_BOUND_SHARE * width || s.hi - t <= AT_BOUND_SHARE * width);
                // Creep keeps the output moving the way a command change moved it: a gain of the
                // other sign than the static gain dy/du, or 0 (fitted freely, so that the fit is
                // not stuck at 0), is not creep.
                let at = at || (s.param.is_creep_gain() && t * self.bounds.gain_sign <= 0.0);
                (s.param, s.value(t), s.range(), at)
            })
            .collect()
    }
}

/// θ as [`AxisModel::encode`] builds it: the entries, their typical sizes and what each is.
struct Theta {
    /// The entries.
    th: Vec<f64>,
    /// Their typical sizes.
    typ: Vec<f64>,
    /// What each is.
    spec: Vec<ParamSpec>,
}

impl Theta {
    fn push(&mut self, th: f64, typ: f64, spec: ParamSpec) {
        self.th.push(th);
        self.typ.push(typ);
        self.spec.push(spec);
    }
}

/// The sizes of an axis model that θ's typical sizes are scaled by.
#[derive(Clone, Copy)]
struct Scales {
    /// The larger of |k1| and |k2|.
    k: f64,
    /// The input range's span \[V\].
    span: f64,
    /// k times the span \[m\].
    stroke: f64,
}

/// The data one axis is fitted on.
pub struct FitData<'a> {
    /// Input (f32, as the core sees it).
    pub u: &'a [f32],
    /// Measured \[m\].
    pub y: &'a [f64],
    /// The other axis's z, for coupling.
    pub other_z: Option<&'a [f64]>,
    /// First scored sample.
    pub from: usize,
    /// A block of scored samples left out of the fit (held out).
    pub held_out: Option<Block>,
    /// Each record (segment of the model) has its own constant sensor offset, re-estimated on the
    /// samples scored in it.
    pub free_offset: bool,
    /// `Some(loop rate)` \[Hz\]: only sets that [`super::stage::compensator_check`] accepts at
    /// this loop rate are feasible (`--invertible`); the others score an infinite SSE.
    pub invertible_at_hz: Option<f32>,
}

impl FitData<'_> {
    /// Whether sample `k` is fitted.
    pub fn fitted(&self, k: usize) -> bool {
        k >= self.from && !self.held_out.is_some_and(|b| b.contains(k))
    }

    /// Number of fitted samples.
    pub fn fitted_count(&self) -> usize {
        let n = self.u.len().saturating_sub(self.from);
        n - self.held_out.map_or(0, |b| {
            (self.from..self.u.len()).filter(|&k| b.contains(k)).count()
        })
    }
}

/// A held-out block of the cross-validation: the samples `start..end`, or with `interleave` =
/// (segment length L, blocks K, this block i) those of them in the segments j = ⌊(k − start)/L⌋
/// with j mod K = i (every K-th segment, so that each block sees the whole record).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Block {
    /// First sample.
    pub start: usize,
    /// One past the last sample.
    pub end: usize,
    /// Interleaved segments (L, K, i); `None`: contiguous.
    pub interleave: Option<(usize, usize, usize)>,
}

impl Block {
    /// The contiguous block `start..end`.
    pub fn contiguous(start: usize, end: usize) -> Self {
        Self {
            start,
            end,
            interleave: None,
        }
    }

    /// Whether sample `k` is in the block.
    pub fn contains(&self, k: usize) -> bool {
        k >= self.start
            && k < self.end
            && self
                .interleave
                .is_none_or(|(len, blocks, i)| ((k - self.start) / len.max(1)) % blocks.max(1) == i)
    }

    /// Number of samples in the block.
    pub fn count(&self) -> usize {
        (self.start..self.end).filter(|&k| self.contains(k)).count()
    }
}

/// SSE of a model on the fitted samples (∞ when the core refuses it).
pub fn sse(model: &AxisModel, d: &FitData) -> f64 {
    sse_where(model, d, |k| d.fitted(k))
}

/// SSE of a model over the samples `k` with `keep(k)` (∞ when the core refuses it); with free
/// offsets each record's offset is re-estimated on its kept samples.
pub fn sse_where(model: &AxisModel, d: &FitData, keep: impl Fn(usize) -> bool) -> f64 {
    let mut out = vec![0.0; d.u.len()];
    let ok = model.simulate_into(d.u, d.other_z, |k, y, _, _| out[k] = y);
    if d.free_offset {
        add_record_offsets(&mut out, d.y, &model.segments, &keep);
    }
    let acc: f64 = (0..out.len())
        .filter(|&k| keep(k))
        .map(|k| (d.y[k] - out[k]).powi(2))
        .sum();
    if ok.is_ok() && acc.is_finite() {
        acc
    } else {
        f64::INFINITY
    }
}

/// Adds to each record's prediction its mean error over the samples with `keep(k)` (its own
/// constant offset, least squares); a record without kept samples is left alone.
pub fn add_record_offsets(
    predicted: &mut [f64],
    y: &[f64],
    segments: &[usize],
    keep: impl Fn(usize) -> bool,
) {
    let n = predicted.len();
    for (i, &a) in segments.iter().enumerate() {
        let b = segments.get(i + 1).copied().unwrap_or(n).min(n);
        let (mut sum, mut count) = (0.0, 0usize);
        for k in a..b {
            if keep(k) {
                sum += y[k] - predicted[k];
                count += 1;
            }
        }
        if count > 0 {
            let offset = sum / count as f64;
            predicted[a..b].iter_mut().for_each(|p| *p += offset);
        }
    }
}

/// Forward-difference steps of the parameters: relative to |θ_i| or to a tenth of its typical size,
/// times `step_scale`, pointing inwards at an upper bound (so that no column is zero).
fn difference_steps(th: &[f64], typ: &[f64], spec: &[ParamSpec], step_scale: f64) -> Vec<f64> {
    (0..th.len())
        .map(|i| {
            let rel = step_scale * if typ[i] >= 10.0 { 1e-3 } else { 1e-4 };
            let h = (rel * th[i].abs()).max(rel * typ[i] * 0.1).max(1e-300);
            if th[i] + h > spec[i].hi {
                -h
            } else {
                h
            }
        })
        .collect()
}

/// JᵀJ and Jᵀr of the Jacobian columns `cols` and the residual `r`.
fn normal_equations(cols: &[Vec<f64>], r: &[f64]) -> (Vec<Vec<f64>>, Vec<f64>) {
    let p = cols.len();
    let mut jtj = vec![vec![0.0; p]; p];
    let mut jtr = vec![0.0; p];
    for i in 0..p {
        for j in i..p {
            let s: f64 = cols[i].iter().zip(&cols[j]).map(|(a, b)| a * b).sum();
            jtj[i][j] = s;
            jtj[j][i] = s;
        }
        jtr[i] = cols[i].iter().zip(r).map(|(a, b)| a * b).sum();
    }
    (jtj, jtr)
}

/// A prediction over the fitted samples and the hysteresis path it was simulated on (`None` when it
/// ran on a path given to it).
struct Prediction {
    /// Predicted output at the fitted samples \[m\].
    y: Vec<f64>,
    /// The hysteresis path it computed.
    path: Option<HysteresisPath>,
}

/// What one refit evaluates: the model it decodes θ into and the fitted samples of the data.
struct RefitProblem<'a> {
    /// The model θ is decoded into.
    model: &'a AxisModel,
    /// The data.
    d: &'a FitData<'a>,
    /// The fitted samples' indices.
    idx: Vec<usize>,
}

impl RefitProblem<'_> {
    /// The prediction at θ over the fitted samples, and the hysteresis path it ran on. A path
    /// given that fits θ's Bouc-Wen set is reused (a column of a map or effect parameter): the
    /// same numbers as a whole simulation, without integrating the operator again.
    fn predict(&self, th: &[f64], on: Option<&HysteresisPath>) -> Option<Prediction> {
        let (m, d) = (self.model.decode(th), self.d);
        if let Some(rate) = d.invertible_at_hz {
            super::stage::compensator_check(&m, rate).ok()?;
        }
        let path = match on {
            Some(p) if p.fits(&m) => None,
            _ => Some(m.hysteresis_path(d.u).ok()?),
        };
        let mut out = vec![0.0; d.u.len()];
        let run = path.as_ref().or(on)?;
        m.simulate_on_path(run, d.u, d.other_z, |k, y, _, _| out[k] = y)
            .ok()?;
        if d.free_offset {
            add_record_offsets(&mut out, d.y, &m.segments, |k| d.fitted(k));
        }
        let y: Vec<f64> = self.idx.iter().map(|&k| out[k]).collect();
        y.iter()
            .all(|v| v.is_finite())
            .then_some(Prediction { y, path })
    }

    /// The SSE of a prediction, summed in the order of [`sse`] (so the same number).
    fn sse_of(&self, prediction: &Option<Prediction>) -> f64 {
        let Some(Prediction { y: out, .. }) = prediction else {
            return f64::INFINITY;
        };
        let mut acc = 0.0;
        for (&k, y) in self.idx.iter().zip(out) {
            acc += (self.d.y[k] - y).powi(2);
        }
        if acc.is_finite() {
            acc
        } else {
            f64::INFINITY
        }
    }

    /// The forward-difference Jacobian columns at θ (base prediction `base`), in parallel; a
    /// column whose step the core refuses is zero.
    fn jacobian(&self, th: &[f64], steps: &[f64], base: &Prediction) -> Vec<Vec<f64>> {
        (0..th.len())
            .into_par_iter()
            .map(|i| {
                let mut t = th.to_vec();
                t[i] += steps[i];
                let Some(moved) = self.predict(&t, base.path.as_ref()) else {
                    return vec![0.0; base.y.len()];
                };
                moved
                    .y
                    .iter()
                    .zip(&base.y)
                    .map(|(a, b)| (a - b) / steps[i])
                    .collect()
            })
            .collect()
    }
}

/// Relative central-difference step of [`linearise`] (ten times the fit's forward steps: the
/// f32 simulation's rounding stays far below the difference, and a central difference's error is
/// of second order in the step).
const UNCERTAINTY_STEP_SCALE: f64 = 10.0;

/// The name of a parameter in the report's `params` ([`super::params_report`]).
pub fn report_name(param: Param) -> String {
    let group = match param {
        Param::Beta | Param::Gamma | Param::Exponent => "bouc_wen",
        Param::LinearGain | Param::HysteresisGain | Param::Offset => "static_map",
        _ => "effects",
    };
    format!("{group}.{}", param.name())
}

/// The Jacobian of `model`'s prediction over the fitted samples of `d` with respect to each of
/// its fitted parameters in the parameter's own unit, and the residual y − ŷ there: what
/// [`crate::uncertainty::estimate`] turns into standard errors. Central differences of θ (a
/// one-sided one at a bound of its range), each column one core simulation; an entry of θ that
/// is the logarithm of its parameter p has its column divided by p (∂ŷ/∂p = (∂ŷ/∂ln p)/p, the
/// delta method). Held entries (with free offsets, y0) are not parameters; with free offsets
/// each record's own offset, re-estimated in every prediction, is a nuisance parameter (its
/// indicator column, orthogonal to the others, counts it in N − p).
pub fn linearise(model: &AxisModel, d: &FitData) -> crate::Result<Linearised> {
    let (th, typ, spec) = model.encode();
    let th: Vec<f64> = th
        .iter()
        .zip(&spec)
        .map(|(t, s)| t.clamp(s.lo, s.hi))
        .collect();
    let problem = RefitProblem {
        model,
        d,
        idx: (0..d.u.len()).filter(|&k| d.fitted(k)).collect(),
    };
    let base = problem
        .predict(&th, None)
        .ok_or_else(|| crate::Error::Refused("the core refuses the fitted set".into()))?;
    let steps = difference_steps(&th, &typ, &spec, UNCERTAINTY_STEP_SCALE);
    let free: Vec<usize> = (0..th.len()).filter(|&i| spec[i].lo < spec[i].hi).collect();
    let columns: Vec<crate::Result<Vec<f64>>> = free
        .par_iter()
        .map(|&i| {
            let h = steps[i].abs();
            let at = |delta: f64| -> Option<(f64, Vec<f64>)> {
                let t = th[i] + delta;
                if !(spec[i].lo..=spec[i].hi).contains(&t) {
                    return None;
                }
                let mut moved = th.clone();
                moved[i] = t;
                problem.predict(&moved, None).map(|p| (delta, p.y))
            };
            let column: Vec<f64> = match (at(h), at(-h)) {
                (Some((a, ya)), Some((b, yb))) => {
                    ya.iter().zip(&yb).map(|(p, m)| (p - m) / (a - b)).collect()
                }
                (Some((a, y)), None) | (None, Some((a, y))) => {
                    y.iter().zip(&base.y).map(|(p, q)| (p - q) / a).collect()
                }
                (None, None) => {
                    return Err(crate::Error::Refused(format!(
                        "the core refuses the set with {} moved by its difference step",
                        spec[i].param
                    )))
                }
            };
            let per_unit = if spec[i].log {
                1.0 / spec[i].value(th[i])
            } else {
                1.0
            };
            Ok(column.into_iter().map(|c| c * per_unit).collect())
        })
        .collect();
    let mut columns = columns.into_iter().collect::<Result<Vec<_>, _>>()?;
    let parameters = free
        .iter()
        .map(|&i| Parameter::new(report_name(spec[i].param), spec[i].value(th[i])))
        .collect();
    if d.free_offset && model.segments.len() > 1 {
        let n = d.u.len();
        for (r, &a) in model.segments.iter().enumerate() {
            let b = model.segments.get(r + 1).copied().unwrap_or(n);
            columns.push(
                problem
                    .idx
                    .iter()
                    .map(|&k| if k >= a && k < b { 1.0 } else { 0.0 })
                    .collect(),
            );
        }
    }
    let residual = problem
        .idx
        .iter()
        .zip(&base.y)
        .map(|(&k, p)| d.y[k] - p)
        .collect();
    Ok(Linearised {
        parameters,
        columns,
        residual,
    })
}

/// Bisection steps of [`last_accepted_on_the_way`] (the share of the way to 2⁻¹⁰).
const WAY_BISECTIONS: usize = 10;

/// The last set `accepts` takes on the straight line in θ from `from` (which it accepts) to `to`
/// (a model with the same parameters): θ(t) = θ_from + t·(θ_to − θ_from) at the largest t in
/// [0, 1] found by bisection (to 2⁻¹⁰), assuming that the accepted sets along the line are the
/// ones before a single crossing. A start for a fit held to the accepted sets that is as close as
/// it can be to the unconstrained fit. `from` when the parameters differ.
pub fn last_accepted_on_the_way(
    from: &AxisModel,
    to: &AxisModel,
    accepts: impl Fn(&AxisModel) -> bool,
) -> AxisModel {
    let (a, _, spec_a) = from.encode();
    let (b, _, spec_b) = to.encode();
    if spec_a != spec_b {
        return from.clone();
    }
    let at = |t: f64| -> AxisModel {
        let th: Vec<f64> = a.iter().zip(&b).map(|(x, y)| x + t * (y - x)).collect();
        to.decode(&th)
    };
    let end = at(1.0);
    if accepts(&end) {
        return end;
    }
    let (mut lo, mut hi) = (0.0, 1.0);
    for _ in 0..WAY_BISECTIONS {
        let mid = 0.5 * (lo + hi);
        if accepts(&at(mid)) {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    if lo == 0.0 {
        from.clone()
    } else {
        at(lo)
    }
}

/// Levenberg–Marquardt ([`Marquardt`]) on every parameter of `model` over the fitted samples of
/// `d`: forward-difference Jacobian, λ from 1e-3 (÷3 on success down to 1e-9, ×4 on failure or a
/// singular system), twelve tries per iteration, the Marquardt scale floored at 1e-30; an
/// iteration without an accepted step takes the Jacobian again with tenfold difference steps (at
/// most twice), and the fit stops after two accepted steps in a row that gain less than 1e-6.
/// Returns the refitted model, its SSE and the number of model evaluations.
pub fn refit(model: &AxisModel, d: &FitData, max_iterations: usize) -> (AxisModel, f64, u64) {
    let (th0, typ, spec) = model.encode();
    let th: Vec<f64> = th0
        .iter()
        .zip(&spec)
        .map(|(t, s)| t.clamp(s.lo, s.hi))
        .collect();
    let mut lm = RefitSteps {
        problem: RefitProblem {
            model,
            d,
            idx: (0..d.u.len()).filter(|&k| d.fitted(k)).collect(),
        },
        typ,
        bounds: spec.iter().map(|s| (s.lo, s.hi)).collect(),
        spec,
        step_scale: 1.0,
        current: None,
        base: None,
        tried: None,
        evals: 1,
    };
    lm.current = lm.problem.predict(&th, None);
    let best = lm.problem.sse_of(&lm.current);
    if !best.is_finite() || lm.problem.idx.is_empty() {
        return (model.decode(&th), best, lm.evals);
    }
    let settings = Marquardt {
        lambda: 1e-3,
        lambda_min: 1e-9,
        scale_floor: 1e-30,
        tries: 12,
        singular_factor: 4.0,
        iterations: max_iterations,
        min_gain: 0.0,
        small_steps: Some((1e-6, 2)),
        predicted_gain: None,
        hold_at_bounds: false,
    };
    let bounds = lm.bounds.clone();
    let (th, best) = settings.run(&mut lm, th, best, &bounds);
    (model.decode(&th), best, lm.evals)
}

/// [`refit`]'s least-squares problem: the forward-difference Jacobian of [`RefitProblem`] and the
/// predictions it keeps between iterations.
struct RefitSteps<'a> {
    /// The model and the fitted samples.
    problem: RefitProblem<'a>,
    /// The typical size of each θ entry.
    typ: Vec<f64>,
    /// What each θ entry is.
    spec: Vec<ParamSpec>,
    /// Each θ entry's range.
    bounds: Vec<(f64, f64)>,
    /// Difference steps grow tenfold (at most twice) when no step of an iteration improves: with
    /// the f32 simulation, too small a step gives a Jacobian of rounding noise.
    step_scale: f64,
    /// The prediction at the current θ, kept from the accepted trial for the next Jacobian.
    current: Option<Prediction>,
    /// The prediction the last Jacobian was taken at.
    base: Option<Prediction>,
    /// The last tried step's prediction.
    tried: Option<Prediction>,
    /// Model evaluations so far.
    evals: u64,
}

impl LeastSquares for RefitSteps<'_> {
    fn sse(&mut self, theta: &[f64], _abandon_above: f64) -> f64 {
        self.tried = self.problem.predict(theta, None);
        self.evals += 1;
        self.problem.sse_of(&self.tried)
    }

    /// JᵀJ and Jᵀ(ŷ − y) of the forward-difference Jacobian of the prediction ŷ (the residual
    /// r = ŷ − y, so the gradient is −Jᵀ(y − ŷ)).
    fn normal_equations(&mut self, th: &[f64]) -> Option<NormalEquations> {
        let base = self
            .current
            .take()
            .or_else(|| self.problem.predict(th, None))?;
        let steps = difference_steps(th, &self.typ, &self.spec, self.step_scale);
        let cols = self.problem.jacobian(th, &steps, &base);
        self.evals += th.len() as u64;
        let y = self.problem.d.y;
        let r: Vec<f64> = self
            .problem
            .idx
            .iter()
            .zip(&base.y)
            .map(|(&k, b)| y[k] - b)
            .collect();
        let (jtj, jtr) = normal_equations(&cols, &r);
        self.base = Some(base);
        Some(NormalEquations {
            jtj,
            gradient: jtr.iter().map(|v| -v).collect(),
        })
    }

    fn accepted(&mut self, _theta: &[f64], _sse: f64, _gain: f64, _lambda: f64) {
        self.current = self.tried.take();
    }

    fn retry(&mut self) -> bool {
        if self.step_scale >= 100.0 {
            return false;
        }
        self.step_scale *= 10.0;
        self.current = self.base.take();
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A model with every effect of the chain that a path leaves untouched: creep, drift, delay,
    /// even term, mode and coupling.
    fn model_with_effects() -> AxisModel {
        let mut model = crate::close_loop::report::tests::model();
        model.effects = EffectParams {
            even_coefficient_m_per_v2: 1e-11,
            even_center_v: 5.0,
            mode_frequency_hz: 120.0,
            mode_damping: 0.3,
            delay_s: 2.5e-3,
            drift_rate_m_per_s: 1e-8,
            coupling: 0.05,
            drift_settling_m: 2e-8,
            drift_settling_time_constant_s: 0.5,
            ..model.effects
        };
        model.added = Vec::new();
        model.drift_form = DriftForm::Settling;
        model
    }

    /// Every entry of θ reaches its own field of the model: each one moved inside its range (or
    /// by a tenth of its typical size when free), decoded and encoded again, comes back (to the
    /// core's f32), whichever forms the effects take; together the forms cover every [`Param`].
    #[test]
    fn every_theta_entry_reaches_its_own_field() {
        let every_effect = EffectKind::ALL.to_vec();
        let mut kelvin_voigt = model_with_effects();
        kelvin_voigt.added = every_effect.clone();
        kelvin_voigt.creep_elements = 2;
        kelvin_voigt.effects.creep_gain_m_per_v[1] = 1e-9;
        kelvin_voigt.effects.creep_time_constant_s[1] = 0.05;
        kelvin_voigt.rate_form = RateForm::SpreadRelaxation;
        kelvin_voigt.effects.relaxation_gain[0] = 0.5;
        kelvin_voigt.effects.relaxation_time_constant_s[0] = 0.01;
        kelvin_voigt.effects.relaxation_spread_decades = 1.0;
        let mut logarithmic = model_with_effects();
        logarithmic.added = every_effect;
        logarithmic.creep_form = CreepForm::Logarithmic;
        logarithmic.effects.log_creep_gain_m_per_v = 1e-9;
        logarithmic.drift_form = DriftForm::Linear;
        logarithmic.effects.hysteresis_lag_s = 0.01;
        logarithmic.rate_form = RateForm::LagAndTwoRelaxations;
        logarithmic.effects.relaxation_gain = [0.2, 0.1];
        logarithmic.effects.relaxation_time_constant_s = [0.002, 0.02];
        let mut rate_gain = model_with_effects();
        rate_gain.added = EffectKind::ALL.to_vec();
        rate_gain.rate_form = RateForm::RateGain;
        rate_gain.effects.hysteresis_rate_gain_s_per_v = 1e-5;
        let mut seen = std::collections::HashSet::new();
        for model in [kelvin_voigt, logarithmic, rate_gain] {
            let (th, typ, spec) = model.encode();
            let moved: Vec<f64> = th
                .iter()
                .zip(&typ)
                .zip(&spec)
                .map(|((&t, &size), s)| {
                    if (s.hi - s.lo).is_finite() {
                        s.lo + 0.37 * (s.hi - s.lo)
                    } else {
                        t + 0.1 * size
                    }
                })
                .collect();
            let (back, _, _) = model.decode(&moved).encode();
            assert_eq!(back.len(), moved.len());
            for ((s, &m), &b) in spec.iter().zip(&moved).zip(&back) {
                let tol = 1e-6 * if s.log { m.abs().max(1.0) } else { m.abs() };
                assert!(
                    (m - b).abs() <= tol,
                    "{}: set {m:e}, read back {b:e}",
                    s.param
                );
                seen.insert(s.param);
            }
        }
        assert_eq!(seen.len(), Param::ALL.len(), "{seen:?}");
    }

    fn record() -> (Vec<f32>, Vec<f64>) {
        let u: Vec<f32> = (0..2000)
            .map(|k| {
                let t = k as f64 * 1e-3;
                (10.0 - 9.0 * (6.0 * t).cos() + 0.5 * (70.0 * t).sin()) as f32
            })
            .collect();
        let other_z = (0..2000).map(|k| 1e-6 * (k as f64 * 3e-3).sin()).collect();
        (u, other_z)
    }

    fn outputs(
        run: impl FnOnce(&mut dyn FnMut(usize, f64, f64, f64)) -> crate::Result<()>,
    ) -> Vec<(f64, f64, f64)> {
        let mut out = Vec::new();
        run(&mut |_, y, h, z| out.push((y, h, z))).unwrap();
        out
    }

    #[test]
    fn a_shared_hysteresis_path_gives_the_whole_simulation_bit_for_bit() {
        let (u, other_z) = record();
        let base = model_with_effects();
        let path = base.hysteresis_path(&u).unwrap();
        // Another map and other effects on the same Bouc-Wen set: the path fits and is reused.
        let mut other = base.clone();
        other.map.k1_m_per_v *= 1.01;
        other.map.offset_m = -3e-7;
        other.effects.creep_gain_m_per_v[0] = 5e-9;
        other.effects.delay_s = 1.2e-3;
        other.effects.coupling = -0.02;
        assert!(path.fits(&other));
        for m in [&base, &other] {
            let whole = outputs(|v| m.simulate_into(&u, Some(&other_z), v));
            let on_path = outputs(|v| m.simulate_on_path(&path, &u, Some(&other_z), v));
            assert_eq!(whole.len(), u.len());
            assert!(
                whole == on_path,
                "simulation on the path differs from the whole one"
            );
        }
        // The path's h is the operator's (not a constant): the test compares something that moves.
        assert!(path.h.iter().any(|&h| h.abs() > 1.0));
        // Another Bouc-Wen set does not fit the path and is simulated whole.
        let mut steeper = base.clone();
        steeper.bouc_wen.n = 1.6;
        assert!(!path.fits(&steeper));
        let whole = outputs(|v| steeper.simulate_into(&u, Some(&other_z), v));
        let on_path = outputs(|v| steeper.simulate_on_path(&path, &u, Some(&other_z), v));
        assert!(whole == on_path);
        assert!(whole != outputs(|v| base.simulate_into(&u, Some(&other_z), v)));
    }

    #[test]
    fn a_map_the_core_refuses_is_refused_on_a_path_too() {
        let (u, _) = record();
        let base = model_with_effects();
        let path = base.hysteresis_path(&u).unwrap();
        let mut refused = base.clone();
        refused.map.k1_m_per_v = 0.0;
        refused.map.k2_m_per_h = 0.0;
        let err = refused
            .simulate_on_path(&path, &u, None, |_, _, _, _| {})
            .unwrap_err()
            .to_string();
        assert!(err.contains("static map refused"), "{err}");
        let mut bad_effect = base.clone();
        bad_effect.effects.mode_damping = -1.0;
        let err = bad_effect
            .simulate_on_path(&path, &u, None, |_, _, _, _| {})
            .unwrap_err()
            .to_string();
        assert!(err.contains("effects refused"), "{err}");
    }
}
