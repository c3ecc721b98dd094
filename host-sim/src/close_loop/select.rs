//! Whether an effect is added: it must hold on data the fit did not see, and be that effect.
//!
//! **Out of sample.** The scored record is cut into [`FOLDS`] contiguous blocks in time. For each
//! block b, the model with and without the effect is refitted on the other blocks (Levenberg–Marquardt
//! from the full fit) and predicts block b with its state carried through: the whole record is
//! simulated, only block b is scored. The test is scale-free: a block's error depends on where it
//! lies (start-up, large or small loops), so the absolute gains MSE_b(without) − MSE_b(with) spread
//! with the blocks' own error even when every block improves by 99 %. Per block the log ratio
//! ℓ_b = ln(MSE_b(with) / MSE_b(without)) is taken (−4.6 for a 99 % gain, 0 for none); the effect holds
//! when (1) their mean is below zero by more than [`T_CRITICAL`] standard errors,
//! −ℓ̄ > t·s_ℓ/√K (s_ℓ the standard deviation of the ℓ_b, K = 4 blocks: a one-sided t-test of "no
//! gain" at 90 %, Student's t with 3 degrees of freedom), (2) no block is predicted more than
//! [`MAX_BLOCK_LOSS`] worse (ℓ_b ≤ ln 1.1), and (3) the pooled held-out MSE falls by at least
//! [`MIN_RELATIVE_GAIN`] (5 %). On effect-free data the ℓ_b of a spurious effect scatter around 0
//! (or sit within a few per cent of it), which (1) or (3) refuse; a genuine effect lowers every
//! block's error by a similar factor, which passes however different the blocks' errors are. On a
//! `--validate` record (another run) the model fitted on the whole record must also lower the RMS
//! with one constant offset re-estimated on that record; of the effects that hold, the one that
//! predicts that record best is added (the parent module's `best_trial`).
//!
//! **Two blocks.** With two blocks (two records left out in turn) the t-test has one degree of
//! freedom and refuses every effect whose gain differs between them, which is what an effect that
//! grows with the rate does between records at two rates (a mode far above both: its response
//! grows as the square of the input frequency). There a pooled held-out MSE at least
//! [`TWO_BLOCK_GAIN`] lower, no block more than [`MAX_BLOCK_LOSS`] worse, stands in for (1): a
//! gain of a third on data the refit did not see is not a spurious effect's.
//!
//! **Non-stationary record.** When the contiguous blocks see different inputs (amplitudes or
//! rates more than [`STATIONARY_RATIO`] apart: a rising-amplitude sweep), a block would be
//! predicted outside the range the others were fitted on; the blocks then interleave segments of
//! [`PERIODS_PER_SEGMENT`] input periods, so that each sees the whole range
//! ([`single_record_folds`]); a record too short for that keeps its contiguous blocks and the
//! report says the test extrapolates.
//!
//! **Several records.** With several records of one stage the blocks are the records themselves
//! (leave one record out: each record predicted by the model refitted on the others, with its own
//! offset re-estimated when offsets are free), and the t-test takes K − 1 degrees of freedom for K
//! records ([`t_critical`]). Records of very unequal length are the exception
//! ([`unequal_records`]): when the shortest holds less than [`MIN_RECORD_SHARE`] of the longest's
//! scored samples, the fold that holds out the longest would refit on little more than the short
//! one, so the blocks interleave within the records instead ([`interleaved_folds`]), and the
//! report's held-out method says why.
//!
//! **An effect one record shows.** Leaving a record out asks every record to show the effect by a
//! similar factor. An effect that only one record excites (a mode a step record rings and sines far
//! below it barely move) cannot pass that test: refitted without that record, the effect is not
//! identified, and the records that do not excite it gain nothing. When the records refuse an
//! effect only for that consistency, (2) and (3) holding (no record predicted more than
//! [`MAX_BLOCK_LOSS`] worse, the pooled held-out MSE [`MIN_RELATIVE_GAIN`] lower), it is judged
//! again on [`FOLDS`] blocks that each take every [`FOLDS`]-th segment of
//! [`PERIODS_PER_SEGMENT`] input periods from every record ([`interleaved_folds`]), so that each
//! refit sees part of every record, by rules (1)–(3); the report gives both. Once such an effect
//! is in the model, every later effect (and the held-out RMS the report gives) is judged on those
//! blocks alone: a record left out would take the first effect's identification with it, and the
//! later effect would be judged against a model that lost it.
//!
//! **Plausibility.** Every effect parameter is fitted inside the range that makes it that effect
//! ([`super::full::EffectBounds`]): creep time constants from three sample periods to a third of
//! the record and gains of the sign of the stage's static gain dy/du (the output keeps moving the
//! way a command change moved it), a
//! settling drift slower than two input periods, a delay up to 5 % of the input period (at most
//! 64 samples), a mode between ten times the dominant input frequency and 85 % of Nyquist. A fit
//! that ends within [`super::full::AT_BOUND_SHARE`] of such a bound is not that effect and is
//! refused.
//!
//! **Noise floor.** Nothing is added once the residual RMS is within [`NOISE_FLOOR_FACTOR`] of the
//! sensor noise estimated from the data ([`super::diagnose::noise_estimate`]) and the residual is
//! white (Ljung–Box Q over 20 lags below its 95 % limit): a residual near the noise in RMS whose
//! samples are still correlated holds structure, and the candidates are tried on it (they must
//! still hold out of sample).

