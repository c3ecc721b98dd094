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
//! θ = (log10 m, log10 c, log10 k, log10 α, β·γ, β·δ, ν); differential evolution on the first
//! 2048 samples (input upsampled by 4 only; a trial's simulation stops once its running SSE passes
//! its parent's; at most 200 generations, fewer once 10 in a row each gain less than 1e-7 of the
//! best SSE), then Levenberg–Marquardt on the whole training record with the Jacobian from the
//! sensitivity equations (`sensitivities`; one pass instead of one simulation per parameter). Never
//! fit on test data: this sees only the record it is given.

// Index loops for the small dense algebra; `%` rather than `is_multiple_of` (rust-version 1.80).
#![allow(clippy::needless_range_loop, clippy::manual_is_multiple_of)]

use super::{
    fit_block, FitBlock, Identification, IdentifyError, IdentifySettings, IdentifySummary, Record,
};
use crate::identify::model::Identified;
use piezo_core::{HystereticOscillator, OscillatorParams, OscillatorState};
use rand_chacha::ChaCha8Rng;
use rand_core::{RngCore, SeedableRng};
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
/// core's own step. Writes the residuals `y_k − y_meas` and the entries `columns` of the rows
/// `∂y_k/∂θ` of the scored samples `from..limit` (two calls with disjoint columns run in parallel).
fn sensitivities(
    params: OscillatorParams,
    sample_period_s: f64,
    fine: &[f32],
    factor: usize,
    measured: (&[f64], usize, usize),
    columns: std::ops::Range<usize>,
    out: (&mut [f64], &mut [[f64; DIM]]),
) -> bool {
    let (resid, jac) = out;
    let (y_meas, from, limit) = measured;
    let m = f64::from(params.mass_kg);
    let c = f64::from(params.damping_n_s_per_m);
    let k = f64::from(params.stiffness_n_per_m);
    let alpha = f64::from(params.alpha_n_per_m);
    let bg = f64::from(params.beta_per_m) * f64::from(params.gamma);
    let bd = f64::from(params.beta_per_m) * f64::from(params.delta);
    let nu = f64::from(params.nu);
    let ln10 = std::f64::consts::LN_10;
    let h = f64::from((sample_period_s / factor as f64) as f32);
    // State and sensitivities: [y, v, z] and s[j] = ∂[y, v, z]/∂θ_j.
    type Block = ([f64; 3], [[f64; 3]; DIM]);
    let rhs = |x: &[f64; 3], s: &[[f64; 3]; DIM], u: f64| -> Block {
        let (y, v, z) = (x[0], x[1], x[2]);
        let az = z.abs();
        let p = if nu == 1.0 { 1.0 } else { az.powf(nu - 1.0) };
        let acc = (u - c * v - k * y - z) / m;
        let zdot = alpha * v - (bg * v.abs() * p * z + bd * v * p * az);
        let dzdv = alpha - (bg * v.signum() * p * z + bd * p * az);
        let dzdz = -nu * p * (bg * v.abs() + bd * v * z.signum());
        let ln_az = if az > 0.0 { az.ln() } else { 0.0 };
        let forcing: [[f64; 3]; DIM] = [
            [0.0, -ln10 * acc, 0.0],
            [0.0, -ln10 * c * v / m, 0.0],
            [0.0, -ln10 * k * y / m, 0.0],
            [0.0, 0.0, ln10 * alpha * v],
            [0.0, 0.0, -v.abs() * p * z],
            [0.0, 0.0, -v * p * az],
            [0.0, 0.0, -(bg * v.abs() * p * z + bd * v * p * az) * ln_az],
        ];
        let mut ds = [[0.0; 3]; DIM];
        for j in columns.clone() {
            let sj = s[j];
            ds[j] = [
                sj[1],
                -(k * sj[0] + c * sj[1] + sj[2]) / m + forcing[j][1],
                dzdv * sj[1] + dzdz * sj[2] + forcing[j][2],
            ];
        }
        ([v, acc, zdot], ds)
    };
    let axpy = |x: &Block, d: &Block, w: f64| -> Block {
        let mut out = *x;
        for i in 0..3 {
            out.0[i] += w * d.0[i];
        }
        for j in columns.clone() {
            for i in 0..3 {
                out.1[j][i] += w * d.1[j][i];
            }
        }
        out
    };
    let mut state: Block = ([0.0; 3], [[0.0; 3]; DIM]);
    let mut u0 = f64::from(fine.first().copied().unwrap_or(0.0));
    let fine = &fine[..(limit * factor).min(fine.len())];
    for (i, &v) in fine.iter().enumerate().skip(1) {
        let u1 = f64::from(v);
        let um = u0 + (u1 - u0) * 0.5;
        let k1 = rhs(&state.0, &state.1, u0);
        let s2 = axpy(&state, &k1, 0.5 * h);
        let k2 = rhs(&s2.0, &s2.1, um);
        let s3 = axpy(&state, &k2, 0.5 * h);
        let k3 = rhs(&s3.0, &s3.1, um);
        let s4 = axpy(&state, &k3, h);
        let k4 = rhs(&s4.0, &s4.1, u1);
        let mut next = state;
        for i in 0..3 {
            next.0[i] += h / 6.0 * (k1.0[i] + 2.0 * k2.0[i] + 2.0 * k3.0[i] + k4.0[i]);
        }
        for j in columns.clone() {
            for i in 0..3 {
                next.1[j][i] +=
                    h / 6.0 * (k1.1[j][i] + 2.0 * k2.1[j][i] + 2.0 * k3.1[j][i] + k4.1[j][i]);
            }
        }
        state = next;
        u0 = u1;
        if i % factor == 0 {
            let sample = i / factor;
            if sample >= from && sample < limit {
                let r = sample - from;
                resid[r] = f64::from(state.0[0] as f32) - y_meas[sample];
                for j in columns.clone() {
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
}

/// Fits the oscillator to a training record.
pub fn identify(record: &Record, s: &IdentifySettings) -> Result<Identification, IdentifyError> {
    let started = Instant::now();
    let factor = UPSAMPLING as usize;
    let t = record.sample_period_s();
    let fine: Vec<f32> = upsample(&record.u, factor)
        .into_iter()
        .map(|v| v as f32)
        .collect();
    let from = record.index_at(s.start_s);
    let n = record.u.len();
    let evaluations = AtomicU64::new(0);
    // The global stage runs on the input upsampled by 4 only (RK4 at 3 kHz: ω·h ≈ 0.075, plenty for
    // ranking candidates) and on the first 2048 samples; the local stage on the full rate and record.
    let coarse_factor = 4;
    let coarse: Vec<f32> = upsample(&record.u, coarse_factor)
        .into_iter()
        .map(|v| v as f32)
        .collect();
    let coarse_obj = Objective {
        fine: &coarse,
        factor: coarse_factor,
        y: &record.y_m,
        from,
        t,
        evaluations: &evaluations,
    };
    let obj = Objective {
        fine: &fine,
        factor,
        y: &record.y_m,
        from,
        t,
        evaluations: &evaluations,
    };
    let bounds = [
        (-1.0, 1.5),
        (-0.5, 2.5),
        (3.0, 6.0),
        (3.0, 6.0),
        (0.0, 5000.0),
        (-5000.0, 5000.0),
        (1.0, 2.5),
    ];
    let pb = indicatif::ProgressBar::new(240);
    if !s.progress {
        pb.set_draw_target(indicatif::ProgressDrawTarget::hidden());
    }
    pb.set_message("oscillator DE");
    // Global stage on the first 2048 samples, one member started at the equation-error estimate.
    let short = n.min(from + 2048);
    let dim = bounds.len();
    let pop = 40;
    let mut rng = ChaCha8Rng::seed_from_u64(s.seed);
    let unif = |rng: &mut ChaCha8Rng| (rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64;
    let mut x: Vec<Vec<f64>> = (0..pop)
        .map(|_| {
            bounds
                .iter()
                .map(|&(lo, hi)| lo + (hi - lo) * unif(&mut rng))
                .collect()
        })
        .collect();
    if let Some(init) = equation_error_start(record, &bounds) {
        x[0] = init;
    }
    let mut f: Vec<f64> = x
        .par_iter()
        .map(|th| coarse_obj.residuals(th, short, f64::INFINITY))
        .collect();
    let mut stall = 0;
    for _ in 0..200 {
        pb.inc(1);
        let best = (0..pop).min_by(|&a, &b| f[a].total_cmp(&f[b])).unwrap_or(0);
        let trials: Vec<Vec<f64>> = (0..pop)
            .map(|i| {
                let r1 = (rng.next_u64() % pop as u64) as usize;
                let r2 = (rng.next_u64() % pop as u64) as usize;
                let jr = (rng.next_u64() % dim as u64) as usize;
                (0..dim)
                    .map(|j| {
                        let (lo, hi) = bounds[j];
                        if j == jr || unif(&mut rng) < 0.9 {
                            let v = x[i][j]
                                + 0.5 * (x[best][j] - x[i][j])
                                + 0.5 * (x[r1][j] - x[r2][j]);
                            v.clamp(lo, hi)
                        } else {
                            x[i][j]
                        }
                    })
                    .collect()
            })
            .collect();
        let ft: Vec<f64> = trials
            .par_iter()
            .zip(f.par_iter())
            .map(|(th, &parent)| coarse_obj.residuals(th, short, parent))
            .collect();
        let before = f[best];
        for (i, (th, v)) in trials.into_iter().zip(ft).enumerate() {
            if v <= f[i] {
                x[i] = th;
                f[i] = v;
            }
        }
        let after = f.iter().copied().fold(f64::INFINITY, f64::min);
        if std::env::var_os("PIEZO_ID_DEBUG").is_some() {
            eprintln!("oscillator DE: best SSE {after:.6e}");
        }
        // Converged: the best gained less than 1e-6 (relative) over 10 generations.
        stall = if after < before * (1.0 - 1e-7) {
            0
        } else {
            stall + 1
        };
        if stall >= 10 {
            break;
        }
    }
    let best = (0..pop).min_by(|&a, &b| f[a].total_cmp(&f[b])).unwrap_or(0);
    let mut theta = x[best].clone();
    // Local stage: LM on the whole record, the Jacobian by the sensitivity equations.
    pb.set_message("oscillator LM");
    let m = n - from;
    let (mut resid, mut resid_copy) = (vec![0.0; m], vec![0.0; m]);
    let mut jac = vec![[0.0; DIM]; m];
    let mut jac_hi = vec![[0.0; DIM]; m];
    let mut fbest = obj.residuals(&theta, n, f64::INFINITY);
    let mut lambda = 1e-3;
    for _ in 0..40 {
        pb.inc(1);
        evaluations.fetch_add(1, Ordering::Relaxed);
        let measured = (record.y_m.as_slice(), from, n);
        let params = params_of(&theta);
        let (lo, hi) = rayon::join(
            || {
                sensitivities(
                    params,
                    t,
                    &fine,
                    factor,
                    measured,
                    0..4,
                    (&mut resid, &mut jac),
                )
            },
            || {
                let out = (&mut resid_copy[..], &mut jac_hi[..]);
                sensitivities(params, t, &fine, factor, measured, 4..DIM, out)
            },
        );
        if !(lo && hi) {
            break;
        }
        for (row, high) in jac.iter_mut().zip(&jac_hi) {
            row[4..].copy_from_slice(&high[4..]);
        }
        let mut jtj = vec![vec![0.0; dim]; dim];
        let mut jtr = vec![0.0; dim];
        for (row, &r0) in jac.iter().zip(&resid) {
            for a in 0..dim {
                jtr[a] += row[a] * r0;
                for b in a..dim {
                    jtj[a][b] += row[a] * row[b];
                }
            }
        }
        for a in 0..dim {
            for b in 0..a {
                jtj[a][b] = jtj[b][a];
            }
        }
        let mut improved = false;
        for _ in 0..10 {
            let mut aug: Vec<Vec<f64>> = (0..dim)
                .map(|a| {
                    let mut row = jtj[a].clone();
                    row[a] += lambda * jtj[a][a].max(1e-30);
                    row.push(-jtr[a]);
                    row
                })
                .collect();
            let Some(d) = super::fit::solve_dense_pub(&mut aug, dim) else {
                lambda *= 10.0;
                continue;
            };
            let trial: Vec<f64> = theta
                .iter()
                .zip(&d)
                .zip(&bounds)
                .map(|((a, b), &(lo, hi))| (a + b).clamp(lo, hi))
                .collect();
            let ft = obj.residuals(&trial, n, f64::INFINITY);
            if ft < fbest {
                improved = (fbest - ft) / fbest > 1e-9;
                theta = trial;
                fbest = ft;
                lambda = (lambda / 3.0).max(1e-12);
                break;
            }
            lambda *= 4.0;
        }
        if !improved {
            break;
        }
    }
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
    Ok(fit_block(&record.y_m[from..], &predicted[from..]))
}

/// The oscillator's output per sample of `record` \[m\] (input upsampled by `substeps`).
pub fn predict(set: &Identified, record: &Record) -> Result<Vec<f64>, String> {
    let Identified::Oscillator {
        params, substeps, ..
    } = *set
    else {
        return Err("not an oscillator set".into());
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
    .map_err(|e| format!("parameter set refused by piezo-core: {e}"))?;
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
        match super::fit::solve_dense_pub(&mut aug, 3) {
            Some(x) => (
                tt - (0..3).map(|a| x[a] * b[a]).sum::<f64>(),
                [x[0], x[1], x[2]],
            ),
            None => (f64::INFINITY, [0.0; 3]),
        }
    };
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let unif = |rng: &mut ChaCha8Rng| (rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64;
    let pop = 24;
    let mut x: Vec<Vec<f64>> = (0..pop)
        .map(|_| {
            bounds[..3]
                .iter()
                .map(|&(lo, hi)| lo + (hi - lo) * unif(&mut rng))
                .collect()
        })
        .collect();
    let mut f: Vec<f64> = x.par_iter().map(|v| cost(v).0).collect();
    for _ in 0..150 {
        let best = (0..pop).min_by(|&a, &b| f[a].total_cmp(&f[b])).unwrap_or(0);
        let trials: Vec<Vec<f64>> = (0..pop)
            .map(|i| {
                let r1 = (rng.next_u64() % pop as u64) as usize;
                let r2 = (rng.next_u64() % pop as u64) as usize;
                (0..3)
                    .map(|j| {
                        let v =
                            x[i][j] + 0.5 * (x[best][j] - x[i][j]) + 0.5 * (x[r1][j] - x[r2][j]);
                        v.clamp(bounds[j].0, bounds[j].1)
                    })
                    .collect()
            })
            .collect();
        let ft: Vec<f64> = trials.par_iter().map(|v| cost(v).0).collect();
        for (i, (v, c)) in trials.into_iter().zip(ft).enumerate() {
            if c <= f[i] {
                x[i] = v;
                f[i] = c;
            }
        }
    }
    let best = (0..pop).min_by(|&a, &b| f[a].total_cmp(&f[b])).unwrap_or(0);
    let (_, lin) = cost(&x[best]);
    if std::env::var_os("PIEZO_ID_DEBUG").is_some() {
        eprintln!(
            "equation-error (m, c, k) = {:?}, (alpha, p, q) = {lin:?}, f_max {f_max} Hz",
            x[best]
        );
    }
    if !(lin[0] > 0.0) {
        return None;
    }
    let mut theta = x[best].clone();
    theta.push(lin[0].log10().clamp(bounds[3].0, bounds[3].1));
    theta.push(lin[1].clamp(bounds[4].0, bounds[4].1));
    theta.push(lin[2].clamp(bounds[5].0, bounds[5].1));
    theta.push(1.0);
    if std::env::var_os("PIEZO_ID_DEBUG").is_some() {
        eprintln!("equation-error start: {theta:?}");
    }
    Some(theta)
}
