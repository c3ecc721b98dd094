//! The decision log of `close-loop` as typed values: per step the residual and the noise floor, the
//! candidates with their screening, in-sample and out-of-sample gains, plausibility and decision, and
//! the step's outcome; each in words ([`Step::words`]) and for the JSON report ([`Step::report`]),
//! built last.
//! In-sample gain: 1 − MSE₁/MSE₀ on the whole scored record; ΔBIC = N·ln(SSE₁/SSE₀) + p·ln N is
//! reported for reference only (with N in the thousands it favours any effect that lowers the
//! residual at all).

use super::choose::{Skipped, SkippedReport};
use super::diagnose::{Candidate, EffectKind};
use super::full::AxisModel;
use super::param::Param;
use super::select::{
    Decision, Floor, FloorReport, OutOfSample, OutOfSampleReport, Plausibility, PlausibilityReport,
    RunGain, RunGainReport, Stop,
};
use std::collections::BTreeMap;

/// One candidate effect, fitted and judged.
#[derive(Debug, Clone)]
pub struct Trial {
    /// The effect.
    pub effect: EffectKind,
    /// Its form in words.
    pub form: String,
    /// Its screening on the residual.
    pub screening: Candidate,
    /// The fitted effect parameters (name, value).
    pub parameters: Vec<(Param, f64)>,
    /// In-sample RMS before \[m\].
    pub rms_before: f64,
    /// In-sample RMS with the effect, whole model refitted \[m\].
    pub rms_after: f64,
    /// ΔBIC of the refit.
    pub delta_bic: f64,
    /// Plausibility of the fitted parameters.
    pub plausibility: Plausibility,
    /// The cross-validated gain (absent when it was refused before).
    pub out_of_sample: Option<OutOfSample>,
    /// The gain on the `--validate` record (when given and reached).
    pub another_run: Option<RunGain>,
    /// With `--invertible`, when the compensator refused the fit: both fits' figures and its
    /// refusal (then the trial is the fit held to the sets it accepts, or refused as not
    /// invertible); `None` otherwise.
    pub invertibility: Option<String>,
    /// The decision.
    pub decision: Decision,
    /// The fitted model with the effect.
    pub model: AxisModel,
    /// Its in-sample SSE \[m²\].
    pub sse: f64,
}

impl Trial {
    /// The in-sample gain: share by which the MSE falls.
    pub fn in_sample_gain(&self) -> f64 {
        1.0 - (self.rms_after / self.rms_before).powi(2)
    }

    /// The name with its form ("creep (logarithmic)").
    pub fn label(&self) -> String {
        if self.form.is_empty() {
            self.effect.name().to_string()
        } else {
            format!("{} ({})", self.effect.name(), self.form)
        }
    }

    /// In words.
    pub fn words(&self) -> String {
        let mut s = format!(
            "{}: screening explains {:.1} % of the residual variance; in sample RMS {:.4e} -> {:.4e} m ({:+.1} % MSE, dBIC {:.0})",
            self.label(),
            100.0 * self.screening.share,
            self.rms_before,
            self.rms_after,
            -100.0 * self.in_sample_gain(),
            self.delta_bic
        );
        if let Some(o) = &self.out_of_sample {
            s.push_str(&format!(
                "; out of sample held-out MSE {:+.1} % (per block {}; t = {:.2})",
                -100.0 * o.relative_gain,
                o.log_ratios
                    .iter()
                    .map(|l| format!("{:+.1} %", 100.0 * l.exp_m1()))
                    .collect::<Vec<_>>()
                    .join(", "),
                o.t_statistic()
            ));
        }
        if let Some(r) = &self.another_run {
            s.push_str(&format!(
                "; another run: zeroed RMS {:.4e} -> {:.4e} m",
                r.rms_zeroed_without, r.rms_zeroed_with
            ));
        }
        s.push_str(&format!(
            "; plausibility: {}; {}",
            self.plausibility.words(),
            self.decision.words()
        ));
        if let Some(reason) = &self.invertibility {
            s.push_str(&format!(" (--invertible: {reason})"));
        }
        s
    }

