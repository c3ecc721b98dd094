//! `host-sim compensate`: the voltages the firmware would command for a reference record, computed
//! on the host with the same core code, for a wave table or any DAC.
//!
//! ```text
//! host-sim compensate --params STAGE.toml --reference REF.csv --out U.csv
//! ```
//!
//! * `STAGE.toml`: a stage file (`piezo_stage::StageFile::load`: parsed and validated with the
//!   core's constructors at its `loop_rate_hz`); each axis a static model (symmetric or
//!   asymmetric) with its compensator and effects.
//! * `REF.csv`: `t_s` and the desired stage output `r_<unit>` (one-axis stage file) or `rx_<unit>`
//!   and `ry_<unit>` (two axes), unit `m`, `mm`, `um` or `nm`, sampled at the stage file's loop
//!   period T = 1/`loop_rate_hz` (its `t_s` a record's time base, `csv::Rows::time`; the mean
//!   step within 1e-6 of T, every step within 1 %; errors name the file and the lines).
//!   Every reference value must be finite in the core's f32.
//! * `U.csv`: `t_s,u_V` or `t_s,ux_V,uy_V`: the stack voltage of each tick \[V\] (the amplifier's
//!   output; a DAC sample is this / `io.amplifier_gain_v_per_v`).
//! * `--plot FIG.svg|.png`: per axis the reference r, the position y the stage file's forward
//!   model (with its effects, as `predict` runs it, from rest at `output_min_v` like the
//!   compensator) predicts for the voltages, the voltages, and e = y − r; ranges from `--settle`
//!   seconds on, the start-up transient before it shaded; the summary adds the RMS of e there.
//!
//! Per tick j, exactly the firmware's loop (`piezo_core::inverse_chain`, the code the firmware's
//! `xy_loop` calls), from rest at each axis's `output_min_v` u0 (`CompensatorState::at_rest(u0)`,
//! `EffectsState::at_rest(u0)`):
//!
//! ```text
//! r[j + L]                         the reference sampled L = M + max ⌈D⌉ ticks ahead
//!                                  (its last sample held past the end)
//! z*[j+M] = decouple(κx, κy, r(j+M+D) − d((j+M+D)·T))      delay, drift, coupling (two axes)
//! w*[j]   = s*(z*[j−1], z*[j], z*[j+1]) − creep[j] − e·(u[j−1] − u_c)²   mode, creep, even term
//! u[j]    = compensator(w*[j])     inverse hysteresis model, inside the output window and the
//!                                  slew limit of the stage file
//! commit(u[j], w[j])               the effects state follows the voltage commanded
//! ```
//!
//! The stage output of tick j, r\[j\], appears at sample j (after the delay D). Without effects
//! w\*\[j\] = r\[j\]. The firmware's safety guard (same window and slew limit, plus a margin) never
//! acts on these voltages, so they are the ones the firmware writes, to f32 rounding
//! (`tests/tests/qemu_compensate.rs` checks the QEMU image against this command).

use crate::csv::{read_rows, write_csv, Table};
use crate::identify::unit_factor;
use piezo_core::{
    compensate_pair, compensate_periodic_pair, compensate_periodic_single, compensate_single,
    FeedforwardAxis, FeedforwardCounts, InverseChain, PeriodicSettings, PeriodicSettling,
};
use piezo_stage::{AxisChain, StageError, StageErrorKind, StageFile, ValidStage};
use std::path::{Path, PathBuf};

/// Arguments of `compensate`.
#[derive(Debug, clap::Args)]
pub struct CompensateArgs {
    /// Stage file (TOML): models, effects, limits and loop rate of each axis.
    #[arg(long)]
    pub params: PathBuf,
    /// Reference record (CSV): `t_s` and `r_m` (one axis) or `rx_m`, `ry_m` (two axes); `_um`,
    /// `_nm`, `_mm` also accepted (and `t_ms`, `t_us`, `t_ns`); sampled at the stage file's loop
    /// rate. With `--signal`: where
    /// the generated reference is written first.
    #[arg(long)]
    pub reference: PathBuf,
    /// Generate the reference from SPEC (`host-sim simulate`'s signal grammar, values in µm,
    /// sampled at the stage file's loop rate; the same on both axes of a two-axis stage, or a
    /// two-axis `raster`), e.g. `triangle:low=6,high=58,freq=2,duration=2`.
    #[arg(long)]
    pub signal: Option<String>,
    /// Output CSV: `t_s,u_V` or `t_s,ux_V,uy_V` (stack voltages per tick; directory created if
    /// missing).
    #[arg(long)]
    pub out: PathBuf,
    /// Figure (`.svg` or `.png`): per axis the reference and the position the stage file's
    /// model predicts for the voltages (its forward model with its effects, as `predict` runs
    /// it), the stack voltages, and the tracking error (predicted − reference).
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// With `--plot`: the first this many seconds are the start-up transient (from rest at
    /// output_min_v), shaded and left out of the axis ranges and of the RMS error reported.
    #[arg(long, default_value_t = 0.0)]
    pub settle: f64,
}

