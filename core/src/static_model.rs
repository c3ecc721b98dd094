//! The static output map of seed 001 and its asymmetric variant.
//!
//! ```text
//! y = k1·u + k2·h + y0                                         (seed 001 eq. 1, with an offset y0)
//! ```
//!
//! with `h` from the Bouc-Wen operator ([`crate::bouc_wen`]), `y` in metres, `k1` in m/V, `k2` in m per
//! unit of h.
//!
//! # Asymmetric variant (seed 001 eq. 3) — the reading implemented here
//! The printed equation is garbled (MODELS.md); this crate implements it literally, in time:
//!
//! ```text
//! U(t) = u(t − φ)                                   φ: input shift [s], |φ| ≤ one sample period T
//! ḣ = A·U̇ − β·|U̇|·|h|^(n−1)·h − γ·U̇·|h|^n + δ·u·sgn(u̇)      δ [h per V·s]
//! y = k1·u + k2·h + y0
//! ```
//!
//! Discretised at the sample period T: the shift is a fractional-sample delay by linear interpolation
//! (extrapolation for φ < 0), `U[k] = u[k] − (φ/T)·(u[k] − u[k−1])`; the Bouc-Wen part is integrated
//! exactly along the path from `U[k−1]` to `U[k]`; the δ-term adds `δ·sgn(Δu)·T·(u[k−1] + u[k])/2`
//! (the trapezoidal integral of u over the sample, exact for a linear ramp), half before and half after
//! the Bouc-Wen increment (Strang splitting). With δ = 0 and φ = 0 this is exactly the standard model.
//! Note what the literal reading implies: the δ-term is rate-dependent (it acts per second, not per
//! volt) and is discontinuous at u̇ = 0; it can carry h past the Bouc-Wen bound H (seed 001's Case II
//! reaches 1.04·H), so the asymmetric model clamps h only at 1.25·H (and the inverse checks
//! monotonicity up to there). Over one period of a time-symmetric
//! input the δ-term integrates to zero; over an input with unequal rise and fall times it drifts
//! until that clamp holds it.
//!
//! # Hysteresis driven by a lag of the input (rate-dependent hysteresis)
//! [`StaticModel::with_input_lag`]: the Bouc-Wen operator is driven by v, a first-order lag of the
//! command, while the linear strain k1·u follows the command at once:
//!
//! ```text
//! τ_v·v̇ = u − v,   ḣ = A·v̇ − β·|v̇|·|h|^(n−1)·h − γ·v̇·|h|^n,   y = k1·u + k2·h + y0
//! ```
//!
//! (a Bouc-Wen operator behind linear input dynamics, the Wiener–Hammerstein structures of
//! rate-dependent piezo hysteresis: e.g. Rakotondrabe, "Bouc–Wen modeling and inverse multiplicative
//! structure to compensate hysteresis nonlinearity in piezoelectric actuators", IEEE T-ASE 8(2),
//! 2011, and the dielectric relaxation of the stack's domain switching). At low rates v = u and
//! the model is the standard one; as the rate rises h lags the command and the loop opens and
//! tilts. Sampled exactly for a command that ramps linearly between samples (first-order hold,
//! as a sampled smooth drive and an amplifier's output do), with x = T/τ_v:
//!
//! ```text
//! v[k] = v[k−1] + c·(u[k−1] − v[k−1]) + b·(u[k] − u[k−1]),   c = 1 − e^(−x),   b = 1 − c/x
//! ```
//!
//! (c and b from f64; b ≈ x/2 for τ_v ≫ T), and h is integrated exactly along v's move. The
//! one-step map's slope is `dy/du[k] = k1 + k2·b·dh/dv`: the compensator's Newton solve uses it.
//! Sign convention: τ_v > 0 \[s\], 0 is no lag; v starts at rest at the first command. The
//! state's `hysteresis.input_v` is v.
//!
//! The inverse's recursion through the lag (on a branch of quasi-static slope
//! S = k1 + k2·dh/dv = k1·(1 + r)) carries an error in v by the factor
//! `λ = (e^(−x) − r·(c − b))/(1 + r·b)` per sample: |λ| < 1 for every r > −1 since c − b < b when
//! x ≤ 1; [`crate::compensator::Compensator::new`] asks r > −1 and λ ≥ −1/2 (no more ringing than
//! half a step) on every branch.

