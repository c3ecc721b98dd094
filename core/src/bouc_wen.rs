//! The Bouc-Wen hysteresis operator, stepped in input increments.
//!
//! ```text
//! ḣ = A·u̇ − β·|u̇|·|h|^(n−1)·h − γ·u̇·|h|^n                      (BW; MODELS.md, all three seeds)
//! ```
//!
//! `u` is the input in volts; `h` has the unit of `A·u` (seed 000: newtons with k1 = 1 N/V; seed 001:
//! volts scaled by k2 into the output). The law is rate-independent: dividing by u̇ gives
//!
//! ```text
//! dh/du = f(h, s) = A − (β·s·sgn h + γ)·|h|^n,      s = sgn(du)                       (BW-u)
//! ```
//!
//! so one sample is integrated *exactly along the input path* from `u[k−1]` to `u[k]`, whatever the
//! sample rate: a DAC step (zero-order hold) and a linear ramp (first-order hold) between the same two
//! samples give the same `h` at the sample instant. Paths:
//!
//! * **n = 1**: while `sgn h` is fixed, (BW-u) is linear, `dh/du = A − κ·h` with `κ = β·s + γ·sgn h`,
//!   so `h₁ = h₀ + (A − κ·h₀)·Δu·g(κ·Δu)`, `g(z) = (1 − e^(−z))/z` (exact; a 5-term series below
//!   |z| = 0.1, libm `expm1f` above). A zero crossing of `h` inside the step is located in closed form,
//!   `Δu₀ = ln(1 − κ·h₀/A)/κ`, and the rest of the step continues from `h = 0` with the other `κ`.
//! * **n = 2**: while `sgn h` is fixed, (BW-u) is the Riccati equation `dh/du = A − c·h²`,
//!   `c = β·s·sgn h + γ`, solved exactly by `h₁ = (h₀ + A·Δu·G)/(1 + c·h₀·Δu·G)` with
//!   `G = tanh(√z)/√z` (z = A·c·Δu² > 0) or `tan(√−z)/√−z` (z < 0); zero crossings as for n = 1 with
//!   `Δu₀ = −(h₀/A)·R(c·h₀²/A)`, `R(w) = artanh(√w)/√w`.
//! * **general n ≥ 1**: classical RK4 in `u`, by target: on the Cortex-M4F in f32 with the core's
//!   f32 power ([`crate::math::pow_nonnegative`], ≤ 3.3e-7 relative, measured; libm's `powf` computes
//!   in f64, which that FPU emulates in software); on a host in f64, rounded to the f32 state once per
//!   sample, with one f64 power per sub-step and the other stages' powers by the binomial series
//!   `|h·(1 + x)|^n = |h|^n·(1 + x)^n` (same sub-steps; within 0.5 ulp of the same rule in exact
//!   arithmetic over the bench records, where f32 arithmetic is off by up to 5.5 ulp). A number
//!   of sub-steps is chosen per sample from a Lipschitz bound `J = n·max|β ± γ|·H^(n−1)` of (BW-u) over
//!   the reachable states: `m = ⌈|Δu|·J/0.1⌉`, so `J·Δu/m ≤ 0.1` and the local error per sub-step is
//!   below ~1e-6 of the state scale. For a bounded set and an increment needing more than 64
//!   sub-steps (a jump deep into saturation), RK4 sub-steps sized by the stiffness of the branch being
//!   followed run until the state is within 1e-3·H of the loading equilibrium `h* = sgn(A·Δu)·H` (at
//!   most 1024), and the rest of the path decays toward it in closed form, `h* + (h − h*)·e^(−J*·|rest|)` with `J* = n·A'/H`. A range-limited set never
//!   needs that tail: its increments are bounded by the declared span.
//!
//! # Bounded classes (Ikhouane & Rodellar; MODELS.md)
//! With `A' = |A|` and `γ' = γ·sgn A` (the substitution h → −h flips the sign of γ):
//! * `β ≥ 0` is required. Then unloading (`s·sgn h < 0`) shrinks |h| at least as fast as loading grows
//!   it, and the largest |h| reachable from `h = 0` with the input kept in a range of span S is the
//!   monotone loading sweep `L(S)` of `dh/du = A' − (β + γ')·h^n` from 0 over S.
//! * `β + γ' > 0` (classes I and II): bounded for every input, `|h| ≤ H = (A'/(β + γ'))^(1/n)`;
//!   built with a finite input range, the bound used (for the state clamp and the inverse's
//!   monotonicity check) is the tighter `min(H, L(S))`.
//! * `β + γ' ≤ 0`: unbounded on loading. Accepted only through [`BoucWen::with_input_range`], when
//!   `L(S)` stays below a declared state limit; the input is then clamped into that range on every
//!   step. The published NAC2024 set (β + γ = −0.0123, n = 1.419) reaches |h| = 10 at an input span
//!   of 33.6 V, |h| = 266 at 81.2 V and blows up (|h| → ∞) at a finite span of 99.9 V (see
//!   [`max_input_span`]; the figures are asserted in this module's tests, the last against the closed
//!   form `A'^(1/n−1)·|β+γ'|^(−1/n)·(π/n)/sin(π/n)`).
//!
//! The per-sample step never fails: a non-finite input holds the previous input, the state is clamped
//! to the reachable bound (which absorbs f32 rounding), and the result is always finite.

use crate::error::{finite, ParamError};
#[cfg(not(target_os = "none"))]
use crate::math::pow_host_f64;
use crate::math::{clamp, max, min, pow_nonnegative_inline};

/// Raw Bouc-Wen parameters as identified or published (not yet validated).
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "serde", serde(deny_unknown_fields))]
pub struct BoucWenParams {
    /// A: gain of the hysteretic state on the input \[h per V\]. Must be nonzero; may be negative.
    pub a: f32,
    /// β: weight of the |u̇|-term (≥ 0).
    pub beta: f32,
    /// γ: weight of the u̇-term (any sign).
    pub gamma: f32,
    /// n: smoothness exponent, 1 ≤ n ≤ 16.
    pub n: f32,
}

/// Which boundedness class a validated set belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BoundClass {
    /// β + γ' > 0 and β ≥ 0: |h| ≤ (A'/(β + γ'))^(1/n) for every input.
    Bounded,
    /// β + γ' ≤ 0 and β ≥ 0: valid only over the declared input range, where |h| stays within the
    /// declared state limit.
    RangeLimited,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Exponent {
    One,
    Two,
    General,
}

/// Largest number of RK4 sub-steps of the general-n path in one sample.
const MAX_SUBSTEPS: f32 = 64.0;
/// Largest number of RK4 sub-steps a range-limited set (β + γ' ≤ 0) of general n may need over its
/// whole input span (its per-sample path has no cap: a set beyond it is refused when built).
const MAX_SPAN_SUBSTEPS: f64 = 4096.0;
/// Largest number of RK4 sub-steps spent on the way into saturation before the closed-form tail.
const SATURATION_SUBSTEPS: f32 = 1024.0;
/// Pieces a general-n RK4 sub-step is cut into where it may cross h = 0.
pub(crate) const ZERO_CROSSING_SPLIT: usize = 8;
/// Target of `J·Δu` per RK4 sub-step of the general-n path.
const SUBSTEP_THETA: f32 = 0.1;
/// Bound on the truncation of the host RK4's binomial series of the stage powers, relative to the
/// power at the sub-step's start.
#[cfg(not(target_os = "none"))]
const SERIES_TOLERANCE: f64 = 1e-11;
/// Largest |x| the host RK4 takes the binomial series for, whatever n.
#[cfg(not(target_os = "none"))]
const SERIES_REACH_CAP: f64 = 0.25;

/// The host RK4's power at a stage point `h·(1 + x)` from the power at the start `h` of its sub-step:
/// `|h·(1 + x)|^n = |h|^n·(1 + x)^n` with `(1 + x)^n = Σ_{j=0..7} C(n, j)·x^j`, used for
/// `|x| ≤ reach`, the largest |x| (≤ `SERIES_REACH_CAP`) whose truncation `Σ_{j≥8} |C(n, j)|·|x|^j`
/// is at most `SERIES_TOLERANCE`: 0.065 for n = 1.5, 0.25 for n = 3.06 (and every integer n ≤ 7,
/// where the series is exact), 0.0066 for n = 16.
#[cfg(not(target_os = "none"))]
#[derive(Debug, Clone, Copy, PartialEq)]
struct StageSeries {
    /// C(n, j), j = 0..=7.
    coefficients: [f64; 8],
    reach: f64,
}