/// Help text after the options.
pub const HELP: &str = "Runs the firmware's per-tick chain on the host: the reference sampled \
ahead by the effects' lead, the inverse effects (delay, drift, coupling, mode, creep, even term), \
each axis's compensator inside the stage file's output window and slew limit, from rest at \
output_min_v. The voltages are the stack voltages (divide by io.amplifier_gain_v_per_v for the DAC).";

/// A reference record at the output samples.
#[derive(Debug, Clone, PartialEq)]
pub struct Reference {
    /// Sample times \[s\].
    pub t_s: Vec<f64>,
    /// The file line of each sample (for errors).
    pub lines: Vec<usize>,
    /// Per axis (1 or 2): the column it came from and the samples \[m\].
    pub axes: Vec<(String, Vec<f32>)>,
}

/// Reads a reference record: `t_<unit>` (a record's time base: `t_s`, or `t_ms`, `t_us`, `t_ns`)
/// and `r_<unit>` or `rx_<unit>`, `ry_<unit>`, finite in f32, converted to SI; errors name the
/// file, the line and the column.
pub fn read_reference(path: &Path) -> crate::Result<Reference> {
    let rows = read_rows(path).map_err(crate::Error::from)?;
    let table = &rows.table;
    let (t_name, t_factor) = table
        .names
        .iter()
        .filter(|n| n.starts_with("t_"))
        .find_map(|n| match crate::identify::unit_of(n) {
            Some((f, crate::identify::Quantity::Time)) => Some((n.clone(), f)),
            _ => None,
        })
        .ok_or_else(|| {
            crate::Error::Usage(format!(
                "{}: no time column: expected `t_s` (or t_ms, t_us, t_ns); columns: {}",
                path.display(),
                table.names.join(", ")
            ))
        })?;
    let t_s = rows
        .time(&t_name, t_factor)
        .map_err(crate::Error::from)?
        .iter()
        .map(|t| t * t_factor)
        .collect();
    let find = |prefix: &str| {
        table
            .names
            .iter()
            .find(|n| n.starts_with(prefix) && unit_factor(n).is_some_and(|_| !n.ends_with("_s")))
            .cloned()
    };
    let names = match (find("rx_"), find("ry_"), find("r_")) {
        (Some(x), Some(y), _) => vec![x, y],
        (_, _, Some(r)) => vec![r],
        _ => {
            return Err(crate::Error::Usage(format!(
                "{}: no reference column: expected `r_m` (one axis) or `rx_m` and `ry_m` (two \
                 axes), or the same in mm, um, nm; columns: {}",
                path.display(),
                table.names.join(", ")
            )))
        }
    };
    let axes = names
        .into_iter()
        .map(|name| {
            let factor = unit_factor(&name).unwrap_or(1.0);
            let column = rows.f32_column(&name, factor).map_err(crate::Error::from)?;
            Ok((name, column.iter().map(|&v| v as f32).collect()))
        })
        .collect::<crate::Result<_>>()?;
    Ok(Reference {
        t_s,
        lines: rows.lines,
        axes,
    })
}

/// Refuses a record whose sample period is not the loop period 1/`rate_hz`, naming the lines.
fn check_period(
    reference: &Path,
    record: &Reference,
    params: &Path,
    rate_hz: f32,
) -> crate::Result<()> {
    let t_s = &record.t_s;
    let period_s = 1.0 / f64::from(rate_hz);
    let mean = (t_s[t_s.len() - 1] - t_s[0]) / (t_s.len() - 1) as f64;
    let uneven = t_s
        .windows(2)
        .position(|w| ((w[1] - w[0]) - period_s).abs() > 1e-2 * period_s);
    if (mean - period_s).abs() > 1e-6 * period_s || uneven.is_some() {
        let line = |i: usize| record.lines.get(i).copied().unwrap_or(0);
        let at = uneven.map_or(String::new(), |i| {
            format!(
                " (the step from line {} to line {}, t_s = {} s, is {} s)",
                line(i),
                line(i + 1),
                t_s[i],
                t_s[i + 1] - t_s[i]
            )
        });
        return Err(crate::Error::Usage(format!(
            "{}: sample period {mean} s (column t_s, lines {}-{}){at} differs from the loop \
             period {period_s} s of {} (stage.loop_rate_hz = {rate_hz} Hz): resample the \
             reference at the loop rate",
            reference.display(),
            line(0),
            line(t_s.len() - 1),
            params.display()
        )));
    }
    Ok(())
}

/// The feed-forward settings of each axis of a validated stage file (read from `params`).
pub fn feedforward_axes(
    file: &StageFile,
    valid: &ValidStage,
    params: &Path,
) -> crate::Result<Vec<FeedforwardAxis>> {
    let text = std::fs::read_to_string(params).unwrap_or_default();
    feedforward_axes_of(file, valid, &params.display().to_string(), &text)
}

