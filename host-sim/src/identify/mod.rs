//! `identify` and `predict`: fit a piezo-core model to a recorded (u, y) and validate it on new data.
//!
//! Records are CSV files with unit-suffixed columns (`t_s`, `u_V` or `u_N`, `y_m`, `y_um`, `y_nm`);
//! values are converted to SI on reading. The model always starts at rest at the first sample and is
//! simulated over the whole record (it sees only u); the fit and the reported measures use the samples
//! from `--start` on, so that a start-up transient warms the state up without being scored.
//!
//! Methods ([`fit`]): `vp-de-lm` (the default: variable projection, differential evolution,
//! Levenberg–Marquardt) and `ga` (seed 001's genetic algorithm as published: Case I for the symmetric
//! model; Case I, then δ (Case II, `--no-shift`) or δ and φ (Case III) with the six held, for the
//! asymmetric model) and `two-step` (seed 000's two-step method for the dynamic model, [`two_step`]:
//! mechanics from a ramp-edged square wave `--mech-data`, then the hysteresis from the sine `--data`;
//! it falls back to `vp-de-lm` when the data leave its β + γ < 0 assumption).

pub mod fit;
pub mod linearise;
pub mod model;
pub mod oscillator;
pub mod output_filter;
pub mod predict;
pub mod two_step;

use crate::csv::{read_rows, Table};
use crate::to_json;
use crate::uncertainty::Uncertainty;
use fit::{Problem, Progress, TracePoint};
use model::{to_axis, Identified, ModelKind};
use serde_json::json;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Identification methods.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Method {
    /// Variable projection + differential evolution + Levenberg–Marquardt (default).
    VpDeLm,
    /// Seed 001's genetic algorithm as published.
    Ga,
    /// Seed 000's two-step method (dynamic model; needs `--mech-data`).
    TwoStep,
}

impl Method {
    /// Name in reports.
    pub fn name(self) -> &'static str {
        match self {
            Self::VpDeLm => "vp-de-lm",
            Self::Ga => "ga",
            Self::TwoStep => "two-step",
        }
    }
}

/// A record in SI units.
#[derive(Debug, Clone)]
pub struct Record {
    /// Source file.
    pub path: PathBuf,
    /// Times \[s\].
    pub t_s: Vec<f64>,
    /// Input \[V\] or \[N\].
    pub u: Vec<f64>,
    /// Output \[m\].
    pub y_m: Vec<f64>,
    /// The first sample of each record when several records of one stage are held end to end
    /// (`[0]` for one): every model starts from rest at each ([`Record::concatenate`]).
    pub segments: Vec<usize>,
    /// The files of the records (one per segment).
    pub sources: Vec<PathBuf>,
}

pub use crate::csv::{unit_of, Quantity};

/// SI factor of a column's unit suffix ([`unit_of`]).
pub fn unit_factor(name: &str) -> Option<f64> {
    unit_of(name).map(|(f, _)| f)
}

fn pick(table: &Table, given: Option<&str>, prefix: &str, flag: &str) -> crate::Result<String> {
    if let Some(name) = given {
        table
            .column(name)
            .map_err(|e| crate::Error::Usage(format!("{flag}: {e}")))?;
        return Ok(name.to_string());
    }
    table
        .names
        .iter()
        .find(|n| n.starts_with(prefix))
        .cloned()
        .ok_or_else(|| {
            crate::Error::Usage(format!(
                "{}: no `{prefix}*` column (columns: {}); name one with {flag}",
                table.path.display(),
                table.names.join(", ")
            ))
        })
}

/// The SI factor of column `name`'s unit, which must measure one of `wanted`, or an error naming
/// the file, the column, the flag and what the suffix is: none, unknown, or of another quantity.
fn si_factor(path: &Path, name: &str, flag: &str, wanted: &[Quantity]) -> crate::Result<f64> {
    let expected = wanted
        .iter()
        .map(|q| q.name())
        .collect::<Vec<_>>()
        .join(" or ");
    let why = match (name.rsplit_once('_'), unit_of(name)) {
        (_, Some((factor, q))) if wanted.contains(&q) => return Ok(factor),
        (_, Some((_, q))) => format!("its unit is {}, {flag} needs {expected}", q.name()),
        (Some((_, unit)), None) => format!("its unit suffix `{unit}` is unknown"),
        (None, None) => "it has no unit suffix (`name_unit`)".to_string(),
    };
    Err(crate::Error::Usage(format!(
        "{flag}: {}: column `{name}`: {why} (units: {})",
        path.display(),
        crate::csv::unit_names(wanted)
    )))
}

/// Warnings for a record whose values look read in the wrong unit: an output span outside
/// [`PLAUSIBLE_STROKE_M`] or an input span outside [`PLAUSIBLE_INPUT_SPAN_V`] (volts only), each
/// naming the column and the unit it was read with; and for a record whose input never moves
/// (nothing of the hysteresis in it: its output's moves are noise, drift or another input's).
pub fn scale_warnings(
    path: &Path,
    u_name: &str,
    u: &[f64],
    y_name: &str,
    y_m: &[f64],
) -> Vec<String> {
    // (column, values, quantity checked, plausible span, SI unit, what it would be implausible for)
    let checks = [
        (
            y_name,
            y_m,
            Quantity::Length,
            PLAUSIBLE_STROKE_M,
            "m",
            "a piezo stage's stroke",
        ),
        (
            u_name,
            u,
            Quantity::Voltage,
            PLAUSIBLE_INPUT_SPAN_V,
            "V",
            "a piezo drive",
        ),
    ];
    let (u_min, u_max) = min_max(u);
    let constant = (u_max == u_min).then(|| {
        format!(
            "{}: column `{u_name}` is constant ({u_min} over {} samples): the record holds \
             nothing of the hysteresis, and every model of the input sees its output's moves as \
             error; is it the input column?",
            path.display(),
            u.len()
        )
    });
    checks
        .into_iter()
        .filter_map(|(name, values, quantity, (lo, hi), unit, what)| {
            let (min, max) = min_max(values);
            let span = max - min;
            let checked = unit_of(name).is_some_and(|(_, q)| q == quantity);
            let suffix = name.rsplit_once('_').map_or("", |(_, s)| s);
            (checked && span.is_finite() && span > 0.0 && !(lo..=hi).contains(&span)).then(|| {
                format!(
                    "{}: column `{name}` spans {span:.3e} {unit} as read with its unit suffix \
                     `_{suffix}`: outside {lo:.0e}–{hi:.0e} {unit}, implausible for {what}; are \
                     its values in the unit its name says?",
                    path.display()
                )
            })
        })
        .chain(constant)
        .collect()
}

/// The input columns a record of `data` (its first file, when several are comma-separated) is
/// read with: `u` split at its commas (`--u`), or else the header's first `u_*` column (what
/// [`Record::read_axes`] picks); empty when the header cannot be read.
pub fn input_columns(data: &Path, u: Option<&str>) -> Vec<String> {
    if let Some(u) = u {
        return u.split(',').map(|p| p.trim().to_string()).collect();
    }
    let text = data.to_string_lossy();
    let first = Path::new(text.split(',').next().unwrap_or_default().trim());
    let header = std::fs::File::open(first).ok().and_then(|f| {
        use std::io::BufRead;
        std::io::BufReader::new(f)
            .lines()
            .map_while(Result::ok)
            .find(|l| !l.trim().is_empty() && !l.starts_with('#'))
    });
    header
        .and_then(|h| {
            h.trim_start_matches('\u{feff}')
                .split(',')
                .map(str::trim)
                .find(|n| n.starts_with("u_"))
                .map(str::to_string)
        })
        .into_iter()
        .collect()
}

/// Warnings for records whose input, in volts, leaves the drive range of the io chain `io`
/// (`dac_range_v × amplifier_gain_v_per_v`, of the stage file `stage`) by more than 0.1 % of it:
/// the stage could not have been driven there, so the column is in another unit than its suffix
/// says or `[io]` is not the stage's. Each names the file, the column and its suffix; `u_names`
/// are the records' input columns ([`input_columns`]).
pub fn drive_warnings(
    path: &Path,
    u_names: &[String],
    records: &[Record],
    io: &piezo_stage::Io,
    stage: &Path,
) -> Vec<String> {
    let (lo, hi) = io.chain().drive_range_v();
    let (lo, hi) = (f64::from(lo), f64::from(hi));
    let slack = 1e-3 * (hi - lo).abs();
    u_names
        .iter()
        .zip(records)
        .filter(|(name, _)| unit_of(name).is_some_and(|(_, q)| q == Quantity::Voltage))
        .filter_map(|(name, r)| {
            let (min, max) = min_max(&r.u);
            let suffix = name.rsplit_once('_').map_or("", |(_, s)| s);
            (min < lo - slack || max > hi + slack).then(|| {
                format!(
                    "{}: column `{name}` spans {min:.4}–{max:.4} V as read with its unit suffix \
                     `_{suffix}`: beyond the {lo}–{hi} V the io chain of {} drives \
                     (io.dac_range_v × io.amplifier_gain_v_per_v); are its values in the unit its \
                     name says, and is that [io] your stage's?",
                    path.display(),
                    stage.display()
                )
            })
        })
        .collect()
}

