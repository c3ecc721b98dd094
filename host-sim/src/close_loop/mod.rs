//! `close-loop`: fit the base model, read its residual, name the effect it lacks, keep it only if it
//! holds on data the fit did not see and is physically that effect, refit, repeat; report the error
//! before and after, in sample, on held-out blocks and on another run (`--validate`).
//!
//! 1. Base model: the symmetric Bouc-Wen model y = k1·u + k2·h + y0 fitted by `identify`'s default
//!    method (`vp-de-lm`), per axis, polished by the Levenberg–Marquardt that fits the candidates. The sensor noise σ is estimated from its residual
//!    ([`diagnose::noise_estimate`]: second differences, median absolute deviation).
//! 2. Each step: stop when the residual RMS is within [`select::NOISE_FLOOR_FACTOR`]·σ. Otherwise
//!    every effect not yet in the model is screened on the residual ([`diagnose`]: creep, Kelvin–Voigt
//!    or logarithmic; drift, linear or settling, a function of time alone; delay; asymmetry, an even
//!    term; dynamics, a second-order mode, force-driven or stack-driven (its damping on the motion
//!    relative to the drive), both fitted; coupling; rate-dependent hysteresis, a relaxation of
//!    the hysteretic part), and the best [`MAX_TRIALS`] are fitted for real (the whole model
//!    refitted by Levenberg–Marquardt, [`full`]), together with every phase effect the screening
//!    cannot separate from one of them (creep, delay, rate-dependent hysteresis, dynamics:
//!    [`choose`]); the report says of every other effect why it was not fitted. A candidate is refused if a
//!    parameter ran to the bound of the range that makes it that effect, if its gain does not hold
//!    on held-out blocks of the record (blocked cross-validation over time, state carried through),
//!    or if it makes the prediction of a `--validate` record worse ([`select`]). Of those that hold,
//!    the one with the largest held-out gain is added. An effect added earlier that the model no
//!    longer needs (refitted without it, within 1 % RMS) is removed.
//! 3. Stop when nothing holds. The decisions, with their evidence, are typed ([`report`]) and turned
//!    into JSON last.
//!
//! 4. With `--invertible` ([`CloseLoopSettings::whole_set_invertible`]) every set kept is one
//!    `host-sim compensate` runs ([`stage::compensator_check`]: the stage file's check at its
//!    loop rate, a strictly monotone map, min/max |dy/du| ≥ 0.01). A base polish or a candidate's
//!    fit that the compensator refuses is fitted again held to the sets it accepts (started from
//!    the last accepted set on the way to it); a candidate that gains nothing so is refused as not
//!    invertible, with both fits' figures. A search from a base the compensator refuses that ends
//!    at such a set runs again from the held base.
//!
//! The final models are stage-file axes ([`stage`]); the in-sample, held-out and validation
//! predictions run through piezo-stage's chain, the code `predict` and the firmware run.

pub mod choose;
mod cli;
pub mod diagnose;
pub mod full;
pub mod param;
mod plots;
pub mod report;
pub mod select;
pub mod stage;

pub use cli::{close_loop_cmd, read_records, CloseLoopArgs};
pub use plots::write_plots;
pub use stage::{
    compensator_check, parameter_file, stage_and_io_for, validate, write_stage_file, Fit,
    Validation, ValidationReport,
};

use crate::identify::{identify, min_max, IdentifyError, IdentifySettings, Method, Record};
use crate::uncertainty::Uncertainty;
use diagnose::{
    noise_estimate, screen, Candidate, EffectInit, EffectKind, ResidualFigures, Signals,
};
use full::{last_accepted_on_the_way, refit, sse, AxisModel, EffectBounds, FitData, Simulation};
use piezo_core::effects::EffectParams;
use piezo_core::{BoucWenParams, StaticMap};
use rayon::prelude::*;
use report::{Step, StepOutcome, StepReport, Trial};
use select::{held_out_sse, Decision, Floor, OutOfSample, Plausibility, Refusal, RunGain, Stop};
use std::time::Instant;

/// Most candidates fitted per step (the best by screening share).
pub const MAX_TRIALS: usize = 4;
/// Levenberg–Marquardt iterations of a candidate's fit on the whole record.
const TRIAL_ITERATIONS: usize = 20;

/// Why `close-loop` failed. `Display` gives the message the command line prints.
#[derive(Debug, Clone)]
pub enum CloseLoopError {
    /// Too few samples from `--start` on to fit and cross-validate.
    TooFewSamples {
        /// The first scored time \[s\].
        start_s: f64,
    },
    /// The base identification failed.
    Identify(IdentifyError),
    /// The base identification gave a model other than a static one.
    BaseNotStatic,
    /// A model the core refused, or a record it could not run, with its cause.
    Host(Box<crate::Error>),
}

impl std::fmt::Display for CloseLoopError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::TooFewSamples { start_s } => write!(
                f,
                "--start {start_s}: too few samples left to fit and cross-validate"
            ),
            Self::Identify(e) => e.fmt(f),
            Self::BaseNotStatic => f.write_str("base identification did not give a static model"),
            Self::Host(e) => e.fmt(f),
        }
    }
}

impl std::error::Error for CloseLoopError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            Self::Identify(e) => e.source(),
            Self::Host(e) => e.source(),
            _ => None,
        }
    }
}

impl From<crate::Error> for CloseLoopError {
    fn from(e: crate::Error) -> Self {
        Self::Host(Box::new(e))
    }
}

impl From<IdentifyError> for CloseLoopError {
    fn from(e: IdentifyError) -> Self {
        Self::Identify(e)
    }
}

/// Settings of one run.
#[derive(Debug, Clone)]
pub struct CloseLoopSettings {
    /// First scored time \[s\].
    pub start_s: f64,
    /// Smallest screening share of the residual variance for a candidate to be fitted (a quarter
    /// of it).
    pub min_share: f64,
    /// Seed of the base identification.
    pub seed: u64,
    /// The base identified among the sets the compensator accepts over the record's range
    /// (`identify --invertible`).
    pub invertible: bool,
    /// Several records: each has its own constant sensor offset.
    pub free_offset: bool,
    /// Every set the search keeps, base and effects, is one `host-sim compensate` and the firmware
    /// run ([`stage::compensator_check`] at `loop_rate_hz`): a fit the compensator refuses is
    /// fitted again held to the sets it accepts, or refused as not invertible (what the command
    /// line's `--invertible` asks; it needs `invertible` for the base).
    pub whole_set_invertible: bool,
    /// The loop rate of the stage file to be written \[Hz\] (its effects are discretised at it);
    /// `None`: the record's rate, as a stage file written without `--stage` has it.
    pub loop_rate_hz: Option<f32>,
    /// Effects that may be added.
    pub allowed: Vec<EffectKind>,
    /// Progress on stderr.
    pub progress: bool,
}

impl Default for CloseLoopSettings {
    fn default() -> Self {
        Self {
            start_s: 0.0,
            min_share: 0.05,
            seed: 1,
            invertible: false,
            free_offset: false,
            whole_set_invertible: false,
            loop_rate_hz: None,
            allowed: EffectKind::ALL.to_vec(),
            progress: false,
        }
    }
}

/// Another run of the same axis that candidates must not predict worse (`--validate`).
#[derive(Debug, Clone)]
pub struct OtherRun {
    /// Input (f32).
    pub u: Vec<f32>,
    /// Measured \[m\].
    pub y: Vec<f64>,
    /// First scored sample.
    pub from: usize,
    /// The other axis's z on this run (two-axis records).
    pub other_z: Option<Vec<f64>>,
}

impl OtherRun {
    /// RMS of `model`'s prediction with one offset re-estimated (∞ if the core refuses it).
    pub fn rms_zeroed(&self, model: &AxisModel) -> f64 {
        match model.simulate(&self.u, self.other_z.as_deref()) {
            Ok(sim) => {
                let n = sim.y.len().min(self.y.len());
                let from = self.from.min(n);
                Fit::of(&self.y[from..n], &sim.y[from..n]).rms_zeroed
            }
            Err(_) => f64::INFINITY,
        }
    }
}

/// One axis's outcome.
#[derive(Debug, Clone)]
pub struct AxisOutcome {
    /// Axis name (`x`, `y`).
    pub name: String,
    /// The base model.
    pub base: AxisModel,
    /// The final model.
    pub model: AxisModel,
    /// The decision log.
    pub steps: Vec<Step>,
    /// Sensor noise estimate \[m\].
    pub noise_m: f64,
    /// The record's input range \[V\].
    pub input_range_v: (f64, f64),
    /// The record's largest input rate and band (`[x.identified]`'s, of
    /// [`crate::identify::record_envelope`]).
    pub envelope: (Option<f32>, Option<[f32; 2]>),
    /// Base model's prediction of the fitted record (piezo-stage's chain) \[m\].
    pub before: Vec<f64>,
    /// Final model's prediction \[m\].
    pub after: Vec<f64>,
    /// Scores of `before` over the scored samples.
    pub fit_before: Fit,
    /// Scores of `after`.
    pub fit_after: Fit,
    /// Held-out RMS (cross-validation) of the base and the final model \[m\].
    pub held_out_rms: (f64, f64),
    /// How the held-out blocks were chosen, in words.
    pub held_out_method: String,
    /// Per record, when several records were fitted together (one entry otherwise).
    pub records: Vec<RecordFits>,
    /// The final fit's uncertainty on the fitted record ([`full::linearise`],
    /// [`crate::uncertainty::estimate`]), or why it was not computed.
    pub uncertainty: crate::Result<Uncertainty>,
}

/// One record's scores before and after, when several records were fitted together.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct RecordFits {
    /// The record's file.
    pub data: String,
    /// The base model's scores on it.
    pub before: Fit,
    /// The final model's scores on it.
    pub after: Fit,
}