/// [`feedforward_axes`] of a stage file named `name` whose text is `text` (an error is located in
/// it: line, column and key).
pub fn feedforward_axes_of(
    file: &StageFile,
    valid: &ValidStage,
    name: &str,
    text: &str,
) -> crate::Result<Vec<FeedforwardAxis>> {
    valid
        .axes
        .iter()
        .zip(file.axes())
        .map(|(axis, (_, given))| match (axis.chain, axis.compensator) {
            (AxisChain::Static { effects, .. }, Some(compensator)) => Ok(FeedforwardAxis {
                compensator,
                effects,
                rest_v: given.limits.output_min_v,
            }),
            _ => {
                let message = format!(
                    "\"{}\": the firmware compensates the static models only (symmetric, \
                     asymmetric)",
                    axis.kind.name()
                );
                let key = format!("{}.model", axis.name);
                Err(
                    StageError::new(name, StageErrorKind::Invalid, &key, message)
                        .located(name, text)
                        .into(),
                )
            }
        })
        .collect()
}

/// What `compensate` computed.
#[derive(Debug, Clone, PartialEq)]
pub struct Compensation {
    /// Sample times \[s\] (the reference's).
    pub t_s: Vec<f64>,
    /// Per axis: the column name (`u_V` or `ux_V`, `uy_V`) and the stack voltage per tick \[V\].
    pub voltages_v: Vec<(String, Vec<f32>)>,
    /// Ticks, and the samples limited by the window or the slew limit.
    pub counts: FeedforwardCounts,
    /// L: ticks the reference is read ahead of the current tick.
    pub lead_ticks: u32,
    /// For a reference played in a loop ([`compensate_periodic`]): how the period settled.
    pub settling: Option<PeriodicSettling>,
}

impl Compensation {
    /// As a CSV table: `t_s` and the voltages.
    pub fn to_table(&self) -> Table {
        let mut names = vec!["t_s".to_string()];
        let mut columns = vec![self.t_s.clone()];
        for (name, u) in &self.voltages_v {
            names.push(name.clone());
            columns.push(u.iter().map(|&v| f64::from(v)).collect());
        }
        Table {
            path: PathBuf::new(),
            names,
            columns,
        }
    }
}

/// Runs the firmware's chain for the stage file at `params` over the record at `reference`;
/// every voltage must be finite (refused naming the tick, its time and the reference's line).
pub fn compensate(params: &Path, reference: &Path) -> crate::Result<Compensation> {
    compensate_record(params, reference, &|| read_reference(reference))
}

/// The record `read` gives, from `reference` (perhaps changed; errors name that file's lines),
/// read after the stage file loaded.
type ReadRecord<'a> = &'a dyn Fn() -> crate::Result<Reference>;

/// [`compensate`] over the record `read` gives.
fn compensate_record(
    params: &Path,
    reference: &Path,
    read: ReadRecord<'_>,
) -> crate::Result<Compensation> {
    let (file, valid) = StageFile::load(params).map_err(crate::Error::from)?;
    let text = std::fs::read_to_string(params).unwrap_or_default();
    let record = &read()?;
    compensate_stage(&file, &valid, (params, &text), reference, record, false)
}

/// The stage file `file` (validated as `valid`; named `params.0`, its text `params.1`, for
/// located errors) run over `record` (from `reference`, named in errors): from rest as
/// [`compensate`], or played in a loop as [`compensate_periodic`] when `periodic`. The one
/// function behind `host-sim compensate` and the Python package's `Stage.compensate`.
pub fn compensate_stage(
    file: &StageFile,
    valid: &ValidStage,
    (params, text): (&Path, &str),
    reference: &Path,
    record: &Reference,
    periodic: bool,
) -> crate::Result<Compensation> {
    if periodic {
        return compensate_periodic_stage(file, valid, (params, text), reference, record);
    }
    check_period(reference, record, params, file.stage.loop_rate_hz)?;
    let axes = feedforward_axes_of(file, valid, &params.display().to_string(), text)?;
    let result = run_chain(&axes, params, reference, record)?;
    for (name, u) in &result.voltages_v {
        if let Some(k) = u.iter().position(|v| !v.is_finite()) {
            return Err(crate::Error::Usage(format!(
                "{name} is not a finite number at tick {k} (t = {} s, line {} of {}): nothing \
                 is written",
                record.t_s[k],
                record.lines[k],
                reference.display()
            )));
        }
    }
    Ok(result)
}

/// The compensator's command (from rest, or periodic as [`compensate_periodic`]) for a stage
/// whose output is `γ·y_model + c` per axis (`gain_offset[axis] = (γ, c)`, γ > 0): the chain runs
/// over `(r − c)/γ`, the output the model must give for the stage to give r.
pub fn compensate_for_gain(
    params: &Path,
    reference: &Path,
    periodic: bool,
    gain_offset: &[(f64, f64)],
) -> crate::Result<Compensation> {
    let read = || {
        let mut record = read_reference(reference)?;
        for ((_, r), &(gain, offset)) in record.axes.iter_mut().zip(gain_offset) {
            for v in r.iter_mut() {
                *v = ((f64::from(*v) - offset) / gain) as f32;
            }
        }
        Ok(record)
    };
    if periodic {
        compensate_periodic_record(params, reference, &read)
    } else {
        compensate_record(params, reference, &read)
    }
}

