//! `host-sim learn`: one step of iterative learning control for a trajectory the stage repeats
//! (`piezo_core::learning`): from the reference, the command of the last trial and what the
//! sensor measured, the command of the next trial.
//!
//! ```text
//! host-sim learn --params STAGE.toml --reference R.csv --command U.csv --measured Y.csv \
//!     --out U_NEXT.csv --report STEP.json [--periodic]
//! ```
//!
//! * `R.csv` as `compensate` reads it; iteration 0's command u_0 is `compensate`'s for it, and
//!   `U.csv` is either that (as `compensate` writes it: `t_s,u_V` or `t_s,ux_V,uy_V`) or a table
//!   this command wrote.
//! * `Y.csv`: a record as `identify` reads it: `t_s` and the measured output, `--y` naming the
//!   columns (default: the first `y_*` for one axis, `x_m,y_m` for two), the same length and
//!   sample period as `U.csv`; sample j is the output of command sample j (the stage file's delay
//!   is the learning's shift).
//! * Per axis `u_{k+1} = u_0 + Q·(u_k − u_0 + L·(r − y_k))`, inside the stage file's output window
//!   and slew limit; L and the cut-off of Q from the stage file's model (module doc of
//!   `piezo_core::learning`).
//! * `U_NEXT.csv`: `t_s`, the voltages, and the reference it belongs to (`r_m` or `rx_m,ry_m`),
//!   after `#` lines with the iteration and the FNV-1a 32 of the stage file's bytes (as the
//!   firmware's build logs it): a table learned for another reference or stage file is refused.
//! * `STEP.json`: per axis the error of the trial just measured (`rms_m`, `max_abs_m`), the
//!   cut-off `q_cutoff_hz`, the learning gain and the samples limited; the rule.

use crate::compensate::{compensate, feedforward_axes, read_reference, Reference};
use crate::csv::{read_csv, write_csv, Table};
use crate::identify::unit_factor;
use crate::link::fnv1a32;
use piezo_core::{Learning, LearningParams, Trial};
use piezo_stage::StageFile;
use std::path::{Path, PathBuf};

/// Arguments of `learn`.
#[derive(Debug, clap::Args)]
pub struct LearnArgs {
    /// Stage file (TOML): the model, effects and limits the learning inverts.
    #[arg(long)]
    pub params: PathBuf,
    /// Reference record (CSV, as `compensate` reads it).
    #[arg(long)]
    pub reference: PathBuf,
    /// Command of the trial just run (CSV: `compensate`'s output or a table `learn` wrote).
    #[arg(long)]
    pub command: PathBuf,
    /// Measured record of that trial (CSV with `t_s` and the output columns).
    #[arg(long)]
    pub measured: PathBuf,
    /// Output columns of --measured, comma-separated for two axes (default: the first `y_*`
    /// for one axis, `x_m,y_m` for two).
    #[arg(long)]
    pub y: Option<String>,
    /// The record is one period of a trajectory played in a loop (filter and shift wrap around);
    /// without it, one run from rest at the window's lower end.
    #[arg(long)]
    pub periodic: bool,
    /// Output CSV: the next command and its reference (directory created if missing).
    #[arg(long)]
    pub out: PathBuf,
    /// Output JSON: the error of this trial per axis, the cut-off and the rule.
    #[arg(long)]
    pub report: PathBuf,
    /// The uncertainty the learning must converge for.
    #[command(flatten)]
    pub learning: LearningArgs,
}

