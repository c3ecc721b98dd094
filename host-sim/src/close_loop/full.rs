//! The model `close-loop` refits: piezo-core's static Bouc-Wen model followed by the core's effect chain
//! ([`piezo_core::effects`]), one per axis, and a Levenberg–Marquardt fit of all its parameters at once.
//!
//! Per axis and command sample j (the chain of `piezo_core::effects`):
//! w = k1·u + k2·h + y0 (h the Bouc-Wen state, A = 1), s = w + e·(u_{j−1} − u_c)² + Σ g_i·x_i (creep),
//! z = M(s) (second-order mode), y(t_j + D) = z_j + drift·t + c·z_other. The simulation is the core's f32
//! code; only the optimiser runs in f64.
//!
//! Parameter vector θ: (β, γ, n, k1, k2, y0), then per added effect: creep (g_i, ln τ_i) per element,
//! drift (rate), delay (D \[s\], used as max(D, 0)), asymmetry (e \[m/V²\]; u_c held), dynamics (ln f, ln ζ),
//! coupling (c). The Jacobian is by forward differences (one core simulation per column, in parallel),
//! steps Marquardt-scaled; a set the core refuses scores an infinite SSE and the step is rejected.

// Small dense linear algebra reads best with index loops.
#![allow(clippy::needless_range_loop)]

use super::diagnose::{EffectInit, EffectKind};
use crate::identify::fit::solve_dense_pub;
use crate::identify::model::bouc_wen;
use piezo_core::effects::{EffectParams, Effects, EffectsState};
use piezo_core::{BoucWenParams, ModelState, StaticMap, StaticModel};
use rayon::prelude::*;

/// One axis's complete model, in SI.
#[derive(Debug, Clone, PartialEq)]
pub struct AxisModel {
    /// Bouc-Wen parameters (A = 1).
    pub bouc_wen: BoucWenParams,
    /// y = k1·u + k2·h + y0.
    pub map: StaticMap,
    /// The effect chain's parameters (all zero: none).
    pub effects: EffectParams,
    /// Effects in the order they were added.
    pub added: Vec<EffectKind>,
    /// Input range the Bouc-Wen set is validated over \[V\].
    pub input_range_v: (f32, f32),
    /// Range of the hysteresis output w (the measured range widened by a quarter each side) \[m\].
    pub w_range_m: (f32, f32),
    /// Sample period \[s\].
    pub sample_period_s: f32,
}

/// A simulation of the whole record.
#[derive(Debug, Clone, Default)]
pub struct Simulation {
    /// Prediction \[m\].
    pub y: Vec<f64>,
    /// Bouc-Wen state.
    pub h: Vec<f64>,
    /// The axis output delayed, before drift and coupling (what the other axis couples to) \[m\].
    pub zd: Vec<f64>,
}

impl AxisModel {
    /// Builds the core objects (validation).
    pub fn build(&self) -> Result<(StaticModel, Effects), String> {
        let h = bouc_wen(self.bouc_wen, self.input_range_v)
            .map_err(|e| format!("Bouc-Wen set refused by piezo-core: {e}"))?;
        let model = StaticModel::new(h, self.map)
            .map_err(|e| format!("static map refused by piezo-core: {e}"))?;
        let effects = Effects::new(self.effects, self.sample_period_s, self.w_range_m)
            .map_err(|e| format!("effects refused by piezo-core: {e}"))?;
        Ok((model, effects))
    }

    /// Simulates the record (the model sees only u, and the other axis's delayed output for coupling).
    pub fn simulate(&self, u: &[f32], other_zd: Option<&[f64]>) -> Result<Simulation, String> {
        let mut out = Simulation {
            y: Vec::with_capacity(u.len()),
            h: Vec::with_capacity(u.len()),
            zd: Vec::with_capacity(u.len()),
        };
        self.simulate_into(u, other_zd, |_, y, h, zd| {
            out.y.push(y);
            out.h.push(h);
            out.zd.push(zd);
        })?;
        Ok(out)
    }