#[cfg(not(target_os = "none"))]
impl StageSeries {
    fn new(n: f64) -> Self {
        let mut coefficients = [0.0; 8];
        let mut binomial = 1.0;
        for (j, c) in coefficients.iter_mut().enumerate() {
            *c = binomial;
            binomial *= (n - j as f64) / (j as f64 + 1.0);
        }
        // The truncation at |x| = X, increasing in X; past j = n the ratio of consecutive terms is
        // below X, so the sum to j = 400 plus a geometric bound on the rest is an upper bound.
        // The sum stops once past j = n + 1 its terms fall below 1e-6 of the tolerance (the bound
        // on the rest keeps it an upper bound).
        let truncation = |x: f64| {
            let (mut term, mut sum) = (binomial.abs() * libm::pow(x, 8.0), 0.0);
            for j in 8..400 {
                if j as f64 > n + 1.0 && term < 1e-6 * SERIES_TOLERANCE {
                    break;
                }
                sum += term;
                term *= libm::fabs((n - j as f64) / (j as f64 + 1.0)) * x;
            }
            sum + term / (1.0 - x)
        };
        let reach = if truncation(SERIES_REACH_CAP) <= SERIES_TOLERANCE {
            SERIES_REACH_CAP
        } else {
            let (mut lo, mut hi) = (0.0, SERIES_REACH_CAP);
            // 24 halvings: the reach to 1.5e-8, far below what moves the series' error.
            for _ in 0..24 {
                let mid = 0.5 * (lo + hi);
                if truncation(mid) <= SERIES_TOLERANCE {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            lo
        };
        Self {
            coefficients,
            reach,
        }
    }

    /// `(1 + x)^n` for `|x| ≤ reach` (Estrin's scheme: a short dependency chain).
    #[inline(always)]
    fn factor(&self, x: f64) -> f64 {
        let c = &self.coefficients;
        let x2 = x * x;
        let x4 = x2 * x2;
        ((c[0] + c[1] * x) + x2 * (c[2] + c[3] * x))
            + x4 * ((c[4] + c[5] * x) + x2 * (c[6] + c[7] * x))
    }
}

/// The branch data of one increment of the host RK4: the direction s = sgn Δu is fixed over it, so
/// `c = β·s·σ + γ` takes one of two values, by the sign σ of h.
#[cfg(not(target_os = "none"))]
#[derive(Clone, Copy)]
struct HostBranch {
    a: f64,
    n: f64,
    /// c for h ≥ 0.
    c_pos: f64,
    /// c for h < 0.
    c_neg: f64,
}

#[cfg(not(target_os = "none"))]
impl HostBranch {
    #[inline(always)]
    fn c(&self, h: f64) -> f64 {
        if h < 0.0 {
            self.c_neg
        } else {
            self.c_pos
        }
    }
}

/// Validated Bouc-Wen settings. Cannot hold an invalid set; its step never fails.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BoucWen {
    params: BoucWenParams,
    exponent: Exponent,
    class: BoundClass,
    input_min_v: f32,
    input_max_v: f32,
    /// Largest |h| reachable from rest (h = 0) with the input inside the range.
    state_bound: f32,
    /// `state_bound` with a small margin: the clamp applied after every step.
    clamp_bound: f32,
    /// RK4 sub-steps per volt of input increment (general n only).
    substeps_per_v: f32,
    /// The stage powers of the host's f64 RK4 (general n only).
    #[cfg(not(target_os = "none"))]
    series: StageSeries,
}

/// The state of one Bouc-Wen operator: the last input it was advanced to and its hysteretic state.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct HysteresisState {
    /// Last input seen \[V\].
    pub input_v: f32,
    /// Hysteretic state h \[unit of A·u\].
    pub h: f32,
}

impl HysteresisState {
    /// At rest at input `input_v`: no hysteretic state (the virgin curve starts here).
    pub fn at_rest(input_v: f32) -> Self {
        Self { input_v, h: 0.0 }
    }
}

/// Largest |h| accepted for a range-limited set (β + γ·sgn A ≤ 0) over its input range: the
/// one `state_limit` of [`BoucWen::with_input_range`] that the stage file, the firmware and the
/// host tools pass (bounded sets never reach it).
pub const STATE_LIMIT: f32 = 1e6;

impl BoucWen {
    /// Validates a set that must be bounded for every input (β ≥ 0, β + γ·sgn A > 0).
    ///
    /// A set with β + γ·sgn A ≤ 0 (such as the published NAC2024 set) is refused with
    /// [`ParamError::UnboundedWithoutRange`]; use [`BoucWen::with_input_range`] for it.
    pub fn new(params: BoucWenParams) -> Result<Self, ParamError> {
        Self::build(params, f32::NEG_INFINITY, f32::INFINITY, f32::INFINITY)
    }

    /// Validates a set for use over the input range `[input_min_v, input_max_v]` only
    /// ([`STATE_LIMIT`] is the `state_limit` the stage file, the firmware and the tools use).
    ///
    /// For a bounded set the range only clamps the input. For β + γ·sgn A ≤ 0 the set is accepted
    /// when the largest |h| reachable from rest over that range, `L(u_max − u_min)`, is at most
    /// `state_limit`; otherwise [`ParamError::StateLimitExceeded`] says the largest span that would
    /// be accepted.
    pub fn with_input_range(
        params: BoucWenParams,
        input_min_v: f32,
        input_max_v: f32,
        state_limit: f32,
    ) -> Result<Self, ParamError> {
        finite("input_min_v", input_min_v)?;
        finite("input_max_v", input_max_v)?;
        if input_max_v <= input_min_v {
            return Err(ParamError::OutOfRange {
                field: "input_max_v",
                value: input_max_v,
                requirement: "> input_min_v",
            });
        }
        finite("state_limit", state_limit)?;
        if state_limit <= 0.0 {
            return Err(ParamError::OutOfRange {
                field: "state_limit",
                value: state_limit,
                requirement: "> 0",
            });
        }
        Self::build(params, input_min_v, input_max_v, state_limit)
    }

    fn build(
        params: BoucWenParams,
        input_min_v: f32,
        input_max_v: f32,
        state_limit: f32,
    ) -> Result<Self, ParamError> {
        let BoucWenParams { a, beta, gamma, n } = params;
        finite("a", a)?;
        finite("beta", beta)?;
        finite("gamma", gamma)?;
        finite("n", n)?;
        if a == 0.0 {
            return Err(ParamError::OutOfRange {
                field: "a",
                value: a,
                requirement: "nonzero",
            });
        }
        if !(1.0..=16.0).contains(&n) {
            return Err(ParamError::OutOfRange {
                field: "n",
                value: n,
                requirement: "in [1, 16]",
            });
        }
        let gamma_normalised = gamma * a.signum();
        if beta < 0.0 {
            return Err(ParamError::UnboundableClass {
                beta,
                gamma_normalised,
            });
        }
        let (a_abs, load, nn) = (
            f64::from(a.abs()),
            f64::from(beta) + f64::from(gamma_normalised),
            f64::from(n),
        );
        let span = f64::from(input_max_v) - f64::from(input_min_v);
        let (class, state_bound) = if load > 0.0 {
            let bound = libm::pow(a_abs / load, 1.0 / nn);
            // With a finite range the loading sweep over its span may stay well below the bound;
            // the monotonicity check of the inverse and the state clamp then use that tighter level.
            let reach = if span.is_finite() {
                bounded_reach(a_abs, load, nn, span)
            } else {
                bound
            };
            (BoundClass::Bounded, reach.min(bound))
        } else {
            if !state_limit.is_finite() {
                return Err(ParamError::UnboundedWithoutRange {
                    beta_plus_gamma: load as f32,
                });
            }
            match unbounded_reach(a_abs, load, nn, span, f64::from(state_limit)) {
                Ok(reach) => (BoundClass::RangeLimited, reach),
                Err(max_span) => {
                    return Err(ParamError::StateLimitExceeded {
                        span_v: span as f32,
                        state_limit,
                        max_span_v: max_span as f32,
                    })
                }
            }
        };
        let exponent = if n == 1.0 {
            Exponent::One
        } else if n == 2.0 {
            Exponent::Two
        } else {
            Exponent::General
        };
        let lipschitz = nn
            * (f64::from(beta) + f64::from(gamma).abs())
            * libm::pow(state_bound.max(1e-30), nn - 1.0);
        // A range-limited set's general-n path is not capped per sample (module doc): bound its
        // cost at build time, so that no sample can take longer than a sweep of the whole span.
        let span_substeps = lipschitz * span / f64::from(SUBSTEP_THETA);
        if class == BoundClass::RangeLimited
            && exponent == Exponent::General
            && (span_substeps.is_nan() || span_substeps > MAX_SPAN_SUBSTEPS)
        {
            return Err(ParamError::OutOfRange {
                field: "n",
                value: n,
                requirement:
                    "with beta + gamma <= 0, at most 4096 RK4 sub-steps over the input span \
                              (n (beta + |gamma|) h_max^(n-1) span <= 409.6)",
            });
        }
        let state_bound_f32 = state_bound as f32;
        Ok(Self {
            params,
            exponent,
            class,
            input_min_v,
            input_max_v,
            state_bound: state_bound_f32,
            clamp_bound: state_bound_f32 * (1.0 + 1e-5) + f32::MIN_POSITIVE,
            substeps_per_v: (lipschitz / f64::from(SUBSTEP_THETA)) as f32,
            #[cfg(not(target_os = "none"))]
            series: StageSeries::new(nn),
        })
    }

