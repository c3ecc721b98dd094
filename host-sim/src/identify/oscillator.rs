//! Identification of the Bouc-Wen benchmark oscillator (core [`piezo_core::HystereticOscillator`]).
//!
//! The benchmark's data were generated at 15 kHz and decimated to 750 Hz; the input is a multisine
//! up to 150 Hz, which a straight line between 750 Hz samples follows badly. So the record's input is
//! first interpolated band-limited (trigonometric interpolation by FFT zero padding, exact for a
//! periodic multisine) by [`UPSAMPLING`], and the core oscillator runs at that rate with one RK4 sub-step
//! per upsampled sample; its output is read at the original samples. `predict` does the same.
//!
//! A record that is not one or more whole periods (a sine sweep) would be wrapped by that
//! interpolation: its last sample joined to its first, and the jump rung through the record as
//! Gibbs oscillations between the samples. Such a record, recognised by the energy its wrap puts
//! into the top tenth of the band (≥ 1e-15 of the total; whole periods of a band-limited input leave
//! only rounding there, ~1e-23), is interpolated as its even extension `u, reversed(u)` instead, which
//! is continuous at both joins.
//!
//! β, γ and δ enter only as the products β·γ and β·δ, so β is fixed at 1 and γ, δ carry the products.
//! θ = (log10 m, log10 c, log10 k, log10 α, β·γ, β·δ, ν), started at an equation-error estimate.
//! Differential evolution on the first 2048 samples (input upsampled by 4 only; a trial's simulation
//! stops once its running SSE passes its parent's; at most 200 generations, fewer once 10 in a row
//! each gain less than 1e-7 of the best SSE), skipped when the equation-error start already beats
//! its whole random initial population. Then Levenberg–Marquardt on the whole training record with
//! the Jacobian from the sensitivity equations (`sensitivities`; one pass instead of one simulation
//! per parameter), a parameter at a bound held there while its gradient points outwards: first on
//! the input upsampled by 4 (a fifth of the cost per iteration) to within 1e-6 of the SSE, then
//! polished at the full rate until a step gains less than 1e-9 or the linear model promises less.
//! Both optimisers are [`crate::optimise`]'s, with the settings above.
//! Never fit on test data: this sees only the record it is given.

// Index loops for the small dense algebra; `%` rather than `is_multiple_of` (rust-version 1.80).
#![allow(clippy::needless_range_loop, clippy::manual_is_multiple_of)]

use super::{
    fit_block, FitBlock, Identification, IdentifyError, IdentifySettings, IdentifySummary, Record,
};
use crate::identify::model::Identified;
use crate::optimise::{
    evolution, linear, Boundary, Evolution, LeastSquares, Marquardt, NormalEquations, Population,
    Stall,
};
use piezo_core::{HystereticOscillator, OscillatorParams, OscillatorState};
use rand_chacha::ChaCha8Rng;
use rand_core::SeedableRng;
use rayon::prelude::*;
use rustfft::num_complex::Complex;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

/// Input upsampling factor (750 Hz → 15 kHz, the benchmark's own integration rate).
pub const UPSAMPLING: u32 = 20;

/// Band-limited interpolation of a record: `factor` samples per input sample. Taken as periodic
/// when it is (module doc), else through its even extension.
pub fn upsample(u: &[f64], factor: usize) -> Vec<f64> {
    if is_whole_periods(u) {
        return upsample_periodic(u, factor);
    }
    let even: Vec<f64> = u.iter().chain(u.iter().rev()).copied().collect();
    let mut fine = upsample_periodic(&even, factor);
    fine.truncate(u.len() * factor);
    fine
}

/// Whether the periodic extension of `u` is band-limited: less than 1e-15 of its spectral energy in
/// the top tenth of the band.
fn is_whole_periods(u: &[f64]) -> bool {
    let n = u.len();
    let mut spec: Vec<Complex<f64>> = u.iter().map(|&v| Complex::new(v, 0.0)).collect();
    rustfft::FftPlanner::<f64>::new()
        .plan_fft_forward(n)
        .process(&mut spec);
    let half = n / 2 + 1;
    let energy = |k: &usize| spec[*k].norm_sqr();
    let total: f64 = (0..half).map(|k| energy(&k)).sum();
    let top: f64 = (half * 9 / 10..half).map(|k| energy(&k)).sum();
    !(top > 1e-15 * total)
}

