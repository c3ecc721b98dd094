//! The objective and the optimisers: variable projection, differential evolution,
//! Levenberg–Marquardt (both [`crate::optimise`]'s, with the settings below), and seed 001's
//! genetic algorithm.
//!
//! # Objective (variable projection)
//! For the static models the output is linear in (k1, k2, y0) once h is known:
//! `y = k1·u + k2·h(θ) + y0`. One evaluation simulates the core model with the map (0, 1, 0), so that
//! its output *is* h(θ), accumulates the 3×3 normal equations of the basis (u, h, 1) in f64 while it
//! runs, and solves them on the stack: the SSE at the best linear parameters for θ, without storing
//! or copying the record (an evaluation makes no heap allocation; `benches/identify.rs` checks that
//! memory stays flat in N). For the dynamic model the basis is (x₁, 1), where x₁ is the core
//! `DynamicModel` with k0 = 1 N/m and k1 = 1 N/V, so the linear parameters are the compliance 1/k0 and x0.
//!
//! The Bouc-Wen scale is redundant with k2 (h → c·h, A → c·A, β → β/|c|^(n−1), γ → γ·sgn c/|c|^(n−1),
//! k2 → k2/c leaves y unchanged), so the static models fix A = 1 and search
//! θ = (log10(H/U), r, n[, d, p]) with H = (1/(β+γ))^(1/n) the state bound, U the input span,
//! r = (β − γ)/(β + γ) ≥ −1 (β ≥ 0), d = δ·U·T_rec/H and p = φ/T. This keeps β + γ > 0 (the bounded class).
//!
//! # Method `vp-de-lm`
//! 1. Differential evolution (DE/current-to-best/1/bin, F = 0.6, CR = 0.9, seeded ChaCha8, so
//!    deterministic for a given `--seed`) on the record decimated to at most 2500 samples (the
//!    hysteresis is rate-independent, so the decimated input path gives nearly the same h), each
//!    generation evaluated in parallel (rayon). A trial's simulation stops as soon as the projected
//!    SSE of the samples seen so far exceeds its parent's SSE (a lower bound of its own, so the
//!    selection is the same as with the whole record). The screening integrates the general-n
//!    Bouc-Wen path with RK4 sub-steps of J·Δu ≤ 0.5 instead of the core's 0.1
//!    ([`piezo_core::BoucWen::with_substep_target`]: about 2.6e-4 of the state scale per sub-step):
//!    a stiff candidate set (small H, large n) costs sub-steps in proportion to its J along the
//!    input path, whatever the decimation, and such sets were most of the search's time.
//! 2. Levenberg–Marquardt on the full record from the DE optimum. The static models take the exact
//!    Jacobian of the projected residual in Kaufman's form, J = −P⊥·k2·∂h/∂θ, from one pass of the
//!    core's forward sensitivities ([`piezo_core::sensitivity`]: ∂h/∂(β, γ, n, δ, φ) along the input
//!    path, chained to θ), run beside the base point's simulation; the dynamic model a
//!    forward-difference Jacobian (each column one core simulation, in parallel, into buffers
//!    allocated once per run). Marquardt scaling, every trial point evaluated by the same projected
//!    objective; it stops when an iteration fails to improve or two in a row gain less than
//!    0.1·SSE/N (a tenth of the residual variance: below the parameters' one-σ significance).
//!
//! # Several records
//! A problem may hold several records of one stage end to end ([`Problem::segments`]: the first
//! sample of each). The simulation starts from rest at each record's first sample. With
//! [`Problem::free_offset`] each record has its own constant sensor offset: the offsets are
//! projected out with the linear parameters (the basis (u, h) centred per record, so the SSE is
//! the sum of each record's zeroed SSE) and the Jacobian is taken by forward differences (the
//! core's sensitivities run over one record from rest).
//!
//! The optimisers record their best θ after every DE generation and LM iteration
//! ([`Problem::trace`]), so that `benches/identify.rs` can report the time to fitness.

// Small dense linear algebra reads best with index loops.
#![allow(clippy::needless_range_loop)]

use super::model::{bouc_wen, CoreModel, Identified, ModelKind};
use crate::optimise::evolution::{self, uniform};
use crate::optimise::{
    linear, Boundary, Evolution, LeastSquares, Marquardt, NormalEquations, Population, Stall,
};
use piezo_core::{static_sensitivities, SENSITIVITY_PARAMETERS};
use piezo_core::{
    Asymmetry, BoucWenParams, Compensator, CompensatorSettings, DynamicModel,
    MassSpringDamperParams, StaticMap, StaticModel,
};
use rand_chacha::ChaCha8Rng;
use rand_core::{RngCore, SeedableRng};
use rayon::prelude::*;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::Instant;

/// `J·Δu` per RK4 sub-step of the general-n Bouc-Wen path while differential evolution screens
/// on the decimated record (the core's default, used for the full record, is 0.1).
const SCREENING_SUBSTEP_TARGET: f32 = 0.5;

/// One point of an optimiser's progress: the best θ after a DE generation or an LM iteration.
#[derive(Debug, Clone)]
pub struct TracePoint {
    /// `"de"` (after the initial population or a generation) or `"lm"` (after an iteration).
    pub stage: &'static str,
    /// Seconds since the problem was prepared.
    pub seconds: f64,
    /// Core simulations run so far.
    pub evaluations: u64,
    /// The optimiser's best θ so far.
    pub theta: Vec<f64>,
    /// Its SSE \[m²\] on every `stride`-th sample (DE works on the decimated record).
    pub sse: f64,
    /// Decimation of `sse` (1: the full record).
    pub stride: usize,
}