use crate::bouc_wen::{BoucWen, HysteresisState};
use crate::error::{finite, positive, ParamError};
use crate::math::clamp;

/// With δ ≠ 0 the state is clamped at this multiple of the Bouc-Wen bound H, and the inverse's
/// monotonicity check covers states up to it: the δ-term may carry h past H (seed 001 Case II reaches
/// 1.04·H), and over inputs with unequal rise and fall times it drifts until this clamp holds it.
pub const ASYMMETRIC_STATE_FACTOR: f32 = 1.25;

/// The linear part of the static map: y = k1·u + k2·h + y0.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "serde", serde(deny_unknown_fields))]
pub struct StaticMap {
    /// k1: direct gain \[m/V\].
    pub k1_m_per_v: f32,
    /// k2: gain of the hysteretic state \[m per unit of h\].
    pub k2_m_per_h: f32,
    /// y0: output offset \[m\].
    pub offset_m: f32,
}

impl StaticMap {
    /// y = k1·u + k2·h + y0.
    #[inline]
    pub fn output(&self, input_v: f32, h: f32) -> f32 {
        self.k1_m_per_v * input_v + self.k2_m_per_h * h + self.offset_m
    }

    fn validate(&self) -> Result<(), ParamError> {
        finite("k1_m_per_v", self.k1_m_per_v)?;
        finite("k2_m_per_h", self.k2_m_per_h)?;
        finite("offset_m", self.offset_m)?;
        if self.k1_m_per_v == 0.0 && self.k2_m_per_h == 0.0 {
            return Err(ParamError::OutOfRange {
                field: "k1_m_per_v",
                value: 0.0,
                requirement: "nonzero when k2_m_per_h is zero",
            });
        }
        Ok(())
    }
}

/// The asymmetric terms of seed 001 (both zero for the standard model).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "serde", serde(deny_unknown_fields))]
pub struct Asymmetry {
    /// δ: asymmetric factor, ΔE = δ·u·sgn(u̇) added to ḣ \[h per V·s\].
    pub delta_per_v_s: f32,
    /// φ: input shift, U(t) = u(t − φ) \[s\]; |φ| ≤ the sample period.
    pub input_shift_s: f32,
}

/// A validated static (or asymmetric static) hysteresis model: settings only.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StaticModel {
    hysteresis: BoucWen,
    map: StaticMap,
    /// δ·T/2 \[h per V\]: half of the δ-increment per unit of mean input.
    delta_half_step: f32,
    /// φ/T: the fractional input shift.
    shift_fraction: f32,
    sample_period_s: f32,
    /// c = 1 − e^(−T/τ_v) of the input lag (0: none).
    lag_fraction: f32,
    /// b = 1 − c·τ_v/T: the share of the current command's step that reaches v (first-order hold).
    lag_hold_share: f32,
    /// τ_v \[s\] (0: none).
    lag_s: f32,
}

/// The state of a [`StaticModel`].
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ModelState {
    /// Last input u\[k−1\] \[V\].
    pub input_v: f32,
    /// Bouc-Wen state: its `input_v` is the shifted input U\[k−1\], its `h` the hysteretic state.
    pub hysteresis: HysteresisState,
}

impl ModelState {
    /// At rest at input `input_v`.
    pub fn at_rest(input_v: f32) -> Self {
        Self {
            input_v,
            hysteresis: HysteresisState::at_rest(input_v),
        }
    }
}

/// Shortest input lag, in sample periods: a shorter one is a one-sample delay of h, not a lag.
pub const MIN_INPUT_LAG_PERIODS: f32 = 1.0;

/// Longest input lag \[s\]: beyond it the lag is creep, not rate-dependent hysteresis.
pub const MAX_INPUT_LAG_S: f32 = 1.0;