/// Trigonometric interpolation of a record taken as periodic.
fn upsample_periodic(u: &[f64], factor: usize) -> Vec<f64> {
    let n = u.len();
    let m = n * factor;
    let mut planner = rustfft::FftPlanner::<f64>::new();
    let mut spec: Vec<Complex<f64>> = u.iter().map(|&v| Complex::new(v, 0.0)).collect();
    planner.plan_fft_forward(n).process(&mut spec);
    let mut wide = vec![Complex::new(0.0, 0.0); m];
    let half = n / 2;
    for k in 0..n {
        let v = spec[k];
        if n % 2 == 0 && k == half {
            // Split the Nyquist bin between +f and −f.
            wide[half] += v * 0.5;
            wide[m - half] += v * 0.5;
        } else if k < half || (n % 2 == 1 && k == half) {
            wide[k] = v;
        } else {
            wide[m - (n - k)] = v;
        }
    }
    planner.plan_fft_inverse(m).process(&mut wide);
    wide.iter().map(|c| c.re / n as f64).collect()
}

fn params_of(theta: &[f64]) -> OscillatorParams {
    OscillatorParams {
        mass_kg: 10f64.powf(theta[0]) as f32,
        damping_n_s_per_m: 10f64.powf(theta[1]) as f32,
        stiffness_n_per_m: 10f64.powf(theta[2]) as f32,
        alpha_n_per_m: 10f64.powf(theta[3]) as f32,
        beta_per_m: 1.0,
        gamma: theta[4] as f32,
        delta: theta[5] as f32,
        nu: theta[6] as f32,
    }
}

/// Simulates a set on an upsampled input; `visit(k, y)` at every original sample.
pub fn simulate(
    params: OscillatorParams,
    sample_period_s: f64,
    fine_input: &[f32],
    factor: usize,
    mut visit: impl FnMut(usize, f32),
) -> Result<(), piezo_core::ParamError> {
    simulate_while(params, sample_period_s, fine_input, factor, |k, y| {
        visit(k, y);
        true
    })
}

/// [`simulate`], stopping when `visit` returns false.
fn simulate_while(
    params: OscillatorParams,
    sample_period_s: f64,
    fine_input: &[f32],
    factor: usize,
    mut visit: impl FnMut(usize, f32) -> bool,
) -> Result<(), piezo_core::ParamError> {
    let model = HystereticOscillator::new(params, (sample_period_s / factor as f64) as f32, 1)?;
    let mut state = OscillatorState {
        input_n: f64::from(fine_input.first().copied().unwrap_or(0.0)),
        ..Default::default()
    };
    // Sample k sits at fine index k·factor; the first sample is the initial (rest) state.
    if !visit(0, 0.0) {
        return Ok(());
    }
    for (i, &v) in fine_input.iter().enumerate().skip(1) {
        let y = model.step(&mut state, v);
        if i % factor == 0 && !visit(i / factor, y) {
            break;
        }
    }
    Ok(())
}

/// Number of identified parameters θ.
const DIM: usize = 7;

/// The search box of θ (log10 m, log10 c, log10 k, log10 α, β·γ, β·δ, ν).
const BOUNDS: [(f64, f64); DIM] = [
    (-1.0, 1.5),
    (-0.5, 2.5),
    (3.0, 6.0),
    (3.0, 6.0),
    (0.0, 5000.0),
    (-5000.0, 5000.0),
    (1.0, 2.5),
];

/// The oscillator's right-hand side and its derivatives, in f64 from the f32 parameters.
struct Tangent {
    m: f64,
    c: f64,
    k: f64,
    c_m: f64,
    k_m: f64,
    inv_m: f64,
    alpha: f64,
    bg: f64,
    bd: f64,
    nu: f64,
}

/// State x = (y, ẏ, z) and its sensitivities s\[j\] = ∂x/∂θ_j (only the columns `LO..HI` used).
type Block = ([f64; 3], [[f64; 3]; DIM]);