/// A record prepared for fitting.
pub struct Problem {
    /// Model family.
    pub kind: ModelKind,
    /// Input (f32, as the core sees it).
    pub u: Vec<f32>,
    /// Measured output \[m\].
    pub y: Vec<f64>,
    /// First sample that is scored (earlier samples only warm the state up).
    pub score_from: usize,
    /// Sample period \[s\].
    pub sample_period_s: f64,
    /// Input range the sets are validated over \[V\].
    pub input_range_v: (f32, f32),
    /// Asymmetric model: fit the input shift φ too (Case III) or keep it 0 (Case II).
    pub fit_shift: bool,
    /// Require the compensator to accept the set (what the firmware build checks).
    pub invertible: bool,
    /// The first sample of each record (`[0]` for one record); the simulation restarts from rest
    /// at each.
    pub segments: Vec<usize>,
    /// Each record has its own constant sensor offset (projected out per record).
    pub free_offset: bool,
    y_mean: f64,
    y_scale: f64,
    evaluations: AtomicU64,
    started: Instant,
    trace: Mutex<Vec<TracePoint>>,
}

/// Result of one projected evaluation.
#[derive(Debug, Clone, Copy)]
pub struct Eval {
    /// Sum of squared errors over the scored samples \[m²\] (∞ when infeasible).
    pub sse: f64,
    /// Linear parameters in normalised units (with free offsets, the third is the first
    /// record's offset).
    lin: [f64; 3],
}

/// The normal equations of one record's scored samples (basis (u, h, 1) or (x₁, 1)).
#[derive(Debug, Clone, Copy, Default)]
struct Sums {
    g: [[f64; 3]; 3],
    rhs: [f64; 3],
    yy: f64,
}

impl Sums {
    fn add(&mut self, phi: &[f64; 3], yn: f64, nb: usize) {
        for a in 0..nb {
            self.rhs[a] += phi[a] * yn;
            for b in 0..nb {
                self.g[a][b] += phi[a] * phi[b];
            }
        }
        self.yy += yn * yn;
    }

    /// Adds `record`'s sums centred on its own means (its constant projected out; the constant
    /// is basis entry `nb − 1`).
    fn add_centred(&mut self, record: &Sums, nb: usize) {
        let c = nb - 1;
        let n = record.g[c][c];
        if n <= 0.0 {
            return;
        }
        for a in 0..c {
            for b in 0..c {
                self.g[a][b] += record.g[a][b] - record.g[a][c] * record.g[b][c] / n;
            }
            self.rhs[a] += record.rhs[a] - record.g[a][c] * record.rhs[c] / n;
        }
        self.yy += record.yy - record.rhs[c] * record.rhs[c] / n;
    }

    /// The record's offset (normalised) for the linear parameters `lin` of the non-constant
    /// entries: mean(y) − Σ lin·mean(φ).
    fn offset(&self, lin: &[f64; 3], nb: usize) -> f64 {
        let c = nb - 1;
        let n = self.g[c][c].max(1.0);
        (self.rhs[c] - (0..c).map(|a| lin[a] * self.g[a][c]).sum::<f64>()) / n
    }
}

impl Problem {
    /// Prepares a record; `score_from` is the first scored sample.
    pub fn new(
        kind: ModelKind,
        u: &[f64],
        y: &[f64],
        score_from: usize,
        sample_period_s: f64,
    ) -> Self {
        let u32s: Vec<f32> = u.iter().map(|&v| v as f32).collect();
        let lo = u32s.iter().copied().fold(f32::INFINITY, f32::min);
        let hi = u32s.iter().copied().fold(f32::NEG_INFINITY, f32::max);
        let scored = &y[score_from.min(y.len())..];
        let n = scored.len().max(1) as f64;
        let mean = scored.iter().sum::<f64>() / n;
        let var = scored.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / n;
        Self {
            kind,
            u: u32s,
            y: y.to_vec(),
            score_from,
            sample_period_s,
            input_range_v: (lo, if hi > lo { hi } else { lo + 1.0 }),
            fit_shift: true,
            invertible: false,
            segments: vec![0],
            free_offset: false,
            y_mean: mean,
            y_scale: if var > 0.0 { var.sqrt() } else { 1.0 },
            evaluations: AtomicU64::new(0),
            started: Instant::now(),
            trace: Mutex::new(Vec::new()),
        }
    }

    /// Records the optimiser's best θ so far (a few per run: after each DE generation, LM iteration).
    fn record(&self, stage: &'static str, theta: &[f64], sse: f64, stride: usize) {
        let point = TracePoint {
            stage,
            seconds: self.started.elapsed().as_secs_f64(),
            evaluations: self.evaluations(),
            theta: theta.to_vec(),
            sse,
            stride,
        };
        if let Ok(mut t) = self.trace.lock() {
            t.push(point);
        }
    }

    /// The progress recorded by the optimisers so far (time to fitness).
    pub fn trace(&self) -> Vec<TracePoint> {
        self.trace.lock().map(|t| t.clone()).unwrap_or_default()
    }

    /// Number of scored samples.
    pub fn scored_len(&self) -> usize {
        self.scored()
    }

    /// Core simulations run so far.
    pub fn evaluations(&self) -> u64 {
        self.evaluations.load(Ordering::Relaxed)
    }

    fn span(&self) -> f64 {
        f64::from(self.input_range_v.1 - self.input_range_v.0)
    }

    /// Search box of θ for the projected methods.
    pub fn bounds(&self) -> Vec<(f64, f64)> {
        let mut b = vec![(-1.5, 1.0), (-1.0, 30.0), (1.0, 5.0)];
        match self.kind {
            ModelKind::Asymmetric => {
                b.push((-1.0, 1.0));
                if self.fit_shift {
                    b.push((-1.0, 1.0));
                }
            }
            ModelKind::Dynamic => {
                // A relative to k1 = 1, natural frequency / sample rate, damping ratio.
                b.push((-2.0, 2.0));
                b.push((-2.5, -0.31));
                b.push((-2.0, 0.5));
            }
            _ => {}
        }
        b
    }