/// The models' predictions of a record of several records through piezo-stage's chain, each
/// record from rest at its first sample.
fn predict_records(
    models: &[&AxisModel],
    us: &[Vec<f32>],
    record: &Record,
) -> crate::Result<Vec<Vec<f64>>> {
    let n = us.iter().map(Vec::len).min().unwrap_or(0);
    let mut out = vec![vec![0.0; n]; models.len()];
    for (a, b) in record.segment_ranges() {
        let (a, b) = (a.min(n), b.min(n));
        let part: Vec<Vec<f32>> = us.iter().map(|u| u[a..b].to_vec()).collect();
        for (o, p) in out.iter_mut().zip(stage::predict(models, &part)?) {
            o[a..b].copy_from_slice(&p);
        }
    }
    Ok(out)
}

/// With free offsets, the map's offset is set to the first record's own offset (the stage file's;
/// the other records' are re-estimated on their samples): y0 plus the first record's mean error.
fn hold_first_record_offset(
    model: &mut AxisModel,
    record: &Record,
    u: &[f32],
    from: usize,
) -> crate::Result<()> {
    if !model.free_offset {
        return Ok(());
    }
    let sim = model.simulate(u, None)?;
    let (a, b) = record.segment_ranges()[0];
    let a = a.max(from).min(b);
    let n = (b - a).max(1) as f64;
    let mean_error = (a..b).map(|k| record.y_m[k] - sim.y[k]).sum::<f64>() / n;
    model.map.offset_m += mean_error as f32;
    Ok(())
}

/// The outcome of a run.
#[derive(Debug, Clone)]
pub struct Outcome {
    /// Per axis.
    pub axes: Vec<AxisOutcome>,
    /// First scored sample.
    pub from: usize,
    /// The scored window \[s\].
    pub window_s: (f64, f64),
    /// The fitted record.
    pub data: String,
    /// All axes together, base model.
    pub before: Fit,
    /// All axes together, final model.
    pub after: Fit,
    /// The prediction of `--validate` (when given).
    pub validation: Option<Validation>,
}

impl Outcome {
    /// The effects added on any axis, in order.
    pub fn effects_added(&self) -> Vec<&'static str> {
        let mut v: Vec<&'static str> = Vec::new();
        for a in &self.axes {
            for e in &a.model.added {
                if !v.contains(&e.name()) {
                    v.push(e.name());
                }
            }
        }
        v
    }

    /// The report (the command writes it with the stage file's name and verdict added).
    pub fn report(&self) -> OutcomeReport<'_> {
        OutcomeReport {
            unit: "m",
            data: &self.data,
            window_s: self.window_s,
            samples: self.axes.first().map_or(0, |a| a.before.len() - self.from),
            base_model: "symmetric Bouc-Wen y = k1*u + k2*h + y0 (vp-de-lm)",
            before: self.before,
            after: self.after,
            effects_added: self.effects_added(),
            steps: self
                .axes
                .iter()
                .flat_map(|a| a.steps.iter().map(Step::report))
                .collect(),
            words: self
                .axes
                .iter()
                .flat_map(|a| a.steps.iter().map(Step::words))
                .collect(),
            axes: self.axes.iter().map(AxisOutcome::report).collect(),
            validation: self.validation.as_ref().map(Validation::report),
        }
    }
}

impl AxisOutcome {
    /// The axis's part of the report: its effects, scores, parameters and uncertainty.
    pub fn report(&self) -> AxisReport<'_> {
        AxisReport {
            axis: &self.name,
            effects_added: self
                .model
                .added
                .iter()
                .map(|&effect| AddedEffect {
                    effect,
                    form: self.model.form(effect),
                })
                .collect(),
            noise_estimate_m: self.noise_m,
            before: self.fit_before,
            after: self.fit_after,
            held_out: HeldOutReport {
                rms_before: self.held_out_rms.0,
                rms_after: self.held_out_rms.1,
                method: &self.held_out_method,
            },
            records: &self.records,
            base_params: params_report(&self.base),
            params: params_report(&self.model),
            uncertainty: crate::uncertainty::keys_of(&self.uncertainty),
        }
    }
}

/// The outcome of a run in a report ([`Outcome::report`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct OutcomeReport<'a> {
    /// The unit of every RMS, offset and error: `m`.
    pub unit: &'static str,
    /// The fitted record.
    pub data: &'a str,
    /// The scored window \[s\].
    pub window_s: (f64, f64),
    /// Scored samples per axis.
    pub samples: usize,
    /// The base model, in words.
    pub base_model: &'static str,
    /// All axes together, base model.
    pub before: Fit,
    /// All axes together, final model.
    pub after: Fit,
    /// The effects added on any axis, in order ([`Outcome::effects_added`]).
    pub effects_added: Vec<&'static str>,
    /// Every step of every axis.
    pub steps: Vec<StepReport<'a>>,
    /// Every step of every axis in words.
    pub words: Vec<String>,
    /// Per axis.
    pub axes: Vec<AxisReport<'a>>,
    /// The prediction of `--validate` (absent without it).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub validation: Option<ValidationReport<'a>>,
}

/// One axis in a report ([`AxisOutcome::report`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct AxisReport<'a> {
    /// Axis name (`x`, `y`).
    pub axis: &'a str,
    /// The effects of the final model, in the order they were added, with their forms.
    pub effects_added: Vec<AddedEffect>,
    /// Sensor noise estimate \[m\].
    pub noise_estimate_m: f64,
    /// Scores of the base model.
    pub before: Fit,
    /// Scores of the final model.
    pub after: Fit,
    /// Held-out RMS of both models.
    pub held_out: HeldOutReport<'a>,
    /// Per record.
    pub records: &'a [RecordFits],
    /// The base model's parameters.
    pub base_params: ParamsReport<'a>,
    /// The final model's parameters.
    pub params: ParamsReport<'a>,
    /// `uncertainty`, `correlation` and `prediction_band_rms_m`
    /// ([`crate::uncertainty::keys_of`]), beside the other keys.
    #[serde(flatten)]
    pub uncertainty: serde_json::Map<String, serde_json::Value>,
}

/// An effect of the final model in a report.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct AddedEffect {
    /// The effect.
    pub effect: EffectKind,
    /// Its form ([`AxisModel::form`]).
    pub form: String,
}

/// The held-out RMS of an axis in a report.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct HeldOutReport<'a> {
    /// Base model \[m\].
    pub rms_before: f64,
    /// Final model \[m\].
    pub rms_after: f64,
    /// How the held-out blocks were chosen, in words.
    pub method: &'a str,
}

/// Parameters of an axis model in a report (SI; [`params_report`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ParamsReport<'a> {
    /// Bouc-Wen parameters.
    pub bouc_wen: BoucWenParams,
    /// y = k1·u + k2·h + y0.
    pub static_map: StaticMap,
    /// The effect chain's parameters.
    pub effects: &'a EffectParams,
    /// The input range the set is valid over \[V\].
    pub input_range_v: (f32, f32),
    /// Sample period \[s\].
    pub sample_period_s: f32,
}

/// Parameters of an axis model (for the report, SI).
pub fn params_report(m: &AxisModel) -> ParamsReport<'_> {
    ParamsReport {
        bouc_wen: m.bouc_wen,
        static_map: m.map,
        effects: &m.effects,
        input_range_v: m.input_range_v,
        sample_period_s: m.sample_period_s,
    }
}

fn log(show: bool, msg: impl AsRef<str>) {
    if show {
        eprintln!("close-loop: {}", msg.as_ref());
    }
}

/// The loop rate every set is checked at with `whole_set_invertible` (`--invertible`,
/// [`stage::compensator_check`]); `None` without it.
fn invertible_at_hz(record: &Record, s: &CloseLoopSettings) -> Option<f32> {
    s.whole_set_invertible.then(|| {
        s.loop_rate_hz
            .unwrap_or_else(|| crate::stage_file::rate_of(1.0 / record.sample_period_s()))
    })
}

/// The base model of one axis: the identified set polished on the whole record, and with
/// `--invertible`, when the compensator refuses that polish, the polish held to the sets it
/// accepts (started from the last set it accepts on the way from the identified set to the free
/// polish).
fn base_model(
    record: &Record,
    s: &CloseLoopSettings,
) -> Result<(AxisModel, Option<AxisModel>), CloseLoopError> {
    let id = identify(
        record,
        &IdentifySettings {
            model: crate::identify::model::ModelKind::Symmetric,
            method: Method::VpDeLm,
            seed: s.seed,
            start_s: s.start_s,
            no_shift: true,
            invertible: s.invertible,
            free_offset: s.free_offset,
            progress: s.progress,
        },
    )?;
    let crate::identify::model::Identified::Static {
        bouc_wen,
        map,
        sample_period_s,
        input_range_v,
        ..
    } = id.set
    else {
        return Err(CloseLoopError::BaseNotStatic);
    };
    let from = record.index_at(s.start_s);
    let (lo, hi) = min_max(&record.y_m[from..]);
    let stroke = (hi - lo).max(1e-12);
    let pad = 0.25 * stroke;
    let (u_lo, u_hi) = min_max(&record.u);
    let ts = record.sample_period_s();
    // With several records: the longest record's duration, and the highest dominant input
    // frequency of all (a mode must lie above every record's band).
    let ranges = record.segment_ranges();
    let record_s = ranges
        .iter()
        .map(|&(a, b)| ts * (b - a.max(from).min(b)) as f64)
        .fold(0.0, f64::max);
    let f_dom = ranges
        .iter()
        .filter(|&&(a, b)| b > a.max(from) + 10)
        .map(|&(a, b)| diagnose::dominant_frequency_hz(&record.u[a.max(from)..b], ts))
        .fold(0.0, f64::max);
    // The static gain dy/du: the least-squares slope of y on u over the scored samples, its size
    // the stroke over the input span.
    let slope = {
        let (us, ys) = (&record.u[from..], &record.y_m[from..]);
        let n = us.len().max(1) as f64;
        let (mu, my) = (us.iter().sum::<f64>() / n, ys.iter().sum::<f64>() / n);
        us.iter()
            .zip(ys)
            .map(|(u, y)| (u - mu) * (y - my))
            .sum::<f64>()
    };
    let gain = stroke / (u_hi - u_lo).max(1e-12) * if slope < 0.0 { -1.0 } else { 1.0 };
    let window = stage::output_window(&record.u);
    let mut model = AxisModel {
        bouc_wen,
        map,
        effects: Default::default(),
        added: Vec::new(),
        creep_form: full::CreepForm::KelvinVoigt,
        creep_elements: 1,
        rate_form: full::RateForm::InputLag,
        with_rate_gain: false,
        drift_form: full::DriftForm::Linear,
        input_range_v: window,
        w_range_m: ((lo - pad) as f32, (hi + pad) as f32),
        sample_period_s,
        bounds: EffectBounds::for_record(ts, record_s, f_dom, stroke, gain, u_hi - u_lo),
        segments: record.segments.clone(),
        free_offset: s.free_offset && record.segments.len() > 1,
    };
    // The stage file's output window is the record's range rounded outwards; the Bouc-Wen set must
    // hold over it, and with `--invertible` the compensator accept it there (else the record's own
    // range is kept).
    let invertible_at_hz = invertible_at_hz(record, s);
    let accepted = |m: &AxisModel| {
        invertible_at_hz.is_none_or(|rate| stage::compensator_check(m, rate).is_ok())
    };
    if model.build().is_err() || !accepted(&model) {
        model.input_range_v = input_range_v;
    }
    // Polished by the same Levenberg–Marquardt as every candidate (on the core's f32 chain), so
    // that a candidate's gain is not the base parameters' own.
    let u: Vec<f32> = record.u.iter().map(|&v| v as f32).collect();
    let data = FitData {
        u: &u,
        y: &record.y_m,
        other_z: None,
        from,
        held_out: None,
        free_offset: model.free_offset,
        invertible_at_hz: None,
    };
    let (polished, sse_polished, _) = refit(&model, &data, 2 * TRIAL_ITERATIONS);
    let free = if sse_polished.is_finite() && sse_polished < sse(&model, &data) {
        polished
    } else {
        model.clone()
    };
    let held = match invertible_at_hz {
        Some(rate) if !accepted(&free) => {
            let start = last_accepted_on_the_way(&model, &free, accepted);
            let (p, sse_p, _) = refit(&start, &held_to(&data, rate), 2 * TRIAL_ITERATIONS);
            Some(if sse_p.is_finite() && accepted(&p) {
                p
            } else {
                start
            })
        }
        _ => None,
    };
    Ok((free, held))
}

