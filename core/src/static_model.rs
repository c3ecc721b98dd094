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
//!
//! # Hysteresis whose gain rises with the input's speed (rate-dependent Bouc-Wen)
//! [`StaticModel::with_rate_gain`]: the operator's input gain grows with the speed of its input
//! (the command, or the lagged v when there is a lag),
//!
//! ```text
//! ḣ = A·(1 + c·|v̇|)·v̇ − β·|v̇|·|h|^(n−1)·h − γ·v̇·|h|^n,   y = k1·u + k2·h + y0
//! ```
//!
//! the first-order member of the rate-dependent Bouc-Wen family, whose coefficients are
//! functions of the input rate (the frequency-dependent hysteresis of piezo actuators reported
//! e.g. by Zhu, Bian & Rui, "Online parameter identification of the asymmetrical Bouc–Wen model
//! for piezoelectric actuators", Precision Engineering 38, 2014, 921–927; here A grows linearly
//! with |v̇|). At a constant speed the loop is a
//! Bouc-Wen loop of gain A·k, k = 1 + c·|v̇|: taller and wider as the rate rises, without the
//! lag's tilt. Sampled with the sample's mean speed, k = 1 + (c/T)·|Δv|, constant over the
//! sample: with h = k^(1/n)·g the law is the standard one in g over the input k^(1 − 1/n)·Δv,
//! `dg/dv' = A − (β·s·sgn g + γ)·|g|^n`, so the sample is integrated exactly by the operator's
//! own paths, h₁ = k^(1/n)·G(h₀/k^(1/n), k^(1 − 1/n)·Δv). The state is clamped at the bound
//! reached at the gain of a whole-span move in one sample; the compensator's monotonicity check
//! covers the gains its slew limit allows ([`StaticModel::slope_range_for_step`]). Sign
//! convention: c ≥ 0 \[s/V\], 0 is rate-independent; it needs a bounded operator
//! (β + γ·sgn A > 0) with a finite input range.

use crate::bouc_wen::{BoucWen, BoucWenParams, HysteresisState};
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

/// Which one-step update a model runs, chosen once when built: one test per sample picks it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum OneStep {
    /// The operator driven by the (shifted) command, with the asymmetric terms when there are.
    Command,
    /// The operator driven by a first-order lag of the command.
    Lag,
    /// The operator's gain rising with its input's speed (with or without the lag).
    RateGain,
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
    /// c/T \[1/V\]: the operator's gain factor per volt of its input's move in one sample,
    /// k = 1 + (c/T)·|Δv| (0: rate-independent).
    rate_per_v: f32,
    /// c \[s/V\] of the rate-dependent gain (0: none).
    rate_gain_s_per_v: f32,
    /// 1/n of the operator (the rate-dependent gain's scaling h = k^(1/n)·g).
    inverse_exponent: f32,
    /// The clamp of |h| with a rate-dependent gain: the bound reached at the gain of a move over
    /// the whole input span in one sample (0: none).
    rate_state_limit: f32,
    /// The one-step update these settings run.
    one_step: OneStep,
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

/// Largest rate-dependent gain c \[s/V\]: the operator's gain doubles at 1 kV/s (a 10 Hz sine
/// over 16 V); a stronger dependence is not hysteresis that a one-sample gain describes.
pub const MAX_RATE_GAIN_S_PER_V: f32 = 1e-3;

/// Refuses a rate-dependent gain c = `gain_s_per_v` other than 0 or within
/// (0, [`MAX_RATE_GAIN_S_PER_V`]] (NaN included), naming `hysteresis_rate_gain_s_per_v`.
pub(crate) fn check_rate_gain(gain_s_per_v: f32) -> Result<(), ParamError> {
    if gain_s_per_v == 0.0 || (gain_s_per_v > 0.0 && gain_s_per_v <= MAX_RATE_GAIN_S_PER_V) {
        return Ok(());
    }
    Err(ParamError::OutOfRange {
        field: "hysteresis_rate_gain_s_per_v",
        value: gain_s_per_v,
        requirement: "0 (none) or in (0, 1e-3] s/V",
    })
}

