//! `host-sim link learn`: iterative learning control ([`piezo_core::learning`]) with the
//! firmware over its command link: the firmware plays a learned voltage table with its wave
//! table (control mode `learned`, or `learned+feedback`), the host records whole periods and
//! computes the next table with the same learning step as `host-sim learn`.
//!
//! ```text
//! host-sim link --connect C learn --params STAGE.toml (--signal SPEC --duration-per-trial S |
//!     --reference R.csv) --iterations N --out DIR [--feedback] [--periods P] [--resume T.csv]
//! ```
//!
//! * **Reference**: one period of a periodic trajectory at the loop rate, one wave table entry
//!   per tick (m = 1), at most the table's capacity: `--signal` (`simulate`'s grammar, metres as
//!   `link track`) sampled at t = k/f_loop for k < round(S·f_loop), written to
//!   `DIR/reference.csv`; or a record `compensate` reads. The wave table plays it in a loop.
//! * **Iteration 0**: u_0 = the compensator's command for the reference played in a loop
//!   (`learn::base_command`, as `host-sim learn --periodic` takes it: `compensate`'s chain over
//!   warm-up periods, the period it settles to), limited as every learned table is (window,
//!   slew limit, the wrap from the last entry to the first): the learning step with no error; with
//!   `--resume` a table `link learn` or `learn` wrote, refused (naming both) when it was learned
//!   for another reference or stage file.
//! * **A trial** k: the table u_k is loaded (the compensator plays meanwhile), the loop switches
//!   to it mid-period (same phase), `--settle-periods` whole passes are played, then `--periods`
//!   whole passes are recorded (frames cut by their pass number) and averaged per entry: the
//!   reading of tick k+1 is the output of the voltage of tick k. The error e = r − y of the
//!   averaged period gives `rms_m`/`max_abs_m` (`rms_raw_m`: over the passes unaveraged), and
//!   `learn::step_checked` (the step of `host-sim learn --periodic`, on the voltages applied) the
//!   next table; with `--periods` ≥ 2 the step reads the averaged record's noise from the
//!   spread between the passes (`piezo_core::pass_noise_rms`, as `learn --periodic` does for a
//!   record of whole passes), which also lets it learn above Q's cut-off (`--harmonic-gain`).
//! * **Back-off** (`--back-off`, `piezo_core::learning::back_off`): per axis, a trial whose
//!   averaged error grew more than 5 % above the trial before's is not learned from: the next
//!   table lies halfway between the two, and ρ of the learning above the cut-off is halved from
//!   then on.
//! * **Stop**: after `--iterations` steps, or early when `--patience` trials in a row do not
//!   bring the error (the RMS of both axes, √((rms_x² + rms_y²)/2)) below 98 % of the best so
//!   far. The best table (lowest error) is loaded and left playing.
//! * **Written**: `DIR/learn.json` (per iteration and axis RMS and largest error, Q's cut-off,
//!   the rules), `DIR/table.csv` (the best table in `host-sim learn`'s format: `t_s, ux_V,
//!   uy_V, rx_m, ry_m` after its iteration and the stage file's FNV-1a 32), `DIR/learn.png`
//!   (error against iteration). Progress per trial on stderr.

use crate::compensate::{feedforward_axes, read_reference, Reference};
use crate::csv::{write_csv, Table};
use crate::learn::{
    axis_learnings, base_command, read_learned_table, rule_text, step_axes, step_checked,
    write_learned_table, AxesPrevious, AxesTrial, AxisStep, LearnStep, LearningArgs, StepFiles,
    TableContext,
};
use crate::link::{fnv1a32, run_limits, Client};
use crate::plot::{plot_grid, Chart, Legend, Panel, Role, Series};
use crate::record::{LoopFrame, TimeBase};
use crate::signal::SignalSpec;
use piezo_core::learning::{step_back, BackOff, Verdict};
use piezo_core::{pass_noise_rms, TrialNoise};
use piezo_link::{Control, Frame, Program, Request, Response};
use piezo_stage::StageFile;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// An iteration lowers the error when it is below this fraction of the best so far.
pub const IMPROVEMENT: f64 = 0.98;

