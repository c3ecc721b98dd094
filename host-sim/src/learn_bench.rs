//! `host-sim learn-bench`: iterative learning control ([`piezo_core::learning`]) on the XY stage
//! of `servo-bench` — host-sim's f64 plant (piezo-reference, independent of the core) with
//! creep, drift, sensor noise, ADC and DAC quantisation and its flexure modes — for periodic
//! triangles and sines.
//!
//! **Stage file**: `servo-bench`'s (the stacks' Bouc-Wen sets scaled by the identified platform
//! gain, its servo) plus, per axis, the first mode identified from the step response and a delay
//! of half a loop period (the zero-order hold: sample j is held over \[t_j, t_{j+1}) and read at
//! t_j). Robustness rows scale its static gain (k1, k2) or its mode frequency.
//!
//! **Run** (one continuous run per row, tick by tick at the loop rate): a fade-in from rest to
//! the reference's first sample (50 ms), the compensator's own command over whole periods of at
//! least 0.1 s (`compensate`'s chain on that reference), then trials: trial k plays the periodic
//! table u_k over the fewest whole periods lasting ≥ 0.1 s and numbering ≥ 10 as far as they fit
//! in 1 s (a trial's RMS error at the sensor's noise spreads less from one trial to the next the
//! more periods it holds), after `settle_periods` whole periods
//! (1 by default, as `link learn`) in which the new table settles: the switch's transient — with
//! feedback the servo unwinding the correction the table took over, and the creep of the step —
//! is not periodic, and a trial of one period that recorded it taught the next table to undo it
//! (at 10 Hz the second trial rose 1.33× above the first, 1.56× with the stage file's mode 15 %
//! low). The table of trial 0 is the compensator's command of the next period. After each
//! trial the readings and the applied voltages (table + servo correction with feedback) are
//! averaged over its periods, and the learning step (periodic) gives u_{k+1}; with `--back-off`,
//! unless the trial's measured error grew: then the axis steps back halfway to the table before
//! (`piezo_core::learning::back_off`). Modes: **learned** (the table alone) and
//! **learned+feedback** (the servo of the stage file adds its correction to the table; the
//! learning then sees the applied voltage, so its factor is S·Q·(1 − L·G)).
//!
//! **Figures**: per trial the RMS and the largest |true position − reference| over the trial, in
//! % of the axis's stroke, the worse axis; references between 20 % and 90 % of the stroke.

#![allow(clippy::needless_range_loop)] // axis indices run over parallel per-axis arrays

use crate::compensate::{feedforward_axes, periodic_settings};
use crate::effects::Effects;
use crate::learn::{rebase, rescaled, rule_text};
use crate::plant::XyStage;
use crate::plot::{plot_grid, Chart, Legend, Panel, Role, Series};
use crate::servo_bench::{
    controllers, default_plant_effects, identify_rig, stack_file_at, Rig, Shape,
    DEFAULT_LOOP_RATE_HZ, HIGH, LOW,
};
use piezo_core::learning::{step_back, BackOff, Verdict};
use piezo_core::{
    compensate_pair, compensate_periodic_pair, pass_noise_rms, Learning, LearningParams,
    PreviousTrial, ServoMode, ServoState, Trial, TrialNoise,
};
use piezo_stage::StageFile;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// How the learned table reaches the stage.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LearnMode {
    /// The table alone.
    Learned,
    /// The table plus the servo's correction.
    LearnedFeedback,
}

impl LearnMode {
    /// `learned` or `learned+feedback`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Learned => "learned",
            Self::LearnedFeedback => "learned+feedback",
        }
    }

    fn servo_mode(self) -> ServoMode {
        match self {
            Self::Learned => ServoMode::Feedforward,
            Self::LearnedFeedback => ServoMode::FeedforwardFeedback,
        }
    }
}

/// What is changed in the stage file the learning and the compensator use.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Perturbation {
    /// The identified file.
    Nominal,
    /// Static gain (k1, k2) times this.
    Gain(f64),
    /// Mode frequency times this.
    ModeFrequency(f64),
}

impl Perturbation {
    /// `nominal`, `gain x0.6`, `mode x1.15`.
    pub fn label(self) -> String {
        match self {
            Self::Nominal => "nominal".into(),
            Self::Gain(g) => format!("gain x{g}"),
            Self::ModeFrequency(m) => format!("mode x{m}"),
        }
    }
}

/// What the bench runs.
#[derive(Debug, Clone, PartialEq)]
pub struct LearnBenchSettings {
    /// Loop rate \[Hz\].
    pub loop_rate_hz: f64,
    /// Reference frequencies (Hz).
    pub frequencies_hz: Vec<f64>,
    /// Reference shapes.
    pub shapes: Vec<Shape>,
    /// Modes.
    pub modes: Vec<LearnMode>,
    /// Learning steps (trials 0 ..= this).
    pub iterations: usize,
    /// A trial is the fewest whole periods lasting at least this \[s\] ...
    pub trial_min_s: f64,
    /// ... and numbering at least this many, as far as they fit in [`TRIAL_PERIODS_WITHIN_S`]:
    /// at the sensor's noise a trial's RMS error spreads from one trial to the next, less the
    /// more periods it holds (a 10 Hz trial of one period rose up to 1.08× with its table
    /// replayed unchanged, of ten periods 1.03×).
    pub trial_min_periods: usize,
    /// Whole periods each new table plays before its trial is recorded (`link learn`'s
    /// `--settle-periods`): the switch's transient, the servo unwinding the correction the table
    /// took over, is not the table's error.
    pub settle_periods: usize,
    /// The compensator's warm-up: whole periods lasting at least this \[s\].
    pub warmup_min_s: f64,
    /// Fade-in from rest \[s\].
    pub fade_in_s: f64,
    /// Effect specs the plant carries.
    pub plant_effects: Vec<String>,
    /// The learning's uncertainty and margin.
    pub params: LearningParams,
    /// Perturbed stage files, each run on `robustness_cases` in `robustness_mode`.
    pub perturbations: Vec<Perturbation>,
    /// (shape, frequency) of the robustness rows.
    pub robustness_cases: Vec<(Shape, f64)>,
    /// Mode of the robustness rows.
    pub robustness_mode: LearnMode,
    /// The error-growth back-off between trials (`piezo_core::learning::back_off`; off by
    /// default: on this bench, with one settling period per table, it moved the targets' final
    /// errors by at most 5 % and made the learned-only 10 Hz sine erratic, rises up to 2.0×).
    pub back_off: bool,
    /// Trials the last table plays again after the last trial, without learning: the spread
    /// of one table's error from trial to trial (the sensor's noise, the drift), against which
    /// a rise between learning trials is read.
    pub repeat_trials: usize,
}