    fn bouc_wen_of(&self, theta: &[f64], a: f64) -> BoucWenParams {
        let n = theta[2];
        let h = self.span() * 10f64.powf(theta[0]);
        let b = a.abs() * h.powf(-n);
        BoucWenParams {
            a: a as f32,
            beta: (b * (1.0 + theta[1]) / 2.0) as f32,
            gamma: (a.signum() * b * (1.0 - theta[1]) / 2.0) as f32,
            n: n as f32,
        }
    }

    fn asymmetry_of(&self, theta: &[f64], stride: usize) -> Asymmetry {
        if self.kind != ModelKind::Asymmetric {
            return Asymmetry::default();
        }
        let h = self.span() * 10f64.powf(theta[0]);
        let duration = self.sample_period_s * self.u.len() as f64;
        let t = self.sample_period_s * stride as f64;
        Asymmetry {
            delta_per_v_s: (theta[3] * h / (self.span() * duration)) as f32,
            input_shift_s: if self.fit_shift {
                (theta[4] * t) as f32
            } else {
                0.0
            },
        }
    }

    /// The core model with the linear parameters set to the basis ((0, 1, 0) or k0 = k1 = 1).
    fn basis_model(&self, theta: &[f64], stride: usize) -> Option<CoreModel> {
        let t = (self.sample_period_s * stride as f64) as f32;
        match self.kind {
            ModelKind::Symmetric | ModelKind::Asymmetric => {
                let bw = bouc_wen(self.bouc_wen_of(theta, 1.0), self.input_range_v).ok()?;
                // The decimated record (differential evolution) screens with coarser sub-steps.
                let bw = if stride > 1 {
                    bw.with_substep_target(SCREENING_SUBSTEP_TARGET).ok()?
                } else {
                    bw
                };
                let map = StaticMap {
                    k1_m_per_v: 0.0,
                    k2_m_per_h: 1.0,
                    offset_m: 0.0,
                };
                let asym = self.asymmetry_of(theta, stride);
                Some(CoreModel::Static(
                    StaticModel::with_asymmetry(bw, map, asym, t).ok()?,
                ))
            }
            ModelKind::Dynamic => {
                let bw = bouc_wen(self.bouc_wen_of(theta, theta[3]), self.input_range_v).ok()?;
                let wn = 2.0 * std::f64::consts::PI * 10f64.powf(theta[4]) / self.sample_period_s;
                let zeta = 10f64.powf(theta[5]);
                let mech = MassSpringDamperParams {
                    mass_kg: (1.0 / (wn * wn)) as f32,
                    damping_n_s_per_m: (2.0 * zeta / wn) as f32,
                    stiffness_n_per_m: 1.0,
                    rest_position_m: 0.0,
                    force_per_volt_n_per_v: 1.0,
                };
                Some(CoreModel::Dynamic(DynamicModel::new(bw, mech, t).ok()?))
            }
            ModelKind::Oscillator => None,
        }
    }

    /// The decimated indices (every `stride`-th sample) at which a record starts, after the first.
    fn restarts(&self, stride: usize) -> Vec<usize> {
        let mut r: Vec<usize> = self.segments.iter().map(|s| s.div_ceil(stride)).collect();
        r.dedup();
        r
    }

    /// Each record's constant sensor offset \[m\] at θ (the map's offset for every record without
    /// free offsets).
    pub fn record_offsets_m(&self, theta: &[f64]) -> Vec<f64> {
        let mut n = vec![0usize; self.segments.len()];
        let mut sum = vec![0.0f64; self.segments.len()];
        let e = self.eval_full(theta);
        let Some(set) = self.identified(theta, &e) else {
            return vec![f64::NAN; self.segments.len()];
        };
        let Ok(CoreModel::Static(model)) = set.build() else {
            return vec![f64::NAN; self.segments.len()];
        };
        let offset = f64::from(model.map().offset_m);
        let mut visit = |k: usize, v: f32| -> bool {
            if k >= self.score_from {
                let r = self.segments.partition_point(|&s| s <= k).saturating_sub(1);
                sum[r] += self.y[k] - f64::from(v) + offset;
                n[r] += 1;
            }
            true
        };
        simulate_iter(
            &CoreModel::Static(model),
            self.u.iter().copied(),
            &self.segments,
            &mut visit,
        );
        if !self.free_offset {
            return vec![offset; self.segments.len()];
        }
        sum.iter()
            .zip(&n)
            .map(|(s, &n)| if n > 0 { s / n as f64 } else { offset })
            .collect()
    }

    fn basis_len(&self) -> usize {
        if self.kind == ModelKind::Dynamic {
            2
        } else {
            3
        }
    }