/// A start for the creep fit with gains of the sign of the stage's static gain (σ) and the static
/// gain k1 + (creep's gain) of `model` kept, when `fitted` (from the screening's start `init`)
/// ended with a creep gain of the other sign or 0; `None` otherwise. The start's gain per element
/// is the largest of the fitted and screened magnitudes and 2 % of |k1| (a stack's creep per
/// decade of time); `always`: also when the gains have the right sign. With `invertible_at_hz`
/// (`--invertible`) the start must be a set the
/// compensator accepts: lowering k1 can make the map turn back after a reversal, so the gains
/// (and the shift of k1 with them) are halved, up to [`FEASIBLE_HALVINGS`] times, until it is;
/// `None` if they never are.
fn creep_restart(
    model: &AxisModel,
    fitted: &AxisModel,
    init: EffectInit,
    invertible_at_hz: Option<f32>,
    always: bool,
) -> Option<AxisModel> {
    let e = &fitted.effects;
    let b = model.bounds;
    let sign = b.gain_sign;
    let k1 = f64::from(model.map.k1_m_per_v);
    let floor = 0.02 * k1.abs();
    // The start with its creep gains scaled by `scale`.
    let start: Box<dyn Fn(f64) -> AxisModel> = match init {
        EffectInit::Creep {
            gains_m_per_v,
            time_constants_s,
        } => {
            let n = fitted.creep_elements;
            let gains = &e.creep_gain_m_per_v[..n];
            if !always && gains.iter().all(|&g| f64::from(g) * sign > 0.0) {
                return None;
            }
            let mut g = [0.0; 2];
            for i in 0..n {
                g[i] = sign
                    * f64::from(gains[i])
                        .abs()
                        .max(gains_m_per_v[i].abs())
                        .max(floor);
            }
            Box::new(move |scale| {
                let g = g.map(|v| scale * v);
                let mut m = model.with_effect(EffectInit::Creep {
                    gains_m_per_v: g,
                    time_constants_s,
                });
                m.map.k1_m_per_v = (k1 - g.iter().sum::<f64>()) as f32;
                m
            })
        }
        EffectInit::LogCreep { gain_m_per_v } => {
            let g_fit = f64::from(e.log_creep_gain_m_per_v);
            if !always && g_fit * sign > 0.0 {
                return None;
            }
            let g = sign * g_fit.abs().max(gain_m_per_v.abs()).max(0.5 * floor);
            // After a step the logarithmic creep has reached g·log10(1 + t/t0); at half the record:
            let decades = (1.0 + 0.5 * b.record_s / b.sample_period_s).log10();
            Box::new(move |scale| {
                let g = scale * g;
                let mut m = model.with_effect(EffectInit::LogCreep { gain_m_per_v: g });
                m.map.k1_m_per_v = (k1 - g * decades) as f32;
                m
            })
        }
        _ => return None,
    };
    let Some(rate) = invertible_at_hz else {
        return Some(start(1.0));
    };
    (0..=FEASIBLE_HALVINGS)
        .map(|i| start(0.5f64.powi(i as i32)))
        .find(|m| stage::compensator_check(m, rate).is_ok())
}

/// Relaxation gains g the rate-dependent hysteresis's fit is started again from
/// ([`AxisModel::relaxation_restart`]): records slow against τ fix only k2·(1 + g) and τ·g/(1 + g),
/// and the fit from the screening's split stays near it.
const RELAXATION_RESTART_GAINS: [f64; 3] = [0.5, 3.0, 20.0];

/// Most halvings of a creep restart's gains in search of a start the compensator accepts.
const FEASIBLE_HALVINGS: usize = 4;

/// What a candidate is judged against: the fitted data, its held-out blocks, the current model's
/// held-out and in-sample SSE, the other run (`--validate`) and the loop rate of `--invertible`.
struct Bench<'a> {
    /// The data the candidate is fitted on.
    data: &'a FitData<'a>,
    /// The held-out blocks (cross-validation).
    blocks: &'a [full::Block],
    /// The current model's held-out SSE per block.
    held_without: &'a [f64],
    /// With several records, the blocks within them.
    within_records: Option<&'a [full::Block]>,
    /// The current model's held-out SSE per block within the records (computed when first
    /// needed).
    within_without: std::cell::OnceCell<Vec<f64>>,
    /// The current model's SSE.
    sse0: f64,
    /// The run the candidate must not predict worse.
    run: Option<&'a OtherRun>,
    /// Times of the record \[s\].
    t_s: &'a [f64],
    /// `--invertible`: the loop rate every set added must pass [`stage::compensator_check`] at.
    invertible_at_hz: Option<f32>,
}

/// The candidate fitted on `data` (the whole model refitted from the screening's start) and its
/// SSE. A base fitted without creep has the creep's long-term gain in k1 (and its lag in the
/// loop), so a creep fit started from the screening may settle at a gain of the wrong sign. It is
/// started again with gains of the static gain's sign and the static gain held (k1 lowered by the
/// creep's gain). On data held to the compensator's sets ([`FitData::invertible_at_hz`]) a creep
/// fit that could not lower k1 and gained nothing is started again the same way, from the largest
/// share of that start the compensator accepts. `run` (`--validate`) chooses the rate-dependent
/// hysteresis's form ([`fit_rate_dependent`]).
fn fit_candidate(
    model: &AxisModel,
    cand: &Candidate,
    data: &FitData,
    sse0: f64,
    run: Option<&OtherRun>,
) -> (AxisModel, f64) {
    let (mut fitted, mut sse1) = if cand.effect == EffectKind::RateDependent {
        fit_rate_dependent(model, cand, data, run)
    } else if cand.effect == EffectKind::Dynamics {
        fit_dynamics(model, cand, data)
    } else {
        let (fitted, sse1, _) = refit(&model.with_effect(cand.init), data, TRIAL_ITERATIONS);
        (fitted, sse1)
    };
    let stuck = data.invertible_at_hz.is_some() && !(sse1 < sse0);
    if let Some(start) = creep_restart(model, &fitted, cand.init, data.invertible_at_hz, stuck) {
        let (again, sse_again, _) = refit(&start, data, TRIAL_ITERATIONS);
        if sse_again.is_finite()
            && Plausibility::of(&again, cand.effect).plausible()
            && (!stuck || sse_again < sse1)
        {
            fitted = again;
            sse1 = sse_again;
        }
    }
    (fitted, sse1)
}

/// Mode frequencies, spread geometrically over the plausible range, from which the mode is also
/// fitted: a mode whose response lies near the noise in a record (far above the input's band)
/// leaves a shallow SSE over its frequency, and a fit from the screening's start alone may slide
/// to a bound of the range while the stage's own mode lies between.
const MODE_RESTARTS: usize = 4;

/// Damping ratio of the restarts' starts.
const MODE_RESTART_DAMPING: f64 = 0.02;

/// The mode's two forms (`mode_relative_damping` ρ, piezo-core's effects): 0, the damping acts on
/// the mode's own motion (a force-driven mode, z̈ + 2ζω·ż + ω²·(z − s) = 0); 1, it acts on the
/// motion relative to the drive (a mode driven through the stack's own spring and damper,
/// z̈ + 2ζω·(ż − ṡ) + ω²·(z − s) = 0, whose phase well below the mode is zero).
const MODE_FORMS: [f32; 2] = [0.0, 1.0];

