//! `host-sim servo-bench`: feedforward, feedback and both on the XY flexure stage of seed 002,
//! with what no model captures in the plant — creep, thermal drift, sensor noise, DAC and ADC
//! quantisation — and the stage's own resonances (first modes ≈ 3.2 kHz in x, 2.2 kHz in y).
//!
//! **Controller** (per axis, piezo-core, the code the firmware runs): the inverse feedforward is
//! `firmware/params/xy-stage.toml` (the stacks' Bouc-Wen sets) with its output scaled to the
//! platform by the static gain identified on the plant (least squares over a 1 Hz, 0–120 V
//! raised cosine); the servo ([`piezo_core::servo`]) is tuned by [`piezo_core::servo::tune`]
//! from that model's largest dy/du and the first mode identified from a 10 V step response
//! (an AR(2) fit of the samples after the step), with a latency of 1.5 loop periods. Both go
//! through the stage file (`[x.servo]`) and its validation. The identified mode (f_n, ζ, a
//! force-driven mode) also goes into the axis's effects, so that the feedforward inverts it
//! (`s* = z* + (2ζ/ω)·ż* + z̈*/ω²`, [`piezo_core::inverse_chain::InverseChain`], as the
//! firmware's loop runs a stage file with effects): the drive is pre-shaped and a triangle's
//! corners do not ring the stage; off with `BenchSettings::mode_feedforward` = false
//! (`--no-mode-feedforward`). A triangle's corner asks for an impulse Δṙ/ω²; above 22 kHz the
//! inverse spreads it over the 2h + 1 ticks nearest 90 µs
//! ([`piezo_core::effects::MODE_CURVATURE_SPAN_S`]), so its height stays that of a 10 kHz tick
//! (≈ 0.7 V on y) instead of Δṙ/(T·ω²) in one tick (≈ 3.6 V at 50 kHz, which the slew limit,
//! 2 V per tick there, would cut short).
//!
//! **Loop** at the bench's rate (10 kHz unless `--rates` says otherwise: the stack file is run at
//! that rate, the DAC updates at it and the servo is tuned for it), per tick k: the sensor is sampled at t_k; the compensator is given the
//! reference one tick ahead, r\[k+1\] (the voltage is held over \[t_k, t_{k+1}) and shows at
//! t_{k+1}); the servo compares r\[k\] with the measurement; the voltage goes to the plant
//! through the DAC (zero-order hold, quantised). The plant is host-sim's f64 XY stage, integrated
//! by Dormand–Prince between ticks, with the creep bank as extra states.
//!
//! **Modes** ([`ServoMode`]): open loop = the linear map `u_min + (r − y_rest)/g` with the
//! model's first-loading gain; feedforward = the compensator; feedback = the servo alone;
//! feedforward + feedback = both.
//!
//! **Figures**: RMS and largest |true position − reference| after `settle_s` (0.1 s), in % of the
//! axis's stroke, the worse of the two axes; references between 20 % and 90 % of the stroke
//! (below 20 % the descending branch, lifted by creep and drift, needs less than 0 V), triangles
//! and sines starting at the low end, faded in from the rest position over `fade_in_s` (50 ms).
//! Closed-loop bandwidth: the −3 dB frequency (relative to the response between 10 and 50 Hz,
//! both signals detrended) of position/reference measured with a logarithmic chirp
//! (5 % of stroke around mid-stroke, 5 Hz → 4.5 kHz) in each mode, the lower of the two axes.

#![allow(clippy::needless_range_loop)] // axis indices run over parallel per-axis arrays

use crate::effects::Effects;
use crate::ode::{Dp45, Dp45Settings, OdeSystem};
use crate::plant::{InputAt, Plant, XyStage};
use crate::plot::{plot_grid, Chart, Legend, Panel, Role, Series};
use piezo_core::inverse_chain::InverseChain;
use piezo_core::servo::{tune, StageDynamics, Tuning, TuningGoal};
use piezo_core::{Compensator, CompensatorState, Servo, ServoMode, ServoState};
use piezo_stage::{StageFile, ValidStage};
use rand_chacha::ChaCha8Rng;
use rand_core::{RngCore, SeedableRng};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The stack model the feedforward starts from.
pub(crate) const STACK_FILE: &str = include_str!("../../firmware/params/xy-stage.toml");

/// The effects the bench's plant carries at the loop rate `loop_rate_hz` (host-sim effect
/// specs): creep, drift, 2 nm sensor noise, a 3.125 nm ADC and a 16-bit 0–120 V DAC updated at
/// the loop rate.
pub fn default_plant_effects(loop_rate_hz: f64) -> Vec<String> {
    vec![
        "creep:tau=0.1/1,weight=0.02/0.02".into(),
        "drift:rate=1e-7,amplitude=3e-7,tau=0.5".into(),
        "noise:rms_m=2e-9,seed=11".into(),
        "adc:lsb_m=3.125e-9".into(),
        format!("dac:bits=16,min=0,max=120,rate_hz={loop_rate_hz}"),
    ]
}

/// The loop rate of the bench when none is given \[Hz\].
pub const DEFAULT_LOOP_RATE_HZ: f64 = 10_000.0;

/// Lower end of the tracking references \[fraction of the stroke\]: above what the descending
/// branch reaches at 0 V once creep and drift have added to it.
pub const LOW: f64 = 0.2;
/// Upper end of the tracking references \[fraction of the stroke\].
pub const HIGH: f64 = 0.9;

/// Reference shapes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Shape {
    /// Triangle, rising first from the low end.
    Triangle,
    /// Sine, −cos from the low end.
    Sine,
}

impl Shape {
    /// `triangle` or `sine`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Triangle => "triangle",
            Self::Sine => "sine",
        }
    }

    /// The shape's value in [0, 1] at `t_s` for frequency `hz`.
    pub(crate) fn unit(self, hz: f64, t_s: f64) -> f64 {
        match self {
            Self::Triangle => crate::demo::triangle(0.0, 1.0, hz, t_s),
            Self::Sine => 0.5 - 0.5 * (2.0 * std::f64::consts::PI * hz * t_s).cos(),
        }
    }
}

/// What the bench runs.
#[derive(Debug, Clone, PartialEq)]
pub struct BenchSettings {
    /// Loop rate \[Hz\].
    pub loop_rate_hz: f64,
    /// Reference frequencies \[Hz\].
    pub frequencies_hz: Vec<f64>,
    /// Reference shapes.
    pub shapes: Vec<Shape>,
    /// Modes.
    pub modes: Vec<ServoMode>,
    /// Reference periods scored per run (at least `min_scored_s`).
    pub periods: f64,
    /// Shortest scored time per run \[s\].
    pub min_scored_s: f64,
    /// The reference fades in from the rest position over this time (raised cosine) \[s\].
    pub fade_in_s: f64,
    /// Time after the start that is not scored (≥ the fade-in) \[s\].
    pub settle_s: f64,
    /// Length of the bandwidth chirp \[s\]; 0: no bandwidth measurement.
    pub chirp_s: f64,
    /// Effect specs the plant carries.
    pub plant_effects: Vec<String>,
    /// Steps whose settling is measured, as fractions of the stroke (from the low end of the
    /// tracking range, both axes at once); empty: none.
    pub step_fractions: Vec<f64>,
    /// The reference holds its start this long after the fade-in before it steps \[s\].
    pub step_hold_s: f64,
    /// How long after the step the settling is watched \[s\].
    pub step_watch_s: f64,
    /// Whether the feedforward inverts the identified first mode as well (the effects chain's
    /// mode, [`piezo_core::inverse_chain::InverseChain`]), so that the drive is pre-shaped and a
    /// reference's corners do not ring the stage.
    pub mode_feedforward: bool,
    /// Whether the tuning may hold the mode by phase, with a notch with lead
    /// ([`piezo_core::servo::TuningGoal::mode_by_phase`]; `--mode-by-phase`): on a fast loop a
    /// higher crossover, with a loop that needs the mode where it was identified.
    pub mode_by_phase: bool,
}