/// Warm-up of [`compensate_periodic`]: whole periods lasting at least this \[s\] (and at least
/// [`MIN_WARMUP_PERIODS`]).
pub const WARMUP_S: f64 = 0.1;
/// Fewest warm-up periods of [`compensate_periodic`].
pub const MIN_WARMUP_PERIODS: usize = 2;
/// Longest settling of [`compensate_periodic`]: whole periods lasting at most this \[s\] (and
/// at least the warm-up).
pub const MAX_SETTLING_S: f64 = 20.0;
/// The period is settled when no command moves more than this share of the output window from
/// the period before (1.2 mV for a 0–120 V window, below a 16-bit DAC's step).
pub const SETTLED_WINDOW_SHARE: f64 = 1e-5;

/// The settling rule of [`compensate_periodic`] for a period of `period_s` and the output
/// windows of `axes`.
pub fn periodic_settings(axes: &[FeedforwardAxis], period_s: f64) -> PeriodicSettings {
    let periods = |s: f64| (s / period_s).ceil().clamp(0.0, 1e6) as usize;
    let min_periods = periods(WARMUP_S).max(MIN_WARMUP_PERIODS);
    let span = axes
        .iter()
        .map(|a| {
            let s = a.compensator.settings();
            f64::from(s.limits.output_max_v - s.limits.output_min_v)
        })
        .fold(f64::INFINITY, f64::min);
    PeriodicSettings {
        min_periods,
        max_periods: periods(MAX_SETTLING_S).max(min_periods),
        tolerance_v: (SETTLED_WINDOW_SHARE * span) as f32,
    }
}

/// The compensator's command for a reference played in a loop: the record at `reference` is
/// one period; the chain of [`compensate`] runs from rest over it repeated
/// ([`piezo_core::compensate_periodic_pair`]) until a period moves no command more than
/// [`SETTLED_WINDOW_SHARE`] of the window from the one before, after at least the warm-up (the
/// fewest whole periods lasting [`WARMUP_S`], at least [`MIN_WARMUP_PERIODS`]: the hysteresis
/// leaves its first-loading branch and settles on the periodic loop, which a Bouc-Wen loop
/// does only geometrically) and at most [`MAX_SETTLING_S`]; the look-ahead of the period's end
/// reads the next period. The period taken, `t_s` the record's; `counts` are of the whole run,
/// `settling` says how it ended (a stage file with drift moves every period).
pub fn compensate_periodic(params: &Path, reference: &Path) -> crate::Result<Compensation> {
    compensate_periodic_record(params, reference, &|| read_reference(reference))
}

/// [`compensate_periodic`] over the record `read` gives.
fn compensate_periodic_record(
    params: &Path,
    reference: &Path,
    read: ReadRecord<'_>,
) -> crate::Result<Compensation> {
    let (file, valid) = StageFile::load(params).map_err(crate::Error::from)?;
    let text = std::fs::read_to_string(params).unwrap_or_default();
    let record = &read()?;
    compensate_periodic_stage(&file, &valid, (params, &text), reference, record)
}

/// [`compensate_periodic`] of a loaded stage file (see [`compensate_stage`]).
fn compensate_periodic_stage(
    file: &StageFile,
    valid: &ValidStage,
    (params, text): (&Path, &str),
    reference: &Path,
    record: &Reference,
) -> crate::Result<Compensation> {
    check_period(reference, record, params, file.stage.loop_rate_hz)?;
    let axes = feedforward_axes_of(file, valid, &params.display().to_string(), text)?;
    let n = record.t_s.len();
    let period_s = n as f64 / f64::from(file.stage.loop_rate_hz);
    let settings = periodic_settings(&axes, period_s);
    let (voltages_v, settling, lead_ticks) = match (axes.as_slice(), record.axes.as_slice()) {
        ([x], [(_, r)]) => {
            let mut u = vec![0.0; n];
            let settling = compensate_periodic_single(x, r, settings, &mut u);
            let lead = InverseChain::single(x.effects, x.rest_v).map_or(0, |c| c.lead_ticks());
            (vec![("u_V".to_string(), u)], settling, lead)
        }
        ([x, y], [(_, rx), (_, ry)]) => {
            let (mut ux, mut uy) = (vec![0.0; n], vec![0.0; n]);
            let settling = compensate_periodic_pair([x, y], [rx, ry], settings, [&mut ux, &mut uy]);
            let lead = InverseChain::new([x.effects, y.effects], [x.rest_v, y.rest_v])
                .map_or(0, |c| c.lead_ticks());
            (
                vec![("ux_V".to_string(), ux), ("uy_V".to_string(), uy)],
                settling,
                lead,
            )
        }
        (stage_axes, columns) => return Err(axes_mismatch(params, stage_axes, reference, columns)),
    };
    for (name, u) in &voltages_v {
        if let Some(k) = u.iter().position(|v| !v.is_finite()) {
            return Err(crate::Error::Usage(format!(
                "{name} is not a finite number at tick {k} of the period (t = {} s, line {} of \
                 {}), played in a loop: nothing is written",
                record.t_s[k],
                record.lines[k],
                reference.display()
            )));
        }
    }
    Ok(Compensation {
        t_s: record.t_s.clone(),
        voltages_v,
        counts: settling.counts,
        lead_ticks,
        settling: Some(settling),
    })
}