/// Output spans a piezo stage's record plausibly has \[m\]: the stroke the stage file's
/// validation accepts.
pub use piezo_stage::PLAUSIBLE_STROKE_M;
/// Input spans a piezo drive plausibly has \[V\]: 10 mV to 10 kV.
pub const PLAUSIBLE_INPUT_SPAN_V: (f64, f64) = (1e-2, 1e4);

impl Record {
    /// Reads a one-axis record; columns default to the first `t_*`, `u_*` and `y_*` of the header.
    pub fn read(
        path: &Path,
        t: Option<&str>,
        u: Option<&str>,
        y: Option<&str>,
    ) -> crate::Result<Self> {
        let mut records = Self::read_axes(path, t, u, y)?;
        if records.len() != 1 {
            return Err(crate::Error::Usage(format!(
                "{}: one axis expected, --u and --y name {}",
                path.display(),
                records.len()
            )));
        }
        Ok(records.remove(0))
    }

    /// Reads one record per axis from one CSV file, the one reader of every record the tools
    /// fit or score: `t` names the time column, `u` and `y` the input and output columns, two
    /// comma-separated each for a two-axis record (defaults: the first `t_*`, `u_*`, `y_*`).
    /// Values are converted to SI. The time column must be a uniform sampling time base
    /// ([`crate::csv::Rows::time`]: strictly increasing, no gap or jump, every step within 1.5
    /// times the median); inputs must be finite in the core's f32; at least 10 samples. Every
    /// error names the file, and a bad value its line and column.
    pub fn read_axes(
        path: &Path,
        t: Option<&str>,
        u: Option<&str>,
        y: Option<&str>,
    ) -> crate::Result<Vec<Self>> {
        let split = |v: Option<&str>| -> Vec<Option<String>> {
            match v {
                None => vec![None],
                Some(s) => s.split(',').map(|p| Some(p.trim().to_string())).collect(),
            }
        };
        let (us, ys) = (split(u), split(y));
        if us.len() != ys.len() || us.len() > 2 {
            return Err(crate::Error::Usage(format!(
                "--u and --y: give one column each, or two comma-separated each for a two-axis \
                 record (got {} and {})",
                us.len(),
                ys.len()
            )));
        }
        let rows = read_rows(path).map_err(crate::Error::from)?;
        let table = &rows.table;
        let t_name = pick(table, t, "t_", "--t")?;
        let columns = us
            .iter()
            .zip(&ys)
            .map(|(u, y)| {
                Ok((
                    pick(table, u.as_deref(), "u_", "--u")?,
                    pick(table, y.as_deref(), "y_", "--y")?,
                ))
            })
            .collect::<crate::Result<Vec<_>>>()?;
        let t_s: Vec<f64> = {
            let factor = si_factor(path, &t_name, "--t", &[Quantity::Time])?;
            let t = rows.time(&t_name, factor).map_err(crate::Error::from)?;
            t.iter().map(|v| v * factor).collect()
        };
        if t_s.len() < 10 {
            return Err(crate::Error::Usage(format!(
                "{}: {} samples, fewer than 10",
                path.display(),
                t_s.len()
            )));
        }
        columns
            .into_iter()
            .map(|(u_name, y_name)| {
                let u = rows
                    .f32_column(
                        &u_name,
                        si_factor(path, &u_name, "--u", &[Quantity::Voltage, Quantity::Force])?,
                    )
                    .map_err(crate::Error::from)?;
                let factor = si_factor(path, &y_name, "--y", &[Quantity::Length, Quantity::Force])?;
                let y_m: Vec<f64> = table
                    .column(&y_name)
                    .map_err(crate::Error::from)?
                    .iter()
                    .map(|v| v * factor)
                    .collect();
                let warnings = scale_warnings(path, &u_name, &u, &y_name, &y_m);
                for w in &warnings {
                    eprintln!("warning: {w}");
                }
                Ok(Self {
                    path: path.into(),
                    t_s: t_s.clone(),
                    u,
                    y_m,
                    segments: vec![0],
                    sources: vec![path.into()],
                })
            })
            .collect()
    }

    /// A record of one sample period from its parts, from the first sample's time on.
    pub fn from_parts(path: PathBuf, t_s: Vec<f64>, u: Vec<f64>, y_m: Vec<f64>) -> Self {
        Self {
            sources: vec![path.clone()],
            path,
            t_s,
            u,
            y_m,
            segments: vec![0],
        }
    }

    /// Whether `other` is this record again: the same file, or the same samples (u and y) under
    /// another name.
    pub fn is_same_record(&self, other: &Record) -> bool {
        self.path == other.path || (self.u == other.u && self.y_m == other.y_m)
    }

    /// Several records of one stage end to end, each a segment that models start from rest at its
    /// own first sample; times continue from one record to the next. The sample periods must agree
    /// within 0.1 %.
    pub fn concatenate(parts: Vec<Record>) -> crate::Result<Record> {
        // A record given twice (the same file, or the same samples under another name) would be
        // judged on itself when the records are held out in turn.
        for (i, a) in parts.iter().enumerate() {
            if let Some(b) = parts[..i].iter().find(|b| b.is_same_record(a)) {
                return Err(crate::Error::Usage(format!(
                    "{}: the same record as {} (each record is held out in turn, so a record \
                     given twice would be judged on itself)",
                    a.path.display(),
                    b.path.display()
                )));
            }
        }
        let mut parts = parts.into_iter();
        let Some(mut out) = parts.next() else {
            return Err(crate::Error::Usage("no record".into()));
        };
        let ts = out.sample_period_s();
        for r in parts {
            let t = r.sample_period_s();
            if (t - ts).abs() > 1e-3 * ts {
                return Err(crate::Error::Usage(format!(
                    "{}: sample period {t:.6e} s differs from {}'s {ts:.6e} s",
                    r.path.display(),
                    out.path.display()
                )));
            }
            let shift = out.t_s[out.t_s.len() - 1] + ts - r.t_s[0];
            let at = out.u.len();
            out.segments.extend(r.segments.iter().map(|s| s + at));
            out.sources.extend(r.sources);
            out.t_s.extend(r.t_s.iter().map(|t| t + shift));
            out.u.extend(r.u);
            out.y_m.extend(r.y_m);
        }
        out.path = PathBuf::from(
            out.sources
                .iter()
                .map(|p| p.display().to_string())
                .collect::<Vec<_>>()
                .join(","),
        );
        Ok(out)
    }

    /// The sample ranges of the records (segments) as (first, end).
    pub fn segment_ranges(&self) -> Vec<(usize, usize)> {
        let n = self.u.len();
        self.segments
            .iter()
            .enumerate()
            .map(|(i, &a)| (a, self.segments.get(i + 1).copied().unwrap_or(n)))
            .collect()
    }

    /// Mean sample period \[s\].
    pub fn sample_period_s(&self) -> f64 {
        (self.t_s[self.t_s.len() - 1] - self.t_s[0]) / (self.t_s.len() - 1) as f64
    }

    /// Cuts the record after `end_s` (`--end`); an error if fewer than 10 samples remain.
    pub fn cut_after(&mut self, end_s: f64) -> crate::Result<()> {
        let n = self
            .t_s
            .iter()
            .position(|&t| t > end_s)
            .unwrap_or(self.t_s.len());
        if n < 10 {
            return Err(crate::Error::Usage(format!(
                "--end {end_s}: fewer than 10 samples before it"
            )));
        }
        self.t_s.truncate(n);
        self.u.truncate(n);
        self.y_m.truncate(n);
        self.segments.retain(|&s| s < n);
        self.sources.truncate(self.segments.len());
        Ok(())
    }

    /// Index of the first sample at or after `start_s`.
    pub fn index_at(&self, start_s: f64) -> usize {
        self.t_s
            .iter()
            .position(|&t| t >= start_s)
            .unwrap_or(self.t_s.len())
    }
}

/// Prints a developer trace line of the optimisers' stages on stderr when `PIEZO_ID_DEBUG` is set
/// (read once); the line is only formatted then.
pub(crate) fn trace(line: impl FnOnce() -> String) {
    static ENABLED: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    if *ENABLED.get_or_init(|| std::env::var_os("PIEZO_ID_DEBUG").is_some()) {
        eprintln!("{}", line());
    }
}

/// Settings of one identification.
#[derive(Debug, Clone)]
pub struct IdentifySettings {
    /// Model family.
    pub model: ModelKind,
    /// Method.
    pub method: Method,
    /// Seed of the random generators.
    pub seed: u64,
    /// First scored time \[s\].
    pub start_s: f64,
    /// Asymmetric model: keep φ = 0 (seed 001's Case II).
    pub no_shift: bool,
    /// Require the firmware's compensator to accept the set.
    pub invertible: bool,
    /// Several records: each has its own constant sensor offset (`--free-offset`).
    pub free_offset: bool,
    /// Show a progress bar.
    pub progress: bool,
}

impl IdentifySettings {
    /// `model` by the default method (`vp-de-lm`), seed 1, scored from t = 0, unconstrained, without
    /// a progress bar: the command line's defaults, for runs from code.
    pub fn new(model: ModelKind) -> Self {
        Self {
            model,
            method: Method::VpDeLm,
            seed: 1,
            start_s: 0.0,
            no_shift: false,
            invertible: false,
            free_offset: false,
            progress: false,
        }
    }
}

