//! Adaptive Dormand–Prince 5(4) integrator in f64 (the reference integrator of the simulated plants).
//!
//! Embedded Runge–Kutta pair of Dormand & Prince (1980), coefficients as in Hairer, Nørsett & Wanner,
//! *Solving ODEs I*, table 5.2. The 5th-order solution is propagated (local extrapolation); the step is
//! accepted when the RMS of `err_i / (atol + rtol·max(|x_i|, |x_new_i|))` is ≤ 1 and the next step is
//! `h·clamp(0.9·err^(−1/5), 0.2, 5)`. [`Dp45::advance`] always lands exactly on `t_end` (step clipping),
//! so callers clip at sample instants, input breakpoints and known reversal times by calling it once per
//! segment. It is deliberately unrelated to the fixed-step f32 model step of `piezo-core`.

use std::fmt;

/// A first-order system ẋ = f(t, x).
pub trait OdeSystem {
    /// Number of states.
    fn dim(&self) -> usize;
    /// Writes f(t, x) into `dx` (same length as `x`).
    fn rhs(&self, t: f64, x: &[f64], dx: &mut [f64]);
}

/// Integrator failures.
#[derive(Debug, Clone, PartialEq)]
pub enum OdeError {
    /// The controller asked for a step below `min_step_s`.
    StepTooSmall {
        /// Time reached, s.
        t_s: f64,
        /// Step asked for, s.
        step_s: f64,
    },
    /// A state or derivative became NaN or infinite.
    NonFinite {
        /// Time reached, s.
        t_s: f64,
    },
    /// More than `max_steps` steps in one call.
    TooManySteps {
        /// Time reached, s.
        t_s: f64,
    },
}

impl fmt::Display for OdeError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::StepTooSmall { t_s, step_s } => {
                write!(f, "integrator step {step_s:e} s too small at t = {t_s:e} s")
            }
            Self::NonFinite { t_s } => write!(f, "state became non-finite at t = {t_s:e} s"),
            Self::TooManySteps { t_s } => write!(f, "too many integrator steps at t = {t_s:e} s"),
        }
    }
}

impl std::error::Error for OdeError {}

/// Tolerances and step limits.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Dp45Settings {
    /// Relative tolerance.
    pub rtol: f64,
    /// Absolute tolerance (state units).
    pub atol: f64,
    /// Largest step, in the independent variable's unit (s for time).
    pub max_step_s: f64,
    /// Smallest step before giving up.
    pub min_step_s: f64,
    /// Step budget of one `advance` call.
    pub max_steps: usize,
}

impl Default for Dp45Settings {
    fn default() -> Self {
        Self {
            rtol: 1e-9,
            atol: 1e-15,
            max_step_s: f64::INFINITY,
            min_step_s: 1e-18,
            max_steps: 10_000_000,
        }
    }
}

/// Counters since construction.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Dp45Stats {
    /// Accepted steps.
    pub accepted: u64,
    /// Rejected steps.
    pub rejected: u64,
    /// Right-hand-side evaluations.
    pub rhs_evals: u64,
}

const C2: f64 = 1.0 / 5.0;
const C3: f64 = 3.0 / 10.0;
const C4: f64 = 4.0 / 5.0;
const C5: f64 = 8.0 / 9.0;
const A21: f64 = 1.0 / 5.0;
const A31: f64 = 3.0 / 40.0;
const A32: f64 = 9.0 / 40.0;
const A41: f64 = 44.0 / 45.0;
const A42: f64 = -56.0 / 15.0;
const A43: f64 = 32.0 / 9.0;
const A51: f64 = 19372.0 / 6561.0;
const A52: f64 = -25360.0 / 2187.0;
const A53: f64 = 64448.0 / 6561.0;
const A54: f64 = -212.0 / 729.0;
const A61: f64 = 9017.0 / 3168.0;
const A62: f64 = -355.0 / 33.0;
const A63: f64 = 46732.0 / 5247.0;
const A64: f64 = 49.0 / 176.0;
const A65: f64 = -5103.0 / 18656.0;
const B1: f64 = 35.0 / 384.0;
const B3: f64 = 500.0 / 1113.0;
const B4: f64 = 125.0 / 192.0;
const B5: f64 = -2187.0 / 6784.0;
const B6: f64 = 11.0 / 84.0;
// Error coefficients: 5th-order weights minus 4th-order weights.
const E1: f64 = 71.0 / 57600.0;
const E3: f64 = -71.0 / 16695.0;
const E4: f64 = 71.0 / 1920.0;
const E5: f64 = -17253.0 / 339200.0;
const E6: f64 = 22.0 / 525.0;
const E7: f64 = -1.0 / 40.0;