    /// This operator with the general-n path's RK4 sub-steps sized to `J·Δu ≤ substep_target`
    /// instead of 0.1 (module doc): a coarser step for screening many candidate sets, whose local
    /// error per sub-step is about `substep_target⁵/120` of the state scale (2.6e-4 at 0.5), and
    /// which stays stable (RK4's limit is J·Δu ≈ 2.8). No effect for n = 1 and n = 2 (exact paths).
    /// Refuses a target outside [0.1, 1].
    pub fn with_substep_target(mut self, substep_target: f32) -> Result<Self, ParamError> {
        if !(SUBSTEP_THETA..=1.0).contains(&substep_target) {
            return Err(ParamError::OutOfRange {
                field: "substep_target",
                value: substep_target,
                requirement: "in [0.1, 1]",
            });
        }
        self.substeps_per_v *= SUBSTEP_THETA / substep_target;
        Ok(self)
    }

    /// The parameters this operator was built from.
    pub fn params(&self) -> BoucWenParams {
        self.params
    }

    /// The boundedness class of the set.
    pub fn class(&self) -> BoundClass {
        self.class
    }

    /// The input range the operator clamps to, `(min, max)` in volts (±∞ when unrestricted).
    pub fn input_range_v(&self) -> (f32, f32) {
        (self.input_min_v, self.input_max_v)
    }

    /// The largest |h| reachable from rest: `(A'/(β + γ'))^(1/n)` for a bounded set, `L(span)` for
    /// a range-limited one.
    pub fn state_bound(&self) -> f32 {
        self.state_bound
    }

    /// The largest |h| the loading sweep reaches from rest over an input span `span_v` \[V\] for
    /// a bounded set: `min(H, L(span))` (module doc); `None` for a range-limited set.
    pub(crate) fn bounded_reach_over(&self, span_v: f64) -> Option<f64> {
        let BoucWenParams { a, beta, gamma, n } = self.params;
        let load = f64::from(beta) + f64::from(gamma * a.signum());
        if self.class != BoundClass::Bounded || load <= 0.0 {
            return None;
        }
        let (a_abs, nn) = (f64::from(a.abs()), f64::from(n));
        let bound = libm::pow(a_abs / load, 1.0 / nn);
        Some(if span_v.is_finite() {
            bounded_reach(a_abs, load, nn, span_v).min(bound)
        } else {
            bound
        })
    }

    /// The bound [`BoucWen::clamp_state`] clamps |h| to: the state bound with a margin of 1e-5
    /// for rounding.
    #[inline]
    pub(crate) fn clamp_bound(&self) -> f32 {
        self.clamp_bound
    }

    /// RK4 sub-steps per volt of the general-n path (`J/θ`, module doc), as built.
    #[inline]
    pub(crate) fn substeps_per_v(&self) -> f32 {
        self.substeps_per_v
    }

    /// Clamps an input into the validated range; a non-finite input is replaced by `hold_v`.
    #[inline]
    pub fn sanitize_input(&self, input_v: f32, hold_v: f32) -> f32 {
        let u = if input_v.is_finite() { input_v } else { hold_v };
        clamp(u, self.input_min_v, self.input_max_v)
    }

    /// Clamps a state into the reachable bound; NaN becomes 0.
    #[inline]
    pub fn clamp_state(&self, h: f32) -> f32 {
        if h.is_nan() {
            0.0
        } else {
            clamp(h, -self.clamp_bound, self.clamp_bound)
        }
    }

    /// Advances `state` to the input `input_v` (sanitised: clamped into the range, a non-finite
    /// input holds the previous one) and returns the new `h`.
    #[inline]
    pub fn step(&self, state: &mut HysteresisState, input_v: f32) -> f32 {
        let previous = self.sanitize_input(state.input_v, 0.0);
        let u = self.sanitize_input(input_v, previous);
        state.h = self.advance(self.clamp_state(state.h), u - previous);
        state.input_v = u;
        state.h
    }

    /// The state reached from `h` after the input moves monotonically by `delta_u_v` (exact along the
    /// path for n = 1 and n = 2; RK4 with sub-steps otherwise). Always finite and within the bound.
    #[inline]
    pub fn advance(&self, h: f32, delta_u_v: f32) -> f32 {
        let h1 = self.advance_unclamped(h, delta_u_v);
        if h1.is_nan() {
            self.clamp_state(h)
        } else {
            self.clamp_state(h1)
        }
    }

    /// The increment of [`BoucWen::advance`] without the final safety clamp to the reachable bound:
    /// for analysis and for tests of boundedness. Inside the validated range it stays within the
    /// bound up to rounding; outside it may grow without limit.
    #[inline]
    pub fn advance_unclamped(&self, h: f32, delta_u_v: f32) -> f32 {
        if delta_u_v == 0.0 || !delta_u_v.is_finite() {
            return h;
        }
        match self.exponent {
            Exponent::One => self.advance_n1(h, delta_u_v),
            Exponent::Two => self.advance_n2(h, delta_u_v),
            Exponent::General => self.advance_general(h, delta_u_v),
        }
    }

    /// The path slope dh/du = A − (β·s·sgn h + γ)·|h|^n for an input moving in direction
    /// `direction` (its sign is used; 0 counts as positive).
    #[inline]
    pub fn slope(&self, h: f32, direction: f32) -> f32 {
        let BoucWenParams { a, beta, gamma, n } = self.params;
        let s = if direction < 0.0 { -1.0 } else { 1.0 };
        let sigma = if h < 0.0 { -1.0 } else { 1.0 };
        let magnitude = match self.exponent {
            Exponent::One => h.abs(),
            Exponent::Two => h * h,
            Exponent::General => pow_nonnegative_inline(h.abs(), n),
        };
        a - (beta * s * sigma + gamma) * magnitude
    }

    /// The extreme path slopes dh/du over all reachable states and both directions:
    /// `(min, max)`. (BW-u) is monotone in |h|^n on each branch, so the extremes lie at |h| = 0 and
    /// |h| = bound on the loading and unloading branches.
    pub fn slope_range(&self) -> (f32, f32) {
        self.slope_range_within(self.state_bound)
    }

    /// The extreme path slopes dh/du over |h| ≤ `bound` and both directions: `(min, max)`.
    pub fn slope_range_within(&self, bound: f32) -> (f32, f32) {
        let BoucWenParams { a, beta, gamma, n } = self.params;
        let hn = libm::powf(bound, n);
        let candidates = [a, a - (beta + gamma) * hn, a - (gamma - beta) * hn];
        let mut lo = f32::INFINITY;
        let mut hi = f32::NEG_INFINITY;
        for c in candidates {
            lo = lo.min(c);
            hi = hi.max(c);
        }
        (lo, hi)
    }