/// Why an identification failed. `Display` gives the message the command line prints.
#[derive(Debug, Clone)]
pub enum IdentifyError {
    /// Fewer than 10 samples from `--start` on.
    TooFewSamples {
        /// The first scored time \[s\].
        start_s: f64,
    },
    /// The optimiser found no set piezo-core accepts.
    NoFeasibleSet,
    /// piezo-core refused the set to score.
    Refused(String),
    /// `--method ga` on a model it does not fit.
    GaStaticOnly,
    /// `--method two-step` without the square-wave record.
    NeedsMechData,
    /// `--method two-step` on a model other than the dynamic one.
    TwoStepDynamicOnly(ModelKind),
    /// A score that is not a finite number.
    NonFinite(NonFinite),
    /// Anything else (unreadable or unsuitable data, options that do not go together), with its
    /// cause.
    Host(Box<crate::Error>),
}

impl std::fmt::Display for IdentifyError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::TooFewSamples { start_s } => {
                write!(f, "--start {start_s}: fewer than 10 samples left to fit")
            }
            Self::NoFeasibleSet => f.write_str(
                "no feasible parameter set found (every candidate was refused by piezo-core)",
            ),
            Self::Refused(e) => write!(f, "parameter set refused by piezo-core: {e}"),
            Self::NonFinite(e) => write!(f, "the fit's score: {e}"),
            Self::GaStaticOnly => f.write_str(
                "--method ga: seed 001's GA fits the static models only (symmetric, asymmetric)",
            ),
            Self::NeedsMechData => f.write_str(
                "--method two-step needs the square-wave record too: give --mech-data (library: identify::two_step::identify)",
            ),
            Self::TwoStepDynamicOnly(model) => write!(
                f,
                "--method two-step: seed 000's two-step method identifies the dynamic model only (got --model {})",
                model.name()
            ),
            Self::Host(e) => e.fmt(f),
        }
    }
}

impl std::error::Error for IdentifyError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            Self::Host(e) => e.source(),
            _ => None,
        }
    }
}

impl From<crate::Error> for IdentifyError {
    fn from(e: crate::Error) -> Self {
        Self::Host(Box::new(e))
    }
}

/// The fit block of the reports (SI): the error measures of a prediction over the scored samples
/// (NaN where a measure is undefined, e.g. on no samples; `null` in JSON).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct FitBlock {
    /// RMS error \[m\].
    pub rms: f64,
    /// Largest absolute error \[m\].
    pub max_abs: f64,
    /// R² = 1 − SSE/SST.
    pub r2: f64,
    /// MRD = max|x − x̂| / max|x| · 100 %.
    pub mrd_percent: f64,
    /// Smallest error x̂ − x \[m\].
    pub rae_min: f64,
    /// Largest error x̂ − x \[m\].
    pub rae_max: f64,
}

/// A result that is not a finite number, and the sample that made it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NonFinite {
    /// What is not finite (`the prediction`, `the sum of squared residuals`, ...).
    pub what: &'static str,
    /// The sample (0-based index into the record).
    pub index: usize,
    /// Its time \[s\].
    pub t_s: f64,
    /// The measured output there \[m\].
    pub measured_m: f64,
    /// The predicted output there \[m\].
    pub predicted_m: f64,
}

impl std::fmt::Display for NonFinite {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} is not a finite number at sample {} (t = {} s; measured {:e} m, predicted {:e} m): \
             nothing is scored or written from it",
            self.what, self.index, self.t_s, self.measured_m, self.predicted_m
        )
    }
}

impl std::error::Error for NonFinite {}

/// The first sample from `from` on whose prediction is not finite, as an error.
pub fn check_finite(
    t_s: &[f64],
    measured: &[f64],
    predicted: &[f64],
    from: usize,
) -> Result<(), NonFinite> {
    match (from..predicted.len()).find(|&k| !predicted[k].is_finite()) {
        Some(k) => Err(non_finite("the prediction", k, t_s, measured, predicted)),
        None => Ok(()),
    }
}

fn non_finite(
    what: &'static str,
    k: usize,
    t_s: &[f64],
    measured: &[f64],
    predicted: &[f64],
) -> NonFinite {
    let at = |v: &[f64]| v.get(k).copied().unwrap_or(f64::NAN);
    NonFinite {
        what,
        index: k,
        t_s: at(t_s),
        measured_m: at(measured),
        predicted_m: at(predicted),
    }
}

/// The fit block of `predicted` against `measured` (whole records, times `t_s`) over the samples
/// from `from` on. The sums (SSE = Σ(x̂ − x)², Σx and SST = Σ(x − x̄)²) run in f64 and are checked
/// as they grow: a prediction that is not finite, or a sum that overflows, is refused naming the
/// sample; an empty range, or R² and MRD where they are undefined (SST = 0, max|x| = 0), give NaN.
pub fn fit_block(
    t_s: &[f64],
    measured: &[f64],
    predicted: &[f64],
    from: usize,
) -> Result<FitBlock, NonFinite> {
    use piezo_core::metrics;
    check_finite(t_s, measured, predicted, from)?;
    let n = measured.len().min(predicted.len());
    let fail = |what, k| non_finite(what, k, t_s, measured, predicted);
    let (mut sse, mut sum) = (0.0f64, 0.0f64);
    for k in from..n {
        let e = predicted[k] - measured[k];
        sse += e * e;
        if !sse.is_finite() {
            return Err(fail("the sum of squared residuals (it overflows f64)", k));
        }
        sum += measured[k];
        if !sum.is_finite() {
            return Err(fail(
                "the sum of the measured outputs (it overflows f64)",
                k,
            ));
        }
    }
    let mean = sum / (n.saturating_sub(from)) as f64;
    let mut sst = 0.0f64;
    for (k, x) in measured.iter().enumerate().take(n).skip(from) {
        let d = x - mean;
        sst += d * d;
        if !sst.is_finite() {
            return Err(fail(
                "the sum of squared deviations from the mean output (it overflows f64)",
                k,
            ));
        }
    }
    let (measured, predicted) = (&measured[from.min(n)..n], &predicted[from.min(n)..n]);
    let (lo, hi) = metrics::rae(measured, predicted).unwrap_or((f64::NAN, f64::NAN));
    Ok(FitBlock {
        rms: metrics::rms(measured, predicted).unwrap_or(f64::NAN),
        max_abs: lo.abs().max(hi.abs()),
        r2: metrics::r_squared(measured, predicted).unwrap_or(f64::NAN),
        mrd_percent: metrics::mrd_percent(measured, predicted).unwrap_or(f64::NAN),
        rae_min: lo,
        rae_max: hi,
    })
}

/// Simulates a set on a record and returns the fit block over the samples from `from`.
pub fn score(set: &Identified, record: &Record, from: usize) -> Result<FitBlock, IdentifyError> {
    if set.kind() == ModelKind::Oscillator {
        return oscillator::score(set, record, from);
    }
    let model = set
        .build()
        .map_err(|e| IdentifyError::Refused(e.to_string()))?;
    let predicted = simulate_records(&model, record);
    fit_block(&record.t_s, &record.y_m, &predicted, from).map_err(IdentifyError::NonFinite)
}

/// The model's output over a record, from rest at each of its records' first samples \[m\].
pub fn simulate_records(model: &model::CoreModel, record: &Record) -> Vec<f64> {
    let u: Vec<f32> = record.u.iter().map(|&v| v as f32).collect();
    let mut predicted = vec![0.0f64; u.len()];
    for (a, b) in record.segment_ranges() {
        model.simulate(&u[a..b], |k, v| predicted[a + k] = f64::from(v));
    }
    predicted
}

/// One record's fit, when several are fitted together.
#[derive(Debug, Clone, serde::Serialize)]
pub struct RecordFit {
    /// The record's file.
    pub data: String,
    /// RMS error over the record \[m\] (with its own offset when offsets are free).
    pub rms_m: f64,
    /// RMS error with the record's mean error removed (its offset re-estimated) \[m\].
    pub rms_zeroed_m: f64,
    /// The record's constant sensor offset \[m\]: the map's offset, or its own when free.
    pub offset_m: f64,
}

/// The prediction of each record from rest, with its own offset when `free_offset` (the record's
/// mean error added to the map's offset), the per-record fits, and the whole fit from `from` on.
pub fn fit_records(
    set: &Identified,
    record: &Record,
    from: usize,
    free_offset: bool,
) -> Result<(Vec<f64>, FitBlock, Vec<RecordFit>), IdentifyError> {
    let model = set
        .build()
        .map_err(|e| IdentifyError::Refused(e.to_string()))?;
    let mut predicted = simulate_records(&model, record);
    let map_offset = match set {
        Identified::Static { map, .. } => f64::from(map.offset_m),
        _ => 0.0,
    };
    let mut fits = Vec::new();
    for (i, (a, b)) in record.segment_ranges().into_iter().enumerate() {
        let a = a.max(from).min(b);
        let (y, p) = (&record.y_m[a..b], &mut predicted[a..b]);
        let n = y.len().max(1) as f64;
        let mean_error = y.iter().zip(p.iter()).map(|(y, p)| y - p).sum::<f64>() / n;
        let rms = |shift: f64, p: &[f64]| {
            (y.iter()
                .zip(p)
                .map(|(y, p)| (y - p - shift).powi(2))
                .sum::<f64>()
                / n)
                .sqrt()
        };
        let rms_zeroed_m = rms(mean_error, p);
        let mut offset_m = map_offset;
        if free_offset {
            p.iter_mut().for_each(|v| *v += mean_error);
            offset_m += mean_error;
        }
        fits.push(RecordFit {
            data: record.sources.get(i).map_or_else(
                || record.path.display().to_string(),
                |p| p.display().to_string(),
            ),
            rms_m: rms(0.0, p),
            rms_zeroed_m,
            offset_m,
        });
    }
    let whole =
        fit_block(&record.t_s, &record.y_m, &predicted, from).map_err(IdentifyError::NonFinite)?;
    Ok((predicted, whole, fits))
}

