//! Whether an effect is added: it must hold on data the fit did not see, and be that effect.
//!
//! **Out of sample.** The scored record is cut into [`FOLDS`] contiguous blocks in time. For each
//! block b, the model with and without the effect is refitted on the other blocks (Levenberg–Marquardt
//! from the full fit) and predicts block b with its state carried through: the whole record is
//! simulated, only block b is scored. With g_b = MSE_b(without) − MSE_b(with), the effect holds when
//! the mean gain ḡ exceeds its spread across the folds, ḡ > [`SPREAD_FACTOR`]·s_g/√K (s_g the
//! standard deviation of the g_b, K the number of folds), and the pooled held-out MSE falls by at
//! least [`MIN_RELATIVE_GAIN`]. On a `--validate` record (another run) the model fitted on the whole
//! record must also lower the RMS with one constant offset re-estimated on that record.
//!
//! **Plausibility.** Every effect parameter is fitted inside the range that makes it that effect
//! ([`super::full::EffectBounds`]): creep time constants from three sample periods to a third of
//! the record and gains > 0 (the output keeps moving in the direction of a command change), a
//! settling drift slower than two input periods, a delay up to 5 % of the input period (at most
//! 64 samples), a mode between ten times the dominant input frequency and 85 % of Nyquist. A fit
//! that ends within [`super::full::AT_BOUND_SHARE`] of such a bound is not that effect and is
//! refused.
//!
//! **Noise floor.** Nothing is added once the residual RMS is within [`NOISE_FLOOR_FACTOR`] of the
//! sensor noise estimated from the data ([`super::diagnose::noise_estimate`]).

use super::diagnose::{EffectKind, ResidualFigures};
use super::full::{refit, sse_where, AxisModel, FitData};
use rayon::prelude::*;
use serde_json::{json, Value};

/// Number of blocks of the cross-validation.
pub const FOLDS: usize = 4;
/// The mean held-out gain must exceed this many standard errors of the fold gains: the one-sided
/// 90 % point of Student's t with FOLDS − 1 = 3 degrees of freedom (a one-sided t-test of "no gain").
pub const SPREAD_FACTOR: f64 = 1.638;
/// The pooled held-out MSE must fall by at least this share.
pub const MIN_RELATIVE_GAIN: f64 = 0.01;
/// Nothing is added when the residual RMS is below this factor times the noise estimate.
pub const NOISE_FLOOR_FACTOR: f64 = 1.2;
/// Levenberg–Marquardt iterations of a fold's refit (it starts from the full fit).
pub const FOLD_ITERATIONS: usize = 8;

/// The blocks of the cross-validation: `FOLDS` contiguous ranges of samples over `from..n`.
pub fn folds(from: usize, n: usize) -> Vec<(usize, usize)> {
    let len = n.saturating_sub(from);
    (0..FOLDS)
        .map(|b| (from + b * len / FOLDS, from + (b + 1) * len / FOLDS))
        .filter(|(a, b)| b > a)
        .collect()
}

/// The held-out SSE of `model` per block: refitted on the other blocks, the whole record simulated,
/// the block scored.
pub fn held_out_sse(model: &AxisModel, data: &FitData, blocks: &[(usize, usize)]) -> Vec<f64> {
    blocks
        .par_iter()
        .map(|&(a, b)| {
            let d = FitData {
                u: data.u,
                y: data.y,
                other_z: data.other_z,
                from: data.from,
                held_out: Some((a, b)),
            };
            let (fitted, _, _) = refit(model, &d, FOLD_ITERATIONS);
            sse_where(&fitted, &d, |k| k >= a && k < b)
        })
        .collect()
}

/// The cross-validated gain of an effect.
#[derive(Debug, Clone, PartialEq)]
pub struct OutOfSample {
    /// The held-out blocks \[s\].
    pub blocks_s: Vec<(f64, f64)>,
    /// Held-out MSE per block without the effect \[m²\].
    pub mse_without: Vec<f64>,
    /// Held-out MSE per block with it \[m²\].
    pub mse_with: Vec<f64>,
    /// Mean of the per-block gains \[m²\].
    pub mean_gain: f64,
    /// Standard deviation of the per-block gains \[m²\].
    pub spread: f64,
    /// Share by which the pooled held-out MSE falls.
    pub relative_gain: f64,
}