/// Refuses an input lag τ_v = `lag_s` other than 0 or within
/// \[[`MIN_INPUT_LAG_PERIODS`]·T, [`MAX_INPUT_LAG_S`]\] at the sample period `period_s` = T (NaN
/// included), naming `hysteresis_lag_s`: the one bound of the lag, for the model and for the
/// effect parameters that carry it.
pub(crate) fn check_input_lag(lag_s: f32, period_s: f32) -> Result<(), ParamError> {
    if lag_s == 0.0 || (lag_s >= MIN_INPUT_LAG_PERIODS * period_s && lag_s <= MAX_INPUT_LAG_S) {
        return Ok(());
    }
    Err(ParamError::OutOfRange {
        field: "hysteresis_lag_s",
        value: lag_s,
        requirement: "0 (none) or between one sample period and 1 s",
    })
}

/// Input step of [`StaticModel::first_loading`] \[V\].
pub const FIRST_LOADING_STEP_V: f32 = 0.01;

impl StaticModel {
    /// The standard (symmetric) model of seed 001: y = k1·u + k2·h + y0.
    pub fn new(hysteresis: BoucWen, map: StaticMap) -> Result<Self, ParamError> {
        map.validate()?;
        Ok(Self {
            hysteresis,
            map,
            delta_half_step: 0.0,
            shift_fraction: 0.0,
            sample_period_s: 0.0,
            lag_fraction: 0.0,
            lag_hold_share: 0.0,
            lag_s: 0.0,
        })
    }

    /// The asymmetric model of seed 001 sampled at `sample_period_s` (see the module doc for the
    /// reading). Refuses |φ| > T.
    pub fn asymmetric(
        hysteresis: BoucWen,
        map: StaticMap,
        asymmetry: Asymmetry,
        sample_period_s: f32,
    ) -> Result<Self, ParamError> {
        map.validate()?;
        positive("sample_period_s", sample_period_s)?;
        finite("delta_per_v_s", asymmetry.delta_per_v_s)?;
        finite("input_shift_s", asymmetry.input_shift_s)?;
        if asymmetry.input_shift_s.abs() > sample_period_s {
            return Err(ParamError::OutOfRange {
                field: "input_shift_s",
                value: asymmetry.input_shift_s,
                requirement: "within ± one sample period",
            });
        }
        Ok(Self {
            hysteresis,
            map,
            delta_half_step: 0.5 * asymmetry.delta_per_v_s * sample_period_s,
            shift_fraction: asymmetry.input_shift_s / sample_period_s,
            sample_period_s,
            lag_fraction: 0.0,
            lag_hold_share: 0.0,
            lag_s: 0.0,
        })
    }

    /// Seed 001's model with the asymmetry `asymmetry`: [`StaticModel::new`] when δ = φ = 0 (a
    /// zero asymmetry is the symmetric model, with no sample period to check), otherwise
    /// [`StaticModel::asymmetric`] at `sample_period_s`. The one place that chooses between them.
    pub fn with_asymmetry(
        hysteresis: BoucWen,
        map: StaticMap,
        asymmetry: Asymmetry,
        sample_period_s: f32,
    ) -> Result<Self, ParamError> {
        if asymmetry == Asymmetry::default() {
            Self::new(hysteresis, map)
        } else {
            Self::asymmetric(hysteresis, map, asymmetry, sample_period_s)
        }
    }

    /// This model with its Bouc-Wen operator driven by a first-order lag of the command, time
    /// constant `lag_s` = τ_v \[s\] at the sample period `sample_period_s` (module doc). `lag_s`
    /// = 0 leaves the model as it is. Refuses a negative or non-finite τ_v, a τ_v below
    /// [`MIN_INPUT_LAG_PERIODS`] sample periods or above [`MAX_INPUT_LAG_S`], and a lag on the
    /// asymmetric model.
    pub fn with_input_lag(mut self, lag_s: f32, sample_period_s: f32) -> Result<Self, ParamError> {
        finite("hysteresis_lag_s", lag_s)?;
        if lag_s == 0.0 {
            self.lag_fraction = 0.0;
            self.lag_hold_share = 0.0;
            self.lag_s = 0.0;
            return Ok(self);
        }
        let period = positive("sample_period_s", sample_period_s)?;
        if self.is_asymmetric() {
            return Err(ParamError::OutOfRange {
                field: "hysteresis_lag_s",
                value: lag_s,
                requirement: "0 on the asymmetric model (the lag drives the standard operator)",
            });
        }
        check_input_lag(lag_s, period)?;
        let x = f64::from(period) / f64::from(lag_s);
        let c = -libm::expm1(-x);
        self.lag_fraction = c as f32;
        self.lag_hold_share = (1.0 - c / x) as f32;
        self.lag_s = lag_s;
        self.sample_period_s = period;
        Ok(self)
    }

