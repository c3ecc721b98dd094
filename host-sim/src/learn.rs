//! `host-sim learn`: one step of iterative learning control for a trajectory the stage repeats
//! (`piezo_core::learning`): from the reference, the command of the last trial and what the
//! sensor measured, the command of the next trial.
//!
//! ```text
//! host-sim learn --params STAGE.toml --reference R.csv --command U.csv --measured Y.csv \
//!     --out U_NEXT.csv --report STEP.json [--periodic]
//! ```
//!
//! * `R.csv` as `compensate` reads it; iteration 0's command u_0 is `compensate`'s for it (with
//!   `--periodic`: the period it settles to with the record played in a loop,
//!   `compensate::compensate_periodic`), and `U.csv` is either that (as `compensate` writes it:
//!   `t_s,u_V` or `t_s,ux_V,uy_V`) or a table this command or `link learn` wrote.
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
//! * With `--periodic`, `Y.csv` may hold several whole passes of the table: they are averaged,
//!   and the averaged record's noise is read from the spread between them
//!   (`piezo_core::pass_noise_rms`; `noise_from_passes` in `STEP.json`) instead of the error's
//!   fourth differences. Only such a trial learns above Q's cut-off (`--harmonic-gain` ρ, 0.5 by default):
//!   at each harmonic of the period the stage's response measured on the trial, gated
//!   (`piezo_core::learning`, module `harmonics`). With a servo the command file does not
//!   show (learned+feedback over the link, the table as U), Ĝ is the table → output response,
//!   which is what an update of the table needs.
//! * One step has no memory of the trials before: the error-growth back-off
//!   (`piezo_core::learning::back_off`: a trial whose error grew more than 5 % over the one
//!   before steps back halfway to the table before) is the loop's, as `learn-bench` and
//!   `link learn` run it.
//! * `STEP.json`: per axis the error of the trial just measured (`rms_m`, `max_abs_m`), the
//!   cut-off `q_cutoff_hz`, the learning gain, the samples limited, the sensor noise estimated from
//!   the error (`noise_rms_m`), the share of L·e learned (`learned_share`) and the harmonics
//!   above the cut-off learned from the measured response (`harmonics_learned`); the rule.

use crate::compensate::{
    compensate, compensate_for_gain, compensate_periodic, feedforward_axes, read_reference,
    Compensation, Reference,
};
use crate::csv::{read_csv, write_csv, Table};
use crate::identify::unit_factor;
use crate::link::fnv1a32;
use piezo_core::{FeedforwardAxis, Learning, LearningParams, PreviousTrial, Trial, TrialNoise};
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
    /// A stage file without a mode: the plant may still have one at or above this fraction of the
    /// loop rate (0.5 trusts the file's claim of no dynamics up to the Nyquist frequency).
    #[arg(long, default_value_t = LearningParams::default().unmodelled_mode_fraction)]
    pub unmodelled_mode_fraction: f32,
    /// Gain rho of the learning at a periodic trial's harmonics above Q's cut-off from the
    /// stage's response measured on the trial (0 leaves them to Q).
    #[arg(long, default_value_t = LearningParams::default().harmonic_gain)]
    pub harmonic_gain: f32,
    /// Largest share of the trial's error RMS that the step at the harmonics above Q's cut-off
    /// may mix, as the stage file's model predicts, into the harmonics above the cut-off (the
    /// step is scaled down to it; 0 leaves it unscaled).
    #[arg(long, default_value_t = LearningParams::default().collateral_share)]
    pub collateral_share: f32,
}

impl LearningArgs {
    /// As the core's parameters (validated when a `Learning` is built).
    pub fn params(&self) -> LearningParams {
        LearningParams {
            gain_min: self.gain_min,
            gain_max: self.gain_max,
            mode_frequency_tolerance: self.mode_tolerance,
            margin: self.margin,
            unmodelled_mode_fraction: self.unmodelled_mode_fraction,
            harmonic_gain: self.harmonic_gain,
            collateral_share: self.collateral_share,
        }
    }
}

/// Help text after the options.
pub const HELP: &str = "One step of iterative learning control per axis: u_next = u_0 + Q(u - u_0 + L(r - y)), \
u_0 the compensator's command for the reference, L the inverse of the stage file's model along u (slope dy/du, \
mode, the error taken D samples later, gain 2/(gain_min + gain_max)), Q a zero-phase 4th-order Butterworth \
low-pass (forward and backward, circular with --periodic) whose cut-off is the highest with |Q(1 - LG)| <= 1 - margin \
for plant gains in [gain_min, gain_max] times the model's and its mode within +-mode-tolerance (a file without a mode: none, or one at or above unmodelled-mode-fraction times the loop rate, damping 0.02). Each step learns the share s = max(0, 1 - noise/in-band error) of L(r - y): the sensor noise estimated from the error's fourth differences, so that a trial at the noise does not fill the table with it; with --periodic, harmonic by harmonic within twice Q's cut-off (s_h = max(0, 1 - noise/|E(h)|^2)). With --periodic, the measured record may hold several whole passes: they are averaged and their noise \
read from the spread between them; such a trial also learns at the period's harmonics above the cut-off from the stage's response \
measured on it (--harmonic-gain rho, 0.5 by default; 0 leaves them to Q). The table is clamped \
to the output window and slew limit, and carries its reference and the stage file's FNV-1a 32: a table learned \
for another reference or stage file is refused.";