impl BenchSettings {
    /// The reference's share at `t_s` of the fade-in from rest: a raised cosine over
    /// `fade_in_s`, then 1.
    fn fade(&self, t_s: f64) -> f64 {
        if t_s < self.fade_in_s {
            0.5 - 0.5 * (std::f64::consts::PI * t_s / self.fade_in_s).cos()
        } else {
            1.0
        }
    }
}

/// The settling band of a step: |true position − reference| within this share of the step.
pub const SETTLING_BAND: f64 = 0.02;

impl Default for BenchSettings {
    fn default() -> Self {
        Self {
            loop_rate_hz: DEFAULT_LOOP_RATE_HZ,
            frequencies_hz: vec![1.0, 10.0, 100.0],
            shapes: vec![Shape::Triangle, Shape::Sine],
            modes: ServoMode::ALL.to_vec(),
            periods: 2.0,
            min_scored_s: 0.2,
            fade_in_s: 0.05,
            settle_s: 0.1,
            chirp_s: 1.0,
            plant_effects: default_plant_effects(DEFAULT_LOOP_RATE_HZ),
            step_fractions: vec![0.01, 0.1, 0.5],
            step_hold_s: 0.1,
            step_watch_s: 0.1,
            mode_feedforward: true,
            mode_by_phase: false,
        }
    }
}

/// The settling of one step in one mode.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Settling {
    /// Mode.
    pub mode: ServoMode,
    /// The step, a fraction of the stroke.
    pub fraction: f64,
    /// Per axis: the time from the step until |true position − reference| stays within
    /// [`SETTLING_BAND`] of the step \[s\]; `None` when it is still outside at the end of the watch.
    pub settle_s: [Option<f64>; 2],
}

/// The settling time of `error` (from the step on, one sample per tick of `fs`): the time after
/// which |error| stays within `band`; `None` if the last sample is outside.
pub fn settling_time(error: &[f64], band: f64, fs: f64) -> Option<f64> {
    match error.iter().rposition(|e| !(e.abs() <= band)) {
        None => Some(0.0),
        Some(k) if k + 1 == error.len() => None,
        Some(k) => Some((k + 1) as f64 / fs),
    }
}

/// One row of the table.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Row {
    /// Mode.
    pub mode: ServoMode,
    /// Reference shape.
    pub shape: Shape,
    /// Reference frequency \[Hz\].
    pub freq_hz: f64,
    /// RMS tracking error, % of stroke (worse axis).
    pub rms_percent: f64,
    /// Largest |tracking error|, % of stroke (worse axis).
    pub max_percent: f64,
    /// Closed-loop −3 dB bandwidth of the mode \[Hz\] (lower axis; NaN when not measured).
    pub bandwidth_hz: f64,
}

/// Position/reference of one mode over frequency.
#[derive(Debug, Clone, PartialEq)]
pub struct Response {
    /// Mode.
    pub mode: ServoMode,
    /// Band centres \[Hz\].
    pub freq_hz: Vec<f64>,
    /// |y/r| per axis.
    pub magnitude: [Vec<f64>; 2],
    /// Phase of y/r per axis \[°\].
    pub phase_deg: [Vec<f64>; 2],
    /// −3 dB bandwidth per axis \[Hz\].
    pub bandwidth_hz: [f64; 2],
}

/// Error against time of one run (for the plots).
#[derive(Debug, Clone, PartialEq)]
pub struct Trace {
    /// Mode.
    pub mode: ServoMode,
    /// Shape.
    pub shape: Shape,
    /// Frequency \[Hz\].
    pub freq_hz: f64,
    /// Sample times \[s\].
    pub t_s: Vec<f64>,
    /// Position − reference per axis \[m\].
    pub error_m: [Vec<f64>; 2],
}

/// Everything the bench measured.
#[derive(Debug, Clone)]
pub struct BenchReport {
    /// The table.
    pub rows: Vec<Row>,
    /// Closed-loop responses per mode.
    pub responses: Vec<Response>,
    /// Error traces.
    pub traces: Vec<Trace>,
    /// Identified per axis: (platform/stack gain, first mode \[Hz\], its damping).
    pub identified: [(f64, f64, f64); 2],
    /// The servo tuning per axis.
    pub tunings: [Tuning; 2],
    /// Stroke per axis \[m\].
    pub stroke_m: [f64; 2],
    /// Step settling per mode and step size.
    pub settling: Vec<Settling>,
    /// How long after each step the settling was watched \[s\].
    pub step_watch_s: f64,
    /// Wall-clock seconds.
    pub seconds: f64,
}

/// The plant between ticks: XY stage plus creep states, voltage held.
struct Segment<'a> {
    stage: &'a XyStage,
    creep: &'a [(f64, f64)],
    u_v: [f64; 2],
}

impl InputAt for Segment<'_> {
    fn input(&self, channel: usize, _t_s: f64) -> (f64, f64) {
        (self.u_v[channel.min(1)], 0.0)
    }
}

impl OdeSystem for Segment<'_> {
    fn dim(&self) -> usize {
        self.stage.state_dim() + 2 * self.creep.len()
    }
    fn rhs(&self, t: f64, x: &[f64], dx: &mut [f64]) {
        let n = self.stage.state_dim();
        let (px, cx) = x.split_at(n);
        let (pdx, cdx) = dx.split_at_mut(n);
        self.stage.rhs(t, px, self, pdx);
        let mut free = [0.0; 2];
        self.stage.free_displacement(px, &self.u_v, &mut free);
        let m = self.creep.len();
        for j in 0..2 {
            for (i, &(tau, w)) in self.creep.iter().enumerate() {
                cdx[j * m + i] = (w * free[j] - cx[j * m + i]) / tau;
            }
        }
    }
}

/// The simulated rig, stepped one tick at a time: DAC → XY stage (+ creep, drift) → sensor
/// (noise, ADC).
pub struct Rig<'a> {
    stage: &'a XyStage,
    effects: &'a Effects,
    creep: Vec<(f64, f64)>,
    x: Vec<f64>,
    ode: Dp45,
    t_s: f64,
    period_s: f64,
    held_v: [f64; 2],
    rng: ChaCha8Rng,
}

impl<'a> Rig<'a> {
    /// At rest at 0 V, t = 0.
    pub fn new(stage: &'a XyStage, effects: &'a Effects, loop_rate_hz: f64) -> Self {
        let creep = effects
            .creep
            .as_ref()
            .map_or(Vec::new(), |c| c.elements.clone());
        let dim = stage.state_dim() + 2 * creep.len();
        let mut x = vec![0.0; dim];
        stage.initial_state(&mut x[..stage.state_dim()]);
        let seed = effects.noise.map_or(0, |n| n.seed);
        Self {
            stage,
            effects,
            creep,
            x,
            ode: Dp45::new(
                dim,
                Dp45Settings {
                    rtol: 1e-8,
                    atol: 1e-14,
                    ..Default::default()
                },
            ),
            t_s: 0.0,
            period_s: 1.0 / loop_rate_hz,
            held_v: [0.0; 2],
            rng: ChaCha8Rng::seed_from_u64(seed),
        }
    }