use super::diagnose::{EffectKind, ResidualFigures, ResidualReport};
use super::full::{refit, sse_where, AxisModel, Block, FitData};
use super::param::Param;
use rayon::prelude::*;

/// Number of blocks of the cross-validation.
pub const FOLDS: usize = 4;
/// The mean log ratio of the held-out MSEs must lie this many standard errors below zero: the
/// one-sided 90 % point of Student's t with FOLDS − 1 = 3 degrees of freedom.
pub const T_CRITICAL: f64 = 1.638;
/// No held-out block may be predicted worse than this factor of its MSE without the effect.
pub const MAX_BLOCK_LOSS: f64 = 1.1;
/// The pooled held-out MSE must fall by at least this share.
pub const MIN_RELATIVE_GAIN: f64 = 0.05;
/// With two blocks: the pooled held-out MSE must fall by at least this share in place of the
/// t-test (module doc).
pub const TWO_BLOCK_GAIN: f64 = 1.0 / 3.0;
/// Nothing is added when the residual RMS is below this factor times the noise estimate.
pub const NOISE_FLOOR_FACTOR: f64 = 1.2;
/// Levenberg–Marquardt iterations of a fold's refit (it starts from the full fit).
pub const FOLD_ITERATIONS: usize = 8;

/// The one-sided 90 % point of Student's t with `blocks` − 1 degrees of freedom ([`T_CRITICAL`]
/// for [`FOLDS`] blocks; ∞ for fewer than two blocks: no test).
pub fn t_critical(blocks: usize) -> f64 {
    match blocks {
        0 | 1 => f64::INFINITY,
        2 => 3.078,
        3 => 1.886,
        4 => T_CRITICAL,
        5 => 1.533,
        6 => 1.476,
        _ => 1.44,
    }
}

/// The blocks of leave-one-record-out: each record's scored samples (from `from` on).
pub fn record_folds(from: usize, segments: &[usize], n: usize) -> Vec<Block> {
    segments
        .iter()
        .enumerate()
        .map(|(i, &a)| (a.max(from), segments.get(i + 1).copied().unwrap_or(n)))
        .filter(|(a, b)| b > a)
        .map(|(a, b)| Block::contiguous(a, b))
        .collect()
}

/// The shortest record's share of the longest below which leaving one record out is not the
/// test: refitted without the longest record, the model would stand on too little of the data
/// ([`unequal_records`]).
pub const MIN_RECORD_SHARE: f64 = 0.25;

