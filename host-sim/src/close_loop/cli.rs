//! The `close-loop` command: its arguments, the records it reads (only the selected columns are
//! parsed; the others are ignored, whatever their names), and the files it writes (report JSON,
//! stage file, plots).

use super::{close_loop_validated, stage, write_plots, CloseLoopSettings, OutcomeReport};
use crate::identify::Record;
use crate::stage_file::{RefusalKind, StageFileReport, Verdict, WrittenStage};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Arguments of `close-loop`.
#[derive(Debug, clap::Args)]
#[command(after_help = "\
Fits the symmetric Bouc-Wen model (identify's vp-de-lm), then repeatedly screens the residual for the \
effects creep (Kelvin-Voigt or logarithmic), drift (linear or settling, independent of u), delay, \
asymmetry, dynamics (a mode, force-driven or stack-driven), rate-dependent hysteresis (the hysteretic \
part relaxes, or the Bouc-Wen operator is driven by a lag of the command) and (two-axis records) \
coupling, fits the best candidates and every phase effect (creep, delay, rate-dependent hysteresis, \
dynamics) the screening cannot separate from one of them, and adds one only if its parameters stay \
inside the range that makes it that effect, its gain holds on held-out blocks of the record (blocked \
cross-validation over time, interleaved one-period segments when the input's amplitude or rate changes \
along the record; several records: leave one record out, or interleaved segments of every record \
when one holds less than a quarter of the longest's samples) and on the --validate record, and the \
residual is not yet at the sensor noise estimated from the data. Every decision and its evidence, and \
why each other effect was not fitted, goes into the report. \
Two-axis records: --u ux_V,uy_V --y x_m,y_m.")]
pub struct CloseLoopArgs {
    /// Record to fit (CSV with unit-suffixed columns); several comma-separated records of one stage
    /// are fitted together, each from rest at its own first sample, and cross-validated by leaving
    /// one record out (on interleaved segments of every record when one holds less than a quarter
    /// of the longest's samples).
    #[arg(long)]
    pub data: PathBuf,
    /// Several records: each has its own constant sensor offset, re-estimated per record (the
    /// stage file keeps the first record's).
    #[arg(long)]
    pub free_offset: bool,
    /// Time column (default: first `t_*`).
    #[arg(long)]
    pub t: Option<String>,
    /// Input column(s), comma-separated for two axes (default: first `u_*`).
    #[arg(long)]
    pub u: Option<String>,
    /// Output column(s), comma-separated for two axes (default: first `y_*`).
    #[arg(long)]
    pub y: Option<String>,
    /// First scored time (s); earlier samples only warm the model up.
    #[arg(long, default_value_t = 0.0)]
    pub start: f64,
    /// Last time used for the fit (s).
    #[arg(long)]
    pub end: Option<f64>,
    /// Another record (another run, or the same file with --validate-start at or after --end)
    /// both models predict from its first sample, seeing only u; an effect that predicts it worse
    /// is not added, and of the effects that hold, the one that predicts it best is. A record whose
    /// scored samples were fitted is refused.
    #[arg(long)]
    pub validate: Option<PathBuf>,
    /// First scored time of the validation record (s).
    #[arg(long, default_value_t = 0.0)]
    pub validate_start: f64,
    /// Smallest share of the residual variance a candidate's screening must explain (a quarter of
    /// it) to be fitted.
    #[arg(long, default_value_t = 0.05)]
    pub min_share: f64,
    /// Seed of the base identification.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Only sets the firmware's compensator accepts (strictly monotone map), base and effects:
    /// every set kept is checked as `host-sim compensate` checks a stage file.
    #[arg(long)]
    pub invertible: bool,
    /// Report JSON to write.
    #[arg(long)]
    pub report: PathBuf,
    /// Stage file of the final model (default: the report's path with .toml).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Stage file to carry `[stage]` and `[io]` from (default: the record's rate and a placeholder io).
    #[arg(long)]
    pub stage: Option<PathBuf>,
    /// Write the stage file even if the firmware would refuse it (reported), instead of failing.
    #[arg(long)]
    pub allow_refused: bool,
    /// Directory for the plots (SVG and PNG).
    #[arg(long)]
    pub plots: Option<PathBuf>,
}

/// Reads one record per axis (`Record::read_axes`, the reader of every record): `t`, `u` and `y`
/// name the columns (defaults: the first `t_*`, `u_*`, `y_*`; `u` and `y` comma-separated for two
/// axes); cut after `end` \[s\] when given.
pub fn read_records(
    data: &Path,
    t: Option<&str>,
    u: Option<&str>,
    y: Option<&str>,
    end: Option<f64>,
) -> crate::Result<Vec<Record>> {
    let mut records = Record::read_axes(data, t, u, y)?;
    if let Some(end) = end {
        for r in &mut records {
            r.cut_after(end)?;
        }
    }
    Ok(records)
}

/// Runs `close-loop`. `[stage]` and `[io]` (`--stage`) are read before the search, so that a bad
/// file is said at once. After the search, the stage file, the plots and the report are each
/// written whatever became of the others; the report (written last) holds the firmware's verdict
/// on the set, the refusal and what could not be written. A refused set (unless `--allow-refused`)
/// or a file not written makes the command fail after that.
pub fn close_loop_cmd(a: &CloseLoopArgs) -> crate::Result<String> {
    if !(a.min_share > 0.0 && a.min_share < 1.0) {
        return Err(crate::Error::Usage(format!(
            "--min-share {}: must be in (0, 1)",
            a.min_share
        )));
    }
    let mut parts: Vec<Vec<Record>> = Vec::new();
    let data_text = a.data.to_string_lossy();
    for part in data_text
        .split(',')
        .map(str::trim)
        .filter(|p| !p.is_empty())
    {
        let axes = read_records(
            Path::new(part),
            a.t.as_deref(),
            a.u.as_deref(),
            a.y.as_deref(),
            a.end,
        )
        .map_err(|e| crate::Error::Usage(format!("--data: {e}")))?;
        parts.resize_with(axes.len(), Vec::new);
        for (i, r) in axes.into_iter().enumerate() {
            parts[i].push(r);
        }
    }
    let validation = match &a.validate {
        Some(v) => Some(
            read_records(v, a.t.as_deref(), a.u.as_deref(), a.y.as_deref(), None)
                .map_err(|e| crate::Error::Usage(format!("--validate: {e}")))?,
        ),
        None => None,
    };
    // A record fitted cannot also judge the effects on the samples they were fitted on: the same
    // record validates only from --validate-start on, at or after --end.
    let overlap = a.end.is_none_or(|end| a.validate_start < end);
    if let (true, Some(v), Some(fitted)) = (overlap, &validation, parts.first()) {
        if let Some(same) = fitted.iter().find(|r| r.is_same_record(&v[0])) {
            return Err(crate::Error::Usage(format!(
                "--validate: {} is the --data record {}, {}: the effects would be judged on \
                 samples they were fitted on (pass another run, or fit the record's first part \
                 with --end and validate its rest with --validate-start at or after it)",
                v[0].path.display(),
                same.path.display(),
                match a.end {
                    None => "fitted whole".to_string(),
                    Some(end) => format!(
                        "fitted up to --end {end} s and validated from --validate-start {} s",
                        a.validate_start
                    ),
                }
            )));
        }
    }
    let records = parts
        .into_iter()
        .map(|p| Record::concatenate(p).map_err(|e| crate::Error::Usage(format!("--data: {e}"))))
        .collect::<Result<Vec<_>, _>>()?;
    if records[0].segments.len() > 1 && a.start > 0.0 {
        return Err(crate::Error::Usage(
            "--start: with several records each is scored from its first sample".into(),
        ));
    }
    if let Some(v) = &validation {
        if v.len() != records.len() {
            return Err(crate::Error::Usage(format!(
                "--validate: {} axes, --data has {}",
                v.len(),
                records.len()
            )));
        }
        // The models run at the fitted records' sample period; another period would be another
        // discrete model, and every effect would be judged on a run it does not describe.
        let ts = records[0].sample_period_s();
        if let Some(r) = v
            .iter()
            .find(|r| (r.sample_period_s() - ts).abs() > 1e-3 * ts)
        {
            return Err(crate::Error::Usage(format!(
                "--validate: {}: sample period {:.6e} s differs from --data's {ts:.6e} s \
                 (record it, or resample it, at the fitted records' rate)",
                r.path.display(),
                r.sample_period_s()
            )));
        }
    }
    let (stage, io) = stage::stage_and_io_for(&records, &a.data, a.stage.as_deref())?;
    if let Some(path) = &a.stage {
        let u_names = crate::identify::input_columns(&a.data, a.u.as_deref());
        for w in crate::identify::drive_warnings(&a.data, &u_names, &records, &io, path) {
            eprintln!("warning: {w}");
        }
    }
    let settings = CloseLoopSettings {
        start_s: a.start,
        min_share: a.min_share,
        seed: a.seed,
        invertible: a.invertible,
        free_offset: a.free_offset,
        whole_set_invertible: a.invertible,
        loop_rate_hz: Some(stage.loop_rate_hz),
        progress: true,
        ..Default::default()
    };
    let started = Instant::now();
    let outcome = close_loop_validated(
        &records,
        &settings,
        validation.as_deref().map(|v| (v, a.validate_start)),
    )?;
    let out = a
        .out
        .clone()
        .unwrap_or_else(|| a.report.with_extension("toml"));
    let data = a.data.display().to_string();
    let given = a.stage.as_deref();
    let written = stage::write_stage_file(&outcome, &out, &data, stage, io)?;
    let mut plots = Vec::new();
    let mut plots_failed = None;
    if a.plots.is_some() && records[0].segments.len() > 1 {
        eprintln!("warning: --plots: drawn for one record only; none drawn for several");
    } else if let Some(dir) = &a.plots {
        match write_plots(&outcome, &records, dir, &["svg", "png"]) {
            Ok(p) => plots = p,
            Err(e) => plots_failed = Some(format!("--plots {}: not written: {e}", dir.display())),
        }
    }
    let report = CloseLoopReport {
        outcome: outcome.report(),
        stage_file: written.report(a.invertible, given),
        invertible: invertible_report(a.invertible, &written),
        plots: &plots,
        plots_not_written: plots_failed.as_deref(),
        seconds: started.elapsed().as_secs_f64(),
    };
    // Written as a JSON value, so that the keys are sorted as in every report.
    let reported = crate::to_json(&report)
        .and_then(|report| serde_json::to_string_pretty(&report).map_err(crate::Error::from))
        .and_then(|json| {
            if let Some(dir) = a.report.parent().filter(|d| !d.as_os_str().is_empty()) {
                std::fs::create_dir_all(dir).map_err(crate::Error::write("", dir))?;
            }
            std::fs::write(&a.report, json).map_err(crate::Error::from)
        });
    let mut line = format!(
        "close-loop {data}: rms {:.4e} -> {:.4e} m, effects added: [{}]",
        outcome.before.rms,
        outcome.after.rms,
        outcome.effects_added().join(", ")
    );
    for ax in &outcome.axes {
        if ax.records.len() > 1 {
            for r in &ax.records {
                line.push_str(&format!(
                    "\n{}: {}: rms {:.4e} -> {:.4e} m (zeroed {:.4e} -> {:.4e} m)",
                    ax.name,
                    r.data,
                    r.before.rms,
                    r.after.rms,
                    r.before.rms_zeroed,
                    r.after.rms_zeroed
                ));
            }
        }
    }
    for ax in &outcome.axes {
        match &ax.uncertainty {
            Ok(u) => {
                for l in u.lines(&format!("{}:   ", ax.name)) {
                    line.push('\n');
                    line.push_str(&l);
                }
            }
            Err(why) => line.push_str(&format!("\n{}:   uncertainty not computed: {why}", ax.name)),
        }
    }
    if let Some(v) = &outcome.validation {
        line.push_str(&format!(
            "; validation rms {:.4e} -> {:.4e} m, zeroed {:.4e} -> {:.4e} m",
            v.before.rms, v.after.rms, v.before.rms_zeroed, v.after.rms_zeroed
        ));
    }
    let files: Vec<String> = [
        reported.is_ok().then(|| a.report.display().to_string()),
        written
            .not_written
            .is_none()
            .then(|| out.display().to_string()),
    ]
    .into_iter()
    .flatten()
    .collect();
    line.push_str(&format!(
        "; {} written ({})",
        if files.is_empty() {
            "nothing".to_string()
        } else {
            files.join(" and ")
        },
        written.verdict.summary(a.allow_refused)
    ));
    if !plots.is_empty() {
        line.push_str(&format!(", {} plots", plots.len()));
    }
    line.push_str(&written.identity_line());
    let mut failures = Vec::new();
    failures.extend(written.error(a.invertible, given, a.allow_refused));
    failures.extend(plots_failed);
    if let Err(e) = reported {
        failures.push(format!("--report {}: not written: {e}", a.report.display()));
    }
    if failures.is_empty() {
        Ok(line)
    } else {
        Err(crate::Error::Usage(format!(
            "{line}\n{}",
            failures.join("\n")
        )))
    }
}

/// The report `close-loop` writes: the outcome, the stage file written and its verdict, whether
/// it is invertible, the plots and the run's wall time.
#[derive(serde::Serialize)]
struct CloseLoopReport<'a> {
    /// The outcome's keys.
    #[serde(flatten)]
    outcome: OutcomeReport<'a>,
    /// The stage file's keys.
    #[serde(flatten)]
    stage_file: StageFileReport<'a>,
    /// Whether the set written is invertible.
    invertible: InvertibleReport,
    /// The plots written.
    plots: &'a [String],
    /// Why the plots could not be written (null: written, or none asked for).
    plots_not_written: Option<&'a str>,
    /// Wall time of the run \[s\].
    seconds: f64,
}

/// The report's `invertible`: whether `--invertible` was asked for and whether the set written is
/// one `host-sim compensate` runs (the check it makes: [`Verdict`]), and why not.
#[derive(serde::Serialize)]
struct InvertibleReport {
    /// `--invertible` was given.
    required: bool,
    /// The set written is one `compensate` runs.
    holds: bool,
    /// Why not (null when it holds).
    reason: Option<String>,
}

fn invertible_report(required: bool, written: &WrittenStage) -> InvertibleReport {
    let reason = match &written.verdict {
        Verdict::Accepted => None,
        Verdict::Refused {
            kind: RefusalKind::NotInvertible,
            message,
        } => Some(format!("not invertible: {message}")),
        v => Some(v.words()),
    };
    InvertibleReport {
        required,
        holds: reason.is_none(),
        reason,
    }
}