impl Default for LearnBenchSettings {
    fn default() -> Self {
        Self {
            loop_rate_hz: DEFAULT_LOOP_RATE_HZ,
            frequencies_hz: vec![1.0, 10.0, 100.0],
            shapes: vec![Shape::Triangle, Shape::Sine],
            modes: vec![LearnMode::Learned, LearnMode::LearnedFeedback],
            iterations: 15,
            trial_min_s: 0.1,
            trial_min_periods: 10,
            settle_periods: 1,
            warmup_min_s: 0.1,
            fade_in_s: 0.05,
            plant_effects: default_plant_effects(DEFAULT_LOOP_RATE_HZ),
            params: LearningParams::default(),
            perturbations: vec![
                Perturbation::Gain(0.6),
                Perturbation::Gain(1.5),
                Perturbation::ModeFrequency(1.15),
                Perturbation::ModeFrequency(0.85),
            ],
            robustness_cases: vec![
                (Shape::Sine, 100.0),
                (Shape::Triangle, 100.0),
                (Shape::Triangle, 10.0),
            ],
            robustness_mode: LearnMode::LearnedFeedback,
            back_off: false,
            repeat_trials: 3,
        }
    }
}

/// The error of every trial of one run.
#[derive(Debug, Clone, PartialEq)]
pub struct Curve {
    /// Mode.
    pub mode: LearnMode,
    /// Shape.
    pub shape: Shape,
    /// Frequency \[Hz\].
    pub freq_hz: f64,
    /// The stage file's perturbation.
    pub perturbation: Perturbation,
    /// Per trial (0 = the compensator's command): RMS error, % of stroke, worse axis.
    pub rms_percent: Vec<f64>,
    /// Per trial: largest |error|, % of stroke, worse axis.
    pub max_percent: Vec<f64>,
    /// Cut-off of Q per axis \[Hz\].
    pub cutoff_hz: [f64; 2],
    /// Periods per trial.
    pub periods_per_trial: usize,
    /// RMS of the last trial's measured error (averaged over its periods) above Q's cut-off,
    /// % of stroke, worse axis: what the learning leaves to the compensator.
    pub above_cutoff_percent: f64,
    /// Per learning step: the harmonics above Q's cut-off learned from the stage's response
    /// measured on the trial, the worse axis's count.
    pub harmonics_learned: Vec<usize>,
    /// Per learning step: whether an axis stepped back (its trial's measured error grew more
    /// than 5 % above the trial before's; `piezo_core::learning::back_off`).
    pub stepped_back: Vec<bool>,
    /// The last table played again, without learning, per trial: RMS error, % of stroke, worse
    /// axis ([`LearnBenchSettings::repeat_trials`]).
    pub repeat_percent: Vec<f64>,
}

impl Curve {
    /// The error of the last trial (RMS, % of stroke).
    pub fn last(&self) -> f64 {
        self.rms_percent.last().copied().unwrap_or(f64::NAN)
    }

    /// The largest ratio between consecutive trials of the last table played again (the last
    /// trial and its repeats): how much one table's error moves from trial to trial by itself.
    pub fn repeat_spread(&self) -> f64 {
        let again = std::iter::once(self.last()).chain(self.repeat_percent.iter().copied());
        worst_ratio(again, f64::NAN)
    }

    /// The largest ratio rms\[k\]/rms\[k−1\] for k > `after`.
    pub fn worst_ratio_after(&self, after: usize) -> f64 {
        worst_ratio(self.rms_percent.iter().skip(after).copied(), 0.0)
    }
}

/// The largest ratio of a value to the one before it, folded from `empty` (what fewer than two
/// values give) with `f64::max`.
fn worst_ratio(values: impl Iterator<Item = f64>, empty: f64) -> f64 {
    let mut before = None;
    let mut worst = empty;
    for v in values {
        if let Some(b) = before {
            worst = f64::max(worst, v / b);
        }
        before = Some(v);
    }
    worst
}

/// Everything the bench measured.
#[derive(Debug, Clone)]
pub struct LearnBenchReport {
    /// Nominal runs.
    pub curves: Vec<Curve>,
    /// Robustness runs.
    pub robustness: Vec<Curve>,
    /// The stage file the learning used (nominal).
    pub stage_toml: String,
    /// Largest sensitivity |S| of each axis's servo (the learned+feedback factor's bound).
    pub sensitivity_peak: [f64; 2],
    /// The settings.
    pub settings: LearnBenchSettings,
    /// Wall-clock seconds.
    pub seconds: f64,
}

/// The rig and the stage file every run starts from.
struct Context<'a> {
    stage: &'a XyStage,
    effects: &'a Effects,
    file: StageFile,
    stroke_m: [f64; 2],
    settings: &'a LearnBenchSettings,
}

