//! Exact propagation of a linear time-invariant system with constant forcing over an input hold.
//!
//! Between two breakpoints of zero-order-hold inputs the input u is constant, so u̇ = 0 and a Bouc-Wen
//! state does not move (ḣ = A·u̇ − … = 0). A plant whose remaining dynamics are linear then obeys, on
//! the whole hold [t₀, t₀ + Δ],
//!
//! ẋ = A·x + g,   g constant (it carries the held u and the frozen h),
//!
//! whose solution is, with f₀ = A·x(t₀) + g = ẋ(t₀) the right-hand side at the start of the hold,
//!
//! x(t₀ + Δ) = e^{AΔ}·x(t₀) + Ψ(Δ)·g = x(t₀) + Ψ(Δ)·f₀,   Ψ(Δ) = ∫₀^Δ e^{As} ds = Δ·φ₁(AΔ),
//!
//! (e^{AΔ} = I + Ψ(Δ)·A). So one evaluation of the right-hand side and one matrix–vector product per
//! hold give the state at its end exactly, up to rounding: no step size, no tolerance, no
//! excitation-dependent work. A does not have to be invertible (frozen states are zero rows).
//!
//! **Computing Ψ.** Ψ is the upper-right block of the exponential of the augmented matrix,
//!
//! exp([[AΔ, I], [0, 0]]) = [[e^{AΔ}, φ₁(AΔ)], [0, I]],   Ψ(Δ) = Δ·φ₁(AΔ),
//!
//! evaluated by [`expm`]: a diagonal similarity D by powers of two first (Parlett–Reinsch balancing
//! of AΔ, exact in floating point: mechanical states in m and m/s differ by the modes' ω), then
//! scaling and squaring with the degree-13 Padé approximant (Higham, *SIAM J. Matrix Anal. Appl.* 26,
//! 2005): the norm is divided by 2^s until ‖·‖₁ ≤ θ₁₃ = 5.37, r₁₃ = (V − U)⁻¹(V + U), then squared s
//! times. [`HoldPropagator`] keeps one Ψ per distinct hold length (bit-exact key): a 10 kHz hold
//! grid k/f_s has a handful of distinct differences in f64, so the exponentials are computed a
//! handful of times per run.

use std::collections::HashMap;

/// Row-major n×n product c = a·b.
fn matmul(a: &[f64], b: &[f64], n: usize) -> Vec<f64> {
    let mut c = vec![0.0; n * n];
    for i in 0..n {
        for k in 0..n {
            let aik = a[i * n + k];
            if aik == 0.0 {
                continue;
            }
            let (row, brow) = (&mut c[i * n..(i + 1) * n], &b[k * n..(k + 1) * n]);
            for (cij, bkj) in row.iter_mut().zip(brow) {
                *cij += aik * bkj;
            }
        }
    }
    c
}

/// Largest absolute column sum.
fn norm1(a: &[f64], n: usize) -> f64 {
    (0..n)
        .map(|j| (0..n).map(|i| a[i * n + j].abs()).sum::<f64>())
        .fold(0.0, f64::max)
}

/// Solves a·x = b for the n×n row-major `a` and n×m row-major `b` (Gaussian elimination with
/// partial pivoting); `b` is overwritten with x.
fn solve(mut a: Vec<f64>, b: &mut [f64], n: usize, m: usize) {
    for col in 0..n {
        let p = (col..n)
            .max_by(|&r, &s| a[r * n + col].abs().total_cmp(&a[s * n + col].abs()))
            .unwrap_or(col);
        if p != col {
            for j in 0..n {
                a.swap(col * n + j, p * n + j);
            }
            for j in 0..m {
                b.swap(col * m + j, p * m + j);
            }
        }
        let d = a[col * n + col];
        for r in col + 1..n {
            let f = a[r * n + col] / d;
            if f == 0.0 {
                continue;
            }
            for j in col..n {
                a[r * n + j] -= f * a[col * n + j];
            }
            for j in 0..m {
                b[r * m + j] -= f * b[col * m + j];
            }
        }
    }
    for col in (0..n).rev() {
        let d = a[col * n + col];
        for j in 0..m {
            let mut s = b[col * m + j];
            for k in col + 1..n {
                s -= a[col * n + k] * b[k * m + j];
            }
            b[col * m + j] = s / d;
        }
    }
}

