//! Sampled simulation of a plant under signals and effects.
//!
//! The joint state [amplifier outputs | plant states | creep elements] is integrated with [`Dp45`] between
//! consecutive events: output sample instants k/f_s and the breakpoints (jumps, corners, reversals) of every
//! input signal. At a breakpoint where a held input jumps (and no amplifier smooths it), the plant moves its
//! hysteresis state along the jump ([`Plant::input_jump`]). Outputs are recorded at the sample instants
//! (after any jump at that instant), then delayed, made noisy and quantised as the effects ask.
//!
//! [`simulate`] reads as those steps: it checks the settings and the input span, sets up the run
//! (`Run::start`: the joint state at rest, the jump to u(0), the integrator or the exact hold
//! propagator), then per sample advances the state over the interval's breakpoints
//! (`Run::advance_to`, one segment at a time by `Run::advance_segment`, Dormand–Prince or exact, with
//! the jumps after each), records the sample (`Record::push_sample`) and at the end applies the
//! sensor effects.
//!
//! **Exact propagation over holds.** When every segment is a hold of a linear system, each segment is
//! propagated in closed form instead ([`crate::hold`]). That needs
//!
//! - every input piecewise constant ([`Signal::is_piecewise_constant`]: zero-order-hold data,
//!   staircases, steps, or any signal behind the `dac` effect), so that u̇ = 0 and the Bouc-Wen
//!   states are frozen between breakpoints (they move only at the jumps, by [`Plant::input_jump`]);
//! - no `amplifier` effect (its output v moves during a hold, v̇ = 2π·f_c·(u − v), so the plant's
//!   input is not held and h moves);
//! - a plant that gives its linear form over holds, [`Plant::held_input_linear`] (the XY stage and
//!   the NAC2024 actuator, its second mode included; not the asymmetric stage, whose input time
//!   shift reads the input before the hold).
//!
//! The joint state z = [plant states x | creep elements c] then obeys, over the hold [t₀, t₀ + Δ],
//! ż = A_z·z + g with g constant, where A_z has the plant's A, and the creep rows
//! ċ_ji = (w_i·(F_j·x + const) − c_ji)/τ_i (F the Jacobian of the free displacement, zero for both
//! plants: it depends on the held u and the frozen h only). Hence
//!
//! z(t₀ + Δ) = z(t₀) + Ψ(Δ)·ż(t₀),   Ψ(Δ) = ∫₀^Δ e^{A_z·s} ds,
//!
//! with ż(t₀) one evaluation of the right-hand side just after the jumps at t₀ and Ψ(Δ) computed once
//! per distinct Δ. For the XY stage per axis, x = [q, q̇, h] and
//! A = [[0, I, 0], [−M⁻¹K, −τd·M⁻¹K, 0], [0, 0, 0]]; the τd·f·η̇ impulse of a jump is carried by
//! [`Plant::input_jump`] moving h, and η = d·(1 + a·u)·(u − h) enters g. The other effects are
//! compatible: `drift`, `delay`, `noise`, `adc` act on the sampled outputs, `coupling` on the
//! outputs, `electrostriction` on the held drive, `dac` makes the input a hold. Anything else (a
//! smooth or piecewise-linear input, the amplifier, a plant without the linear form, or
//! [`SimSettings::exact_holds`] off) is integrated with [`Dp45`] as before; [`SimOutput`] counts
//! the exact segments and the Dormand–Prince steps. Against Dormand–Prince at rtol 1e-11 the exact
//! path agrees to ≈ 1e-16 m on XY-stage records of ≈ 60 µm (`tests/exact_holds.rs`), closer than
//! the default tolerances (rtol 1e-8: ≈ 1e-15 m).

use crate::csv::Table;
use crate::effects::{DacSignal, Effects};
use crate::hold::HoldPropagator;
use crate::ode::{Dp45, Dp45Settings, Dp45Stats, OdeError, OdeSystem};
use crate::plant::{InputAt, Plant, PlantError};
use crate::signal::{Signal, SignalError};
use rand_chacha::ChaCha8Rng;
use rand_core::{RngCore, SeedableRng};
use std::fmt;

