//! A bipolar piezo stack actuator whose rate dependence is a spread of dielectric relaxation times,
//! with one structural mode near 740 Hz: the stand-in for an actuator none of the core's
//! rate-dependent forms describes exactly.
//!
//! **Dielectric relaxation** (a discrete relaxation spectrum, after the Debye sum of relaxor and
//! soft-PZT ceramics: the permittivity ε(ω) = ε∞ + Σ Δεᵢ/(1 + jωτᵢ)). The domain switching that
//! makes the hysteresis follows the stack voltage u through K first-order relaxations,
//!
//! τᵢ·v̇ᵢ = u − vᵢ (i = 1..K),  v = Σ wᵢ·vᵢ  (Σ wᵢ = 1, at rest v = u),
//!
//! and the Bouc-Wen operator (n = 1, h in volts) is driven by v:
//! ḣ = α·v̇ − β·|v̇|·h − γ·v̇·|h|. The linear piezo strain follows u at once, so the stack's free
//! elongation is η = d·(u − h). Its transfer from u to v, Σ wᵢ/(1 + sτᵢ), is not one first-order
//! lag: with τ = 0.2, 1 and 5 ms (weights 0.4, 0.35, 0.25) its phase lag grows about linearly in
//! log f (10°, 15°, 23° at 20, 40, 100 Hz) while its gain falls (0.94, 0.86, 0.72). Since the
//! hysteretic part −d·h lags while d·u does not, the output's loop opening at u = 0 *falls* as
//! the rate rises (3.8, 2.8, 2.2, 0.9 µm at 1, 20, 40, 100 Hz: `tests/plants.rs`), the loop
//! tilting instead; a stack whose whole strain relaxes would widen its loops.
//!
//! **Mode** (force-driven, the stack pushing a mass on its own stiffness): the measured tip
//! displacement z obeys z̈ + 2ζω·ż + ω²·(z − η) = 0, f = ω/2π = 740 Hz, ζ = 0.03 (a ≈ 740 Hz ring
//! after steps).
//!
//! **Values.** Hysteresis of the XY stage's x stack (α = 0.18522, β = 0.029586, γ = −0.020710, the
//! bounded class: |h| ≤ α/(β + γ) ≈ 20.9 V); d chosen so that the first sweep −90 → +90 V (from
//! the h a first loading to −90 V leaves) spans 35 µm; valid for |u| ≤ 100 V.
//!
//! State: `[z, ż, h, v₁, …, v_K]`. A voltage step moves no state at once (v is continuous), so
//! [`Plant::input_jump`] does nothing and the plant is integrated by the adaptive Dormand–Prince
//! pair over holds too.

use super::{drive, InputAt, Plant, PlantError};
use crate::bouc_wen::BoucWen;

/// Largest relaxation terms.
pub const MAX_RELAXATIONS: usize = 4;

/// The bipolar stack. Build with [`BipolarStack::new`] (checked) or [`Default`].
#[derive(Debug, Clone, PartialEq)]
pub struct BipolarStack {
    relaxation_times_s: Vec<f64>,
    relaxation_weights: Vec<f64>,
    mode_frequency_hz: f64,
    mode_damping: f64,
    hysteresis: BoucWen,
    d_m_per_v: f64,
    /// Electrostrictive coefficient e, 1/V (effect).
    pub electrostriction_per_v: f64,
}

impl Default for BipolarStack {
    fn default() -> Self {
        // Valid by construction (the `default_is_valid` test).
        Self::new(
            &[0.2e-3, 1e-3, 5e-3],
            &[0.4, 0.35, 0.25],
            740.0,
            0.03,
            35e-6,
        )
        .unwrap_or_else(|_| unreachable!("the default parameters are valid"))
    }
}