/// Result of `identify`.
#[derive(Debug, Clone)]
pub struct Identification {
    /// The set.
    pub set: Identified,
    /// How it was found and how well it fits.
    pub summary: IdentifySummary,
}

/// How a set was found and how well it fits: the report's figures besides the parameters.
#[derive(Debug, Clone, serde::Serialize)]
pub struct IdentifySummary {
    /// Model family name.
    pub model: &'static str,
    /// Method name (the one that produced the set: `vp-de-lm` after a two-step fallback).
    pub method: &'static str,
    /// The fit over the scored samples.
    pub fit: FitBlock,
    /// Model evaluations.
    pub evaluations: u64,
    /// Wall time \[s\].
    pub seconds: f64,
    /// The search coordinates that ended at a bound (`vp-de-lm` and `ga` only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub at_bounds: Option<Vec<&'static str>>,
    /// Per record, when several records were fitted together.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub records: Vec<RecordFit>,
    /// The two-step method's notes and diagnostics (`--method two-step`).
    #[serde(flatten, skip_serializing_if = "Option::is_none")]
    pub two_step: Option<two_step::TwoStepReport>,
}

/// One axis's `identify` report: the summary, the parameters and the data warnings.
#[derive(Debug, Clone, serde::Serialize)]
pub struct IdentifyResult<'a> {
    /// `x` or `y`.
    pub axis: &'static str,
    /// How the set was found and how well it fits.
    #[serde(flatten)]
    pub summary: &'a IdentifySummary,
    /// The set.
    pub params: &'a Identified,
    /// Data warnings ([`data_warnings`]).
    pub warnings: Vec<String>,
}

fn bar(len: u64, show: bool) -> Progress {
    if show {
        let pb = indicatif::ProgressBar::new(len);
        if let Ok(style) = indicatif::ProgressStyle::with_template(
            "{spinner} {msg} [{bar:30}] {pos}/{len} {elapsed_precise}",
        ) {
            pb.set_style(style);
        }
        pb
    } else {
        indicatif::ProgressBar::hidden()
    }
}

/// Runs one identification on a record.
pub fn identify(record: &Record, s: &IdentifySettings) -> Result<Identification, IdentifyError> {
    identify_traced(record, s).map(|(id, _)| id)
}

/// [`identify`], also returning the optimisers' progress (best θ after every DE generation and LM
/// iteration, with its time and evaluation count; empty for the oscillator model).
pub fn identify_traced(
    record: &Record,
    s: &IdentifySettings,
) -> Result<(Identification, Vec<TracePoint>), IdentifyError> {
    if s.model == ModelKind::Oscillator {
        return oscillator::identify(record, s).map(|id| (id, Vec::new()));
    }
    let started = Instant::now();
    let from = record.index_at(s.start_s);
    if record.u.len() - from < 10 {
        return Err(IdentifyError::TooFewSamples { start_s: s.start_s });
    }
    let mut problem = Problem::new(
        s.model,
        &record.u,
        &record.y_m,
        from,
        record.sample_period_s(),
    );
    problem.fit_shift = !s.no_shift;
    problem.invertible = s.invertible;
    problem.segments = record.segments.clone();
    problem.free_offset = s.free_offset;
    if record.segments.len() > 1 && s.method != Method::VpDeLm {
        return Err(crate::Error::Usage(format!(
            "several records: method {} fits one record; use vp-de-lm",
            s.method.name()
        ))
        .into());
    }
    let mut at_bounds = Vec::new();
    let set = match s.method {
        Method::VpDeLm => {
            let bounds = problem.bounds();
            let pb = bar(100, s.progress);
            pb.set_message(format!("{} DE", s.model.name()));
            let (theta, _) = fit::differential_evolution(&problem, &bounds, s.seed, 12, &pb);
            trace(|| {
                format!(
                    "DE: {} evaluations, {:.3} s",
                    problem.evaluations(),
                    started.elapsed().as_secs_f64()
                )
            });
            pb.set_message(format!("{} LM", s.model.name()));
            let (theta, _) = fit::levenberg_marquardt(&problem, &bounds, theta, 40, &pb);
            pb.finish_and_clear();
            at_bounds = at_search_bounds(s.model, &theta, &bounds);
            let e = problem.eval_full(&theta);
            problem
                .identified(&theta, &e)
                .ok_or(IdentifyError::NoFeasibleSet)?
        }
        Method::Ga => {
            if s.model == ModelKind::Dynamic {
                return Err(IdentifyError::GaStaticOnly);
            }
            let pb = bar(
                if s.model == ModelKind::Asymmetric {
                    200
                } else {
                    100
                },
                s.progress,
            );
            pb.set_message("GA case I");
            let base = [0.0; 8];
            let (g, _) = fit::genetic_algorithm(&problem, &base, &[0, 1, 2, 3, 4, 5], s.seed, &pb);
            let g = if s.model == ModelKind::Asymmetric {
                pb.set_message("GA case II/III");
                let free: &[usize] = if s.no_shift { &[6] } else { &[6, 7] };
                fit::genetic_algorithm(&problem, &g, free, s.seed + 1, &pb).0
            } else {
                g
            };
            pb.finish_and_clear();
            fit::ga_set(&problem, &g)
        }
        Method::TwoStep => {
            return Err(IdentifyError::NeedsMechData);
        }
    };
    let (_, fit, records) = fit_records(&set, record, from, s.free_offset)?;
    let summary = IdentifySummary {
        model: s.model.name(),
        method: s.method.name(),
        fit,
        evaluations: problem.evaluations(),
        seconds: started.elapsed().as_secs_f64(),
        at_bounds: Some(at_bounds),
        records: if record.segments.len() > 1 {
            records
        } else {
            Vec::new()
        },
        two_step: None,
    };
    Ok((Identification { set, summary }, problem.trace()))
}

/// A coordinate of the `vp-de-lm` search (the static models' θ, [`fit`]'s module doc; the
/// dynamic model adds its three).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SearchCoordinate {
    /// log10(H/U): the state bound over the input span.
    SaturationLevel,
    /// r = (β − γ)/(β + γ).
    LoopShape,
    /// The Bouc-Wen exponent n.
    Exponent,
    /// The asymmetric factor δ (asymmetric model).
    AsymmetricFactor,
    /// The input shift φ (asymmetric model).
    InputShift,
    /// A/k1 (dynamic model).
    HysteresisGain,
    /// The natural frequency (dynamic model).
    NaturalFrequency,
    /// The damping ratio (dynamic model).
    DampingRatio,
}

impl SearchCoordinate {
    /// The coordinates of `model`'s search, in θ's order.
    pub fn of(model: ModelKind) -> Vec<Self> {
        let mut all = vec![Self::SaturationLevel, Self::LoopShape, Self::Exponent];
        match model {
            ModelKind::Asymmetric => all.extend([Self::AsymmetricFactor, Self::InputShift]),
            ModelKind::Dynamic => all.extend([
                Self::HysteresisGain,
                Self::NaturalFrequency,
                Self::DampingRatio,
            ]),
            ModelKind::Symmetric | ModelKind::Oscillator => {}
        }
        all
    }

    /// In words, for reports.
    pub fn description(self) -> &'static str {
        match self {
            Self::SaturationLevel => "the saturation level log10(H / input span)",
            Self::LoopShape => "the loop shape (beta - gamma) / (beta + gamma)",
            Self::Exponent => "the exponent n",
            Self::AsymmetricFactor => "the asymmetric factor delta",
            Self::InputShift => "the input shift phi",
            Self::HysteresisGain => "the hysteresis gain A / k1",
            Self::NaturalFrequency => "the natural frequency",
            Self::DampingRatio => "the damping ratio",
        }
    }
}

/// The search coordinates that ended within 0.1 % of the box's width of a bound, in words. The
/// exponent at its lower bound n = 1 is a common, exact value, not a sign of trouble.
fn at_search_bounds(model: ModelKind, theta: &[f64], bounds: &[(f64, f64)]) -> Vec<&'static str> {
    theta
        .iter()
        .zip(bounds)
        .zip(SearchCoordinate::of(model))
        .filter(|((&t, &(lo, hi)), c)| {
            let tol = 1e-3 * (hi - lo);
            (t - lo < tol && *c != SearchCoordinate::Exponent) || hi - t < tol
        })
        .map(|(_, c)| c.description())
        .collect()
}