/// The learning's uncertainty and margin on the command line (`learn`, `learn-bench`).
#[derive(Debug, Clone, Copy, clap::Args)]
pub struct LearningArgs {
    /// Smallest plant/model gain ratio the learning must converge for.
    #[arg(long, default_value_t = LearningParams::default().gain_min)]
    pub gain_min: f32,
    /// Largest plant/model gain ratio the learning must converge for.
    #[arg(long, default_value_t = LearningParams::default().gain_max)]
    pub gain_max: f32,
    /// Relative error of the stage file's mode frequency the learning must converge for.
    #[arg(long, default_value_t = LearningParams::default().mode_frequency_tolerance)]
    pub mode_tolerance: f32,
    /// Margin m of the monotone convergence |Q(1 - LG)| <= 1 - m.
    #[arg(long, default_value_t = LearningParams::default().margin)]
    pub margin: f32,
}

impl LearningArgs {
    /// As the core's parameters (validated when a `Learning` is built).
    pub fn params(&self) -> LearningParams {
        LearningParams {
            gain_min: self.gain_min,
            gain_max: self.gain_max,
            mode_frequency_tolerance: self.mode_tolerance,
            margin: self.margin,
        }
    }
}

/// Help text after the options.
pub const HELP: &str = "One step of iterative learning control per axis: u_next = u_0 + Q(u - u_0 + L(r - y)), \
u_0 the compensator's command for the reference, L the inverse of the stage file's model along u (slope dy/du, \
mode, the error taken D samples later, gain 2/(gain_min + gain_max)), Q a zero-phase 4th-order Butterworth \
low-pass (forward and backward, circular with --periodic) whose cut-off is the highest with |Q(1 - LG)| <= 1 - margin \
for plant gains in [gain_min, gain_max] times the model's and its mode within +-mode-tolerance. The table is clamped \
to the output window and slew limit, and carries its reference and the stage file's FNV-1a 32: a table learned \
for another reference or stage file is refused.";

/// The learning of one axis in a step.
#[derive(Debug, Clone, PartialEq)]
pub struct AxisStep {
    /// `x` or `y`.
    pub axis: &'static str,
    /// RMS of r − y over the trial just measured \[m\].
    pub rms_m: f64,
    /// Largest |r − y| over that trial \[m\].
    pub max_abs_m: f64,
    /// Cut-off of Q \[Hz\].
    pub q_cutoff_hz: f64,
    /// λ.
    pub learning_gain: f64,
    /// Samples of the new command moved by the window or the slew limit.
    pub limited: usize,
}

/// What a step computed.
#[derive(Debug, Clone, PartialEq)]
pub struct LearnStep {
    /// Sample times \[s\] (the reference's).
    pub t_s: Vec<f64>,
    /// Per axis: column name and the next command \[V\].
    pub next_v: Vec<(String, Vec<f32>)>,
    /// The reference the table belongs to.
    pub reference: Reference,
    /// The iteration of the table written (the command's + 1).
    pub iteration: u32,
    /// FNV-1a 32 of the stage file's bytes.
    pub stage_fnv1a32: u32,
    /// Per axis.
    pub axes: Vec<AxisStep>,
    /// The uncertainty and margin the cut-off was chosen for.
    pub params: LearningParams,
    /// Whether the trial was periodic.
    pub periodic: bool,
}

/// The rule, as printed in reports.
pub fn rule_text(p: &LearningParams) -> String {
    format!(
        "Q: zero-phase 4th-order Butterworth (forward and backward), |Q(f)| = 1/(1 + (tan(pi f T)/tan(pi f_c T))^8); \
         f_c the highest (at most 0.4/T) with |Q(f)| * max |1 - lambda*gamma*G_mu(f)*Lhat(f)| <= 1 - {m} at 2048 \
         frequencies up to 1/(2T), over gamma in [{lo}, {hi}] (plant/model gain) and the mode at (1 +- {t}) f_mode \
         (33 values and f itself); lambda = 2/(gamma_min + gamma_max); G_mu = continuous mode * exp(-j 2 pi f D T), \
         Lhat = the learning's own shift by D (linear interpolation) and central-difference mode inverse",
        m = p.margin,
        lo = p.gain_min,
        hi = p.gain_max,
        t = p.mode_frequency_tolerance
    )
}