/// The early-stop rule, as reports state it.
pub fn stop_rule(patience: usize) -> String {
    format!(
        "stop when {patience} trial(s) in a row do not bring the error sqrt((rms_x^2 + rms_y^2)/2) \
         below {IMPROVEMENT} times the best so far; the best table is kept"
    )
}

/// Arguments of `link learn`.
#[derive(Debug, Clone, clap::Args)]
pub struct LinkLearnArgs {
    /// Stage file (TOML) the firmware runs (its FNV-1a 32 must be the firmware's): the model,
    /// effects and limits the learning inverts.
    #[arg(long)]
    pub params: PathBuf,
    /// One period of the reference (simulate's grammar, metres), sampled at the loop rate for
    /// --duration-per-trial.
    #[arg(long, requires = "duration_per_trial", conflicts_with = "reference")]
    pub signal: Option<String>,
    /// The period the signal is sampled for (s): one trial, one pass over the table.
    #[arg(long)]
    pub duration_per_trial: Option<f64>,
    /// One period of the reference as a record (`compensate`'s CSV, at the loop rate).
    #[arg(long, required_unless_present = "signal")]
    pub reference: Option<PathBuf>,
    /// Learning steps (trials 0 ..= N, fewer if the error stops falling).
    #[arg(long)]
    pub iterations: usize,
    /// Output directory: learn.json, table.csv, learn.png (and reference.csv for --signal).
    #[arg(long)]
    pub out: PathBuf,
    /// Learn with the servo's correction on top of the table (control mode learned+feedback).
    #[arg(long)]
    pub feedback: bool,
    /// Whole periods recorded and averaged per trial.
    #[arg(long, default_value_t = 2)]
    pub periods: u32,
    /// Whole periods played before each trial's record.
    #[arg(long, default_value_t = 1)]
    pub settle_periods: u32,
    /// The error-growth back-off: per axis, a trial whose averaged error grew more than 5 % above
    /// the trial before's is not learned from; the next table lies halfway between the two, and
    /// the harmonic gain halves (`piezo_core::learning::back_off`).
    #[arg(long)]
    pub back_off: bool,
    /// Trials in a row without a new best (by 2 %) before stopping.
    #[arg(long, default_value_t = 2)]
    pub patience: usize,
    /// Start from this table (`link learn`'s table.csv or `learn`'s output) instead of u_0.
    #[arg(long)]
    pub resume: Option<PathBuf>,
    /// The uncertainty the learning must converge for.
    #[command(flatten)]
    pub learning: LearningArgs,
}

/// One trial's error.
#[derive(Debug, Clone, PartialEq)]
pub struct TrialError {
    /// The table's iteration (the resumed table's + the trial).
    pub iteration: u32,
    /// Per axis: the learning step's summary of the averaged period.
    pub axes: Vec<AxisStep>,
    /// Per axis: RMS of r − y over the recorded passes, unaveraged \[m\].
    pub rms_raw_m: Vec<f64>,
}

impl TrialError {
    /// √((rms_x² + rms_y²)/2) of the averaged period \[m\].
    pub fn combined_m(&self) -> f64 {
        let sum: f64 = self.axes.iter().map(|a| a.rms_m * a.rms_m).sum();
        (sum / self.axes.len().max(1) as f64).sqrt()
    }
}

/// What a run learned.
#[derive(Debug, Clone)]
pub struct LinkLearnReport {
    /// Per trial.
    pub trials: Vec<TrialError>,
    /// Index into `trials` of the best table.
    pub best: usize,
    /// The best table per axis \[V\].
    pub best_table: Vec<Vec<f32>>,
    /// Stopped before `--iterations` because the error stopped falling.
    pub stopped_early: bool,
    /// The reference.
    pub reference: Reference,
    /// Where the reference came from.
    pub reference_path: PathBuf,
    /// Q's cut-off per axis \[Hz\].
    pub q_cutoff_hz: Vec<f64>,
    /// The learning gain per axis.
    pub learning_gain: Vec<f64>,
    /// FNV-1a 32 of the stage file.
    pub stage_fnv1a32: u32,
    /// Loop rate \[Hz\].
    pub loop_rate_hz: f64,
}