impl Tangent {
    fn new(params: OscillatorParams) -> Self {
        let m = f64::from(params.mass_kg);
        let c = f64::from(params.damping_n_s_per_m);
        let k = f64::from(params.stiffness_n_per_m);
        Self {
            m,
            c,
            k,
            c_m: c / m,
            k_m: k / m,
            inv_m: 1.0 / m,
            alpha: f64::from(params.alpha_n_per_m),
            bg: f64::from(params.beta_per_m) * f64::from(params.gamma),
            bd: f64::from(params.beta_per_m) * f64::from(params.delta),
            nu: f64::from(params.nu),
        }
    }

    /// ẋ and Ṡ for the columns `LO..HI`, written into `out` (no copies of the whole block).
    #[inline(always)]
    fn rhs<const LO: usize, const HI: usize>(&self, x: &Block, u: f64, out: &mut Block) {
        let ln10 = std::f64::consts::LN_10;
        let (y, v, z) = (x.0[0], x.0[1], x.0[2]);
        let az = z.abs();
        let p = if self.nu == 1.0 {
            1.0
        } else {
            az.powf(self.nu - 1.0)
        };
        let (bg, bd) = (self.bg, self.bd);
        let acc = (u - self.c * v - self.k * y - z) / self.m;
        let hyst = bg * v.abs() * p * z + bd * v * p * az;
        out.0 = [v, acc, self.alpha * v - hyst];
        let dzdv = self.alpha - (bg * v.signum() * p * z + bd * p * az);
        let dzdz = -self.nu * p * (bg * v.abs() + bd * v * z.signum());
        // ∂ż/∂ν needs ln|z| only in the block that holds ν's column.
        let ln_az = if HI == DIM && az > 0.0 { az.ln() } else { 0.0 };
        for j in LO..HI {
            let forcing = match j {
                0 => [-ln10 * acc, 0.0],
                1 => [-ln10 * self.c * v * self.inv_m, 0.0],
                2 => [-ln10 * self.k * y * self.inv_m, 0.0],
                3 => [0.0, ln10 * self.alpha * v],
                4 => [0.0, -v.abs() * p * z],
                5 => [0.0, -v * p * az],
                _ => [0.0, -hyst * ln_az],
            };
            let sj = x.1[j];
            out.1[j] = [
                sj[1],
                -(self.k_m * sj[0] + self.c_m * sj[1] + sj[2] * self.inv_m) + forcing[0],
                dzdv * sj[1] + dzdz * sj[2] + forcing[1],
            ];
        }
    }
}

/// `out = x + w·d` on the state and the columns `LO..HI`.
#[inline(always)]
fn axpy<const LO: usize, const HI: usize>(x: &Block, d: &Block, w: f64, out: &mut Block) {
    for i in 0..3 {
        out.0[i] = x.0[i] + w * d.0[i];
    }
    for j in LO..HI {
        for i in 0..3 {
            out.1[j][i] = x.1[j][i] + w * d.1[j][i];
        }
    }
}