    /// (true platform positions, sensor readings) at the present tick \[m\].
    pub fn sense(&mut self) -> ([f64; 2], [f64; 2]) {
        let n = self.stage.state_dim();
        let mut y = [0.0; 2];
        self.stage.output(&self.x[..n], &self.held_v, &mut y);
        let m = self.creep.len();
        let drift = self.effects.drift.map_or(0.0, |d| d.at(self.t_s));
        for j in 0..2 {
            y[j] += self.x[n + j * m..n + (j + 1) * m].iter().sum::<f64>() + drift;
        }
        let mut read = y;
        for r in &mut read {
            if let Some(noise) = self.effects.noise {
                *r += noise.rms_m * gaussian(&mut self.rng);
            }
            if let Some(lsb) = self.effects.adc_lsb_m {
                *r = (*r / lsb).round() * lsb;
            }
        }
        (y, read)
    }

    /// Applies `u_v` (through the DAC) and advances to the next tick.
    pub fn apply(&mut self, u_v: [f64; 2]) -> crate::Result<()> {
        let n = self.stage.state_dim();
        for ch in 0..2 {
            let u = self.effects.dac.map_or(u_v[ch], |d| d.quantise(u_v[ch]));
            if u != self.held_v[ch] {
                self.stage
                    .input_jump(&mut self.x[..n], ch, self.held_v[ch], u);
                self.held_v[ch] = u;
            }
        }
        let seg = Segment {
            stage: self.stage,
            creep: &self.creep,
            u_v: self.held_v,
        };
        let end = self.t_s + self.period_s;
        self.ode
            .advance(&seg, &mut self.t_s, &mut self.x, end)
            .map_err(crate::Error::from)?;
        self.t_s = end;
        self.stage
            .check_state(&self.x[..n])
            .map_err(crate::Error::from)
    }
}