/// With several records, the shortest one's index and scored samples and the longest one's
/// scored samples, when the shortest holds less than [`MIN_RECORD_SHARE`] of the longest: the
/// records are then too unequal for leave-one-record-out (the fold that holds out the longest
/// refits on the short one alone, and the fold that holds out the short one judges on a few
/// samples), and the blocks interleave within the records instead. `None` otherwise.
pub fn unequal_records(from: usize, segments: &[usize], n: usize) -> Option<(usize, usize, usize)> {
    let folds = record_folds(from, segments, n);
    if folds.len() < 2 {
        return None;
    }
    let lengths: Vec<usize> = folds.iter().map(|b| b.end - b.start).collect();
    let longest = lengths.iter().copied().max()?;
    let (index, shortest) = lengths
        .iter()
        .copied()
        .enumerate()
        .min_by_key(|&(_, len)| len)?;
    ((shortest as f64) < MIN_RECORD_SHARE * longest as f64).then_some((index, shortest, longest))
}

/// [`FOLDS`] blocks over the scored samples `from..n` that interleave: segments of
/// [`PERIODS_PER_SEGMENT`] periods of the dominant input frequency `f_dom_hz` (at least 10
/// samples) go to the blocks in turn, so that each block and each refit sees the whole of a
/// non-stationary record ([`single_record_folds`]), or, over several records end to end, part of
/// every record (module doc, "An effect one record shows"). `None` when the samples hold fewer
/// than two segments per block or the frequency is not positive.
pub fn interleaved_folds(from: usize, n: usize, ts: f64, f_dom_hz: f64) -> Option<Vec<Block>> {
    if !(f_dom_hz > 0.0 && f_dom_hz.is_finite() && ts > 0.0) {
        return None;
    }
    let seg = ((PERIODS_PER_SEGMENT / f_dom_hz / ts).round() as usize).max(10);
    if n.saturating_sub(from) / seg < 2 * FOLDS {
        return None;
    }
    Some(
        (0..FOLDS)
            .map(|i| Block {
                start: from,
                end: n,
                interleave: Some((seg, FOLDS, i)),
            })
            .collect(),
    )
}

/// The blocks of the cross-validation: `FOLDS` contiguous ranges of samples over `from..n`.
pub fn folds(from: usize, n: usize) -> Vec<Block> {
    let len = n.saturating_sub(from);
    (0..FOLDS)
        .map(|b| (from + b * len / FOLDS, from + (b + 1) * len / FOLDS))
        .filter(|(a, b)| b > a)
        .map(|(a, b)| Block::contiguous(a, b))
        .collect()
}

/// Largest ratio between the contiguous blocks' input amplitudes (half the range of u) or input
/// rates (largest |du/dt|) for a record to count as stationary.
pub const STATIONARY_RATIO: f64 = 1.25;

/// Input periods per interleaved segment (the shortest that holds a whole loop).
pub const PERIODS_PER_SEGMENT: f64 = 1.0;