/// The mode fitted in both its forms ([`MODE_FORMS`]), each from the screening's start and from
/// [`MODE_RESTARTS`] frequencies across its plausible range; kept: the plausible fit with the
/// lowest SSE (the lowest SSE when none is plausible). Which form a stage's mode takes is the
/// data's to say: below the mode the two differ by the phase lag 2ζ·f/f_mode of the force-driven
/// form, and after a reversal by how long the mode rings.
fn fit_dynamics(model: &AxisModel, cand: &Candidate, data: &FitData) -> (AxisModel, f64) {
    let (lo, hi) = model.bounds.mode_frequency_hz;
    let mut starts = vec![cand.init];
    if lo > 0.0 && hi > lo {
        starts.extend((0..MODE_RESTARTS).map(|i| {
            let share = (i as f64 + 0.5) / MODE_RESTARTS as f64;
            EffectInit::Dynamics {
                frequency_hz: lo * (hi / lo).powf(share),
                damping: MODE_RESTART_DAMPING,
            }
        }));
    }
    let starts: Vec<(EffectInit, f32)> = MODE_FORMS
        .iter()
        .flat_map(|&rho| starts.iter().map(move |&init| (init, rho)))
        .collect();
    let fits: Vec<(AxisModel, f64, bool)> = starts
        .par_iter()
        .map(|&(init, rho)| {
            let mut start = model.with_effect(init);
            start.effects.mode_relative_damping = rho;
            let (fitted, sse, _) = refit(&start, data, TRIAL_ITERATIONS);
            let plausible = Plausibility::of(&fitted, cand.effect).plausible();
            (fitted, sse, plausible)
        })
        .collect();
    best_fit(fits).map_or((model.clone(), f64::INFINITY), |(m, sse, _)| (m, sse))
}

/// The rate-dependent hysteresis fitted in its forms ([`full::RateForm`]): the operator driven
/// by a lag of the command, the relaxation of its output (that one also from other splits of its
/// first-order lag into g and τ, [`AxisModel::relaxation_restart`]), on several records the
/// relaxation of the whole output (the linear strain too: loops that widen with rate), the input
/// lag together with one or two relaxation elements (started from the input lag's fit, one element at a time:
/// [`fit_one_more_relaxation`]), and either relaxation with its time constants spread over W
/// decades (started from its one-lag fit, [`fit_spread`]), and the operator's gain rising with
/// the command's speed (the rate-dependent Bouc-Wen gain A·(1 + c·|u̇|)), alone and beside the
/// input lag and the best other form (started from their fits; the gain then acts on the lagged
/// input), kept only where the compensator accepts its set or refuses it without the gain too. The form kept is the plausible one with the lowest SSE (the lowest
/// SSE when none is plausible): which form a stage's rate dependence takes is the data's to say.
/// The richer forms nest the input lag (a relaxation gain → 0 runs to its plausible bound), so on
/// a stage with one lag they are not plausible and the input lag is kept; a spread of dielectric
/// relaxation times, which one lag cannot follow across rates, keeps two time constants.
///
/// With a `--validate` record (`run`), the plausible form that predicts it best is kept instead
/// (zeroed RMS; forms within [`HELD_OUT_TIE`] of the best gain 1 − (RMS / the current model's
/// RMS)² are a tie, decided by the lower SSE): the forms fit the fitted rates alike and part at
/// others (a stack whose hysteretic part relaxes over a spread of times: fitted on 20 and 40 Hz,
/// the spread relaxation predicts 100 Hz better than the input lag with a relaxation, which fits
/// 20 and 40 Hz closer).
fn fit_rate_dependent(
    model: &AxisModel,
    cand: &Candidate,
    data: &FitData,
    run: Option<&OtherRun>,
) -> (AxisModel, f64) {
    let fit_form = |form: full::RateForm| {
        let mut base = model.clone();
        base.rate_form = form;
        let (mut fitted, mut sse1, _) = refit(&base.with_effect(cand.init), data, TRIAL_ITERATIONS);
        for gain in RELAXATION_RESTART_GAINS {
            let Some(start) = fitted.relaxation_restart(gain) else {
                continue;
            };
            let (again, sse_again, _) = refit(&start, data, TRIAL_ITERATIONS);
            if sse_again < sse1 && Plausibility::of(&again, cand.effect).plausible() {
                fitted = again;
                sse1 = sse_again;
            }
        }
        let plausible = Plausibility::of(&fitted, cand.effect).plausible();
        (fitted, sse1, plausible)
    };
    let lag = fit_form(full::RateForm::InputLag);
    let lag_fit = lag.0.clone();
    let relaxation = fit_form(full::RateForm::Relaxation);
    // Whether the whole output relaxes shows in how the loops open from one rate to another;
    // within one record at one rate its lag is the delay's signature, so it is fitted only on
    // several records.
    let whole = (model.segments.len() > 1).then(|| fit_form(full::RateForm::WholeRelaxation));
    let both = fit_one_more_relaxation(&lag.0, cand, data);
    let three = both
        .as_ref()
        .and_then(|b| fit_one_more_relaxation(&b.0, cand, data));
    // With another run, the spread must predict it better than its one lag; without one, the
    // records must resolve it.
    let run = run.map(|run| (run, run.rms_zeroed(model)));
    let judge = run.map_or(SpreadJudge::Records, |(run, rms_zeroed_without)| {
        SpreadJudge::Run {
            run,
            rms_zeroed_without,
        }
    });
    let spread = fit_spread(
        &relaxation.0,
        full::RateForm::SpreadRelaxation,
        cand,
        data,
        judge,
    );
    let whole_spread = whole.as_ref().and_then(|w| {
        fit_spread(
            &w.0,
            full::RateForm::WholeSpreadRelaxation,
            cand,
            data,
            judge,
        )
    });
    let gain = fit_form(full::RateForm::RateGain);
    let mut forms: Vec<(AxisModel, f64, bool)> = [
        Some(lag),
        Some(relaxation),
        whole,
        both,
        three,
        spread,
        whole_spread,
        Some(gain),
    ]
    .into_iter()
    .flatten()
    .collect();
    // The input lag and the best plausible other form with the operator's rate-dependent gain
    // beside them: a lag or a relaxation that levels off with the rate, and a gain that keeps
    // growing with the speed (the gain acts on the lagged input when there is a lag).
    let best_alone = best_fit(
        forms
            .iter()
            .filter(|f| !f.0.rate_form.has_rate_gain())
            .cloned()
            .collect(),
    )
    .filter(|f| f.2 && f.0.rate_form != full::RateForm::InputLag);
    let with_gain: Vec<AxisModel> = [Some(lag_fit), best_alone.map(|f| f.0)]
        .into_iter()
        .flatten()
        .map(|mut start| {
            start.with_rate_gain = true;
            start.effects.hysteresis_rate_gain_s_per_v = full::RATE_GAIN_START_S_PER_V as f32;
            start
        })
        .collect();
    let fitted: Vec<(AxisModel, f64, bool)> = with_gain
        .par_iter()
        .map(|start| {
            let (fitted, sse, _) = refit(start, data, TRIAL_ITERATIONS);
            let plausible = Plausibility::of(&fitted, cand.effect).plausible();
            (fitted, sse, plausible)
        })
        .collect();
    forms.extend(fitted);
    let forms: Vec<(AxisModel, f64, bool)> = forms
        .into_iter()
        .map(|(m, sse, plausible)| {
            // A form whose set the compensator refuses because of its gain is no model of the
            // stage (with `--invertible` every fit is already held to the sets it accepts): a
            // rate-dependent gain's map must stay monotone at the speeds the slew limit allows.
            // A stage whose map folds without the gain (a set no compensator inverts, written
            // without `--invertible`) is judged by its fit alone.
            let gains = m.rate_form.has_rate_gain() || m.with_rate_gain;
            let runs = data.invertible_at_hz.is_some() || !gains || {
                let rate = crate::stage_file::rate_of(1.0 / f64::from(m.sample_period_s));
                let mut without_gain = m.clone();
                without_gain.effects.hysteresis_rate_gain_s_per_v = 0.0;
                stage::compensator_check(&m, rate).is_ok()
                    || stage::compensator_check(&without_gain, rate).is_err()
            };
            (m, sse, plausible && runs)
        })
        .collect();
    // With the other run: each plausible form's gain on it (−∞ for the others).
    let gains: Option<Vec<f64>> = run.map(|(run, rms_zeroed_without)| {
        forms
            .iter()
            .map(|(m, sse, plausible)| {
                let gain = RunGain {
                    rms_zeroed_without,
                    rms_zeroed_with: run.rms_zeroed(m),
                }
                .gain();
                if *plausible && sse.is_finite() && gain.is_finite() {
                    gain
                } else {
                    f64::NEG_INFINITY
                }
            })
            .collect()
    });
    let top = gains.as_ref().map_or(f64::NEG_INFINITY, |g| {
        g.iter().copied().fold(f64::NEG_INFINITY, f64::max)
    });
    let chosen = match gains {
        // The best on the other run, ties by the lower SSE.
        Some(gains) if top > f64::NEG_INFINITY => forms
            .into_iter()
            .zip(gains)
            .filter(|(_, g)| *g >= top - HELD_OUT_TIE)
            .map(|(f, _)| f)
            .min_by(|a, b| a.1.total_cmp(&b.1)),
        // Without it (or with no plausible form): the lowest SSE.
        _ => best_fit(forms),
    };
    let (m, sse, _) = chosen.expect("the input lag and the relaxation are always fitted");
    (m, sse)
}

/// The plausible fit with the lowest SSE (the lowest SSE when none is plausible; a non-finite SSE
/// never wins).
fn best_fit(fits: Vec<(AxisModel, f64, bool)>) -> Option<(AxisModel, f64, bool)> {
    let key = |f: &(AxisModel, f64, bool)| {
        (
            f.2,
            if f.1.is_finite() {
                -f.1
            } else {
                f64::NEG_INFINITY
            },
        )
    };
    let mut best: Option<(AxisModel, f64, bool)> = None;
    for fit in fits {
        if best.as_ref().is_none_or(|b| key(&fit) > key(b)) {
            best = Some(fit);
        }
    }
    best
}

/// Spreads W of the spread relaxation's starts \[decades\].
const SPREAD_STARTS: [f64; 2] = [1.0, 2.5];