/// Standard normal deviate (Box–Muller).
fn gaussian(rng: &mut ChaCha8Rng) -> f64 {
    let u1 = ((rng.next_u64() >> 11) as f64 + 0.5) / (1u64 << 53) as f64;
    let u2 = ((rng.next_u64() >> 11) as f64) / (1u64 << 53) as f64;
    (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
}

/// Drives the rig open loop with `voltages`; returns the sensor readings per tick.
fn drive(
    stage: &XyStage,
    effects: &Effects,
    loop_rate_hz: f64,
    voltages: impl Iterator<Item = [f64; 2]>,
) -> crate::Result<Vec<[f64; 2]>> {
    let mut rig = Rig::new(stage, effects, loop_rate_hz);
    let mut out = Vec::new();
    for u in voltages {
        out.push(rig.sense().1);
        rig.apply(u)?;
    }
    Ok(out)
}

/// First mode (f_n \[Hz\], ζ) from a step response: y\[k\] = a1·y\[k−1\] + a2·y\[k−2\] + c by
/// least squares, poles of z² − a1·z − a2, s = ln z / T.
fn mode_from_step(y: &[f64], period_s: f64) -> Option<(f64, f64)> {
    // Normal equations of the 3-parameter fit.
    let mut ata = [[0.0; 3]; 3];
    let mut atb = [0.0; 3];
    for k in 2..y.len() {
        let row = [y[k - 1], y[k - 2], 1.0];
        for i in 0..3 {
            for j in 0..3 {
                ata[i][j] += row[i] * row[j];
            }
            atb[i] += row[i] * y[k];
        }
    }
    let mut augmented: [[f64; 4]; 3] = std::array::from_fn(|i| {
        let [a, b, c] = ata[i];
        [a, b, c, atb[i]]
    });
    let mut x = [0.0; 3];
    if !crate::optimise::linear::solve_augmented(&mut augmented, &mut x) {
        return None;
    }
    let [a1, a2, _] = x;
    let disc = a1 * a1 + 4.0 * a2;
    if disc >= 0.0 {
        return None;
    }
    let (re, im) = (a1 / 2.0, (-disc).sqrt() / 2.0);
    let (r, theta) = ((re * re + im * im).sqrt(), im.atan2(re));
    let (sr, si) = (r.ln() / period_s, theta / period_s);
    let wn = (sr * sr + si * si).sqrt();
    Some((wn / (2.0 * std::f64::consts::PI), -sr / wn))
}

/// The identification experiments: a 1 Hz raised cosine 0–120 V (1 s), then 0 V held for 0.2 s
/// and a 10 V step recorded for 20 ms. Returns per axis the platform/stack gain (least squares
/// of the readings on the stack model's output) and the first mode.
pub(crate) fn identify_rig(
    stage: &XyStage,
    effects: &Effects,
    stack: &ValidStage,
    fs: f64,
) -> crate::Result<[(f64, f64, f64); 2]> {
    let n_cos = fs as usize;
    let n_rest = (0.2 * fs) as usize;
    let n_step = (0.02 * fs) as usize;
    let u = |k: usize| {
        if k < n_cos {
            60.0 - 60.0 * (2.0 * std::f64::consts::PI * k as f64 / fs).cos()
        } else if k < n_cos + n_rest {
            0.0
        } else {
            10.0
        }
    };
    let y = drive(
        stage,
        effects,
        fs,
        (0..n_cos + n_rest + n_step).map(|k| [u(k), u(k)]),
    )?;
    let mut out = [(0.0, 0.0, 0.0); 2];
    for a in 0..2 {
        let Some(piezo_stage::AxisChain::Static { model, .. }) = stack.axes.get(a).map(|v| v.chain)
        else {
            return Err(crate::Error::Usage(
                "the stack file has no static model for both axes".into(),
            ));
        };
        let mut state = piezo_core::ModelState::at_rest(0.0);
        let (mut sym, mut smm) = (0.0, 0.0);
        for k in 0..n_cos {
            // The reading at k + 1 shows the voltage of tick k.
            let m = f64::from(model.step(&mut state, u(k) as f32));
            sym += y[k + 1][a] * m;
            smm += m * m;
        }
        let step: Vec<f64> = y[n_cos + n_rest + 1..].iter().map(|v| v[a]).collect();
        let (f, zeta) = mode_from_step(&step, 1.0 / fs).ok_or_else(|| {
            crate::Error::Usage("no oscillatory mode in the step response".into())
        })?;
        out[a] = (sym / smm, f, zeta);
    }
    Ok(out)
}

/// One axis's controller: the compensator (with the inverse of the identified mode when the
/// bench pre-shapes the drive), the linear baseline and the servo.
#[derive(Debug, Clone)]
pub(crate) struct AxisController {
    compensator: Compensator,
    compensator_state: CompensatorState,
    /// The inverse effects chain around the compensator (the mode), fed the reference of the
    /// next tick onwards; `None`: the compensator aims at the reference itself.
    chain: Option<InverseChain>,
    servo: Servo,
    servo_state: ServoState,
    rest_v: f32,
    rest_output_m: f32,
    linear_gain_m_per_v: f32,
}

impl AxisController {
    /// One tick: the servo's output for reference `r_now`, the compensator's (or the linear
    /// map's) voltage for `r_next`, the reading `measured_m`. With a chain, `ahead` yields the
    /// reference from `r_next` onwards, one sample per call (the chain's lead reads ahead), and
    /// the compensator aims at the chain's target w\*; the chain then commits the voltage
    /// applied, as the firmware's loop does.
    fn tick(
        &mut self,
        r_now: f32,
        r_next: f32,
        measured_m: f32,
        mut ahead: impl FnMut() -> f32,
    ) -> f32 {
        let target = match self.chain.as_mut() {
            Some(chain) => {
                chain
                    .next_targets(|| {
                        let r = ahead();
                        [r, r]
                    })
                    .1[0]
            }
            None => r_next,
        };
        let model = self
            .compensator
            .compensate(&mut self.compensator_state, target)
            .voltage_v;
        let ff = if self.servo_state.mode().model_feedforward() {
            model
        } else {
            self.rest_v + (r_next - self.rest_output_m) / self.linear_gain_m_per_v
        };
        let u = self
            .servo
            .step(&mut self.servo_state, r_now, measured_m, ff)
            .voltage_v;
        if let Some(chain) = self.chain.as_mut() {
            let w = self
                .compensator
                .model()
                .output(&self.compensator_state.model);
            chain.commit(0, u, w);
        }
        u
    }
}

/// The controllers of both axes: the stack file scaled to the platform, its servo tuned from
/// the identified mode, both validated through the stage file.
/// The stack file (`firmware/params/xy-stage.toml`) with its compensator and servo at the loop
/// rate `fs` \[Hz\], whatever rate the file itself runs at.
pub(crate) fn stack_file_at(fs: f64) -> crate::Result<StageFile> {
    let mut file = StageFile::parse("firmware/params/xy-stage.toml", STACK_FILE)
        .map_err(crate::Error::from)?;
    file.stage.loop_rate_hz = fs as f32;
    Ok(file)
}

pub(crate) fn controllers(
    stack_file: &StageFile,
    identified: &[(f64, f64, f64); 2],
) -> crate::Result<([AxisController; 2], [Tuning; 2], StageFile)> {
    controllers_with(stack_file, identified, false, false)
}

/// [`controllers`], with `mode_feedforward`: the identified first mode (f_n, ζ; a force-driven
/// mode, ρ = 0) in each axis's effects, so the feedforward inverts it as well
/// (`s* = z* + (2ζ/ω)·ż* + z̈*/ω²`, [`piezo_core::effects`]); with `mode_by_phase` the tuning
/// may hold the mode by phase ([`TuningGoal::mode_by_phase`]).
pub(crate) fn controllers_with(
    stack_file: &StageFile,
    identified: &[(f64, f64, f64); 2],
    mode_feedforward: bool,
    mode_by_phase: bool,
) -> crate::Result<([AxisController; 2], [Tuning; 2], StageFile)> {
    let goal = TuningGoal {
        mode_by_phase,
        ..TuningGoal::default()
    };
    let mut file = stack_file.clone();
    let axes = [Some(&mut file.x), file.y.as_mut()];
    for (axis, &(gain, f_n, zeta)) in axes.into_iter().zip(identified) {
        let axis = axis.ok_or_else(|| crate::Error::Usage("the stack file has one axis".into()))?;
        if mode_feedforward {
            axis.effects.mode_frequency_hz = f_n as f32;
            axis.effects.mode_damping = zeta as f32;
            axis.effects.mode_relative_damping = 0.0;
        }
        let map = axis
            .static_map
            .as_mut()
            .ok_or_else(|| crate::Error::Usage("no static map".into()))?;
        map.k1_m_per_v = (f64::from(map.k1_m_per_v) * gain) as f32;
        map.k2_m_per_h = (f64::from(map.k2_m_per_h) * gain) as f32;
    }
    let valid = file.validate().map_err(crate::Error::from)?;
    let mut tunings = Vec::new();
    for (a, v) in valid.axes.iter().enumerate() {
        let compensator = v
            .compensator
            .ok_or_else(|| crate::Error::Usage("no compensator".into()))?;
        let dynamics = StageDynamics::from_compensator(
            &compensator,
            identified[a].1 as f32,
            identified[a].2 as f32,
            1.5 * valid.sample_period_s,
        );
        let tuning = tune(&dynamics, &goal, compensator.settings())
            .map_err(|e| crate::Error::Usage(format!("servo tuning of axis {}: {e}", v.name)))?;
        tunings.push(tuning);
    }
    file.x.servo = Some(tunings[0].params);
    if let Some(y) = file.y.as_mut() {
        y.servo = Some(tunings[1].params);
    }
    let valid = file.validate().map_err(crate::Error::from)?;
    let build = |a: usize| -> crate::Result<AxisController> {
        let v = valid
            .axes
            .get(a)
            .ok_or_else(|| crate::Error::Usage("missing axis".into()))?;
        let compensator = v
            .compensator
            .ok_or_else(|| crate::Error::Usage("no compensator".into()))?;
        let rest_v = compensator.settings().limits.output_min_v;
        let chain = match v.chain {
            piezo_stage::AxisChain::Static { effects, .. } if mode_feedforward => {
                Some(InverseChain::single(effects, rest_v).ok_or_else(|| {
                    crate::Error::Usage("the mode's inverse chain could not be built".into())
                })?)
            }
            _ => None,
        };
        Ok(AxisController {
            compensator,
            compensator_state: CompensatorState::at_rest(rest_v),
            chain,
            servo: v
                .servo
                .ok_or_else(|| crate::Error::Usage("no servo".into()))?,
            servo_state: ServoState::at_rest(rest_v, ServoMode::Feedforward),
            rest_v,
            rest_output_m: v.rest_output_m,
            linear_gain_m_per_v: v.linear_gain_m_per_v,
        })
    };
    Ok(([build(0)?, build(1)?], [tunings[0], tunings[1]], file))
}

/// Runs the closed loop in `mode` over `n` ticks of `reference(k)` \[m per axis\]; returns the
/// true positions.
fn run_loop(
    stage: &XyStage,
    effects: &Effects,
    fs: f64,
    controllers: &[AxisController; 2],
    mode: ServoMode,
    n: usize,
    reference: &dyn Fn(usize) -> [f64; 2],
) -> crate::Result<[Vec<f64>; 2]> {
    let mut c = controllers.clone();
    for axis in &mut c {
        axis.servo_state = ServoState::at_rest(axis.rest_v, mode);
    }
    let mut rig = Rig::new(stage, effects, fs);
    let mut out = [Vec::with_capacity(n), Vec::with_capacity(n)];
    // The next reference sample each axis's chain reads: it starts at r[1], the target of the
    // first command.
    let mut fed = [1usize; 2];
    for k in 0..n {
        let (truth, read) = rig.sense();
        let (now, next) = (reference(k), reference(k + 1));
        let mut u = [0.0; 2];
        for a in 0..2 {
            out[a].push(truth[a]);
            let ahead = || {
                let r = reference(fed[a])[a] as f32;
                fed[a] += 1;
                r
            };
            u[a] = f64::from(c[a].tick(now[a] as f32, next[a] as f32, read[a] as f32, ahead));
        }
        rig.apply(u)?;
    }
    Ok(out)
}

/// |y/r| and phase per log band of a chirp run (FFT ratio, bands of 1/12 decade).
fn band_response(r: &[f64], y: &[f64], fs: f64) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    use rustfft::num_complex::Complex;
    let n = r.len();
    let fft = rustfft::FftPlanner::<f64>::new().plan_fft_forward(n);
    // Detrended: the least-squares line through the record removed (drift, creep).
    let spectrum = |v: &[f64]| {
        let nf = v.len() as f64;
        let tm = (nf - 1.0) / 2.0;
        let m = v.iter().sum::<f64>() / nf;
        let (mut stt, mut sty) = (0.0, 0.0);
        for (k, &x) in v.iter().enumerate() {
            stt += (k as f64 - tm) * (k as f64 - tm);
            sty += (k as f64 - tm) * (x - m);
        }
        let slope = sty / stt;
        let mut buf: Vec<Complex<f64>> = v
            .iter()
            .enumerate()
            .map(|(k, &x)| Complex::new(x - m - slope * (k as f64 - tm), 0.0))
            .collect();
        fft.process(&mut buf);
        buf
    };
    let (rs, ys) = (spectrum(r), spectrum(y));
    let (mut f_out, mut mag, mut phase) = (Vec::new(), Vec::new(), Vec::new());
    let mut lo = 5.0f64;
    while lo < 4000.0 {
        let hi = lo * 10f64.powf(1.0 / 12.0);
        let (k0, k1) = ((lo * n as f64 / fs) as usize, (hi * n as f64 / fs) as usize);
        let (mut cross, mut power) = (Complex::new(0.0, 0.0), 0.0);
        for k in k0.max(1)..k1.min(n / 2) {
            cross += ys[k] * rs[k].conj();
            power += rs[k].norm_sqr();
        }
        if power > 0.0 {
            let h = cross / power;
            f_out.push((lo * hi).sqrt());
            mag.push(h.norm());
            phase.push(h.arg().to_degrees());
        }
        lo = hi;
    }
    (f_out, mag, phase)
}