/// The blocks of one record's cross-validation, and in words how they were chosen. Contiguous
/// blocks ([`folds`]) when every block sees the same input: their amplitudes (half the range of
/// u) and rates (largest |du/dt|) within [`STATIONARY_RATIO`] of each other. Otherwise (a
/// rising-amplitude sweep, a record whose rate changes) a contiguous block would be predicted
/// outside the range the others were fitted on, so the blocks interleave: segments of
/// [`PERIODS_PER_SEGMENT`] periods of the dominant input frequency `f_dom_hz` (at least 10
/// samples) go to the blocks in turn, each block sees the whole range of amplitude and rate. If
/// there are too few segments for that (fewer than 2·FOLDS), the contiguous blocks are kept and
/// the words say the test extrapolates.
pub fn single_record_folds(u: &[f64], from: usize, ts: f64, f_dom_hz: f64) -> (Vec<Block>, String) {
    let contiguous = folds(from, u.len());
    let figures: Vec<(f64, f64)> = contiguous
        .iter()
        .map(|b| {
            let s = &u[b.start..b.end];
            let (lo, hi) = s
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| {
                    (l.min(v), h.max(v))
                });
            let rate = s
                .windows(2)
                .map(|w| ((w[1] - w[0]) / ts).abs())
                .fold(0.0, f64::max);
            (0.5 * (hi - lo), rate)
        })
        .collect();
    let spread = |f: &dyn Fn(&(f64, f64)) -> f64| {
        let (lo, hi) = figures
            .iter()
            .map(f)
            .fold((f64::INFINITY, 0.0f64), |(l, h), v| (l.min(v), h.max(v)));
        hi / lo.max(1e-300)
    };
    let (amp, rate) = (spread(&|f| f.0), spread(&|f| f.1));
    let contiguous_words = "blocked cross-validation over time: each block predicted by the model \
                            refitted on the others";
    if amp <= STATIONARY_RATIO && rate <= STATIONARY_RATIO {
        return (contiguous, contiguous_words.into());
    }
    let why = format!(
        "the input is not stationary: the contiguous blocks' amplitudes differ {amp:.2}x and \
         their rates {rate:.2}x"
    );
    let Some(blocks) = interleaved_folds(from, u.len(), ts, f_dom_hz) else {
        return (
            contiguous,
            format!(
                "{contiguous_words}; {why} and the record is too short to interleave \
                 segments of {PERIODS_PER_SEGMENT} x the input period, so each block is predicted outside the \
                 range the others were fitted on: a gain on the later blocks is an extrapolation"
            ),
        );
    };
    let seg = blocks[0].interleave.map_or(0, |(len, _, _)| len);
    (
        blocks,
        format!(
            "interleaved cross-validation: {why}, so segments of {seg} samples ({PERIODS_PER_SEGMENT} \
             x the period of the dominant input frequency, {f_dom_hz:.1} Hz) go to the {FOLDS} \
             blocks in turn and each block sees the whole range; each block predicted by the model \
             refitted on the others, state carried through"
        ),
    )
}