/// The stage file with `p` applied.
fn perturbed(file: &StageFile, p: Perturbation) -> crate::Result<StageFile> {
    let mut file = file.clone();
    for axis in [Some(&mut file.x), file.y.as_mut()].into_iter().flatten() {
        match p {
            Perturbation::Nominal => {}
            Perturbation::Gain(g) => {
                let map = axis
                    .static_map
                    .as_mut()
                    .ok_or_else(|| crate::Error::Usage("no static map".into()))?;
                map.k1_m_per_v = (f64::from(map.k1_m_per_v) * g) as f32;
                map.k2_m_per_h = (f64::from(map.k2_m_per_h) * g) as f32;
            }
            Perturbation::ModeFrequency(m) => {
                let f = &mut axis.effects.mode_frequency_hz;
                *f = (f64::from(*f) * m) as f32;
            }
        }
    }
    Ok(file)
}

/// One run: warm-up, then `iterations + 1` trials with a learning step after each but the last.
fn run_case(
    ctx: &Context<'_>,
    shape: Shape,
    freq_hz: f64,
    mode: LearnMode,
    perturbation: Perturbation,
) -> crate::Result<Curve> {
    let s = ctx.settings;
    let fs = s.loop_rate_hz;
    let file = perturbed(&ctx.file, perturbation)?;
    let valid = file.validate().map_err(crate::Error::from)?;
    let axes = feedforward_axes(&file, &valid, Path::new("learn-bench stage file"))?;
    let mut learning = Vec::new();
    let mut servos = Vec::new();
    for (a, v) in valid.axes.iter().enumerate() {
        learning.push(
            Learning::new(&axes[a].compensator, &axes[a].effects, s.params)
                .map_err(|e| crate::Error::Usage(format!("learning of axis {}: {e}", v.name)))?,
        );
        servos.push(
            v.servo
                .ok_or_else(|| crate::Error::Usage("the stage file has no servo".into()))?,
        );
    }
    let period = (fs / freq_hz).round() as usize;
    let whole = |min_s: f64| ((min_s * freq_hz).ceil() as usize).max(1);
    let trial_periods =
        whole(s.trial_min_s).max(s.trial_min_periods.min(whole(TRIAL_PERIODS_WITHIN_S)));
    let warm_periods = whole(s.warmup_min_s);
    let lead = (s.fade_in_s * fs).round() as usize;
    let r: [Vec<f32>; 2] = [0, 1].map(|a| {
        (0..period)
            .map(|j| {
                let unit = shape.unit(freq_hz, j as f64 / fs);
                (ctx.stroke_m[a] * (LOW + (HIGH - LOW) * unit)) as f32
            })
            .collect()
    });
    // The stage's warm-up: the compensator over the fade-in and warm_periods periods (then the
    // table for as many).
    let full = lead + warm_periods * period;
    let reference = |a: usize, k: usize| -> f32 {
        if k < lead {
            let fade = 0.5 - 0.5 * (std::f64::consts::PI * k as f64 / lead as f64).cos();
            (f64::from(r[a][0]) * fade) as f32
        } else {
            r[a][(k - lead) % period]
        }
    };
    let full_r: [Vec<f32>; 2] = [0, 1].map(|a| (0..full).map(|k| reference(a, k)).collect());
    let (mut ux, mut uy) = (vec![0.0f32; full], vec![0.0f32; full]);
    compensate_pair(
        [&axes[0], &axes[1]],
        [&full_r[0], &full_r[1]],
        [&mut ux, &mut uy],
    );
    let warm = lead + warm_periods * period;
    // u_0: the period the compensator settles to with the reference played in a loop (as
    // `host-sim learn --periodic`), re-solved for the gain and offset a trial shows
    // (`learn::rebase`, as `host-sim learn`).
    let settings = periodic_settings(&axes, period as f64 / fs);
    let periodic_base = |gain_offset: &[(f64, f64)]| -> [Vec<f32>; 2] {
        let scaled: [Vec<f32>; 2] = [0, 1].map(|a| {
            let (gain, offset) = gain_offset[a];
            r[a].iter()
                .map(|&v| ((f64::from(v) - offset) / gain) as f32)
                .collect()
        });
        let (mut ux, mut uy) = (vec![0.0f32; period], vec![0.0f32; period]);
        compensate_periodic_pair(
            [&axes[0], &axes[1]],
            [&scaled[0], &scaled[1]],
            settings,
            [&mut ux, &mut uy],
        );
        [ux, uy]
    };
    let mut base = periodic_base(&[(1.0, 0.0); 2]);
    let mut table = base.clone();
    let mut rig = Rig::new(ctx.stage, ctx.effects, fs);
    let mut states = [0, 1].map(|a| ServoState::at_rest(axes[a].rest_v, mode.servo_mode()));
    let mut tick = |states: &mut [ServoState; 2], r_now: [f32; 2], ff: [f32; 2]| {
        let (truth, read) = rig.sense();
        let mut u = [0.0f32; 2];
        for a in 0..2 {
            u[a] = servos[a]
                .step(&mut states[a], r_now[a], read[a] as f32, ff[a])
                .voltage_v;
        }
        rig.apply(u.map(f64::from))?;
        Ok::<_, crate::Error>((truth, read, u))
    };
    for k in 0..warm {
        tick(&mut states, [full_r[0][k], full_r[1][k]], [ux[k], uy[k]])?;
    }
    // Then the table itself, so that the stage's hysteresis settles on its loop before trial 0.
    for _ in 0..warm_periods {
        for j in 0..period {
            tick(&mut states, [r[0][j], r[1][j]], [base[0][j], base[1][j]])?;
        }
    }
    let (mut rms_percent, mut max_percent) = (Vec::new(), Vec::new());
    let mut above_cutoff_percent = 0.0f64;
    let mut harmonics_learned = Vec::new();
    let mut stepped_back = Vec::new();
    let mut repeat_percent = Vec::new();
    // A trial's RMS error from its sums of squares per axis, % of stroke, the worse axis.
    let ticks = (trial_periods * period) as f64;
    let worst_percent = |sq: [f64; 2]| {
        (0..2)
            .map(|a| 100.0 * (sq[a] / ticks).sqrt() / ctx.stroke_m[a])
            .fold(0.0, f64::max)
    };
    // The error-growth back-off per axis and the table it holds (`piezo_core::learning::back_off`).
    let mut back_off = [BackOff::new(); 2];
    let mut held = table.clone();
    // The trial before's averaged command and measured period (the harmonic step's two-trial
    // estimate).
    // (voltages applied, readings, table), per axis.
    type PerAxis = [Vec<f32>; 2];
    let mut last_trial: Option<(PerAxis, PerAxis, PerAxis)> = None;
    let servo_on = mode == LearnMode::LearnedFeedback;
    for trial in 0..=s.iterations {
        if trial > 0 {
            for _ in 0..s.settle_periods {
                for j in 0..period {
                    tick(&mut states, [r[0][j], r[1][j]], [table[0][j], table[1][j]])?;
                }
            }
        }
        let mut y_sum = [vec![0.0f64; period], vec![0.0f64; period]];
        let mut u_sum = [vec![0.0f64; period], vec![0.0f64; period]];
        // Every pass, for the noise of their average (the spread between them).
        let mut y_passes = [Vec::new(), Vec::new()];
        let mut u_passes = [Vec::new(), Vec::new()];
        let (mut sq, mut max) = ([0.0f64; 2], [0.0f64; 2]);
        for _ in 0..trial_periods {
            for j in 0..period {
                let (truth, read, u) =
                    tick(&mut states, [r[0][j], r[1][j]], [table[0][j], table[1][j]])?;
                for a in 0..2 {
                    let e = truth[a] - f64::from(r[a][j]);
                    sq[a] += e * e;
                    max[a] = max[a].max(e.abs());
                    y_sum[a][j] += read[a];
                    u_sum[a][j] += f64::from(u[a]);
                    y_passes[a].push(read[a] as f32);
                    u_passes[a].push(u[a]);
                }
            }
        }
        rms_percent.push(worst_percent(sq));
        max_percent.push(
            (0..2)
                .map(|a| 100.0 * max[a] / ctx.stroke_m[a])
                .fold(0.0, f64::max),
        );
        let m = trial_periods as f64;
        if trial == s.iterations {
            for a in 0..2 {
                let e: Vec<f64> = (0..period)
                    .map(|j| y_sum[a][j] / m - f64::from(r[a][j]))
                    .collect();
                let above = rms_above(&e, fs, learning[a].cutoff_hz());
                above_cutoff_percent = above_cutoff_percent.max(100.0 * above / ctx.stroke_m[a]);
            }
            // The same table again, without learning (its spread from trial to trial).
            for _ in 0..s.repeat_trials {
                let mut sq = [0.0f64; 2];
                for _ in 0..trial_periods {
                    for j in 0..period {
                        let (truth, _, _) =
                            tick(&mut states, [r[0][j], r[1][j]], [table[0][j], table[1][j]])?;
                        for a in 0..2 {
                            sq[a] += (truth[a] - f64::from(r[a][j])).powi(2);
                        }
                    }
                }
                repeat_percent.push(worst_percent(sq));
            }
            break;
        }
        let y: [Vec<f32>; 2] = [0, 1].map(|a| y_sum[a].iter().map(|v| (v / m) as f32).collect());
        let u: [Vec<f32>; 2] = [0, 1].map(|a| u_sum[a].iter().map(|v| (v / m) as f32).collect());
        let gains = [0, 1].map(|a| {
            learning[a].gain_ratio(&Trial {
                reference_m: &r[a],
                command_v: &u[a],
                measured_m: &y[a],
                base_v: &base[a],
                periodic: true,
                noise: None,
                previous: None,
                table_v: None,
            })
        });
        let noise = [0, 1].map(|a| {
            Some(TrialNoise {
                measured_m: pass_noise_rms(&y_passes[a], period)?,
                command_v: pass_noise_rms(&u_passes[a], period)?,
            })
        });
        let previous = table.clone();
        let mut harmonics = [0usize; 2];
        let mut backed = false;
        let mut stepping = learning.clone();
        if let Some(gain_offset) = rebase(&gains, &s.params) {
            base = periodic_base(&gain_offset);
            stepping = rescaled(&learning, &gain_offset)?;
        }
        for a in 0..2 {
            let (y, u) = (&y[a], &u[a]);
            // The trial's measured error (its averaged period) against the held table's.
            let measured_rms = (y
                .iter()
                .zip(&r[a])
                .map(|(&y, &r)| f64::from(r - y).powi(2))
                .sum::<f64>()
                / period as f64)
                .sqrt();
            let verdict = if s.back_off {
                back_off[a].judge(measured_rms)
            } else {
                Verdict::Learn
            };
            match verdict {
                Verdict::Learn => {
                    held[a].clone_from(&previous[a]);
                    let rho = s.params.harmonic_gain * back_off[a].harmonic_scale() as f32;
                    stepping[a]
                        .with_harmonic_gain(rho)
                        .map_err(crate::Error::from)?
                        .step(
                            &Trial {
                                reference_m: &r[a],
                                command_v: u,
                                measured_m: y,
                                base_v: &base[a],
                                periodic: true,
                                noise: noise[a],
                                previous: last_trial.as_ref().map(|(u, y, t)| PreviousTrial {
                                    command_v: &u[a],
                                    measured_m: &y[a],
                                    table_v: servo_on.then_some(t[a].as_slice()),
                                }),
                                table_v: servo_on.then_some(previous[a].as_slice()),
                            },
                            &mut table[a],
                        )
                        .map(|summary| harmonics[a] = summary.harmonics_learned)
                        .map_err(crate::Error::from)?;
                }
                Verdict::StepBack => {
                    backed = true;
                    step_back(&held[a], &previous[a], &mut table[a]);
                }
            }
            // The new table carries the correction the servo held over the last trial: the
            // servo hands it over at the switch (entry 0).
            states[a].take_over(table[a][0] - previous[a][0]);
        }
        last_trial = Some((u, y, previous));
        harmonics_learned.push(harmonics[0].max(harmonics[1]));
        stepped_back.push(backed);
    }
    Ok(Curve {
        mode,
        shape,
        freq_hz,
        perturbation,
        rms_percent,
        max_percent,
        cutoff_hz: [learning[0].cutoff_hz(), learning[1].cutoff_hz()],
        periods_per_trial: trial_periods,
        above_cutoff_percent,
        harmonics_learned,
        stepped_back,
        repeat_percent,
    })
}