    /// Whether n = 1 (the linear-in-h closed form applies).
    #[inline]
    pub fn is_exponent_one(&self) -> bool {
        self.exponent == Exponent::One
    }

    /// For n = 1, the branch of an increment from `h0` in direction `direction`: `(q, κ, σ)` with
    /// κ = β·s + γ·σ, q = A − κ·h₀, σ the sign of h on the branch, so that
    /// h(Δu) = h₀ + q·Δu·g(κΔu) until h reaches zero.
    #[inline]
    pub(crate) fn n1_branch(&self, h0: f32, direction: f32) -> (f32, f32, f32) {
        let BoucWenParams { a, beta, gamma, .. } = self.params;
        let s = if direction < 0.0 { -1.0 } else { 1.0 };
        let sigma = self.branch_sign(h0, s);
        let kappa = beta * s + gamma * sigma;
        (a - kappa * h0, kappa, sigma)
    }

    /// For n = 1, the input increment at which h reaches zero from `h0` on the branch κ (h moving
    /// toward zero): dh/du = A − κ·h gives `Δu₀ = ln(1 + x)/κ` with x = −κ·h₀/A, written as
    /// `Δu₀ = −(h₀/A)·ln(1 + x)/x` so that κ → 0 is regular. `None` when x ≤ −1 (h never
    /// reaches zero on this branch). The model's own step ([`BoucWen::advance`]) splits a step
    /// that crosses zero here.
    #[inline]
    pub(crate) fn n1_zero_reach(&self, h0: f32, kappa: f32) -> Option<f32> {
        let a = self.params.a;
        let x = -kappa * h0 / a;
        if x <= -1.0 {
            return None;
        }
        Some(-(h0 / a) * log1p_ratio(x))
    }

    /// Sign used while `h` is zero: the state leaves zero in the direction of `A·Δu`.
    #[inline]
    fn branch_sign(&self, h: f32, du: f32) -> f32 {
        if h > 0.0 || (h == 0.0 && self.params.a * du > 0.0) {
            1.0
        } else {
            -1.0
        }
    }

    fn advance_n1(&self, h0: f32, du: f32) -> f32 {
        let BoucWenParams { a, beta, gamma, .. } = self.params;
        let s = du.signum();
        let sigma = self.branch_sign(h0, du);
        let kappa = beta * s + gamma * sigma;
        let h1 = h0 + (a - kappa * h0) * du * relax_factor(kappa * du);
        if h1 * sigma >= 0.0 {
            return h1;
        }
        // h crossed zero inside the step (see `n1_zero_reach`).
        let Some(du0) = self.n1_zero_reach(h0, kappa) else {
            return h1;
        };
        let rest = if (du - du0) * s > 0.0 { du - du0 } else { 0.0 };
        let kappa_after = beta * s - gamma * sigma;
        a * rest * relax_factor(kappa_after * rest)
    }

    fn advance_n2(&self, h0: f32, du: f32) -> f32 {
        let BoucWenParams { a, beta, gamma, .. } = self.params;
        let s = du.signum();
        let sigma = self.branch_sign(h0, du);
        let c = beta * s * sigma + gamma;
        // Moving toward zero? Then locate the crossing first: the closed form of the other branch
        // must not be used past it (on the tan branch it would run into its pole).
        if h0 != 0.0 && (a - c * h0 * h0) * du * sigma < 0.0 {
            // h₀ + A·Δu₀·G(A·c·Δu₀²) = 0  ⇔  Δu₀ = −(h₀/A)·R(c·h₀²/A), reachable when c·h₀²/A < 1.
            let w = c * h0 * h0 / a;
            if w < 1.0 {
                let du0 = -(h0 / a) * artanh_ratio(w);
                if (du - du0) * s > 0.0 {
                    let rest = du - du0;
                    let c_after = -beta * s * sigma + gamma;
                    return a * rest * riccati_factor(a * c_after * rest * rest);
                }
            }
        }
        let g = riccati_factor(a * c * du * du);
        let denominator = 1.0 + c * h0 * du * g;
        if denominator <= 0.0 {
            // Finite-u blow-up of the tan branch (only outside the validated range).
            return sigma * f32::INFINITY;
        }
        (h0 + a * du * g) / denominator
    }

    fn advance_general(&self, h0: f32, du: f32) -> f32 {
        let needed = max(libm::ceilf(du.abs() * self.substeps_per_v), 1.0);
        if needed <= MAX_SUBSTEPS || self.class == BoundClass::RangeLimited {
            // Range-limited sets have |Δu| ≤ span, so `needed` is bounded by the build-time span.
            return self.integrate(h0, du, needed);
        }
        // A bounded set and a long increment: RK4 sub-steps with J·Δu ≤ θ for the largest stiffness
        // |∂f/∂h| met during the sub-step: on the loading branch it never exceeds J* = n·A'/H (its
        // value at h*); on the unloading branch |h| only shrinks, so J(h) = n·|β·s·sgn h + γ|·|h|^(n−1)
        // at the start bounds it, and a crossing into loading stays below J*. Sub-steps run until the
        // state is within 1e-3·H of the loading equilibrium h* = sgn(A·Δu)·H (or
        // SATURATION_SUBSTEPS are spent); from there the deviation decays as e^(−J*·|rest|),
        // J* = n·A'/H, the exact rate of the flow linearised at h* (the tail's relative error is
        // about (n − 1)/2 · 1e-3 of a deviation of at most 1e-3·H).
        let BoucWenParams { a, beta, gamma, n } = self.params;
        let s = du.signum();
        let bound = self.state_bound;
        let equilibrium = bound * (a * du).signum();
        let decay_rate = n * a.abs() / bound;
        let mut h = h0;
        let mut rest = du.abs();
        let mut spent = 0.0;
        while rest > 0.0 {
            if (h - equilibrium).abs() <= 1e-3 * bound || spent >= SATURATION_SUBSTEPS {
                return equilibrium + (h - equilibrium) * libm::expf(-decay_rate * rest);
            }
            let sigma = if h < 0.0 { -1.0 } else { 1.0 };
            // |h|^(n−1) as |h|^n/|h| (0 at h = 0, where the max with J* takes over).
            let magnitude = h.abs();
            let power_ratio = if magnitude > 0.0 {
                pow_nonnegative_inline(magnitude, n) / magnitude
            } else {
                0.0
            };
            let branch = n * (beta * s * sigma + gamma).abs() * power_ratio;
            let length = min(SUBSTEP_THETA / max(branch, decay_rate), rest);
            h = self.integrate(h, s * length, 1.0);
            rest -= length;
            spent += 1.0;
        }
        h
    }

    /// `substeps` classical RK4 steps of (BW-u) over the increment `du`, by target: in f32 on bare
    /// metal (`rk4`), in f64 on a host (`rk4_f64`); the same sub-steps.
    #[inline(always)]
    fn integrate(&self, h0: f32, du: f32, substeps: f32) -> f32 {
        #[cfg(target_os = "none")]
        {
            self.rk4(h0, du, substeps)
        }
        #[cfg(not(target_os = "none"))]
        {
            self.rk4_f64(h0, du, substeps)
        }
    }

    /// `substeps` classical RK4 steps of (BW-u) over the increment `du`, in f32 (the Cortex-M4F's
    /// path; on a host it only serves the tests as the comparison). A sub-step that starts
    /// within `2·|A·Δu_sub|` of h = 0, where it may cross the kink of |h|^n (RK4 drops to order n + 1
    /// there), is cut into 8.
    #[cfg(any(target_os = "none", test))]
    fn rk4(&self, h0: f32, du: f32, substeps: f32) -> f32 {
        let dh = du / substeps;
        let near_zero = 2.0 * (self.params.a * dh).abs();
        let mut h = h0;
        let mut i = 0.0;
        while i < substeps {
            if h.abs() < near_zero {
                for _ in 0..ZERO_CROSSING_SPLIT {
                    h = self.rk4_step(h, dh / ZERO_CROSSING_SPLIT as f32, du);
                }
            } else {
                h = self.rk4_step(h, dh, du);
            }
            i += 1.0;
        }
        h
    }

