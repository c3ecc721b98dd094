//! Forward sensitivities of the static model's hysteretic state to its parameters along an input
//! path: exact gradients for Levenberg–Marquardt, one pass instead of one simulation per parameter.
//!
//! The recursion is the one of [`StaticModel::step`] (module doc of [`crate::static_model`]), in f64,
//! with p = (β, γ, n, δ, φ) and A fixed:
//!
//! ```text
//! U[k] = u[k] − (φ/T)·(u[k] − u[k−1])                         shifted input
//! d[k] = (δ·T/2)·sgn(Δu[k])·(u[k−1] + u[k])/2                  half of the δ-term
//! h[k] = clamp( Φ(h[k−1] + d[k]; U[k] − U[k−1]) + d[k] )        (d = 0 for the symmetric model)
//! ```
//!
//! where Φ(h; ΔU) integrates dh/dU = f(h) = A − (β·s·σ + γ)·|h|^n (s = sgn ΔU, σ = sgn h) by classical
//! RK4 over m = max(1, ⌈|ΔU|·J/θ⌉) sub-steps of Δ = ΔU/m, J = n·(β + |γ|)·H^(n−1) at the state
//! bound H (the operator's own sub-step rule, θ = 0.1 unless built coarser; a sub-step that starts
//! within 2·|A·Δ| of h = 0 is cut into 8).
//! The sensitivities S\[k\] = ∂h\[k\]/∂p are that recursion differentiated (discrete forward
//! sensitivities): per RK4 stage a_i = h + c_i·Δ·k_(i−1), k_i = f(a_i),
//!
//! ```text
//! ∂a_i = ∂h + c_i·(∂Δ·k_(i−1) + Δ·∂k_(i−1)),   ∂k_i = f_h(a_i)·∂a_i + f_p(a_i)
//! f_h = −(β·s·σ + γ)·n·|h|^(n−1)·σ,  f_β = −s·σ·|h|^n,  f_γ = −|h|^n,  f_n = −(β·s·σ + γ)·|h|^n·ln|h|
//! ```
//!
//! with ∂Δ = ∂(U\[k\] − U\[k−1\])/m (only φ moves U: ∂U\[k\]/∂φ = −Δu\[k\]/T) and ∂d\[k\]/∂δ = d\[k\]/δ. A state
//! held by the clamp has zero sensitivity. The state itself is integrated alongside in f64, so it
//! matches the model's f32 state to the model's rounding, not bit for bit: these are gradients for an
//! optimiser, the model's outputs still come from [`StaticModel::step`].

use crate::bouc_wen::ZERO_CROSSING_SPLIT;
use crate::math::pow_f64;
use crate::static_model::StaticModel;

/// Number of parameters of [`static_sensitivities`]: β, γ, n, δ \[h per V·s\], φ \[s\].
pub const SENSITIVITY_PARAMETERS: usize = 5;

/// Tangent vector ∂/∂(β, γ, n, δ, φ).
type Tangent = [f64; SENSITIVITY_PARAMETERS];

/// Sub-steps of one increment are capped here (a long increment of a stiff set saturates; its
/// sensitivity is then small and RK4 at J·Δ ≤ 2.7 stays stable).
const MAX_TANGENT_SUBSTEPS: f64 = 1024.0;

/// The Bouc-Wen law in f64.
#[derive(Clone, Copy)]
struct Law {
    a: f64,
    beta: f64,
    gamma: f64,
    n: f64,
}

impl Law {
    /// f, f_h and (f_β, f_γ, f_n) at `h`, input moving in direction `s`.
    #[inline]
    fn eval(&self, h: f64, s: f64) -> (f64, f64, [f64; 3]) {
        let sigma = if h < 0.0 { -1.0 } else { 1.0 };
        let c = self.beta * s * sigma + self.gamma;
        let x = h.abs();
        if x == 0.0 {
            let fh = if self.n == 1.0 { -c * sigma } else { 0.0 };
            return (self.a, fh, [0.0; 3]);
        }
        let p = pow_f64(x, self.n);
        let f = self.a - c * p;
        let fh = -c * self.n * (p / x) * sigma;
        (f, fh, [-s * sigma * p, -p, -c * p * libm::log(x)])
    }
}