/// The learning of one axis in a step; serialised as its entry of `STEP.json` (without the
/// axis's name, the key, and the model gain's offset).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct AxisStep {
    /// `x` or `y`.
    #[serde(skip)]
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
    /// The sensor noise estimated from the trial's error \[m\].
    pub noise_rms_m: f64,
    /// The share of L·e learned (1 far above the noise, 0 at it).
    pub learned_share: f64,
    /// Harmonics above Q's cut-off learned from the stage's response measured on the trial.
    pub harmonics_learned: usize,
    /// α: the factor their step was scaled by so that its mixing above the cut-off, as the
    /// model predicts it, stays within `--collateral-share` of the error (1 unscaled).
    pub harmonic_scale: f64,
    /// Whether the noise came from the spread between the record's passes (else from the
    /// error's fourth differences).
    pub noise_from_passes: bool,
    /// (γ̂, ĉ \[m\]): the stage's output against the model's for the trial's command, when the
    /// model explains the trial (`Learning::gain_ratio`).
    #[serde(skip)]
    pub model_gain: Option<(f64, f64)>,
    /// Ĝ(h) \[m/V\] as (re, im) per harmonic h (index), (0, 0) where none: the stage's response
    /// at the harmonics the step accepted, now or at an earlier step it was given
    /// (`Learning::step_remembering`); the table `learn` writes carries them.
    #[serde(skip)]
    pub remembered: Vec<[f32; 2]>,
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
    /// The periodic trial the table was learned from, per axis its command u_k \[V\] and its
    /// measured period y_k \[m\] (passes averaged): the table carries them (columns
    /// [`TRIAL_COMMAND_PREFIX`]…, [`TRIAL_MEASURED_PREFIX`]…) so that the next step reads the
    /// stage's response from the change between the two trials (`piezo_core::PreviousTrial`).
    pub learned_from: Option<LearnedFrom>,
}

/// A periodic trial as a table carries it ([`LearnStep::learned_from`]).
#[derive(Debug, Clone, PartialEq)]
pub struct LearnedFrom {
    /// u_k per axis \[V\].
    pub command_v: Vec<Vec<f32>>,
    /// y_k per axis, one period \[m\].
    pub measured_m: Vec<Vec<f32>>,
}

/// The column of a table carrying the command of the trial it was learned from: this prefix
/// and the command's own column (`trial_u_V`, `trial_ux_V`).
pub const TRIAL_COMMAND_PREFIX: &str = "trial_";
/// The column carrying that trial's measured period: this prefix and the axis (`trial_y_m`;
/// `trial_y_x_m` and `trial_y_y_m` for two axes).
pub const TRIAL_MEASURED_PREFIX: &str = "trial_y";

/// A table's voltage columns for `axes` axes: `u_V`, or `ux_V` and `uy_V`.
fn voltage_columns(axes: usize) -> &'static [&'static str] {
    if axes == 1 {
        &["u_V"]
    } else {
        &["ux_V", "uy_V"]
    }
}

/// The columns of a table carrying its trial, command and measured, for `axes` axes.
fn trial_columns(axes: usize) -> Vec<(String, String)> {
    let names = voltage_columns(axes);
    names
        .iter()
        .enumerate()
        .map(|(i, name)| {
            let measured = match axes {
                1 => format!("{TRIAL_MEASURED_PREFIX}_m"),
                _ => format!("{TRIAL_MEASURED_PREFIX}_{}_m", ["x", "y"][i]),
            };
            (format!("{TRIAL_COMMAND_PREFIX}{name}"), measured)
        })
        .collect()
}

/// The rule, as printed in reports.
pub fn rule_text(p: &LearningParams) -> String {
    format!(
        "Q: zero-phase 4th-order Butterworth (forward and backward), |Q(f)| = 1/(1 + (tan(pi f T)/tan(pi f_c T))^8); \
         f_c the highest (at most 0.4/T) with |Q(f)| * max |1 - lambda*gamma*G_mu(f)*Lhat(f)| <= 1 - {m} at 2048 \
         frequencies up to 1/(2T), over gamma in [{lo}, {hi}] (plant/model gain) and the mode at (1 +- {t}) f_mode \
         (33 values and f itself); lambda = 2/(gamma_min + gamma_max); G_mu = continuous mode * exp(-j 2 pi f D T), \
         Lhat = the learning's own shift by D (linear interpolation) and central-difference mode inverse; \
         a stage file without a mode: none in the plant or one at or above {u}/T, damping {z} (33 values from there \
         to 2/T, and f itself); each step learns the share s = max(0, 1 - sigma^2 b/<(Q e)^2>) of L e, sigma the \
         noise from the 25th percentile of the error's fourth differences (or the spread between the passes), b the share \
         of a white noise Q passes; a periodic trial its share per harmonic h <= 2 f_c n T, s_h = max(0, 1 - (sigma^2/n)/|E(h)|^2); \
         learning above f_c (rho > 0) only once <(Q e)^2> <= 0.5 <e^2>, its step scaled by alpha = min(1, kappa e_rms/c), \
         c the RMS the model predicts it mixes into the harmonics above f_c through the stage file's dynamics, kappa = {k}",
        k = p.collateral_share,
        u = p.unmodelled_mode_fraction,
        z = piezo_core::UNMODELLED_MODE_DAMPING,
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
        if let Some(trial) = &self.learned_from {
            let wide = |v: &Vec<f32>| v.iter().map(|&x| f64::from(x)).collect::<Vec<f64>>();
            for (i, (command, measured)) in trial_columns(self.next_v.len()).into_iter().enumerate()
            {
                names.push(command);
                columns.push(wide(&trial.command_v[i]));
                names.push(measured);
                columns.push(wide(&trial.measured_m[i]));
            }
        }
        Table {
            path: PathBuf::new(),
            names,
            columns,
        }
    }

    /// The `#` lines before the table.
    pub fn header(&self, params: &Path) -> String {
        let mut header = format!(
            "# host-sim learn: iteration {}\n# {STAGE_KEY}{:#010x} ({})\n",
            self.iteration,
            self.stage_fnv1a32,
            params.display()
        );
        // The stage's responses at the harmonics, `h:re:im` in m/V, for the next step.
        for ((name, _), axis) in self.next_v.iter().zip(&self.axes) {
            let kept: Vec<String> = axis
                .remembered
                .iter()
                .enumerate()
                .filter(|(_, g)| g[0] != 0.0 || g[1] != 0.0)
                .map(|(h, g)| format!("{h}:{:e}:{:e}", g[0], g[1]))
                .collect();
            if !kept.is_empty() {
                header += &format!("# {RESPONSES_KEY}{name}: {}\n", kept.join(" "));
            }
        }
        header
    }

    /// `STEP.json`: one entry per axis, named by its column, beside the iteration, the stage
    /// file's fingerprint, whether the trial was periodic and the rule.
    pub fn report(&self) -> StepReport<'_> {
        StepReport {
            axes: self
                .axes
                .iter()
                .map(|a| {
                    let report = AxisStepReport {
                        step: a,
                        model_gain_ratio: a.model_gain.map(|g| g.0),
                        base_resolved: rebase(&[a.model_gain], &self.params).is_some(),
                    };
                    (a.axis.to_string(), report)
                })
                .collect(),
            iteration: self.iteration,
            stage_fnv1a32: format!("{:#010x}", self.stage_fnv1a32),
            periodic: self.periodic,
            rule: rule_text(&self.params),
        }
    }
}