/// −3 dB frequency (searched above 10 Hz) relative to the mean response between 10 and 50 Hz.
fn bandwidth(freq: &[f64], mag: &[f64]) -> f64 {
    let low: Vec<f64> = freq
        .iter()
        .zip(mag)
        .filter(|(f, _)| (10.0..50.0).contains(*f))
        .map(|(_, m)| *m)
        .collect();
    let reference = low.iter().sum::<f64>() / low.len().max(1) as f64;
    freq.iter()
        .zip(mag)
        .find(|(f, m)| **f > 10.0 && **m < reference * std::f64::consts::FRAC_1_SQRT_2)
        .map_or(f64::NAN, |(f, _)| *f)
}

/// The chirp run of one mode: mid-stroke held for 0.1 s, then a log chirp 5 Hz → 4.5 kHz of
/// 5 % of stroke.
fn measure_response(
    stage: &XyStage,
    effects: &Effects,
    settings: &BenchSettings,
    controllers: &[AxisController; 2],
    stroke_m: [f64; 2],
    mode: ServoMode,
) -> crate::Result<Response> {
    let fs = settings.loop_rate_hz;
    let hold = (0.1 * fs) as usize;
    let n = (settings.chirp_s * fs) as usize;
    let (f0, f1, d) = (5.0f64, 4500.0f64, settings.chirp_s);
    let rate = (f1 / f0).ln() / d;
    let chirp = |k: usize| {
        if k < hold {
            return 0.0;
        }
        let t = (k - hold) as f64 / fs;
        (2.0 * std::f64::consts::PI * f0 * ((rate * t).exp() - 1.0) / rate).sin()
    };
    let reference = |k: usize| [0, 1].map(|a| stroke_m[a] * (0.5 + 0.05 * chirp(k)));
    let y = run_loop(stage, effects, fs, controllers, mode, hold + n, &reference)?;
    let r: [Vec<f64>; 2] = [0, 1].map(|a| (hold..hold + n).map(|k| reference(k)[a]).collect());
    let mut freq = Vec::new();
    let (mut magnitude, mut phase_deg) = ([Vec::new(), Vec::new()], [Vec::new(), Vec::new()]);
    let mut bw = [0.0; 2];
    for a in 0..2 {
        let (f, m, p) = band_response(&r[a], &y[a][hold..], fs);
        bw[a] = bandwidth(&f, &m);
        freq = f;
        magnitude[a] = m;
        phase_deg[a] = p;
    }
    Ok(Response {
        mode,
        freq_hz: freq,
        magnitude,
        phase_deg,
        bandwidth_hz: bw,
    })
}

/// Runs the bench; `progress` receives one line per phase.
pub fn run_bench(
    settings: &BenchSettings,
    progress: &mut (dyn FnMut(&str) + Send),
) -> crate::Result<BenchReport> {
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
    let (ctl, tunings, _) = controllers_with(
        &stack_file,
        &identified,
        settings.mode_feedforward,
        settings.mode_by_phase,
    )?;
    let (ax, ay) = stage.axes();
    let g = stage.static_gain();
    let stroke_m = [g[0] * ax.free_stroke_m, g[1] * ay.free_stroke_m];
    let responses: Vec<Response> = if settings.chirp_s > 0.0 {
        progress("measuring the closed-loop responses");
        settings
            .modes
            .par_iter()
            .map(|&m| measure_response(&stage, &effects, settings, &ctl, stroke_m, m))
            .collect::<Result<_, _>>()?
    } else {
        Vec::new()
    };
    let mut cases = Vec::new();
    for &shape in &settings.shapes {
        for &f in &settings.frequencies_hz {
            for &mode in &settings.modes {
                cases.push((shape, f, mode));
            }
        }
    }
    progress(&format!("tracking: {} runs", cases.len()));
    let skip = (settings.settle_s * fs).ceil() as usize;
    let runs: Vec<(Row, Trace)> = cases
        .par_iter()
        .map(|&(shape, f, mode)| {
            let scored = (settings.periods / f).max(settings.min_scored_s);
            let n = skip + (scored * fs).round() as usize;
            let reference = |k: usize| {
                let (t, fade) = (k as f64 / fs, settings.fade(k as f64 / fs));
                [0, 1].map(|a| stroke_m[a] * (LOW + (HIGH - LOW) * shape.unit(f, t)) * fade)
            };
            let y = run_loop(&stage, &effects, fs, &ctl, mode, n, &reference)?;
            let error_m: [Vec<f64>; 2] =
                [0, 1].map(|a| (0..n).map(|k| y[a][k] - reference(k)[a]).collect());
            let (mut rms, mut max) = (0.0f64, 0.0f64);
            for a in 0..2 {
                let e = &error_m[a][skip..];
                let r = (e.iter().map(|v| v * v).sum::<f64>() / e.len() as f64).sqrt();
                let m = e.iter().fold(0.0f64, |m, v| m.max(v.abs()));
                rms = rms.max(100.0 * r / stroke_m[a]);
                max = max.max(100.0 * m / stroke_m[a]);
            }
            let bandwidth_hz = responses
                .iter()
                .find(|r| r.mode == mode)
                .map_or(f64::NAN, |r| r.bandwidth_hz[0].min(r.bandwidth_hz[1]));
            let row = Row {
                mode,
                shape,
                freq_hz: f,
                rms_percent: rms,
                max_percent: max,
                bandwidth_hz,
            };
            let t_s = (0..n).map(|k| k as f64 / fs).collect();
            Ok((
                row,
                Trace {
                    mode,
                    shape,
                    freq_hz: f,
                    t_s,
                    error_m,
                },
            ))
        })
        .collect::<crate::Result<_>>()?;
    let (rows, traces) = runs.into_iter().unzip();
    let steps: Vec<(ServoMode, f64)> = settings
        .modes
        .iter()
        .flat_map(|&m| settings.step_fractions.iter().map(move |&f| (m, f)))
        .collect();
    if !steps.is_empty() {
        progress(&format!("steps: {} runs", steps.len()));
    }
    let step_k = ((settings.fade_in_s + settings.step_hold_s) * fs).round() as usize;
    let n_steps = step_k + (settings.step_watch_s * fs).round() as usize;
    let settling: Vec<Settling> = steps
        .par_iter()
        .map(|&(mode, fraction)| {
            let reference = |k: usize| {
                let fade = settings.fade(k as f64 / fs);
                let level = if k >= step_k { LOW + fraction } else { LOW };
                [0, 1].map(|a| stroke_m[a] * level * fade)
            };
            let y = run_loop(&stage, &effects, fs, &ctl, mode, n_steps, &reference)?;
            let settle_s = [0, 1].map(|a| {
                let error: Vec<f64> = (step_k..n_steps)
                    .map(|k| y[a][k] - reference(k)[a])
                    .collect();
                settling_time(&error, SETTLING_BAND * fraction * stroke_m[a], fs)
            });
            Ok(Settling {
                mode,
                fraction,
                settle_s,
            })
        })
        .collect::<crate::Result<_>>()?;
    Ok(BenchReport {
        settling,
        step_watch_s: settings.step_watch_s,
        rows,
        responses,
        traces,
        identified,
        tunings,
        stroke_m,
        seconds: start.elapsed().as_secs_f64(),
    })
}