    /// Simulates and calls `visit(k, y, h, zd)` per sample, without allocating.
    pub fn simulate_into(
        &self,
        u: &[f32],
        other_zd: Option<&[f64]>,
        mut visit: impl FnMut(usize, f64, f64, f64),
    ) -> Result<(), String> {
        let (model, effects) = self.build()?;
        let Some(&u0) = u.first() else {
            return Ok(());
        };
        let mut s = ModelState::at_rest(u0);
        let mut es = EffectsState::new();
        let c = f64::from(self.effects.coupling);
        for (k, &v) in u.iter().enumerate() {
            let w = model.step(&mut s, v);
            effects.forward_z(&mut es, v, w);
            let zd = f64::from(effects.delayed_z(&es));
            let other = other_zd.map_or(0.0, |o| o[k]);
            let y = zd + f64::from(effects.drift_m(&es)) + c * other;
            visit(k, y, f64::from(s.hysteresis.h), zd);
        }
        Ok(())
    }

    /// Adds an effect with its screening values (the model keeps its other parameters).
    pub fn with_effect(&self, init: EffectInit) -> Self {
        let mut m = self.clone();
        let e = &mut m.effects;
        let kind = match init {
            EffectInit::Creep {
                gains_m_per_v,
                time_constants_s,
            } => {
                for i in 0..2 {
                    e.creep_gain_m_per_v[i] = gains_m_per_v[i] as f32;
                    e.creep_time_constant_s[i] = time_constants_s[i] as f32;
                }
                EffectKind::Creep
            }
            EffectInit::Drift { rate_m_per_s } => {
                e.drift_rate_m_per_s = rate_m_per_s as f32;
                EffectKind::Drift
            }
            EffectInit::Delay { delay_s } => {
                e.delay_s = delay_s as f32;
                EffectKind::Delay
            }
            EffectInit::Asymmetry {
                coefficient_m_per_v2,
                center_v,
            } => {
                e.even_coefficient_m_per_v2 = coefficient_m_per_v2 as f32;
                e.even_center_v = center_v as f32;
                EffectKind::Asymmetry
            }
            EffectInit::Dynamics {
                frequency_hz,
                damping,
            } => {
                e.mode_frequency_hz = frequency_hz as f32;
                e.mode_damping = damping as f32;
                EffectKind::Dynamics
            }
            EffectInit::Coupling { coefficient } => {
                e.coupling = coefficient as f32;
                EffectKind::Coupling
            }
        };
        if !m.added.contains(&kind) {
            m.added.push(kind);
        }
        m
    }

    /// The model without `kind` (its parameters zeroed; the rest kept).
    pub fn without_effect(&self, kind: EffectKind) -> Self {
        let mut m = self.clone();
        m.added.retain(|k| *k != kind);
        let e = &mut m.effects;
        match kind {
            EffectKind::Creep => {
                e.creep_gain_m_per_v = Default::default();
                e.creep_time_constant_s = Default::default();
            }
            EffectKind::Drift => e.drift_rate_m_per_s = 0.0,
            EffectKind::Delay => e.delay_s = 0.0,
            EffectKind::Asymmetry => {
                e.even_coefficient_m_per_v2 = 0.0;
                e.even_center_v = 0.0;
            }
            EffectKind::Dynamics => {
                e.mode_frequency_hz = 0.0;
                e.mode_damping = 0.0;
            }
            EffectKind::Coupling => e.coupling = 0.0,
        }
        m
    }

    fn creep_elements(&self) -> usize {
        if !self.added.contains(&EffectKind::Creep) {
            return 0;
        }
        self.effects
            .creep_gain_m_per_v
            .iter()
            .take(2)
            .filter(|g| **g != 0.0)
            .count()
            .max(1)
    }