/// `STEP.json` ([`LearnStep::report`]).
#[derive(Debug, Clone, serde::Serialize)]
pub struct StepReport<'a> {
    /// Per axis, by its column name.
    #[serde(flatten)]
    pub axes: std::collections::BTreeMap<String, AxisStepReport<'a>>,
    /// The iteration of the table written.
    pub iteration: u32,
    /// FNV-1a 32 of the stage file, `0x%08x`.
    pub stage_fnv1a32: String,
    /// Whether the trial was periodic.
    pub periodic: bool,
    /// The rule the cut-off and the shares follow.
    pub rule: String,
}

/// One axis of [`StepReport`]: the error of the trial just measured (SI) and how the step learned.
#[derive(Debug, Clone, serde::Serialize)]
pub struct AxisStepReport<'a> {
    /// The step's figures.
    #[serde(flatten)]
    pub step: &'a AxisStep,
    /// γ̂, the plant/model gain the trial showed, where it showed one.
    pub model_gain_ratio: Option<f64>,
    /// Whether the learning's base could be scaled to that gain.
    pub base_resolved: bool,
}

const STAGE_KEY: &str = "stage_fnv1a32 = ";
const ITERATION_KEY: &str = "# host-sim learn: iteration ";
const RESPONSES_KEY: &str = "harmonic_responses_m_per_v ";

/// A command file: its table and, for a table `learn` wrote, the iteration and the stage file's
/// fingerprint and name.
struct CommandFile {
    table: Table,
    iteration: u32,
    stage: Option<(u32, String)>,
    /// Per voltage column, the stage's responses at the harmonics the step that wrote the
    /// table had accepted: (h, \[re, im\] m/V).
    remembered: Vec<(String, Vec<HarmonicResponse>)>,
}

/// One harmonic's remembered response as a table carries it: (h, \[re, im\] m/V).
type HarmonicResponse = (usize, [f32; 2]);

