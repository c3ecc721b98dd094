//! Bouc-Wen hysteresis law in f64, shared by the reference plants (independent of `piezo-core`).
//!
//! ḣ = A·u̇ − β·|u̇|·|h|^(n−1)·h − γ·u̇·|h|^n   (MODELS.md, eq. BW; seeds 000, 001, 002).
//!
//! The law is rate-independent, so an instantaneous monotone jump of the input from `u_from` to `u_to`
//! (a zero-order-hold DAC step) moves h along dh/du = A − (β·sgn(Δu·h) + γ)·|h|^n; [`BoucWen::jump`]
//! integrates that in u with the adaptive Dormand–Prince pair of [`crate::ode`].

use crate::ode::{Dp45, Dp45Settings, OdeSystem};

/// Bouc-Wen parameters (dimensionless shape; h carries the unit of A times the input unit).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BoucWen {
    /// A (α in seed 002): initial slope dh/du.
    pub a: f64,
    /// β.
    pub beta: f64,
    /// γ.
    pub gamma: f64,
    /// Exponent n (> 0).
    pub n: f64,
}

impl BoucWen {
    /// |h|^(n−1)·h written as sgn(h)·|h|^n, which stays finite at h = 0 for any n > 0.
    fn h_pow(&self, h: f64) -> (f64, f64) {
        let m = h.abs().powf(self.n);
        (m, m * h.signum() * if h == 0.0 { 0.0 } else { 1.0 })
    }

    /// ḣ for input rate `du` (input units per second).
    pub fn rate(&self, h: f64, du: f64) -> f64 {
        let (m, signed) = self.h_pow(h);
        self.a * du - self.beta * du.abs() * signed - self.gamma * du * m
    }

    /// ḣ of the rate-dependent Bouc-Wen, whose gain grows with the input's speed:
    /// A·(1 + |u̇|/ṙ₀)·u̇ in place of A·u̇, ṙ₀ = `rate_scale` (input units per second; 0: the
    /// standard operator, [`Self::rate`]).
    pub fn rate_with_speed_gain(&self, h: f64, du: f64, rate_scale: f64) -> f64 {
        let extra = if rate_scale > 0.0 {
            self.a * du * du.abs() / rate_scale
        } else {
            0.0
        };
        self.rate(h, du) + extra
    }

    /// dh/du along a path whose input moves in the direction of `direction` (sign only).
    pub fn slope(&self, h: f64, direction: f64) -> f64 {
        let (m, _) = self.h_pow(h);
        let s = (direction * h).signum() * if direction * h == 0.0 { 0.0 } else { 1.0 };
        self.a - (self.beta * s + self.gamma) * m
    }

    /// True when h stays bounded for every input (Ikhouane & Rodellar, with A < 0 mapped by h → −h).
    pub fn is_bounded_class(&self) -> bool {
        let g = if self.a < 0.0 {
            -self.gamma
        } else {
            self.gamma
        };
        self.beta + g > 0.0 && self.beta - g >= 0.0
    }

    /// h after the input moves monotonically from `u_from` to `u_to` (rate-independent jump).
    pub fn jump(&self, h: f64, u_from: f64, u_to: f64) -> f64 {
        if u_from == u_to || !h.is_finite() {
            return h;
        }
        struct Path<'a> {
            bw: &'a BoucWen,
            direction: f64,
        }
        impl OdeSystem for Path<'_> {
            fn dim(&self) -> usize {
                1
            }
            fn rhs(&self, _u: f64, x: &[f64], dx: &mut [f64]) {
                dx[0] = self.direction * self.bw.slope(x[0], self.direction);
            }
        }
        // Integrate in s = |u − u_from| so the independent variable always increases.
        let direction = (u_to - u_from).signum();
        let span = (u_to - u_from).abs();
        let path = Path {
            bw: self,
            direction,
        };
        let settings = Dp45Settings {
            rtol: 1e-12,
            atol: 1e-15 * (1.0 + h.abs()),
            max_step_s: span / 8.0,
            ..Default::default()
        };
        let mut ode = Dp45::new(1, settings);
        let (mut s, mut x) = (0.0, [h]);
        // The slope is only C0 where h crosses zero; step-size control handles that kink.
        match ode.advance(&path, &mut s, &mut x, span) {
            Ok(()) => x[0],
            Err(_) => f64::NAN,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn n1_jump_matches_closed_form() {
        // n = 1, loading from h = 0 with u̇ > 0 and h > 0: dh/du = A − (β+γ)h → h = A/(β+γ)(1 − e^{−(β+γ)u}).
        let bw = BoucWen {
            a: 0.2,
            beta: 0.03,
            gamma: -0.01,
            n: 1.0,
        };
        let h = bw.jump(0.0, 0.0, 50.0);
        let exact = 0.2 / 0.02 * (1.0 - (-0.02f64 * 50.0).exp());
        assert!((h - exact).abs() < 1e-9, "{h} vs {exact}");
    }

    #[test]
    fn jump_equals_time_integration_of_rate() {
        // Rate independence: a 1 V/s ramp integrated in time gives the same h as the jump.
        let bw = BoucWen {
            a: 0.192,
            beta: 0.034,
            gamma: -0.0463,
            n: 1.419,
        };
        struct Ramp(BoucWen);
        impl OdeSystem for Ramp {
            fn dim(&self) -> usize {
                1
            }
            fn rhs(&self, _t: f64, x: &[f64], dx: &mut [f64]) {
                dx[0] = self.0.rate(x[0], -1.0);
            }
        }
        let mut ode = Dp45::new(
            1,
            Dp45Settings {
                rtol: 1e-12,
                atol: 1e-15,
                ..Default::default()
            },
        );
        let (mut t, mut x) = (0.0, [0.5]);
        ode.advance(&Ramp(bw), &mut t, &mut x, 7.0).unwrap();
        let h = bw.jump(0.5, 3.0, -4.0);
        assert!((h - x[0]).abs() < 1e-9, "{h} vs {}", x[0]);
    }

    #[test]
    fn boundedness_classes() {
        assert!(!BoucWen {
            a: 0.192,
            beta: 0.034,
            gamma: -0.0463,
            n: 1.419
        }
        .is_bounded_class());
        assert!(BoucWen {
            a: -0.0702,
            beta: 4.4575,
            gamma: 3.4926,
            n: 3.0587
        }
        .is_bounded_class());
    }
}