impl BenchReport {
    /// The row of `mode`, `shape`, `freq_hz`.
    pub fn row(&self, mode: ServoMode, shape: Shape, freq_hz: f64) -> Option<&Row> {
        self.rows
            .iter()
            .find(|r| r.mode == mode && r.shape == shape && r.freq_hz == freq_hz)
    }

    /// The table as printed.
    pub fn table(&self) -> String {
        let mut s = String::new();
        for (a, name) in ["x", "y"].iter().enumerate() {
            let (gain, f, z) = self.identified[a];
            let t = &self.tunings[a];
            s += &format!(
                "{name}: identified platform gain {gain:.4}, mode {f:.0} Hz, zeta {z:.3}; servo ki {:.3e} V/(m s), \
                 notch {:.0} Hz, low-pass {:.0} Hz; crossover {:.0} Hz, phase margin {:.0} deg, Ms {:.2}\n",
                t.params.ki_v_per_m_s,
                t.params.notch_frequency_hz,
                t.params.lowpass_frequency_hz,
                t.crossover_hz,
                t.phase_margin_deg,
                t.sensitivity_peak
            );
        }
        s += "\n| mode | signal | freq [Hz] | RMS [% stroke] | max [% stroke] | bandwidth [Hz] |\n";
        s += "|---|---|---|---|---|---|\n";
        for r in &self.rows {
            s += &format!(
                "| {} | {} | {} | {:.4} | {:.4} | {:.0} |\n",
                r.mode.name(),
                r.shape.name(),
                r.freq_hz,
                r.rms_percent,
                r.max_percent,
                r.bandwidth_hz
            );
        }
        if !self.settling.is_empty() {
            s += &format!(
                "\nStep settling: the time until |true position - reference| stays within {:.0} % \
                 of the step (steps from {:.0} % of the stroke, both axes):\n\n",
                100.0 * SETTLING_BAND,
                100.0 * LOW
            );
            s += "| mode | step [% stroke] | settling x [ms] | settling y [ms] |\n|---|---|---|---|\n";
            let ms = |v: Option<f64>| {
                v.map_or(format!("> {:.0}", 1e3 * self.step_watch_s), |t| {
                    format!("{:.2}", 1e3 * t)
                })
            };
            for st in &self.settling {
                s += &format!(
                    "| {} | {} | {} | {} |\n",
                    st.mode.name(),
                    100.0 * st.fraction,
                    ms(st.settle_s[0]),
                    ms(st.settle_s[1])
                );
            }
        }
        s += &format!("({:.1} s)\n", self.seconds);
        s
    }

    /// `servo.json`: `{"rows": [...], "settling": [...]}` (a figure that is not a number is
    /// `null`).
    pub fn report(&self) -> BenchJson {
        BenchJson {
            rows: self.rows.iter().map(Row::report).collect(),
            settling: self
                .settling
                .iter()
                .map(|st| SettlingJson {
                    mode: st.mode.name(),
                    step_fraction: st.fraction,
                    band_fraction_of_step: SETTLING_BAND,
                    settle_s: st.settle_s,
                })
                .collect(),
        }
    }

    /// Writes `servo.json` and the plots (`servo-error.*`, `servo-bode.*`) into `dir`.
    pub fn write(&self, dir: &Path, extensions: &[&str]) -> crate::Result<Vec<String>> {
        std::fs::create_dir_all(dir).map_err(crate::Error::write("--out", dir))?;
        let mut files = Vec::new();
        let json = dir.join("servo.json");
        let text = serde_json::to_string_pretty(&self.report()).map_err(crate::Error::from)?;
        std::fs::write(&json, text).map_err(crate::Error::write("", &json))?;
        files.push(json.display().to_string());
        let figures: [(&str, Vec<Chart>, usize); 2] = [
            ("servo-error", self.error_panels(), 2),
            ("servo-bode", self.bode_panels(), 2),
        ];
        for (name, panels, columns) in figures {
            if panels.is_empty() {
                continue;
            }
            for ext in extensions {
                let path: PathBuf = dir.join(format!("{name}.{ext}"));
                plot_grid(&path, &panels, columns).map_err(crate::Error::from)?;
                files.push(path.display().to_string());
            }
        }
        Ok(files)
    }

    fn error_panels(&self) -> Vec<Chart> {
        let mut panels = Vec::new();
        let (lo, hi) = (
            self.rows
                .iter()
                .map(|r| r.freq_hz)
                .fold(f64::INFINITY, f64::min),
            self.rows.iter().map(|r| r.freq_hz).fold(0.0, f64::max),
        );
        for mode in ServoMode::ALL {
            for f in [lo, hi] {
                let Some(t) = self
                    .traces
                    .iter()
                    .find(|t| t.mode == mode && t.freq_hz == f && t.shape == Shape::Triangle)
                else {
                    continue;
                };
                let series = (0..2)
                    .map(|a| {
                        let pts = t
                            .t_s
                            .iter()
                            .zip(&t.error_m[a])
                            .map(|(&x, &e)| (x, 1e6 * e))
                            .collect();
                        let s = Series::line(["x", "y"][a], pts, 2000);
                        if a == 0 {
                            s.role(role(mode))
                        } else {
                            s
                        }
                    })
                    .collect();
                panels.push(
                    Panel::new(
                        format!("{}: {f} Hz triangle", mode.name()),
                        "t [s]",
                        "position - reference [um]",
                        series,
                    )
                    .legend(Legend::Below),
                );
            }
        }
        panels
    }