fn read_command(path: &Path) -> crate::Result<CommandFile> {
    let text = std::fs::read_to_string(path).map_err(crate::Error::read("", path))?;
    let table = crate::csv::parse_csv(path, &text).map_err(crate::Error::from)?;
    let mut iteration = 0;
    let mut stage = None;
    let mut remembered = Vec::new();
    for (i, line) in text.lines().enumerate().filter(|(_, l)| l.starts_with('#')) {
        let bad = || {
            crate::Error::Usage(format!(
                "{}:{}: unreadable learn header `{line}`",
                path.display(),
                i + 1
            ))
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
        } else if let Some(rest) = line
            .strip_prefix("# ")
            .and_then(|l| l.strip_prefix(RESPONSES_KEY))
        {
            let (column, entries) = rest.split_once(':').ok_or_else(bad)?;
            let entries = entries
                .split_whitespace()
                .map(|entry| {
                    let mut parts = entry.split(':');
                    let (Some(h), Some(re), Some(im), None) =
                        (parts.next(), parts.next(), parts.next(), parts.next())
                    else {
                        return Err(bad());
                    };
                    let g = [re.parse::<f32>(), im.parse::<f32>()];
                    match (h.parse::<usize>(), g) {
                        (Ok(h), [Ok(re), Ok(im)]) if re.is_finite() && im.is_finite() => {
                            Ok((h, [re, im]))
                        }
                        _ => Err(bad()),
                    }
                })
                .collect::<crate::Result<Vec<_>>>()?;
            remembered.push((column.trim().to_string(), entries));
        }
    }
    Ok(CommandFile {
        table,
        iteration,
        stage,
        remembered,
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
fn command_columns(file: &CommandFile, path: &Path, axes: usize) -> crate::Result<Vec<Vec<f32>>> {
    let names = voltage_columns(axes);
    names
        .iter()
        .map(|name| {
            let column = file.table.column(name).map_err(|e| {
                crate::Error::Usage(format!(
                    "{e} ({} is read as `compensate` writes it)",
                    path.display()
                ))
            })?;
            Ok(column.iter().map(|&v| v as f32).collect())
        })
        .collect()
}

/// The files a table is checked against: the stage file and its FNV-1a 32, the reference.
#[derive(Debug, Clone, Copy)]
pub struct TableContext<'a> {
    /// The stage file.
    pub params: &'a Path,
    /// FNV-1a 32 of its bytes.
    pub stage_hash: u32,
    /// The reference record's file.
    pub reference_path: &'a Path,
    /// The reference.
    pub reference: &'a Reference,
}

/// Refuses a table learned for another stage file or reference, naming both.
fn check_table_belongs(
    file: &CommandFile,
    command: &Path,
    c: &TableContext<'_>,
) -> crate::Result<()> {
    let (stage_hash, reference) = (c.stage_hash, c.reference);
    if let Some((hash, name)) = &file.stage {
        if *hash != stage_hash {
            return Err(crate::Error::Usage(format!(
                "{} was learned with the stage file {name} (fnv1a32 {hash:#010x}), not with {} \
                 (fnv1a32 {stage_hash:#010x}): learn from that file's table, or start again from \
                 `host-sim compensate` with this one",
                command.display(),
                c.params.display()
            )));
        }
    }
    let names: &[&str] = if reference.axes.len() == 1 {
        &["r_m"]
    } else {
        &["rx_m", "ry_m"]
    };
    let t = file.table.column("t_s").map_err(crate::Error::from)?;
    for (name, (given, r)) in names.iter().zip(&reference.axes) {
        let Ok(stored) = file.table.column(name) else {
            if file.stage.is_some() {
                return Err(crate::Error::Usage(format!(
                    "{}: a learned table without its reference column `{name}`",
                    command.display()
                )));
            }
            continue;
        };
        if let Some(j) = (0..stored.len()).find(|&j| stored[j] as f32 != r[j]) {
            return Err(crate::Error::Usage(format!(
                "{} was learned for another reference than {}: at t_s = {} s the table's `{name}` \
                 is {} m, the reference's `{given}` {} m",
                command.display(),
                c.reference_path.display(),
                t[j],
                stored[j],
                r[j]
            )));
        }
    }
    Ok(())
}

/// The measured output columns: `--y`, or the defaults for `axes` axes.
fn measured_columns(table: &Table, y: Option<&str>, axes: usize) -> crate::Result<Vec<String>> {
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
        return Err(crate::Error::Usage(format!(
            "{}: {} output column(s) ({}) for a {axes}-axis stage file; name them with --y \
             (columns: {})",
            table.path.display(),
            names.len(),
            names.join(", "),
            table.names.join(", ")
        )));
    }
    Ok(names)
}

/// A command file as [`read_learned_table`] reads it.
#[derive(Debug, Clone, PartialEq)]
pub struct LearnedTable {
    /// Its iteration (0 for `compensate`'s output).
    pub iteration: u32,
    /// Its time column \[s\].
    pub t_s: Vec<f64>,
    /// Per axis the voltages \[V\].
    pub voltages_v: Vec<Vec<f32>>,
    /// Per axis the stage's responses at the harmonics the table's step accepted
    /// ([`AxisStep::remembered`]), n/2 + 1 entries; all (0, 0) for a table without them.
    pub remembered: Vec<Vec<[f32; 2]>>,
    /// The trial it was learned from, where it carries one ([`LearnStep::learned_from`]).
    pub learned_from: Option<LearnedFrom>,
}

/// A command for `axes` axes read from `path` (`compensate`'s output, iteration 0, or a table
/// `learn` or `link learn` wrote), refused when its length is not the reference's or it was
/// learned for another stage file or reference (both named).
pub fn read_learned_table(
    path: &Path,
    c: &TableContext<'_>,
    axes: usize,
) -> crate::Result<LearnedTable> {
    let command = read_command(path)?;
    let n = c.reference.t_s.len();
    let t_u = command.table.column("t_s").map_err(crate::Error::from)?;
    if t_u.len() != n {
        return Err(crate::Error::Usage(format!(
            "{} has {} samples but the reference {} has {n}",
            path.display(),
            t_u.len(),
            c.reference_path.display()
        )));
    }
    check_table_belongs(&command, path, c)?;
    let voltages_v = command_columns(&command, path, axes)?;
    let names = voltage_columns(axes);
    let mut remembered = vec![vec![[0.0f32; 2]; n / 2 + 1]; axes];
    for (column, entries) in &command.remembered {
        let Some(axis) = names.iter().position(|name| name == column) else {
            return Err(crate::Error::Usage(format!(
                "{}: harmonic responses for `{column}`, which is not among its columns {}",
                path.display(),
                names.join(", ")
            )));
        };
        for &(h, g) in entries {
            let slot = remembered[axis].get_mut(h).ok_or_else(|| {
                crate::Error::Usage(format!(
                    "{}: a harmonic response at harmonic {h} of `{column}`, above the table's \
                     n/2 = {}",
                    path.display(),
                    n / 2
                ))
            })?;
            *slot = g;
        }
    }
    let trial: Option<Vec<(Vec<f32>, Vec<f32>)>> = trial_columns(axes)
        .iter()
        .map(|(u, y)| {
            let column = |name: &str| {
                command
                    .table
                    .column(name)
                    .ok()
                    .map(|c| c.iter().map(|&v| v as f32).collect::<Vec<f32>>())
            };
            Some((column(u)?, column(y)?))
        })
        .collect();
    let learned_from = trial.map(|axes| {
        let (command_v, measured_m) = axes.into_iter().unzip();
        LearnedFrom {
            command_v,
            measured_m,
        }
    });
    Ok(LearnedTable {
        iteration: command.iteration,
        t_s: t_u.to_vec(),
        voltages_v,
        remembered,
        learned_from,
    })
}

/// u_0, the compensator's command for the reference at `reference`: [`compensate`]'s from rest
/// for a trial from rest, [`compensate_periodic`]'s (the period it settles to, played in a loop)
/// for a periodic one.
pub fn base_command(
    params: &Path,
    reference: &Path,
    periodic: bool,
) -> crate::Result<Compensation> {
    if periodic {
        let base = compensate_periodic(params, reference)?;
        if let Some(s) = base.settling.filter(|s| !s.settled) {
            eprintln!(
                "note: the compensator's command for {} played in a loop still moved {:.3e} V \
                 per period after {} periods (drift or creep in the stage file move it every \
                 period): the table's wrap carries that step",
                reference.display(),
                s.change_v,
                s.periods
            );
        }
        Ok(base)
    } else {
        compensate(params, reference)
    }
}

/// u_0 is re-solved when the trial shows the stage's gain more than this factor away from the
/// model's (either way).
pub const REBASE_MIN_RATIO: f64 = 1.1;

/// Per axis, (γ̂, ĉ) of `Learning::gain_ratio` for the trial (`None` where the model does not
/// explain it).
pub fn model_gains(
    learnings: &[Learning],
    reference: &Reference,
    command_v: &[Vec<f32>],
    measured_m: &[Vec<f32>],
    periodic: bool,
) -> Vec<Option<(f64, f64)>> {
    learnings
        .iter()
        .enumerate()
        .map(|(i, learning)| {
            learning.gain_ratio(&Trial {
                reference_m: &reference.axes[i].1,
                command_v: &command_v[i],
                measured_m: &measured_m[i],
                base_v: &command_v[i],
                periodic,
                noise: None,
                previous: None,
                table_v: None,
            })
        })
        .collect()
}

/// The (γ, c) per axis to re-solve u_0 for (`compensate::compensate_for_gain`), when some axis's
/// γ̂ lies more than [`REBASE_MIN_RATIO`] from 1: that axis's (γ̂ held to the learning's
/// [gain_min, gain_max], ĉ), (1, 0) for the others. `None`: u_0 stands. The learning's L and Q
/// are those of the stage file either way (their rule's promise is for the file's model).
pub fn rebase(gains: &[Option<(f64, f64)>], params: &LearningParams) -> Option<Vec<(f64, f64)>> {
    let off = |g: &Option<(f64, f64)>| {
        g.is_some_and(|(gamma, _)| gamma.ln().abs() > REBASE_MIN_RATIO.ln())
    };
    gains.iter().any(off).then(|| {
        gains
            .iter()
            .map(|g| match g {
                Some((gamma, c)) if off(g) => (
                    gamma.clamp(f64::from(params.gain_min), f64::from(params.gain_max)),
                    *c,
                ),
                _ => (1.0, 0.0),
            })
            .collect()
    })
}

/// The learnings for the (γ, c) of [`rebase`]: L's gain divided by γ (`Learning::with_model_gain`).
pub fn rescaled(
    learnings: &[Learning],
    gain_offset: &[(f64, f64)],
) -> crate::Result<Vec<Learning>> {
    learnings
        .iter()
        .zip(gain_offset)
        .map(|(learning, &(gain, _))| learning.with_model_gain(gain).map_err(crate::Error::from))
        .collect()
}

/// Each axis's learning, from the stage file's feed-forward (`names`: the axes' names).
pub fn axis_learnings(
    axes: &[FeedforwardAxis],
    names: &[&str],
    params: LearningParams,
) -> crate::Result<Vec<Learning>> {
    axes.iter()
        .zip(names)
        .map(|(axis, name)| {
            Learning::new(&axis.compensator, &axis.effects, params)
                .map_err(|e| crate::Error::Usage(format!("learning settings of axis {name}: {e}")))
        })
        .collect()
}

/// One trial of every axis, as a learning step reads it: per axis (in `learnings`' order) the
/// trial's command, what was measured and the compensator's command u_0, each the reference's
/// length.
#[derive(Debug, Clone, Copy)]
pub struct AxesTrial<'a> {
    /// Each axis's learning.
    pub learnings: &'a [Learning],
    /// The axes' names (`x`, `y`).
    pub names: &'a [&'static str],
    /// The reference.
    pub reference: &'a Reference,
    /// u_k per axis \[V\].
    pub command_v: &'a [Vec<f32>],
    /// y_k per axis \[m\].
    pub measured_m: &'a [Vec<f32>],
    /// u_0 per axis \[V\].
    pub base_v: &'a [Vec<f32>],
    /// One period of a trajectory played in a loop (else one run from rest).
    pub periodic: bool,
    /// For a trial that averages several passes: per axis the averaged record's noise from the
    /// spread between them (`piezo_core::pass_noise_rms`), where known; `None` else (the noise
    /// then comes from the error's fourth differences).
    pub noise: Option<&'a [Option<TrialNoise>]>,
    /// Per axis the table the trial played, where a servo added its correction on top
    /// (`command_v` the voltages applied); `None`: the command is the table.
    pub table_v: Option<&'a [Vec<f32>]>,
    /// The trial before on the same trajectory, for the harmonic step's two-trial estimate
    /// (`piezo_core::PreviousTrial`).
    pub previous: Option<AxesPrevious<'a>>,
    /// Per axis the stage's responses at the harmonics accepted at earlier steps on the same
    /// trajectory ([`AxisStep::remembered`]); `None`: none kept.
    pub remembered: Option<&'a [Vec<[f32; 2]>]>,
}