    /// θ and the typical size of each entry (for difference steps).
    pub fn encode(&self) -> (Vec<f64>, Vec<f64>) {
        let b = self.bouc_wen;
        let m = self.map;
        let k = f64::from(m.k1_m_per_v)
            .abs()
            .max(f64::from(m.k2_m_per_h).abs());
        let span = f64::from(self.input_range_v.1 - self.input_range_v.0).max(1e-9);
        let stroke = (k * span).max(1e-12);
        let bg = f64::from(b.beta.abs() + b.gamma.abs()).max(1e-12);
        let mut th = vec![
            f64::from(b.beta),
            f64::from(b.gamma),
            f64::from(b.n),
            f64::from(m.k1_m_per_v),
            f64::from(m.k2_m_per_h),
            f64::from(m.offset_m),
        ];
        let mut typ = vec![bg, bg, 1.0, k, k, stroke];
        let e = &self.effects;
        let ts = f64::from(self.sample_period_s);
        for kind in &self.added {
            match kind {
                EffectKind::Creep => {
                    for i in 0..self.creep_elements() {
                        th.push(f64::from(e.creep_gain_m_per_v[i]));
                        typ.push(0.01 * k);
                        th.push(f64::from(e.creep_time_constant_s[i]).max(1e-9).ln());
                        typ.push(10.0);
                    }
                }
                EffectKind::Drift => {
                    th.push(f64::from(e.drift_rate_m_per_s));
                    typ.push(0.01 * stroke);
                }
                EffectKind::Delay => {
                    th.push(f64::from(e.delay_s));
                    typ.push(10.0 * ts);
                }
                EffectKind::Asymmetry => {
                    th.push(f64::from(e.even_coefficient_m_per_v2));
                    typ.push(0.01 * f64::from(m.k1_m_per_v).abs() / span);
                }
                EffectKind::Dynamics => {
                    th.push(f64::from(e.mode_frequency_hz).max(1e-9).ln());
                    typ.push(10.0);
                    th.push(f64::from(e.mode_damping).max(1e-9).ln());
                    typ.push(10.0);
                }
                EffectKind::Coupling => {
                    th.push(f64::from(e.coupling));
                    typ.push(0.1);
                }
            }
        }
        (th, typ)
    }

    /// The model of θ (inverse of [`Self::encode`]).
    pub fn decode(&self, th: &[f64]) -> Self {
        let mut m = self.clone();
        m.bouc_wen.beta = th[0] as f32;
        m.bouc_wen.gamma = th[1] as f32;
        m.bouc_wen.n = th[2] as f32;
        m.map.k1_m_per_v = th[3] as f32;
        m.map.k2_m_per_h = th[4] as f32;
        m.map.offset_m = th[5] as f32;
        let mut i = 6;
        let creep = self.creep_elements();
        for kind in &self.added {
            let e = &mut m.effects;
            match kind {
                EffectKind::Creep => {
                    for c in 0..creep {
                        e.creep_gain_m_per_v[c] = th[i] as f32;
                        e.creep_time_constant_s[c] = th[i + 1].exp() as f32;
                        i += 2;
                    }
                }
                EffectKind::Drift => {
                    e.drift_rate_m_per_s = th[i] as f32;
                    i += 1;
                }
                EffectKind::Delay => {
                    e.delay_s = th[i].max(0.0) as f32;
                    i += 1;
                }
                EffectKind::Asymmetry => {
                    e.even_coefficient_m_per_v2 = th[i] as f32;
                    i += 1;
                }
                EffectKind::Dynamics => {
                    e.mode_frequency_hz = th[i].exp() as f32;
                    e.mode_damping = th[i + 1].exp() as f32;
                    i += 2;
                }
                EffectKind::Coupling => {
                    e.coupling = th[i] as f32;
                    i += 1;
                }
            }
        }
        m
    }
}

/// The data one axis is fitted on.
pub struct FitData<'a> {
    /// Input (f32, as the core sees it).
    pub u: &'a [f32],
    /// Measured \[m\].
    pub y: &'a [f64],
    /// The other axis's delayed output, for coupling.
    pub other_zd: Option<&'a [f64]>,
    /// First scored sample.
    pub from: usize,
}

/// SSE of a model on the scored samples (∞ when the core refuses it).
pub fn sse(model: &AxisModel, d: &FitData) -> f64 {
    let mut acc = 0.0;
    let ok = model.simulate_into(d.u, d.other_zd, |k, y, _, _| {
        if k >= d.from {
            acc += (d.y[k] - y).powi(2);
        }
    });
    if ok.is_ok() && acc.is_finite() {
        acc
    } else {
        f64::INFINITY
    }
}