    fn bode_panels(&self) -> Vec<Chart> {
        let mut panels = Vec::new();
        for (a, axis) in ["x", "y"].iter().enumerate() {
            let series = |f: &dyn Fn(&Response) -> Vec<f64>| {
                self.responses
                    .iter()
                    .map(|r| {
                        let pts = r.freq_hz.iter().copied().zip(f(r)).collect();
                        Series::line(r.mode.name(), pts, 1000).role(role(r.mode))
                    })
                    .collect()
            };
            let db = |r: &Response| r.magnitude[a].iter().map(|m| 20.0 * m.log10()).collect();
            let ph = |r: &Response| r.phase_deg[a].clone();
            panels.push(
                Panel::new(
                    format!("closed loop {axis}/r: magnitude"),
                    "frequency [Hz]",
                    "|y/r| [dB]",
                    series(&db),
                )
                .log_x()
                .legend(Legend::Below),
            );
            panels.push(
                Panel::new(
                    format!("closed loop {axis}/r: phase"),
                    "frequency [Hz]",
                    "phase [deg]",
                    series(&ph),
                )
                .log_x()
                .legend(Legend::Below),
            );
        }
        panels
    }
}

fn role(mode: ServoMode) -> Role {
    match mode {
        ServoMode::OpenLoop => Role::OpenLoop,
        ServoMode::Feedforward => Role::Feedforward,
        ServoMode::Feedback => Role::Feedback,
        ServoMode::FeedforwardFeedback => Role::FeedforwardFeedback,
    }
}

/// Arguments of `servo-bench`.
#[derive(Debug, clap::Args)]
pub struct ServoBenchArgs {
    /// Output directory (created if missing): servo.json and the plots.
    #[arg(long, default_value = "out/servo")]
    pub out: PathBuf,
    /// Plot format, as in `demo` and `reproduce`.
    #[arg(long, value_enum, default_value_t = crate::plot::PlotFormat::Both)]
    pub format: crate::plot::PlotFormat,
    /// Effect the plant carries (host-sim effect spec, repeatable; default: creep, drift, 2 nm
    /// noise, a 3.125 nm ADC and a 16-bit 0-120 V DAC at the loop rate; `none` for a clean plant).
    #[arg(long = "plant-effect")]
    pub plant_effects: Vec<String>,
    /// Loop rates (Hz), comma-separated: the whole bench (identification, tuning, runs) at each;
    /// with more than one, each rate's files go to `OUT/<rate>-hz/` and a table across the rates
    /// follows (`rates.json`).
    #[arg(long, value_delimiter = ',', default_value = "10000")]
    pub rates: Vec<f64>,
    /// The feedforward without the identified mode's inverse (the compensator aims at the
    /// reference itself), to measure what pre-shaping the drive gains.
    #[arg(long)]
    pub no_mode_feedforward: bool,
    /// Let the tuning hold the mode by phase as well (a notch with lead, chosen where it gives
    /// the higher crossover: on a fast loop), not only by gain (a plain notch).
    #[arg(long)]
    pub mode_by_phase: bool,
}

/// Help after the options.
pub const HELP: &str = "The plant is host-sim's f64 XY stage (seed 002, modes at 3.2 and 2.2 kHz) with creep, thermal drift, \
sensor noise, ADC and DAC quantisation, stepped tick by tick at the loop rate (--rates, default 10 kHz; several rates run the whole bench at each and \
add a table across them). The feedforward is piezo-core's compensator \
(firmware/params/xy-stage.toml scaled to the platform by the identified gain) behind the inverse of the identified first mode \
(the effects chain's mode; --no-mode-feedforward: the compensator alone), the servo piezo-core's, tuned by \
piezo_core::servo::tune from the identified first mode (--mode-by-phase: also notches with lead). Rows: 1, 10, 100 Hz triangles and sines between 20 % and 90 % \
of the stroke (faded in over 50 ms, scored after 0.1 s) in open-loop, feedforward, feedback and feedforward+feedback; errors in % of stroke (worse axis), \
closed-loop bandwidth from a chirp (lower axis).";

/// Runs `servo-bench`.
pub fn servo_bench_cmd(a: &ServoBenchArgs) -> crate::Result<String> {
    let extensions = a.format.extensions();
    if a.rates.is_empty() {
        return Err(crate::Error::Usage(
            "--rates: give at least one loop rate".into(),
        ));
    }
    for &rate in &a.rates {
        // The core's limit on the filters (0.45·f_s) and the firmware's loop rates.
        if !(rate.is_finite() && (1_000.0..=1e6).contains(&rate)) {
            return Err(crate::Error::Usage(format!(
                "--rates {rate}: a loop rate in [1000, 1e6] Hz"
            )));
        }
    }
    let mut reports = Vec::new();
    let mut out = String::new();
    for &rate in &a.rates {
        let mut settings = BenchSettings {
            loop_rate_hz: rate,
            plant_effects: default_plant_effects(rate),
            mode_feedforward: !a.no_mode_feedforward,
            mode_by_phase: a.mode_by_phase,
            ..BenchSettings::default()
        };
        if !a.plant_effects.is_empty() {
            settings.plant_effects = a
                .plant_effects
                .iter()
                .filter(|e| e.as_str() != "none")
                .cloned()
                .collect();
        }
        eprintln!("loop rate {rate} Hz");
        let report = run_bench(&settings, &mut |line: &str| eprintln!("{line}"))?;
        let dir = if a.rates.len() == 1 {
            a.out.clone()
        } else {
            a.out.join(format!("{rate}-hz"))
        };
        let files = report.write(&dir, extensions)?;
        if a.rates.len() > 1 {
            out += &format!("## loop rate {rate} Hz\n\n");
        }
        out += &format!("{}written: {}\n", report.table(), files.join(", "));
        reports.push((rate, report));
    }
    if reports.len() > 1 {
        let json = a.out.join("rates.json");
        let text =
            serde_json::to_string_pretty(&rates_json(&reports)).map_err(crate::Error::from)?;
        std::fs::write(&json, text).map_err(crate::Error::write("", &json))?;
        out += &format!("\n{}written: {}\n", rates_table(&reports), json.display());
    }
    Ok(out.trim_end().to_string())
}

/// The modes and signals of the table across rates: (mode, shape, frequency).
const RATE_COLUMNS: [(ServoMode, Shape, f64); 4] = [
    (ServoMode::Feedforward, Shape::Triangle, 100.0),
    (ServoMode::Feedback, Shape::Triangle, 100.0),
    (ServoMode::FeedforwardFeedback, Shape::Triangle, 100.0),
    (ServoMode::FeedforwardFeedback, Shape::Triangle, 1.0),
];