/// The smallest and largest value of `v` ((+∞, −∞) when empty).
pub fn min_max(v: &[f64]) -> (f64, f64) {
    v.iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| {
            (a.min(x), b.max(x))
        })
}

/// Data warnings for an identified set on `record` from sample `from`: an input that barely moves,
/// a fit that explains nothing (R² ≈ 0), optimiser parameters at their search bounds.
pub fn data_warnings(record: &Record, from: usize, id: &Identification) -> Vec<String> {
    let mut out = Vec::new();
    let (lo, hi) = min_max(&record.u[from..]);
    if !(hi - lo > 1e-6 * hi.abs().max(lo.abs()).max(1e-12)) {
        out.push(format!(
            "the input is constant ({lo} V) over the fitted window: it cannot identify a hysteresis model"
        ));
    }
    let r2 = id.summary.fit.r2;
    if r2 < 0.1 {
        out.push(format!(
            "R² = {r2:.3}: the model explains almost none of the output (wrong columns, or no response to u?)"
        ));
    }
    if let Identified::Static { bouc_wen, map, .. } = id.set {
        // Small-signal gain from rest: dy/du = k1 + k2·A.
        let net = f64::from(map.k1_m_per_v) + f64::from(map.k2_m_per_h) * f64::from(bouc_wen.a);
        let k1 = f64::from(map.k1_m_per_v);
        if k1.abs() > 20.0 * net.abs() {
            out.push(format!(
                "k1 = {k1:.4e} m/V and k2·A = {:.4e} m/V nearly cancel (net {net:.3e} m/V): a degenerate set \
                 whose output is a small difference of large terms; try --start past a start-up \
                 transient, or --invertible",
                net - k1
            ));
        }
    }
    if let Some(at) = &id.summary.at_bounds {
        for name in at {
            out.push(format!(
                "{name} ended at its search bound: the data do not pin it down (or the model family does not fit)"
            ));
        }
    }
    out
}

/// The `[x.identified]` provenance of a set fitted to `record` from sample `from`.
pub fn provenance(
    record: &Record,
    from: usize,
    method: &str,
    fit_rms_m: f64,
) -> piezo_stage::Provenance {
    let (lo, hi) = min_max(&record.u);
    let provenance = piezo_stage::Provenance {
        data: record.path.display().to_string(),
        window_s: [
            record.t_s[from.min(record.t_s.len() - 1)],
            record.t_s[record.t_s.len() - 1],
        ],
        method: method.to_string(),
        fit_rms_m,
        input_range_v: [lo as f32, hi as f32],
        sample_period_s: record.sample_period_s() as f32,
        input_rate_max_v_per_s: None,
        band_hz: None,
    };
    record_envelope(record, provenance)
}

/// `provenance` with the envelope of `record`'s input (`piezo_stage::Provenance::with_envelope_of`):
/// its largest rate within each of its records (a jump from one record to the next is not a
/// rate), its band over the first.
pub fn record_envelope(
    record: &Record,
    provenance: piezo_stage::Provenance,
) -> piezo_stage::Provenance {
    let dt = record.sample_period_s();
    let ranges = record.segment_ranges();
    let (a, b) = ranges.first().copied().unwrap_or((0, record.u.len()));
    let mut provenance = provenance.with_envelope_of(&record.u[a..b], dt);
    let rate = ranges
        .iter()
        .map(|&(a, b)| piezo_stage::input_rate_max_v_per_s(&record.u[a..b], dt))
        .fold(0.0, f64::max);
    provenance.input_rate_max_v_per_s = Some(rate as f32);
    provenance
}

/// The `--t/--u/--y` column choice shared by `identify` and `predict`: one axis, or two with
/// comma lists (`--u ux_V,uy_V --y x_m,y_m`).
#[derive(Debug, clap::Args)]
pub struct Columns {
    /// Time column (default: first `t_*`).
    #[arg(long)]
    pub t: Option<String>,
    /// Input column, or two comma-separated for a two-axis record (default: first `u_*`).
    #[arg(long)]
    pub u: Option<String>,
    /// Output column, or two comma-separated for a two-axis record (default: first `y_*`).
    #[arg(long)]
    pub y: Option<String>,
}

impl Columns {
    /// Reads `data` with these columns: one record per axis; several comma-separated files are
    /// records of one stage held end to end ([`Record::concatenate`]); errors name `--data`.
    pub fn read_axes(&self, data: &std::path::Path) -> crate::Result<Vec<Record>> {
        let text = data.to_string_lossy();
        if !text.contains(',') {
            return self.read_axes_one(data);
        }
        let mut per_axis: Vec<Vec<Record>> = Vec::new();
        for part in text.split(',').map(str::trim).filter(|p| !p.is_empty()) {
            let axes = self.read_axes_one(std::path::Path::new(part))?;
            per_axis.resize_with(axes.len(), Vec::new);
            for (i, r) in axes.into_iter().enumerate() {
                per_axis[i].push(r);
            }
        }
        per_axis
            .into_iter()
            .map(|parts| {
                Record::concatenate(parts).map_err(|e| crate::Error::Usage(format!("--data: {e}")))
            })
            .collect()
    }

    /// One file ([`Record::read_axes`]): one record per axis; errors name `--data`.
    fn read_axes_one(&self, data: &std::path::Path) -> crate::Result<Vec<Record>> {
        Record::read_axes(
            data,
            self.t.as_deref(),
            self.u.as_deref(),
            self.y.as_deref(),
        )
        .map_err(|e| crate::Error::Usage(format!("--data: {e}")))
    }

    fn read(&self, data: &std::path::Path) -> crate::Result<Record> {
        let mut records = self.read_axes(data)?;
        if records.len() != 1 {
            return Err(crate::Error::Usage("--mech-data: one axis only".into()));
        }
        Ok(records.remove(0))
    }
}

/// Arguments of `identify`.
#[derive(Debug, clap::Args)]
#[command(
    after_help = "Methods:\n  vp-de-lm  default: variable projection (k1, k2, offset by least squares in every evaluation), differential evolution on the decimated record, then Levenberg-Marquardt on the full record; deterministic for a given --seed, parallel over cores\n  ga        seed 001's genetic algorithm as published (population 30, 100 generations, crossover 0.7, mutation 0.2, RMS fitness, its search ranges); asymmetric: Case I, then delta (Case II, --no-shift) or delta and phi (Case III)\n  two-step  seed 000's two-step method (--model dynamic only): step 1 takes k0, c0, m0 (k1 = 1 N/V) from the steady-state integrals K0, K1, K2 of the response to a ramp-edged square wave (--mech-data, e.g. `simulate --plant nac2024 --signal square:duration=1e-4`); step 2 takes A, beta, gamma, n from the sine --data by the log-linear least squares of eq. 15-24 on the 25-75 % band of each stroke, derivatives by CWT-TRT (gaus1, s = 4); step 2b (not in the paper) fixes the scale of k0, c0, m0 that step 1 cannot see (it measures (k1 + h(B)/B)/k0). Needs beta + gamma < 0: otherwise (or when ill-posed) it says why in the summary's notes and on stderr and runs vp-de-lm instead\nThe model simulated is piezo-core's f32 model, from rest at the record's first input; sets the core refuses are infeasible. Two-axis records: --u ux_V,uy_V --y x_m,y_m fits each axis and writes both. The stage file written (--out) is validated as the firmware's build validates it: a set the firmware would refuse makes identify exit non-zero after writing it, unless --allow-refused."
)]
pub struct IdentifyArgs {
    /// Record to fit (CSV with unit-suffixed columns); several comma-separated records of one stage
    /// are fitted together, each from rest at its own first sample (`a.csv,b.csv,c.csv`).
    #[arg(long)]
    pub data: PathBuf,
    /// Several records: each has its own constant sensor offset (the sensor's zero moved between
    /// them), re-estimated per record; the stage file keeps the first record's.
    #[arg(long)]
    pub free_offset: bool,
    /// `--method two-step`: the ramp-edged square-wave record for step 1 (same columns as --data).
    #[arg(long)]
    pub mech_data: Option<PathBuf>,
    /// Model family.
    #[arg(long, value_enum)]
    pub model: ModelKind,
    /// Method.
    #[arg(long, value_enum, default_value_t = Method::VpDeLm)]
    pub method: Method,
    /// Column choice.
    #[command(flatten)]
    pub columns: Columns,
    /// First scored time (s); earlier samples only warm the model state up.
    #[arg(long, default_value_t = 0.0)]
    pub start: f64,
    /// Last time used (s) (the record is cut there; later samples can be scored by `predict --start`).
    #[arg(long)]
    pub end: Option<f64>,
    /// Seed of the random generators.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Asymmetric model: keep the input shift phi at 0 (seed 001's Case II).
    #[arg(long)]
    pub no_shift: bool,
    /// Only sets the firmware's compensator accepts (strictly monotone map) are feasible.
    #[arg(long)]
    pub invertible: bool,
    /// An existing stage file whose `[stage]` and `[io]` sections are carried into --out (without it:
    /// the record's rate and a placeholder io chain).
    #[arg(long)]
    pub stage: Option<PathBuf>,
    /// Write and exit 0 also when the firmware would refuse the set.
    #[arg(long)]
    pub allow_refused: bool,
    /// Stage file to write (TOML).
    #[arg(long)]
    pub out: PathBuf,
    /// Summary JSON to write.
    #[arg(long)]
    pub report: PathBuf,
    /// Folder for the plots of the fit (measured against model in time and as loops, residual).
    #[arg(long)]
    pub plots: Option<PathBuf>,
}