/// The Jacobian of the simulated output with respect to θ by the sensitivity equations, integrated
/// along the same input path and with the same RK4 stages as the core's step (one sub-step per
/// upsampled sample, the input linear inside it): with x = (y, ẏ, z), f(x, u; θ) the oscillator's
/// right-hand side and S = ∂x/∂θ, `Ṡ = (∂f/∂x)·S + ∂f/∂θ`. In θ's coordinates
/// (log10 m, log10 c, log10 k, log10 α, β·γ, β·δ, ν), with p = |z|^(ν−1):
///
/// ```text
/// ∂v̇/∂(y, v, z) = −(k, c, 1)/m          ∂ż/∂v = α − (βγ·sgn v·p·z + βδ·p·|z|)
/// ∂ż/∂z = −ν·p·(βγ·|v| + βδ·v·sgn z)
/// ∂v̇/∂θ₀..₂ = −ln10·(v̇, c·v/m, k·y/m)   ∂ż/∂θ₃ = ln10·α·v
/// ∂ż/∂(βγ, βδ) = −(|v|·p·z, v·p·|z|)     ∂ż/∂ν = −(βγ·|v|·p·z + βδ·v·p·|z|)·ln|z|
/// ```
///
/// The state is the core's (f64 from f32 parameters); every objective value still comes from the
/// core's own step. Writes the residuals `y_k − y_meas` and the entries `LO..HI` of the rows
/// `∂y_k/∂θ` of the scored samples `from..limit` (two calls with disjoint columns run in parallel).
fn sensitivities<const LO: usize, const HI: usize>(
    params: OscillatorParams,
    sample_period_s: f64,
    fine: &[f32],
    factor: usize,
    measured: (&[f64], usize, usize),
    out: (&mut [f64], &mut [[f64; DIM]]),
) -> bool {
    let (resid, jac) = out;
    let (y_meas, from, limit) = measured;
    let f = Tangent::new(params);
    let h = f64::from((sample_period_s / factor as f64) as f32);
    let zero: Block = ([0.0; 3], [[0.0; 3]; DIM]);
    let (mut state, mut stage) = (zero, zero);
    let (mut k1, mut k2, mut k3, mut k4) = (zero, zero, zero, zero);
    let mut u0 = f64::from(fine.first().copied().unwrap_or(0.0));
    let fine = &fine[..(limit * factor).min(fine.len())];
    for (i, &v) in fine.iter().enumerate().skip(1) {
        let u1 = f64::from(v);
        let um = u0 + (u1 - u0) * 0.5;
        f.rhs::<LO, HI>(&state, u0, &mut k1);
        axpy::<LO, HI>(&state, &k1, 0.5 * h, &mut stage);
        f.rhs::<LO, HI>(&stage, um, &mut k2);
        axpy::<LO, HI>(&state, &k2, 0.5 * h, &mut stage);
        f.rhs::<LO, HI>(&stage, um, &mut k3);
        axpy::<LO, HI>(&state, &k3, h, &mut stage);
        f.rhs::<LO, HI>(&stage, u1, &mut k4);
        for i in 0..3 {
            state.0[i] += h / 6.0 * (k1.0[i] + 2.0 * k2.0[i] + 2.0 * k3.0[i] + k4.0[i]);
        }
        for j in LO..HI {
            for i in 0..3 {
                state.1[j][i] +=
                    h / 6.0 * (k1.1[j][i] + 2.0 * k2.1[j][i] + 2.0 * k3.1[j][i] + k4.1[j][i]);
            }
        }
        u0 = u1;
        if i % factor == 0 {
            let sample = i / factor;
            if sample >= from && sample < limit {
                let r = sample - from;
                resid[r] = f64::from(state.0[0] as f32) - y_meas[sample];
                for j in LO..HI {
                    jac[r][j] = state.1[j][0];
                }
            }
        }
    }
    state.0.iter().all(|v| v.is_finite())
}

struct Objective<'a> {
    fine: &'a [f32],
    factor: usize,
    y: &'a [f64],
    from: usize,
    t: f64,
    evaluations: &'a AtomicU64,
}

/// The Gauss–Newton normal equations at one θ, accumulated on the stack: JᵀJ and Jᵀr.
struct Normal {
    jtj: [[f64; DIM]; DIM],
    jtr: [f64; DIM],
}

impl From<Normal> for NormalEquations {
    fn from(n: Normal) -> Self {
        Self {
            jtj: n.jtj.iter().map(|row| row.to_vec()).collect(),
            gradient: n.jtr.to_vec(),
        }
    }
}

impl Objective<'_> {
    /// SSE of θ on the samples `from..limit`; ∞ as soon as the running sum passes `abandon_above`
    /// (a losing trial of differential evolution: the rest can only add to it).
    fn residuals(&self, theta: &[f64], limit: usize, abandon_above: f64) -> f64 {
        self.evaluations.fetch_add(1, Ordering::Relaxed);
        let factor = self.factor;
        let fine = &self.fine[..(limit * factor).min(self.fine.len())];
        let mut sse = 0.0;
        let ok = simulate_while(params_of(theta), self.t, fine, factor, |k, v| {
            if k >= self.from && k < limit {
                let e = f64::from(v) - self.y[k];
                sse += e * e;
            }
            sse <= abandon_above
        });
        if ok.is_err() || !sse.is_finite() {
            f64::INFINITY
        } else {
            sse
        }
    }

    /// JᵀJ and Jᵀr on the samples `from..limit` from one sensitivity pass, split over two threads
    /// by columns; `None` if the state left the finite range.
    fn normal_equations(&self, theta: &[f64], limit: usize) -> Option<Normal> {
        self.evaluations.fetch_add(1, Ordering::Relaxed);
        let rows = limit - self.from;
        let (mut resid, mut resid_copy) = (vec![0.0; rows], vec![0.0; rows]);
        let (mut jac, mut jac_hi) = (vec![[0.0; DIM]; rows], vec![[0.0; DIM]; rows]);
        let measured = (self.y, self.from, limit);
        let params = params_of(theta);
        let (fine, factor, t) = (self.fine, self.factor, self.t);
        let (lo, hi) = rayon::join(
            || sensitivities::<0, 4>(params, t, fine, factor, measured, (&mut resid, &mut jac)),
            || {
                let out = (&mut resid_copy[..], &mut jac_hi[..]);
                sensitivities::<4, DIM>(params, t, fine, factor, measured, out)
            },
        );
        if !(lo && hi) {
            return None;
        }
        let mut normal = Normal {
            jtj: [[0.0; DIM]; DIM],
            jtr: [0.0; DIM],
        };
        for ((row, high), &r0) in jac.iter_mut().zip(&jac_hi).zip(&resid) {
            row[4..].copy_from_slice(&high[4..]);
            for a in 0..DIM {
                normal.jtr[a] += row[a] * r0;
                for b in a..DIM {
                    normal.jtj[a][b] += row[a] * row[b];
                }
            }
        }
        for a in 0..DIM {
            for b in 0..a {
                normal.jtj[a][b] = normal.jtj[b][a];
            }
        }
        Some(normal)
    }
}