/// Dormand–Prince 5(4) integrator with its work buffers and the step-size suggestion carried between calls.
#[derive(Debug, Clone)]
pub struct Dp45 {
    settings: Dp45Settings,
    step_s: f64,
    k: [Vec<f64>; 7],
    tmp: Vec<f64>,
    stats: Dp45Stats,
}

impl Dp45 {
    /// New integrator for systems of dimension `dim`.
    pub fn new(dim: usize, settings: Dp45Settings) -> Self {
        Self {
            settings,
            step_s: 0.0,
            k: std::array::from_fn(|_| vec![0.0; dim]),
            tmp: vec![0.0; dim],
            stats: Dp45Stats::default(),
        }
    }

    /// Counters.
    pub fn stats(&self) -> Dp45Stats {
        self.stats
    }

    /// Settings in use.
    pub fn settings(&self) -> &Dp45Settings {
        &self.settings
    }

    /// Integrates `x` from `*t` to exactly `t_end` (no-op if `t_end <= *t`), updating `*t`.
    pub fn advance<S: OdeSystem + ?Sized>(
        &mut self,
        sys: &S,
        t: &mut f64,
        x: &mut [f64],
        t_end: f64,
    ) -> Result<(), OdeError> {
        let n = x.len();
        debug_assert_eq!(n, sys.dim());
        if self.tmp.len() != n {
            *self = Self::new(n, self.settings);
        }
        let span = t_end - *t;
        if span <= 0.0 {
            return Ok(());
        }
        let s = self.settings;
        let [k1, k2, k3, k4, k5, k6, k7] = &mut self.k;
        let tmp = &mut self.tmp;
        sys.rhs(*t, x, k1);
        self.stats.rhs_evals += 1;
        if self.step_s <= 0.0 || !self.step_s.is_finite() {
            self.step_s = initial_step(x, k1, &s, span);
        }
        let mut steps = 0usize;
        loop {
            let remaining = t_end - *t;
            if remaining <= 0.0 {
                return Ok(());
            }
            let mut h = self.step_s.min(s.max_step_s);
            // Clip at t_end; avoid leaving a sliver smaller than 1 % of a step.
            let last = h >= remaining * 0.99;
            if last {
                h = remaining;
            }
            if h < s.min_step_s && !last {
                return Err(OdeError::StepTooSmall { t_s: *t, step_s: h });
            }
            steps += 1;
            if steps > s.max_steps {
                return Err(OdeError::TooManySteps { t_s: *t });
            }
            let t0 = *t;
            let t_new = if last { t_end } else { t0 + h };
            let stages = [&mut *k1, k2, k3, k4, k5, k6, k7];
            let err = trial(sys, stages, tmp, x, (t0, h, t_new), &s);
            self.stats.rhs_evals += 6;
            if !err.is_finite() {
                // Retry smaller; give up only when the step floor is reached.
                self.stats.rejected += 1;
                self.step_s = h * 0.1;
                if self.step_s < s.min_step_s {
                    return Err(OdeError::NonFinite { t_s: t0 });
                }
                continue;
            }
            let factor = if err == 0.0 {
                5.0
            } else {
                (0.9 * err.powf(-0.2)).clamp(0.2, 5.0)
            };
            if err <= 1.0 {
                self.stats.accepted += 1;
                x.copy_from_slice(tmp);
                std::mem::swap(k1, k7); // first-same-as-last
                *t = t_new;
                // Do not let a clipped final step shrink the suggestion for the next call.
                self.step_s = if last {
                    self.step_s.max(h * factor)
                } else {
                    h * factor
                };
            } else {
                self.stats.rejected += 1;
                self.step_s = h * factor.min(1.0);
                if self.step_s < s.min_step_s {
                    return Err(OdeError::StepTooSmall {
                        t_s: t0,
                        step_s: self.step_s,
                    });
                }
            }
        }
    }
}

/// The first step's size from the derivative scale (Hairer's simple variant).
fn initial_step(x: &[f64], k1: &[f64], s: &Dp45Settings, span: f64) -> f64 {
    let n = x.len();
    let mut d0 = 0.0;
    let mut d1 = 0.0;
    for i in 0..n {
        let sc = s.atol + s.rtol * x[i].abs();
        d0 += (x[i] / sc).powi(2);
        d1 += (k1[i] / sc).powi(2);
    }
    let (d0, d1) = ((d0 / n as f64).sqrt(), (d1 / n as f64).sqrt());
    if d0 < 1e-5 || d1 < 1e-5 {
        1e-6 * span
    } else {
        0.01 * d0 / d1
    }
}