/// Identifies one axis's record (`mech`: the square-wave record of `--method two-step`).
fn identify_axis(
    record: &Record,
    settings: &IdentifySettings,
    mech: Option<&Record>,
) -> crate::Result<Identification> {
    if settings.method == Method::TwoStep {
        let mech = mech.ok_or_else(|| {
            crate::Error::Usage(
                "--method two-step: give the square-wave record with --mech-data".into(),
            )
        })?;
        Ok(two_step::identify(mech, record, settings)?)
    } else {
        if mech.is_some() {
            return Err(crate::Error::Usage(
                "--mech-data is used by --method two-step only".into(),
            ));
        }
        Ok(identify(record, settings)?)
    }
}

/// Every axis of a record identified, as the stage file `identify` writes it.
#[derive(Debug, Clone)]
pub struct IdentifiedStage {
    /// The stage file: `[stage]` and `[io]` given or made from the record, an axis per record.
    pub file: piezo_stage::StageFile,
    /// Its comment header (what made it, from which data).
    pub header: String,
    /// Per axis: the identification and its data warnings ([`data_warnings`]).
    pub axes: Vec<(Identification, Vec<String>)>,
    /// Per axis: the fit's uncertainty ([`fit_uncertainty`]), or why it was not computed.
    pub uncertainty: Vec<crate::Result<Uncertainty>>,
    /// The summary lines the command prints.
    pub lines: Vec<String>,
}

impl IdentifiedStage {
    /// The report's identification part: one axis's summary, parameters, uncertainty
    /// ([`crate::uncertainty::keys_of`]: `uncertainty`, `correlation`, `prediction_band_rms_m`)
    /// and warnings, or `{"axes": [...]}` for two.
    pub fn report(&self) -> crate::Result<serde_json::Value> {
        let mut summaries = Vec::new();
        for (((id, warnings), axis), u) in self.axes.iter().zip(["x", "y"]).zip(&self.uncertainty) {
            let mut value = to_json(&IdentifyResult {
                axis,
                summary: &id.summary,
                params: &id.set,
                warnings: warnings.clone(),
            })?;
            if let Some(map) = value.as_object_mut() {
                map.extend(crate::uncertainty::keys_of(u));
            }
            summaries.push(value);
        }
        if summaries.len() == 1 {
            Ok(summaries.remove(0))
        } else {
            Ok(json!({ "axes": summaries }))
        }
    }
}

/// Identifies every axis of `records` (one per axis) with `settings` (`mech`: the square-wave
/// record of the two-step method) into a stage file whose `[stage]` and `[io]` are `given`, or
/// made from the records (their rate, a placeholder io chain covering a static set's input range;
/// said on stderr); `data` names the records in the header. The one function behind
/// `host-sim identify` and the Python package's `identify`.
pub fn identify_stage(
    records: &[Record],
    settings: &IdentifySettings,
    mech: Option<&Record>,
    given: Option<(piezo_stage::Stage, piezo_stage::Io)>,
    data: &str,
) -> crate::Result<IdentifiedStage> {
    let first = records
        .first()
        .ok_or_else(|| crate::Error::Usage("no record to identify".into()))?;
    if first.segments.len() > 1 && settings.start_s > 0.0 {
        return Err(crate::Error::Usage(
            "--start: with several records each is scored from its first sample".into(),
        ));
    }
    let (stage, io) = match given {
        Some(given) => given,
        None => {
            // The output window of a static set is the record's input range: a placeholder io
            // chain covers it.
            let drive_range_v =
                if matches!(settings.model, ModelKind::Symmetric | ModelKind::Asymmetric) {
                    records.iter().fold((0.0f32, 0.0f32), |(lo, hi), r| {
                        let (a, b) = min_max(&r.u);
                        (lo.min(a as f32), hi.max(b as f32))
                    })
                } else {
                    (0.0, 0.0)
                };
            crate::stage_file::stage_and_io(
                None,
                &format!("identified-{}", settings.model.name()),
                1.0 / first.sample_period_s(),
                drive_range_v,
            )?
        }
    };
    let names = ["x", "y"];
    let mut axes = Vec::new();
    let mut identified = Vec::new();
    let mut uncertainty = Vec::new();
    let mut lines = Vec::new();
    for (i, record) in records.iter().enumerate() {
        if records.len() > 1 {
            eprintln!("identify: axis {} ({})", names[i], record.path.display());
        }
        let id = identify_axis(record, settings, mech)?;
        let from = record.index_at(settings.start_s);
        let warnings = data_warnings(record, from, &id);
        for w in &warnings {
            eprintln!("warning: {}: {w}", names[i]);
        }
        let summary = &id.summary;
        let rms = summary.fit.rms;
        lines.push(format!(
            "{}: {} {}: rms {:.4e} m, r2 {}, {} evaluations, {:.2} s",
            names[i],
            summary.model,
            summary.method,
            rms,
            json!(summary.fit.r2),
            summary.evaluations,
            summary.seconds,
        ));
        for r in &summary.records {
            lines.push(format!(
                "{}:   {}: rms {:.4e} m, zeroed {:.4e} m, offset {:.4e} m",
                names[i], r.data, r.rms_m, r.rms_zeroed_m, r.offset_m
            ));
        }
        let u = fit_uncertainty(&id, record, settings);
        match &u {
            Ok(u) => lines.extend(u.lines(&format!("{}:   ", names[i]))),
            Err(why) => lines.push(format!("{}:   uncertainty not computed: {why}", names[i])),
        }
        uncertainty.push(u);
        axes.push(to_axis(
            &id.set,
            provenance(record, from, summary.method, rms),
        ));
        identified.push((id, warnings));
    }
    let header = format!(
        "Identified by `host-sim identify` ({} model, method {}) from {data}, scored from t = {} s.\nSI units.",
        settings.model.name(),
        settings.method.name(),
        settings.start_s
    );
    let mut axes = axes.into_iter();
    let file = piezo_stage::StageFile {
        stage,
        io,
        x: axes
            .next()
            .ok_or_else(|| crate::Error::Usage("no axis to write".into()))?,
        y: axes.next(),
    };
    Ok(IdentifiedStage {
        file,
        header,
        axes: identified,
        uncertainty,
        lines,
    })
}

/// The uncertainty of `id`'s set fitted to `record` with `settings` (its standard errors,
/// correlations and prediction band, [`crate::uncertainty`]), from the Jacobian of the output in
/// the parameters as written ([`linearise`]); why not, when it cannot be given (the oscillator
/// model, parameters the record does not identify).
pub fn fit_uncertainty(
    id: &Identification,
    record: &Record,
    settings: &IdentifySettings,
) -> crate::Result<Uncertainty> {
    let from = record.index_at(settings.start_s);
    let fitted = linearise::linearise(
        &id.set,
        record,
        from,
        settings.model,
        !settings.no_shift,
        settings.free_offset,
    )?;
    crate::uncertainty::estimate(&fitted)
}

fn write_json(path: &Path, value: &serde_json::Value, flag: &'static str) -> crate::Result<()> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(crate::Error::write("", dir))?;
    }
    let text = serde_json::to_string_pretty(value).map_err(crate::Error::from)?;
    std::fs::write(path, text).map_err(crate::Error::write(flag, path))
}