/// The control mode trials run in.
fn mode(a: &LinkLearnArgs) -> Control {
    if a.feedback {
        Control::LearnedFeedback
    } else {
        Control::Learned
    }
}

/// `--signal` sampled at the loop rate for one period, written to `DIR/reference.csv`.
fn write_signal_reference(
    spec: &str,
    duration_s: f64,
    rate_hz: f64,
    capacity: u32,
    path: &Path,
) -> crate::Result<()> {
    let parsed =
        SignalSpec::parse(spec).map_err(|e| crate::Error::Link(format!("--signal: {e}")))?;
    let signals = parsed
        .build(2)
        .map_err(|e| crate::Error::Link(format!("--signal: {e}")))?;
    let n = (duration_s * rate_hz).round();
    if !(duration_s.is_finite() && n >= 2.0 && n <= f64::from(capacity)) {
        return Err(crate::Error::Link(format!(
            "--duration-per-trial {duration_s} s is {n} ticks at the device's {rate_hz} Hz: one \
             table entry per tick needs 2 to {capacity}"
        )));
    }
    let t_s: Vec<f64> = (0..n as usize).map(|k| k as f64 / rate_hz).collect();
    let axis = |i: usize| -> Vec<f64> {
        t_s.iter()
            .map(|&t| f64::from(signals[i].value(t) as f32))
            .collect()
    };
    let table = Table {
        path: path.to_path_buf(),
        names: vec!["t_s".into(), "rx_m".into(), "ry_m".into()],
        columns: vec![t_s.clone(), axis(0), axis(1)],
    };
    write_csv(path, &table).map_err(|e| crate::Error::Link(format!("{}: {e}", path.display())))
}

/// Loads `table` as the learned table and plays it from the next tick: the compensator plays
/// while it is replaced.
fn play(client: &mut Client, table: &[Vec<f32>], control: Control) -> crate::Result<()> {
    if client.status()?.feedforward == piezo_link::Feedforward::Learned {
        client.expect(Request::Control(Control::Feedforward))?;
    }
    let entries: Vec<[f32; 2]> = (0..table[0].len())
        .map(|j| [table[0][j], table[1][j]])
        .collect();
    client.load_table(&entries, true)?;
    match client.request(Request::Control(control))? {
        Response::Done => Ok(()),
        Response::Refused(r) => Err(crate::Error::Link(format!(
            "the firmware refused the learned table ({:?}): {}",
            r.kind, r.reason
        ))),
        other => Err(crate::Error::Link(format!(
            "unexpected answer to control: {other:?}"
        ))),
    }
}

/// RMS of r − y over one averaged period \[m\] (non-finite samples left out).
fn period_rms(reference_m: &[f32], measured_m: &[f32]) -> f64 {
    let (sum, count) = reference_m
        .iter()
        .zip(measured_m)
        .map(|(&r, &y)| f64::from(r) - f64::from(y))
        .filter(|e| e.is_finite())
        .fold((0.0, 0usize), |(s, c), e| (s + e * e, c + 1));
    (sum / count as f64).sqrt()
}

/// A trial's record, averaged over its passes.
struct TrialRecord {
    /// Per axis the voltages applied \[V\].
    command_v: Vec<Vec<f32>>,
    /// Per axis the readings that answer them \[m\].
    measured_m: Vec<Vec<f32>>,
    /// Per axis the RMS of r − y over the passes unaveraged \[m\].
    rms_raw_m: Vec<f64>,
    /// Per axis the averaged record's noise from the spread between the passes
    /// (`piezo_core::pass_noise_rms` of the readings and of the voltages), when there are
    /// several.
    noise: Vec<Option<TrialNoise>>,
}