/// Parlett–Reinsch balancing by powers of two: returns d with D⁻¹·a·D (d on the diagonal of D)
/// written into `a`. Rows or columns without off-diagonal entries are left alone.
fn balance(a: &mut [f64], n: usize) -> Vec<f64> {
    let mut d = vec![1.0; n];
    for _ in 0..100 {
        let mut done = true;
        for i in 0..n {
            let mut c = 0.0;
            let mut r = 0.0;
            for j in (0..n).filter(|&j| j != i) {
                c += a[j * n + i].abs();
                r += a[i * n + j].abs();
            }
            if c == 0.0 || r == 0.0 {
                continue;
            }
            let s = c + r;
            let mut f = 1.0;
            let mut g = r / 2.0;
            while c < g {
                f *= 2.0;
                c *= 4.0;
            }
            g = r * 2.0;
            while c > g {
                f /= 2.0;
                c /= 4.0;
            }
            if (c + r) / f < 0.95 * s {
                done = false;
                d[i] *= f;
                for j in 0..n {
                    a[i * n + j] /= f;
                    a[j * n + i] *= f;
                }
            }
        }
        if done {
            break;
        }
    }
    d
}

/// e^a of the n×n row-major `a`: balancing, then scaling and squaring with the degree-13 Padé
/// approximant (Higham 2005).
pub fn expm(a: &[f64], n: usize) -> Vec<f64> {
    assert_eq!(a.len(), n * n, "expm: matrix is not n×n");
    let mut b = a.to_vec();
    let d = balance(&mut b, n);
    const THETA13: f64 = 5.371_920_351_148_152;
    const P: [f64; 14] = [
        64_764_752_532_480_000.0,
        32_382_376_266_240_000.0,
        7_771_770_303_897_600.0,
        1_187_353_796_428_800.0,
        129_060_195_264_000.0,
        10_559_470_521_600.0,
        670_442_572_800.0,
        33_522_128_640.0,
        1_323_241_920.0,
        40_840_800.0,
        960_960.0,
        16_380.0,
        182.0,
        1.0,
    ];
    let nrm = norm1(&b, n);
    let s = if nrm > THETA13 {
        (nrm / THETA13).log2().ceil() as i32
    } else {
        0
    };
    let scale = 2f64.powi(-s);
    b.iter_mut().for_each(|v| *v *= scale);
    let a2 = matmul(&b, &b, n);
    let a4 = matmul(&a2, &a2, n);
    let a6 = matmul(&a4, &a2, n);
    let lin = |c6: f64, c4: f64, c2: f64, c0: f64| {
        let mut m = vec![0.0; n * n];
        for i in 0..n * n {
            m[i] = c6 * a6[i] + c4 * a4[i] + c2 * a2[i];
        }
        for i in 0..n {
            m[i * n + i] += c0;
        }
        m
    };
    // U = A·[A6·(b13·A6 + b11·A4 + b9·A2) + b7·A6 + b5·A4 + b3·A2 + b1·I]
    let u_inner = matmul(&a6, &lin(P[13], P[11], P[9], 0.0), n);
    let u_tail = lin(P[7], P[5], P[3], P[1]);
    let u_sum: Vec<f64> = u_inner.iter().zip(&u_tail).map(|(x, y)| x + y).collect();
    let u = matmul(&b, &u_sum, n);
    // V = A6·(b12·A6 + b10·A4 + b8·A2) + b6·A6 + b4·A4 + b2·A2 + b0·I
    let v_inner = matmul(&a6, &lin(P[12], P[10], P[8], 0.0), n);
    let v_tail = lin(P[6], P[4], P[2], P[0]);
    let v: Vec<f64> = v_inner.iter().zip(&v_tail).map(|(x, y)| x + y).collect();
    let vm_u: Vec<f64> = v.iter().zip(&u).map(|(x, y)| x - y).collect();
    let mut r: Vec<f64> = v.iter().zip(&u).map(|(x, y)| x + y).collect();
    solve(vm_u, &mut r, n, n);
    for _ in 0..s {
        r = matmul(&r, &r, n);
    }
    // Undo the similarity: e^a = D·e^b·D⁻¹.
    for i in 0..n {
        for j in 0..n {
            r[i * n + j] *= d[i] / d[j];
        }
    }
    r
}

/// Ψ(Δ) = ∫₀^Δ e^{As} ds of the n×n row-major `a`, from the exponential of [[AΔ, I], [0, 0]].
pub fn hold_integral(a: &[f64], n: usize, dt: f64) -> Vec<f64> {
    assert_eq!(a.len(), n * n, "hold_integral: matrix is not n×n");
    let m = 2 * n;
    let mut aug = vec![0.0; m * m];
    for i in 0..n {
        for j in 0..n {
            aug[i * m + j] = a[i * n + j] * dt;
        }
        aug[i * m + n + i] = 1.0;
    }
    let e = expm(&aug, m);
    let mut psi = vec![0.0; n * n];
    for i in 0..n {
        for j in 0..n {
            psi[i * n + j] = e[i * m + n + j] * dt;
        }
    }
    psi
}