/// The held-out SSE of `model` per block: refitted on the other blocks, the whole record simulated,
/// the block scored.
pub fn held_out_sse(model: &AxisModel, data: &FitData, blocks: &[Block]) -> Vec<f64> {
    blocks
        .par_iter()
        .map(|&block| {
            let d = FitData {
                u: data.u,
                y: data.y,
                other_z: data.other_z,
                from: data.from,
                held_out: Some(block),
                free_offset: data.free_offset,
                invertible_at_hz: data.invertible_at_hz,
            };
            let (fitted, _, _) = refit(model, &d, FOLD_ITERATIONS);
            sse_where(&fitted, &d, |k| block.contains(k))
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
    /// Per block, ln(MSE with / MSE without).
    pub log_ratios: Vec<f64>,
    /// Mean of the log ratios.
    pub mean_log_ratio: f64,
    /// Standard deviation of the log ratios.
    pub spread: f64,
    /// Share by which the pooled held-out MSE falls.
    pub relative_gain: f64,
}

impl OutOfSample {
    /// From the per-block SSEs without and with the effect, blocks `blocks` (sample indices),
    /// times `t_s`.
    pub fn new(without: &[f64], with: &[f64], blocks: &[Block], t_s: &[f64]) -> Self {
        let n: Vec<f64> = blocks.iter().map(|b| b.count() as f64).collect();
        let mse_without: Vec<f64> = without.iter().zip(&n).map(|(s, n)| s / n).collect();
        let mse_with: Vec<f64> = with.iter().zip(&n).map(|(s, n)| s / n).collect();
        let log_ratios: Vec<f64> = mse_without
            .iter()
            .zip(&mse_with)
            .map(|(a, b)| {
                if b.is_finite() {
                    (b.max(1e-300) / a.max(1e-300)).ln()
                } else {
                    f64::INFINITY
                }
            })
            .collect();
        let k = log_ratios.len().max(1) as f64;
        let mean_log_ratio = log_ratios.iter().sum::<f64>() / k;
        let spread = if log_ratios.len() > 1 && mean_log_ratio.is_finite() {
            (log_ratios
                .iter()
                .map(|l| (l - mean_log_ratio).powi(2))
                .sum::<f64>()
                / (k - 1.0))
                .sqrt()
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
                .map(|b| (t_s[b.start.min(last)], t_s[(b.end - 1).min(last)]))
                .collect(),
            mse_without,
            mse_with,
            log_ratios,
            mean_log_ratio,
            spread,
            relative_gain,
        }
    }

    /// The standard error of the mean log ratio.
    pub fn standard_error(&self) -> f64 {
        self.spread / (self.log_ratios.len().max(1) as f64).sqrt()
    }

    /// The t statistic of "no gain": −mean / standard error (∞ when every block gains alike).
    pub fn t_statistic(&self) -> f64 {
        let se = self.standard_error();
        if se > 0.0 {
            -self.mean_log_ratio / se
        } else if self.mean_log_ratio < 0.0 {
            f64::INFINITY
        } else {
            0.0
        }
    }

    /// Whether the effect holds out of sample (module doc).
    pub fn holds(&self) -> bool {
        let consistent = self.t_statistic() > t_critical(self.log_ratios.len())
            || (self.log_ratios.len() == 2 && self.relative_gain >= TWO_BLOCK_GAIN);
        consistent && self.none_worse_and_pooled_gain()
    }

    /// Whether rules (2) and (3) hold (no block more than [`MAX_BLOCK_LOSS`] worse, the pooled
    /// held-out MSE [`MIN_RELATIVE_GAIN`] lower), whatever the consistency test (1) says.
    pub fn none_worse_and_pooled_gain(&self) -> bool {
        self.mean_log_ratio.is_finite()
            && self.log_ratios.iter().all(|&l| l <= MAX_BLOCK_LOSS.ln())
            && self.relative_gain >= MIN_RELATIVE_GAIN
    }

    /// For the report: the blocks' figures, the t statistic, the rule and whether it holds.
    pub fn report(&self) -> OutOfSampleReport<'_> {
        OutOfSampleReport {
            method: format!("blocked cross-validation, {} blocks (over time in one record, interleaved segments when it is not stationary; one record each with several, or, judged within the records, interleaved segments of every record): refit on the other blocks, simulate the whole record, score the held-out block", self.log_ratios.len()),
            blocks_s: &self.blocks_s,
            mse_without_m2: &self.mse_without,
            mse_with_m2: &self.mse_with,
            log_ratios: &self.log_ratios,
            mean_log_ratio: self.mean_log_ratio,
            spread: self.spread,
            t_statistic: self.t_statistic(),
            relative_gain: self.relative_gain,
            rule: format!(
                "mean of ln(MSE with / MSE without) over the blocks more than {} standard errors below 0 (one-sided t-test, 90 %; with two blocks: or the pooled held-out MSE >= {:.0} % lower), no block more than {MAX_BLOCK_LOSS} x worse, pooled held-out MSE >= {:.0} % lower",
                t_critical(self.log_ratios.len()),
                100.0 * TWO_BLOCK_GAIN,
                100.0 * MIN_RELATIVE_GAIN
            ),
            holds: self.holds(),
        }
    }
}

/// The cross-validated gain in a report ([`OutOfSample::report`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct OutOfSampleReport<'a> {
    /// How the blocks were held out, in words.
    pub method: String,
    /// The held-out blocks \[s\].
    pub blocks_s: &'a [(f64, f64)],
    /// Held-out MSE per block without the effect \[m²\].
    pub mse_without_m2: &'a [f64],
    /// Held-out MSE per block with it \[m²\].
    pub mse_with_m2: &'a [f64],
    /// Per block, ln(MSE with / MSE without).
    pub log_ratios: &'a [f64],
    /// Mean of the log ratios.
    pub mean_log_ratio: f64,
    /// Standard deviation of the log ratios.
    pub spread: f64,
    /// [`OutOfSample::t_statistic`].
    pub t_statistic: f64,
    /// Share by which the pooled held-out MSE falls.
    pub relative_gain: f64,
    /// The rule, in words.
    pub rule: String,
    /// [`OutOfSample::holds`].
    pub holds: bool,
}

/// One parameter against the range that makes the effect that effect.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Check {
    /// The parameter (its name in reports: the core's field).
    pub parameter: Param,
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

    /// For the report: the checks and whether every one passed.
    pub fn report(&self) -> PlausibilityReport<'_> {
        PlausibilityReport {
            plausible: self.plausible(),
            checks: &self.checks,
        }
    }
}