/// The spread form `to` ([`full::RateForm::SpreadRelaxation`] or
/// [`full::RateForm::WholeSpreadRelaxation`]) fitted from the one-time-constant fit `from`
/// ([`full::RateForm::Relaxation`] or [`full::RateForm::WholeRelaxation`]): started at each of
/// [`SPREAD_STARTS`] with the gain kept and the centre τ_w moved so that the mean of the lags' time
/// constants is the fitted τ_w (the first-order lag g·τ̄ that slow records fix is kept); the
/// plausible fit with the lowest SSE. The spread form nests the single lag (W → 0), so on a stage
/// one lag describes, W runs to its lower bound and the fit is not plausible; W near 0 fits as
/// well as one lag and is not plausible either unless `judge` says the spread holds.
fn fit_spread(
    from: &AxisModel,
    to: full::RateForm,
    cand: &Candidate,
    data: &FitData,
    judge: SpreadJudge,
) -> Option<(AxisModel, f64, bool)> {
    use piezo_core::effects::{relaxation_spread_factor, RELAXATION_SPREAD_POINTS as N};
    if !from.added.contains(&EffectKind::RateDependent)
        || !matches!(
            from.rate_form,
            full::RateForm::Relaxation | full::RateForm::WholeRelaxation
        )
    {
        return None;
    }
    let (lo, hi) = from.bounds.relaxation_tau_s;
    let tau = f64::from(from.effects.relaxation_time_constant_s[0]);
    let fits = SPREAD_STARTS
        .iter()
        .map(|&w| {
            let mean = (0..N).map(|k| relaxation_spread_factor(w, k)).sum::<f64>() / N as f64;
            let mut start = from.clone();
            start.rate_form = to;
            start.effects.relaxation_time_constant_s[0] = (tau / mean).clamp(lo, hi) as f32;
            start.effects.relaxation_spread_decades = w as f32;
            let (fitted, sse, _) = refit(&start, data, TRIAL_ITERATIONS);
            let plausible = Plausibility::of(&fitted, cand.effect).plausible();
            (fitted, sse, plausible)
        })
        .collect();
    let (m, sse, plausible) = best_fit(fits)?;
    let holds = plausible && judge.holds(&m, from, data);
    Some((m, sse, holds))
}

/// What decides whether a fitted spread of relaxation times holds against its one lag.
#[derive(Clone, Copy)]
enum SpreadJudge<'a> {
    /// The records alone: W more than [`SPREAD_RESOLVED`] standard errors above 0 (the
    /// Bartlett-corrected errors of the fit's linearisation).
    Records,
    /// Another run (`--validate`): the spread's gain on it, 1 − (RMS with / without)², more than
    /// [`HELD_OUT_TIE`] above the one lag's (a spread that predicts it as well is the one lag's).
    Run {
        run: &'a OtherRun,
        /// The run's zeroed RMS without the effect \[m\].
        rms_zeroed_without: f64,
    },
}

impl SpreadJudge<'_> {
    /// Whether the spread fit `spread` holds against the one-lag fit `one_lag` on `data`.
    fn holds(self, spread: &AxisModel, one_lag: &AxisModel, data: &FitData) -> bool {
        match self {
            Self::Run {
                run,
                rms_zeroed_without,
            } => {
                let gain = |m: &AxisModel| {
                    RunGain {
                        rms_zeroed_without,
                        rms_zeroed_with: run.rms_zeroed(m),
                    }
                    .gain()
                };
                gain(spread) > gain(one_lag) + HELD_OUT_TIE
            }
            Self::Records => spread_is_resolved(spread, data),
        }
    }
}

/// Whether the fit `m`'s spread W lies more than [`SPREAD_RESOLVED`] standard errors above 0.
fn spread_is_resolved(m: &AxisModel, data: &FitData) -> bool {
    full::linearise(m, data)
        .and_then(|l| crate::uncertainty::estimate(&l))
        .ok()
        .and_then(|u| {
            let name = full::report_name(param::Param::RelaxationSpread);
            let i = u.parameters.iter().position(|p| p.name == name)?;
            u.standard_errors.get(i).copied()
        })
        .is_some_and(|se| f64::from(m.effects.relaxation_spread_decades) > SPREAD_RESOLVED * se)
}

/// How many standard errors a fitted spread W must lie above 0 to be kept.
const SPREAD_RESOLVED: f64 = 2.0;

/// Relaxation time constants of the two-time-constant form's starts, as multiples of the fitted
/// input lag τ_v: a spread of relaxation times lies on both sides of the one lag that fits best.
const LAG_AND_RELAXATION_STARTS: [f64; 3] = [0.2, 4.0, 20.0];

/// One more relaxation element on the input-lag fit `from`: from [`full::RateForm::InputLag`] to
/// [`full::RateForm::LagAndRelaxation`] (the first element, two time constants), or from that form
/// to [`full::RateForm::LagAndTwoRelaxations`] (the second element, three). The new element i is
/// started at [`LAG_AND_RELAXATION_STARTS`] times the fitted input lag τ_v with gain
/// gᵢ = [`full::LAG_AND_RELAXATION_START_GAIN`], the static hysteretic gain k2·(1 + Σ g) kept
/// (k2 ← k2·(1 + G)/(1 + G + gᵢ), G the gains already there); kept, the plausible fit with the
/// lowest SSE. `None` when `from` has no input lag, or is neither of those forms, or (for the
/// second element) is not plausible. The richer form nests the poorer (gᵢ → 0), so on a stage the
/// poorer one describes the new gain runs to its lower bound and the fit is not plausible.
fn fit_one_more_relaxation(
    from: &AxisModel,
    cand: &Candidate,
    data: &FitData,
) -> Option<(AxisModel, f64, bool)> {
    let (slot, to) = match from.rate_form {
        full::RateForm::InputLag => (0, full::RateForm::LagAndRelaxation),
        full::RateForm::LagAndRelaxation if Plausibility::of(from, cand.effect).plausible() => {
            (1, full::RateForm::LagAndTwoRelaxations)
        }
        _ => return None,
    };
    if !(from.effects.hysteresis_lag_s > 0.0) {
        return None;
    }
    let b = from.bounds;
    let tau_v = f64::from(from.effects.hysteresis_lag_s);
    let g = full::LAG_AND_RELAXATION_START_GAIN;
    let g_there: f64 = from.effects.relaxation_gain[..slot]
        .iter()
        .map(|&x| f64::from(x))
        .sum();
    let fits: Vec<(AxisModel, f64, bool)> = LAG_AND_RELAXATION_STARTS
        .par_iter()
        .filter_map(|&share| {
            let tau_w = share * tau_v;
            if !(tau_w > b.relaxation_tau_s.0 && tau_w < b.relaxation_tau_s.1) {
                return None;
            }
            let mut start = from.clone();
            start.rate_form = to;
            start.map.k2_m_per_h =
                (f64::from(start.map.k2_m_per_h) * (1.0 + g_there) / (1.0 + g_there + g)) as f32;
            start.effects.relaxation_gain[slot] = g as f32;
            start.effects.relaxation_time_constant_s[slot] = tau_w as f32;
            if slot == 0 {
                start.effects.relaxation_linear_m_per_v = start.map.k1_m_per_v;
            }
            let (fitted, sse, _) = refit(&start, data, TRIAL_ITERATIONS);
            let plausible = Plausibility::of(&fitted, cand.effect).plausible();
            Some((fitted, sse, plausible))
        })
        .collect();
    best_fit(fits)
}

/// The candidate fitted on `held` (data held to the sets the compensator accepts) when its
/// unconstrained fit `free` is a set it refuses: the better of the fit from the last set it
/// accepts on the way from the screening's start to `free` ([`last_accepted_on_the_way`]) and
/// [`fit_candidate`] on `held`.
fn fit_held(
    model: &AxisModel,
    cand: &Candidate,
    held: &FitData,
    free: &AxisModel,
    sse0: f64,
    run: Option<&OtherRun>,
) -> (AxisModel, f64) {
    let Some(rate) = held.invertible_at_hz else {
        return fit_candidate(model, cand, held, sse0, run);
    };
    let accepted = |m: &AxisModel| stage::compensator_check(m, rate).is_ok();
    // The start in the form the free fit took (the rate-dependent hysteresis has two).
    let mut base = model.clone();
    base.rate_form = free.rate_form;
    let start = last_accepted_on_the_way(&base.with_effect(cand.init), free, accepted);
    let (on_the_way, sse_way, _) = refit(&start, held, TRIAL_ITERATIONS);
    let (again, sse_again) = fit_candidate(model, cand, held, sse0, run);
    if sse_again < sse_way {
        (again, sse_again)
    } else {
        (on_the_way, sse_way)
    }
}

/// `data` held to the sets the compensator accepts at `rate` \[Hz\].
fn held_to<'a>(data: &FitData<'a>, rate: f32) -> FitData<'a> {
    FitData {
        u: data.u,
        y: data.y,
        other_z: data.other_z,
        from: data.from,
        held_out: data.held_out,
        free_offset: data.free_offset,
        invertible_at_hz: Some(rate),
    }
}