    /// For the report: the screening, the fitted parameters, the in-sample and out-of-sample
    /// gains, the plausibility, the decision and the words.
    pub fn report(&self) -> TrialReport<'_> {
        TrialReport {
            effect: self.effect,
            form: &self.form,
            screening: ScreeningReport {
                test: self.screening.test,
                share: self.screening.share,
                delta_bic: self.screening.delta_bic,
                figures: self.screening.figures.iter().copied().collect(),
            },
            parameters: self
                .parameters
                .iter()
                .map(|&(p, v)| (p.name(), v))
                .collect(),
            in_sample: InSampleReport {
                rms_before: self.rms_before,
                rms_after: self.rms_after,
                gain: self.in_sample_gain(),
                delta_bic: self.delta_bic,
            },
            out_of_sample: self.out_of_sample.as_ref().map(OutOfSample::report),
            another_run: self.another_run.as_ref().map(RunGain::report),
            plausibility: self.plausibility.report(),
            invertibility: self.invertibility.as_deref(),
            decision: self.decision,
            words: self.words(),
        }
    }
}

/// A candidate in a report ([`Trial::report`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct TrialReport<'a> {
    /// The effect.
    pub effect: EffectKind,
    /// Its form in words.
    pub form: &'a str,
    /// Its screening on the residual.
    pub screening: ScreeningReport,
    /// The fitted effect parameters by name ([`Param::name`]).
    pub parameters: BTreeMap<&'static str, f64>,
    /// The in-sample gain of the refit.
    pub in_sample: InSampleReport,
    /// The cross-validated gain (null when it was refused before).
    pub out_of_sample: Option<OutOfSampleReport<'a>>,
    /// The gain on the `--validate` record (null unless given and reached).
    pub another_run: Option<RunGainReport>,
    /// Plausibility of the fitted parameters.
    pub plausibility: PlausibilityReport<'a>,
    /// With `--invertible`, the compensator's refusal of the free fit (null otherwise).
    pub invertibility: Option<&'a str>,
    /// The decision ([`Decision::name`]).
    pub decision: Decision,
    /// In words ([`Trial::words`]).
    pub words: String,
}

/// A candidate's screening in a report.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ScreeningReport {
    /// What was tested, in words.
    pub test: &'static str,
    /// Share of the residual variance explained.
    pub share: f64,
    /// ΔBIC of adding it.
    pub delta_bic: f64,
    /// The screening's figures by name.
    pub figures: BTreeMap<&'static str, f64>,
}

/// A candidate's in-sample gain in a report.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct InSampleReport {
    /// RMS before \[m\].
    pub rms_before: f64,
    /// RMS with the effect, whole model refitted \[m\].
    pub rms_after: f64,
    /// [`Trial::in_sample_gain`].
    pub gain: f64,
    /// ΔBIC of the refit.
    pub delta_bic: f64,
}

/// What a step did.
#[derive(Debug, Clone, PartialEq)]
pub enum StepOutcome {
    /// An effect was added.
    Added {
        /// The effect.
        effect: EffectKind,
        /// Its form.
        form: String,
        /// In-sample RMS after \[m\].
        rms_after: f64,
    },
    /// An effect added earlier was taken out again: the model refitted without it is within 1 %.
    Removed {
        /// The effect.
        effect: EffectKind,
        /// In-sample RMS without it \[m\].
        rms_without: f64,
    },
    /// The search stopped.
    Stopped(Stop),
    /// With `--invertible`: the search so far ended at a set the compensator refuses (why), and
    /// starts again from the base held to the sets it accepts.
    Restarted {
        /// The compensator's refusal of the set the search ended at.
        refusal: String,
    },
}

/// One step of the search on one axis.
#[derive(Debug, Clone)]
pub struct Step {
    /// Axis name.
    pub axis: String,
    /// Step number (from 1).
    pub number: usize,
    /// In-sample RMS at the start \[m\].
    pub rms_before: f64,
    /// Residual and noise floor at the start.
    pub floor: Floor,
    /// Every screened candidate (effect, form, share, ΔBIC), best first.
    pub screened: Vec<(EffectKind, &'static str, f64, f64)>,
    /// The effects not fitted in this step, and why ([`super::choose`]).
    pub not_tried: Vec<Skipped>,
    /// The candidates fitted and judged.
    pub trials: Vec<Trial>,
    /// The outcome.
    pub outcome: StepOutcome,
}

impl Step {
    /// The effect the step added, if any.
    pub fn added(&self) -> Option<EffectKind> {
        match self.outcome {
            StepOutcome::Added { effect, .. } => Some(effect),
            _ => None,
        }
    }