/// A stage file's axes and a reference's columns that do not match.
fn axes_mismatch(
    params: &Path,
    stage_axes: &[FeedforwardAxis],
    reference: &Path,
    columns: &[(String, Vec<f32>)],
) -> crate::Error {
    crate::Error::Usage(format!(
        "{} has {} axis(es) but {} has {} reference column(s) ({}): give `r_m` for a one-axis \
         stage file, `rx_m` and `ry_m` for a two-axis one",
        params.display(),
        stage_axes.len(),
        reference.display(),
        columns.len(),
        columns
            .iter()
            .map(|(name, _)| name.as_str())
            .collect::<Vec<_>>()
            .join(", ")
    ))
}

/// The chain of `axes` (from `params`) over `record` (from `reference`).
fn run_chain(
    axes: &[FeedforwardAxis],
    params: &Path,
    reference: &Path,
    record: &Reference,
) -> crate::Result<Compensation> {
    let n = record.t_s.len();
    match (axes, record.axes.as_slice()) {
        ([x], [(_, r)]) => {
            let mut u = vec![0.0; n];
            let counts = compensate_single(x, r, &mut u);
            Ok(Compensation {
                t_s: record.t_s.clone(),
                voltages_v: vec![("u_V".into(), u)],
                counts,
                lead_ticks: InverseChain::single(x.effects, x.rest_v).map_or(0, |c| c.lead_ticks()),
                settling: None,
            })
        }
        ([x, y], [(_, rx), (_, ry)]) => {
            let (mut ux, mut uy) = (vec![0.0; n], vec![0.0; n]);
            let counts = compensate_pair([x, y], [rx, ry], [&mut ux, &mut uy]);
            Ok(Compensation {
                t_s: record.t_s.clone(),
                voltages_v: vec![("ux_V".into(), ux), ("uy_V".into(), uy)],
                counts,
                lead_ticks: InverseChain::new([x.effects, y.effects], [x.rest_v, y.rest_v])
                    .map_or(0, |c| c.lead_ticks()),
                settling: None,
            })
        }
        (stage_axes, columns) => Err(axes_mismatch(params, stage_axes, reference, columns)),
    }
}

/// `host-sim compensate`: computes and writes the voltages; returns the summary line.
pub fn compensate_cmd(a: &CompensateArgs) -> crate::Result<String> {
    if let Some(plot) = &a.plot {
        crate::track_plot::check_plot_path("--plot", plot)?;
    }
    if !(a.settle >= 0.0 && a.settle.is_finite()) {
        return Err(crate::Error::Usage(format!(
            "--settle {}: must be a time ≥ 0 s",
            a.settle
        )));
    }
    if let Some(spec) = &a.signal {
        write_reference(&a.params, spec, &a.reference)?;
    }
    let result = compensate(&a.params, &a.reference)?;
    write_csv(&a.out, &result.to_table())
        .map_err(|e| crate::Error::Usage(format!("--out: {e}")))?;
    let (_, valid) = StageFile::load(&a.params).map_err(crate::Error::from)?;
    let envelope = envelope_summary(&valid, &result.voltages_v);
    let plotted = match &a.plot {
        Some(plot) => plot_compensation(a, plot, &result)?,
        None => String::new(),
    };
    let c = result.counts;
    Ok(format!(
        "compensate: {} ticks of {} written to {} (lead {} ticks; limited by the window or slew \
         limit: {} samples){envelope}{plotted}",
        c.ticks,
        result
            .voltages_v
            .iter()
            .map(|(name, _)| name.as_str())
            .collect::<Vec<_>>()
            .join(", "),
        a.out.display(),
        result.lead_ticks,
        c.limited
    ))
}