/// One stage of Levenberg–Marquardt: its starting damping, the relative SSE gain below which it
/// stops, and its iteration cap.
struct LmStage {
    lambda: f64,
    tolerance: f64,
    iterations: usize,
}

/// The scored samples `from..limit` of an objective as a least-squares problem.
struct Samples<'a, 'o> {
    obj: &'a Objective<'o>,
    limit: usize,
    pb: &'a indicatif::ProgressBar,
}

impl LeastSquares for Samples<'_, '_> {
    fn sse(&mut self, theta: &[f64], abandon_above: f64) -> f64 {
        // A trial is abandoned once it passes the best SSE (it would be rejected).
        self.obj.residuals(theta, self.limit, abandon_above)
    }

    fn normal_equations(&mut self, theta: &[f64]) -> Option<NormalEquations> {
        self.obj.normal_equations(theta, self.limit).map(Into::into)
    }

    fn iteration(&mut self) {
        self.pb.inc(1);
    }

    fn tried(&mut self, lambda: f64, sse: f64) {
        let factor = self.obj.factor;
        super::trace(|| format!("oscillator LM (x{factor}): lambda {lambda:.1e}, SSE {sse:.9e}"));
    }
}

/// Levenberg–Marquardt ([`Marquardt`]) on the scored samples `from..limit` of `obj`, the
/// Jacobian by the sensitivity equations; λ from the stage's (÷3 on success down to 1e-12, ×4 on
/// failure, ×10 on a singular system), ten tries per iteration, a parameter at a bound whose
/// gradient points outwards held there; stops when a step gains at most the stage's tolerance or
/// the linear model promises less. Returns θ and its SSE.
fn levenberg_marquardt(
    obj: &Objective,
    theta: Vec<f64>,
    limit: usize,
    stage: LmStage,
    pb: &indicatif::ProgressBar,
) -> (Vec<f64>, f64) {
    let sse = obj.residuals(&theta, limit, f64::INFINITY);
    let settings = Marquardt {
        lambda: stage.lambda,
        lambda_min: 1e-12,
        scale_floor: 1e-30,
        tries: 10,
        singular_factor: 10.0,
        iterations: stage.iterations,
        min_gain: stage.tolerance,
        small_steps: None,
        predicted_gain: Some(stage.tolerance),
        hold_at_bounds: true,
    };
    settings.run(&mut Samples { obj, limit, pb }, theta, sse, &BOUNDS)
}