/// Simulation errors.
#[derive(Debug, Clone, PartialEq)]
pub enum SimError {
    /// From the plant.
    Plant(PlantError),
    /// From the integrator.
    Ode(OdeError),
    /// From a signal.
    Signal(SignalError),
    /// Invalid settings.
    Settings(String),
}

impl fmt::Display for SimError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Plant(e) => e.fmt(f),
            Self::Ode(e) => e.fmt(f),
            Self::Signal(e) => e.fmt(f),
            Self::Settings(m) => write!(f, "{m}"),
        }
    }
}

impl std::error::Error for SimError {}

impl From<PlantError> for SimError {
    fn from(e: PlantError) -> Self {
        Self::Plant(e)
    }
}
impl From<OdeError> for SimError {
    fn from(e: OdeError) -> Self {
        Self::Ode(e)
    }
}
impl From<SignalError> for SimError {
    fn from(e: SignalError) -> Self {
        Self::Signal(e)
    }
}

/// Sampling and integrator settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SimSettings {
    /// Output sample rate, Hz.
    pub sample_rate_hz: f64,
    /// Duration, s; samples at k/f_s for k = 0 .. round(duration·f_s) − 1.
    pub duration_s: f64,
    /// Integrator tolerances (atol in state units; the default suits nm-scale displacements).
    pub ode: Dp45Settings,
    /// Propagate the holds of zero-order-hold inputs exactly when the plant and effects allow it (see
    /// the module doc); `false` integrates every segment with the Dormand–Prince pair (for checks).
    pub exact_holds: bool,
}

impl SimSettings {
    /// Default tolerances (rtol 1e-8, atol 1e-14).
    pub fn new(sample_rate_hz: f64, duration_s: f64) -> Self {
        Self {
            sample_rate_hz,
            duration_s,
            ode: Dp45Settings {
                rtol: 1e-8,
                atol: 1e-14,
                ..Default::default()
            },
            exact_holds: true,
        }
    }
}

/// Sampled result.
#[derive(Debug, Clone, PartialEq)]
pub struct SimOutput {
    /// Sample times, s.
    pub t_s: Vec<f64>,
    /// Input names (`u_V` or `ux_V`, `uy_V`).
    pub input_names: Vec<String>,
    /// Commanded inputs per channel, V (after the DAC if present).
    pub inputs_v: Vec<Vec<f64>>,
    /// Output names (`y_m` or `x_m`, `y_m`).
    pub output_names: Vec<String>,
    /// Measured outputs per channel, m.
    pub outputs_m: Vec<Vec<f64>>,
    /// Integrator counters (of the segments integrated with the Dormand–Prince pair).
    pub stats: Dp45Stats,
    /// Segments propagated exactly over a hold (0 when the run is not eligible).
    pub exact_segments: u64,
}

impl SimOutput {
    /// As a CSV table: `t_s`, inputs, outputs.
    pub fn to_table(&self) -> Table {
        let mut names = vec!["t_s".to_string()];
        names.extend(self.input_names.iter().cloned());
        names.extend(self.output_names.iter().cloned());
        let mut columns = vec![self.t_s.clone()];
        columns.extend(self.inputs_v.iter().cloned());
        columns.extend(self.outputs_m.iter().cloned());
        Table {
            path: Default::default(),
            names,
            columns,
        }
    }
}

struct Ctx<'a> {
    plant: &'a dyn Plant,
    signals: &'a [Box<dyn Signal>],
    effects: &'a Effects,
    n_in: usize,
    n_amp: usize,
    n_plant: usize,
    n_out: usize,
}

struct Segment<'a> {
    ctx: &'a Ctx<'a>,
    t_start: f64,
}

struct Inputs<'a> {
    ctx: &'a Ctx<'a>,
    t_now: f64,
    t_start: f64,
    amp_state: &'a [f64],
}