/// A trial: after `settle` whole passes, `periods` whole passes recorded and averaged per
/// entry. Per axis the applied voltages and the readings that answer them, and every
/// reading's error against the reference (unaveraged).
fn record(
    client: &mut Client,
    reference: &Reference,
    settle: u32,
    periods: u32,
) -> crate::Result<TrialRecord> {
    let n = reference.t_s.len();
    let first = match client.expect(Request::Frames { decimation: 1 })? {
        Response::Streaming { next_frame, .. } => next_frame,
        other => {
            return Err(crate::Error::Link(format!(
                "unexpected answer to frames: {other:?}"
            )))
        }
    };
    let mut start = None;
    let frames = client.frames_through(|f: &Frame| {
        if f.sequence.wrapping_sub(first) >= u32::MAX / 2 {
            return false;
        }
        let s = *start.get_or_insert(f.trial.wrapping_add(1 + settle));
        f.trial == s.wrapping_add(periods)
    });
    client.expect(Request::Frames { decimation: 0 })?;
    client.take_frames();
    let frames = frames?;
    let start = start.ok_or_else(|| crate::Error::Link("no frame".into()))?;
    let kept: Vec<&Frame> = frames
        .iter()
        .filter(|f| f.sequence.wrapping_sub(first) < u32::MAX / 2)
        .skip_while(|f| f.trial != start)
        .collect();
    let expected = periods as usize * n + 1;
    let contiguous = kept
        .windows(2)
        .all(|w| w[1].sequence == w[0].sequence.wrapping_add(1));
    if kept.len() != expected || !contiguous {
        return Err(crate::Error::Link(format!(
            "the record of {periods} passes of {n} entries has {} frames, {} (frames lost: \
             the link does not keep up with one frame per tick)",
            kept.len(),
            if contiguous {
                "contiguous"
            } else {
                "with gaps"
            }
        )));
    }
    let frames: Vec<LoopFrame> = kept
        .iter()
        .map(|f| LoopFrame::from_link(f, u64::from(f.sequence.wrapping_sub(first))))
        .collect();
    // Each voltage with the reading that answers it, the next frame's (the loop rate only
    // times the rows, which are not written here).
    let rows = crate::record::record(
        &frames,
        TimeBase {
            loop_rate_hz: 1.0,
            decimation: 1,
        },
    )
    .rows;
    let mut u = vec![vec![0.0f64; n]; 2];
    let mut y = vec![vec![0.0f64; n]; 2];
    // Every pass, for the spread between them.
    let mut u_passes: [Vec<f32>; 2] = [0, 1].map(|_| Vec::with_capacity(rows.len()));
    let mut y_passes: [Vec<f32>; 2] = [0, 1].map(|_| Vec::with_capacity(rows.len()));
    let mut sq = [0.0f64; 2];
    for (k, row) in rows.iter().enumerate() {
        let j = k % n;
        for i in 0..2 {
            let r = reference.axes[i].1[j];
            if row.reference_m[i] != r {
                return Err(crate::Error::Link(format!(
                    "frame {}: the firmware's reference {} m is not entry {j}'s {r} m: the wave \
                     table is not the reference (another client changed it?)",
                    first.wrapping_add(row.sequence as u32),
                    row.reference_m[i]
                )));
            }
            u[i][j] += f64::from(row.commanded_v[i]);
            y[i][j] += f64::from(row.sensor_m[i]);
            u_passes[i].push(row.commanded_v[i]);
            y_passes[i].push(row.sensor_m[i]);
            let e = f64::from(r) - f64::from(row.sensor_m[i]);
            sq[i] += e * e;
        }
    }
    let m = f64::from(periods);
    let average = |v: Vec<Vec<f64>>| -> Vec<Vec<f32>> {
        v.into_iter()
            .map(|a| a.into_iter().map(|x| (x / m) as f32).collect())
            .collect()
    };
    let raw = sq.map(|s| (s / (m * n as f64)).sqrt()).to_vec();
    let noise = (0..2)
        .map(|i| {
            Some(TrialNoise {
                measured_m: pass_noise_rms(&y_passes[i], n)?,
                command_v: pass_noise_rms(&u_passes[i], n)?,
            })
        })
        .collect();
    Ok(TrialRecord {
        command_v: average(u),
        measured_m: average(y),
        rms_raw_m: raw,
        noise,
    })
}