/// Levenberg–Marquardt on every parameter of `model`; returns the refitted model, its SSE and the
/// number of model evaluations. `progress(iteration, sse)` is called once per iteration.
pub fn refit(
    model: &AxisModel,
    d: &FitData,
    max_iterations: usize,
    mut progress: impl FnMut(usize, f64),
) -> (AxisModel, f64, u64) {
    let (mut th, typ) = model.encode();
    let p = th.len();
    let n = d.u.len() - d.from;
    let mut evals = 1u64;
    let mut best = sse(model, d);
    if !best.is_finite() {
        return (model.clone(), best, evals);
    }
    let predict = |th: &[f64]| -> Option<Vec<f64>> {
        let m = model.decode(th);
        let mut out = vec![0.0; n];
        m.simulate_into(d.u, d.other_zd, |k, y, _, _| {
            if k >= d.from {
                out[k - d.from] = y;
            }
        })
        .ok()?;
        out.iter().all(|v| v.is_finite()).then_some(out)
    };
    let mut lambda = 1e-3;
    let mut stalls = 0;
    // Difference steps grow tenfold (at most twice) when no step of an iteration improves: with the
    // f32 simulation, too small a step gives a Jacobian of rounding noise.
    let mut step_scale = 1.0;
    let mut it = 0;
    while it < max_iterations {
        it += 1;
        let Some(base) = predict(&th) else { break };
        let steps: Vec<f64> = (0..p)
            .map(|i| {
                let rel = step_scale * if typ[i] >= 10.0 { 1e-3 } else { 1e-4 };
                (rel * th[i].abs()).max(rel * typ[i] * 0.1).max(1e-300)
            })
            .collect();
        let cols: Vec<Option<Vec<f64>>> = (0..p)
            .into_par_iter()
            .map(|i| {
                let mut t = th.clone();
                t[i] += steps[i];
                let y = predict(&t)?;
                Some(
                    y.iter()
                        .zip(&base)
                        .map(|(a, b)| (a - b) / steps[i])
                        .collect(),
                )
            })
            .collect();
        evals += p as u64 + 1;
        let cols: Vec<Vec<f64>> = cols
            .into_iter()
            .map(|c| c.unwrap_or_else(|| vec![0.0; n]))
            .collect();
        let r: Vec<f64> = (0..n).map(|k| d.y[d.from + k] - base[k]).collect();
        let mut jtj = vec![vec![0.0; p]; p];
        let mut jtr = vec![0.0; p];
        for i in 0..p {
            for j in i..p {
                let s: f64 = cols[i].iter().zip(&cols[j]).map(|(a, b)| a * b).sum();
                jtj[i][j] = s;
                jtj[j][i] = s;
            }
            jtr[i] = cols[i].iter().zip(&r).map(|(a, b)| a * b).sum();
        }
        let mut improved = false;
        for _ in 0..12 {
            let mut a: Vec<Vec<f64>> = (0..p)
                .map(|i| {
                    let mut row = jtj[i].clone();
                    row[i] += lambda * jtj[i][i].max(1e-30);
                    row.push(jtr[i]);
                    row
                })
                .collect();
            let Some(delta) = solve_dense_pub(&mut a, p) else {
                lambda *= 4.0;
                continue;
            };
            let trial: Vec<f64> = th.iter().zip(&delta).map(|(a, b)| a + b).collect();
            let s = sse(&model.decode(&trial), d);
            evals += 1;
            if s < best {
                let gain = (best - s) / best;
                th = trial;
                best = s;
                lambda = (lambda / 3.0).max(1e-9);
                improved = true;
                stalls = if gain < 1e-6 { stalls + 1 } else { 0 };
                break;
            }
            lambda *= 4.0;
        }
        progress(it, best);
        if !improved && step_scale < 100.0 {
            step_scale *= 10.0;
            lambda = 1e-3;
            continue;
        }
        if !improved || stalls >= 2 {
            break;
        }
    }
    (model.decode(&th), best, evals)
}