/// The state after a sample whose command is `u` and whose operator input moved to `v`, its h to
/// `moved` (the last h kept when that is not finite).
#[inline(always)]
fn moved_along(state: &ModelState, u: f32, v: f32, moved: f32) -> ModelState {
    ModelState {
        input_v: u,
        hysteresis: HysteresisState {
            input_v: v,
            h: if moved.is_finite() {
                moved
            } else {
                state.hysteresis.h
            },
        },
    }
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
            rate_per_v: 0.0,
            rate_gain_s_per_v: 0.0,
            inverse_exponent: 1.0 / hysteresis.params().n,
            rate_state_limit: 0.0,
            one_step: OneStep::Command,
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
            rate_per_v: 0.0,
            rate_gain_s_per_v: 0.0,
            inverse_exponent: 1.0 / hysteresis.params().n,
            rate_state_limit: 0.0,
            one_step: OneStep::Command,
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
            self.choose_one_step();
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
        self.choose_one_step();
        Ok(self)
    }

    /// τ_v of the input lag \[s\] (0: none).
    pub fn input_lag_s(&self) -> f32 {
        self.lag_s
    }

    /// This model with the operator's gain rising with its input's speed,
    /// `A·(1 + c·|v̇|)` with c = `gain_s_per_v` \[s/V\], at the sample period `sample_period_s`
    /// (module doc). 0 leaves the model as it is. Refuses c outside [0, [`MAX_RATE_GAIN_S_PER_V`]],
    /// a gain on the asymmetric model, and a gain on an operator that is not bounded
    /// (β + γ·sgn A ≤ 0) or has no finite input range: its state bound at speed would not be.
    pub fn with_rate_gain(
        mut self,
        gain_s_per_v: f32,
        sample_period_s: f32,
    ) -> Result<Self, ParamError> {
        finite("hysteresis_rate_gain_s_per_v", gain_s_per_v)?;
        if gain_s_per_v == 0.0 {
            self.rate_per_v = 0.0;
            self.rate_gain_s_per_v = 0.0;
            self.rate_state_limit = 0.0;
            self.choose_one_step();
            return Ok(self);
        }
        let period = positive("sample_period_s", sample_period_s)?;
        check_rate_gain(gain_s_per_v)?;
        let refuse = |requirement| ParamError::OutOfRange {
            field: "hysteresis_rate_gain_s_per_v",
            value: gain_s_per_v,
            requirement,
        };
        if self.is_asymmetric() {
            return Err(refuse(
                "0 on the asymmetric model (the gain scales the standard operator)",
            ));
        }
        let (lo, hi) = self.hysteresis.input_range_v();
        let span = f64::from(hi) - f64::from(lo);
        let rate_per_v = f64::from(gain_s_per_v) / f64::from(period);
        let limit = self
            .rate_reach(rate_per_v * span, span)
            .filter(|l| l.is_finite() && *l < f64::from(f32::MAX) / 2.0)
            .ok_or_else(|| {
                refuse(
                    "0 unless the operator is bounded (beta + gamma·sgn A > 0) over a finite \
                     input range",
                )
            })?;
        self.rate_per_v = rate_per_v as f32;
        self.rate_gain_s_per_v = gain_s_per_v;
        self.rate_state_limit = (limit * (1.0 + 1e-5)) as f32 + f32::MIN_POSITIVE;
        self.sample_period_s = period;
        self.choose_one_step();
        Ok(self)
    }

    /// The largest |h| reached from rest when every sample's gain factor is at most
    /// 1 + `extra_gain` over the input span `span_v`: with h = k^(1/n)·g, g runs the standard
    /// operator over k^(1 − 1/n)·span, so `k^(1/n)·min(H, L(k^(1 − 1/n)·span))`.
    fn rate_reach(&self, extra_gain: f64, span_v: f64) -> Option<f64> {
        let k = 1.0 + extra_gain;
        let inv_n = f64::from(self.inverse_exponent);
        let reach = self
            .hysteresis
            .bounded_reach_over(libm::pow(k, 1.0 - inv_n) * span_v)?;
        Some(libm::pow(k, inv_n) * reach)
    }

    /// Picks the one-step update the settings need.
    fn choose_one_step(&mut self) {
        self.one_step = if self.rate_per_v != 0.0 {
            OneStep::RateGain
        } else if self.lag_fraction != 0.0 {
            OneStep::Lag
        } else {
            OneStep::Command
        };
    }

    /// c of the rate-dependent gain \[s/V\] (0: none).
    pub fn rate_gain_s_per_v(&self) -> f32 {
        self.rate_gain_s_per_v
    }

    /// Whether the operator's gain depends on its input's speed.
    pub fn has_rate_gain(&self) -> bool {
        self.rate_per_v != 0.0
    }

    /// [`StaticModel::next_state`] with an input lag:
    /// v\[k\] = v\[k−1\] + c·(u\[k−1\] − v\[k−1\]) + b·(u\[k\] − u\[k−1\]), h moved along v's move.
    #[inline(always)]
    fn next_state_lagged(&self, state: &ModelState, u: f32) -> ModelState {
        let v0 = state.hysteresis.input_v;
        let v = v0
            + self.lag_fraction * (state.input_v - v0)
            + self.lag_hold_share * (u - state.input_v);
        let moved = self.hysteresis.advance(state.hysteresis.h, v - v0);
        moved_along(state, u, v, moved)
    }

    /// [`StaticModel::next_state`] with a rate-dependent gain (out of line: the models without
    /// one keep their path as it was): v is the command, or its lag, and h moves along v's move.
    #[cold]
    #[inline(never)]
    fn next_state_with_rate_gain(&self, state: &ModelState, u: f32) -> ModelState {
        let v0 = state.hysteresis.input_v;
        let v = if self.lag_fraction != 0.0 {
            v0 + self.lag_fraction * (state.input_v - v0)
                + self.lag_hold_share * (u - state.input_v)
        } else {
            u
        };
        let moved = self.rate_advance(state.hysteresis.h, v - v0);
        moved_along(state, u, v, moved)
    }

    /// [`StaticModel::step_slope`] with a rate-dependent gain: `k1 + k2·dh₁/dv`, times b with a lag.
    #[cold]
    #[inline(never)]
    fn step_slope_with_rate_gain(
        &self,
        from: &ModelState,
        reached: &ModelState,
        direction: f32,
    ) -> f32 {
        let v_move = reached.hysteresis.input_v - from.hysteresis.input_v;
        let branch = if v_move != 0.0 { v_move } else { direction };
        let dh_dv = self.rate_slope(from.hysteresis.h, reached.hysteresis.h, v_move, branch);
        let share = if self.lag_fraction != 0.0 {
            self.lag_hold_share
        } else {
            1.0
        };
        self.map.k1_m_per_v + self.map.k2_m_per_h * share * dh_dv
    }

    /// The operator's increment from `h` along an input move `delta_v` with the rate-dependent
    /// gain k = 1 + (c/T)·|Δv|: h₁ = k^(1/n)·G(h/k^(1/n), k^(1 − 1/n)·Δv) (module doc), clamped
    /// to the rate bound.
    fn rate_advance(&self, h: f32, delta_v: f32) -> f32 {
        if !delta_v.is_finite() {
            return self.hysteresis.advance(h, delta_v);
        }
        let k = 1.0 + self.rate_per_v * delta_v.abs();
        let (scale, path) = self.rate_scales(k);
        let moved = self.hysteresis.advance_unclamped(h / scale, path * delta_v) * scale;
        let limit = self.rate_state_limit;
        if moved.is_finite() {
            clamp(moved, -limit, limit)
        } else {
            clamp(h, -limit, limit)
        }
    }

    /// (k^(1/n), k^(1 − 1/n)) for a gain factor k ≥ 1.
    #[inline]
    fn rate_scales(&self, k: f32) -> (f32, f32) {
        let inv_n = self.inverse_exponent;
        let scale = if inv_n == 1.0 {
            k
        } else if inv_n == 0.5 {
            libm::sqrtf(k)
        } else {
            crate::math::pow_nonnegative(k, inv_n)
        };
        (scale, k / scale)
    }

    /// dh₁/dΔv of the operator's step from `h0` to `h1` along `delta_v` (its branch `branch` when
    /// it did not move). Without a rate gain the operator's slope at h₁. With one
    /// ([`StaticModel::rate_slope`]), f(h) = A·k − (β·s·sgn h + γ)·|h|^n at the sample's k plus
    /// the gain's share,
    /// ∂h₁/∂k·(c/T)·s with `∂h₁/∂k = (h₁ − h₀·f(h₁)/f(h₀))/(n·k) + (1 − 1/n)·Δv·f(h₁)/k`
    /// (the flow's sensitivity to its start is f(h₁)/f(h₀) in one dimension).
    #[inline(always)]
    fn operator_slope(&self, h0: f32, h1: f32, delta_v: f32, branch: f32) -> f32 {
        if self.rate_per_v != 0.0 {
            return self.rate_slope(h0, h1, delta_v, branch);
        }
        self.hysteresis.slope(h1, branch)
    }

    /// [`StaticModel::operator_slope`] with a rate-dependent gain.
    fn rate_slope(&self, h0: f32, h1: f32, delta_v: f32, branch: f32) -> f32 {
        let plain = self.hysteresis.slope(h1, branch);
        let a = self.hysteresis.params().a;
        let k = 1.0 + self.rate_per_v * delta_v.abs();
        let f1 = plain + a * (k - 1.0);
        let f0 = self.hysteresis.slope(h0, branch) + a * (k - 1.0);
        let ratio = f1 / f0;
        let ratio = if ratio.is_finite() { ratio } else { 1.0 };
        let inv_n = self.inverse_exponent;
        let dh_dk = (h1 - h0 * ratio) * inv_n / k + (1.0 - inv_n) * delta_v * f1 / k;
        let s = if branch < 0.0 { -1.0 } else { 1.0 };
        f1 + dh_dk * self.rate_per_v * s
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
        self.one_step != OneStep::Command || self.is_asymmetric()
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
        if self.one_step != OneStep::Command {
            return if self.one_step == OneStep::Lag {
                self.next_state_lagged(state, u)
            } else {
                self.next_state_with_rate_gain(state, u)
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
        if self.one_step != OneStep::Command {
            if self.one_step == OneStep::RateGain {
                return self.step_slope_with_rate_gain(from, reached, direction);
            }
            // dy/du = k1 + k2·b·dh/dv, on the branch v moved along.
            let v_move = reached.hysteresis.input_v - from.hysteresis.input_v;
            let branch = if v_move != 0.0 { v_move } else { direction };
            let dh_dv = self.hysteresis.slope(reached.hysteresis.h, branch);
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
        self.operator_slope(from.hysteresis.h, reached.hysteresis.h, v_move, branch)
    }

    /// The sample period the asymmetric terms were discretised at \[s\] (0 for the symmetric model).
    pub fn sample_period_s(&self) -> f32 {
        self.sample_period_s
    }

    /// The largest |h| the model's state can take: the Bouc-Wen bound, times
    /// [`ASYMMETRIC_STATE_FACTOR`] when δ ≠ 0.
    pub fn state_limit(&self) -> f32 {
        if self.rate_per_v != 0.0 {
            self.rate_state_limit
        } else if self.delta_half_step != 0.0 {
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

    /// The extreme one-step slopes dy/du over all reachable states and both directions (with a
    /// rate-dependent gain: for moves up to the whole input span in one sample,
    /// [`StaticModel::slope_range_for_step`]).
    pub fn slope_range(&self) -> (f32, f32) {
        if self.rate_per_v != 0.0 {
            let (lo, hi) = self.hysteresis.input_range_v();
            return self.slope_range_for_step(hi - lo);
        }
        let (lo, hi) = self.hysteresis.slope_range_within(self.state_limit());
        let w = 1.0 - self.shift_fraction;
        let k2 = self.map.k2_m_per_h;
        let spread = (k2 * self.delta_half_step).abs();
        let a = self.map.k1_m_per_v + k2 * w * lo;
        let b = self.map.k1_m_per_v + k2 * w * hi;
        (a.min(b) - spread, a.max(b) + spread)
    }

    /// The extreme one-step slopes dy/du over the states reachable with input moves of at most
    /// `max_step_v` \[V\] per sample and both directions. Without a rate gain,
    /// [`StaticModel::slope_range`]. With one (module doc), the gain factor stays below
    /// k_c = 1 + (c/T)·M, the states below H_c = k_c^(1/n)·min(H, L(k_c^(1 − 1/n)·S)) (S the
    /// input span), and the slope is f(h₁) + ∂h₁/∂k·(c/T)·s with f = A·k − κ·|h|^n: for n = 1,
    /// ∂h₁/∂k·(c/T)·s = A·(k − 1)·g(κΔv), g(z) = (1 − e^(−z))/z ≤ e^(J·M) with
    /// J = n·(β + |γ|)·H_c^(n−1). The envelope takes A's factor over [1, k_c + (k_c − 1)·e^(J·M)]
    /// and |h|^n over [0, H_c^n] on the loading and the unloading branch.
    pub fn slope_range_for_step(&self, max_step_v: f32) -> (f32, f32) {
        if self.rate_per_v == 0.0 {
            return self.slope_range();
        }
        let BoucWenParams { a, beta, gamma, n } = self.hysteresis.params();
        let (lo_v, hi_v) = self.hysteresis.input_range_v();
        let span = f64::from(hi_v) - f64::from(lo_v);
        let step = f64::from(max_step_v.max(0.0)).min(span);
        let extra = f64::from(self.rate_per_v) * step;
        let bound = self.rate_reach(extra, span).unwrap_or(f64::INFINITY);
        let (a, beta, gamma, nn) = (
            f64::from(a),
            f64::from(beta),
            f64::from(gamma),
            f64::from(n),
        );
        let lipschitz = nn * (beta + gamma.abs()) * libm::pow(bound, nn - 1.0);
        let k_hi = 1.0 + extra * (1.0 + libm::exp((lipschitz * step).min(700.0)));
        let hn = libm::pow(bound, nn);
        let (k1, k2) = (
            f64::from(self.map.k1_m_per_v),
            f64::from(self.map.k2_m_per_h),
        );
        let mut lo = f64::INFINITY;
        let mut hi = f64::NEG_INFINITY;
        for k in [1.0, k_hi] {
            for slope in [
                a * k,
                a * k - (beta + gamma) * hn,
                a * k - (gamma - beta) * hn,
            ] {
                let dy = k1 + k2 * slope;
                lo = lo.min(dy);
                hi = hi.max(dy);
            }
        }
        (lo as f32, hi as f32)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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

    /// The x stack (fixture, exponent `n`) with half its hysteretic gain in the map and the
    /// operator's gain rising with speed, c = `gain` \[s/V\], at 10 kHz.
    fn rate_stage(n: f32, gain: f32) -> StaticModel {
        let map = StaticMap {
            k1_m_per_v: 3.2e-7,
            k2_m_per_h: -1.6e-7,
            offset_m: 0.0,
        };
        StaticModel::new(crate::fixtures::x_stack(n, crate::STATE_LIMIT), map)
            .unwrap()
            .with_rate_gain(gain, 1e-4)
            .unwrap()
    }

    /// The rate gain's sampled model is the continuous law ḣ = A·(1 + c·|u̇|)·u̇ − β·|u̇|·|h|^(n−1)·h
    /// − γ·u̇·|h|^n for a command ramping linearly between samples: an f64 RK4 reference with
    /// 400 sub-steps per sample agrees within 1e-6 of the stroke over three periods of a 100 Hz
    /// 0–120 V sine, for n = 1, 2 and 1.5; and the loop is rate-dependent (the 100 Hz loop
    /// differs from the 1 Hz one's by more than 1 % of the stroke where c = 0 gives the same).
    #[test]
    fn a_rate_gain_is_the_continuous_law_sampled() {
        let period = 1e-4f64;
        let gain = 5e-6f64;
        for n in [1.0f32, 2.0, 1.5] {
            let model = rate_stage(n, gain as f32);
            let p = model.hysteresis().params();
            let (a, beta, gamma, nn) = (
                f64::from(p.a),
                f64::from(p.beta),
                f64::from(p.gamma),
                f64::from(n),
            );
            let drive = |k: usize| {
                60.0 - 60.0 * libm::cos(2.0 * core::f64::consts::PI * 100.0 * k as f64 * period)
            };
            let mut state = ModelState::at_rest(0.0);
            let mut h = 0.0f64;
            let mut worst = 0.0f64;
            for k in 1..300 {
                let (u0, u1) = (drive(k - 1), drive(k));
                let speed = (u1 - u0) / period;
                let f = |h: f64| {
                    a * (1.0 + gain * speed.abs()) * speed
                        - beta * speed.abs() * h.abs().powf(nn - 1.0) * h
                        - gamma * speed * h.abs().powf(nn)
                };
                let dt = period / 400.0;
                for _ in 0..400 {
                    let k1 = f(h);
                    let k2 = f(h + 0.5 * dt * k1);
                    let k3 = f(h + 0.5 * dt * k2);
                    let k4 = f(h + dt * k3);
                    h += dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4);
                }
                let y = f64::from(model.step(&mut state, u1 as f32));
                let want = 3.2e-7 * u1 - 1.6e-7 * h;
                worst = worst.max((y - want).abs());
            }
            let stroke = 3.2e-7 * 120.0 * 0.5;
            assert!(worst < 1e-6 * stroke, "n = {n}: worst {worst} m");
        }
        // Rate-dependent: the 100 Hz loop against the 1 Hz one at the same phase.
        let opening = |model: &StaticModel, freq: f32| {
            let mut state = ModelState::at_rest(0.0);
            let steps = (1.0 / (freq * 1e-4)) as usize;
            let mut up = 0.0f32;
            let mut down = 0.0f32;
            for k in 0..2 * steps {
                let phase = (k % steps) as f32 / steps as f32;
                let u = 60.0 - 60.0 * libm::cosf(2.0 * core::f32::consts::PI * phase);
                let y = model.step(&mut state, u);
                if k >= steps && k - steps == steps / 4 {
                    up = y;
                }
                if k >= steps && k - steps == 3 * steps / 4 {
                    down = y;
                }
            }
            down - up
        };
        let stroke = 3.2e-7 * 120.0 * 0.5;
        let (fast, slow) = (rate_stage(1.0, 5e-6), rate_stage(1.0, 0.0));
        let widened = opening(&fast, 100.0) - opening(&fast, 1.0);
        let unchanged = opening(&slow, 100.0) - opening(&slow, 1.0);
        assert!(widened.abs() > 0.01 * stroke, "{widened}");
        assert!(unchanged.abs() < 1e-4 * stroke, "{unchanged}");
    }

    /// A zero rate gain is the model it was built from, bit for bit.
    #[test]
    fn a_zero_rate_gain_changes_nothing() {
        let base = rate_stage(1.5, 0.0);
        let same = base.with_rate_gain(0.0, 1e-4).unwrap();
        assert_eq!(base, same);
        assert!(!same.has_rate_gain());
    }

    /// The one-step slope the compensator's Newton solve takes with a rate gain is the
    /// derivative of the one-step map: against central differences (over a quarter of the move,
    /// in f32) over both directions, states on both sides of zero and moves up to 10 V, within
    /// 1 % relative, for n = 1, 2 and 1.5.
    #[test]
    fn the_rate_gain_s_step_slope_is_the_map_s_derivative() {
        for n in [1.0f32, 2.0, 1.5] {
            let model = rate_stage(n, 5e-6);
            for h0 in [-8.0f32, -0.5, 0.0, 3.0, 12.0] {
                for du in [-10.0f32, -2.0, -0.1, 0.1, 2.0, 10.0] {
                    let from = ModelState {
                        input_v: 60.0,
                        hysteresis: HysteresisState {
                            input_v: 60.0,
                            h: h0,
                        },
                    };
                    let at = |d: f32| model.next_state(&from, 60.0 + d);
                    let reached = at(du);
                    let slope = model.step_slope(&from, &reached, du.signum());
                    let e = 0.25 * du.abs();
                    let (y_hi, y_lo) = (at(du + e), at(du - e));
                    let numeric = (model.output(&y_hi) - model.output(&y_lo)) / (2.0 * e);
                    let err = ((slope - numeric) / numeric).abs();
                    assert!(err < 1e-2, "n {n} h0 {h0} du {du}: {slope} vs {numeric}");
                }
            }
        }
    }

    /// Rate gains the model cannot run are refused when built, naming the field.
    #[test]
    fn rate_gain_refusals_name_the_field() {
        let base = rate_stage(1.0, 0.0);
        for gain in [-1e-6, 2e-3, f32::NAN, f32::INFINITY] {
            let got = base.with_rate_gain(gain, 1e-4);
            assert!(
                matches!(
                    got,
                    Err(ParamError::OutOfRange {
                        field: "hysteresis_rate_gain_s_per_v",
                        ..
                    }) | Err(ParamError::NonFinite {
                        field: "hysteresis_rate_gain_s_per_v"
                    })
                ),
                "{gain}: {got:?}"
            );
        }
        // An operator that is bounded only over its range (β + γ ≤ 0), and the asymmetric model.
        let ranged = BoucWen::with_input_range(
            BoucWenParams {
                a: 0.2,
                beta: 0.01,
                gamma: -0.02,
                n: 1.0,
            },
            0.0,
            120.0,
            crate::STATE_LIMIT,
        )
        .unwrap();
        let refused = StaticModel::new(ranged, base.map())
            .unwrap()
            .with_rate_gain(1e-6, 1e-4);
        assert!(
            matches!(
                refused,
                Err(ParamError::OutOfRange {
                    field: "hysteresis_rate_gain_s_per_v",
                    ..
                })
            ),
            "{refused:?}"
        );
        let asymmetric = StaticModel::asymmetric(
            *base.hysteresis(),
            base.map(),
            Asymmetry {
                delta_per_v_s: 1e-3,
                input_shift_s: 0.0,
            },
            1e-4,
        )
        .unwrap();
        assert!(asymmetric.with_rate_gain(1e-6, 1e-4).is_err());
    }
}