/// The table across loop rates: per rate the tuned crossover and phase margin of each axis and
/// the RMS error (% stroke, worse axis) of `RATE_COLUMNS`; the last column is the
/// feedforward + feedback RMS at a 100 Hz triangle relative to the first rate's.
pub fn rates_table(reports: &[(f64, BenchReport)]) -> String {
    let mut s = String::from(
        "| loop rate [Hz] | x crossover [Hz] / margin [deg] | y crossover [Hz] / margin [deg] |",
    );
    for (mode, shape, f) in RATE_COLUMNS {
        s += &format!(" {} {} {f} Hz RMS [%] |", mode.name(), shape.name());
    }
    s += " ff+fb 100 Hz vs first rate |\n|---|---|---|";
    s += &"---|".repeat(RATE_COLUMNS.len() + 1);
    s += "\n";
    let hybrid = |r: &BenchReport| {
        r.row(ServoMode::FeedforwardFeedback, Shape::Triangle, 100.0)
            .map_or(f64::NAN, |row| row.rms_percent)
    };
    let first = reports.first().map_or(f64::NAN, |(_, r)| hybrid(r));
    for (rate, r) in reports {
        let [x, y] = &r.tunings;
        s += &format!(
            "| {rate} | {:.0} / {:.1} | {:.0} / {:.1} |",
            x.crossover_hz, x.phase_margin_deg, y.crossover_hz, y.phase_margin_deg
        );
        for (mode, shape, f) in RATE_COLUMNS {
            let v = r
                .row(mode, shape, f)
                .map_or(f64::NAN, |row| row.rms_percent);
            s += &format!(" {v:.4} |");
        }
        s += &format!(" {:.2} |\n", hybrid(r) / first);
    }
    s
}

/// `{"rates": [{"loop_rate_hz", "tunings": [...], "rows": [...]}]}`.
pub fn rates_json(reports: &[(f64, BenchReport)]) -> RatesJson {
    RatesJson {
        rates: reports
            .iter()
            .map(|(rate, r)| RateJson {
                loop_rate_hz: *rate,
                tunings: ["x", "y"]
                    .iter()
                    .zip(&r.tunings)
                    .map(|(axis, t)| TuningJson {
                        axis,
                        crossover_hz: t.crossover_hz,
                        phase_margin_deg: t.phase_margin_deg,
                        sensitivity_peak: t.sensitivity_peak,
                        lowpass_frequency_hz: t.params.lowpass_frequency_hz,
                        notch_frequency_hz: t.params.notch_frequency_hz,
                        notch_q: t.params.notch_q,
                        notch_pole_frequency_hz: t.params.notch_pole_frequency_hz,
                        ki_v_per_m_s: t.params.ki_v_per_m_s,
                    })
                    .collect(),
                rows: r.rows.iter().map(Row::report).collect(),
            })
            .collect(),
    }
}

/// `servo.json` ([`BenchReport::report`]).
#[derive(Debug, Clone, serde::Serialize)]
pub struct BenchJson {
    /// One per mode, signal and frequency.
    pub rows: Vec<RowJson>,
    /// One per mode: the settling of the step.
    pub settling: Vec<SettlingJson>,
}

/// A [`Row`] as `servo.json` writes it.
#[derive(Debug, Clone, serde::Serialize)]
pub struct RowJson {
    /// The servo mode's name.
    pub mode: &'static str,
    /// The signal's name.
    pub signal: &'static str,
    /// Its frequency \[Hz\].
    pub freq_hz: f64,
    /// RMS error, % of stroke.
    pub rms_percent: f64,
    /// Largest error, % of stroke.
    pub max_percent: f64,
    /// The −3 dB bandwidth of the mode \[Hz\].
    pub bandwidth_hz: f64,
}

impl Row {
    /// This row as `servo.json` writes it.
    pub fn report(&self) -> RowJson {
        RowJson {
            mode: self.mode.name(),
            signal: self.shape.name(),
            freq_hz: self.freq_hz,
            rms_percent: self.rms_percent,
            max_percent: self.max_percent,
            bandwidth_hz: self.bandwidth_hz,
        }
    }
}

/// A [`Settling`] as `servo.json` writes it.
#[derive(Debug, Clone, serde::Serialize)]
pub struct SettlingJson {
    /// The servo mode's name.
    pub mode: &'static str,
    /// The step, as a share of the stroke.
    pub step_fraction: f64,
    /// The settling band, as a share of the step.
    pub band_fraction_of_step: f64,
    /// Time to settle per axis \[s\] (`null`: never within the watch).
    pub settle_s: [Option<f64>; 2],
}

/// `servo-rates.json` ([`rates_json`]).
#[derive(Debug, Clone, serde::Serialize)]
pub struct RatesJson {
    /// One per loop rate.
    pub rates: Vec<RateJson>,
}

/// One loop rate of [`RatesJson`].
#[derive(Debug, Clone, serde::Serialize)]
pub struct RateJson {
    /// The loop rate \[Hz\].
    pub loop_rate_hz: f64,
    /// The tuning per axis.
    pub tunings: Vec<TuningJson>,
    /// The rows at this rate.
    pub rows: Vec<RowJson>,
}

/// One axis's tuning in [`RateJson`].
#[derive(Debug, Clone, serde::Serialize)]
pub struct TuningJson {
    /// `x` or `y`.
    pub axis: &'static str,
    /// Crossover \[Hz\].
    pub crossover_hz: f32,
    /// Phase margin \[°\].
    pub phase_margin_deg: f32,
    /// Peak of |S|.
    pub sensitivity_peak: f32,
    /// The servo's low-pass \[Hz\].
    pub lowpass_frequency_hz: f32,
    /// The servo's notch \[Hz\].
    pub notch_frequency_hz: f32,
    /// The notch's Q.
    pub notch_q: f32,
    /// The notch's poles \[Hz\] (0: at its centre, a plain notch).
    pub notch_pole_frequency_hz: f32,
    /// The integral gain \[V/(m·s)\].
    pub ki_v_per_m_s: f32,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A row and a settling serialise with the keys `servo.json` has always had, a figure that
    /// is not a number as `null`.
    #[test]
    fn a_bench_report_serialises_with_the_keys_of_servo_json() {
        let row = Row {
            mode: ServoMode::Feedforward,
            shape: Shape::Sine,
            freq_hz: 10.0,
            rms_percent: 0.5,
            max_percent: 1.0,
            bandwidth_hz: f64::NAN,
        };
        let json = crate::to_json(&row.report()).unwrap();
        assert_eq!(
            crate::json_keys(&json),
            std::collections::BTreeSet::from([
                "mode",
                "signal",
                "freq_hz",
                "rms_percent",
                "max_percent",
                "bandwidth_hz",
            ])
        );
        assert_eq!(json["mode"], ServoMode::Feedforward.name());
        assert!(json["bandwidth_hz"].is_null());
        let settling = SettlingJson {
            mode: ServoMode::Feedforward.name(),
            step_fraction: 0.1,
            band_fraction_of_step: SETTLING_BAND,
            settle_s: [Some(1e-3), None],
        };
        let json = crate::to_json(&settling).unwrap();
        assert_eq!(json["settle_s"], serde_json::json!([1e-3, null]));
        assert_eq!(
            crate::json_keys(&json),
            std::collections::BTreeSet::from([
                "mode",
                "step_fraction",
                "band_fraction_of_step",
                "settle_s",
            ])
        );
    }

    #[test]
    fn settling_is_the_time_after_the_last_sample_outside_the_band() {
        let fs = 1000.0;
        assert_eq!(settling_time(&[0.5, 0.3, 0.01, 0.0], 0.1, fs), Some(0.002));
        assert_eq!(settling_time(&[0.05, 0.0], 0.1, fs), Some(0.0));
        // Outside at the end: not settled; a NaN counts as outside.
        assert_eq!(settling_time(&[0.0, 0.5], 0.1, fs), None);
        assert_eq!(settling_time(&[f64::NAN, 0.0], 0.1, fs), Some(0.001));
    }
}