    /// Projected evaluation on every `stride`-th sample; with `resid`, the normalised residuals of
    /// the scored samples are written there (and `scratch` holds the basis; both of record length).
    /// With a finite `abandon_above` \[m²\] the simulation stops, returning an infinite SSE, as soon
    /// as the projected SSE of the samples seen so far exceeds it: that partial minimum is a lower
    /// bound of the whole record's (the whole record's best linear parameters do no better on its
    /// first part), so such a θ is certainly worse than `abandon_above`.
    fn evaluate(
        &self,
        theta: &[f64],
        stride: usize,
        mut buffers: Option<(&mut [f64], &mut [[f64; 3]])>,
        abandon_above: f64,
    ) -> Eval {
        self.evaluations.fetch_add(1, Ordering::Relaxed);
        let bad = Eval {
            sse: f64::INFINITY,
            lin: [0.0; 3],
        };
        let Some(model) = self.basis_model(theta, stride) else {
            return bad;
        };
        let nb = self.basis_len();
        let mut total = Sums::default();
        let (mean, scale) = (self.y_mean, self.y_scale);
        let mut finite = true;
        let decimated = self.u.iter().copied().step_by(stride);
        let mut k_scored = 0usize;
        // With free offsets each record's sums are centred when it ends (no partial bound).
        let free = self.free_offset && self.segments.len() > 1;
        let abandon_n = if free {
            f64::INFINITY
        } else {
            abandon_above / (scale * scale)
        };
        let mut abandoned = false;
        let mut records: Vec<Sums> = if free {
            vec![Sums::default(); self.segments.len()]
        } else {
            Vec::new()
        };
        let restarts = self.restarts(stride);
        // The decimated input is fed through an iterator adapter without copying the record.
        let mut visit = |k: usize, v: f32| -> bool {
            let i = k * stride;
            if i < self.score_from {
                return true;
            }
            if !v.is_finite() {
                finite = false;
            }
            let phi = if nb == 3 {
                [f64::from(self.u[i]), f64::from(v), 1.0]
            } else {
                [f64::from(v), 1.0, 0.0]
            };
            let yn = (self.y[i] - mean) / scale;
            if free {
                let r = restarts.partition_point(|&s| s <= k).saturating_sub(1);
                records[r].add(&phi, yn, nb);
            } else {
                total.add(&phi, yn, nb);
            }
            if let Some((_, basis)) = buffers.as_mut() {
                basis[k_scored] = phi;
            }
            k_scored += 1;
            if k_scored & 127 == 0 && abandon_n.is_finite() {
                if let Some(lin) = solve(&total.g, &total.rhs, nb) {
                    let partial = total.yy - (0..nb).map(|a| lin[a] * total.rhs[a]).sum::<f64>();
                    if partial > abandon_n * (1.0 + 1e-9) {
                        abandoned = true;
                        return false;
                    }
                }
            }
            true
        };
        simulate_iter(&model, decimated, &restarts, &mut visit);
        if !finite || abandoned {
            return bad;
        }
        // Free offsets: the constant leaves the basis, each record centred on its own means.
        let nl = if free {
            for r in &records {
                total.add_centred(r, nb);
            }
            nb - 1
        } else {
            nb
        };
        let Some(mut lin) = solve(&total.g, &total.rhs, nl) else {
            return bad;
        };
        let sse_n: f64 = total.yy - (0..nl).map(|a| lin[a] * total.rhs[a]).sum::<f64>();
        let offsets: Vec<f64> = records.iter().map(|r| r.offset(&lin, nb)).collect();
        if let Some((resid, basis)) = buffers {
            let mut i = self.score_from.div_ceil(stride) * stride;
            for (r, phi) in resid.iter_mut().zip(basis.iter()).take(k_scored) {
                let yn = (self.y[i] - mean) / scale;
                let fitted = if free {
                    let seg = self.segments.partition_point(|&s| s <= i).saturating_sub(1);
                    (0..nl).map(|a| lin[a] * phi[a]).sum::<f64>() + offsets[seg]
                } else {
                    (0..nb).map(|a| lin[a] * phi[a]).sum::<f64>()
                };
                *r = yn - fitted;
                i += stride;
            }
        }
        if free {
            lin[nb - 1] = offsets.first().copied().unwrap_or(0.0);
        }
        let out = Eval {
            sse: sse_n.max(0.0) * scale * scale,
            lin,
        };
        if self.invertible && self.kind != ModelKind::Dynamic {
            match self.identified(theta, &out) {
                Some(set) if self.compensator_accepts(&set) => {}
                _ => return bad,
            }
        }
        out
    }

    fn compensator_accepts(&self, set: &Identified) -> bool {
        let Ok(CoreModel::Static(m)) = set.build() else {
            return false;
        };
        let settings = CompensatorSettings {
            // Only invertibility is asked here: no slew limit.
            limits: piezo_core::Limits::new(
                self.input_range_v.0,
                self.input_range_v.1,
                f32::INFINITY,
            ),
            sample_period_s: 1e-4,
        };
        Compensator::new(m, settings).is_ok()
    }

    /// SSE of θ with its projected linear parameters, on every `stride`-th sample.
    pub fn sse(&self, theta: &[f64], stride: usize) -> f64 {
        self.evaluate(theta, stride, None, f64::INFINITY).sse
    }

    /// [`Problem::sse`], or ∞ as soon as it is certainly above `threshold` \[m²\] (differential
    /// evolution's selection against the parent: the outcome is the same, the rest of a losing
    /// trial's simulation is skipped).
    pub fn sse_unless_above(&self, theta: &[f64], stride: usize, threshold: f64) -> f64 {
        self.evaluate(theta, stride, None, threshold).sse
    }

    /// The parameter set of θ (with its projected linear parameters), in SI.
    pub fn identified(&self, theta: &[f64], e: &Eval) -> Option<Identified> {
        let s = self.y_scale;
        let t = self.sample_period_s as f32;
        match self.kind {
            ModelKind::Symmetric | ModelKind::Asymmetric => Some(Identified::Static {
                bouc_wen: self.bouc_wen_of(theta, 1.0),
                map: StaticMap {
                    k1_m_per_v: (s * e.lin[0]) as f32,
                    k2_m_per_h: (s * e.lin[1]) as f32,
                    offset_m: (s * e.lin[2] + self.y_mean) as f32,
                },
                asymmetry: self.asymmetry_of(theta, 1),
                sample_period_s: t,
                input_range_v: self.input_range_v,
            }),
            ModelKind::Dynamic => {
                // x = x0 + s·G*(u + h); a negative compliance flips the sign of the forcing.
                let compliance = s * e.lin[0];
                let flip = compliance.signum();
                let a = theta[3] * flip;
                let mut bw = self.bouc_wen_of(theta, theta[3]);
                bw.a = a as f32;
                bw.gamma *= flip as f32;
                let k0 = 1.0 / compliance.abs();
                let wn = 2.0 * std::f64::consts::PI * 10f64.powf(theta[4]) / self.sample_period_s;
                let zeta = 10f64.powf(theta[5]);
                Some(Identified::Dynamic {
                    bouc_wen: bw,
                    mechanics: MassSpringDamperParams {
                        mass_kg: (k0 / (wn * wn)) as f32,
                        damping_n_s_per_m: (2.0 * zeta * k0 / wn) as f32,
                        stiffness_n_per_m: k0 as f32,
                        rest_position_m: (s * e.lin[1] + self.y_mean) as f32,
                        force_per_volt_n_per_v: flip as f32,
                    },
                    sample_period_s: t,
                    input_range_v: self.input_range_v,
                })
            }
            ModelKind::Oscillator => None,
        }
    }

