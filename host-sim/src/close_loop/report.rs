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
    /// With several records, the gain on blocks within the records, judged when the records
    /// refused the effect only for the consistency of their gains
    /// ([`super::select`], "An effect one record shows"); `None` otherwise.
    pub within_records: Option<OutOfSample>,
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
        // "; <where> held-out MSE −x % (per block …; t = …)".
        let held_out = |place: &str, o: &OutOfSample| {
            format!(
                "; {place} held-out MSE {:+.1} % (per block {}; t = {:.2})",
                -100.0 * o.relative_gain,
                o.log_ratios
                    .iter()
                    .map(|l| format!("{:+.1} %", 100.0 * l.exp_m1()))
                    .collect::<Vec<_>>()
                    .join(", "),
                o.t_statistic()
            )
        };
        if let Some(o) = &self.out_of_sample {
            s.push_str(&held_out("out of sample", o));
        }
        if let Some(o) = &self.within_records {
            s.push_str(&held_out("within the records", o));
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
            within_records: self.within_records.as_ref().map(OutOfSample::report),
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
    /// The gain on blocks within the records (null unless judged: [`Trial::within_records`]).
    pub within_records: Option<OutOfSampleReport<'a>>,
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

#[cfg(test)]
pub(super) mod tests {
    use super::*;
    use crate::close_loop::choose::NotTried;
    use crate::close_loop::diagnose::{EffectInit, ResidualFigures};
    use crate::close_loop::full::{CreepForm, DriftForm, EffectBounds, RateForm};
    use crate::close_loop::select::{Check, Refusal};
    use crate::json_keys as keys;
    use piezo_core::{BoucWenParams, StaticMap};
    use std::collections::BTreeSet;

    /// A static axis model with one creep element.
    pub(in crate::close_loop) fn model() -> AxisModel {
        AxisModel {
            bouc_wen: BoucWenParams {
                a: 1.0,
                beta: 0.02,
                gamma: 0.015,
                n: 1.5,
            },
            map: StaticMap {
                k1_m_per_v: 1.0e-7,
                k2_m_per_h: -2.0e-8,
                offset_m: 1e-7,
            },
            effects: piezo_core::effects::EffectParams {
                creep_gain_m_per_v: [3e-9, 0.0, 0.0],
                creep_time_constant_s: [0.2, 0.0, 0.0],
                ..Default::default()
            },
            added: vec![EffectKind::Creep],
            creep_form: CreepForm::KelvinVoigt,
            creep_elements: 1,
            rate_form: RateForm::InputLag,
            with_rate_gain: false,
            drift_form: DriftForm::Linear,
            input_range_v: (0.0, 20.0),
            w_range_m: (-1e-5, 1e-5),
            sample_period_s: 1e-3,
            bounds: EffectBounds::for_record(1e-3, 2.0, 1.0, 2e-6, 1e-7, 20.0),
            segments: vec![0],
            free_offset: false,
        }
    }

    /// A creep candidate, added, with its out-of-sample gain and another run.
    pub(in crate::close_loop) fn trial() -> Trial {
        Trial {
            effect: EffectKind::Creep,
            form: "Kelvin-Voigt, 1 element".into(),
            screening: Candidate {
                effect: EffectKind::Creep,
                share: 0.6,
                delta_bic: -700.0,
                init: EffectInit::Creep {
                    gains_m_per_v: [3e-9, 0.0],
                    time_constants_s: [0.2, 0.0],
                },
                test: "first-order lag of u",
                figures: vec![("time_constant_s", 0.2), ("gain_m_per_v", 3e-9)],
            },
            parameters: vec![(Param::CreepGain0, 3e-9), (Param::CreepTimeConstant0, 0.2)],
            rms_before: 2e-7,
            rms_after: 1e-7,
            delta_bic: -650.0,
            plausibility: Plausibility {
                checks: vec![Check {
                    parameter: Param::CreepTimeConstant0,
                    value: 0.2,
                    range: (3e-4, 1.0),
                    at_bound: false,
                }],
            },
            out_of_sample: Some(OutOfSample {
                blocks_s: vec![(0.0, 0.5), (0.5, 1.0)],
                mse_without: vec![4e-14, 4e-14],
                mse_with: vec![1e-14, 2e-14],
                log_ratios: vec![(0.25f64).ln(), (0.5f64).ln()],
                mean_log_ratio: -1.0,
                spread: 0.5,
                relative_gain: 0.625,
            }),
            within_records: None,
            another_run: Some(RunGain {
                rms_zeroed_without: 3e-7,
                rms_zeroed_with: 2e-7,
            }),
            invertibility: None,
            decision: Decision::Added,
            model: model(),
            sse: 1e-11,
        }
    }

    /// The step that added [`trial`], with one effect not fitted.
    pub(in crate::close_loop) fn step() -> Step {
        Step {
            axis: "x".into(),
            number: 1,
            rms_before: 2e-7,
            floor: Floor {
                residual: ResidualFigures {
                    rms: 2e-7,
                    noise: 2e-9,
                    ljung_box_q20: 900.0,
                },
                noise_m: 2e-9,
            },
            screened: vec![
                (EffectKind::Creep, "Kelvin-Voigt", 0.6, -700.0),
                (EffectKind::Drift, "linear", 0.01, 3.0),
            ],
            not_tried: vec![Skipped {
                effect: EffectKind::Drift,
                form: "linear",
                share: Some(0.01),
                reason: NotTried::BelowShare { needed: 0.05 },
            }],
            trials: vec![trial()],
            outcome: StepOutcome::Added {
                effect: EffectKind::Creep,
                form: "Kelvin-Voigt, 1 element".into(),
                rms_after: 1e-7,
            },
        }
    }

    /// A candidate serialises with the keys of the report, nested as before: screening,
    /// parameters by name, in-sample and out-of-sample gains, another run, plausibility.
    #[test]
    fn a_trial_serialises_with_the_keys_of_the_report() {
        let t = trial();
        let json = crate::to_json(&t.report()).unwrap();
        assert_eq!(
            keys(&json),
            BTreeSet::from([
                "effect",
                "form",
                "screening",
                "parameters",
                "in_sample",
                "out_of_sample",
                "within_records",
                "another_run",
                "plausibility",
                "invertibility",
                "decision",
                "words",
            ])
        );
        assert_eq!(json["effect"], "creep");
        assert_eq!(json["decision"], "added");
        assert_eq!(json["words"], t.words().as_str());
        assert!(json["invertibility"].is_null());
        assert_eq!(
            keys(&json["screening"]),
            BTreeSet::from(["test", "share", "delta_bic", "figures"])
        );
        assert_eq!(json["screening"]["figures"]["time_constant_s"], 0.2);
        assert_eq!(
            keys(&json["parameters"]),
            BTreeSet::from([Param::CreepGain0.name(), Param::CreepTimeConstant0.name()])
        );
        assert_eq!(
            keys(&json["in_sample"]),
            BTreeSet::from(["rms_before", "rms_after", "gain", "delta_bic"])
        );
        assert_eq!(json["in_sample"]["gain"], t.in_sample_gain());
        // The gain's own keys are checked beside `OutOfSample`; here, that it is nested whole.
        let gain = t.out_of_sample.as_ref().unwrap();
        assert_eq!(
            json["out_of_sample"],
            crate::to_json(&gain.report()).unwrap()
        );
        assert_eq!(
            json["out_of_sample"]["blocks_s"][1],
            serde_json::json!([0.5, 1.0])
        );
        assert_eq!(
            keys(&json["another_run"]),
            BTreeSet::from(["rms_zeroed_without", "rms_zeroed_with", "holds"])
        );
        assert_eq!(json["another_run"]["holds"], true);
        assert_eq!(
            keys(&json["plausibility"]),
            BTreeSet::from(["plausible", "checks"])
        );
        assert_eq!(
            keys(&json["plausibility"]["checks"][0]),
            BTreeSet::from(["parameter", "value", "range", "at_bound"])
        );
        assert_eq!(
            json["plausibility"]["checks"][0]["parameter"],
            Param::CreepTimeConstant0.name()
        );

        let refused = Trial {
            out_of_sample: None,
            within_records: None,
            another_run: None,
            invertibility: Some("not invertible".into()),
            decision: Decision::Refused(Refusal::Implausible),
            ..trial()
        };
        let json = crate::to_json(&refused.report()).unwrap();
        assert!(json["out_of_sample"].is_null() && json["another_run"].is_null());
        assert_eq!(json["invertibility"], "not invertible");
        assert_eq!(json["decision"], "refused-implausible");
    }

    /// A step serialises with the keys of the report: its outcome, the effect and form it added
    /// (null when it stopped), the noise floor, the screening, the candidates and those not fitted.
    #[test]
    fn a_step_serialises_with_the_keys_of_the_report() {
        let s = step();
        let json = crate::to_json(&s.report()).unwrap();
        assert_eq!(
            keys(&json),
            BTreeSet::from([
                "axis",
                "step",
                "outcome",
                "effect",
                "form",
                "removed",
                "rms_before",
                "rms",
                "noise",
                "screening",
                "candidates",
                "not_tried",
                "words",
            ])
        );
        assert_eq!(json["outcome"], "added");
        assert_eq!(json["effect"], "creep");
        assert_eq!(json["form"], "Kelvin-Voigt, 1 element");
        assert_eq!(json["removed"], false);
        assert_eq!(json["rms"], 1e-7);
        assert_eq!(json["words"], s.words().as_str());
        assert_eq!(
            keys(&json["noise"]),
            BTreeSet::from([
                "residual",
                "noise_estimate_m",
                "noise_floor_m",
                "at_noise_floor",
            ])
        );
        assert_eq!(json["noise"]["residual"]["white"], false);
        assert_eq!(
            keys(&json["screening"][1]),
            BTreeSet::from(["effect", "form", "share", "delta_bic"])
        );
        assert_eq!(json["screening"][1]["effect"], "drift");
        assert_eq!(json["candidates"][0]["effect"], "creep");
        assert_eq!(json["not_tried"][0]["reason"], "below-share");

        let removed = Step {
            outcome: StepOutcome::Removed {
                effect: EffectKind::Drift,
                rms_without: 1.5e-7,
            },
            ..step()
        };
        let json = crate::to_json(&removed.report()).unwrap();
        assert_eq!(json["outcome"], "removed");
        assert_eq!(json["effect"], "drift");
        assert!(json["form"].is_null());
        assert_eq!(json["removed"], true);
        assert_eq!(json["rms"], 1.5e-7);
        let stopped = Step {
            outcome: StepOutcome::Stopped(Stop::NothingHolds),
            ..step()
        };
        let json = crate::to_json(&stopped.report()).unwrap();
        assert_eq!(json["outcome"], "stopped-nothing-holds");
        assert!(json["effect"].is_null() && json["form"].is_null());
        assert_eq!(json["rms"], 2e-7);
    }
}