/// Fits, judges and decides one candidate. With `--invertible`, a fit the compensator refuses is
/// fitted again held to the sets it accepts (the Levenberg–Marquardt rejects every step out of
/// them), and judged as that fit, its held-out blocks refitted the same way; if that fit gains
/// nothing in sample, the candidate is refused as not invertible, with both fits' figures and the
/// compensator's refusal.
fn try_candidate(model: &AxisModel, cand: &Candidate, bench: &Bench) -> Trial {
    let (data, sse0) = (bench.data, bench.sse0);
    let n = data.fitted_count() as f64;
    let (mut fitted, mut sse1) = fit_candidate(model, cand, data, sse0, bench.run);
    let rms = |sse: f64| (sse / n).sqrt();
    let mut invertibility = None;
    let mut refused_as_not_invertible = false;
    let constrained = bench.invertible_at_hz.map(|rate| held_to(data, rate));
    let mut fit_data = data;
    if let (Some(rate), Some(held)) = (bench.invertible_at_hz, constrained.as_ref()) {
        if let Err(refusal) = stage::compensator_check(&fitted, rate) {
            let (c, sse_c) = fit_held(model, cand, held, &fitted, sse0, bench.run);
            let free = format!(
                "the fit reaches in-sample RMS {:.4e} m with a set the compensator refuses ({refusal})",
                rms(sse1)
            );
            if sse_c < sse0 && stage::compensator_check(&c, rate).is_ok() {
                invertibility = Some(format!(
                    "{free}; held to the sets it accepts: {:.4e} m",
                    rms(sse_c)
                ));
                (fitted, sse1, fit_data) = (c, sse_c, held);
            } else {
                let held_rms = if sse_c.is_finite() {
                    format!("{:.4e} m, no gain", rms(sse_c))
                } else {
                    "no set".to_string()
                };
                invertibility = Some(format!("{free}; held to the sets it accepts: {held_rms}"));
                refused_as_not_invertible = true;
            }
        }
    }
    let kind = cand.effect;
    let p_new = (fitted.encode().0.len() - model.encode().0.len()) as f64;
    let plausibility = Plausibility::of(&fitted, kind);
    let mut trial = Trial {
        effect: kind,
        form: fitted.form(kind),
        screening: cand.clone(),
        parameters: plausibility
            .checks
            .iter()
            .map(|c| (c.parameter, c.value))
            .collect(),
        rms_before: rms(sse0),
        rms_after: rms(sse1),
        delta_bic: n * (sse1.max(1e-300) / sse0.max(1e-300)).ln() + p_new * n.ln(),
        plausibility,
        out_of_sample: None,
        within_records: None,
        another_run: None,
        invertibility,
        decision: Decision::HoldsNotBest,
        model: fitted,
        sse: sse1,
    };
    let refuse = |r| Decision::Refused(r);
    // Two creep elements where the fit does not need the second: the single element is tried.
    if let EffectInit::Creep {
        gains_m_per_v,
        time_constants_s,
    } = cand.init
    {
        if gains_m_per_v[1] != 0.0 && !trial.plausibility.plausible() {
            let single = Candidate {
                init: EffectInit::Creep {
                    gains_m_per_v: [gains_m_per_v[0], 0.0],
                    time_constants_s,
                },
                ..cand.clone()
            };
            return try_candidate(model, &single, bench);
        }
    }
    if !sse1.is_finite() {
        trial.decision = refuse(Refusal::FitFailed);
    } else if !trial.plausibility.plausible() {
        trial.decision = refuse(Refusal::Implausible);
    } else if sse1 >= sse0 {
        trial.decision = refuse(Refusal::NoInSampleGain);
    } else if refused_as_not_invertible {
        trial.decision = refuse(Refusal::NotInvertible);
    } else {
        let with = held_out_sse(&trial.model, fit_data, bench.blocks);
        let oos = OutOfSample::new(bench.held_without, &with, bench.blocks, bench.t_s);
        let mut holds = oos.holds();
        // Refused by the records only for the consistency of their gains: judged again on
        // blocks within the records (module doc of `select`, "An effect one record shows").
        if let Some(within_blocks) = bench.within_records.filter(|_| !holds) {
            if oos.none_worse_and_pooled_gain() {
                let without = bench
                    .within_without
                    .get_or_init(|| held_out_sse(model, fit_data, within_blocks));
                let with = held_out_sse(&trial.model, fit_data, within_blocks);
                let within = OutOfSample::new(without, &with, within_blocks, bench.t_s);
                holds = within.holds();
                trial.within_records = Some(within);
            }
        }
        trial.out_of_sample = Some(oos);
        if !holds {
            trial.decision = refuse(Refusal::NotOutOfSample);
        } else if let Some(run) = bench.run {
            let gain = RunGain {
                rms_zeroed_without: run.rms_zeroed(model),
                rms_zeroed_with: run.rms_zeroed(&trial.model),
            };
            trial.another_run = Some(gain);
            if !gain.holds() {
                trial.decision = refuse(Refusal::WorseOnAnotherRun);
            }
        }
    }
    trial
}

/// The search's result on one axis.
struct AxisSearch {
    /// The final model.
    model: AxisModel,
    /// The decision log.
    steps: Vec<Step>,
    /// Sensor noise estimate \[m\].
    noise_m: f64,
    /// Held-out RMS (cross-validation) of the base and the final model \[m\].
    held_out_rms: (f64, f64),
    /// How the held-out blocks were chosen, in words.
    held_out_method: String,
}

/// One axis's search problem: the record, its fitted data and held-out blocks, the settings and
/// the other run.
struct Search<'a> {
    /// Axis name (`x`, `y`).
    name: &'a str,
    /// The fitted record.
    record: &'a Record,
    /// The other axis's z (two-axis records).
    other_z: Option<&'a [f64]>,
    /// The run's settings.
    s: &'a CloseLoopSettings,
    /// The run candidates must not predict worse (`--validate`).
    run: Option<&'a OtherRun>,
    /// The data every model is fitted on.
    data: FitData<'a>,
    /// The held-out blocks (cross-validation).
    blocks: Vec<full::Block>,
    /// With several records, the blocks within them ([`select::interleaved_folds`]).
    within_records: Option<Vec<full::Block>>,
    /// Number of scored samples.
    n_scored: f64,
}

impl Search<'_> {
    /// y − ŷ over the scored samples.
    fn residual(&self, sim: &Simulation) -> Vec<f64> {
        (self.data.from..self.data.u.len())
            .map(|k| self.record.y_m[k] - sim.y[k])
            .collect()
    }

    /// The RMS over the scored samples of an SSE.
    fn rms(&self, sse: f64) -> f64 {
        (sse / self.n_scored).sqrt()
    }

    /// A progress line.
    fn log(&self, msg: impl AsRef<str>) {
        log(self.s.progress, format!("{}: {}", self.name, msg.as_ref()));
    }

    /// The effects allowed and not yet in `model` screened on the residual of its simulation `sim`,
    /// best first.
    fn screen(&self, model: &AxisModel, sim: &Simulation) -> Vec<Candidate> {
        let remaining: Vec<EffectKind> = self
            .s
            .allowed
            .iter()
            .copied()
            .filter(|e| !model.added.contains(e))
            .filter(|e| *e != EffectKind::Coupling || self.other_z.is_some())
            .collect();
        let signals = Signals {
            t_s: &self.record.t_s,
            u: &self.record.u,
            y: &self.record.y_m,
            y_hat: &sim.y,
            h: &sim.h,
            other_y_hat: self.other_z,
            from: self.data.from,
            sample_period_s: self.record.sample_period_s(),
            segments: &self.record.segments,
        };
        if remaining.is_empty() {
            Vec::new()
        } else {
            screen(&signals, &remaining)
        }
    }

    /// Each of `chosen` fitted and judged against `model` (SSE `current_sse`, held-out SSE
    /// `held_without`).
    fn trials(
        &self,
        model: &AxisModel,
        chosen: &[&Candidate],
        held_without: &[f64],
        current_sse: f64,
    ) -> Vec<Trial> {
        let bench = Bench {
            data: &self.data,
            blocks: &self.blocks,
            held_without,
            within_records: self.within_records.as_deref(),
            within_without: std::cell::OnceCell::new(),
            sse0: current_sse,
            run: self.run,
            t_s: &self.record.t_s,
            invertible_at_hz: invertible_at_hz(self.record, self.s),
        };
        let mut trials = Vec::new();
        for cand in chosen {
            let started = Instant::now();
            let trial = try_candidate(model, cand, &bench);
            self.log(format!(
                "{} ({:.1} s)",
                trial.words(),
                started.elapsed().as_secs_f64()
            ));
            trials.push(trial);
        }
        trials
    }

    /// An effect added earlier that `added` makes redundant (refitted without it, within 1 % RMS,
    /// and with `--invertible` a set the compensator accepts) is taken out again, a step logged
    /// for each; returns the model and its SSE.
    fn prune(
        &self,
        mut model: AxisModel,
        mut current_sse: f64,
        added: EffectKind,
        floor: Floor,
        steps: &mut Vec<Step>,
    ) -> (AxisModel, f64) {
        for kind in model.added.clone().into_iter().filter(|k| *k != added) {
            let (pruned, sse_p, _) =
                refit(&model.without_effect(kind), &self.data, TRIAL_ITERATIONS);
            let rms_p = self.rms(sse_p);
            let accepted = invertible_at_hz(self.record, self.s)
                .is_none_or(|rate| stage::compensator_check(&pruned, rate).is_ok());
            if accepted && rms_p.is_finite() && rms_p < 1.01 * self.rms(current_sse) {
                steps.push(Step {
                    axis: self.name.into(),
                    number: steps.len() + 1,
                    rms_before: self.rms(current_sse),
                    floor,
                    screened: Vec::new(),
                    not_tried: Vec::new(),
                    trials: Vec::new(),
                    outcome: StepOutcome::Removed {
                        effect: kind,
                        rms_without: rms_p,
                    },
                });
                self.log(format!("removed {}", kind.name()));
                model = pruned;
                current_sse = sse_p;
            }
        }
        (model, current_sse)
    }
}

/// Held-out gains (pooled relative MSE reductions) within this of the largest are a tie.
const HELD_OUT_TIE: f64 = 0.02;

/// The trial that holds with the largest held-out gain (for a trial judged within the records,
/// its gain there: the records' pooled gain dilutes an effect that one record shows). Candidates
/// whose gains are within [`HELD_OUT_TIE`] of it (two percentage points: closer than the blocks'
/// spread can tell apart) are a tie, decided by the lower in-sample ΔBIC: the effect that explains
/// the whole fitted record better.
///
/// With a `--validate` record, every trial that holds has been scored on it too, and the one that
/// predicts it best is added: the held-out blocks come from the fitted records' own conditions,
/// the other run from those the stage file is for (another rate, another session), and two forms
/// that both hold on the blocks can extrapolate to it very differently (the gain is
/// 1 − (RMS with / RMS without)², zeroed RMS). Trials within [`HELD_OUT_TIE`] of the best gain
/// on the other run are a tie, decided by the rule above.
fn best_trial(trials: &[Trial]) -> Option<usize> {
    let gain = |t: &Trial| {
        t.within_records
            .as_ref()
            .or(t.out_of_sample.as_ref())
            .map_or(0.0, |o| o.relative_gain)
    };
    let run_gain = |t: &Trial| t.another_run.map_or(0.0, |r| r.gain());
    let holding = || {
        trials
            .iter()
            .enumerate()
            .filter(|(_, t)| t.decision == Decision::HoldsNotBest)
    };
    let top_run = holding()
        .map(|(_, t)| run_gain(t))
        .fold(f64::NEG_INFINITY, f64::max);
    let contenders = || holding().filter(|(_, t)| run_gain(t) >= top_run - HELD_OUT_TIE);
    let top = contenders()
        .map(|(_, t)| gain(t))
        .fold(f64::NEG_INFINITY, f64::max);
    contenders()
        .filter(|(_, t)| gain(t) >= top - HELD_OUT_TIE)
        .min_by(|a, b| a.1.delta_bic.total_cmp(&b.1.delta_bic))
        .map(|(i, _)| i)
}