/// Differential evolution ([`Evolution`]: current-to-best/1/bin, F = 0.5, CR = 0.9, any two
/// donors, mutants clamped into the bounds; population 40) on the samples `from..limit` of `obj`,
/// one member started at `start`. When `start` already beats every member of the random initial
/// population (each of those is abandoned once it passes the start's SSE), the generations are
/// skipped: on the benchmark's two training files they never improved on it. Else at most 200
/// generations, fewer once 10 in a row each gain less than 1e-7 of the best SSE.
fn differential_evolution(
    obj: &Objective,
    start: Option<Vec<f64>>,
    limit: usize,
    seed: u64,
    pb: &indicatif::ProgressBar,
) -> Vec<f64> {
    let pop = 40;
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut x = evolution::random_population(&BOUNDS, pop, &mut rng);
    let mut f = vec![f64::INFINITY; pop];
    let mut abandon_above = f64::INFINITY;
    let mut first = 0;
    if let Some(start) = start {
        f[0] = obj.residuals(&start, limit, f64::INFINITY);
        abandon_above = f[0];
        x[0] = start;
        first = 1;
    }
    let rest: Vec<f64> = x[first..]
        .par_iter()
        .map(|th| obj.residuals(th, limit, abandon_above))
        .collect();
    // An abandoned member's SSE is a partial sum already past the start's.
    if abandon_above.is_finite() && rest.iter().all(|&v| v > abandon_above) {
        super::trace(|| {
            "oscillator DE: the equation-error start beats the initial population".into()
        });
        return x.swap_remove(0);
    }
    // The abandoned members' SSE in full.
    f[first..].copy_from_slice(&rest);
    let again: Vec<(usize, f64)> = (first..pop)
        .into_par_iter()
        .filter(|&i| f[i] > abandon_above && f[i].is_finite())
        .map(|i| (i, obj.residuals(&x[i], limit, f64::INFINITY)))
        .collect();
    for (i, v) in again {
        f[i] = v;
    }
    let settings = Evolution {
        weight: 0.5,
        crossover: Some(0.9),
        distinct_donors: false,
        boundary: Boundary::Clamp,
        generations: 200,
        // Converged: the best gained less than 1e-7 (relative) in each of 10 generations.
        stall: Some(Stall {
            gain: 1e-7,
            generations: 10,
        }),
        spread: None,
    };
    let population = Population { members: x, sse: f };
    let objective = |th: &[f64], parent: f64| obj.residuals(th, limit, parent);
    let generation = |p: &Population| {
        pb.inc(1);
        let (_, after) = p.best();
        super::trace(|| format!("oscillator DE: best SSE {after:.6e}"));
    };
    settings
        .run(population, &BOUNDS, &mut rng, objective, generation)
        .0
}

/// The record's input upsampled band-limited by `factor`, in f32 as the core steps it.
fn upsampled(record: &Record, factor: usize) -> Vec<f32> {
    upsample(&record.u, factor)
        .into_iter()
        .map(|v| v as f32)
        .collect()
}

/// Fits the oscillator to a training record.
pub fn identify(record: &Record, s: &IdentifySettings) -> Result<Identification, IdentifyError> {
    let started = Instant::now();
    let factor = UPSAMPLING as usize;
    let t = record.sample_period_s();
    let from = record.index_at(s.start_s);
    let n = record.u.len();
    let evaluations = AtomicU64::new(0);
    // The global stage and the first local one run on the input upsampled by 4 only (RK4 at 3 kHz:
    // ω·h ≈ 0.075, plenty for ranking candidates and for approaching the minimum); the final
    // polish at the full rate.
    let coarse_factor = 4;
    let (fine, coarse) = rayon::join(
        || upsampled(record, factor),
        || upsampled(record, coarse_factor),
    );
    let objective = |fine, factor| Objective {
        fine,
        factor,
        y: &record.y_m,
        from,
        t,
        evaluations: &evaluations,
    };
    let (obj, coarse_obj) = (objective(&fine, factor), objective(&coarse, coarse_factor));
    let pb = indicatif::ProgressBar::new(240);
    if !s.progress {
        pb.set_draw_target(indicatif::ProgressDrawTarget::hidden());
    }
    pb.set_message("oscillator DE");
    // Global stage on the first 2048 samples, one member started at the equation-error estimate.
    let short = n.min(from + 2048);
    let theta = differential_evolution(
        &coarse_obj,
        equation_error_start(record, &BOUNDS),
        short,
        s.seed,
        &pb,
    );
    let seconds = || started.elapsed().as_secs_f64();
    super::trace(|| format!("oscillator global stage: {:.2} s", seconds()));
    // Local stage: LM on the whole record at the coarse rate, then polished at the full rate.
    pb.set_message("oscillator LM");
    let approach = LmStage {
        lambda: 1e-3,
        tolerance: 1e-6,
        iterations: 40,
    };
    let (theta, _) = levenberg_marquardt(&coarse_obj, theta, n, approach, &pb);
    super::trace(|| format!("oscillator coarse LM: {:.2} s", seconds()));
    let polish = LmStage {
        lambda: 1e-4,
        tolerance: 1e-9,
        iterations: 40,
    };
    let (theta, _) = levenberg_marquardt(&obj, theta, n, polish, &pb);
    super::trace(|| format!("oscillator polish: {:.2} s {theta:?}", seconds()));
    pb.finish_and_clear();
    let set = Identified::Oscillator {
        params: params_of(&theta),
        sample_period_s: t as f32,
        substeps: UPSAMPLING,
    };
    let fit = score(&set, record, from)?;
    Ok(Identification {
        set,
        summary: IdentifySummary {
            records: Vec::new(),
            model: "oscillator",
            method: s.method.name(),
            fit,
            evaluations: evaluations.load(Ordering::Relaxed),
            seconds: started.elapsed().as_secs_f64(),
            at_bounds: None,
            two_step: None,
        },
    })
}