    /// The full evaluation of θ on the whole record.
    pub fn eval_full(&self, theta: &[f64]) -> Eval {
        self.evaluate(theta, 1, None, f64::INFINITY)
    }

    /// SSE of a complete parameter set (no projection), as seed 001's GA scores it.
    pub fn sse_direct(&self, set: &Identified) -> f64 {
        self.evaluations.fetch_add(1, Ordering::Relaxed);
        let Ok(model) = set.build() else {
            return f64::INFINITY;
        };
        if self.invertible && !self.compensator_accepts(set) {
            return f64::INFINITY;
        }
        let mut sse = 0.0;
        model.simulate(&self.u, |k, v| {
            if k >= self.score_from {
                let e = f64::from(v) - self.y[k];
                sse += e * e;
            }
        });
        if sse.is_finite() {
            sse
        } else {
            f64::INFINITY
        }
    }

    fn scored(&self) -> usize {
        self.u.len().saturating_sub(self.score_from)
    }

    /// The static model's state and its sensitivities to (β, γ, n, δ, φ) at θ along the whole record
    /// into `work` (record length); false for the dynamic model or an unbuildable θ.
    fn sensitivities(
        &self,
        theta: &[f64],
        work: &mut (Vec<f64>, Vec<[f64; SENSITIVITY_PARAMETERS]>),
    ) -> bool {
        let Some(CoreModel::Static(model)) = self.basis_model(theta, 1) else {
            return false;
        };
        self.evaluations.fetch_add(1, Ordering::Relaxed);
        static_sensitivities(&model, &self.u, &mut work.0, &mut work.1);
        true
    }

    /// ∂(β, γ, n, δ, φ)/∂θ_j of the static models' search coordinates (module doc): with
    /// H = U·10^θ0, b = H^(−n), β = b·(1 + r)/2, γ = b·(1 − r)/2, δ = d·H/(U·T_rec), φ = p·T.
    fn parameter_jacobian(&self, theta: &[f64]) -> [[f64; 8]; SENSITIVITY_PARAMETERS] {
        let mut d = [[0.0; 8]; SENSITIVITY_PARAMETERS];
        let ln10 = std::f64::consts::LN_10;
        let (n, r) = (theta[2], theta[1]);
        let h = self.span() * 10f64.powf(theta[0]);
        let b = h.powf(-n);
        let (db0, db2) = (-n * ln10 * b, -h.ln() * b);
        d[0][0] = 0.5 * (1.0 + r) * db0;
        d[0][1] = 0.5 * b;
        d[0][2] = 0.5 * (1.0 + r) * db2;
        d[1][0] = 0.5 * (1.0 - r) * db0;
        d[1][1] = -0.5 * b;
        d[1][2] = 0.5 * (1.0 - r) * db2;
        d[2][2] = 1.0;
        if self.kind == ModelKind::Asymmetric {
            let duration = self.sample_period_s * self.u.len() as f64;
            let per_d = h / (self.span() * duration);
            d[3][0] = theta[3] * per_d * ln10;
            d[3][3] = per_d;
            if self.fit_shift {
                d[4][4] = self.sample_period_s;
            }
        }
        d
    }

    /// The Gauss–Newton normal equations (JᵀJ, Jᵀr) of the projected residual at θ from the static
    /// model's forward sensitivities ([`piezo_core::sensitivity`]), Kaufman's form of the variable
    /// projection Jacobian: J = −P⊥·C with C_j = k2·∂h/∂θ_j (normalised units) and P⊥ the projector
    /// off the basis (u, h, 1), so JᵀJ = CᵀC − (ΦᵀC)ᵀ·(ΦᵀΦ)⁻¹·(ΦᵀC) and Jᵀr = −Cᵀr (Φᵀr = 0).
    /// `basis` and `resid` are the base point's (from [`Problem::evaluate`]), `lin` its linear
    /// parameters, `sens` the sensitivities from [`Problem::sensitivities`]. `None` when not finite.
    fn sensitivity_normal_equations(
        &self,
        theta: &[f64],
        lin: &[f64; 3],
        basis: &[[f64; 3]],
        resid: &[f64],
        sens: &[[f64; SENSITIVITY_PARAMETERS]],
    ) -> Option<(Vec<Vec<f64>>, Vec<f64>)> {
        let dim = theta.len();
        let dp = self.parameter_jacobian(theta);
        let m = self.scored();
        let mut ctc = vec![vec![0.0f64; dim]; dim];
        let mut ctr = vec![0.0f64; dim];
        let mut phic = [[0.0f64; 8]; 3];
        let mut g = [[0.0f64; 3]; 3];
        for k in 0..m {
            let s = &sens[self.score_from + k];
            let mut c = [0.0f64; 8];
            for j in 0..dim {
                let dh: f64 = (0..SENSITIVITY_PARAMETERS).map(|i| s[i] * dp[i][j]).sum();
                c[j] = lin[1] * dh;
            }
            let phi = &basis[k];
            for a in 0..dim {
                ctr[a] += c[a] * resid[k];
                for b in a..dim {
                    ctc[a][b] += c[a] * c[b];
                }
                for i in 0..3 {
                    phic[i][a] += phi[i] * c[a];
                }
            }
            for i in 0..3 {
                for l in 0..3 {
                    g[i][l] += phi[i] * phi[l];
                }
            }
        }
        let mut jtj = vec![vec![0.0f64; dim]; dim];
        for a in 0..dim {
            let col: [f64; 3] = std::array::from_fn(|i| phic[i][a]);
            let projected = solve(&g, &col, 3)?;
            for b in a..dim {
                let v = ctc[a][b] - (0..3).map(|i| projected[i] * phic[i][b]).sum::<f64>();
                jtj[a][b] = v;
                jtj[b][a] = v;
            }
        }
        let jtr = ctr.iter().map(|v| -v).collect();
        jtj.iter()
            .flatten()
            .chain(&jtr)
            .all(|v| v.is_finite())
            .then_some((jtj, jtr))
    }
}