/// The trial before ([`AxesTrial::previous`]), per axis.
#[derive(Debug, Clone, Copy)]
pub struct AxesPrevious<'a> {
    /// u_{k−1} per axis \[V\].
    pub command_v: &'a [Vec<f32>],
    /// y_{k−1} per axis \[m\].
    pub measured_m: &'a [Vec<f32>],
    /// Its table per axis, where a servo added its correction on top.
    pub table_v: Option<&'a [Vec<f32>]>,
}

/// One learning step per axis: the next command from the trial. The error of the trial and the
/// next command per axis.
pub fn step_axes(trial: &AxesTrial<'_>) -> crate::Result<(Vec<AxisStep>, Vec<Vec<f32>>)> {
    let mut steps = Vec::new();
    let mut next_v = Vec::new();
    for (i, learning) in trial.learnings.iter().enumerate() {
        let name = trial.names[i];
        let mut next = vec![0.0f32; trial.reference.t_s.len()];
        let noise = trial.noise.and_then(|n| n.get(i).copied().flatten());
        let mut remembered = match trial.remembered {
            Some(r) => {
                let mut kept = r.get(i).cloned().unwrap_or_default();
                kept.resize(trial.reference.t_s.len() / 2 + 1, [0.0; 2]);
                kept
            }
            None => Vec::new(),
        };
        let summary = learning
            .step_remembering(
                &Trial {
                    reference_m: &trial.reference.axes[i].1,
                    command_v: &trial.command_v[i],
                    measured_m: &trial.measured_m[i],
                    base_v: &trial.base_v[i],
                    periodic: trial.periodic,
                    noise,
                    previous: trial.previous.map(|p| PreviousTrial {
                        command_v: &p.command_v[i],
                        measured_m: &p.measured_m[i],
                        table_v: p.table_v.map(|t| t[i].as_slice()),
                    }),
                    table_v: trial.table_v.map(|t| t[i].as_slice()),
                },
                &mut remembered,
                &mut next,
            )
            .map_err(|e| crate::Error::Usage(format!("axis {name}: {e}")))?;
        steps.push(AxisStep {
            axis: name,
            rms_m: summary.rms_error_m,
            max_abs_m: summary.max_abs_error_m,
            q_cutoff_hz: learning.cutoff_hz(),
            learning_gain: learning.learning_gain(),
            limited: summary.limited,
            noise_rms_m: summary.noise_rms_m,
            learned_share: summary.learned_share,
            harmonics_learned: summary.harmonics_learned,
            harmonic_scale: summary.harmonic_scale,
            noise_from_passes: noise.is_some(),
            model_gain: None,
            remembered,
        });
        next_v.push(next);
    }
    Ok((steps, next_v))
}

