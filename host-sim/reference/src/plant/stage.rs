//! Asymmetric piezo stage of seed 001 (MODELS.md §2), Cases I–III of its genetic-algorithm fit.
//!
//! y = k1·u + k2·h (paper: y in mm; here y is returned in **metres**, y_m = 1e-3·(k1·u + k2·h)),
//! with the asymmetric Bouc-Wen reading of MODELS.md:
//!
//! U(t) = u(t − φ)  (φ a **time shift in seconds**),
//! ḣ = A·U̇ − β·|U̇|·|h|^(n−1)·h − γ·U̇·|h|^n + δ·u·sgn(u̇)   (δ term added to ḣ literally, time in s).
//!
//! Case I: k1 = −3.51711e-4 mm/V, k2 = −1.94566e-3 mm, A = −7.02182e-2, β = 4.45753, γ = 3.49259,
//! n = 3.05869; Case II adds δ = −1.95e-2; Case III adds φ = 5.16e-7 s. Input of the paper:
//! u = 10 − 10·cos(4πt) V, N = 10 000 samples over 1 s. The set is of the bounded class (|h| ≤ ≈ 0.43
//! without the δ term). For zero-order-hold inputs the jump of U is applied at the jump of u (φ is far
//! shorter than any sample period). sgn(0) = 0.
//!
//! Two rate dependences the paper does not have may be switched on (effects `dielectric-lag` and
//! `rate-bouc-wen`, as on the XY stage): the operator driven by a first-order lag of the input,
//! τ_v·v̇ = U − v (state `[h, v]`; the linear term k1·u follows u at once), and its gain growing
//! with its input's speed, A·(1 + |v̇|/ṙ₀)·v̇ in place of A·v̇.

use super::{drive, InputAt, Plant, PlantError};
use crate::bouc_wen::BoucWen;

/// Which identified parameter set.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StageCase {
    /// Six standard parameters.
    I,
    /// With δ.
    II,
    /// With δ and φ.
    III,
}

/// The seed 001 stage. State: `[h]`.
#[derive(Debug, Clone, PartialEq)]
pub struct AsymmetricStage {
    /// k1, mm/V (paper units).
    pub k1_mm_per_v: f64,
    /// k2, mm per unit h.
    pub k2_mm: f64,
    /// Bouc-Wen parameters.
    pub hysteresis: BoucWen,
    /// δ, 1/(V·s)·V… (ḣ units per volt).
    pub asymmetry_delta: f64,
    /// φ, s.
    pub input_shift_s: f64,
    /// Electrostrictive coefficient e, 1/V (effect).
    pub electrostriction_per_v: f64,
    /// τ_v of the operator's input lag, s (effect `dielectric-lag`; 0: none).
    pub dielectric_lag_s: f64,
    /// ṙ₀ of the operator's rate-dependent gain A·(1 + |v̇|/ṙ₀), V/s (effect `rate-bouc-wen`;
    /// 0: none).
    pub hysteresis_rate_scale_v_per_s: f64,
}

impl AsymmetricStage {
    /// Parameters of `case` from the paper's table.
    pub fn new(case: StageCase) -> Self {
        let (delta, phi) = match case {
            StageCase::I => (0.0, 0.0),
            StageCase::II => (-1.95e-2, 0.0),
            StageCase::III => (-1.95e-2, 5.16e-7),
        };
        Self {
            k1_mm_per_v: -3.51711e-4,
            k2_mm: -1.94566e-3,
            hysteresis: BoucWen {
                a: -7.02182e-2,
                beta: 4.45753,
                gamma: 3.49259,
                n: 3.05869,
            },
            asymmetry_delta: delta,
            input_shift_s: phi,
            electrostriction_per_v: 0.0,
            dielectric_lag_s: 0.0,
            hysteresis_rate_scale_v_per_s: 0.0,
        }
    }
}

fn sgn(v: f64) -> f64 {
    if v > 0.0 {
        1.0
    } else if v < 0.0 {
        -1.0
    } else {
        0.0
    }
}

impl Plant for AsymmetricStage {
    fn name(&self) -> &'static str {
        "stage"
    }
    fn input_names(&self) -> &'static [&'static str] {
        &["u_V"]
    }
    fn output_names(&self) -> &'static [&'static str] {
        &["y_m"]
    }
    fn state_dim(&self) -> usize {
        if self.dielectric_lag_s > 0.0 {
            2
        } else {
            1
        }
    }
    fn initial_state(&self, x: &mut [f64]) {
        x.fill(0.0);
    }
    fn rhs(&self, t: f64, x: &[f64], input: &dyn InputAt, dx: &mut [f64]) {
        let (u, du) = input.input(0, t);
        let (u_shifted, du_shifted) = if self.input_shift_s == 0.0 {
            (u, du)
        } else {
            input.input(0, (t - self.input_shift_s).max(0.0))
        };
        // The operator's input rate: U̇, or v̇ = (U − v)/τ_v behind the lag.
        let rate = if self.dielectric_lag_s > 0.0 {
            let dv = (u_shifted - x[1]) / self.dielectric_lag_s;
            dx[1] = dv;
            dv
        } else {
            du_shifted
        };
        dx[0] =
            self.hysteresis
                .rate_with_speed_gain(x[0], rate, self.hysteresis_rate_scale_v_per_s)
                + self.asymmetry_delta * u * sgn(du);
    }
    fn input_jump(&self, x: &mut [f64], _channel: usize, u_from: f64, u_to: f64) {
        if self.dielectric_lag_s > 0.0 {
            // v is continuous: a step moves h only as v follows it.
            return;
        }
        x[0] = self.hysteresis.jump(x[0], u_from, u_to);
    }
    fn output(&self, x: &[f64], u: &[f64], y: &mut [f64]) {
        let (ud, _) = drive(u[0], 0.0, self.electrostriction_per_v);
        y[0] = 1e-3 * (self.k1_mm_per_v * ud + self.k2_mm * x[0]);
    }
    fn free_displacement(&self, x: &[f64], u: &[f64], out: &mut [f64]) {
        self.output(x, u, out);
    }
    fn default_sample_rate_hz(&self) -> f64 {
        10_000.0
    }
    fn check_input_span(&self, _u_min_v: f64, _u_max_v: f64) -> Result<(), PlantError> {
        Ok(()) // bounded class
    }
    fn set_electrostriction(&mut self, per_v: f64) {
        self.electrostriction_per_v = per_v;
    }
}