/// One RK4 sub-step of length `dh` (tangent `dd`) from `h` (tangent `t`).
#[inline]
fn tangent_rk4(law: &Law, s: f64, h: f64, t: &Tangent, dh: f64, dd: &Tangent) -> (f64, Tangent) {
    let mut k_prev = 0.0;
    let mut tk_prev = [0.0; SENSITIVITY_PARAMETERS];
    let mut sum_k = 0.0;
    let mut sum_tk = [0.0; SENSITIVITY_PARAMETERS];
    for (c, w) in [(0.0, 1.0), (0.5, 2.0), (0.5, 2.0), (1.0, 1.0)] {
        let a = h + c * dh * k_prev;
        let (f, fh, fp) = law.eval(a, s);
        let mut tk = [0.0; SENSITIVITY_PARAMETERS];
        for j in 0..SENSITIVITY_PARAMETERS {
            let ta = t[j] + c * (dd[j] * k_prev + dh * tk_prev[j]);
            tk[j] = fh * ta + if j < 3 { fp[j] } else { 0.0 };
            sum_tk[j] += w * tk[j];
        }
        sum_k += w * f;
        k_prev = f;
        tk_prev = tk;
    }
    let mut t_next = *t;
    for j in 0..SENSITIVITY_PARAMETERS {
        t_next[j] += dd[j] * sum_k / 6.0 + dh * sum_tk[j] / 6.0;
    }
    (h + dh * sum_k / 6.0, t_next)
}

/// Φ(h; ΔU) and its tangent: RK4 sub-steps by the core's rule.
fn tangent_advance(
    law: &Law,
    per_volt: f64,
    h: f64,
    t: &Tangent,
    du: f64,
    t_du: &Tangent,
) -> (f64, Tangent) {
    if du == 0.0 {
        return (h, *t);
    }
    let m = libm::ceil(du.abs() * per_volt).clamp(1.0, MAX_TANGENT_SUBSTEPS);
    let s = if du < 0.0 { -1.0 } else { 1.0 };
    let dh = du / m;
    let dd = t_du.map(|v| v / m);
    let near_zero = 2.0 * (law.a * dh).abs();
    let (mut h, mut t) = (h, *t);
    for _ in 0..m as usize {
        if h.abs() < near_zero {
            let pieces = ZERO_CROSSING_SPLIT as f64;
            let dh_piece = dh / pieces;
            let dd_piece = dd.map(|v| v / pieces);
            for _ in 0..ZERO_CROSSING_SPLIT {
                (h, t) = tangent_rk4(law, s, h, &t, dh_piece, &dd_piece);
            }
        } else {
            (h, t) = tangent_rk4(law, s, h, &t, dh, &dd);
        }
    }
    (h, t)
}