/// The position the stage file of `a` predicts for the voltages of `result` (its forward model
/// with its effects, run as `predict` runs it: [`crate::identify::predict::predict_axes`], from
/// rest at the first voltage) against the reference, drawn to `plot`
/// ([`crate::track_plot::tracking_charts`], scored from `--settle`); returns the summary's
/// `; predicted tracking error …` with the RMS of predicted − reference over the scored window.
fn plot_compensation(
    a: &CompensateArgs,
    plot: &Path,
    result: &Compensation,
) -> crate::Result<String> {
    use crate::identify::{predict, Record};
    use crate::track_plot::{tracking_charts, write_figure, TrackAxis};
    let stage = predict::read_stage(&a.params)?;
    let reference = read_reference(&a.reference)?;
    let t_s = &result.t_s;
    let from = t_s.partition_point(|&t| t < t_s[0] + a.settle);
    if from + 1 >= t_s.len() {
        return Err(crate::Error::Usage(format!(
            "--settle {}: leaves fewer than two of the {} samples to score",
            a.settle,
            t_s.len()
        )));
    }
    // The compensator starts from rest at each axis's output_min_v; the model starts from rest at
    // its first input: one sample at output_min_v, one period before the first tick, puts it in
    // the same state (and is dropped after).
    let period_s = 1.0 / f64::from(stage.file.stage.loop_rate_hz);
    let with_rest: Vec<Record> = result
        .voltages_v
        .iter()
        .zip(&reference.axes)
        .zip(stage.file.axes())
        .map(|(((_, u), (_, r)), (_, axis))| {
            let rest = f64::from(axis.limits.output_min_v);
            Record::from_parts(
                a.reference.clone(),
                std::iter::once(t_s[0] - period_s)
                    .chain(t_s.iter().copied())
                    .collect(),
                std::iter::once(rest)
                    .chain(u.iter().map(|&v| f64::from(v)))
                    .collect(),
                std::iter::once(f64::from(r[0]))
                    .chain(r.iter().map(|&v| f64::from(v)))
                    .collect(),
            )
        })
        .collect();
    let mut predicted = predict::predict_axes(&stage, &with_rest, from + 1)?;
    for p in &mut predicted {
        p.predicted_m.remove(0);
    }
    let records: Vec<Record> = with_rest
        .into_iter()
        .map(|r| Record::from_parts(r.path, t_s.clone(), r.u[1..].to_vec(), r.y_m[1..].to_vec()))
        .collect();
    let names: Vec<&str> = match predicted.len() {
        1 => vec![""],
        _ => predicted.iter().map(|p| p.axis).collect(),
    };
    let axes: Vec<TrackAxis<'_>> = records
        .iter()
        .zip(&predicted)
        .zip(&names)
        .map(|((r, p), name)| TrackAxis {
            name,
            reference_m: &r.y_m,
            position_m: &p.predicted_m,
            position: "predicted",
            voltage_v: &r.u,
        })
        .collect();
    let charts = tracking_charts(t_s, &axes, from)?;
    write_figure("--plot", plot, &charts, axes.len())?;
    let rms: Vec<String> = predicted
        .iter()
        .map(|p| format!("{} rms {:.4e} m", p.axis, p.fit.rms))
        .collect();
    Ok(format!(
        "; predicted tracking error from t = {} s: {}; figure {}",
        t_s[from],
        rms.join(", "),
        plot.display()
    ))
}

/// The ticks of each axis's voltages `voltages_v` (one per loop tick) that leave its identified
/// envelope, as the firmware counts them (`piezo_core::EnvelopeMonitor::count`, from rest at the
/// first voltage), per axis of `valid` that has one.
pub fn envelope_counts(
    valid: &ValidStage,
    voltages_v: &[(String, Vec<f32>)],
) -> Vec<(&'static str, piezo_core::EnvelopeCounts)> {
    valid
        .axes
        .iter()
        .zip(voltages_v)
        .filter_map(|(axis, (_, u))| Some((axis.name, axis.envelope?.count(u.iter().copied()))))
        .collect()
}

/// `; outside the identified envelope: x N ticks (…)` for the summary line, or nothing when no
/// axis has an envelope.
fn envelope_summary(valid: &ValidStage, voltages_v: &[(String, Vec<f32>)]) -> String {
    let counts = envelope_counts(valid, voltages_v);
    if counts.is_empty() {
        return String::new();
    }
    let each: Vec<String> = counts
        .iter()
        .map(|(name, c)| {
            format!(
                "{name} {} ticks (by up to {} V, {} V/s over the rate)",
                c.ticks_outside, c.max_voltage_excursion_v, c.max_rate_excursion_v_per_s
            )
        })
        .collect();
    format!("; outside the identified envelope: {}", each.join(", "))
}