/// Where u_0 comes from: the stage file and the reference file (one period for a periodic
/// trial).
#[derive(Debug, Clone, Copy)]
pub struct StepFiles<'a> {
    /// The stage file.
    pub params: &'a Path,
    /// The reference record (one period when the trial is periodic).
    pub reference: &'a Path,
}

/// One learning step per axis, the model's gain checked against the trial first: when the trial
/// shows a stage gain more than [`REBASE_MIN_RATIO`] off the model's ([`model_gains`],
/// [`rebase`]), u_0 is re-solved for it from `files` (`compensate_for_gain`) and L's gain
/// divided by it ([`rescaled`]); else the step of [`step_axes`] with the trial's u_0. Each
/// axis's step carries its γ̂.
pub fn step_checked(
    trial: &AxesTrial<'_>,
    files: &StepFiles<'_>,
) -> crate::Result<(Vec<AxisStep>, Vec<Vec<f32>>)> {
    let gains = model_gains(
        trial.learnings,
        trial.reference,
        trial.command_v,
        trial.measured_m,
        trial.periodic,
    );
    let params = trial
        .learnings
        .first()
        .map(|l| *l.params())
        .unwrap_or_default();
    let (mut steps, next) = match rebase(&gains, &params) {
        Some(gain_offset) => {
            let base =
                compensate_for_gain(files.params, files.reference, trial.periodic, &gain_offset)?;
            let base_v: Vec<Vec<f32>> = base.voltages_v.into_iter().map(|(_, u)| u).collect();
            let learnings = rescaled(trial.learnings, &gain_offset)?;
            step_axes(&AxesTrial {
                learnings: &learnings,
                base_v: &base_v,
                ..*trial
            })?
        }
        None => step_axes(trial)?,
    };
    for (step, gain) in steps.iter_mut().zip(gains) {
        step.model_gain = gain;
    }
    Ok((steps, next))
}