impl LearnStep {
    /// The table written to `--out`: `t_s`, the voltages, the reference \[m\].
    pub fn to_table(&self) -> Table {
        let mut names = vec!["t_s".to_string()];
        let mut columns = vec![self.t_s.clone()];
        for (name, u) in &self.next_v {
            names.push(name.clone());
            columns.push(u.iter().map(|&v| f64::from(v)).collect());
        }
        let reference_names: &[&str] = if self.next_v.len() == 1 {
            &["r_m"]
        } else {
            &["rx_m", "ry_m"]
        };
        for (name, (_, r)) in reference_names.iter().zip(&self.reference.axes) {
            names.push(name.to_string());
            columns.push(r.iter().map(|&v| f64::from(v)).collect());
        }
        Table {
            path: PathBuf::new(),
            names,
            columns,
        }
    }

    /// The `#` lines before the table.
    pub fn header(&self, params: &Path) -> String {
        format!(
            "# host-sim learn: iteration {}\n# {STAGE_KEY}{:#010x} ({})\n",
            self.iteration,
            self.stage_fnv1a32,
            params.display()
        )
    }

    /// `STEP.json`.
    pub fn json(&self) -> serde_json::Value {
        let mut out = serde_json::Map::new();
        for a in &self.axes {
            out.insert(
                a.axis.to_string(),
                serde_json::json!({
                    "rms_m": a.rms_m,
                    "max_abs_m": a.max_abs_m,
                    "q_cutoff_hz": a.q_cutoff_hz,
                    "learning_gain": a.learning_gain,
                    "limited": a.limited,
                }),
            );
        }
        out.insert("iteration".into(), self.iteration.into());
        out.insert(
            "stage_fnv1a32".into(),
            format!("{:#010x}", self.stage_fnv1a32).into(),
        );
        out.insert("periodic".into(), self.periodic.into());
        out.insert("rule".into(), rule_text(&self.params).into());
        serde_json::Value::Object(out)
    }
}

const STAGE_KEY: &str = "stage_fnv1a32 = ";
const ITERATION_KEY: &str = "# host-sim learn: iteration ";

/// A command file: its table and, for a table `learn` wrote, the iteration and the stage file's
/// fingerprint and name.
struct CommandFile {
    table: Table,
    iteration: u32,
    stage: Option<(u32, String)>,
}

fn read_command(path: &Path) -> Result<CommandFile, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let table = crate::csv::parse_csv(path, &text).map_err(|e| e.to_string())?;
    let mut iteration = 0;
    let mut stage = None;
    for (i, line) in text.lines().enumerate().filter(|(_, l)| l.starts_with('#')) {
        let bad = || {
            format!(
                "{}:{}: unreadable learn header `{line}`",
                path.display(),
                i + 1
            )
        };
        if let Some(rest) = line.strip_prefix(ITERATION_KEY) {
            iteration = rest.trim().parse().map_err(|_| bad())?;
        } else if let Some(rest) = line
            .strip_prefix("# ")
            .and_then(|l| l.strip_prefix(STAGE_KEY))
        {
            let (hash, name) = rest.split_once(' ').ok_or_else(bad)?;
            let hash = u32::from_str_radix(hash.trim_start_matches("0x"), 16).map_err(|_| bad())?;
            let name = name.trim().trim_start_matches('(').trim_end_matches(')');
            stage = Some((hash, name.to_string()));
        }
    }
    Ok(CommandFile {
        table,
        iteration,
        stage,
    })
}

/// Mean sample period of a time column \[s\] (NaN for fewer than two samples).
fn mean_period(t_s: &[f64]) -> f64 {
    match t_s {
        [first, .., last] => (last - first) / (t_s.len() - 1) as f64,
        _ => f64::NAN,
    }
}