/// The state h\[k\] (f64) and its sensitivities ∂h\[k\]/∂(β, γ, n, δ, φ) for every sample of
/// `input_v`, the model starting at rest at the first input (as [`crate::ModelState::at_rest`]).
/// Inputs are sanitised as [`StaticModel::step`] does. Writes the first `min` of the three lengths.
/// δ is in h per V·s and φ in s, as in [`crate::Asymmetry`]; for a symmetric model the last two
/// columns are the sensitivities to switching those terms on.
pub fn static_sensitivities(
    model: &StaticModel,
    input_v: &[f32],
    h_out: &mut [f64],
    sensitivity_out: &mut [Tangent],
) {
    let bw = model.hysteresis();
    let p = bw.params();
    let law = Law {
        a: f64::from(p.a),
        beta: f64::from(p.beta),
        gamma: f64::from(p.gamma),
        n: f64::from(p.n),
    };
    let bound = f64::from(bw.state_bound()).max(1e-30);
    // The operator's own sub-step rule (so also a coarser `with_substep_target`).
    let per_volt = f64::from(bw.substeps_per_v());
    let period = f64::from(model.sample_period_s());
    let (delta, shift_fraction) = if period > 0.0 {
        let asym = model.asymmetry();
        (
            f64::from(asym.delta_per_v_s),
            f64::from(asym.input_shift_s) / period,
        )
    } else {
        (0.0, 0.0)
    };
    let limit = f64::from(model.state_limit());
    let count = input_v.len().min(h_out.len()).min(sensitivity_out.len());
    let Some(&first) = input_v.first() else {
        return;
    };
    let mut previous = bw.sanitize_input(first, 0.0);
    let mut shifted_prev = f64::from(previous);
    let mut t_shifted_prev = [0.0; SENSITIVITY_PARAMETERS];
    let mut h = 0.0f64;
    let mut t = [0.0; SENSITIVITY_PARAMETERS];
    for k in 0..count {
        let u = bw.sanitize_input(input_v[k], previous);
        let (uf, pf) = (f64::from(u), f64::from(previous));
        let du = uf - pf;
        let shifted = uf - shift_fraction * du;
        let mut t_shifted = [0.0; SENSITIVITY_PARAMETERS];
        if period > 0.0 {
            t_shifted[4] = -du / period;
        }
        let t_du: Tangent = core::array::from_fn(|j| t_shifted[j] - t_shifted_prev[j]);
        // Half of the δ-term and its derivative by δ.
        let sign = if du > 0.0 {
            1.0
        } else if du < 0.0 {
            -1.0
        } else {
            0.0
        };
        let half_per_delta = 0.5 * period * sign * 0.5 * (uf + pf);
        let half = delta * half_per_delta;
        let mut t_in = t;
        t_in[3] += half_per_delta;
        let (moved, mut t_moved) = tangent_advance(
            &law,
            per_volt,
            h + half,
            &t_in,
            shifted - shifted_prev,
            &t_du,
        );
        let mut next = moved + half;
        t_moved[3] += half_per_delta;
        let cap = if delta == 0.0 {
            bound * (1.0 + 1e-5)
        } else {
            limit
        };
        if !next.is_finite() || t_moved.iter().any(|v| !v.is_finite()) {
            next = h;
            t_moved = [0.0; SENSITIVITY_PARAMETERS];
        } else if next.abs() > cap {
            next = next.clamp(-cap, cap);
            t_moved = [0.0; SENSITIVITY_PARAMETERS];
        }
        h = next;
        t = t_moved;
        h_out[k] = h;
        sensitivity_out[k] = t;
        previous = u;
        shifted_prev = shifted;
        t_shifted_prev = t_shifted;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bouc_wen::{BoucWen, BoucWenParams};
    use crate::static_model::{Asymmetry, ModelState, StaticMap};

    const N: usize = 2000;

    fn input() -> [f32; N] {
        // Two periods of a raised cosine 0 → 20 V with a minor loop, sampled at 1 kHz.
        core::array::from_fn(|k| {
            let t = k as f64 / N as f64;
            let v = 10.0 - 10.0 * libm::cos(4.0 * core::f64::consts::PI * t)
                + 1.5 * libm::sin(22.0 * core::f64::consts::PI * t);
            v as f32
        })
    }

    fn model(p: [f64; 5]) -> StaticModel {
        let bw = BoucWen::with_input_range(
            BoucWenParams {
                a: 1.0,
                beta: p[0] as f32,
                gamma: p[1] as f32,
                n: p[2] as f32,
            },
            -5.0,
            25.0,
            crate::STATE_LIMIT,
        )
        .expect("valid set");
        let map = StaticMap {
            k1_m_per_v: 0.0,
            k2_m_per_h: 1.0,
            offset_m: 0.0,
        };
        StaticModel::asymmetric(
            bw,
            map,
            Asymmetry {
                delta_per_v_s: p[3] as f32,
                input_shift_s: p[4] as f32,
            },
            1e-3,
        )
        .expect("valid model")
    }

    fn states(p: [f64; 5], u: &[f32]) -> ([f64; N], [Tangent; N]) {
        let mut h = [0.0; N];
        let mut s = [[0.0; SENSITIVITY_PARAMETERS]; N];
        static_sensitivities(&model(p), u, &mut h, &mut s);
        (h, s)
    }

    #[test]
    fn the_state_follows_the_model_step() {
        let u = input();
        let p = [0.02, -0.005, 1.6, 0.05, 2e-4];
        let (h, _) = states(p, &u);
        let m = model(p);
        let mut state = ModelState::at_rest(u[0]);
        let mut worst = 0.0f64;
        let mut top = 0.0f64;
        for k in 0..N {
            m.step(&mut state, u[k]);
            worst = worst.max((f64::from(state.hysteresis.h) - h[k]).abs());
            top = top.max(h[k].abs());
        }
        assert!(worst < 1e-5 * top, "worst {worst:e} of {top:e}");
    }

    #[test]
    fn sensitivities_match_central_differences_of_the_f64_recursion() {
        let u = input();
        for p in [
            [0.02, -0.005, 1.6, 0.05, 2e-4],
            [0.05, 0.01, 2.7, -0.1, -3e-4],
            [0.03, -0.01, 1.2, 0.0, 0.0],
        ] {
            let (_, s) = states(p, &u);
            for j in 0..SENSITIVITY_PARAMETERS {
                let step = 1e-3 * p[j].abs().max(if j == 3 { 1e-2 } else { 1e-5 });
                let (mut hi, mut lo) = (p, p);
                hi[j] += step;
                lo[j] -= step;
                let (h_hi, _) = states(hi, &u);
                let (h_lo, _) = states(lo, &u);
                let mut err = 0.0f64;
                let mut scale = 0.0f64;
                for k in 0..N {
                    let fd = (h_hi[k] - h_lo[k]) / (2.0 * step);
                    err = err.max((fd - s[k][j]).abs());
                    scale = scale.max(fd.abs());
                }
                // The parameters pass through f32 in the model: the differences carry its rounding.
                assert!(
                    err <= 1e-4 * scale + 1e-12,
                    "p = {p:?}, parameter {j}: error {err:e} of {scale:e}"
                );
            }
        }
    }
}