impl BipolarStack {
    /// Checks and builds: 1 to 4 (`MAX_RELAXATIONS`) positive relaxation times with positive weights
    /// summing to 1 (within 1e-9), a positive mode frequency and damping ratio in (0, 1), and a
    /// positive span (m) of the first −90 → +90 V sweep.
    pub fn new(
        times_s: &[f64],
        weights: &[f64],
        mode_frequency_hz: f64,
        mode_damping: f64,
        span_m: f64,
    ) -> Result<Self, PlantError> {
        if times_s.is_empty() || times_s.len() > MAX_RELAXATIONS || times_s.len() != weights.len() {
            return Err(PlantError::BadParameter {
                name: "relaxation terms (1..=4 times with one weight each)",
                value: times_s.len() as f64,
            });
        }
        for &t in times_s {
            if !(t > 0.0 && t.is_finite()) {
                return Err(PlantError::BadParameter {
                    name: "relaxation_time_s",
                    value: t,
                });
            }
        }
        for &w in weights {
            if !(w > 0.0 && w.is_finite()) {
                return Err(PlantError::BadParameter {
                    name: "relaxation_weight",
                    value: w,
                });
            }
        }
        let sum: f64 = weights.iter().sum();
        if (sum - 1.0).abs() > 1e-9 {
            return Err(PlantError::BadParameter {
                name: "sum of relaxation weights (must be 1)",
                value: sum,
            });
        }
        if !(mode_frequency_hz > 0.0 && mode_frequency_hz.is_finite()) {
            return Err(PlantError::BadParameter {
                name: "mode_frequency_hz",
                value: mode_frequency_hz,
            });
        }
        if !(mode_damping > 0.0 && mode_damping < 1.0) {
            return Err(PlantError::BadParameter {
                name: "mode_damping",
                value: mode_damping,
            });
        }
        if !(span_m > 0.0 && span_m.is_finite()) {
            return Err(PlantError::BadParameter {
                name: "span_m",
                value: span_m,
            });
        }
        let hysteresis = BoucWen {
            a: 0.18522,
            beta: 0.029586,
            gamma: -0.020710,
            n: 1.0,
        };
        let h_low = hysteresis.jump(0.0, 0.0, -90.0);
        let h_high = hysteresis.jump(h_low, -90.0, 90.0);
        let d_m_per_v = span_m / (180.0 - (h_high - h_low));
        Ok(Self {
            relaxation_times_s: times_s.to_vec(),
            relaxation_weights: weights.to_vec(),
            mode_frequency_hz,
            mode_damping,
            hysteresis,
            d_m_per_v,
            electrostriction_per_v: 0.0,
        })
    }

    /// d, m/V.
    pub fn stack_gain_m_per_v(&self) -> f64 {
        self.d_m_per_v
    }

    /// Relaxation times (s) and weights.
    pub fn relaxations(&self) -> (&[f64], &[f64]) {
        (&self.relaxation_times_s, &self.relaxation_weights)
    }

    /// Mode frequency (Hz) and damping ratio.
    pub fn mode(&self) -> (f64, f64) {
        (self.mode_frequency_hz, self.mode_damping)
    }

    fn eta(&self, u: f64, h: f64) -> f64 {
        let (ud, _) = drive(u, 0.0, self.electrostriction_per_v);
        self.d_m_per_v * (ud - h)
    }
}

impl Plant for BipolarStack {
    fn name(&self) -> &'static str {
        "bipolar-stack"
    }
    fn input_names(&self) -> &'static [&'static str] {
        &["u_V"]
    }
    fn output_names(&self) -> &'static [&'static str] {
        &["y_m"]
    }
    fn state_dim(&self) -> usize {
        3 + self.relaxation_times_s.len()
    }
    fn initial_state(&self, x: &mut [f64]) {
        x.fill(0.0);
    }
    fn rhs(&self, t: f64, x: &[f64], input: &dyn InputAt, dx: &mut [f64]) {
        let (u, _) = input.input(0, t);
        let mut dv = 0.0;
        for (i, (&tau, &w)) in self
            .relaxation_times_s
            .iter()
            .zip(&self.relaxation_weights)
            .enumerate()
        {
            let d = (u - x[3 + i]) / tau;
            dx[3 + i] = d;
            dv += w * d;
        }
        let dh = self.hysteresis.rate(x[2], dv);
        let w = 2.0 * std::f64::consts::PI * self.mode_frequency_hz;
        let eta = self.eta(u, x[2]);
        dx[0] = x[1];
        dx[1] = -2.0 * self.mode_damping * w * x[1] - w * w * (x[0] - eta);
        dx[2] = dh;
    }
    fn input_jump(&self, _x: &mut [f64], _channel: usize, _u_from: f64, _u_to: f64) {
        // v is continuous: a voltage step moves h only as the relaxations follow it.
    }
    fn output(&self, x: &[f64], _u: &[f64], y: &mut [f64]) {
        y[0] = x[0];
    }
    fn free_displacement(&self, x: &[f64], u: &[f64], out: &mut [f64]) {
        out[0] = self.eta(u[0], x[2]);
    }
    fn default_sample_rate_hz(&self) -> f64 {
        10_000.0
    }
    fn check_input_span(&self, u_min_v: f64, u_max_v: f64) -> Result<(), PlantError> {
        super::check_bipolar_span(
            "bipolar-stack",
            "the bipolar stack accepts -100 V .. 100 V",
            u_min_v,
            u_max_v,
        )
    }
    fn set_electrostriction(&mut self, per_v: f64) {
        self.electrostriction_per_v = per_v;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_is_valid_and_bad_parameters_are_refused() {
        let p = BipolarStack::default();
        assert_eq!(p.state_dim(), 6);
        assert!(BipolarStack::new(&[1e-3], &[0.5], 740.0, 0.03, 35e-6).is_err());
        assert!(BipolarStack::new(&[0.0], &[1.0], 740.0, 0.03, 35e-6).is_err());
        assert!(BipolarStack::new(&[1e-3], &[1.0], 740.0, 1.0, 35e-6).is_err());
        assert!(BipolarStack::new(&[1e-3], &[1.0], f64::NAN, 0.03, 35e-6).is_err());
        assert!(BipolarStack::new(&[], &[], 740.0, 0.03, 35e-6).is_err());
    }
}