impl OutOfSample {
    /// From the per-block SSEs without and with the effect, blocks `blocks` (sample indices),
    /// times `t_s`.
    pub fn new(without: &[f64], with: &[f64], blocks: &[(usize, usize)], t_s: &[f64]) -> Self {
        let n: Vec<f64> = blocks.iter().map(|(a, b)| (b - a) as f64).collect();
        let mse_without: Vec<f64> = without.iter().zip(&n).map(|(s, n)| s / n).collect();
        let mse_with: Vec<f64> = with.iter().zip(&n).map(|(s, n)| s / n).collect();
        let gains: Vec<f64> = mse_without
            .iter()
            .zip(&mse_with)
            .map(|(a, b)| a - b)
            .collect();
        let k = gains.len().max(1) as f64;
        let mean_gain = gains.iter().sum::<f64>() / k;
        let spread = if gains.len() > 1 {
            (gains.iter().map(|g| (g - mean_gain).powi(2)).sum::<f64>() / (k - 1.0)).sqrt()
        } else {
            f64::INFINITY
        };
        let pooled_without: f64 = without.iter().sum();
        let pooled_with: f64 = with.iter().sum();
        let relative_gain = if pooled_without > 0.0 && pooled_with.is_finite() {
            1.0 - pooled_with / pooled_without
        } else {
            f64::NEG_INFINITY
        };
        let last = t_s.len().saturating_sub(1);
        Self {
            blocks_s: blocks
                .iter()
                .map(|&(a, b)| (t_s[a.min(last)], t_s[(b - 1).min(last)]))
                .collect(),
            mse_without,
            mse_with,
            mean_gain,
            spread,
            relative_gain,
        }
    }

    /// The standard error of the mean gain \[m²\].
    pub fn standard_error(&self) -> f64 {
        self.spread / (self.mse_with.len().max(1) as f64).sqrt()
    }

    /// Whether the effect holds out of sample (module doc).
    pub fn holds(&self) -> bool {
        self.mean_gain.is_finite()
            && self.mean_gain > SPREAD_FACTOR * self.standard_error()
            && self.relative_gain >= MIN_RELATIVE_GAIN
    }

    /// JSON for the report.
    pub fn to_json(&self) -> Value {
        json!({
            "method": format!("blocked cross-validation over time, {FOLDS} blocks: refit on the other blocks, simulate the whole record, score the held-out block"),
            "blocks_s": self.blocks_s.iter().map(|(a, b)| [a, b]).collect::<Vec<_>>(),
            "mse_without_m2": self.mse_without,
            "mse_with_m2": self.mse_with,
            "mean_gain_m2": self.mean_gain,
            "spread_m2": self.spread,
            "standard_error_m2": self.standard_error(),
            "relative_gain": self.relative_gain,
            "rule": format!("mean gain > {SPREAD_FACTOR} standard errors across the blocks and the pooled held-out MSE {:.0} % lower", 100.0 * MIN_RELATIVE_GAIN),
            "holds": self.holds(),
        })
    }
}

/// One parameter against the range that makes the effect that effect.
#[derive(Debug, Clone, PartialEq)]
pub struct Check {
    /// Parameter name (the core's field).
    pub parameter: &'static str,
    /// Fitted value (SI).
    pub value: f64,
    /// The plausible range.
    pub range: (f64, f64),
    /// The fit ran to a bound of the range.
    pub at_bound: bool,
}

/// The plausibility of a fitted effect.
#[derive(Debug, Clone, PartialEq)]
pub struct Plausibility {
    /// One check per parameter.
    pub checks: Vec<Check>,
}

impl Plausibility {
    /// The checks of `kind` in `model`.
    pub fn of(model: &AxisModel, kind: EffectKind) -> Self {
        Self {
            checks: model
                .effect_parameters(kind)
                .into_iter()
                .map(|(parameter, value, range, at_bound)| Check {
                    parameter,
                    value,
                    range,
                    at_bound,
                })
                .collect(),
        }
    }

    /// Whether no parameter ran to a bound.
    pub fn plausible(&self) -> bool {
        self.checks.iter().all(|c| !c.at_bound)
    }

    /// In words.
    pub fn words(&self) -> String {
        self.checks
            .iter()
            .map(|c| {
                format!(
                    "{} = {:.4e} in [{:.3e}, {:.3e}]{}",
                    c.parameter,
                    c.value,
                    c.range.0,
                    c.range.1,
                    if c.at_bound {
                        " (ran to its bound: not this effect)"
                    } else {
                        ""
                    }
                )
            })
            .collect::<Vec<_>>()
            .join("; ")
    }