/// Simulates `model` on `u` from rest, restarting from rest at each index in `restarts`,
/// calling `visit(k, y_k)` until it returns false.
fn simulate_iter(
    model: &CoreModel,
    u: impl Iterator<Item = f32>,
    restarts: &[usize],
    visit: &mut impl FnMut(usize, f32) -> bool,
) {
    // The decimated record is consumed lazily through a small fixed buffer (no per-evaluation copy).
    let mut chunk = [0.0f32; 256];
    let mut model_state = SimState::new(model);
    let mut k = 0;
    let mut filled = 0;
    for v in u {
        chunk[filled] = v;
        filled += 1;
        if filled == chunk.len() {
            if !model_state.run(model, &chunk, &mut k, restarts, visit) {
                return;
            }
            filled = 0;
        }
    }
    model_state.run(model, &chunk[..filled], &mut k, restarts, visit);
}

enum SimState {
    Fresh,
    Static(piezo_core::ModelState),
    Dynamic(piezo_core::DynamicState),
    Oscillator(piezo_core::OscillatorState),
}

impl SimState {
    fn new(_: &CoreModel) -> Self {
        Self::Fresh
    }

    /// Runs a chunk (from rest again at each index in `restarts`); false when `visit` asked to
    /// stop.
    fn run(
        &mut self,
        model: &CoreModel,
        u: &[f32],
        k: &mut usize,
        restarts: &[usize],
        visit: &mut impl FnMut(usize, f32) -> bool,
    ) -> bool {
        for &v in u {
            if *k > 0 && restarts.binary_search(k).is_ok() {
                *self = Self::Fresh;
            }
            if let Self::Fresh = self {
                *self = match model {
                    CoreModel::Static(_) => Self::Static(piezo_core::ModelState::at_rest(v)),
                    CoreModel::Dynamic(m) => Self::Dynamic(m.at_rest(v)),
                    CoreModel::Oscillator(_) => Self::Oscillator(Default::default()),
                };
            }
            let y = match (model, &mut *self) {
                (CoreModel::Static(m), Self::Static(s)) => m.step(s, v),
                (CoreModel::Dynamic(m), Self::Dynamic(s)) => m.step(s, v),
                (CoreModel::Oscillator(m), Self::Oscillator(s)) => m.step(s, v),
                _ => f32::NAN,
            };
            let go_on = visit(*k, y);
            *k += 1;
            if !go_on {
                return false;
            }
        }
        true
    }
}

/// Solves the symmetric positive (semi)definite system g·x = b of size `n` ≤ 3 (the shared
/// Gaussian elimination, [`crate::optimise::linear`], after a tiny ridge). On the stack: an
/// evaluation makes no heap allocation.
fn solve(g: &[[f64; 3]; 3], b: &[f64; 3], n: usize) -> Option<[f64; 3]> {
    let mut a = [[0.0f64; 4]; 3];
    for i in 0..n {
        a[i][..n].copy_from_slice(&g[i][..n]);
        a[i][i] += 1e-12 * g[i][i].abs() + 1e-300;
        a[i][n] = b[i];
    }
    let mut x = [0.0f64; 3];
    linear::solve_augmented(&mut a[..n], &mut x[..n]).then_some(x)
}

/// Progress reporting (an indicatif bar on stderr, hidden when stderr is not a terminal).
pub type Progress = indicatif::ProgressBar;

/// Differential evolution (DE/current-to-best/1/bin, F = 0.6, CR = 0.9, donors distinct, a
/// coordinate past a bound set back between its parent and the bound) on the decimated record,
/// population max(5·dim, 15); stops after `generations`, after 5 generations in a row that gain
/// less than 1e-4 of the best SSE, or once the worst member is within 0.1 % of the best. Returns
/// the best θ and its SSE.
pub fn differential_evolution(
    problem: &Problem,
    bounds: &[(f64, f64)],
    seed: u64,
    generations: usize,
    progress: &Progress,
) -> (Vec<f64>, f64) {
    let stride = problem.u.len().div_ceil(2500).max(1);
    let pop = (5 * bounds.len()).max(15);
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let members = evolution::random_population(bounds, pop, &mut rng);
    let sse: Vec<f64> = members.par_iter().map(|t| problem.sse(t, stride)).collect();
    let population = Population { members, sse };
    let record = |p: &Population| {
        let (theta, sse) = p.best();
        problem.record("de", theta, sse, stride);
    };
    record(&population);
    let settings = Evolution {
        weight: 0.6,
        crossover: Some(0.9),
        distinct_donors: true,
        boundary: Boundary::BounceBack,
        generations,
        stall: Some(Stall {
            gain: 1e-4,
            generations: 5,
        }),
        spread: Some(1e-3),
    };
    settings.run(
        population,
        bounds,
        &mut rng,
        |t, parent| problem.sse_unless_above(t, stride, parent),
        |p| {
            record(p);
            progress.inc(1);
        },
    )
}