/// Runs one learning step (nothing written).
pub fn learn(a: &LearnArgs) -> crate::Result<LearnStep> {
    let base = base_command(&a.params, &a.reference, a.periodic)?;
    let (file, valid) = StageFile::load(&a.params).map_err(crate::Error::from)?;
    let stage_hash = fnv1a32(&std::fs::read(&a.params).map_err(crate::Error::read("", &a.params))?);
    let axes = feedforward_axes(&file, &valid, &a.params)?;
    let reference = read_reference(&a.reference)?;
    let n = reference.t_s.len();
    let context = TableContext {
        params: &a.params,
        stage_hash,
        reference_path: &a.reference,
        reference: &reference,
    };
    let LearnedTable {
        iteration,
        t_s: t_u,
        voltages_v: u,
        remembered,
        learned_from,
    } = read_learned_table(&a.command, &context, axes.len())?;
    let measured = read_csv(&a.measured).map_err(crate::Error::from)?;
    let t_y = measured.column("t_s").map_err(crate::Error::from)?;
    let passes = t_y.len() / n.max(1);
    let whole_passes = a.periodic && passes >= 2 && t_y.len() == passes * n;
    if t_y.len() != n && !whole_passes {
        return Err(crate::Error::Usage(format!(
            "{}: {} samples, but the command {} has {n}: record one trial of the table{}",
            a.measured.display(),
            t_y.len(),
            a.command.display(),
            if a.periodic {
                " (or, --periodic, whole passes of it)"
            } else {
                ""
            }
        )));
    }
    let (period_u, period_y) = (mean_period(&t_u), mean_period(t_y));
    if !((period_y - period_u).abs() <= 1e-6 * period_u.abs()) {
        return Err(crate::Error::Usage(format!(
            "{}: sample period {period_y} s differs from the command {}'s {period_u} s",
            a.measured.display(),
            a.command.display()
        )));
    }
    let columns = measured_columns(&measured, a.y.as_deref(), axes.len())?;
    let params = a.learning.params();
    let names: Vec<&'static str> = valid.axes.iter().map(|v| v.name).collect();
    let learnings = axis_learnings(&axes, &names, params)?;
    let mut y = Vec::new();
    for column in &columns {
        let factor = unit_factor(column).ok_or_else(|| {
            crate::Error::Usage(format!(
                "{}: column `{}` has no length unit (m, mm, um, nm)",
                a.measured.display(),
                column
            ))
        })?;
        y.push(
            measured
                .column(column)
                .map_err(|e| crate::Error::Usage(format!("--y: {e}")))?
                .iter()
                .map(|&v| (v * factor) as f32)
                .collect::<Vec<f32>>(),
        );
    }
    // Several whole passes: their average, and its noise from the spread between them (the
    // table, the command, is the same every pass).
    let noise: Option<Vec<Option<TrialNoise>>> = whole_passes.then(|| {
        y.iter()
            .map(|record| {
                piezo_core::pass_noise_rms(record, n).map(|measured_m| TrialNoise {
                    measured_m,
                    command_v: 0.0,
                })
            })
            .collect()
    });
    if whole_passes {
        y = y.iter().map(|record| average_passes(record, n)).collect();
    }
    let base_v: Vec<Vec<f32>> = base.voltages_v.iter().map(|(_, u)| u.clone()).collect();
    let files = StepFiles {
        params: &a.params,
        reference: &a.reference,
    };
    let (steps, next) = step_checked(
        &AxesTrial {
            learnings: &learnings,
            names: &names,
            reference: &reference,
            command_v: &u,
            measured_m: &y,
            base_v: &base_v,
            periodic: a.periodic,
            noise: noise.as_deref(),
            table_v: None,
            previous: learned_from
                .as_ref()
                .filter(|_| a.periodic)
                .map(|trial| AxesPrevious {
                    command_v: &trial.command_v,
                    measured_m: &trial.measured_m,
                    table_v: None,
                }),
            remembered: Some(&remembered),
        },
        &files,
    )?;
    let next_v = base
        .voltages_v
        .iter()
        .map(|(name, _)| name.clone())
        .zip(next)
        .collect();
    Ok(LearnStep {
        t_s: reference.t_s.clone(),
        next_v,
        reference,
        iteration: iteration + 1,
        stage_fnv1a32: stage_hash,
        axes: steps,
        params,
        periodic: a.periodic,
        learned_from: a.periodic.then_some(LearnedFrom {
            command_v: u,
            measured_m: y,
        }),
    })
}

/// The mean of `record`'s whole passes of `period` samples, per sample (non-finite samples left
/// out; NaN where no pass has one).
pub fn average_passes(record: &[f32], period: usize) -> Vec<f32> {
    (0..period)
        .map(|j| {
            let (sum, count) = record
                .iter()
                .skip(j)
                .step_by(period)
                .filter(|v| v.is_finite())
                .fold((0.0f64, 0usize), |(s, c), &v| (s + f64::from(v), c + 1));
            (sum / count as f64) as f32
        })
        .collect()
}

/// Writes `step`'s table to `out` with its `#` lines (the iteration, the stage file `params`'s
/// fingerprint and name): the file `learn` reads as `--command`.
pub fn write_learned_table(out: &Path, step: &LearnStep, params: &Path) -> crate::Result<()> {
    write_csv(out, &step.to_table())
        .map_err(|e| crate::Error::Usage(format!("{}: {e}", out.display())))?;
    let text = std::fs::read_to_string(out).map_err(crate::Error::read("", out))?;
    std::fs::write(out, step.header(params) + &text).map_err(crate::Error::write("", out))
}