impl InputAt for Inputs<'_> {
    fn input(&self, channel: usize, t: f64) -> (f64, f64) {
        let sig = &self.ctx.signals[channel.min(self.ctx.n_in - 1)];
        match self.ctx.effects.amplifier {
            Some(amp) => {
                let v = self.amp_state[channel];
                let (u, _) = sig.eval(self.t_now, self.t_now > self.t_start);
                let dv = amp.rate(u, v);
                // A time-shifted query (stage's φ) uses the first-order Taylor expansion of v.
                (v + (t - self.t_now) * dv, dv)
            }
            None => sig.eval(t, t > self.t_start),
        }
    }
}

impl OdeSystem for Segment<'_> {
    fn dim(&self) -> usize {
        self.ctx.n_amp
            + self.ctx.n_plant
            + self.ctx.n_out
                * self
                    .ctx
                    .effects
                    .creep
                    .as_ref()
                    .map_or(0, |c| c.elements.len())
    }
    fn rhs(&self, t: f64, x: &[f64], dx: &mut [f64]) {
        let c = self.ctx;
        let (amp_x, rest) = x.split_at(c.n_amp);
        let (plant_x, creep_x) = rest.split_at(c.n_plant);
        let (amp_dx, rest_dx) = dx.split_at_mut(c.n_amp);
        let (plant_dx, creep_dx) = rest_dx.split_at_mut(c.n_plant);
        let inputs = Inputs {
            ctx: c,
            t_now: t,
            t_start: self.t_start,
            amp_state: amp_x,
        };
        if let Some(amp) = c.effects.amplifier {
            for ch in 0..c.n_amp {
                let (u, _) = c.signals[ch].eval(t, t > self.t_start);
                amp_dx[ch] = amp.rate(u, amp_x[ch]);
            }
        }
        c.plant.rhs(t, plant_x, &inputs, plant_dx);
        if let Some(creep) = &c.effects.creep {
            let mut u = [0.0; 2];
            for (ch, uu) in u.iter_mut().enumerate().take(c.n_in) {
                *uu = inputs.input(ch, t).0;
            }
            let mut free = [0.0; 2];
            c.plant
                .free_displacement(plant_x, &u[..c.n_in], &mut free[..c.n_out]);
            let n = creep.elements.len();
            for j in 0..c.n_out {
                for (i, &(tau, w)) in creep.elements.iter().enumerate() {
                    creep_dx[j * n + i] = (w * free[j] - creep_x[j * n + i]) / tau;
                }
            }
        }
    }
}