    #[cfg(any(target_os = "none", test))]
    #[inline]
    fn rk4_step(&self, h: f32, dh: f32, direction: f32) -> f32 {
        let k1 = self.slope(h, direction);
        let k2 = self.slope(h + 0.5 * dh * k1, direction);
        let k3 = self.slope(h + 0.5 * dh * k2, direction);
        let k4 = self.slope(h + dh * k3, direction);
        h + dh / 6.0 * (k1 + 2.0 * (k2 + k3) + k4)
    }

    /// The host's RK4 of (BW-u): the sub-steps of `rk4` (the same count, the same 8-fold
    /// cut near h = 0), computed in f64 and rounded to the f32 state once, at the end. Per sub-step
    /// of length `d` from `h`:
    ///
    /// ```text
    /// k₁ = f(h),  k₂ = f(h + d·k₁/2),  k₃ = f(h + d·k₂/2),  k₄ = f(h + d·k₃),
    /// h ← h + d/6·(k₁ + 2k₂ + 2k₃ + k₄),      f(h) = A − c(σ)·|h|^n,  c(σ) = β·s·σ + γ
    /// ```
    ///
    /// with s = sgn Δu fixed for the increment (`β·s` formed once) and σ = sgn of the stage point.
    /// `|h|^n` is computed once per sub-step ([`crate::math::pow_host_f64`]); a stage point
    /// `h + e = h·(1 + x)`, `x = e/h`, takes `|h|^n·(1 + x)^n` by the binomial series of
    /// `StageSeries` (relative truncation ≤ 1e-11) when |x| ≤ its reach (then σ is that of h), else
    /// the power of the point itself.
    #[cfg(not(target_os = "none"))]
    #[inline]
    fn rk4_f64(&self, h0: f32, du: f32, substeps: f32) -> f32 {
        let BoucWenParams { a, beta, gamma, n } = self.params;
        let beta_s = if du < 0.0 {
            -f64::from(beta)
        } else {
            f64::from(beta)
        };
        let branch = HostBranch {
            a: f64::from(a),
            n: f64::from(n),
            c_pos: f64::from(gamma) + beta_s,
            c_neg: f64::from(gamma) - beta_s,
        };
        let dh = f64::from(du) / f64::from(substeps);
        let near_zero = 2.0 * (branch.a * dh).abs();
        let split = dh / ZERO_CROSSING_SPLIT as f64;
        let mut h = f64::from(h0);
        // `substeps` is a whole number ≥ 1 (the cast saturates, it cannot panic).
        for _ in 0..substeps as u32 {
            let (pieces, length) = if h.abs() < near_zero {
                (ZERO_CROSSING_SPLIT, split)
            } else {
                (1, dh)
            };
            for _ in 0..pieces {
                h = self.rk4_step_f64(h, length, &branch);
            }
        }
        h as f32
    }

    /// One f64 RK4 sub-step of length `dh` from `h` (`rk4_f64`).
    #[cfg(not(target_os = "none"))]
    #[inline(always)]
    fn rk4_step_f64(&self, h: f64, dh: f64, branch: &HostBranch) -> f64 {
        // c·|h|^n at the start of the sub-step.
        let load = branch.c(h) * pow_host_f64(h.abs(), branch.n);
        // x of a stage point is its slope times (its offset per unit slope)/h; formed off the chain.
        // h = 0 gives ±∞ or NaN here, which fails the reach test and takes the direct power.
        let inverse = 1.0 / h;
        let half = 0.5 * dh;
        let (x_half, x_full) = (half * inverse, dh * inverse);
        let k1 = branch.a - load;
        let k2 = self.stage_slope(h, load, k1, half, x_half, branch);
        let k3 = self.stage_slope(h, load, k2, half, x_half, branch);
        let k4 = self.stage_slope(h, load, k3, dh, x_full, branch);
        h + dh / 6.0 * (k1 + 2.0 * (k2 + k3) + k4)
    }

    /// f at the stage point `h + length·k` of `rk4_step_f64`, `load = c(σ)·|h|^n` at h,
    /// `x_per_slope = length/h`.
    #[cfg(not(target_os = "none"))]
    #[inline(always)]
    fn stage_slope(
        &self,
        h: f64,
        load: f64,
        k: f64,
        length: f64,
        x_per_slope: f64,
        branch: &HostBranch,
    ) -> f64 {
        let x = k * x_per_slope;
        if x.abs() <= self.series.reach {
            branch.a - load * self.series.factor(x)
        } else {
            let point = h + length * k;
            branch.a - branch.c(point) * pow_host_f64(point.abs(), branch.n)
        }
    }
}

/// The largest input span over which the state of a set with β + γ·sgn A ≤ 0 stays within
/// `state_limit`, starting from rest: `∫₀^limit dh / (A' − (β + γ')·h^n)` \[V\]. For a bounded set
/// (β + γ' > 0) the span is unlimited when the limit is at least the bound: returns +∞ then.
pub fn max_input_span(params: BoucWenParams, state_limit: f32) -> f32 {
    let a_abs = f64::from(params.a.abs());
    let load = f64::from(params.beta) + f64::from(params.gamma * params.a.signum());
    let n = f64::from(params.n);
    let limit = f64::from(state_limit);
    if load > 0.0 && libm::pow(a_abs / load, 1.0 / n) <= limit {
        return f32::INFINITY;
    }
    loading_span(a_abs, load, n, limit) as f32
}

/// Span of input needed by the loading sweep `dh/du = A' − load·h^n` to go from 0 to `limit`:
/// `∫₀^limit dh / (A' − load·h^n)` \[V\]; +∞ when the sweep never gets there (a bounded set and a
/// limit at or above its bound). Computed as the [`sweep`] of the class (module doc of the
/// quadrature there), exact to ~1e-13 relative.
fn loading_span(a_abs: f64, load: f64, n: f64, limit: f64) -> f64 {
    if load > 0.0 {
        let bound = libm::pow(a_abs / load, 1.0 / n);
        if limit >= bound {
            return f64::INFINITY;
        }
        // w = −ln(1 − h/H) at the limit.
        let end = -libm::log1p(-limit / bound);
        match sweep(|w| bounded_rate(w, n), end, f64::INFINITY) {
            Sweep::Reached(_) => f64::INFINITY,
            Sweep::Exhausted(tau) => tau * bound / a_abs,
        }
    } else if load == 0.0 {
        limit / a_abs
    } else if n == 1.0 {
        let c = -load;
        libm::log1p(c * limit / a_abs) / c
    } else {
        let scale = libm::pow(a_abs / -load, 1.0 / n);
        let end = libm::log1p(limit / scale);
        match sweep(|s| unbounded_rate(s, n), end, f64::INFINITY) {
            Sweep::Reached(_) => f64::INFINITY,
            Sweep::Exhausted(tau) => tau * scale / a_abs,
        }
    }
}

/// |h| reached by the loading sweep `dh/du = A' − load·h^n` (load > 0) from 0 over `span` volts.
///
/// In the units `z = h/H`, `τ = u·A'/H` (H = (A'/load)^(1/n)) the sweep is `dz/dτ = 1 − z^n`, and
/// with `z = 1 − e^(−w)` its inverse is the quadrature `τ(w) = ∫₀^w e^(−v)/(1 − z(v)^n) dv`, whose
/// integrand is smooth and lies in [1/n, 1]; the `w` with `τ(w) = span·A'/H` is found by [`sweep`].
/// Beyond w = 40, z = 1 − 4e-18 is H in f64.
fn bounded_reach(a_abs: f64, load: f64, n: f64, span: f64) -> f64 {
    let bound = libm::pow(a_abs / load, 1.0 / n);
    let target = span * a_abs / bound;
    // τ(w) ≤ w (the rate is at most 1): τ ≥ 40 needs w ≥ 40.
    if target.is_nan() || target >= 40.0 {
        return bound;
    }
    match sweep(|w| bounded_rate(w, n), 40.0, target) {
        Sweep::Reached(w) => -bound * libm::expm1(-w),
        Sweep::Exhausted(_) => bound,
    }
}

/// dτ/dw = e^(−w)/(1 − z^n), z = 1 − e^(−w) (the bounded sweep in [`bounded_reach`]'s units).
#[inline]
fn bounded_rate(w: f64, n: f64) -> f64 {
    let e = libm::exp(-w);
    // 1 − z^n = −expm1(n·ln z), ln z = log1p(−e^(−w)): no cancellation as z → 1.
    e / -libm::expm1(n * libm::log1p(-e))
}