/// RMS of the components of the periodic record `e` above `cutoff_hz` (Parseval over its DFT).
fn rms_above(e: &[f64], fs: f64, cutoff_hz: f64) -> f64 {
    use rustfft::num_complex::Complex;
    let n = e.len();
    let mut spectrum: Vec<Complex<f64>> = e.iter().map(|&v| Complex::new(v, 0.0)).collect();
    rustfft::FftPlanner::new()
        .plan_fft_forward(n)
        .process(&mut spectrum);
    let above: f64 = spectrum
        .iter()
        .enumerate()
        .filter(|(k, _)| (*k).min(n - k) as f64 * fs / n as f64 > cutoff_hz)
        .map(|(_, x)| x.norm_sqr())
        .sum();
    above.sqrt() / n as f64
}

/// Runs the bench; `progress` receives one line per phase.
pub fn run_learn_bench(
    settings: &LearnBenchSettings,
    progress: &mut (dyn FnMut(&str) + Send),
) -> crate::Result<LearnBenchReport> {
    use rayon::prelude::*;
    let start = Instant::now();
    let fs = settings.loop_rate_hz;
    let mut effects = Effects::default();
    for spec in &settings.plant_effects {
        effects
            .add_spec(spec)
            .map_err(|e| crate::Error::Usage(format!("{spec}: {e}")))?;
    }
    let stage = XyStage::default();
    let stack_file = stack_file_at(fs)?;
    let stack = stack_file.validate().map_err(crate::Error::from)?;
    progress("identifying the platform gain and the first mode");
    let identified = identify_rig(&stage, &effects, &stack, fs)?;
    let (_, tunings, mut file) = controllers(&stack_file, &identified)?;
    for (axis, &(_, f, zeta)) in [Some(&mut file.x), file.y.as_mut()]
        .into_iter()
        .flatten()
        .zip(&identified)
    {
        axis.effects.mode_frequency_hz = f as f32;
        axis.effects.mode_damping = zeta as f32;
        axis.effects.delay_s = (0.5 / fs) as f32;
    }
    file.stage.name = "xy-stage-learn".into();
    let (ax, ay) = stage.axes();
    let g = stage.static_gain();
    let stroke_m = [g[0] * ax.free_stroke_m, g[1] * ay.free_stroke_m];
    let ctx = Context {
        stage: &stage,
        effects: &effects,
        file,
        stroke_m,
        settings,
    };
    let mut cases = Vec::new();
    for &shape in &settings.shapes {
        for &f in &settings.frequencies_hz {
            for &mode in &settings.modes {
                cases.push((shape, f, mode, Perturbation::Nominal));
            }
        }
    }
    let nominal = cases.len();
    for &p in &settings.perturbations {
        for &(shape, f) in &settings.robustness_cases {
            cases.push((shape, f, settings.robustness_mode, p));
        }
    }
    progress(&format!(
        "learning: {} runs of {} trials",
        cases.len(),
        settings.iterations + 1
    ));
    let mut curves: Vec<Curve> = cases
        .par_iter()
        .map(|&(shape, f, mode, p)| run_case(&ctx, shape, f, mode, p))
        .collect::<crate::Result<_>>()?;
    let robustness = curves.split_off(nominal);
    Ok(LearnBenchReport {
        curves,
        robustness,
        stage_toml: ctx.file.to_toml(
            "The XY stage as learn-bench identifies it: xy-stage.toml scaled to the platform, its \
             servo, the first mode and half a loop period of delay",
        ),
        sensitivity_peak: [
            f64::from(tunings[0].sensitivity_peak),
            f64::from(tunings[1].sensitivity_peak),
        ],
        settings: settings.clone(),
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// A trial holds at least [`LearnBenchSettings::trial_min_periods`] periods as far as they fit
/// in this \[s\].
pub const TRIAL_PERIODS_WITHIN_S: f64 = 1.0;

/// A target of the bench: (shape, frequency, largest RMS % of stroke after the last trial).
pub const TARGETS: [(Shape, f64, f64); 3] = [
    (Shape::Sine, 100.0, 0.01),
    (Shape::Triangle, 100.0, 0.1),
    (Shape::Triangle, 10.0, 0.01),
];

impl LearnBenchReport {
    /// The nominal curve of a case.
    pub fn curve(&self, mode: LearnMode, shape: Shape, freq_hz: f64) -> Option<&Curve> {
        self.curves
            .iter()
            .find(|c| c.mode == mode && c.shape == shape && c.freq_hz == freq_hz)
    }

    /// The table as printed.
    pub fn table(&self) -> String {
        let n = self.settings.iterations;
        let mut s = format!(
            "rule: {}\nlearned+feedback: factor |S| * |Q(1 - LG)|, servo |S| peak x {:.2}, y {:.2}\n\n",
            rule_text(&self.settings.params),
            self.sensitivity_peak[0],
            self.sensitivity_peak[1]
        );
        s += "RMS error per trial [% of stroke, worse axis] (trial 0: the compensator's command)\n\n";
        s += "| mode | signal | freq [Hz] | Q cut-off x/y [Hz] |";
        for k in 0..=n {
            s += &format!(" {k} |");
        }
        s += " max after last [%] | above cut-off [%] | worst ratio after 3 | same table again, worst ratio | harmonics learned (last step) |\n|---|---|---|---|";
        s += &"---|".repeat(n + 6);
        s += "\n";
        for c in &self.curves {
            s += &self.row(c, &format!("| {} ", c.mode.name()));
        }
        s += "\nRobustness (stage file perturbed; final / nominal final):\n\n";
        s += "| perturbation | mode | signal | freq [Hz] | Q cut-off x/y [Hz] | first | last | \
              worst ratio after 1 | same table again, worst ratio | final / nominal |\n\
              |---|---|---|---|---|---|---|---|---|---|\n";
        for c in &self.robustness {
            let nominal = self
                .curve(c.mode, c.shape, c.freq_hz)
                .map_or(f64::NAN, Curve::last);
            s += &format!(
                "| {} | {} | {} | {} | {:.0}/{:.0} | {:.4} | {:.5} | {:.3} | {:.3} | {:.2} |\n",
                c.perturbation.label(),
                c.mode.name(),
                c.shape.name(),
                c.freq_hz,
                c.cutoff_hz[0],
                c.cutoff_hz[1],
                c.rms_percent[0],
                c.last(),
                c.worst_ratio_after(1),
                c.repeat_spread(),
                c.last() / nominal
            );
        }
        s += "\nTargets (RMS after the last trial, the better mode):\n";
        for (shape, f, limit) in TARGETS {
            let best = self
                .curves
                .iter()
                .filter(|c| c.shape == shape && c.freq_hz == f)
                .map(|c| (c.last(), c.mode.name()))
                .min_by(|a, b| a.0.total_cmp(&b.0));
            if let Some((v, mode)) = best {
                s += &format!(
                    "  {f} Hz {}: {v:.5} % ({mode}) <= {limit} %: {}\n",
                    shape.name(),
                    if v <= limit { "met" } else { "NOT met" }
                );
            }
        }
        s += &format!("({:.1} s)\n", self.seconds);
        s
    }

    fn row(&self, c: &Curve, start: &str) -> String {
        let mut s = format!(
            "{start}| {} | {} | {:.0}/{:.0} |",
            c.shape.name(),
            c.freq_hz,
            c.cutoff_hz[0],
            c.cutoff_hz[1]
        );
        for v in &c.rms_percent {
            s += &format!(" {v:.4} |");
        }
        s += &format!(
            " {:.4} | {:.4} | {:.3} | {:.3} | {} |\n",
            c.max_percent.last().copied().unwrap_or(f64::NAN),
            c.above_cutoff_percent,
            c.worst_ratio_after(3),
            c.repeat_spread(),
            c.harmonics_learned.last().copied().unwrap_or(0)
        );
        s
    }

    /// `learn.json`: the rule and every curve.
    pub fn report(&self) -> LearnJson<'_> {
        LearnJson {
            rule: rule_text(&self.settings.params),
            curves: self.curves.iter().map(Curve::report).collect(),
            robustness: self.robustness.iter().map(Curve::report).collect(),
        }
    }

    /// Writes `learn.json`, `learn-stage.toml` and the plot `learn-curves.*` into `dir`.
    pub fn write(&self, dir: &Path, extensions: &[&str]) -> crate::Result<Vec<String>> {
        std::fs::create_dir_all(dir).map_err(crate::Error::write("--out", dir))?;
        let mut files = Vec::new();
        let json = dir.join("learn.json");
        let text = serde_json::to_string_pretty(&self.report()).map_err(crate::Error::from)?;
        std::fs::write(&json, text).map_err(crate::Error::write("", &json))?;
        files.push(json.display().to_string());
        let toml = dir.join("learn-stage.toml");
        std::fs::write(&toml, &self.stage_toml).map_err(crate::Error::write("", &toml))?;
        files.push(toml.display().to_string());
        let panels = self.panels();
        for ext in extensions {
            let path: PathBuf = dir.join(format!("learn-curves.{ext}"));
            plot_grid(&path, &panels, 2).map_err(crate::Error::from)?;
            files.push(path.display().to_string());
        }
        Ok(files)
    }

    fn panels(&self) -> Vec<Chart> {
        let points = |c: &Curve| -> Vec<(f64, f64)> {
            c.rms_percent
                .iter()
                .enumerate()
                .map(|(k, &v)| (k as f64, v))
                .collect()
        };
        let mut panels = Vec::new();
        for &mode in &self.settings.modes {
            for &shape in &self.settings.shapes {
                let series: Vec<Series> = self
                    .curves
                    .iter()
                    .filter(|c| c.mode == mode && c.shape == shape)
                    .enumerate()
                    .map(|(i, c)| {
                        Series::line(format!("{} Hz", c.freq_hz), points(c), 100)
                            .role(Role::Other(i))
                    })
                    .collect();
                if series.is_empty() {
                    continue;
                }
                panels.push(
                    Panel::new(
                        format!("{}: {}", mode.name(), shape.name()),
                        "trial",
                        "RMS error [% of stroke]",
                        series,
                    )
                    .log_y()
                    .legend(Legend::Below),
                );
            }
        }
        for &(shape, f) in &self.settings.robustness_cases {
            let mut series: Vec<Series> = self
                .curve(self.settings.robustness_mode, shape, f)
                .map(|c| Series::line("nominal", points(c), 100).role(Role::Feedforward))
                .into_iter()
                .collect();
            for (i, c) in self
                .robustness
                .iter()
                .filter(|c| c.shape == shape && c.freq_hz == f)
                .enumerate()
            {
                series.push(
                    Series::line(c.perturbation.label(), points(c), 100).role(Role::Other(i)),
                );
            }
            panels.push(
                Panel::new(
                    format!(
                        "{}: {f} Hz {}, perturbed stage file",
                        self.settings.robustness_mode.name(),
                        shape.name()
                    ),
                    "trial",
                    "RMS error [% of stroke]",
                    series,
                )
                .log_y()
                .legend(Legend::Below),
            );
        }
        panels
    }
}

/// Arguments of `learn-bench`.
#[derive(Debug, clap::Args)]
pub struct LearnBenchArgs {
    /// Output directory (created if missing): learn.json, learn-stage.toml and the plot.
    #[arg(long, default_value = "out/learn")]
    pub out: PathBuf,
    /// Plot format: svg, png or both.
    #[arg(long, value_enum, default_value_t = crate::plot::PlotFormat::Both)]
    pub format: crate::plot::PlotFormat,
    /// Learning steps per run.
    #[arg(long, default_value_t = 15)]
    pub iterations: usize,
    /// Reference frequencies (Hz), comma-separated.
    #[arg(long, value_delimiter = ',', default_values_t = [1.0, 10.0, 100.0])]
    pub freq: Vec<f64>,
    /// Skip the robustness rows.
    #[arg(long)]
    pub no_robustness: bool,
    /// Loop rate (Hz): the stage file, the servo's tuning, the DAC and the plant's steps.
    #[arg(long, default_value_t = DEFAULT_LOOP_RATE_HZ)]
    pub rate: f64,
    /// A trial is the fewest whole periods lasting at least this (s) and numbering at least
    /// --trial-periods; the learning step sees their average (sensor noise falls as the square
    /// root of the periods).
    #[arg(long, default_value_t = 0.1)]
    pub trial_s: f64,
    /// Whole periods a trial holds at least, as far as they fit in 1 s: at the sensor's noise
    /// a shorter trial's RMS error spreads more from one trial to the next.
    #[arg(long, default_value_t = 10)]
    pub trial_periods: usize,
    /// Whole periods each new table plays before its trial is recorded (the switch's transient is
    /// not the table's error), as `link learn --settle-periods`.
    #[arg(long, default_value_t = 1)]
    pub settle_periods: usize,
    /// Trials the last table plays again without learning after the last trial (the table's
    /// spread from trial to trial, against which a rise between learning trials is read).
    #[arg(long, default_value_t = 3)]
    pub repeat_trials: usize,
    /// Effect the plant carries (host-sim effect spec, repeatable; default as servo-bench;
    /// `none` for a clean plant).
    #[arg(long = "plant-effect")]
    pub plant_effects: Vec<String>,
    /// The error-growth back-off: a trial whose measured error grew more than 5 % above the
    /// trial before's is not learned from; the next table lies halfway between the two, and the
    /// harmonic gain halves (`piezo_core::learning::back_off`).
    #[arg(long)]
    pub back_off: bool,
    /// The uncertainty the learning must converge for.
    #[command(flatten)]
    pub learning: crate::learn::LearningArgs,
}

/// Help after the options.
pub const HELP: &str = "The plant is servo-bench's: host-sim's f64 XY stage (seed 002, modes at 3.2 and 2.2 kHz) with creep, \
thermal drift, sensor noise, ADC and DAC quantisation, stepped tick by tick at 10 kHz. The stage file is servo-bench's with the \
identified first mode and half a loop period of delay. Each run: a 50 ms fade-in, the compensator's command over >= 0.1 s, then \
trials of whole periods (>= 0.1 s, and >= 10 periods as far as they fit in 1 s) playing the periodic table, each new table first settling over --settle-periods periods; after each \
trial one learning step on the averaged period. Modes \
learned (table alone) and learned+feedback (the stage file's servo on top). Robustness: the stage file's gain x0.6 and x1.5 and its \
mode frequency x1.15 and x0.85 on the 100 Hz sine and triangle and the 10 Hz triangle (learned+feedback).";

/// Runs `learn-bench`.
pub fn learn_bench_cmd(a: &LearnBenchArgs) -> crate::Result<String> {
    let mut settings = LearnBenchSettings {
        iterations: a.iterations,
        params: a.learning.params(),
        ..Default::default()
    };
    if a.freq.is_empty() || a.freq.iter().any(|&f| !(f > 0.0 && f <= 1000.0)) {
        return Err(crate::Error::Usage(format!(
            "--freq {:?}: frequencies in (0, 1000] Hz",
            a.freq
        )));
    }
    if !(a.trial_s > 0.0 && a.trial_s <= 10.0) {
        return Err(crate::Error::Usage(format!(
            "--trial-s {}: a trial lasts (0, 10] s",
            a.trial_s
        )));
    }
    if a.trial_periods == 0 {
        return Err(crate::Error::Usage(
            "--trial-periods 0: a trial holds at least one period".into(),
        ));
    }
    if !(a.rate.is_finite() && (1_000.0..=1e6).contains(&a.rate)) {
        return Err(crate::Error::Usage(format!(
            "--rate {}: a loop rate in [1000, 1e6] Hz",
            a.rate
        )));
    }
    settings.loop_rate_hz = a.rate;
    settings.plant_effects = default_plant_effects(a.rate);
    settings.trial_min_s = a.trial_s;
    settings.trial_min_periods = a.trial_periods;
    settings.settle_periods = a.settle_periods;
    settings.repeat_trials = a.repeat_trials;
    settings.back_off = a.back_off;
    settings.frequencies_hz = a.freq.clone();
    settings
        .robustness_cases
        .retain(|(_, f)| a.freq.contains(f));
    if a.no_robustness {
        settings.perturbations.clear();
    }
    if !a.plant_effects.is_empty() {
        settings.plant_effects = a
            .plant_effects
            .iter()
            .filter(|e| e.as_str() != "none")
            .cloned()
            .collect();
    }
    let report = run_learn_bench(&settings, &mut |line: &str| eprintln!("{line}"))?;
    let files = report.write(&a.out, a.format.extensions())?;
    Ok(format!("{}written: {}", report.table(), files.join(", ")))
}

/// `learn.json` ([`LearnBenchReport::report`]).
#[derive(Debug, Clone, serde::Serialize)]
pub struct LearnJson<'a> {
    /// The rule the cut-off and the shares follow.
    pub rule: String,
    /// One per mode, signal and frequency, with the nominal model.
    pub curves: Vec<CurveJson<'a>>,
    /// The same with the model perturbed.
    pub robustness: Vec<CurveJson<'a>>,
}

/// A [`Curve`] as `learn.json` writes it (percentages of the stroke, per trial).
#[derive(Debug, Clone, serde::Serialize)]
pub struct CurveJson<'a> {
    /// The mode's name.
    pub mode: &'static str,
    /// The signal's name.
    pub signal: &'static str,
    /// Its frequency \[Hz\].
    pub freq_hz: f64,
    /// The model's perturbation.
    pub perturbation: String,
    /// Q's cut-off per axis \[Hz\].
    pub q_cutoff_hz: [f64; 2],
    /// Periods averaged per trial.
    pub periods_per_trial: usize,
    /// RMS error per trial.
    pub rms_percent: &'a [f64],
    /// Largest error per trial.
    pub max_percent: &'a [f64],
    /// The final trial's error above Q's cut-off.
    pub above_cutoff_percent: f64,
    /// Harmonics learned per trial.
    pub harmonics_learned: &'a [usize],
    /// Whether the trial stepped back to the best table.
    pub stepped_back: &'a [bool],
    /// The last table played again without learning: RMS error per trial.
    pub repeat_percent: &'a [f64],
}