/// Exact propagation over holds of ẋ = A·x + g (g constant per hold): x ← x + Ψ(Δ)·ẋ(t₀), with
/// Ψ(Δ) computed once per distinct hold length Δ and kept.
#[derive(Debug, Clone)]
pub struct HoldPropagator {
    a: Vec<f64>,
    n: usize,
    cache: HashMap<u64, Vec<f64>>,
    computed: u64,
    holds: u64,
}

/// Distinct hold lengths kept before the cache is emptied (bounds memory on irregular grids).
const CACHE_LIMIT: usize = 256;

impl HoldPropagator {
    /// For the n×n row-major state matrix `a`.
    pub fn new(a: Vec<f64>, n: usize) -> Self {
        assert_eq!(a.len(), n * n, "HoldPropagator: matrix is not n×n");
        Self {
            a,
            n,
            cache: HashMap::new(),
            computed: 0,
            holds: 0,
        }
    }

    /// Moves `x` over a hold of length `dt` (> 0) given the right-hand side `dx0` = ẋ at its start.
    pub fn advance(&mut self, x: &mut [f64], dx0: &[f64], dt: f64) {
        let n = self.n;
        if !self.cache.contains_key(&dt.to_bits()) {
            if self.cache.len() >= CACHE_LIMIT {
                self.cache.clear();
            }
            self.cache
                .insert(dt.to_bits(), hold_integral(&self.a, n, dt));
            self.computed += 1;
        }
        let psi = &self.cache[&dt.to_bits()];
        for (xi, row) in x.iter_mut().zip(psi.chunks_exact(n)) {
            *xi += row.iter().zip(dx0).map(|(p, f)| p * f).sum::<f64>();
        }
        self.holds += 1;
    }

    /// (holds propagated, exponentials computed).
    pub fn counts(&self) -> (u64, u64) {
        (self.holds, self.computed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn expm_of_a_damped_oscillator_matches_closed_form() {
        // ẍ + 2ζω·ẋ + ω²·x = 0 with ω·t = 30 (a stiff case: 23 squarings without balancing).
        let (w, z, t) = (2.0 * std::f64::consts::PI * 45e3, 0.3, 1e-4);
        let a = [0.0, t, -w * w * t, -2.0 * z * w * t];
        let e = expm(&a, 2);
        let wd = w * (1.0 - z * z).sqrt();
        let decay = (-z * w * t).exp();
        let (c, s) = ((wd * t).cos(), (wd * t).sin());
        let exact = [
            decay * (c + z * w / wd * s),
            decay * s / wd,
            -decay * w * w / wd * s,
            decay * (c - z * w / wd * s),
        ];
        let scale = [1.0, 1.0 / w, w, 1.0];
        for i in 0..4 {
            assert!(
                ((e[i] - exact[i]) / scale[i]).abs() < 1e-13 * decay.max(1e-3),
                "{i}: {} vs {}",
                e[i],
                exact[i]
            );
        }
    }

    #[test]
    fn hold_integral_of_a_scalar_decay_and_a_frozen_state() {
        // ẋ = −x/τ + g and a frozen state (zero row): Ψ = τ(1 − e^{−Δ/τ}) and Δ.
        let tau = 0.1;
        let a = [-1.0 / tau, 0.0, 0.0, 0.0];
        let psi = hold_integral(&a, 2, 1e-4);
        let exact = -tau * (-1e-4f64 / tau).exp_m1();
        assert!((psi[0] - exact).abs() < 1e-19, "{} vs {exact}", psi[0]);
        assert!((psi[3] - 1e-4).abs() < 1e-19);
        assert_eq!(psi[1], 0.0);
        assert_eq!(psi[2], 0.0);
    }

    #[test]
    fn two_half_holds_equal_one_hold() {
        // Ψ(2Δ) = Ψ(Δ) + e^{AΔ}·Ψ(Δ), e^{AΔ} = I + Ψ(Δ)·A: the propagator composes.
        let w = 2.0 * std::f64::consts::PI * 3e3;
        let a = vec![0.0, 1.0, -w * w, -0.2 * w];
        let p1 = hold_integral(&a, 2, 5e-5);
        let p2 = hold_integral(&a, 2, 1e-4);
        let e1 = {
            let mut m = matmul(&p1, &a, 2);
            m[0] += 1.0;
            m[3] += 1.0;
            m
        };
        let ep = matmul(&e1, &p1, 2);
        for i in 0..4 {
            let c = p1[i] + ep[i];
            assert!(
                (c - p2[i]).abs() <= 1e-12 * p2[i].abs().max(1e-4 / w),
                "{i}"
            );
        }
    }
}