/// The reach of a set with `load = β + γ' ≤ 0` over `span`: `Ok(|h|)` when the loading sweep stays
/// within `limit`, else `Err(largest span that would)`.
///
/// `load = 0`: h = A'·u. Otherwise, in the units `z = h/h₀`, `τ = u·A'/h₀` with
/// h₀ = (A'/|load|)^(1/n), the sweep is `dz/dτ = 1 + z^n`: for n = 1, `z = e^τ − 1`; for n > 1 it
/// blows up at `τ∞ = (π/n)/sin(π/n)`, so a span with `τ ≥ τ∞` is refused at once; otherwise, with
/// `z = e^s − 1`, `τ(s) = ∫₀^s e^v/(1 + (e^v − 1)^n) dv` (a smooth integrand), solved by [`sweep`] up
/// to `s = ln(1 + limit/h₀)`.
fn unbounded_reach(a_abs: f64, load: f64, n: f64, span: f64, limit: f64) -> Result<f64, f64> {
    let refused = || Err(loading_span(a_abs, load, n, limit));
    if load == 0.0 {
        let reach = a_abs * span;
        return if reach <= limit { Ok(reach) } else { refused() };
    }
    let scale = libm::pow(a_abs / -load, 1.0 / n);
    let target = span * a_abs / scale;
    if n == 1.0 {
        let reach = scale * libm::expm1(target);
        return if reach <= limit { Ok(reach) } else { refused() };
    }
    let blow_up = (core::f64::consts::PI / n) / libm::sin(core::f64::consts::PI / n);
    // z ≥ τ (dz/dτ ≥ 1): a span past the blow-up or one whose linear part alone passes the limit.
    if target.is_nan() || target >= blow_up || target * scale > limit {
        return refused();
    }
    let end = libm::log1p(limit / scale);
    match sweep(|s| unbounded_rate(s, n), end, target) {
        Sweep::Reached(s) => Ok(scale * libm::expm1(s)),
        Sweep::Exhausted(tau) => Err(tau * scale / a_abs),
    }
}

/// dτ/ds = e^s/(1 + (e^s − 1)^n) (the unbounded sweep in [`unbounded_reach`]'s units).
#[inline]
fn unbounded_rate(s: f64, n: f64) -> f64 {
    libm::exp(s) / (1.0 + libm::pow(libm::expm1(s), n))
}

/// Outcome of [`sweep`].
enum Sweep {
    /// The variable at which the integral reaches the target.
    Reached(f64),
    /// The target was not reached before the end: the whole integral.
    Exhausted(f64),
}

/// Walks `τ(x) = ∫₀^x rate` over [0, end] and finds where it reaches `target`.
///
/// Panels: geometric from 2⁻¹² up to 0.5 (they resolve the `x^n` kink at 0 that a non-integer n puts
/// into both rates), then of width 0.5; 8-point Gauss–Legendre on each (error ≪ 1e-13 for these
/// smooth rates). In the panel where τ passes the target, a safeguarded Newton iteration on
/// `τ(x) − target` (slope `rate(x)`, the partial panel by the same rule) locates x.
fn sweep(rate: impl Fn(f64) -> f64, end: f64, target: f64) -> Sweep {
    let mut tau = 0.0;
    let mut lo = 0.0f64;
    let mut width = 1.0 / 4096.0;
    while lo < end {
        let hi = (lo + width).min(end);
        let panel = gauss_legendre(&rate, lo, hi);
        if !panel.is_finite() {
            return Sweep::Exhausted(f64::INFINITY);
        }
        if tau + panel >= target {
            return Sweep::Reached(solve_in_panel(&rate, lo, hi, target - tau));
        }
        tau += panel;
        lo = hi;
        width = if width < 0.5 { 2.0 * width } else { 0.5 };
    }
    Sweep::Exhausted(tau)
}

/// The x in [lo, hi] with `∫_lo^x rate = needed` (0 ≤ needed ≤ the panel's integral).
fn solve_in_panel(rate: &impl Fn(f64) -> f64, lo: f64, hi: f64, needed: f64) -> f64 {
    let (mut a, mut b) = (lo, hi);
    let mut x = (lo + needed / rate(lo)).clamp(lo, hi);
    for _ in 0..50 {
        let residual = gauss_legendre(rate, lo, x) - needed;
        if residual > 0.0 {
            b = x;
        } else {
            a = x;
        }
        let next = x - residual / rate(x);
        let next = if next > a && next < b {
            next
        } else {
            0.5 * (a + b)
        };
        if (next - x).abs() <= 1e-15 * (1.0 + x.abs()) {
            return next;
        }
        x = next;
    }
    x
}

/// ∫_a^b f by 8-point Gauss–Legendre.
fn gauss_legendre(f: &impl Fn(f64) -> f64, a: f64, b: f64) -> f64 {
    const NODES: [(f64, f64); 4] = [
        (0.183_434_642_495_65, 0.362_683_783_378_362),
        (0.525_532_409_916_329, 0.313_706_645_877_887_3),
        (0.796_666_477_413_626_7, 0.222_381_034_453_374_5),
        (0.960_289_856_497_536_3, 0.101_228_536_290_376_3),
    ];
    let (mid, half) = (0.5 * (a + b), 0.5 * (b - a));
    let mut sum = 0.0;
    for (x, w) in NODES {
        sum += w * (f(mid - half * x) + f(mid + half * x));
    }
    sum * half
}

/// g(z) = (1 − e^(−z))/z, g(0) = 1. Series below |z| = 0.1 (truncation < 1.4e-8 relative),
/// libm `expm1f` above.
#[inline]
pub(crate) fn relax_factor(z: f32) -> f32 {
    if z.abs() < 0.1 {
        relax_series(z)
    } else {
        -libm::expm1f(-z) / z
    }
}

/// [`relax_factor`], the same operations so the same bits, with the series inlined at the call
/// site (no call on a small step) and the libm branch, [`relax_libm`], out of line: for the
/// compensator's zero crossings, where a call would hold the solve's registers across it.
#[inline(always)]
pub(crate) fn relax_factor_inline(z: f32) -> f32 {
    if z.abs() < 0.1 {
        relax_series(z)
    } else {
        relax_libm(z)
    }
}

/// [`relax_factor`] above |z| = 0.1: `−expm1(−z)/z` with libm's `expm1f`.
#[inline(never)]
fn relax_libm(z: f32) -> f32 {
    -libm::expm1f(-z) / z
}

/// The 5-term series of g(z) = (1 − e^(−z))/z: 1 − z/2 + z²/6 − z³/24 + z⁴/120 (for |z| < 0.1).
#[inline]
pub(crate) fn relax_series(z: f32) -> f32 {
    1.0 - 0.5 * z * (1.0 - z * (1.0 / 3.0) * (1.0 - 0.25 * z * (1.0 - 0.2 * z)))
}

/// ln(1 + x)/x, 1 at x = 0. Series below |x| = 0.01, libm `log1pf` above.
#[inline]
fn log1p_ratio(x: f32) -> f32 {
    if x.abs() < 0.01 {
        1.0 - x * (0.5 - x * (1.0 / 3.0 - 0.25 * x))
    } else {
        libm::log1pf(x) / x
    }
}

/// G(z) = tanh(√z)/√z for z > 0, tan(√−z)/√−z for z < 0, 1 at 0 (one analytic function of z:
/// 1 − z/3 + 2z²/15 − 17z³/315 + …). Series below |z| = 0.02 (truncation < 4e-9).
#[inline]
fn riccati_factor(z: f32) -> f32 {
    if z.abs() < 0.02 {
        1.0 - z * (1.0 / 3.0 - z * (2.0 / 15.0 - z * (17.0 / 315.0)))
    } else if z > 0.0 {
        let r = libm::sqrtf(z);
        libm::tanhf(r) / r
    } else {
        let r = libm::sqrtf(-z);
        libm::tanf(r) / r
    }
}