    /// JSON for the report.
    pub fn to_json(&self) -> Value {
        json!({
            "plausible": self.plausible(),
            "checks": self.checks.iter().map(|c| json!({
                "parameter": c.parameter, "value": c.value, "range": [c.range.0, c.range.1],
                "at_bound": c.at_bound,
            })).collect::<Vec<_>>(),
        })
    }
}

/// The RMS on another run with and without the effect (one offset re-estimated on that run).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RunGain {
    /// Without the effect \[m\].
    pub rms_zeroed_without: f64,
    /// With it \[m\].
    pub rms_zeroed_with: f64,
}

impl RunGain {
    /// Whether the effect lowers the zeroed RMS on the other run.
    pub fn holds(&self) -> bool {
        self.rms_zeroed_with < self.rms_zeroed_without
    }
}

/// Why an effect was not added.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Refusal {
    /// The core refused every set, or the fit diverged.
    FitFailed,
    /// A parameter ran to the bound of its plausible range.
    Implausible,
    /// The fit does not lower the in-sample residual.
    NoInSampleGain,
    /// The gain does not hold on the held-out blocks.
    NotOutOfSample,
    /// The effect makes the prediction of the `--validate` record worse.
    WorseOnAnotherRun,
}

impl Refusal {
    /// In words.
    pub fn words(self) -> &'static str {
        match self {
            Self::FitFailed => "the fit failed (every set refused by piezo-core)",
            Self::Implausible => "a parameter ran to the bound of its plausible range: not this effect",
            Self::NoInSampleGain => "it does not lower the residual even in sample",
            Self::NotOutOfSample => "the gain does not hold on the held-out blocks (it does not exceed its spread across the folds)",
            Self::WorseOnAnotherRun => "it makes the prediction of the --validate record worse",
        }
    }
}

/// What became of a candidate.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Decision {
    /// Added to the model.
    Added,
    /// It holds, but another candidate held better in this step.
    HoldsNotBest,
    /// Not added.
    Refused(Refusal),
}

impl Decision {
    /// In words.
    pub fn words(self) -> String {
        match self {
            Self::Added => "added".into(),
            Self::HoldsNotBest => "holds, but another candidate holds better this step".into(),
            Self::Refused(r) => format!("refused: {}", r.words()),
        }
    }

    /// Short name for the report.
    pub fn name(self) -> &'static str {
        match self {
            Self::Added => "added",
            Self::HoldsNotBest => "holds-not-best",
            Self::Refused(Refusal::FitFailed) => "refused-fit-failed",
            Self::Refused(Refusal::Implausible) => "refused-implausible",
            Self::Refused(Refusal::NoInSampleGain) => "refused-no-gain",
            Self::Refused(Refusal::NotOutOfSample) => "refused-not-out-of-sample",
            Self::Refused(Refusal::WorseOnAnotherRun) => "refused-worse-on-another-run",
        }
    }
}

/// Why the search stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stop {
    /// The residual is within [`NOISE_FLOOR_FACTOR`] of the noise estimate.
    NoiseFloor,
    /// No candidate held.
    NothingHolds,
    /// Every effect is in the model or the screening found nothing to try.
    NoCandidates,
}

impl Stop {
    /// In words.
    pub fn words(self) -> String {
        match self {
            Self::NoiseFloor => format!(
                "the residual is within {NOISE_FLOOR_FACTOR} x the sensor noise estimate: nothing left to explain"
            ),
            Self::NothingHolds => "no candidate holds on data the fit did not see and is plausible".into(),
            Self::NoCandidates => "no candidate left to try".into(),
        }
    }
}

/// The residual and the noise floor at the start of a step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Floor {
    /// The residual's figures.
    pub residual: ResidualFigures,
    /// The sensor noise estimate of the axis (from the base model's residual) \[m\].
    pub noise_m: f64,
}

impl Floor {
    /// Whether the residual is at the noise floor.
    pub fn reached(&self) -> bool {
        self.residual.rms <= NOISE_FLOOR_FACTOR * self.noise_m
    }

    /// JSON for the report.
    pub fn to_json(&self) -> Value {
        json!({
            "residual": self.residual.to_json(),
            "noise_estimate_m": self.noise_m,
            "noise_floor_m": NOISE_FLOOR_FACTOR * self.noise_m,
            "at_noise_floor": self.reached(),
        })
    }
}