/// One Dormand–Prince 5(4) trial step from `x` at `t0` with step `h` (ending at `t_new`, `t0 + h`
/// or the clipped end): the stages k2 … k7 (k1 given, the derivative at `t0`), the fifth-order
/// solution in `tmp`, and the RMS of the scaled error estimate.
fn trial<S: OdeSystem + ?Sized>(
    sys: &S,
    [k1, k2, k3, k4, k5, k6, k7]: [&mut Vec<f64>; 7],
    tmp: &mut [f64],
    x: &[f64],
    (t0, h, t_new): (f64, f64, f64),
    s: &Dp45Settings,
) -> f64 {
    let n = x.len();
    for i in 0..n {
        tmp[i] = x[i] + h * A21 * k1[i];
    }
    sys.rhs(t0 + C2 * h, tmp, k2);
    for i in 0..n {
        tmp[i] = x[i] + h * (A31 * k1[i] + A32 * k2[i]);
    }
    sys.rhs(t0 + C3 * h, tmp, k3);
    for i in 0..n {
        tmp[i] = x[i] + h * (A41 * k1[i] + A42 * k2[i] + A43 * k3[i]);
    }
    sys.rhs(t0 + C4 * h, tmp, k4);
    for i in 0..n {
        tmp[i] = x[i] + h * (A51 * k1[i] + A52 * k2[i] + A53 * k3[i] + A54 * k4[i]);
    }
    sys.rhs(t0 + C5 * h, tmp, k5);
    for i in 0..n {
        tmp[i] = x[i] + h * (A61 * k1[i] + A62 * k2[i] + A63 * k3[i] + A64 * k4[i] + A65 * k5[i]);
    }
    sys.rhs(t_new, tmp, k6);
    for i in 0..n {
        tmp[i] = x[i] + h * (B1 * k1[i] + B3 * k3[i] + B4 * k4[i] + B5 * k5[i] + B6 * k6[i]);
    }
    sys.rhs(t_new, tmp, k7);
    let mut err = 0.0;
    for i in 0..n {
        let e = h * (E1 * k1[i] + E3 * k3[i] + E4 * k4[i] + E5 * k5[i] + E6 * k6[i] + E7 * k7[i]);
        let sc = s.atol + s.rtol * x[i].abs().max(tmp[i].abs());
        err += (e / sc).powi(2);
    }
    (err / n as f64).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    struct Harmonic {
        omega: f64,
    }
    impl OdeSystem for Harmonic {
        fn dim(&self) -> usize {
            2
        }
        fn rhs(&self, _t: f64, x: &[f64], dx: &mut [f64]) {
            dx[0] = x[1];
            dx[1] = -self.omega * self.omega * x[0];
        }
    }

    struct Decay {
        rate: f64,
    }
    impl OdeSystem for Decay {
        fn dim(&self) -> usize {
            1
        }
        fn rhs(&self, _t: f64, x: &[f64], dx: &mut [f64]) {
            dx[0] = -self.rate * x[0];
        }
    }

    #[test]
    fn harmonic_oscillator_matches_cosine_to_1e9() {
        let omega = 2.0 * std::f64::consts::PI * 3.0;
        let sys = Harmonic { omega };
        let settings = Dp45Settings {
            rtol: 1e-12,
            atol: 1e-14,
            ..Default::default()
        };
        let mut ode = Dp45::new(2, settings);
        let (mut t, mut x) = (0.0, [1.0, 0.0]);
        for k in 1..=1000 {
            let te = k as f64 * 1e-3; // clip at 1 kHz sample instants
            ode.advance(&sys, &mut t, &mut x, te).unwrap();
            assert_eq!(t, te);
            assert!(
                (x[0] - (omega * te).cos()).abs() < 1e-9,
                "t={te} x={}",
                x[0]
            );
            assert!((x[1] + omega * (omega * te).sin()).abs() < 1e-9 * omega);
        }
    }

    #[test]
    fn exponential_decay_matches_to_1e9() {
        let sys = Decay { rate: 50.0 };
        let mut ode = Dp45::new(
            1,
            Dp45Settings {
                rtol: 1e-11,
                atol: 1e-14,
                ..Default::default()
            },
        );
        let (mut t, mut x) = (0.0, [2.0]);
        ode.advance(&sys, &mut t, &mut x, 0.2).unwrap();
        assert!((x[0] - 2.0 * (-10.0f64).exp()).abs() < 1e-9);
        assert!(ode.stats().accepted > 10);
    }

    #[test]
    fn zero_length_advance_is_noop() {
        let sys = Decay { rate: 1.0 };
        let mut ode = Dp45::new(1, Dp45Settings::default());
        let (mut t, mut x) = (1.0, [3.0]);
        ode.advance(&sys, &mut t, &mut x, 1.0).unwrap();
        assert_eq!((t, x[0]), (1.0, 3.0));
    }
}