/// Runs `identify`: one set per axis, one stage file. The stage file, the plots and the report
/// are each written whatever became of the others; the report (written last) holds the firmware's
/// verdict on the set and says what could not be written. A set the firmware refuses (unless
/// `--allow-refused`) or a file not written makes the command fail after that.
pub fn identify_cmd(a: &IdentifyArgs) -> crate::Result<String> {
    let mut records = a.columns.read_axes(&a.data)?;
    if let Some(end) = a.end {
        for r in &mut records {
            r.cut_after(end)?;
        }
    }
    // `[stage]` and `[io]` before the fit, so that a bad --stage is said at once.
    let given = match &a.stage {
        Some(path) => {
            let (file, _) = piezo_stage::StageFile::load(path)
                .map_err(|e| crate::Error::Usage(format!("--stage: {e}")))?;
            let u_names = input_columns(&a.data, a.columns.u.as_deref());
            for w in drive_warnings(&a.data, &u_names, &records, &file.io, path) {
                eprintln!("warning: {w}");
            }
            Some((file.stage, file.io))
        }
        None => None,
    };
    let mech = match (&a.mech_data, a.method) {
        (Some(path), Method::TwoStep) => Some(a.columns.read(path).map_err(|e| {
            crate::Error::Usage(e.to_string().replacen("--data", "--mech-data", 1))
        })?),
        (Some(_), _) => {
            return Err(crate::Error::Usage(
                "--mech-data is used by --method two-step only".into(),
            ))
        }
        (None, _) => None,
    };
    let settings = IdentifySettings {
        model: a.model,
        method: a.method,
        seed: a.seed,
        start_s: a.start,
        no_shift: a.no_shift,
        invertible: a.invertible,
        free_offset: a.free_offset,
        progress: true,
    };
    let identified = identify_stage(
        &records,
        &settings,
        mech.as_ref(),
        given,
        &a.data.display().to_string(),
    )?;
    let (header, file, lines) = (&identified.header, &identified.file, &identified.lines);
    let stage_file = crate::stage_file::write_stage(&a.out, header, file);
    let mut plots = Vec::new();
    let mut plots_failed = None;
    if a.plots.is_some() && records[0].segments.len() > 1 {
        eprintln!("warning: --plots: drawn for one record only; none drawn for several");
    } else if let Some(dir) = &a.plots {
        // The fit as written: the stage file's chain on the fitted record.
        let from = records[0].index_at(a.start);
        let made = if stage_file.not_written.is_some() {
            Err(crate::Error::Usage(
                "the stage file they show was not written".to_string(),
            ))
        } else {
            predict::read_stage(&a.out)
                .and_then(|file| predict::predict_axes(&file, &records, from))
                .and_then(|predicted| {
                    predict::write_plots(dir, "identify", &records, &predicted, from)
                })
        };
        match made {
            Ok(p) => plots = p,
            Err(e) => plots_failed = Some(format!("--plots {}: not written: {e}", dir.display())),
        }
    }
    let mut report = identified.report()?;
    if let (Some(r), serde_json::Value::Object(s)) = (
        report.as_object_mut(),
        to_json(&stage_file.report(a.invertible, a.stage.as_deref()))?,
    ) {
        r.extend(s);
        r.insert("plots".into(), json!(plots));
        r.insert("plots_not_written".into(), json!(plots_failed));
    }
    let reported = write_json(&a.report, &report, "--report");
    let verdict = stage_file.verdict.summary(a.allow_refused);
    let mut failures = Vec::new();
    failures.extend(stage_file.error(a.invertible, a.stage.as_deref(), a.allow_refused));
    failures.extend(plots_failed);
    if let Err(e) = &reported {
        failures.push(format!("{e} (the report was not written)"));
    }
    let written: Vec<String> = [
        stage_file
            .not_written
            .is_none()
            .then(|| a.out.display().to_string()),
        reported.is_ok().then(|| a.report.display().to_string()),
    ]
    .into_iter()
    .flatten()
    .chain(plots)
    .collect();
    let summary = format!(
        "{}\nwritten: {} ({verdict}){}",
        lines.join("\n"),
        if written.is_empty() {
            "nothing".to_string()
        } else {
            written.join(", ")
        },
        stage_file.identity_line()
    );
    if failures.is_empty() {
        Ok(summary)
    } else {
        Err(crate::Error::Usage(format!(
            "{summary}\n{}",
            failures.join("\n")
        )))
    }
}

/// Arguments of `predict`.
#[derive(Debug, clap::Args)]
#[command(
    after_help = "Runs the stage file's chain exactly as the firmware runs it (piezo-core's model and effects, two axes with their coupling), at the record's sample period, from rest at the record's first input; the model sees only u. Inputs outside the identified range are counted and reported; a bounded set is not clamped to that range."
)]
pub struct PredictArgs {
    /// Stage file written by `identify` or `close-loop` (or any stage file).
    #[arg(long)]
    pub params: PathBuf,
    /// Record to simulate (the model sees only u).
    #[arg(long)]
    pub data: PathBuf,
    /// Column choice (two comma-separated per flag for a two-axis stage).
    #[command(flatten)]
    pub columns: Columns,
    /// First scored time (s).
    #[arg(long, default_value_t = 0.0)]
    pub start: f64,
    /// For a record that is one period of a periodic steady state (the benchmark's test multisine):
    /// simulate its input this many times first, so the model starts the scored period in its own
    /// steady state (the model still sees only u).
    #[arg(long, default_value_t = 0)]
    pub periodic_warmup: usize,
    /// The low-pass the record's output went through when it was decimated from a faster rate,
    /// applied to the prediction before it is scored, so that like is compared with like:
    /// `fir-decimate:factors=R1/R2/…[,identified_with=Q1/Q2/…][,order=N]`, MATLAB's
    /// `decimate(y, r, 'fir')` per factor in turn (order-N `fir1`, default 30, zero phase);
    /// `identified_with`: the chain of the record the model was identified on, whose response the
    /// model already carries (divided out). A model identified on the Bouc-Wen benchmark's
    /// multisines (decimated 2, 2, 5), scored on its official sine sweep (decimated 20 in one
    /// stage): `fir-decimate:factors=20,identified_with=2/2/5`.
    #[arg(long)]
    pub output_filter: Option<String>,
    /// The record's sensor offset is its own (the sensor's zero moved since identification):
    /// also report the RMS with the offset re-estimated on the scored samples (`rms_zeroed_m`).
    #[arg(long)]
    pub free_offset: bool,
    /// The `identify` or `close-loop` report of the stage file's fit: its prediction band (the
    /// RMS error expected on a new input of the kind fitted, `prediction_band_rms_m` per axis) is
    /// printed and reported beside the RMS measured here.
    #[arg(long)]
    pub fit_report: Option<PathBuf>,
    /// Report JSON to write.
    #[arg(long)]
    pub report: PathBuf,
    /// The predicted series: t_s, then per axis input, measured, predicted, residual (CSV).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Folder for the plots (measured against predicted, loops, residual; SVG and PNG).
    #[arg(long)]
    pub plots: Option<PathBuf>,
}

/// Repeats a record `copies` times (one period of a periodic steady state).
fn repeated(record: &Record, copies: usize) -> Record {
    let n = record.u.len();
    let period = record.sample_period_s() * n as f64;
    let t0 = record.t_s[0];
    let cycle = |v: &[f64]| v.iter().copied().cycle().take(n * copies).collect();
    Record::from_parts(
        record.path.clone(),
        (0..n * copies)
            .map(|i| t0 + i as f64 * period / n as f64)
            .collect(),
        cycle(&record.u),
        cycle(&record.y_m),
    )
}

/// The prediction band of each of `axes` axes from an `identify` or `close-loop` report (`path`,
/// `--fit-report`): `axes[i].prediction_band_rms_m`, or the top level's for a one-axis `identify`
/// report; `Err(why)` for an axis whose fit has no band (`uncertainty_not_computed`). An error
/// names the file and the key when the file is not such a report or its axes differ.
pub fn prediction_bands(path: &Path, axes: usize) -> crate::Result<Vec<crate::Result<f64>>> {
    let name = path.display();
    let text = std::fs::read_to_string(path).map_err(crate::Error::read("--fit-report", path))?;
    let report: serde_json::Value = serde_json::from_str(&text)
        .map_err(|e| crate::Error::Usage(format!("--fit-report {name}: not a JSON report: {e}")))?;
    let entries: Vec<(String, &serde_json::Value)> = match report.get("axes") {
        Some(serde_json::Value::Array(list)) => list
            .iter()
            .enumerate()
            .map(|(i, v)| (format!("axes[{i}]."), v))
            .collect(),
        _ => vec![(String::new(), &report)],
    };
    if entries.len() != axes {
        return Err(crate::Error::Usage(format!(
            "--fit-report {name}: {} axes, the stage file and record have {axes}",
            entries.len()
        )));
    }
    entries
        .into_iter()
        .map(|(at, entry)| match entry.get("prediction_band_rms_m") {
            Some(v) if v.is_null() => Ok(Err(crate::Error::Fit(
                entry
                    .get("uncertainty_not_computed")
                    .and_then(|w| w.as_str())
                    .unwrap_or("the fit has no prediction band")
                    .to_string(),
            ))),
            Some(v) => v
                .as_f64()
                .filter(|b| b.is_finite() && *b >= 0.0)
                .map(Ok)
                .ok_or_else(|| {
                    crate::Error::Usage(format!(
                        "--fit-report {name}: {at}prediction_band_rms_m: {v} is not a length in m"
                    ))
                }),
            None => Err(crate::Error::Usage(format!(
                "--fit-report {name}: no {at}prediction_band_rms_m (a report of `identify` or \
                 `close-loop` with the fit's uncertainty)"
            ))),
        })
        .collect()
}