/// Simulates an oscillator set on a record (input upsampled as in fitting) and scores it from `from`.
pub fn score(set: &Identified, record: &Record, from: usize) -> Result<FitBlock, IdentifyError> {
    let predicted = predict(set, record)?;
    fit_block(&record.t_s, &record.y_m, &predicted, from).map_err(IdentifyError::NonFinite)
}

/// The oscillator's output per sample of `record` \[m\] (input upsampled by `substeps`).
pub fn predict(set: &Identified, record: &Record) -> crate::Result<Vec<f64>> {
    let Identified::Oscillator {
        params, substeps, ..
    } = *set
    else {
        return Err(crate::Error::Fit("not an oscillator set".into()));
    };
    let factor = substeps as usize;
    let fine: Vec<f32> = upsample(&record.u, factor)
        .into_iter()
        .map(|v| v as f32)
        .collect();
    let mut predicted = vec![0.0f64; record.u.len()];
    simulate(params, record.sample_period_s(), &fine, factor, |k, v| {
        if k < predicted.len() {
            predicted[k] = f64::from(v);
        }
    })
    .map_err(|e| crate::Error::Fit(format!("parameter set refused by piezo-core: {e}")))?;
    Ok(predicted)
}

/// Spectral derivatives of a periodic record: returns (x, ẋ, ẍ, x⃛) band-limited to `f_max_hz`.
fn spectral_derivatives(x: &[f64], t: f64, f_max_hz: f64) -> [Vec<f64>; 4] {
    let n = x.len();
    let mut planner = rustfft::FftPlanner::<f64>::new();
    let mut spec: Vec<Complex<f64>> = x.iter().map(|&v| Complex::new(v, 0.0)).collect();
    planner.plan_fft_forward(n).process(&mut spec);
    let inverse = planner.plan_fft_inverse(n);
    let mut out: [Vec<f64>; 4] = Default::default();
    for (order, o) in out.iter_mut().enumerate() {
        let mut d: Vec<Complex<f64>> = spec
            .iter()
            .enumerate()
            .map(|(k, &v)| {
                let kk = if k <= n / 2 {
                    k as f64
                } else {
                    k as f64 - n as f64
                };
                let f = kk / (n as f64 * t);
                if f.abs() > f_max_hz || (n % 2 == 0 && k == n / 2) {
                    return Complex::new(0.0, 0.0);
                }
                let w = Complex::new(0.0, 2.0 * std::f64::consts::PI * f);
                v * w.powi(order as i32)
            })
            .collect();
        inverse.process(&mut d);
        *o = d.iter().map(|c| c.re / n as f64).collect();
    }
    out
}