/// `host-sim learn`: computes and writes the next command and the report; returns a summary.
pub fn learn_cmd(a: &LearnArgs) -> crate::Result<String> {
    let step = learn(a)?;
    write_learned_table(&a.out, &step, &a.params)
        .map_err(|e| crate::Error::Usage(format!("--out {e}")))?;
    let json = serde_json::to_string_pretty(&step.report()).map_err(crate::Error::from)?;
    if let Some(dir) = a.report.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(crate::Error::write("--report", dir))?;
    }
    std::fs::write(&a.report, json).map_err(crate::Error::write("--report", &a.report))?;
    let axes: Vec<String> = step
        .axes
        .iter()
        .map(|s| {
            format!(
                "{}: rms {:.3e} m, max {:.3e} m, noise {:.2e} m, learned share {:.2}, Q cut-off {:.0} Hz, {} limited",
                s.axis, s.rms_m, s.max_abs_m, s.noise_rms_m, s.learned_share, s.q_cutoff_hz, s.limited
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A two-axis table carries the trial it was learned from in the columns the next step
    /// reads it from, and a table without them gives none.
    #[test]
    fn a_two_axis_table_carries_its_trial() {
        let dir = tempfile::tempdir().unwrap();
        let reference_path = dir.path().join("r.csv");
        std::fs::write(&reference_path, "t_s,rx_m,ry_m\n0,0,1e-6\n0.0001,1e-6,0\n").unwrap();
        let reference = read_reference(&reference_path).unwrap();
        let params = dir.path().join("stage.toml");
        let context = TableContext {
            params: &params,
            stage_hash: 0,
            reference_path: &reference_path,
            reference: &reference,
        };
        let step = LearnStep {
            t_s: reference.t_s.clone(),
            next_v: vec![
                ("ux_V".to_string(), vec![1.0, 2.0]),
                ("uy_V".to_string(), vec![3.0, 4.0]),
            ],
            reference: reference.clone(),
            iteration: 1,
            stage_fnv1a32: 0,
            axes: Vec::new(),
            params: LearningParams::default(),
            periodic: true,
            learned_from: Some(LearnedFrom {
                command_v: vec![vec![0.5, 1.5], vec![2.5, 3.5]],
                measured_m: vec![vec![1e-7, 2e-7], vec![3e-7, 4e-7]],
            }),
        };
        let path = dir.path().join("u1.csv");
        write_learned_table(&path, &step, &params).unwrap();
        let table = read_learned_table(&path, &context, 2).unwrap();
        assert_eq!(table.voltages_v, vec![vec![1.0, 2.0], vec![3.0, 4.0]]);
        assert_eq!(table.learned_from, step.learned_from);
        let bare = LearnStep {
            learned_from: None,
            ..step
        };
        write_learned_table(&path, &bare, &params).unwrap();
        assert_eq!(
            read_learned_table(&path, &context, 2).unwrap().learned_from,
            None
        );
    }

    /// A table's remembered responses are read back as written, and a line that does not read
    /// as `h:re:im` entries is refused naming the file and the line.
    #[test]
    fn a_table_s_harmonic_responses_are_read_back_and_a_bad_line_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("u1.csv");
        let body = "t_s,u_V,r_m\n0,1,0\n0.0001,2,0\n";
        std::fs::write(
            &path,
            format!("# {RESPONSES_KEY}u_V: 3:1.5e-7:-2e-7 7:0:4e-6\n{body}"),
        )
        .unwrap();
        let file = read_command(&path).unwrap();
        assert_eq!(
            file.remembered,
            vec![(
                "u_V".to_string(),
                vec![(3, [1.5e-7, -2e-7]), (7, [0.0, 4e-6])]
            )]
        );
        std::fs::write(&path, format!("# {RESPONSES_KEY}u_V: 3:1.5e-7\n{body}")).unwrap();
        let Err(e) = read_command(&path) else {
            panic!("a response without its imaginary part was read");
        };
        let message = e.to_string();
        assert!(
            message.contains("u1.csv:1:") && message.contains("unreadable learn header"),
            "{message}"
        );
    }

    /// An axis's entry of `STEP.json` has the keys it has always had, the model gain's ratio
    /// alone and no axis name (the entry's key).
    #[test]
    fn an_axis_step_serialises_with_the_keys_of_step_json() {
        let step = AxisStep {
            axis: "x",
            rms_m: 1e-8,
            max_abs_m: 3e-8,
            q_cutoff_hz: 900.0,
            learning_gain: 0.9,
            limited: 0,
            noise_rms_m: 1e-9,
            learned_share: 0.95,
            harmonics_learned: 2,
            harmonic_scale: 0.5,
            noise_from_passes: true,
            model_gain: Some((1.2, 1e-7)),
            remembered: Vec::new(),
        };
        let report = AxisStepReport {
            step: &step,
            model_gain_ratio: step.model_gain.map(|g| g.0),
            base_resolved: true,
        };
        let json = crate::to_json(&report).unwrap();
        assert_eq!(
            crate::json_keys(&json),
            std::collections::BTreeSet::from([
                "rms_m",
                "max_abs_m",
                "q_cutoff_hz",
                "learning_gain",
                "limited",
                "noise_rms_m",
                "learned_share",
                "harmonics_learned",
                "harmonic_scale",
                "noise_from_passes",
                "model_gain_ratio",
                "base_resolved",
            ])
        );
        assert_eq!(json["model_gain_ratio"], 1.2);
    }
}