/// Runs the search on one axis; `other_z` is the other axis's z (two-axis records).
fn close_axis(
    name: &str,
    record: &Record,
    other_z: Option<&[f64]>,
    s: &CloseLoopSettings,
    base: AxisModel,
    run: Option<&OtherRun>,
) -> crate::Result<AxisSearch> {
    let from = record.index_at(s.start_s);
    let u: Vec<f32> = record.u.iter().map(|&v| v as f32).collect();
    let ts = record.sample_period_s();
    let f_dom = diagnose::dominant_frequency_hz(&record.u[from..], ts);
    let mut within_records = (record.segments.len() > 1)
        .then(|| select::interleaved_folds(from, u.len(), ts, f_dom))
        .flatten();
    // Several records: leave one record out (and blocks within them for an effect one record
    // shows); one record: blocks over time, interleaved when the input is not stationary.
    // Records too unequal for leave-one-record-out take the blocks within them (when there are).
    let unequal = select::unequal_records(from, &record.segments, u.len())
        .and_then(|lengths| Some((lengths, within_records.take()?)));
    let judged_within_unequal = unequal.is_some();
    let (blocks, mut held_out_method) = if let Some(((index, shortest, longest), within)) = unequal
    {
        let short = record.sources.get(index).map_or_else(
            || format!("record {}", index + 1),
            |p| p.display().to_string(),
        );
        (
            within,
            format!(
                "blocks within the records (interleaved one-period segments of every record), \
                 not leave one record out: {short} holds {shortest} scored samples, less than \
                 {:.0} % of the longest record's {longest}, so a model refitted without the \
                 longest would stand on too little of the data",
                100.0 * select::MIN_RECORD_SHARE
            ),
        )
    } else if record.segments.len() > 1 {
        (
            select::record_folds(from, &record.segments, u.len()),
            format!(
                "leave one record out: each record predicted by the model refitted on the others{}",
                if within_records.is_some() {
                    "; an effect the records refuse only for the consistency of their gains is \
                     judged again on blocks within the records"
                } else {
                    ""
                }
            ),
        )
    } else {
        select::single_record_folds(&record.u, from, ts, f_dom)
    };
    let mut search = Search {
        name,
        record,
        other_z,
        s,
        run,
        data: FitData {
            u: &u,
            y: &record.y_m,
            other_z,
            from,
            held_out: None,
            free_offset: base.free_offset,
            invertible_at_hz: None,
        },
        blocks,
        within_records,
        n_scored: (u.len() - from) as f64,
    };
    let mut model = base.clone();
    // With free offsets the residual the screening reads has each record's own offset removed.
    let simulate = |m: &AxisModel| -> crate::Result<Simulation> {
        let mut sim = m.simulate(&u, other_z)?;
        if m.free_offset {
            full::add_record_offsets(&mut sim.y, &record.y_m, &m.segments, |k| k >= from);
        }
        Ok(sim)
    };
    let mut sim = simulate(&model)?;
    let noise_m = noise_estimate(&search.residual(&sim));
    let mut current_sse = sse(&model, &search.data);
    let mut base_held = held_out_sse(&model, &search.data, &search.blocks);
    let mut held = Some(base_held.clone());
    let mut steps = Vec::new();
    search.log(format!(
        "base model rms {:.4e} m, sensor noise estimate {noise_m:.4e} m",
        search.rms(current_sse)
    ));
    if judged_within_unequal {
        search.log(format!("held out: {held_out_method}"));
    }
    loop {
        let floor = Floor {
            residual: ResidualFigures::of(&search.residual(&sim)),
            noise_m,
        };
        let mut step = Step {
            axis: name.into(),
            number: steps.len() + 1,
            rms_before: search.rms(current_sse),
            floor,
            screened: Vec::new(),
            not_tried: Vec::new(),
            trials: Vec::new(),
            outcome: StepOutcome::Stopped(Stop::NoiseFloor),
        };
        if floor.reached() {
            search.log(step.words());
            steps.push(step);
            break;
        }
        let candidates = search.screen(&model, &sim);
        step.screened = candidates
            .iter()
            .map(|c| (c.effect, c.init.form(), c.share, c.delta_bic))
            .collect();
        let (tried, mut skipped) = choose::choose(&candidates, 0.25 * s.min_share, MAX_TRIALS);
        skipped.extend(choose::not_screened(
            &s.allowed,
            &model.added,
            other_z.is_some(),
            &candidates,
        ));
        step.not_tried = skipped;
        let chosen: Vec<&Candidate> = tried.iter().map(|&(i, _)| &candidates[i]).collect();
        if chosen.is_empty() {
            step.outcome = StepOutcome::Stopped(Stop::NoCandidates);
            search.log(step.words());
            steps.push(step);
            break;
        }
        let held_without = held
            .get_or_insert_with(|| held_out_sse(&model, &search.data, &search.blocks))
            .clone();
        step.trials = search.trials(&model, &chosen, &held_without, current_sse);
        let Some(best) = best_trial(&step.trials) else {
            step.outcome = StepOutcome::Stopped(Stop::NothingHolds);
            search.log("nothing holds");
            steps.push(step);
            break;
        };
        step.trials[best].decision = Decision::Added;
        let chosen = &step.trials[best];
        model = chosen.model.clone();
        current_sse = chosen.sse;
        held = None;
        step.outcome = StepOutcome::Added {
            effect: chosen.effect,
            form: chosen.form.clone(),
            rms_after: search.rms(current_sse),
        };
        let added = chosen.effect;
        let judged_within = chosen.within_records.is_some();
        search.log(format!("added {}", chosen.label()));
        steps.push(step);
        // An effect only blocks within the records confirmed needs every record to be identified:
        // leaving a record out would also lose it, so every later effect is judged within the
        // records (module doc of `select`, "An effect one record shows").
        if judged_within {
            if let Some(within) = search.within_records.take() {
                search.blocks = within;
                base_held = held_out_sse(&base, &search.data, &search.blocks);
                search.log("from now on every effect is judged on the blocks within the records");
                held_out_method.push_str(
                    "; after an effect judged within the records was added, every later effect \
                     (and the held-out RMS) on the blocks within the records",
                );
            }
        }
        (model, current_sse) = search.prune(model, current_sse, added, floor, &mut steps);
        sim = simulate(&model)?;
    }
    let held_final = held.unwrap_or_else(|| held_out_sse(&model, &search.data, &search.blocks));
    let rms_of = |v: &[f64]| (v.iter().sum::<f64>() / search.n_scored).sqrt();
    let held_out_rms = (rms_of(&base_held), rms_of(&held_final));
    Ok(AxisSearch {
        model,
        steps,
        noise_m,
        held_out_rms,
        held_out_method,
    })
}

/// [`close_axis`] from the base `base.0`; with `--invertible`, when that search ends at a set the
/// compensator refuses and there is a base held to the sets it accepts (`base.1`), the search runs
/// again from that base, which becomes the axis's base (`base.0`). The first search's steps are
/// kept in the log, followed by a step that says why it was not taken.
fn search_axis(
    name: &str,
    record: &Record,
    other_z: Option<&[f64]>,
    s: &CloseLoopSettings,
    base: (&mut AxisModel, Option<&AxisModel>),
    run: Option<&OtherRun>,
) -> crate::Result<AxisSearch> {
    let (free, held) = base;
    let first = close_axis(name, record, other_z, s, free.clone(), run)?;
    let (Some(rate), Some(held)) = (invertible_at_hz(record, s), held) else {
        return Ok(first);
    };
    let Err(refusal) = stage::compensator_check(&first.model, rate) else {
        return Ok(first);
    };
    log(
        s.progress,
        format!(
            "{name}: the search from the base fitted without the constraint ended at a set the \
             compensator refuses; searching again from the base held to the sets it accepts"
        ),
    );
    let mut second = close_axis(name, record, other_z, s, held.clone(), run)?;
    let mut steps = first.steps;
    if let Some(last) = steps.last() {
        steps.push(Step {
            axis: name.into(),
            number: steps.len() + 1,
            rms_before: last.rms_before,
            floor: last.floor,
            screened: Vec::new(),
            not_tried: Vec::new(),
            trials: Vec::new(),
            outcome: StepOutcome::Restarted {
                refusal: refusal.to_string(),
            },
        });
    }
    for step in &mut second.steps {
        step.number += steps.len();
    }
    steps.append(&mut second.steps);
    second.steps = steps;
    *free = held.clone();
    Ok(second)
}

/// Runs `close-loop` on one record per axis (same times).
pub fn close_loop(records: &[Record], s: &CloseLoopSettings) -> Result<Outcome, CloseLoopError> {
    close_loop_validated(records, s, None)
}