    /// τ_v of the input lag \[s\] (0: none).
    pub fn input_lag_s(&self) -> f32 {
        self.lag_s
    }

    /// c = 1 − e^(−T/τ_v): the share of the gap u\[k−1\] − v\[k−1\] the operator's input closes per
    /// sample (0: no lag).
    pub fn input_lag_fraction(&self) -> f32 {
        self.lag_fraction
    }

    /// b = 1 − c·τ_v/T: the share of the current command's step that reaches v in the same
    /// sample (0: no lag).
    pub fn input_lag_hold_share(&self) -> f32 {
        self.lag_hold_share
    }

    /// Whether the operator is driven by a lag of the command.
    pub fn has_input_lag(&self) -> bool {
        self.lag_fraction != 0.0
    }

    /// Whether the one-step map differs from the standard one (asymmetric terms or an input lag):
    /// the state then moves while the command is held, and the compensator's small-step paths
    /// do not apply.
    pub(crate) fn has_extra_terms(&self) -> bool {
        self.is_asymmetric() || self.has_input_lag()
    }

    /// The Bouc-Wen operator.
    pub fn hysteresis(&self) -> &BoucWen {
        &self.hysteresis
    }

    /// The linear map.
    pub fn map(&self) -> StaticMap {
        self.map
    }

    /// The asymmetric terms (zero for the standard model).
    pub fn asymmetry(&self) -> Asymmetry {
        if self.sample_period_s == 0.0 {
            return Asymmetry::default();
        }
        Asymmetry {
            delta_per_v_s: 2.0 * self.delta_half_step / self.sample_period_s,
            input_shift_s: self.shift_fraction * self.sample_period_s,
        }
    }

    /// Whether the asymmetric terms are active.
    pub fn is_asymmetric(&self) -> bool {
        self.delta_half_step != 0.0 || self.shift_fraction != 0.0
    }

    /// Advances the state to input `input_v` and returns the output y \[m\]. A non-finite input holds
    /// the previous one; the input is clamped into the operator's range.
    #[inline]
    pub fn step(&self, state: &mut ModelState, input_v: f32) -> f32 {
        let previous = self.hysteresis.sanitize_input(state.input_v, 0.0);
        let u = self.hysteresis.sanitize_input(input_v, previous);
        *state = self.next_state(state, u);
        self.map.output(u, state.hysteresis.h)
    }

    /// The output y \[m\] of a state.
    #[inline]
    pub fn output(&self, state: &ModelState) -> f32 {
        self.map.output(state.input_v, state.hysteresis.h)
    }

    /// The state after the input moves from `state.input_v` to the (already sanitised) `u`.
    /// Shared by [`StaticModel::step`] and the inverse compensator, so both use one discretisation.
    #[inline]
    pub(crate) fn next_state(&self, state: &ModelState, u: f32) -> ModelState {
        if self.lag_fraction != 0.0 {
            // v[k] = v[k−1] + c·(u[k−1] − v[k−1]) + b·(u[k] − u[k−1]).
            let v0 = state.hysteresis.input_v;
            let v = v0
                + self.lag_fraction * (state.input_v - v0)
                + self.lag_hold_share * (u - state.input_v);
            let moved = self.hysteresis.advance(state.hysteresis.h, v - v0);
            return ModelState {
                input_v: u,
                hysteresis: HysteresisState {
                    input_v: v,
                    h: if moved.is_finite() {
                        moved
                    } else {
                        state.hysteresis.h
                    },
                },
            };
        }
        let previous = state.input_v;
        let du = u - previous;
        let shifted = u - self.shift_fraction * du;
        let mut h = state.hysteresis.h;
        let half = if du > 0.0 {
            self.delta_half_step * 0.5 * (u + previous)
        } else if du < 0.0 {
            -self.delta_half_step * 0.5 * (u + previous)
        } else {
            0.0
        };
        if self.delta_half_step == 0.0 {
            h = self
                .hysteresis
                .advance(h, shifted - state.hysteresis.input_v);
        } else {
            // The δ-term carries h past the Bouc-Wen bound H (seed 001 Case II reaches 1.04·H):
            // integrate unclamped and clamp only at the wider safety bound.
            let moved = self
                .hysteresis
                .advance_unclamped(h + half, shifted - state.hysteresis.input_v)
                + half;
            let bound = self.state_limit();
            if moved.is_finite() {
                h = clamp(moved, -bound, bound);
            }
        }
        ModelState {
            input_v: u,
            hysteresis: HysteresisState {
                input_v: shifted,
                h,
            },
        }
    }

