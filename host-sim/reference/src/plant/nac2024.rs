//! Noliac NAC2024 multilayer plate actuator (seed 000, eq. 1–2, Table 1; MODELS.md §1).
//!
//! m0·ẍ + c0·ẋ + k0·(x − x0) = k1·u + h,  ḣ = A·u̇ − β·|u̇|·|h|^(n−1)·h − γ·u̇·|h|^n,
//! with m0 = 3.419e-4 kg, c0 = 491.03 kg/s, k0 = 3.725e8 N/m, k1 = 1 N/V, A = 0.192 N/V, β = 0.034,
//! γ = −0.0463, n = 1.419 (h in newtons). Output x in metres (static gain k1/k0 ≈ 2.68 nm/V,
//! f_n ≈ 166 kHz, ζ ≈ 0.69), sampled at 2.56 MHz like the paper's laser vibrometer.
//!
//! **Validity.** The published set has β + γ = −0.0123 < 0, so h grows without bound on loading
//! (|h| ≈ 2.5 N for a 9.7 V sine, ≈ 266 N at 50 V, overflow at 100 V). This plant therefore refuses inputs
//! whose peak-to-peak span exceeds [`Nac2024::max_input_span_v`] (default 25 V, which keeps |h| below
//! about 10 N, comparable to the k1·u drive) and stops a simulation with an error when |h| passes
//! [`Nac2024::hysteresis_limit_n`] (default 20 N).
//!
//! **Second mode (effect).** Optional second resonance: a modal displacement x2 with
//! ẍ2 + 2ζ2ω2ẋ2 + ω2²·x2 = ω2²·r2·(k1·u + h)/k0; the output is x + x2. The paper attributes its loss of
//! fit above 140 kHz to the limits of a second-order model; this is the effect a single-mode model lacks.

use super::{drive, HeldLinear, InputAt, Plant, PlantError};
use crate::bouc_wen::BoucWen;

/// A second resonance mode added to the output.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SecondMode {
    /// Natural frequency, Hz.
    pub frequency_hz: f64,
    /// Damping ratio.
    pub damping_ratio: f64,
    /// Static participation r2 (fraction of the first mode's static displacement).
    pub participation: f64,
}

impl Default for SecondMode {
    fn default() -> Self {
        Self {
            frequency_hz: 480e3,
            damping_ratio: 0.05,
            participation: 0.05,
        }
    }
}

/// The NAC2024 plant. States: [x m, ẋ m/s, h N, x2 m, ẋ2 m/s].
#[derive(Debug, Clone, PartialEq)]
pub struct Nac2024 {
    /// m0, kg.
    pub mass_kg: f64,
    /// c0, kg/s.
    pub damping_kg_per_s: f64,
    /// k0, N/m.
    pub stiffness_n_per_m: f64,
    /// k1, N/V.
    pub input_gain_n_per_v: f64,
    /// x0, m.
    pub rest_position_m: f64,
    /// Bouc-Wen parameters (h in N).
    pub hysteresis: BoucWen,
    /// Largest accepted peak-to-peak input span, V.
    pub max_input_span_v: f64,
    /// |h| at which a simulation stops with an error, N.
    pub hysteresis_limit_n: f64,
    /// Optional second resonance mode (effect).
    pub second_mode: Option<SecondMode>,
    /// Electrostrictive coefficient e, 1/V (effect).
    pub electrostriction_per_v: f64,
}

impl Nac2024 {
    /// Table 1 of seed 000.
    pub fn published() -> Self {
        Self {
            mass_kg: 3.419e-4,
            damping_kg_per_s: 491.03,
            stiffness_n_per_m: 3.725e8,
            input_gain_n_per_v: 1.0,
            rest_position_m: 0.0,
            hysteresis: BoucWen {
                a: 0.192,
                beta: 0.034,
                gamma: -0.0463,
                n: 1.419,
            },
            max_input_span_v: 25.0,
            hysteresis_limit_n: 20.0,
            second_mode: None,
            electrostriction_per_v: 0.0,
        }
    }
}