/// Runs the learning over `client` (nothing written but `DIR/reference.csv` for `--signal`);
/// `progress` receives a line per trial.
pub fn link_learn(
    client: &mut Client,
    a: &LinkLearnArgs,
    progress: &mut dyn FnMut(&str),
) -> crate::Result<LinkLearnReport> {
    if a.periods == 0 {
        return Err(crate::Error::Link("--periods must be at least 1".into()));
    }
    std::fs::create_dir_all(&a.out)
        .map_err(|e| crate::Error::Link(format!("--out {}: {e}", a.out.display())))?;
    let (file, valid) = StageFile::load(&a.params).map_err(crate::Error::from)?;
    let bytes = std::fs::read(&a.params)
        .map_err(|e| crate::Error::Link(format!("{}: {e}", a.params.display())))?;
    let stage_hash = fnv1a32(&bytes);
    let axes = feedforward_axes(&file, &valid, &a.params)?;
    if axes.len() != 2 {
        return Err(crate::Error::Link(format!(
            "{}: {} axis; the firmware's tables are two-axis: give a stage file with [x] and [y]",
            a.params.display(),
            axes.len()
        )));
    }
    let status = client.status()?;
    let (rate, capacity) = run_limits(&status)?;
    let capacity = capacity.min(status.learned[1]);
    if status.params_fnv1a32 != stage_hash {
        return Err(crate::Error::Link(format!(
            "the firmware runs {} (fnv1a32 {:#010x}), not {} (fnv1a32 {stage_hash:#010x}): \
             `host-sim link upload --params {}` first",
            status.params_version,
            status.params_fnv1a32,
            a.params.display(),
            a.params.display()
        )));
    }
    let reference_path = match (&a.signal, a.duration_per_trial, &a.reference) {
        (Some(spec), Some(s), None) => {
            let path = a.out.join("reference.csv");
            write_signal_reference(spec, s, rate, capacity, &path)?;
            path
        }
        (None, _, Some(path)) => path.clone(),
        _ => {
            return Err(crate::Error::Link(
                "give --signal with --duration-per-trial, or --reference".into(),
            ))
        }
    };
    let reference = read_reference(&reference_path)?;
    let n = reference.t_s.len();
    if reference.axes.len() != 2 || !(2..=capacity as usize).contains(&n) {
        return Err(crate::Error::Link(format!(
            "{}: {n} samples of {} axis(es): the tables take rx_m and ry_m, 2 to {capacity} entries \
             (one per tick)",
            reference_path.display(),
            reference.axes.len()
        )));
    }
    let base = base_command(&a.params, &reference_path, true)?;
    let base_v: Vec<Vec<f32>> = base.voltages_v.iter().map(|(_, u)| u.clone()).collect();
    let names: Vec<&'static str> = valid.axes.iter().map(|v| v.name).collect();
    let learnings = axis_learnings(&axes, &names, a.learning.params())?;
    let r_m: Vec<Vec<f32>> = reference.axes.iter().map(|(_, r)| r.clone()).collect();
    let (first_iteration, mut table) = match &a.resume {
        Some(path) => {
            let context = TableContext {
                params: &a.params,
                stage_hash,
                reference_path: &reference_path,
                reference: &reference,
            };
            let table = read_learned_table(path, &context, 2)?;
            (table.iteration, table.voltages_v)
        }
        // u_0 limited as every table is: a step with no error.
        None => (
            0,
            step_axes(&AxesTrial {
                learnings: &learnings,
                names: &names,
                reference: &reference,
                command_v: &base_v,
                measured_m: &r_m,
                base_v: &base_v,
                periodic: true,
                noise: None,
                table_v: None,
                previous: None,
                remembered: None,
            })?
            .1,
        ),
    };

    // The wave table: the reference in a loop, tracked by the compensator to start with.
    if status.control.learned() || status.feedforward == piezo_link::Feedforward::Learned {
        client.expect(Request::Control(Control::Feedforward))?;
    }
    let wave: Vec<[f32; 2]> = (0..n).map(|j| [r_m[0][j], r_m[1][j]]).collect();
    client.load_table(&wave, false)?;
    client.expect(Request::Track(Program::Table {
        ticks_per_entry: 1,
        repeat: true,
    }))?;

    let mut trials: Vec<TrialError> = Vec::new();
    let mut best: Option<(usize, Vec<Vec<f32>>)> = None;
    // The error-growth back-off per axis and the table it holds (`piezo_core::learning::back_off`).
    let mut back_off = [BackOff::new(); 2];
    let mut held = table.clone();
    let (mut stall, mut stopped_early) = (0, false);
    // The trial before's voltages, readings and table (the harmonic step's two-trial estimate).
    type PerAxis = Vec<Vec<f32>>;
    let mut last_trial: Option<(PerAxis, PerAxis, PerAxis)> = None;
    for k in 0..=a.iterations {
        play(client, &table, mode(a))?;
        let trial_record = record(client, &reference, a.settle_periods, a.periods)?;
        let status = client.status()?;
        if status.mode != piezo_link::Mode::Running {
            return Err(crate::Error::Link(format!(
                "trial {k}: the firmware left the running state ({:?})",
                status.mode
            )));
        }
        let files = StepFiles {
            params: &a.params,
            reference: &reference_path,
        };
        // Per axis: the trial's measured error against the held table's; ρ above the cut-off
        // halved per trial that backed off.
        let mut verdicts = [Verdict::Learn; 2];
        let mut stepping = Vec::new();
        for (i, learning) in learnings.iter().enumerate() {
            if a.back_off {
                verdicts[i] = back_off[i].judge(period_rms(
                    &reference.axes[i].1,
                    &trial_record.measured_m[i],
                ));
            }
            let rho = learning.params().harmonic_gain * back_off[i].harmonic_scale() as f32;
            stepping.push(
                learning
                    .with_harmonic_gain(rho)
                    .map_err(|e| crate::Error::Link(format!("axis {}: {e}", names[i])))?,
            );
        }
        let (axes_error, mut next) = step_checked(
            &AxesTrial {
                learnings: &stepping,
                names: &names,
                reference: &reference,
                command_v: &trial_record.command_v,
                measured_m: &trial_record.measured_m,
                base_v: &base_v,
                periodic: true,
                noise: Some(&trial_record.noise),
                table_v: a.feedback.then_some(table.as_slice()),
                previous: last_trial.as_ref().map(|(u, y, t)| AxesPrevious {
                    command_v: u,
                    measured_m: y,
                    table_v: a.feedback.then_some(t.as_slice()),
                }),
                remembered: None,
            },
            &files,
        )?;
        for i in 0..2 {
            match verdicts[i] {
                Verdict::Learn => held[i].clone_from(&table[i]),
                Verdict::StepBack => step_back(&held[i], &table[i], &mut next[i]),
            }
        }
        last_trial = Some((
            trial_record.command_v.clone(),
            trial_record.measured_m.clone(),
            table.clone(),
        ));
        let trial = TrialError {
            iteration: first_iteration + k as u32,
            axes: axes_error,
            rms_raw_m: trial_record.rms_raw_m,
        };
        let error = trial.combined_m();
        let best_error = best.as_ref().map(|(b, _)| trials[*b].combined_m());
        let improved = best_error.is_none_or(|b| error < IMPROVEMENT * b);
        if best_error.is_none_or(|b| error < b) {
            best = Some((k, table.clone()));
        }
        stall = if improved { 0 } else { stall + 1 };
        progress(&format!(
            "link learn: iteration {}: {}{}",
            trial.iteration,
            trial
                .axes
                .iter()
                .map(|s| format!(
                    "{} rms {:.2} nm max {:.2} nm",
                    s.axis,
                    s.rms_m * 1e9,
                    s.max_abs_m * 1e9
                ))
                .collect::<Vec<_>>()
                .join(", "),
            if best.as_ref().is_some_and(|(b, _)| *b == k) {
                " (best)"
            } else {
                ""
            }
        ));
        trials.push(trial);
        if k == a.iterations {
            break;
        }
        if stall >= a.patience {
            stopped_early = true;
            progress(&format!("link learn: {}", stop_rule(a.patience)));
            break;
        }
        table = next;
    }
    let (best, best_table) = best.ok_or_else(|| crate::Error::Link("no trial ran".into()))?;
    play(client, &best_table, mode(a))?;
    Ok(LinkLearnReport {
        trials,
        best,
        best_table,
        stopped_early,
        reference,
        reference_path,
        q_cutoff_hz: learnings.iter().map(|l| l.cutoff_hz()).collect(),
        learning_gain: learnings.iter().map(|l| l.learning_gain()).collect(),
        stage_fnv1a32: stage_hash,
        loop_rate_hz: rate,
    })
}