/// Levenberg–Marquardt ([`Marquardt`]) on the full record from `theta` (module doc: sensitivity
/// Jacobian for the static models, forward differences for the dynamic one): λ from 1e-3 (÷3 on
/// success down to 1e-9, ×4 on failure, ×10 on a singular system), ten tries per iteration, the
/// Marquardt scale floored at 1e-12; stops when an iteration fails to improve, on a gain ≤ 1e-10,
/// or after two steps in a row that gain less than 0.1·SSE/N.
pub fn levenberg_marquardt(
    problem: &Problem,
    bounds: &[(f64, f64)],
    mut theta: Vec<f64>,
    iterations: usize,
    progress: &Progress,
) -> (Vec<f64>, f64) {
    let dim = theta.len();
    let m = problem.scored();
    // Several records (each from rest) take differences too: the core's sensitivities run from
    // rest over one record.
    let dynamic = problem.kind == ModelKind::Dynamic || problem.segments.len() > 1;
    let buffers = if dynamic { dim + 1 } else { 1 };
    let states = if dynamic { 0 } else { problem.u.len() };
    let mut full = FullRecord {
        problem,
        bounds,
        dynamic,
        resid: vec![vec![0.0; m]; buffers],
        basis: vec![vec![[0.0; 3]; m]; buffers],
        work: (
            vec![0.0; states],
            vec![[0.0; SENSITIVITY_PARAMETERS]; states],
        ),
        progress,
    };
    for (v, &(lo, hi)) in theta.iter_mut().zip(bounds) {
        *v = v.clamp(lo, hi);
    }
    let f = problem.sse(&theta, 1);
    problem.record("lm", &theta, f, 1);
    let settings = Marquardt {
        lambda: 1e-3,
        lambda_min: 1e-9,
        scale_floor: 1e-12,
        tries: 10,
        singular_factor: 10.0,
        iterations,
        min_gain: 1e-10,
        // Stop once two iterations in a row gain less than a tenth of the residual variance
        // (ΔSSE < 0.1·SSE/N): such steps move θ by well under its one-σ uncertainty and are at
        // the level of the f32 simulation's own rounding, so they only chase noise (and the
        // iteration that then fails costs a Jacobian plus up to ten trial points).
        small_steps: Some((0.1 / m.max(1) as f64, 2)),
        predicted_gain: None,
        hold_at_bounds: false,
    };
    settings.run(&mut full, theta, f, bounds)
}

/// The full-record fit of [`levenberg_marquardt`] as a least-squares problem, with its buffers
/// allocated once per run and reused every iteration: the base point's, and every difference
/// column's (dynamic model, several records, or a static model whose sensitivities are not
/// finite) or the state and its sensitivities (static models).
struct FullRecord<'a> {
    problem: &'a Problem,
    bounds: &'a [(f64, f64)],
    /// Forward differences only (dynamic model or several records).
    dynamic: bool,
    resid: Vec<Vec<f64>>,
    basis: Vec<Vec<[f64; 3]>>,
    work: (Vec<f64>, Vec<[f64; SENSITIVITY_PARAMETERS]>),
    progress: &'a Progress,
}

impl LeastSquares for FullRecord<'_> {
    fn sse(&mut self, theta: &[f64], _abandon_above: f64) -> f64 {
        self.problem.sse(theta, 1)
    }

    fn normal_equations(&mut self, theta: &[f64]) -> Option<NormalEquations> {
        let problem = self.problem;
        let normal = if self.dynamic {
            None
        } else {
            // The base point and the sensitivity pass, side by side.
            let (r0, b0) = (&mut self.resid[0], &mut self.basis[0]);
            let work = &mut self.work;
            let (base, have) = rayon::join(
                || problem.evaluate(theta, 1, Some((r0, b0)), f64::INFINITY),
                || problem.sensitivities(theta, work),
            );
            if !base.sse.is_finite() || !have {
                return None;
            }
            problem.sensitivity_normal_equations(
                theta,
                &base.lin,
                &self.basis[0],
                &self.resid[0],
                &self.work.1,
            )
        };
        let (jtj, gradient) = match normal {
            Some(ne) => ne,
            None => {
                // A static model whose sensitivities are not finite falls back to differences too.
                let (dim, m) = (theta.len(), problem.scored());
                self.resid.resize(dim + 1, vec![0.0; m]);
                self.basis.resize(dim + 1, vec![[0.0; 3]; m]);
                difference_normal_equations(
                    problem,
                    theta,
                    self.bounds,
                    &mut self.resid,
                    &mut self.basis,
                )?
            }
        };
        Some(NormalEquations { jtj, gradient })
    }

    fn iteration(&mut self) {
        self.progress.inc(1);
    }

    fn accepted(&mut self, theta: &[f64], sse: f64, gain: f64, lambda: f64) {
        super::trace(|| format!("LM gain {gain:.3e} lambda {lambda:.1e} theta {theta:?}"));
        self.problem.record("lm", theta, sse, 1);
    }
}