/// Standard normal deviate by Box–Muller from a ChaCha8 stream.
fn gaussian(rng: &mut ChaCha8Rng) -> f64 {
    let u1 = ((rng.next_u64() >> 11) as f64 + 0.5) / (1u64 << 53) as f64;
    let u2 = ((rng.next_u64() >> 11) as f64) / (1u64 << 53) as f64;
    (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
}

/// The state matrix of the joint state [plant states | creep elements] over a hold, when every
/// segment of the run is a hold of a linear system: every input piecewise constant (zero-order
/// hold, a DAC), no amplifier (its output moves during a hold, so the plant's input is not held) and
/// a plant with a [`HeldLinear`](crate::plant::HeldLinear) form. Otherwise `None` (Dormand–Prince).
fn held_state_matrix(
    plant: &dyn Plant,
    signals: &[Box<dyn Signal>],
    effects: &Effects,
    n_out: usize,
) -> Option<(Vec<f64>, usize)> {
    if effects.amplifier.is_some() || !signals.iter().all(|s| s.is_piecewise_constant()) {
        return None;
    }
    let lin = plant.held_input_linear()?;
    let np = plant.state_dim();
    if lin.a.len() != np * np || lin.free_displacement.len() != n_out * np {
        return None;
    }
    let elements: &[(f64, f64)] = effects.creep.as_ref().map_or(&[], |c| &c.elements);
    let n = np + n_out * elements.len();
    let mut a = vec![0.0; n * n];
    for i in 0..np {
        a[i * n..i * n + np].copy_from_slice(&lin.a[i * np..(i + 1) * np]);
    }
    // ċ_ji = (w_i·(F_j·x + const) − c_ji)/τ_i.
    for j in 0..n_out {
        for (i, &(tau, w)) in elements.iter().enumerate() {
            let row = np + j * elements.len() + i;
            for p in 0..np {
                a[row * n + p] = w * lin.free_displacement[j * np + p] / tau;
            }
            a[row * n + row] = -1.0 / tau;
        }
    }
    Some((a, n))
}

/// Runs `plant` under `signals` (one per plant input) with `effects`; the plant must already carry its
/// plant-internal effects (see [`Effects::apply_to_plant`]).
pub fn simulate(
    plant: &dyn Plant,
    signals: Vec<Box<dyn Signal>>,
    effects: &Effects,
    settings: &SimSettings,
) -> Result<SimOutput, SimError> {
    let n_samples = sample_count(plant, signals.len(), settings)?;
    let fs = settings.sample_rate_hz;
    let signals = behind_dac(signals, effects);
    let (lo, hi) = input_span(&signals, n_samples, fs);
    plant.check_input_span(lo, hi)?;
    let ctx = Ctx::new(plant, &signals, effects);
    let mut run = Run::start(&ctx, settings);
    let mut record = Record::with_capacity(&ctx, n_samples);
    for k in 0..n_samples {
        let tk = k as f64 / fs;
        if k > 0 {
            run.advance_to(tk)?;
        }
        record.push_sample(&ctx, &run.x, tk);
    }
    sensor_effects(&mut record.outputs_m, effects, fs);
    Ok(SimOutput {
        t_s: record.t_s,
        input_names: plant.input_names().iter().map(|s| s.to_string()).collect(),
        inputs_v: record.inputs_v,
        output_names: plant.output_names().iter().map(|s| s.to_string()).collect(),
        outputs_m: record.outputs_m,
        stats: run.ode.stats(),
        exact_segments: run.exact.map_or(0, |h| h.counts().0),
    })
}

/// The signals as the plant sees them: each behind the `dac` effect when there is one.
fn behind_dac(signals: Vec<Box<dyn Signal>>, effects: &Effects) -> Vec<Box<dyn Signal>> {
    match effects.dac {
        Some(dac) => signals
            .into_iter()
            .map(|inner| Box::new(DacSignal { inner, dac }) as Box<dyn Signal>)
            .collect(),
        None => signals,
    }
}

impl<'a> Ctx<'a> {
    fn new(plant: &'a dyn Plant, signals: &'a [Box<dyn Signal>], effects: &'a Effects) -> Self {
        let n_in = plant.input_names().len();
        Self {
            plant,
            signals,
            effects,
            n_in,
            n_amp: if effects.amplifier.is_some() { n_in } else { 0 },
            n_plant: plant.state_dim(),
            n_out: plant.output_names().len(),
        }
    }

    /// Where the plant states sit in the joint state.
    fn plant_states(&self) -> std::ops::Range<usize> {
        self.n_amp..self.n_amp + self.n_plant
    }

    /// Creep elements per output.
    fn n_creep(&self) -> usize {
        self.effects.creep.as_ref().map_or(0, |c| c.elements.len())
    }
}

/// The moving part of a run: the joint state at time `t` and what advances it (the Dormand–Prince
/// pair, or the exact hold propagator when the run is eligible).
struct Run<'a> {
    ctx: &'a Ctx<'a>,
    t: f64,
    x: Vec<f64>,
    ode: Dp45,
    exact: Option<HoldPropagator>,
    /// ẋ at the start of a hold (exact path).
    dx0: Vec<f64>,
    /// Breakpoints of the current sample interval, its end included.
    bps: Vec<f64>,
}