impl LinkLearnReport {
    /// `learn.json`: the run's settings, the rule and the error per iteration and axis.
    pub fn report(&self, a: &LinkLearnArgs) -> LinkLearnJson {
        let per_axis = |v: &[f64]| -> BTreeMap<&'static str, f64> {
            ["x", "y"].into_iter().zip(v.iter().copied()).collect()
        };
        let iterations = self
            .trials
            .iter()
            .map(|t| IterationJson {
                iteration: t.iteration,
                axes: t
                    .axes
                    .iter()
                    .zip(&t.rms_raw_m)
                    .map(|(s, &raw)| {
                        let axis = TrialAxisJson {
                            rms_m: s.rms_m,
                            max_abs_m: s.max_abs_m,
                            rms_raw_m: raw,
                            limited: s.limited,
                            noise_rms_m: s.noise_rms_m,
                            noise_from_passes: s.noise_from_passes,
                            harmonics_learned: s.harmonics_learned,
                        };
                        (s.axis, axis)
                    })
                    .collect(),
                rms_m: t.combined_m(),
            })
            .collect();
        LinkLearnJson {
            params: a.params.display().to_string(),
            stage_fnv1a32: format!("{:#010x}", self.stage_fnv1a32),
            reference: self.reference_path.display().to_string(),
            entries: self.reference.t_s.len(),
            loop_rate_hz: self.loop_rate_hz,
            control: mode(a).name(),
            periods_per_trial: a.periods,
            settle_periods: a.settle_periods,
            q_cutoff_hz: per_axis(&self.q_cutoff_hz),
            learning_gain: per_axis(&self.learning_gain),
            best_iteration: self.trials[self.best].iteration,
            stopped_early: self.stopped_early,
            iterations,
            rule: rule_text(&a.learning.params()),
            stop_rule: stop_rule(a.patience),
            error: "e = r - y of the period averaged over the trial's passes (rms_m, max_abs_m; rms_m of the iteration: sqrt((rms_x^2 + rms_y^2)/2)); rms_raw_m over the passes unaveraged; y of entry j is the reading of the tick after it",
        }
    }

    /// The best table as `host-sim learn` writes and reads it.
    pub fn table_step(&self, a: &LinkLearnArgs) -> LearnStep {
        let best = &self.trials[self.best];
        LearnStep {
            t_s: self.reference.t_s.clone(),
            next_v: ["ux_V", "uy_V"]
                .iter()
                .map(|s| s.to_string())
                .zip(self.best_table.iter().cloned())
                .collect(),
            reference: self.reference.clone(),
            iteration: best.iteration,
            stage_fnv1a32: self.stage_fnv1a32,
            axes: best.axes.clone(),
            params: a.learning.params(),
            periodic: true,
            learned_from: None,
        }
    }

    /// `learn.png`: RMS and largest error against iteration, per axis.
    pub fn chart(&self) -> Chart {
        let mut series = Vec::new();
        for (i, name) in ["x", "y"].iter().enumerate() {
            let points = |f: &dyn Fn(&AxisStep) -> f64| -> Vec<(f64, f64)> {
                self.trials
                    .iter()
                    .map(|t| (f64::from(t.iteration), f(&t.axes[i]) * 1e9))
                    .collect()
            };
            series.push(
                Series::markers(format!("{name} RMS"), points(&|s| s.rms_m)).role(Role::Other(i)),
            );
            series.push(
                Series::markers(format!("{name} max |e|"), points(&|s| s.max_abs_m))
                    .role(Role::Other(i + 2)),
            );
        }
        Panel::new(
            "learning over the link: error of each trial's averaged period",
            "iteration",
            "error r - y [nm]",
            series,
        )
        .log_y()
        .legend(Legend::Below)
    }
}