/// Runs `predict`.
pub fn predict_cmd(a: &PredictArgs) -> crate::Result<String> {
    let output_filter = a
        .output_filter
        .as_deref()
        .map(output_filter::OutputFilter::parse)
        .transpose()
        .map_err(|e| crate::Error::Usage(format!("--output-filter: {e}")))?;
    let file = predict::read_stage(&a.params)?;
    let identity = crate::identity::SetIdentity::of_file(&a.params)?;
    if let Some(refusal) = file.firmware_refusal() {
        eprintln!(
            "note: predicted as a forward model; the firmware would refuse this set: {refusal}"
        );
    }
    let mut records = a.columns.read_axes(&a.data)?;
    let u_names = input_columns(&a.data, a.columns.u.as_deref());
    for w in drive_warnings(&a.data, &u_names, &records, &file.file.io, &a.params) {
        eprintln!("warning: {w}");
    }
    let mut start = a.start;
    if a.periodic_warmup > 0 {
        let period = records[0].sample_period_s() * records[0].u.len() as f64;
        records = records
            .iter()
            .map(|r| repeated(r, a.periodic_warmup + 1))
            .collect();
        start += a.periodic_warmup as f64 * period;
    }
    let from = records[0].index_at(start);
    if records[0].u.len() - from < 1 {
        return Err(crate::Error::Usage(format!(
            "--start {}: no samples left",
            a.start
        )));
    }
    let bands = match &a.fit_report {
        Some(path) => Some(prediction_bands(path, records.len())?),
        None => None,
    };
    let mut axes = predict::predict_axes(&file, &records, from)?;
    if let Some(filter) = &output_filter {
        for (p, r) in axes.iter_mut().zip(&records) {
            p.predicted_m = filter.apply(&p.predicted_m, 1.0 / r.sample_period_s());
            p.fit = fit_block(&r.t_s, &r.y_m, &p.predicted_m, from).map_err(|e| {
                crate::Error::Usage(format!("{} with --output-filter: {e}", p.axis))
            })?;
        }
    }
    let mut lines = Vec::new();
    for p in &axes {
        let e = &p.excursion;
        if e.samples > 0 {
            let msg = format!(
                "{}: the input leaves the identified range [{:.4}, {:.4}] V on {} samples ({:.1} %), by up to {:.4} V{}",
                p.axis,
                e.identified_v.0,
                e.identified_v.1,
                e.samples,
                100.0 * e.fraction,
                e.max_v,
                if e.clamped {
                    "; the set is bounded only over its range, so the model clamps the input there"
                } else {
                    " (the model is not clamped: it extrapolates)"
                }
            );
            eprintln!("warning: {msg}");
        }
        if let Some(c) = p.envelope.filter(|c| c.ticks_outside > 0) {
            eprintln!(
                "warning: {}: {} samples leave the identified envelope (range or rate), by up to {} V and {} V/s over its rate",
                p.axis, c.ticks_outside, c.max_voltage_excursion_v, c.max_rate_excursion_v_per_s
            );
        }
        let effects: Vec<String> = p.effects_ran.iter().map(predict::effect_label).collect();
        lines.push(format!(
            "{}: {} with effects [{}] on {}: rms {:.4e} m, r2 {}, mrd {} %",
            p.axis,
            p.model.name(),
            effects.join(", "),
            a.data.display(),
            p.fit.rms,
            json!(p.fit.r2),
            json!(p.fit.mrd_percent),
        ));
    }
    if let Some(bands) = &bands {
        for ((line, band), p) in lines.iter_mut().zip(bands).zip(&axes) {
            match band {
                Ok(b) => line.push_str(&format!(
                    "; prediction band of the fit: rms {b:.4e} m (measured / band {:.2})",
                    p.fit.rms / b
                )),
                Err(why) => line.push_str(&format!("; no prediction band: {why}")),
            }
        }
    }
    let zeroed: Vec<f64> = axes
        .iter()
        .zip(&records)
        .map(|(p, r)| {
            let (y, q) = (&r.y_m[from..], &p.predicted_m[from..]);
            let n = y.len().max(1) as f64;
            let mean = y.iter().zip(q).map(|(y, q)| y - q).sum::<f64>() / n;
            (y.iter()
                .zip(q)
                .map(|(y, q)| (y - q - mean).powi(2))
                .sum::<f64>()
                / n)
                .sqrt()
        })
        .collect();
    if a.free_offset {
        for (line, z) in lines.iter_mut().zip(&zeroed) {
            line.push_str(&format!(", zeroed rms {z:.4e} m"));
        }
    }
    let mut report = json!({
        "params_file": a.params.display().to_string(),
        "data": a.data.display().to_string(),
        "start_s": a.start,
        "periodic_warmup": a.periodic_warmup,
        "output_filter": a.output_filter,
        "axes": axes.iter().map(predict::axis_json).collect::<Vec<_>>(),
    });
    if let (Some(r), serde_json::Value::Object(id)) = (report.as_object_mut(), to_json(&identity)?)
    {
        r.extend(id);
    }
    if a.free_offset {
        report["rms_zeroed_m"] = json!(zeroed);
    }
    if let Some(bands) = &bands {
        report["fit_report"] = json!(a.fit_report.as_ref().map(|p| p.display().to_string()));
        for (i, (band, p)) in bands.iter().zip(&axes).enumerate() {
            let band = band.as_ref().ok().copied();
            if let Some(entry) = report["axes"].get_mut(i).and_then(|e| e.as_object_mut()) {
                entry.insert("prediction_band_rms_m".into(), json!(band));
                entry.insert("rms_over_band".into(), json!(band.map(|b| p.fit.rms / b)));
            }
            if axes.len() == 1 {
                report["prediction_band_rms_m"] = json!(band);
            }
        }
    }
    if axes.len() == 1 {
        // One axis: its blocks also at the top level.
        report["model"] = json!(axes[0].model.name());
        report["effects_ran"] = predict::effects_json(&axes[0].effects_ran);
        report["fit"] = to_json(&axes[0].fit)?;
    }
    write_json(&a.report, &report, "--report")?;
    let mut written = vec![a.report.display().to_string()];
    if let Some(out) = &a.out {
        predict::write_series(out, &records, &axes)?;
        written.push(out.display().to_string());
    }
    if let Some(dir) = &a.plots {
        written.extend(predict::write_plots(dir, "predict", &records, &axes, from)?);
    }
    Ok(format!(
        "{identity}\n{}\nwritten: {}",
        lines.join("\n"),
        written.join(", ")
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An input in millivolts read as volts leaves the 0–120 V the board's chain drives: named
    /// with its column and suffix; inside the drive range, or not a voltage, it is not.
    #[test]
    fn an_input_beyond_the_io_chain_is_named_with_its_column_and_suffix() {
        let dir = tempfile::tempdir().unwrap();
        let data = dir.path().join("r.csv");
        std::fs::write(&data, "# a comment\nt_s,u_mV,y_m\n0,0,0\n").unwrap();
        assert_eq!(input_columns(&data, None), ["u_mV"]);
        assert_eq!(input_columns(&data, Some("ux_V, uy_V")), ["ux_V", "uy_V"]);
        let record = |u_max: f64| {
            let u: Vec<f64> = (0..20).map(|k| u_max * f64::from(k) / 19.0).collect();
            Record::from_parts(
                data.clone(),
                (0..20).map(f64::from).collect(),
                u,
                vec![0.0; 20],
            )
        };
        let io = piezo_stage::Io::placeholder();
        let stage = Path::new("stage.toml");
        let names = ["ux_V".to_string(), "uy_V".to_string()];
        let w = drive_warnings(&data, &names, &[record(120.0), record(1.2e5)], &io, stage);
        assert_eq!(w.len(), 1, "{w:?}");
        assert!(
            w[0].contains("`uy_V`")
                && w[0].contains("suffix `_V`")
                && w[0].contains("0–120 V")
                && w[0].contains("stage.toml"),
            "{}",
            w[0]
        );
        let force = ["u_N".to_string()];
        assert!(drive_warnings(&data, &force, &[record(1e3)], &io, stage).is_empty());
    }

    /// Records are held out in turn: the same file twice, or the same samples under another
    /// name, is refused with both names; two records with their own samples are joined.
    #[test]
    fn a_record_given_twice_is_refused_with_both_names() {
        let record = |name: &str, gain: f64| {
            Record::from_parts(
                PathBuf::from(name),
                (0..20).map(|k| 1e-4 * f64::from(k)).collect(),
                (0..20).map(f64::from).collect(),
                (0..20).map(|k| gain * f64::from(k)).collect(),
            )
        };
        for (a, b) in [("a.csv", "a.csv"), ("a.csv", "copy.csv")] {
            let err = Record::concatenate(vec![record(a, 1e-7), record(b, 1e-7)])
                .unwrap_err()
                .to_string();
            assert!(
                err.contains(&format!("{b}: the same record as {a}")),
                "{err}"
            );
        }
        let joined =
            Record::concatenate(vec![record("a.csv", 1e-7), record("b.csv", 2e-7)]).unwrap();
        assert_eq!(joined.segments, [0, 20]);
    }

    #[test]
    fn the_exponent_at_one_is_no_bound_warning_but_other_bounds_are() {
        let bounds = [(-1.5, 1.0), (-1.0, 30.0), (1.0, 5.0)];
        let at = |theta: &[f64]| at_search_bounds(ModelKind::Symmetric, theta, &bounds);
        assert!(at(&[0.0, 1.0, 1.0]).is_empty());
        assert_eq!(
            at(&[0.0, 1.0, 5.0]),
            [SearchCoordinate::Exponent.description()]
        );
        assert_eq!(
            at(&[0.0, -1.0, 2.0]),
            [SearchCoordinate::LoopShape.description()]
        );
        let dynamic = [
            (-1.5, 1.0),
            (-1.0, 30.0),
            (1.0, 5.0),
            (-2.0, 2.0),
            (-2.5, -0.31),
        ];
        assert_eq!(
            at_search_bounds(ModelKind::Dynamic, &[0.0, 1.0, 2.0, 0.0, -0.31], &dynamic),
            [SearchCoordinate::NaturalFrequency.description()]
        );
    }
}