/// [`close_loop`] with another run (`--validate`: one record per axis and its first scored time)
/// that no added effect may predict worse.
pub fn close_loop_validated(
    records: &[Record],
    s: &CloseLoopSettings,
    other: Option<(&[Record], f64)>,
) -> Result<Outcome, CloseLoopError> {
    let from = records[0].index_at(s.start_s);
    if records[0].u.len() < from + 10 * select::FOLDS {
        return Err(CloseLoopError::TooFewSamples { start_s: s.start_s });
    }
    let mut bases = Vec::new();
    let mut held_bases = Vec::new();
    for (i, r) in records.iter().enumerate() {
        log(s.progress, format!("axis {i}: identifying the base model"));
        let (free, held) = base_model(r, s)?;
        bases.push(free);
        held_bases.push(held);
    }
    let f32s = |r: &Record| -> Vec<f32> { r.u.iter().map(|&v| v as f32).collect() };
    let run_of = |i: usize, other_z: Option<Vec<f64>>| -> Option<OtherRun> {
        let (recs, start) = other?;
        let r = recs.get(i)?;
        Some(OtherRun {
            u: f32s(r),
            y: r.y_m.clone(),
            from: r.index_at(start),
            other_z,
        })
    };
    let names = ["x", "y"];
    let mut finals: Vec<AxisSearch> = Vec::new();
    // The other axis's z each axis was searched with (coupling), for its uncertainty.
    let mut coupled: Vec<Option<Vec<f64>>> = vec![None; records.len()];
    if records.len() == 1 {
        finals.push(search_axis(
            names[0],
            &records[0],
            None,
            s,
            (&mut bases[0], held_bases[0].as_ref()),
            run_of(0, None).as_ref(),
        )?);
    } else {
        // x couples to y's base model, then y to x's final model.
        let z_y = bases[1].simulate(&f32s(&records[1]), None)?.z;
        let other_run = |i: usize, m: &AxisModel| -> Option<Vec<f64>> {
            let (recs, _) = other?;
            m.simulate(&f32s(recs.get(i)?), None).ok().map(|s| s.z)
        };
        let run = run_of(0, other_run(1, &bases[1]));
        finals.push(search_axis(
            names[0],
            &records[0],
            Some(&z_y),
            s,
            (&mut bases[0], held_bases[0].as_ref()),
            run.as_ref(),
        )?);
        let z_x = finals[0].model.simulate(&f32s(&records[0]), None)?.z;
        let run = run_of(1, other_run(0, &finals[0].model));
        finals.push(search_axis(
            names[1],
            &records[1],
            Some(&z_x),
            s,
            (&mut bases[1], held_bases[1].as_ref()),
            run.as_ref(),
        )?);
        coupled = vec![Some(z_y), Some(z_x)];
    }
    // The uncertainty of each final fit, on the data it was fitted on.
    let uncertainty: Vec<crate::Result<Uncertainty>> = finals
        .iter()
        .zip(records)
        .zip(&coupled)
        .map(|((f, r), z)| {
            let u = f32s(r);
            let data = FitData {
                u: &u,
                y: &r.y_m,
                other_z: z.as_deref(),
                from,
                held_out: None,
                free_offset: f.model.free_offset,
                invertible_at_hz: None,
            };
            full::linearise(&f.model, &data).and_then(|l| crate::uncertainty::estimate(&l))
        })
        .collect();
    // The predictions of the fitted record through piezo-stage's chain (each record from rest,
    // with its own offset when offsets are free; the stage file keeps the first record's).
    let us: Vec<Vec<f32>> = records.iter().map(f32s).collect();
    for f in finals.iter_mut() {
        hold_first_record_offset(&mut f.model, &records[0], &us[0], from)?;
    }
    let before = predict_records(&bases.iter().collect::<Vec<_>>(), &us, &records[0])?;
    let after = predict_records(
        &finals.iter().map(|f| &f.model).collect::<Vec<_>>(),
        &us,
        &records[0],
    )?;
    let (mut before, mut after) = (before, after);
    for (i, r) in records.iter().enumerate() {
        if bases[i].free_offset {
            full::add_record_offsets(&mut before[i], &r.y_m, &r.segments, |k| k >= from);
            full::add_record_offsets(&mut after[i], &r.y_m, &r.segments, |k| k >= from);
        }
    }
    let mut axes = Vec::new();
    let (mut all_y, mut all_b, mut all_a) = (Vec::new(), Vec::new(), Vec::new());
    let per_axis = finals.into_iter().zip(bases).zip(records).zip(uncertainty);
    for (i, (((found, base), r), uncertainty)) in per_axis.enumerate() {
        let AxisSearch {
            model,
            steps,
            noise_m,
            held_out_rms,
            held_out_method,
        } = found;
        all_y.extend_from_slice(&r.y_m[from..]);
        all_b.extend_from_slice(&before[i][from..]);
        all_a.extend_from_slice(&after[i][from..]);
        let per_record = r
            .segment_ranges()
            .into_iter()
            .zip(&r.sources)
            .map(|((a, b), src)| {
                let a = a.max(from).min(b);
                RecordFits {
                    data: src.display().to_string(),
                    before: Fit::of(&r.y_m[a..b], &before[i][a..b]),
                    after: Fit::of(&r.y_m[a..b], &after[i][a..b]),
                }
            })
            .collect();
        axes.push(AxisOutcome {
            records: per_record,
            name: names[i].into(),
            fit_before: Fit::of(&r.y_m[from..], &before[i][from..]),
            fit_after: Fit::of(&r.y_m[from..], &after[i][from..]),
            base,
            model,
            steps,
            noise_m,
            input_range_v: min_max(&r.u),
            envelope: {
                let p = crate::identify::record_envelope(r, piezo_stage::Provenance::default());
                (p.input_rate_max_v_per_s, p.band_hz)
            },
            before: before[i].clone(),
            after: after[i].clone(),
            held_out_rms,
            held_out_method,
            uncertainty,
        });
    }
    let mut outcome = Outcome {
        axes,
        from,
        window_s: (
            records[0].t_s[from],
            records[0].t_s[records[0].t_s.len() - 1],
        ),
        data: records[0].path.display().to_string(),
        before: Fit::of(&all_y, &all_b),
        after: Fit::of(&all_y, &all_a),
        validation: None,
    };
    if let Some((recs, start)) = other {
        outcome.validation = Some(validate(&outcome, recs, start)?);
    }
    Ok(outcome)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::json_keys as keys;
    use std::collections::BTreeSet;

    /// One axis that added creep in one step, with a `--validate` record.
    fn outcome() -> Outcome {
        let fit = |rms: f64| Fit {
            rms,
            rms_zeroed: 0.9 * rms,
            offset: 1e-9,
            max_abs: 3.0 * rms,
            r2: 0.999,
        };
        let model = report::tests::model();
        let axis = AxisOutcome {
            name: "x".into(),
            base: AxisModel {
                added: Vec::new(),
                effects: Default::default(),
                ..model.clone()
            },
            model,
            steps: vec![report::tests::step()],
            noise_m: 2e-9,
            input_range_v: (0.0, 20.0),
            envelope: (None, None),
            before: vec![0.0; 1000],
            after: vec![0.0; 1000],
            fit_before: fit(2e-7),
            fit_after: fit(1e-7),
            held_out_rms: (2.1e-7, 1.1e-7),
            held_out_method: "blocked".into(),
            records: vec![RecordFits {
                data: "record.csv".into(),
                before: fit(2e-7),
                after: fit(1e-7),
            }],
            uncertainty: Err(crate::Error::Fit("singular".into())),
        };
        Outcome {
            axes: vec![axis],
            from: 100,
            window_s: (0.1, 1.0),
            data: "record.csv".into(),
            before: fit(2e-7),
            after: fit(1e-7),
            validation: None,
        }
    }

    /// The outcome serialises with the keys of the report: per axis its effects, scores,
    /// held-out RMS, records, both parameter sets and the uncertainty's keys beside them; the
    /// validation only when there is one.
    #[test]
    fn an_outcome_serialises_with_the_keys_of_the_report() {
        let o = outcome();
        let json = crate::to_json(&o.report()).unwrap();
        let top = BTreeSet::from([
            "unit",
            "data",
            "window_s",
            "samples",
            "base_model",
            "before",
            "after",
            "effects_added",
            "steps",
            "words",
            "axes",
        ]);
        assert_eq!(keys(&json), top);
        assert_eq!(json["unit"], "m");
        assert_eq!(json["samples"], 900);
        assert_eq!(json["window_s"], serde_json::json!([0.1, 1.0]));
        assert_eq!(json["effects_added"], serde_json::json!(["creep"]));
        assert_eq!(json["steps"][0]["outcome"], "added");
        assert_eq!(json["words"][0], o.axes[0].steps[0].words().as_str());
        let fit = BTreeSet::from(["rms", "rms_zeroed", "offset", "max_abs", "r2"]);
        assert_eq!(keys(&json["before"]), fit);
        let axis = &json["axes"][0];
        assert_eq!(
            keys(axis),
            BTreeSet::from([
                "axis",
                "effects_added",
                "noise_estimate_m",
                "before",
                "after",
                "held_out",
                "records",
                "base_params",
                "params",
                "uncertainty",
                "correlation",
                "prediction_band_rms_m",
                "uncertainty_not_computed",
            ])
        );
        assert_eq!(
            axis["effects_added"],
            serde_json::json!([{"effect": "creep", "form": "Kelvin-Voigt, 1 element"}])
        );
        assert_eq!(
            keys(&axis["held_out"]),
            BTreeSet::from(["rms_before", "rms_after", "method"])
        );
        assert_eq!(
            keys(&axis["records"][0]),
            BTreeSet::from(["data", "before", "after"])
        );
        assert_eq!(keys(&axis["records"][0]["after"]), fit);
        let params = BTreeSet::from([
            "bouc_wen",
            "static_map",
            "effects",
            "input_range_v",
            "sample_period_s",
        ]);
        assert_eq!(keys(&axis["params"]), params);
        assert_eq!(keys(&axis["base_params"]), params);
        assert_eq!(
            keys(&axis["params"]["bouc_wen"]),
            BTreeSet::from(["a", "beta", "gamma", "n"])
        );
        assert_eq!(
            keys(&axis["params"]["static_map"]),
            BTreeSet::from(["k1_m_per_v", "k2_m_per_h", "offset_m"])
        );
        assert_eq!(
            axis["params"]["effects"],
            serde_json::to_value(o.axes[0].model.effects).unwrap()
        );
        assert_eq!(
            axis["params"]["input_range_v"],
            serde_json::json!([0.0, 20.0])
        );
        assert!(axis["uncertainty"].is_null());
        assert_eq!(axis["uncertainty_not_computed"], "singular");

        let validated = Outcome {
            validation: Some(Validation {
                data: "check.csv".into(),
                start_s: 0.0,
                samples: 500,
                before: o.before,
                after: o.after,
                axes: Vec::new(),
            }),
            ..outcome()
        };
        let json = crate::to_json(&validated.report()).unwrap();
        let mut with_validation = top.clone();
        with_validation.insert("validation");
        assert_eq!(keys(&json), with_validation);
        assert_eq!(json["validation"]["data"], "check.csv");
    }
}