/// The plausibility of a fitted effect in a report ([`Plausibility::report`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct PlausibilityReport<'a> {
    /// [`Plausibility::plausible`].
    pub plausible: bool,
    /// One check per parameter.
    pub checks: &'a [Check],
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
    /// The share by which the effect lowers the zeroed MSE on the other run,
    /// 1 − (RMS with / RMS without)².
    pub fn gain(&self) -> f64 {
        1.0 - (self.rms_zeroed_with / self.rms_zeroed_without).powi(2)
    }

    /// Whether the effect lowers the zeroed RMS on the other run.
    pub fn holds(&self) -> bool {
        self.rms_zeroed_with < self.rms_zeroed_without
    }

    /// For the report: both RMS and whether it holds.
    pub fn report(&self) -> RunGainReport {
        RunGainReport {
            rms_zeroed_without: self.rms_zeroed_without,
            rms_zeroed_with: self.rms_zeroed_with,
            holds: self.holds(),
        }
    }
}

/// The gain on another run in a report ([`RunGain::report`]).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct RunGainReport {
    /// Without the effect \[m\].
    pub rms_zeroed_without: f64,
    /// With it \[m\].
    pub rms_zeroed_with: f64,
    /// [`RunGain::holds`].
    pub holds: bool,
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
    /// With `--invertible`: the fit with the effect is a set the compensator refuses, and held to
    /// the sets it accepts it gains nothing (the trial's `invertibility` says by how much).
    NotInvertible,
}

impl Refusal {
    /// In words.
    pub fn words(self) -> &'static str {
        match self {
            Self::FitFailed => "the fit failed (every set refused by piezo-core)",
            Self::Implausible => "a parameter ran to the bound of its plausible range: not this effect",
            Self::NoInSampleGain => "it does not lower the residual even in sample",
            Self::NotOutOfSample => "the gain does not hold on the held-out blocks (one-sided t-test on the blocks' log MSE ratios, or with two blocks a pooled gain of a third; no block worse; pooled gain; with several records, where the records refuse it only for the t-test, also on blocks within the records)",
            Self::WorseOnAnotherRun => "it makes the prediction of the --validate record worse",
            Self::NotInvertible => "not invertible: with this effect the fit is a set the compensator refuses, and held to the sets it accepts it gains nothing (--invertible)",
        }
    }
}

/// What became of a candidate (serialised as [`Decision::name`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(into = "&'static str")]
pub enum Decision {
    /// Added to the model.
    Added,
    /// It holds, but another candidate held better in this step (a larger held-out gain, or with
    /// `--validate` a better prediction of that record).
    HoldsNotBest,
    /// Not added.
    Refused(Refusal),
}

impl Decision {
    /// In words.
    pub fn words(self) -> String {
        match self {
            Self::Added => "added".into(),
            Self::HoldsNotBest => {
                "holds, but another candidate holds better this step (a larger held-out gain, or \
                 with --validate a better prediction of that record)"
                    .into()
            }
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
            Self::Refused(Refusal::NotInvertible) => "refused-not-invertible",
        }
    }
}

impl From<Decision> for &'static str {
    fn from(decision: Decision) -> Self {
        decision.name()
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
            Self::NoCandidates => "no candidate left to try: each effect is in the model already, \
                 or its screening explains less of the residual than the share a candidate needs \
                 (the report lists each with its share)"
                .into(),
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
    /// Whether the residual is at the noise floor: its RMS within [`NOISE_FLOOR_FACTOR`] of the
    /// noise estimate and white (a residual near the noise in RMS whose samples are still
    /// correlated holds structure a candidate may explain).
    pub fn reached(&self) -> bool {
        self.residual.rms <= NOISE_FLOOR_FACTOR * self.noise_m
            && self.residual.ljung_box_q20 < super::diagnose::LJUNG_BOX_LIMIT_20
    }

    /// For the report: the residual's figures, the noise estimate, the floor and whether it is
    /// reached.
    pub fn report(&self) -> FloorReport {
        FloorReport {
            residual: self.residual.report(),
            noise_estimate_m: self.noise_m,
            noise_floor_m: NOISE_FLOOR_FACTOR * self.noise_m,
            at_noise_floor: self.reached(),
        }
    }
}