impl Plant for Nac2024 {
    fn name(&self) -> &'static str {
        "nac2024"
    }
    fn input_names(&self) -> &'static [&'static str] {
        &["u_V"]
    }
    fn output_names(&self) -> &'static [&'static str] {
        &["y_m"]
    }
    fn state_dim(&self) -> usize {
        5
    }
    fn initial_state(&self, x: &mut [f64]) {
        x.fill(0.0);
        x[0] = self.rest_position_m;
    }
    fn rhs(&self, t: f64, x: &[f64], input: &dyn InputAt, dx: &mut [f64]) {
        let (u, du) = input.input(0, t);
        let (ud, _) = drive(u, du, self.electrostriction_per_v);
        let force = self.input_gain_n_per_v * ud + x[2];
        dx[0] = x[1];
        dx[1] = (force
            - self.damping_kg_per_s * x[1]
            - self.stiffness_n_per_m * (x[0] - self.rest_position_m))
            / self.mass_kg;
        dx[2] = self.hysteresis.rate(x[2], du);
        match self.second_mode {
            Some(m) => {
                let w = 2.0 * std::f64::consts::PI * m.frequency_hz;
                dx[3] = x[4];
                dx[4] = w * w * (m.participation * force / self.stiffness_n_per_m - x[3])
                    - 2.0 * m.damping_ratio * w * x[4];
            }
            None => {
                dx[3] = 0.0;
                dx[4] = 0.0;
            }
        }
    }
    fn input_jump(&self, x: &mut [f64], _channel: usize, u_from: f64, u_to: f64) {
        x[2] = self.hysteresis.jump(x[2], u_from, u_to);
    }
    fn output(&self, x: &[f64], _u: &[f64], y: &mut [f64]) {
        y[0] = x[0] + x[3];
    }
    fn free_displacement(&self, x: &[f64], u: &[f64], out: &mut [f64]) {
        let (ud, _) = drive(u[0], 0.0, self.electrostriction_per_v);
        out[0] = (self.input_gain_n_per_v * ud + x[2]) / self.stiffness_n_per_m;
    }
    fn default_sample_rate_hz(&self) -> f64 {
        2.56e6
    }
    fn check_input_span(&self, u_min_v: f64, u_max_v: f64) -> Result<(), PlantError> {
        let span_v = (u_max_v - u_min_v).max(u_max_v.abs()).max(u_min_v.abs());
        if span_v > self.max_input_span_v {
            return Err(PlantError::InputOutOfRange {
                plant: "nac2024",
                span_v,
                max_span_v: self.max_input_span_v,
                reason: "the published Bouc-Wen set has beta + gamma < 0 and h grows without bound on loading",
            });
        }
        Ok(())
    }
    fn check_state(&self, x: &[f64]) -> Result<(), PlantError> {
        if !(x[2].abs() <= self.hysteresis_limit_n) {
            return Err(PlantError::HysteresisOutOfRange {
                plant: "nac2024",
                value: x[2].abs(),
                limit: self.hysteresis_limit_n,
            });
        }
        Ok(())
    }
    /// With u held the force k1·u + h is constant (h frozen): ẋ = v, v̇ = (force − c0·v − k0·(x − x0))/m0
    /// and, with the second mode, ẍ2 = ω2²·(r2·force/k0 − x2) − 2ζ2ω2·ẋ2; the free displacement
    /// (k1·u + h)/k0 is constant (F = 0).
    fn held_input_linear(&self) -> Option<HeldLinear> {
        let n = self.state_dim();
        let mut a = vec![0.0; n * n];
        a[1] = 1.0;
        a[n] = -self.stiffness_n_per_m / self.mass_kg;
        a[n + 1] = -self.damping_kg_per_s / self.mass_kg;
        if let Some(m) = self.second_mode {
            let w = 2.0 * std::f64::consts::PI * m.frequency_hz;
            a[3 * n + 4] = 1.0;
            a[4 * n + 3] = -w * w;
            a[4 * n + 4] = -2.0 * m.damping_ratio * w;
        }
        Some(HeldLinear {
            a,
            free_displacement: vec![0.0; n],
        })
    }
    fn set_electrostriction(&mut self, per_v: f64) {
        self.electrostriction_per_v = per_v;
    }
}