/// R(w) = artanh(√w)/√w for 0 < w < 1, arctan(√−w)/√−w for w < 0 (1 + w/3 + w²/5 + …).
#[inline]
fn artanh_ratio(w: f32) -> f32 {
    if w.abs() < 0.02 {
        1.0 + w * (1.0 / 3.0 + w * (0.2 + w / 7.0))
    } else if w > 0.0 {
        let r = libm::sqrtf(w);
        libm::atanhf(r) / r
    } else {
        let r = libm::sqrtf(-w);
        libm::atanf(r) / r
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn params(a: f32, beta: f32, gamma: f32, n: f32) -> BoucWenParams {
        BoucWenParams { a, beta, gamma, n }
    }

    /// Reference: fine RK4 of (BW-u) in f64, 20 000 sub-steps.
    fn reference(p: BoucWenParams, h0: f64, du: f64) -> f64 {
        rk4_libm(p, h0, du, 20_000, 0.0)
    }

    #[test]
    fn a_coarser_substep_target_stays_close_and_is_refused_outside_its_range() {
        let p = params(1.0, 0.6, -0.2, 3.0);
        let fine = BoucWen::new(p).expect("valid");
        assert!(fine.with_substep_target(0.05).is_err());
        assert!(fine.with_substep_target(1.5).is_err());
        assert!(fine.with_substep_target(f32::NAN).is_err());
        let coarse = fine.with_substep_target(0.5).expect("in range");
        let bound = fine.state_bound();
        // A loop 0 → 1.2·H → −1.2·H → 0 in increments of H/20 (J·Δu ≈ 0.3 at the bound: three
        // sub-steps by default, one at the coarse target).
        let (mut h_fine, mut h_coarse, mut u) = (0.0f32, 0.0f32, 0.0f32);
        let mut worst = 0.0f32;
        for (from, to) in [(0.0, 1.2), (1.2, -1.2), (-1.2, 0.0)] {
            let steps = ((to - from) as f32).abs() * 20.0;
            let du = (to - from) as f32 * bound / steps;
            for _ in 0..steps as usize {
                h_fine = fine.advance(h_fine, du);
                h_coarse = coarse.advance(h_coarse, du);
                u += du;
                worst = worst.max((h_fine - h_coarse).abs());
            }
        }
        assert!(u.abs() < 1e-3 * bound, "the loop closes at u = 0");
        assert!(
            worst > 0.0,
            "the coarse target takes fewer sub-steps, so it differs"
        );
        assert!(
            worst < 2e-5 * bound,
            "coarse against default: {worst:e} of H = {bound:e}"
        );
    }

    #[test]
    fn large_increments_match_fine_reference_including_zero_crossings() {
        for n in [1.0f32, 1.5, 2.0, 3.0] {
            let p = params(0.8, 0.5, 0.2, n);
            let bw = BoucWen::new(p).unwrap();
            let bound = f64::from(bw.state_bound());
            for &h0 in &[0.0, 0.3 * bound, -0.7 * bound, 0.95 * bound] {
                for &du in &[0.01f64, -0.01, 0.5, -0.5, 3.0, -3.0] {
                    let exact = reference(p, h0, du);
                    let got = f64::from(bw.advance(h0 as f32, du as f32));
                    assert!(
                        (got - exact).abs() <= 2e-5 * bound,
                        "n={n} h0={h0} du={du}: got {got}, reference {exact}"
                    );
                }
            }
        }
    }

    /// Reference for the loading sweep `dh/du = A' − load·h^n` from 0 over `span`: RK4 in u, f64,
    /// 200 000 steps (or `None` past `limit`).
    fn sweep_reference(a: f64, load: f64, n: f64, span: f64, limit: f64) -> Option<f64> {
        let rate = |h: f64| a - load * h.max(0.0).powf(n);
        let steps = 200_000;
        let du = span / steps as f64;
        let mut h = 0.0f64;
        for _ in 0..steps {
            let k1 = rate(h);
            let k2 = rate(h + 0.5 * du * k1);
            let k3 = rate(h + 0.5 * du * k2);
            let k4 = rate(h + du * k3);
            h += du / 6.0 * (k1 + 2.0 * (k2 + k3) + k4);
            if h.is_nan() || h > limit {
                return None;
            }
        }
        Some(h)
    }

    #[test]
    fn loading_reach_matches_a_fine_reference() {
        for n in [1.0f64, 1.419, 2.0, 3.05869, 5.0] {
            for load in [1e-3f64, 0.3, 4.0] {
                for span in [1e-3f64, 0.1, 1.0, 5.0, 40.0] {
                    let a = 0.8;
                    let got = bounded_reach(a, load, n, span);
                    let want = sweep_reference(a, load, n, span, f64::INFINITY).unwrap();
                    assert!(
                        (got - want).abs() <= 1e-9 * want,
                        "bounded n={n} load={load} span={span}: {got} vs {want}"
                    );
                }
                for span in [1e-3f64, 0.1, 1.0, 3.0] {
                    let (a, limit) = (0.8, 50.0);
                    let got = unbounded_reach(a, -load, n, span, limit).ok();
                    let want = sweep_reference(a, -load, n, span, limit);
                    match (got, want) {
                        (Some(g), Some(w)) => assert!(
                            (g - w).abs() <= 1e-9 * w,
                            "unbounded n={n} load={load} span={span}: {g} vs {w}"
                        ),
                        (None, None) => {}
                        other => panic!("unbounded n={n} load={load} span={span}: {other:?}"),
                    }
                }
            }
        }
    }

    /// The step with the f32 RK4 (the Cortex-M4F's arithmetic, here with the host's correctly rounded
    /// f32 power): the host's step before it computed in f64.
    fn step_f32(bw: &BoucWen, state: &mut HysteresisState, input_v: f32) -> f32 {
        let previous = bw.sanitize_input(state.input_v, 0.0);
        let u = bw.sanitize_input(input_v, previous);
        let (h, du) = (bw.clamp_state(state.h), u - previous);
        let h1 = if du == 0.0 {
            h
        } else {
            let needed = max(libm::ceilf(du.abs() * bw.substeps_per_v), 1.0);
            assert!(needed <= MAX_SUBSTEPS);
            bw.rk4(h, du, needed)
        };
        state.h = bw.clamp_state(h1);
        state.input_v = u;
        state.h
    }

    /// The increment `du` from `h` by `substeps` RK4 sub-steps in f64 with libm's `pow`, each cut
    /// into 8 when it starts within `near_zero` of h = 0.
    fn rk4_libm(p: BoucWenParams, h0: f64, du: f64, substeps: u32, near_zero: f64) -> f64 {
        let d = du / f64::from(substeps);
        let (a, beta, gamma, n) = (
            f64::from(p.a),
            f64::from(p.beta),
            f64::from(p.gamma),
            f64::from(p.n),
        );
        let s = du.signum();
        let f = |h: f64| {
            let sigma = if h < 0.0 { -1.0 } else { 1.0 };
            a - (beta * s * sigma + gamma) * libm::pow(h.abs(), n)
        };
        let mut h = h0;
        for _ in 0..substeps {
            let (pieces, d) = if h.abs() < near_zero {
                (8, d / 8.0)
            } else {
                (1, d)
            };
            for _ in 0..pieces {
                let k1 = f(h);
                let k2 = f(h + 0.5 * d * k1);
                let k3 = f(h + 0.5 * d * k2);
                let k4 = f(h + d * k3);
                h += d / 6.0 * (k1 + 2.0 * (k2 + k3) + k4);
            }
        }
        h
    }

    /// The host step (f64 RK4) against the f32 RK4 it replaced, over the records of the
    /// `core/static_general_*` benches (1 M samples of a 0–20 V triangle, 5000-sample period; the sets
    /// n = 1.5 and seed 001 Case I, n = 3.06). Measured (`--nocapture` prints them):
    /// * the two differ by at most 1.1e-7·H (n = 1.5) and 0.7e-7·H (n = 3.06), about one f32 ulp of
    ///   H; bound 2.4e-7·H;
    /// * per sample, the host step is the same sub-step rule in exact arithmetic (f64, libm `pow`)
    ///   rounded once to f32: within 0.5000 ulp of the state (bound 0.501 ulp: the f64 power and
    ///   series), where the f32 RK4 is off by up to 1.6 ulp (n = 1.5) and 5.5 ulp (n = 3.06);
    /// * against an f64 path of 16 sub-steps per sample (state kept in f64), both are within 6.2e-6·H
    ///   (n = 1.5) and 9.0e-7·H (n = 3.06), the truncation of the (unchanged) sub-step rule; their
    ///   two distances differ by less than their distance to each other.
    #[test]
    fn host_step_matches_the_f32_step_over_the_bench_records() {
        extern crate std;
        for p in [
            params(0.8, 0.5, 0.2, 1.5),
            params(-7.02182e-2, 4.45753, 3.49259, 3.05869),
        ] {
            let bw = BoucWen::new(p).unwrap();
            let bound = f64::from(bw.state_bound());
            let same_rule = |h: f32, du: f32| {
                let substeps = max(libm::ceilf(du.abs() * bw.substeps_per_v), 1.0);
                assert!(substeps <= MAX_SUBSTEPS);
                let d = f64::from(du) / f64::from(substeps);
                let near_zero = 2.0 * (f64::from(p.a) * d).abs();
                rk4_libm(p, f64::from(h), f64::from(du), substeps as u32, near_zero)
            };
            let ulps = |got: f32, want: f64| {
                let ulp = f64::from(f32::from_bits((want as f32).abs().to_bits() + 1))
                    - f64::from((want as f32).abs());
                (f64::from(got) - want).abs() / ulp
            };
            let (mut new, mut old) = (HysteresisState::default(), HysteresisState::default());
            let (mut exact, mut previous) = (0.0f64, 0.0f32);
            let (mut apart, mut new_error, mut old_error) = (0.0f64, 0.0f64, 0.0f64);
            let (mut new_ulps, mut old_ulps) = (0.0f64, 0.0f64);
            for k in 0..1_000_000usize {
                let phase = (k % 5000) as f32 / 5000.0;
                let rise = if phase < 0.5 { phase } else { 1.0 - phase };
                let u = 40.0 * rise;
                let du = u - previous;
                let (from_new, from_old) = (new.h, old.h);
                let h_new = bw.step(&mut new, u);
                let h_old = step_f32(&bw, &mut old, u);
                if du != 0.0 {
                    new_ulps = new_ulps.max(ulps(h_new, same_rule(from_new, du)));
                    old_ulps = old_ulps.max(ulps(h_old, same_rule(from_old, du)));
                    exact = rk4_libm(p, exact, f64::from(du), 16, 0.0);
                }
                previous = u;
                let (h_new, h_old) = (f64::from(h_new), f64::from(h_old));
                apart = apart.max((h_new - h_old).abs() / bound);
                new_error = new_error.max((h_new - exact).abs() / bound);
                old_error = old_error.max((h_old - exact).abs() / bound);
            }
            std::println!(
                "n = {}: |new − old| ≤ {apart:.2e}·H; per sample against the same rule in f64: \
                 new ≤ {new_ulps:.4} ulp, old ≤ {old_ulps:.2} ulp; against 16 f64 sub-steps: \
                 new ≤ {new_error:.3e}·H, old ≤ {old_error:.3e}·H",
                p.n
            );
            assert!(apart <= 2.4e-7, "n = {}: {apart:e}", p.n);
            assert!(new_ulps <= 0.501, "n = {}: {new_ulps} ulp", p.n);
            assert!(new_error <= 6.3e-6, "n = {}: {new_error:e}", p.n);
            assert!((new_error - old_error).abs() <= apart, "n = {}", p.n);
        }
    }

    #[test]
    fn splitting_an_increment_gives_the_same_state() {
        for n in [1.0f32, 2.0, 2.5] {
            let bw = BoucWen::new(params(1.0, 0.7, -0.3, n)).unwrap();
            let one = bw.advance(0.2, 2.0);
            let two = bw.advance(bw.advance(0.2, 0.7), 1.3);
            assert!((one - two).abs() < 1e-5, "n={n}: {one} vs {two}");
        }
    }

    #[test]
    fn bound_is_the_saturation_level() {
        let bw = BoucWen::new(params(0.5, 2.0, 0.5, 2.0)).unwrap();
        let expected = (0.5f32 / 2.5).sqrt();
        assert!((bw.state_bound() - expected).abs() < 1e-6);
        let h = bw.advance(0.0, 1000.0);
        assert!((h - expected).abs() < 1e-5, "{h} vs {expected}");
    }

    #[test]
    fn negative_a_is_normalised() {
        // Seed 001, Case I.
        let bw = BoucWen::new(params(-7.02182e-2, 4.45753, 3.49259, 3.05869)).unwrap();
        assert_eq!(bw.class(), BoundClass::Bounded);
        assert!(
            (bw.state_bound() - 0.424).abs() < 0.01,
            "{}",
            bw.state_bound()
        );
    }

    #[test]
    fn rejects_what_it_must() {
        let nan = BoucWen::new(params(f32::NAN, 1.0, 0.0, 1.0));
        assert_eq!(nan, Err(ParamError::NonFinite { field: "a" }));
        assert!(matches!(
            BoucWen::new(params(1.0, -1.0, 2.0, 1.0)),
            Err(ParamError::UnboundableClass { .. })
        ));
        assert!(matches!(
            BoucWen::new(params(1.0, 0.1, 0.5, 0.5)),
            Err(ParamError::OutOfRange { field: "n", .. })
        ));
        assert!(matches!(
            BoucWen::new(params(0.0, 0.1, 0.5, 1.0)),
            Err(ParamError::OutOfRange { field: "a", .. })
        ));
    }

    #[test]
    fn nac2024_is_range_limited() {
        let p = params(0.192, 0.034, -0.0463, 1.419);
        assert!(matches!(
            BoucWen::new(p),
            Err(ParamError::UnboundedWithoutRange { .. })
        ));
        let span = max_input_span(p, 10.0);
        assert!((span - 33.6).abs() < 0.1, "span {span}");
        let span = max_input_span(p, 266.0);
        assert!((span - 81.2).abs() < 0.2, "span {span}");
        // Blow-up span, closed form: ∫₀^∞ dh/(A + a·h^n) = A^(1/n−1)·a^(−1/n)·(π/n)/sin(π/n), a = −(β+γ),
        // minus the tail beyond 10⁶, ∫ dh/(a·h^n) = h^(1−n)/(a·(n − 1)).
        let (a, load, n) = (0.192f64, 0.0123f64, 1.419f64);
        let blow_up = a.powf(1.0 / n - 1.0) * load.powf(-1.0 / n) * (core::f64::consts::PI / n)
            / (core::f64::consts::PI / n).sin();
        let tail = 1e6f64.powf(1.0 - n) / (load * (n - 1.0));
        let span = f64::from(max_input_span(p, 1e6));
        assert!(
            (span - (blow_up - tail)).abs() < 0.05,
            "span {span} vs {}",
            blow_up - tail
        );
        assert!((blow_up - 99.9).abs() < 0.1, "blow-up span {blow_up}");
        let ok = BoucWen::with_input_range(p, -10.0, 10.0, 10.0).unwrap();
        assert_eq!(ok.class(), BoundClass::RangeLimited);
        assert!(ok.state_bound() > 4.0 && ok.state_bound() < 5.0);
        match BoucWen::with_input_range(p, 0.0, 200.0, 10.0) {
            Err(ParamError::StateLimitExceeded { max_span_v, .. }) => {
                assert!((max_span_v - 33.6).abs() < 0.1)
            }
            other => panic!("expected StateLimitExceeded, got {other:?}"),
        }
    }

    #[test]
    fn a_range_limited_set_too_stiff_to_integrate_in_bounded_time_is_refused() {
        // β + γ = 0: h = A·u, reach 20 over the span; J = n·(β + |γ|)·20^0.5.
        let stiff = BoucWenParams {
            a: 1.0,
            beta: 1000.0,
            gamma: -1000.0,
            n: 1.5,
        };
        match BoucWen::with_input_range(stiff, -10.0, 10.0, 1e3) {
            Err(ParamError::OutOfRange { field, .. }) => assert_eq!(field, "n"),
            other => panic!("expected the sub-step bound, got {other:?}"),
        }
        let mild = BoucWenParams {
            beta: 0.01,
            gamma: -0.01,
            ..stiff
        };
        let ok = BoucWen::with_input_range(mild, -10.0, 10.0, 1e3).unwrap();
        assert_eq!(ok.class(), BoundClass::RangeLimited);
        // A whole-span sweep in one sample stays within the bound's sub-steps.
        let h = ok.advance(0.0, 20.0);
        assert!(h.is_finite() && (h - 20.0).abs() < 1e-3, "{h}");
    }
}