/// The residual and the noise floor in a report ([`Floor::report`]).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct FloorReport {
    /// The residual's figures.
    pub residual: ResidualReport,
    /// The sensor noise estimate of the axis \[m\].
    pub noise_estimate_m: f64,
    /// [`NOISE_FLOOR_FACTOR`] times the noise estimate \[m\].
    pub noise_floor_m: f64,
    /// [`Floor::reached`].
    pub at_noise_floor: bool,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::json_keys as keys;
    use std::collections::BTreeSet;

    /// Leave-one-record-out stands while the shortest record holds a quarter of the longest's
    /// scored samples; below that the shortest is named with both lengths; one record never is.
    #[test]
    fn records_under_a_quarter_of_the_longest_are_unequal() {
        // Records of 4000, 1000 and 3000 samples: 1000 is exactly a quarter.
        assert_eq!(unequal_records(0, &[0, 4000, 5000], 8000), None);
        // 999 is below it; the scored samples start at `from`, inside the first record.
        assert_eq!(
            unequal_records(0, &[0, 4000, 4999], 8000),
            Some((1, 999, 4000))
        );
        assert_eq!(
            unequal_records(3500, &[0, 4000, 5000], 8000),
            Some((0, 500, 3000))
        );
        assert_eq!(unequal_records(0, &[0], 8000), None);
    }

    /// The noise floor, the out-of-sample gain, the plausibility and another run's gain serialise
    /// with the keys of the report; a decision as its short name.
    #[test]
    fn the_evidence_serialises_with_the_keys_of_the_report() {
        let floor = Floor {
            residual: ResidualFigures {
                rms: 2.5e-9,
                noise: 2e-9,
                ljung_box_q20: 10.0,
            },
            noise_m: 2e-9,
        };
        let json = crate::to_json(&floor.report()).unwrap();
        assert_eq!(
            keys(&json),
            BTreeSet::from([
                "residual",
                "noise_estimate_m",
                "noise_floor_m",
                "at_noise_floor",
            ])
        );
        assert_eq!(json["noise_floor_m"], NOISE_FLOOR_FACTOR * 2e-9);
        assert_eq!(json["at_noise_floor"], floor.reached());
        assert_eq!(
            json["residual"],
            crate::to_json(&floor.residual.report()).unwrap()
        );

        let gain = OutOfSample {
            blocks_s: vec![(0.0, 0.5), (0.5, 1.0), (1.0, 1.5)],
            mse_without: vec![4e-14, 4e-14, 4e-14],
            mse_with: vec![1e-14, 2e-14, 3e-14],
            log_ratios: vec![(0.25f64).ln(), (0.5f64).ln(), (0.75f64).ln()],
            mean_log_ratio: -0.7,
            spread: 0.5,
            relative_gain: 0.5,
        };
        let json = crate::to_json(&gain.report()).unwrap();
        assert_eq!(
            keys(&json),
            BTreeSet::from([
                "method",
                "blocks_s",
                "mse_without_m2",
                "mse_with_m2",
                "log_ratios",
                "mean_log_ratio",
                "spread",
                "t_statistic",
                "relative_gain",
                "rule",
                "holds",
            ])
        );
        assert_eq!(json["blocks_s"][2], serde_json::json!([1.0, 1.5]));
        assert_eq!(
            json["mse_with_m2"],
            serde_json::json!([1e-14, 2e-14, 3e-14])
        );
        assert_eq!(json["t_statistic"], gain.t_statistic());
        assert_eq!(json["holds"], gain.holds());
        assert!(json["method"].as_str().unwrap().contains("3 blocks"));

        let plausibility = Plausibility {
            checks: vec![Check {
                parameter: Param::Delay,
                value: 6.4e-3,
                range: (0.0, 6.4e-3),
                at_bound: true,
            }],
        };
        let json = crate::to_json(&plausibility.report()).unwrap();
        assert_eq!(
            json,
            serde_json::json!({
                "plausible": false,
                "checks": [{
                    "parameter": Param::Delay.name(),
                    "value": 6.4e-3,
                    "range": [0.0, 6.4e-3],
                    "at_bound": true,
                }],
            })
        );

        let run = RunGain {
            rms_zeroed_without: 1e-7,
            rms_zeroed_with: 2e-7,
        };
        assert_eq!(
            crate::to_json(&run.report()).unwrap(),
            serde_json::json!({
                "rms_zeroed_without": 1e-7,
                "rms_zeroed_with": 2e-7,
                "holds": false,
            })
        );
        for (decision, name) in [
            (Decision::Added, "added"),
            (Decision::HoldsNotBest, "holds-not-best"),
            (
                Decision::Refused(Refusal::NotOutOfSample),
                "refused-not-out-of-sample",
            ),
        ] {
            assert_eq!(crate::to_json(&decision).unwrap(), name);
        }
    }

    /// 2 s of a 10 Hz sine at 1 kHz, amplitude `amp(t)`.
    fn sine(amp: impl Fn(f64) -> f64) -> Vec<f64> {
        (0..2000)
            .map(|k| {
                let t = k as f64 * 1e-3;
                amp(t) * (2.0 * std::f64::consts::PI * 10.0 * t).sin()
            })
            .collect()
    }

    #[test]
    fn a_stationary_record_keeps_contiguous_blocks() {
        let u = sine(|_| 5.0);
        let (blocks, words) = single_record_folds(&u, 0, 1e-3, 10.0);
        assert_eq!(blocks, folds(0, u.len()));
        assert!(words.starts_with("blocked"), "{words}");
    }

    #[test]
    fn a_rising_amplitude_record_interleaves_blocks_that_see_its_whole_range() {
        let u = sine(|t| 1.0 + 4.0 * t);
        let (blocks, words) = single_record_folds(&u, 0, 1e-3, 10.0);
        assert!(words.starts_with("interleaved"), "{words}");
        assert_eq!(blocks.len(), FOLDS);
        // Every sample in exactly one block; every block reaches 80 % of the largest amplitude
        // (its last segment is one of the last FOLDS).
        for k in 0..u.len() {
            assert_eq!(blocks.iter().filter(|b| b.contains(k)).count(), 1);
        }
        let top = u.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for b in &blocks {
            let peak = (b.start..b.end)
                .filter(|&k| b.contains(k))
                .fold(0.0f64, |m, k| m.max(u[k].abs()));
            assert!(peak >= 0.8 * top, "block {b:?}: peak {peak} of {top}");
        }
        // Too short to interleave: contiguous, and the words say why.
        let (short, words) = single_record_folds(&u[..300], 0, 1e-3, 10.0);
        assert_eq!(short, folds(0, 300));
        assert!(words.contains("extrapolation"), "{words}");
    }

    #[test]
    fn the_blocks_within_records_each_take_part_of_every_record() {
        // Three records end to end (samples 0, 1000 and 2500 on), 1 ms samples, 10 Hz: segments
        // of 100 samples go to the four blocks in turn.
        let (records, n) = ([0usize, 1000, 2500], 3000);
        let blocks = interleaved_folds(0, n, 1e-3, 10.0).unwrap();
        assert_eq!(blocks.len(), FOLDS);
        for k in 0..n {
            assert_eq!(blocks.iter().filter(|b| b.contains(k)).count(), 1, "{k}");
        }
        for b in &blocks {
            for (i, &first) in records.iter().enumerate() {
                let last = records.get(i + 1).copied().unwrap_or(n);
                assert!(
                    (first..last).any(|k| b.contains(k)),
                    "block {b:?} has no sample of the record at {first}"
                );
            }
        }
        // Fewer than two segments per block, or no input frequency: none.
        assert_eq!(interleaved_folds(0, 700, 1e-3, 10.0), None);
        assert_eq!(interleaved_folds(0, n, 1e-3, 0.0), None);
    }
}