/// A starting point from the equation error (ν = 1): with spectral derivatives of the steady-state
/// periods (periods of 8192 samples after the first, averaged; else the whole record as one period),
/// z = u − m·ÿ − c·ẏ − k·y and ż = u̇ − m·y⃛ − c·ÿ − k·ẏ must satisfy ż = α·ẏ − p·|ẏ|·z − q·ẏ·|z|.
/// For given (m, c, k) this is linear in (α, p, q) (solved by least squares); (m, c, k) come from a
/// small differential evolution. Band-limited to 1.1 × the highest input line (≤ Nyquist).
fn equation_error_start(record: &Record, bounds: &[(f64, f64)]) -> Option<Vec<f64>> {
    const PERIOD: usize = 8192;
    let n = record.u.len();
    let (u, y) = if n % PERIOD == 0 && n >= 2 * PERIOD {
        let periods = n / PERIOD - 1;
        let avg = |v: &[f64]| -> Vec<f64> {
            (0..PERIOD)
                .map(|i| (1..=periods).map(|p| v[p * PERIOD + i]).sum::<f64>() / periods as f64)
                .collect()
        };
        (avg(&record.u), avg(&record.y_m))
    } else {
        (record.u.clone(), record.y_m.clone())
    };
    let t = record.sample_period_s();
    let [u0, u1, _, _] = spectral_derivatives(&u, t, 1.0 / (2.0 * t));
    // Highest excited line: the last bin with 1e-3 of the peak input amplitude.
    let mut planner = rustfft::FftPlanner::<f64>::new();
    let mut spec: Vec<Complex<f64>> = u.iter().map(|&v| Complex::new(v, 0.0)).collect();
    planner.plan_fft_forward(u.len()).process(&mut spec);
    let peak = spec
        .iter()
        .take(u.len() / 2)
        .map(|c| c.norm())
        .fold(0.0, f64::max);
    let top = (0..u.len() / 2)
        .rev()
        .find(|&k| spec[k].norm() > 1e-3 * peak)?;
    let f_max = (1.1 * top as f64 / (u.len() as f64 * t)).min(0.5 / t);
    let [y0, y1, y2, y3] = spectral_derivatives(&y, t, f_max);
    let cost = |mck: &[f64]| -> (f64, [f64; 3]) {
        let (m, c, k) = (10f64.powf(mck[0]), 10f64.powf(mck[1]), 10f64.powf(mck[2]));
        let mut g = [[0.0f64; 3]; 3];
        let mut b = [0.0f64; 3];
        let mut tt = 0.0;
        for i in 0..u.len() {
            let z = u0[i] - m * y2[i] - c * y1[i] - k * y0[i];
            let zd = u1[i] - m * y3[i] - c * y2[i] - k * y1[i];
            let phi = [y1[i], -y1[i].abs() * z, -y1[i] * z.abs()];
            for a in 0..3 {
                b[a] += phi[a] * zd;
                for bb in 0..3 {
                    g[a][bb] += phi[a] * phi[bb];
                }
            }
            tt += zd * zd;
        }
        let mut aug: Vec<Vec<f64>> = (0..3)
            .map(|a| {
                let mut r = g[a].to_vec();
                r.push(b[a]);
                r
            })
            .collect();
        match linear::solve(&mut aug, 3) {
            Some(x) => (
                tt - (0..3).map(|a| x[a] * b[a]).sum::<f64>(),
                [x[0], x[1], x[2]],
            ),
            None => (f64::INFINITY, [0.0; 3]),
        }
    };
    // Differential evolution over (log10 m, log10 c, log10 k): F = 0.5, every coordinate from the
    // mutant (no crossover), any two donors, clamped into the bounds, 24 members, 150 generations.
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let members = evolution::random_population(&bounds[..3], 24, &mut rng);
    let sse: Vec<f64> = members.par_iter().map(|v| cost(v).0).collect();
    let settings = Evolution {
        weight: 0.5,
        crossover: None,
        distinct_donors: false,
        boundary: Boundary::Clamp,
        generations: 150,
        stall: None,
        spread: None,
    };
    let (mck, _) = settings.run(
        Population { members, sse },
        &bounds[..3],
        &mut rng,
        |v, _| cost(v).0,
        |_| {},
    );
    let (_, lin) = cost(&mck);
    super::trace(|| {
        format!("equation-error (m, c, k) = {mck:?}, (alpha, p, q) = {lin:?}, f_max {f_max} Hz")
    });
    if !(lin[0] > 0.0) {
        return None;
    }
    let mut theta = mck;
    theta.push(lin[0].log10().clamp(bounds[3].0, bounds[3].1));
    theta.push(lin[1].clamp(bounds[4].0, bounds[4].1));
    theta.push(lin[2].clamp(bounds[5].0, bounds[5].1));
    theta.push(1.0);
    super::trace(|| format!("equation-error start: {theta:?}"));
    Some(theta)
}