impl Curve {
    /// This curve as `learn.json` writes it.
    pub fn report(&self) -> CurveJson<'_> {
        CurveJson {
            mode: self.mode.name(),
            signal: self.shape.name(),
            freq_hz: self.freq_hz,
            perturbation: self.perturbation.label(),
            q_cutoff_hz: self.cutoff_hz,
            periods_per_trial: self.periods_per_trial,
            rms_percent: &self.rms_percent,
            max_percent: &self.max_percent,
            above_cutoff_percent: self.above_cutoff_percent,
            harmonics_learned: &self.harmonics_learned,
            stepped_back: &self.stepped_back,
            repeat_percent: &self.repeat_percent,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    /// A curve serialises with the keys `learn.json` has always had, NaN as `null`.
    #[test]
    fn a_curve_serialises_with_the_keys_of_learn_json() {
        let curve = Curve {
            mode: LearnMode::LearnedFeedback,
            shape: Shape::Triangle,
            freq_hz: 100.0,
            perturbation: Perturbation::Gain(0.6),
            rms_percent: vec![1.0, 0.1],
            max_percent: vec![2.0, f64::NAN],
            cutoff_hz: [900.0, 800.0],
            periods_per_trial: 10,
            above_cutoff_percent: 0.01,
            harmonics_learned: vec![3],
            stepped_back: vec![false],
            repeat_percent: vec![0.11, 0.09],
        };
        let json = crate::to_json(&curve.report()).unwrap();
        assert_eq!(
            crate::json_keys(&json),
            std::collections::BTreeSet::from([
                "mode",
                "signal",
                "freq_hz",
                "perturbation",
                "q_cutoff_hz",
                "periods_per_trial",
                "rms_percent",
                "max_percent",
                "above_cutoff_percent",
                "harmonics_learned",
                "stepped_back",
                "repeat_percent",
            ])
        );
        assert!((curve.repeat_spread() - 1.1).abs() < 1e-12);
        assert_eq!(json["mode"], "learned+feedback");
        assert_eq!(json["perturbation"], Perturbation::Gain(0.6).label());
        assert_eq!(json["max_percent"], serde_json::json!([2.0, null]));
        assert_eq!(json["q_cutoff_hz"], serde_json::json!([900.0, 800.0]));
    }

    #[derive(Parser)]
    struct Bench {
        #[command(flatten)]
        args: LearnBenchArgs,
    }

    #[derive(Parser)]
    struct Demo {
        #[command(flatten)]
        args: crate::demo::DemoArgs,
    }

    #[derive(Parser)]
    struct Reproduce {
        #[command(flatten)]
        args: crate::reproduce::ReproduceArgs,
    }

    /// Without `--format`, learn-bench writes the plots demo and reproduce write (SVG and PNG).
    #[test]
    fn the_plot_format_defaults_as_demo_and_reproduce() {
        let bench = Bench::try_parse_from(["learn-bench"]).unwrap().args.format;
        let demo = Demo::try_parse_from(["demo"]).unwrap().args.format;
        let reproduce = Reproduce::try_parse_from(["reproduce"])
            .unwrap()
            .args
            .format;
        assert_eq!(bench, demo);
        assert_eq!(bench, reproduce);
        assert_eq!(bench.extensions(), ["svg", "png"]);
    }
}