/// Writes the reference of `spec` (values in µm) at the loop rate of the stage file at `params`:
/// `t_s,r_um` for one axis, `t_s,rx_um,ry_um` for two.
fn write_reference(params: &Path, spec: &str, path: &Path) -> crate::Result<()> {
    let (file, _) = StageFile::load(params).map_err(crate::Error::from)?;
    let axes = file.axes().len();
    let spec = crate::signal::SignalSpec::parse(spec)
        .map_err(|e| crate::Error::Usage(format!("--signal: {e}")))?;
    let signals = spec
        .build(axes)
        .map_err(|e| crate::Error::Usage(format!("--signal: {e}")))?;
    let rate = f64::from(file.stage.loop_rate_hz);
    if let Some(duration_s) = spec.duration_s {
        if let Some(w) = crate::simulate::csv_length_warning(&spec, duration_s, "duration=") {
            eprintln!("warning: {w}");
        }
    }
    let n = (spec.duration_s.unwrap_or(spec.default_duration_s()) * rate).round() as usize + 1;
    let t_s: Vec<f64> = (0..n).map(|k| k as f64 / rate).collect();
    let mut names = vec!["t_s".to_string()];
    let mut columns = vec![t_s.clone()];
    for (i, signal) in signals.iter().enumerate().take(axes) {
        names.push(match axes {
            1 => "r_um".into(),
            _ => format!("r{}_um", ["x", "y"][i]),
        });
        columns.push(t_s.iter().map(|&t| signal.value(t)).collect());
    }
    let table = Table {
        path: path.into(),
        names,
        columns,
    };
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(crate::Error::write("--reference", dir))?;
    }
    write_csv(path, &table).map_err(|e| crate::Error::Usage(format!("--reference: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::demo::run_xy_stage;
    use crate::effects::Effects;
    use crate::plant::XyStage;

    fn firmware_params(name: &str) -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../firmware/params")
            .join(name)
    }

    /// A directory of the test's own, removed when dropped.
    fn scratch(name: &str) -> tempfile::TempDir {
        tempfile::Builder::new()
            .prefix(&format!("host_sim_compensate_{name}_"))
            .tempdir()
            .unwrap()
    }

    /// Writes a reference CSV with `columns` (name, f(t)) at `rate_hz` for `n` samples.
    fn write_reference(
        path: &Path,
        rate_hz: f64,
        n: usize,
        columns: &[(&str, &dyn Fn(f64) -> f64)],
    ) {
        let mut text = String::from("t_s");
        for (name, _) in columns {
            text.push(',');
            text.push_str(name);
        }
        text.push('\n');
        for k in 0..n {
            let t = k as f64 / rate_hz;
            text.push_str(&t.to_string());
            for (_, f) in columns {
                text.push_str(&format!(",{}", f(t)));
            }
            text.push('\n');
        }
        std::fs::write(path, text).unwrap();
    }

    /// A reference in ms and µm reads as the same one in s and m; a time column of no time unit
    /// is refused, naming the columns.
    #[test]
    fn a_reference_is_read_in_the_units_its_suffixes_name() {
        let scratch = scratch("units");
        let dir = scratch.path();
        let (si, scaled, untimed) = (dir.join("si.csv"), dir.join("ms.csv"), dir.join("no.csv"));
        let r = |t: f64| 10e-6 + 5e-6 * t;
        write_reference(&si, 1000.0, 20, &[("rx_m", &r), ("ry_m", &r)]);
        let mut text = String::from("t_ms,rx_µm,ry_um\n");
        for k in 0..20 {
            let t = k as f64 / 1000.0;
            text.push_str(&format!("{},{},{}\n", t * 1e3, r(t) * 1e6, r(t) * 1e6));
        }
        std::fs::write(&scaled, text).unwrap();
        std::fs::write(&untimed, "x_m,r_m\n0,1e-6\n1,1e-6\n").unwrap();
        let (a, b) = (
            read_reference(&si).unwrap(),
            read_reference(&scaled).unwrap(),
        );
        assert_eq!(a.t_s.len(), b.t_s.len());
        for (x, y) in a.t_s.iter().zip(&b.t_s) {
            assert!((x - y).abs() < 1e-12, "{x} vs {y}");
        }
        for ((_, x), (_, y)) in a.axes.iter().zip(&b.axes) {
            for (p, q) in x.iter().zip(y) {
                assert!((p - q).abs() <= 1e-6 * p.abs(), "{p} vs {q}");
            }
        }
        let e = read_reference(&untimed).unwrap_err().to_string();
        assert!(
            e.contains("no time column") && e.contains("x_m, r_m"),
            "{e}"
        );
    }

    fn triangle(low: f64, high: f64, frequency_hz: f64) -> impl Fn(f64) -> f64 {
        move |t| crate::demo::triangle(low, high, frequency_hz, t)
    }

    /// The XY stage's platform model: `firmware/params/xy-stage.toml` (the plant's stacks: their
    /// exact Bouc-Wen sets and free-elongation gain d, no effects) with the output map scaled by
    /// the flexure's static gain G, so that it gives the platform position the plant measures,
    /// at the test's 10 kHz (the file's own rate is 20 kHz).
    fn platform_stage_file(dir: &Path, gain: [f64; 2]) -> PathBuf {
        let path = firmware_params("xy-stage.toml");
        let text = std::fs::read_to_string(&path).unwrap();
        let mut file = StageFile::parse(&path.display().to_string(), &text).unwrap();
        file.stage.loop_rate_hz = 10_000.0;
        for (axis, g) in [Some(&mut file.x), file.y.as_mut()].into_iter().zip(gain) {
            let map = axis.unwrap().static_map.as_mut().unwrap();
            map.k1_m_per_v = (f64::from(map.k1_m_per_v) * g) as f32;
            map.k2_m_per_h = (f64::from(map.k2_m_per_h) * g) as f32;
        }
        let out = dir.join("xy-platform.toml");
        std::fs::write(
            &out,
            file.to_toml("xy-stage.toml, output scaled to the platform"),
        )
        .unwrap();
        out
    }

    #[test]
    fn voltages_track_the_xy_stage_plant() {
        // The voltages, applied through a zero-order hold to host-sim's independent f64 XY stage
        // (Bouc-Wen stacks, flexure mechanics with modes at 3.2 and 2.2 kHz), must put the
        // platform on the reference: a triangle between 10 % and 90 % of the stroke, faded in
        // from rest over 5 ms (a step from rest would ring the lightly damped modes).
        let scratch = scratch("track");
        let dir = scratch.path();
        let plant = XyStage::default();
        let params = platform_stage_file(dir, plant.static_gain());
        // The platform's stroke over 0–120 V (38 µm of free stroke times G).
        let stroke_m = plant.static_gain().map(|g| g * 38e-6);
        let (rate, n) = (10_000.0, 4_000);
        let fade = |t: f64| {
            if t < 5e-3 {
                0.5 - 0.5 * (std::f64::consts::PI * t / 5e-3).cos()
            } else {
                1.0
            }
        };
        let shape = |i: usize, frequency_hz: f64| {
            let s = stroke_m[i];
            move |t: f64| fade(t) * crate::demo::triangle(0.1 * s, 0.9 * s, frequency_hz, t)
        };
        let (fx, fy) = (shape(0, 10.0), shape(1, 5.0));
        let reference = dir.join("ref.csv");
        write_reference(&reference, rate, n, &[("rx_m", &fx), ("ry_m", &fy)]);
        let result = compensate(&params, &reference).unwrap();
        assert_eq!(result.lead_ticks, 0);
        assert_eq!(result.counts.limited, 0);
        let out = dir.join("u.csv");
        write_csv(&out, &result.to_table()).unwrap();
        let back = crate::csv::read_csv(&out).unwrap();
        assert_eq!(back.names, ["t_s", "ux_V", "uy_V"]);
        let voltages = [1, 2].map(|c| back.columns[c].clone());
        for (c, (_, u)) in result.voltages_v.iter().enumerate() {
            assert!(u.iter().zip(&voltages[c]).all(|(&a, &b)| a == b as f32));
        }
        let y = run_xy_stage(&plant, &voltages, rate, &Effects::default()).unwrap();
        let settle = 10; // 1 ms
        for (i, (r, name)) in [(&fx as &dyn Fn(f64) -> f64, "x"), (&fy, "y")]
            .into_iter()
            .enumerate()
        {
            let sq: f64 = (settle..n)
                .map(|k| (y[i][k] - r(k as f64 / rate)).powi(2))
                .sum();
            let rms = (sq / (n - settle) as f64).sqrt();
            println!(
                "{name}: rms {:.1} nm = {:.3} % of the {:.1} µm stroke",
                rms * 1e9,
                100.0 * rms / stroke_m[i],
                stroke_m[i] * 1e6
            );
            assert!(rms <= 3e-3 * stroke_m[i], "{name}: rms {rms:e} m");
        }
    }

    #[test]
    fn one_axis_stage_with_effects_and_micrometres() {
        // A one-axis stage file (the x axis of xy-stage-effects.toml, coupling taken off) and a
        // reference in µm: the same voltages as the core's single-axis chain in metres.
        let scratch = scratch("one");
        let dir = scratch.path();
        let text = std::fs::read_to_string(firmware_params("xy-stage-effects.toml")).unwrap();
        let one_axis = text
            .split("\n[y]")
            .next()
            .unwrap()
            .replace("coupling = 0.02", "");
        let params = dir.join("x.toml");
        std::fs::write(&params, one_axis).unwrap();
        let reference = dir.join("ref.csv");
        let f = triangle(5.0, 30.0, 20.0);
        write_reference(&reference, 10_000.0, 500, &[("r_um", &f)]);
        let result = compensate(&params, &reference).unwrap();
        assert_eq!(result.voltages_v.len(), 1);
        assert_eq!(result.voltages_v[0].0, "u_V");
        assert_eq!(result.lead_ticks, 2);
        let (file, valid) = StageFile::load(&params).unwrap();
        let axis = feedforward_axes(&file, &valid, &params).unwrap()[0];
        let r: Vec<f32> = (0..500)
            .map(|k| (f(k as f64 / 1e4) * 1e-6) as f32)
            .collect();
        let mut u = vec![0.0; 500];
        compensate_single(&axis, &r, &mut u);
        // µm → m in f64, then f32: the same samples, the same voltages.
        assert_eq!(u, result.voltages_v[0].1);
    }

    #[test]
    fn errors_name_the_file_and_the_column() {
        let scratch = scratch("errors");
        let dir = scratch.path();
        let params = firmware_params("xy-stage-effects.toml");
        let reference = dir.join("ref.csv");
        let f = |t: f64| 10e-6 + t;
        // Wrong rate: names both files and both periods.
        write_reference(&reference, 5_000.0, 100, &[("rx_m", &f), ("ry_m", &f)]);
        let e = compensate(&params, &reference).unwrap_err().to_string();
        assert!(
            e.contains("ref.csv")
                && e.contains("xy-stage-effects.toml")
                && e.contains("0.0002")
                && e.contains("0.0001"),
            "{e}"
        );
        // One column for two axes.
        write_reference(&reference, 10_000.0, 100, &[("r_m", &f)]);
        let e = compensate(&params, &reference).unwrap_err().to_string();
        assert!(e.contains("2 axis") && e.contains("r_m"), "{e}");
        // No reference column.
        write_reference(&reference, 10_000.0, 100, &[("u_V", &f)]);
        let e = compensate(&params, &reference).unwrap_err().to_string();
        assert!(e.contains("ref.csv") && e.contains("rx_m"), "{e}");
        // A bad cell: file, line and column.
        std::fs::write(&reference, "t_s,r_m\n0,1e-6\n0.0001,oops\n").unwrap();
        let e = compensate(&params, &reference).unwrap_err().to_string();
        assert!(e.contains("ref.csv:3") && e.contains("r_m"), "{e}");
        // A stage file that does not exist.
        let e = compensate(&dir.join("none.toml"), &reference)
            .unwrap_err()
            .to_string();
        assert!(e.contains("none.toml"), "{e}");
    }
}