/// The normal equations (JᵀJ, Jᵀr) of the projected residual at θ from a forward-difference
/// Jacobian: each column one core simulation (in parallel) into `resid`/`basis` (the base point's
/// first). For the dynamic model, whose sensitivities the core does not give.
fn difference_normal_equations(
    problem: &Problem,
    theta: &[f64],
    bounds: &[(f64, f64)],
    resid: &mut [Vec<f64>],
    basis: &mut [Vec<[f64; 3]>],
) -> Option<(Vec<Vec<f64>>, Vec<f64>)> {
    let dim = theta.len();
    let m = problem.scored();
    let steps: Vec<f64> = theta
        .iter()
        .zip(bounds)
        .map(|(&v, &(_, hi))| {
            let h = 1e-4 * (1.0 + v.abs());
            if v + h > hi {
                -h
            } else {
                h
            }
        })
        .collect();
    let base_f: Vec<f64> = resid
        .par_iter_mut()
        .zip(basis.par_iter_mut())
        .enumerate()
        .map(|(j, (r, b))| {
            let mut t = theta.to_vec();
            if j > 0 {
                t[j - 1] += steps[j - 1];
            }
            problem.evaluate(&t, 1, Some((r, b)), f64::INFINITY).sse
        })
        .collect();
    if base_f.iter().any(|v| !v.is_finite()) {
        return None;
    }
    // J_j = (r_j − r_0)/h_j; normal equations.
    let mut jtj = vec![vec![0.0f64; dim]; dim];
    let mut jtr = vec![0.0f64; dim];
    for k in 0..m {
        let r0 = resid[0][k];
        let mut col = [0.0f64; 8];
        for j in 0..dim {
            col[j] = (resid[j + 1][k] - r0) / steps[j];
        }
        for a in 0..dim {
            jtr[a] += col[a] * r0;
            for b in a..dim {
                jtj[a][b] += col[a] * col[b];
            }
        }
    }
    for a in 0..dim {
        for b in 0..a {
            jtj[a][b] = jtj[b][a];
        }
    }
    Some((jtj, jtr))
}

/// Seed 001's genetic algorithm as published: population 30, 100 generations, crossover 0.7,
/// mutation 0.2, RMS fitness, its search ranges (in its units: mm and mm/V, converted here to m),
/// stop at fitness 1e-7 mm. Real-coded: binary tournament selection, arithmetic crossover of a pair
/// with probability 0.7, uniform re-draw of each gene with probability 0.2, the best individual kept
/// (elitism). `genes` names which of (k1, k2, A, β, γ, n, δ, φ) are free; the others come from `base`.
pub fn genetic_algorithm(
    problem: &Problem,
    base: &[f64; 8],
    free: &[usize],
    seed: u64,
    progress: &Progress,
) -> ([f64; 8], f64) {
    const RANGES: [(f64, f64); 8] = [
        (-1e-3, 1e-3),
        (-1.0, 1.0),
        (-1.0, 1.0),
        (-10.0, 10.0),
        (0.0, 10.0),
        (2.0, 5.0),
        (-1.0, 1.0),
        (-1e-4, 1e-4),
    ];
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let rms = |g: &[f64; 8]| -> f64 {
        let set = ga_set(problem, g);
        let sse = problem.sse_direct(&set);
        (sse / problem.scored().max(1) as f64).sqrt()
    };
    let mut pop: Vec<[f64; 8]> = (0..30)
        .map(|_| {
            let mut g = *base;
            for &j in free {
                g[j] = RANGES[j].0 + (RANGES[j].1 - RANGES[j].0) * uniform(&mut rng);
            }
            g
        })
        .collect();
    let mut fit: Vec<f64> = pop.par_iter().map(rms).collect();
    for _ in 0..100 {
        progress.inc(1);
        let best = (0..30)
            .min_by(|&a, &b| fit[a].total_cmp(&fit[b]))
            .unwrap_or(0);
        if fit[best] <= 1e-10 {
            break;
        }
        let mut next = vec![pop[best]];
        let tournament = |rng: &mut ChaCha8Rng| {
            let a = (rng.next_u64() % 30) as usize;
            let b = (rng.next_u64() % 30) as usize;
            if fit[a] <= fit[b] {
                a
            } else {
                b
            }
        };
        while next.len() < 30 {
            let (p1, p2) = (pop[tournament(&mut rng)], pop[tournament(&mut rng)]);
            let (mut c1, mut c2) = (p1, p2);
            if uniform(&mut rng) < 0.7 {
                let w = uniform(&mut rng);
                for &j in free {
                    c1[j] = w * p1[j] + (1.0 - w) * p2[j];
                    c2[j] = (1.0 - w) * p1[j] + w * p2[j];
                }
            }
            for c in [&mut c1, &mut c2] {
                for &j in free {
                    if uniform(&mut rng) < 0.2 {
                        c[j] = RANGES[j].0 + (RANGES[j].1 - RANGES[j].0) * uniform(&mut rng);
                    }
                }
            }
            next.push(c1);
            if next.len() < 30 {
                next.push(c2);
            }
        }
        let mut nf: Vec<f64> = next[1..].par_iter().map(rms).collect();
        nf.insert(0, fit[best]);
        pop = next;
        fit = nf;
    }
    let best = (0..30)
        .min_by(|&a, &b| fit[a].total_cmp(&fit[b]))
        .unwrap_or(0);
    (pop[best], fit[best])
}

/// The parameter set of a GA genome (k1 \[mm/V\], k2 \[mm\], A, β, γ, n, δ, φ \[s\]) in SI.
pub fn ga_set(problem: &Problem, g: &[f64; 8]) -> Identified {
    Identified::Static {
        bouc_wen: BoucWenParams {
            a: g[2] as f32,
            beta: g[3] as f32,
            gamma: g[4] as f32,
            n: g[5] as f32,
        },
        map: StaticMap {
            k1_m_per_v: (g[0] * 1e-3) as f32,
            k2_m_per_h: (g[1] * 1e-3) as f32,
            offset_m: 0.0,
        },
        asymmetry: Asymmetry {
            delta_per_v_s: g[6] as f32,
            input_shift_s: g[7] as f32,
        },
        sample_period_s: problem.sample_period_s as f32,
        input_range_v: problem.input_range_v,
    }
}