    /// dy/du\[k\] of the one-step map at the end of a step from `from` to `reached` (whose input moved
    /// in direction `direction`): `k1 + k2·((1 − φ/T)·dh/dU + δ·T/2·sgn Δu)`, with dh/dU taken on the
    /// branch the shifted input U actually moved along. The exact derivative of the path integral
    /// (used as the Newton slope of the inverse).
    #[inline]
    pub(crate) fn step_slope(
        &self,
        from: &ModelState,
        reached: &ModelState,
        direction: f32,
    ) -> f32 {
        if self.lag_fraction != 0.0 {
            // dy/du = k1 + k2·b·dh/dv, on the branch v moved along.
            let dh_dv = self.lagged_input_slope(from, reached, direction);
            return self.map.k1_m_per_v + self.map.k2_m_per_h * self.lag_hold_share * dh_dv;
        }
        let shifted_move = reached.hysteresis.input_v - from.hysteresis.input_v;
        let branch = if shifted_move != 0.0 {
            shifted_move
        } else {
            direction * (1.0 - self.shift_fraction)
        };
        // On the asymmetric model's safety clamp h no longer moves with u.
        let dh_du =
            if self.delta_half_step != 0.0 && reached.hysteresis.h.abs() >= self.state_limit() {
                0.0
            } else {
                self.hysteresis.slope(reached.hysteresis.h, branch)
            };
        let s = if direction < 0.0 { -1.0 } else { 1.0 };
        self.map.k1_m_per_v
            + self.map.k2_m_per_h * ((1.0 - self.shift_fraction) * dh_du + self.delta_half_step * s)
    }

    /// dh/dv \[1/V\]: the operator's slope with respect to its input v (the lagged command of a
    /// model with an input lag), at the state `reached` on the branch v moved along from `from`
    /// (`direction` when it did not move).
    pub(crate) fn lagged_input_slope(
        &self,
        from: &ModelState,
        reached: &ModelState,
        direction: f32,
    ) -> f32 {
        let v_move = reached.hysteresis.input_v - from.hysteresis.input_v;
        let branch = if v_move != 0.0 { v_move } else { direction };
        self.hysteresis.slope(reached.hysteresis.h, branch)
    }

    /// The sample period the asymmetric terms were discretised at \[s\] (0 for the symmetric model).
    pub fn sample_period_s(&self) -> f32 {
        self.sample_period_s
    }

    /// The largest |h| the model's state can take: the Bouc-Wen bound, times
    /// [`ASYMMETRIC_STATE_FACTOR`] when δ ≠ 0.
    pub fn state_limit(&self) -> f32 {
        if self.delta_half_step != 0.0 {
            ASYMMETRIC_STATE_FACTOR * self.hysteresis.state_bound()
        } else {
            self.hysteresis.state_bound()
        }
    }

    /// The first loading from rest at `u0_v` to `u1_v` (> `u0_v`) in steps of
    /// [`FIRST_LOADING_STEP_V`] (at most 10⁶): the output at rest `y(u0)` and the secant gain
    /// `(y(u1) − y(u0)) / (u1 − u0)` \[m, m/V\] — the stage file's rest output and the linear
    /// baseline's gain, computed the same way by the stage file's validation and by the firmware
    /// for an uploaded set.
    pub fn first_loading(&self, u0_v: f32, u1_v: f32) -> (f32, f32) {
        let mut state = ModelState::at_rest(u0_v);
        let rest = self.output(&state);
        let steps = libm::ceilf((u1_v - u0_v) / FIRST_LOADING_STEP_V).clamp(1.0, 1e6) as u32;
        let mut top = rest;
        for k in 1..=steps {
            top = self.step(
                &mut state,
                (u0_v + k as f32 * FIRST_LOADING_STEP_V).min(u1_v),
            );
        }
        (rest, (top - rest) / (u1_v - u0_v))
    }