impl<'a> Run<'a> {
    /// The plant at rest at t = 0, then moved by the jump to u(0) if that is not 0.
    fn start(ctx: &'a Ctx<'a>, settings: &SimSettings) -> Self {
        let dim = Segment { ctx, t_start: 0.0 }.dim();
        let mut x = vec![0.0; dim];
        ctx.plant.initial_state(&mut x[ctx.plant_states()]);
        let ode = Dp45::new(dim, settings.ode);
        let exact = if settings.exact_holds {
            held_state_matrix(ctx.plant, ctx.signals, ctx.effects, ctx.n_out).map(|(a, n)| {
                debug_assert_eq!(n, dim);
                HoldPropagator::new(a, n)
            })
        } else {
            None
        };
        let mut run = Self {
            ctx,
            t: 0.0,
            x,
            ode,
            exact,
            dx0: vec![0.0; dim],
            bps: Vec::new(),
        };
        // The plant rests at u = 0; a non-zero u(0) is a jump at t = 0.
        run.apply_jumps(0.0, true);
        run
    }

    /// Advances from the previous sample instant to `tk` over the breakpoints in between, moving
    /// the hysteresis state along the input jumps at each, then checks the plant state.
    fn advance_to(&mut self, tk: f64) -> Result<(), SimError> {
        self.collect_breakpoints(tk);
        let bps = std::mem::take(&mut self.bps);
        for &tb in &bps {
            self.advance_segment(tb)?;
            self.t = tb;
            self.apply_jumps(tb, false);
        }
        self.bps = bps;
        let c = self.ctx;
        c.plant.check_state(&self.x[c.plant_states()])?;
        Ok(())
    }

    /// The signals' breakpoints strictly inside (t, tk), sorted and distinct, then tk.
    fn collect_breakpoints(&mut self, tk: f64) {
        let t = self.t;
        self.bps.clear();
        for s in self.ctx.signals {
            s.breakpoints(t, tk, &mut self.bps);
        }
        self.bps.retain(|&b| b > t && b < tk);
        self.bps.sort_by(f64::total_cmp);
        self.bps.dedup();
        self.bps.push(tk);
    }

    /// Moves the state from `t` to `tb`: exactly over the hold, or with the Dormand–Prince pair.
    fn advance_segment(&mut self, tb: f64) -> Result<(), SimError> {
        let seg = Segment {
            ctx: self.ctx,
            t_start: self.t,
        };
        match self.exact.as_mut() {
            Some(hold) if tb > self.t => {
                seg.rhs(self.t, &self.x, &mut self.dx0);
                hold.advance(&mut self.x, &self.dx0, tb - self.t);
                if !self.x.iter().all(|v| v.is_finite()) {
                    return Err(OdeError::NonFinite { t_s: tb }.into());
                }
            }
            Some(_) => {}
            None => self.ode.advance(&seg, &mut self.t, &mut self.x, tb)?,
        }
        Ok(())
    }

    /// Moves the hysteresis state along every input that jumps at `tb` (from 0 V when `first`);
    /// nothing behind an amplifier, whose output does not jump.
    fn apply_jumps(&mut self, tb: f64, first: bool) {
        let c = self.ctx;
        if c.n_amp > 0 {
            return;
        }
        for (ch, s) in c.signals.iter().enumerate() {
            let from = if first { 0.0 } else { s.eval(tb, true).0 };
            let to = s.eval(tb, false).0;
            if from != to {
                c.plant
                    .input_jump(&mut self.x[c.plant_states()], ch, from, to);
            }
        }
    }
}

/// The sampled record before the sensor effects.
struct Record {
    t_s: Vec<f64>,
    inputs_v: Vec<Vec<f64>>,
    outputs_m: Vec<Vec<f64>>,
}

impl Record {
    fn with_capacity(ctx: &Ctx<'_>, n_samples: usize) -> Self {
        Self {
            t_s: Vec::with_capacity(n_samples),
            inputs_v: vec![Vec::with_capacity(n_samples); ctx.n_in],
            outputs_m: vec![Vec::with_capacity(n_samples); ctx.n_out],
        }
    }