/// The command's voltage columns for `axes` axes (`u_V`, or `ux_V` and `uy_V`).
fn command_columns(file: &CommandFile, path: &Path, axes: usize) -> Result<Vec<Vec<f32>>, String> {
    let names: &[&str] = if axes == 1 {
        &["u_V"]
    } else {
        &["ux_V", "uy_V"]
    };
    names
        .iter()
        .map(|name| {
            let column = file.table.column(name).map_err(|e| {
                format!("{e} ({} is read as `compensate` writes it)", path.display())
            })?;
            Ok(column.iter().map(|&v| v as f32).collect())
        })
        .collect()
}

/// Refuses a table learned for another stage file or reference.
fn check_table_belongs(
    file: &CommandFile,
    a: &LearnArgs,
    stage_hash: u32,
    reference: &Reference,
) -> Result<(), String> {
    if let Some((hash, name)) = &file.stage {
        if *hash != stage_hash {
            return Err(format!(
                "{} was learned with the stage file {name} (fnv1a32 {hash:#010x}), not with {} \
                 (fnv1a32 {stage_hash:#010x}): learn from that file's table, or start again from \
                 `host-sim compensate` with this one",
                a.command.display(),
                a.params.display()
            ));
        }
    }
    let names: &[&str] = if reference.axes.len() == 1 {
        &["r_m"]
    } else {
        &["rx_m", "ry_m"]
    };
    let t = file.table.column("t_s").map_err(|e| e.to_string())?;
    for (name, (given, r)) in names.iter().zip(&reference.axes) {
        let Ok(stored) = file.table.column(name) else {
            if file.stage.is_some() {
                return Err(format!(
                    "{}: a learned table without its reference column `{name}`",
                    a.command.display()
                ));
            }
            continue;
        };
        if let Some(j) = (0..stored.len()).find(|&j| stored[j] as f32 != r[j]) {
            return Err(format!(
                "{} was learned for another reference than {}: at t_s = {} s the table's `{name}` \
                 is {} m, the reference's `{given}` {} m",
                a.command.display(),
                a.reference.display(),
                t[j],
                stored[j],
                r[j]
            ));
        }
    }
    Ok(())
}

/// The measured output columns: `--y`, or the defaults for `axes` axes.
fn measured_columns(table: &Table, y: Option<&str>, axes: usize) -> Result<Vec<String>, String> {
    let names: Vec<String> = match y {
        Some(list) => list.split(',').map(|s| s.trim().to_string()).collect(),
        None if axes == 2 && table.has("x_m") && table.has("y_m") => {
            vec!["x_m".into(), "y_m".into()]
        }
        None => table
            .names
            .iter()
            .filter(|n| n.starts_with("y_"))
            .take(axes)
            .cloned()
            .collect(),
    };
    if names.len() != axes {
        return Err(format!(
            "{}: {} output column(s) ({}) for a {axes}-axis stage file; name them with --y \
             (columns: {})",
            table.path.display(),
            names.len(),
            names.join(", "),
            table.names.join(", ")
        ));
    }
    Ok(names)
}