    /// The extreme one-step slopes dy/du over all reachable states and both directions.
    pub fn slope_range(&self) -> (f32, f32) {
        let (lo, hi) = self.hysteresis.slope_range_within(self.state_limit());
        let w = 1.0 - self.shift_fraction;
        let k2 = self.map.k2_m_per_h;
        let spread = (k2 * self.delta_half_step).abs();
        let a = self.map.k1_m_per_v + k2 * w * lo;
        let b = self.map.k1_m_per_v + k2 * w * hi;
        (a.min(b) - spread, a.max(b) + spread)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bouc_wen::BoucWenParams;

    fn seed001_case1() -> BoucWen {
        BoucWen::new(BoucWenParams {
            a: -7.02182e-2,
            beta: 4.45753,
            gamma: 3.49259,
            n: 3.05869,
        })
        .unwrap()
    }

    #[test]
    fn symmetric_asymmetry_reduces_to_standard() {
        let map = StaticMap {
            k1_m_per_v: -3.51711e-7,
            k2_m_per_h: -1.94566e-6,
            offset_m: 0.0,
        };
        let standard = StaticModel::new(seed001_case1(), map).unwrap();
        let zero =
            StaticModel::asymmetric(seed001_case1(), map, Asymmetry::default(), 1e-4).unwrap();
        let (mut s1, mut s2) = (ModelState::default(), ModelState::default());
        for k in 0..10_000 {
            let t = k as f32 * 1e-4;
            let u = 10.0 - 10.0 * libm::cosf(4.0 * core::f32::consts::PI * t);
            assert_eq!(standard.step(&mut s1, u), zero.step(&mut s2, u));
        }
    }

    #[test]
    fn delta_changes_the_loop_and_stays_periodic() {
        let map = StaticMap {
            k1_m_per_v: -3.51711e-7,
            k2_m_per_h: -1.94566e-6,
            offset_m: 0.0,
        };
        let asym = Asymmetry {
            delta_per_v_s: -1.95e-2,
            input_shift_s: 5.16e-7,
        };
        let standard = StaticModel::new(seed001_case1(), map).unwrap();
        let model = StaticModel::asymmetric(seed001_case1(), map, asym, 1e-4).unwrap();
        let (mut s1, mut s2) = (ModelState::default(), ModelState::default());
        let mut max_diff = 0.0f32;
        let mut end_of_first = 0.0;
        for k in 0..10_000 {
            let t = k as f32 * 1e-4;
            let u = 10.0 - 10.0 * libm::cosf(4.0 * core::f32::consts::PI * t);
            let y1 = standard.step(&mut s1, u);
            let y2 = model.step(&mut s2, u);
            max_diff = max_diff.max((y1 - y2).abs());
            if k == 4999 {
                end_of_first = y2;
            }
        }
        let end = model.output(&s2);
        // The δ-term moves the output by a visible fraction of a micrometre ...
        assert!(max_diff > 2e-8 && max_diff < 1e-6, "max diff {max_diff}");
        // ... and, for this time-symmetric input, does not drift from cycle to cycle.
        assert!((end - end_of_first).abs() < 1e-9, "{end} vs {end_of_first}");
    }

    #[test]
    fn shift_beyond_one_sample_is_refused() {
        let map = StaticMap {
            k1_m_per_v: 1e-6,
            k2_m_per_h: 1e-7,
            offset_m: 0.0,
        };
        let asym = Asymmetry {
            delta_per_v_s: 0.0,
            input_shift_s: 2e-4,
        };
        assert!(matches!(
            StaticModel::asymmetric(seed001_case1(), map, asym, 1e-4),
            Err(ParamError::OutOfRange {
                field: "input_shift_s",
                ..
            })
        ));
    }
}