    /// In words.
    pub fn words(&self) -> String {
        let head = format!(
            "axis {} step {}: residual RMS {:.4e} m, sensor noise estimate {:.4e} m",
            self.axis, self.number, self.rms_before, self.floor.noise_m
        );
        let outcome = match &self.outcome {
            StepOutcome::Added {
                effect,
                form,
                rms_after,
            } => format!(
                "added {}{} (RMS {:.4e} m)",
                effect.name(),
                if form.is_empty() {
                    String::new()
                } else {
                    format!(" ({form})")
                },
                rms_after
            ),
            StepOutcome::Removed {
                effect,
                rms_without,
            } => format!(
                "removed {}: the model refitted without it is within 1 % (RMS {:.4e} m)",
                effect.name(),
                rms_without
            ),
            StepOutcome::Stopped(stop) => format!("stopped: {}", stop.words()),
            StepOutcome::Restarted { refusal } => format!(
                "the search from the base fitted without --invertible's constraint ended at a set \
                 the compensator refuses ({refusal}); it starts again from the base held to the \
                 sets it accepts"
            ),
        };
        let mut s = format!("{head}. {outcome}.");
        for t in &self.trials {
            s.push_str("\n  - ");
            s.push_str(&t.words());
        }
        for n in &self.not_tried {
            s.push_str("\n  - ");
            s.push_str(&n.words());
        }
        s
    }

    /// For the report: the outcome, the noise floor, the screening, the candidates fitted and
    /// those not, and the words.
    pub fn report(&self) -> StepReport<'_> {
        let (effect, form, outcome) = match &self.outcome {
            StepOutcome::Added { effect, form, .. } => {
                (Some(*effect), Some(form.as_str()), "added")
            }
            StepOutcome::Removed { effect, .. } => (Some(*effect), None, "removed"),
            StepOutcome::Stopped(stop) => (
                None,
                None,
                match stop {
                    Stop::NoiseFloor => "stopped-noise-floor",
                    Stop::NothingHolds => "stopped-nothing-holds",
                    Stop::NoCandidates => "stopped-no-candidates",
                },
            ),
            StepOutcome::Restarted { .. } => (None, None, "restarted-from-held-base"),
        };
        let rms = match &self.outcome {
            StepOutcome::Added { rms_after, .. } => *rms_after,
            StepOutcome::Removed { rms_without, .. } => *rms_without,
            StepOutcome::Stopped(_) | StepOutcome::Restarted { .. } => self.rms_before,
        };
        StepReport {
            axis: &self.axis,
            step: self.number,
            outcome,
            effect,
            form,
            removed: matches!(self.outcome, StepOutcome::Removed { .. }),
            rms_before: self.rms_before,
            rms,
            noise: self.floor.report(),
            screening: self
                .screened
                .iter()
                .map(|&(effect, form, share, delta_bic)| ScreenedReport {
                    effect,
                    form,
                    share,
                    delta_bic,
                })
                .collect(),
            candidates: self.trials.iter().map(Trial::report).collect(),
            not_tried: self.not_tried.iter().map(Skipped::report).collect(),
            words: self.words(),
        }
    }
}

/// A step of the search in a report ([`Step::report`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct StepReport<'a> {
    /// Axis name.
    pub axis: &'a str,
    /// Step number (from 1).
    pub step: usize,
    /// `added`, `removed`, `stopped-noise-floor`, `stopped-nothing-holds`,
    /// `stopped-no-candidates` or `restarted-from-held-base`.
    pub outcome: &'static str,
    /// The effect added or removed (null otherwise).
    pub effect: Option<EffectKind>,
    /// The form of the effect added (null otherwise).
    pub form: Option<&'a str>,
    /// Whether an effect was removed.
    pub removed: bool,
    /// In-sample RMS at the start \[m\].
    pub rms_before: f64,
    /// In-sample RMS after the step \[m\].
    pub rms: f64,
    /// Residual and noise floor at the start.
    pub noise: FloorReport,
    /// Every screened candidate, best first.
    pub screening: Vec<ScreenedReport>,
    /// The candidates fitted and judged.
    pub candidates: Vec<TrialReport<'a>>,
    /// The effects not fitted, and why.
    pub not_tried: Vec<SkippedReport>,
    /// In words ([`Step::words`]).
    pub words: String,
}

/// One screened candidate in a report.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct ScreenedReport {
    /// The effect.
    pub effect: EffectKind,
    /// The form screened.
    pub form: &'static str,
    /// Share of the residual variance explained.
    pub share: f64,
    /// ΔBIC of adding it.
    pub delta_bic: f64,
}