/// Runs one learning step (nothing written).
pub fn learn(a: &LearnArgs) -> Result<LearnStep, String> {
    let base = compensate(&a.params, &a.reference)?;
    let (file, valid) = StageFile::load(&a.params).map_err(|e| e.to_string())?;
    let stage_hash =
        fnv1a32(&std::fs::read(&a.params).map_err(|e| format!("{}: {e}", a.params.display()))?);
    let axes = feedforward_axes(&file, &valid, &a.params)?;
    let reference = read_reference(&a.reference)?;
    let command = read_command(&a.command)?;
    let n = reference.t_s.len();
    let t_u = command.table.column("t_s").map_err(|e| e.to_string())?;
    if t_u.len() != n {
        return Err(format!(
            "{} has {} samples but the reference {} has {n}",
            a.command.display(),
            t_u.len(),
            a.reference.display()
        ));
    }
    check_table_belongs(&command, a, stage_hash, &reference)?;
    let u = command_columns(&command, &a.command, axes.len())?;
    let measured = read_csv(&a.measured).map_err(|e| e.to_string())?;
    let t_y = measured.column("t_s").map_err(|e| e.to_string())?;
    if t_y.len() != n {
        return Err(format!(
            "{}: {} samples, but the command {} has {n}: record one trial of the table",
            a.measured.display(),
            t_y.len(),
            a.command.display()
        ));
    }
    let (period_u, period_y) = (mean_period(t_u), mean_period(t_y));
    if !((period_y - period_u).abs() <= 1e-6 * period_u.abs()) {
        return Err(format!(
            "{}: sample period {period_y} s differs from the command {}'s {period_u} s",
            a.measured.display(),
            a.command.display()
        ));
    }
    let columns = measured_columns(&measured, a.y.as_deref(), axes.len())?;
    let params = a.learning.params();
    let mut steps = Vec::new();
    let mut next_v = Vec::new();
    for (i, axis) in axes.iter().enumerate() {
        let name = valid.axes[i].name;
        let learning = Learning::new(&axis.compensator, &axis.effects, params)
            .map_err(|e| format!("learning settings of axis {name}: {e}"))?;
        let factor = unit_factor(&columns[i]).ok_or_else(|| {
            format!(
                "{}: column `{}` has no length unit (m, mm, um, nm)",
                a.measured.display(),
                columns[i]
            )
        })?;
        let y: Vec<f32> = measured
            .column(&columns[i])
            .map_err(|e| format!("--y: {e}"))?
            .iter()
            .map(|&v| (v * factor) as f32)
            .collect();
        let mut next = vec![0.0f32; n];
        let summary = learning
            .step(
                &Trial {
                    reference_m: &reference.axes[i].1,
                    command_v: &u[i],
                    measured_m: &y,
                    base_v: &base.voltages_v[i].1,
                    periodic: a.periodic,
                },
                &mut next,
            )
            .map_err(|e| format!("axis {name}: {e}"))?;
        steps.push(AxisStep {
            axis: name,
            rms_m: summary.rms_error_m,
            max_abs_m: summary.max_abs_error_m,
            q_cutoff_hz: learning.cutoff_hz(),
            learning_gain: learning.learning_gain(),
            limited: summary.limited,
        });
        next_v.push((base.voltages_v[i].0.clone(), next));
    }
    Ok(LearnStep {
        t_s: reference.t_s.clone(),
        next_v,
        reference,
        iteration: command.iteration + 1,
        stage_fnv1a32: stage_hash,
        axes: steps,
        params,
        periodic: a.periodic,
    })
}

/// `host-sim learn`: computes and writes the next command and the report; returns a summary.
pub fn learn_cmd(a: &LearnArgs) -> Result<String, String> {
    let step = learn(a)?;
    write_csv(&a.out, &step.to_table()).map_err(|e| format!("--out: {e}"))?;
    let text = std::fs::read_to_string(&a.out).map_err(|e| format!("--out: {e}"))?;
    std::fs::write(&a.out, step.header(&a.params) + &text).map_err(|e| format!("--out: {e}"))?;
    let json = serde_json::to_string_pretty(&step.json()).map_err(|e| e.to_string())?;
    if let Some(dir) = a.report.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|e| format!("--report {}: {e}", dir.display()))?;
    }
    std::fs::write(&a.report, json).map_err(|e| format!("--report {}: {e}", a.report.display()))?;
    let axes: Vec<String> = step
        .axes
        .iter()
        .map(|s| {
            format!(
                "{}: rms {:.3e} m, max {:.3e} m, Q cut-off {:.0} Hz, {} limited",
                s.axis, s.rms_m, s.max_abs_m, s.q_cutoff_hz, s.limited
            )
        })
        .collect();
    Ok(format!(
        "learn: iteration {} written to {} ({}); report {}",
        step.iteration,
        a.out.display(),
        axes.join("; "),
        a.report.display()
    ))
}