    /// The sample at `tk` from the joint state `x` (after any jump at `tk`): the commanded inputs,
    /// and per output the plant's output plus its creep elements plus the drift.
    fn push_sample(&mut self, c: &Ctx<'_>, x: &[f64], tk: f64) {
        self.t_s.push(tk);
        let mut u = [0.0; 2];
        for ch in 0..c.n_in {
            u[ch] = if c.n_amp > 0 {
                x[ch]
            } else {
                c.signals[ch].value(tk)
            };
            self.inputs_v[ch].push(c.signals[ch].value(tk));
        }
        let mut y = [0.0; 2];
        c.plant
            .output(&x[c.plant_states()], &u[..c.n_in], &mut y[..c.n_out]);
        let n_creep = c.n_creep();
        for j in 0..c.n_out {
            let creep: f64 = x[c.n_amp + c.n_plant + j * n_creep..][..n_creep]
                .iter()
                .sum();
            let drift = c.effects.drift.map_or(0.0, |d| d.at(tk));
            self.outputs_m[j].push(y[j] + creep + drift);
        }
    }
}

/// Samples of a run, after checking the signal count against the plant's inputs and the rate
/// and duration.
fn sample_count(
    plant: &dyn Plant,
    n_signals: usize,
    settings: &SimSettings,
) -> Result<usize, SimError> {
    let n_in = plant.input_names().len();
    if n_signals != n_in {
        return Err(SimError::Settings(format!(
            "plant {} needs {n_in} input signal(s), got {n_signals}",
            plant.name(),
        )));
    }
    let fs = settings.sample_rate_hz;
    if !(fs > 0.0 && fs.is_finite() && settings.duration_s > 0.0 && settings.duration_s.is_finite())
    {
        return Err(SimError::Settings(format!(
            "sample rate ({fs} Hz) and duration ({} s) must be positive and finite",
            settings.duration_s
        )));
    }
    let n_samples = (settings.duration_s * fs).round() as usize;
    if n_samples == 0 || n_samples > 200_000_000 {
        return Err(SimError::Settings(format!(
            "{n_samples} samples: need 1 .. 2e8"
        )));
    }
    Ok(n_samples)
}

/// The range the inputs span (0 included: the plant starts at rest at 0 V), sampled at the
/// output instants and at the signals' breakpoints.
fn input_span(signals: &[Box<dyn Signal>], n_samples: usize, fs: f64) -> (f64, f64) {
    let t_of = |k: usize| k as f64 / fs;
    let (mut lo, mut hi) = (0.0f64, 0.0f64);
    let mut bps = Vec::new();
    for s in signals {
        s.breakpoints(0.0, t_of(n_samples), &mut bps);
        for v in (0..n_samples)
            .map(|k| s.value(t_of(k)))
            .chain(bps.iter().map(|&t| s.value(t)))
        {
            lo = lo.min(v);
            hi = hi.max(v);
        }
        bps.clear();
    }
    (lo, hi)
}

/// The sensor side of the effects, in this order: delay (linear interpolation), noise
/// (Gaussian, seeded), ADC quantisation.
fn sensor_effects(outputs_m: &mut [Vec<f64>], effects: &Effects, fs: f64) {
    if let Some(d) = effects.sensor_delay_s {
        for ch in outputs_m.iter_mut() {
            let orig = ch.clone();
            for (k, v) in ch.iter_mut().enumerate() {
                let pos = (k as f64 / fs - d) * fs;
                *v = if pos <= 0.0 {
                    orig[0]
                } else {
                    let i = pos.floor() as usize;
                    let f = pos - i as f64;
                    if i + 1 < orig.len() {
                        orig[i] * (1.0 - f) + orig[i + 1] * f
                    } else {
                        orig[orig.len() - 1]
                    }
                };
            }
        }
    }
    if let Some(noise) = effects.noise {
        let mut rng = ChaCha8Rng::seed_from_u64(noise.seed);
        let n_samples = outputs_m.first().map_or(0, Vec::len);
        for k in 0..n_samples {
            for ch in outputs_m.iter_mut() {
                ch[k] += noise.rms_m * gaussian(&mut rng);
            }
        }
    }
    if let Some(lsb) = effects.adc_lsb_m {
        for v in outputs_m.iter_mut().flatten() {
            *v = (*v / lsb).round() * lsb;
        }
    }
}