/// `host-sim link learn`: learns, writes `DIR/learn.json`, `DIR/table.csv`, `DIR/learn.png`;
/// returns a summary (JSON).
pub fn link_learn_cmd(client: &mut Client, a: &LinkLearnArgs) -> crate::Result<String> {
    let report = link_learn(client, a, &mut |line| eprintln!("{line}"))?;
    let json_path = a.out.join("learn.json");
    let table_path = a.out.join("table.csv");
    let png_path = a.out.join("learn.png");
    let json = serde_json::to_string_pretty(&report.report(a)).map_err(crate::Error::from)?;
    std::fs::write(&json_path, json)
        .map_err(|e| crate::Error::Link(format!("{}: {e}", json_path.display())))?;
    write_learned_table(&table_path, &report.table_step(a), &a.params)?;
    plot_grid(&png_path, &[report.chart()], 1)
        .map_err(|e| crate::Error::Link(format!("{}: {e}", png_path.display())))?;
    let written: Vec<String> = [&json_path, &table_path, &png_path]
        .iter()
        .map(|p| p.display().to_string())
        .collect();
    let first = &report.trials[0];
    let best = &report.trials[report.best];
    serde_json::to_string(&serde_json::json!({
        "iterations": report.trials.len() - 1,
        "best_iteration": best.iteration,
        "rms_m": { "first": first.combined_m(), "best": best.combined_m() },
        "stopped_early": report.stopped_early,
        "written": written,
    }))
    .map_err(crate::Error::from)
}
/// `DIR/learn.json` of `link learn` ([`LinkLearnReport::report`]).
#[derive(Debug, Clone, serde::Serialize)]
pub struct LinkLearnJson {
    /// The stage file.
    pub params: String,
    /// Its FNV-1a 32, `0x%08x`.
    pub stage_fnv1a32: String,
    /// The reference file or signal.
    pub reference: String,
    /// Entries of the table.
    pub entries: usize,
    /// The firmware's loop rate \[Hz\].
    pub loop_rate_hz: f64,
    /// The control mode the table ran in.
    pub control: &'static str,
    /// Passes averaged per trial.
    pub periods_per_trial: u32,
    /// Passes let settle before them.
    pub settle_periods: u32,
    /// Q's cut-off per axis \[Hz\].
    pub q_cutoff_hz: BTreeMap<&'static str, f64>,
    /// λ per axis.
    pub learning_gain: BTreeMap<&'static str, f64>,
    /// The iteration whose table was kept.
    pub best_iteration: u32,
    /// Whether the run stopped before its iterations ran out.
    pub stopped_early: bool,
    /// The error of each iteration.
    pub iterations: Vec<IterationJson>,
    /// The learning's rule.
    pub rule: String,
    /// When the run stops early.
    pub stop_rule: String,
    /// What the error figures measure.
    pub error: &'static str,
}

/// One iteration of [`LinkLearnJson`]: per axis by name, and combined.
#[derive(Debug, Clone, serde::Serialize)]
pub struct IterationJson {
    /// The table's iteration.
    pub iteration: u32,
    /// Per axis.
    #[serde(flatten)]
    pub axes: BTreeMap<&'static str, TrialAxisJson>,
    /// √((rms_x² + rms_y²)/2) \[m\].
    pub rms_m: f64,
}

/// One axis of an iteration (SI).
#[derive(Debug, Clone, serde::Serialize)]
pub struct TrialAxisJson {
    /// RMS of the averaged period's error \[m\].
    pub rms_m: f64,
    /// Its largest |error| \[m\].
    pub max_abs_m: f64,
    /// RMS over the passes unaveraged \[m\].
    pub rms_raw_m: f64,
    /// Samples the window or the slew limit held.
    pub limited: usize,
    /// The noise σ the learning's shares were set by \[m\].
    pub noise_rms_m: f64,
    /// Whether σ came from the spread between the passes.
    pub noise_from_passes: bool,
    /// Harmonics above the cut-off learned.
    pub harmonics_learned: usize,
}
