//! The inverse feedforward compensator: desired displacement in, drive voltage out.
//!
//! For a static (or asymmetric static) model the compensator solves, at every sample, the one-step
//! inverse of the *discretised* forward map exactly:
//!
//! ```text
//! find u[k]:   k1·u[k] + k2·h(u[k]) + y0 = y_d[k]                          (static map, seed 001)
//! ```
//!
//! where `h(u[k])` is the Bouc-Wen state reached from the current state when the input moves from
//! `u[k−1]` to `u[k]` — the same function ([`StaticModel`]'s one-step update) that the forward model
//! uses, so forward(inverse(y_d)) = y_d up to f32 rounding. Along a monotone input increment Δu the
//! map is strictly monotone (checked when built, below), and the derivative of the exact path integral
//! is known in closed form, `dy/dΔu = k1 + k2·dh/du(h(Δu))`, so the solve is a safeguarded Newton
//! iteration on Δu inside `[0, Δu_limit]` in the direction that reduces the error: a first guess from
//! the slope at the current state, then corrections that keep a bracket around the root and bisect
//! when Newton would leave it, stopping as soon as one moves the voltage by less than 1e-7 of the
//! window (quadratic convergence in the smooth case: one correction suffices in a loop at a normal
//! rate; for n = 1 the
//! equation is the monotone scalar equation `k1·Δu + k2·(A − κh)·Δu·g(κΔu) = e`). The hysteresis state
//! is always advanced by the voltage actually commanded (after the window and slew limits).
//!
//! Per sample, [`Compensator::compensate`] first tries a small-step path chosen once when built
//! (n = 1: series reversion of the closed form; general n: series reversion of the Taylor flow
//! with one power per sample; both documented with their equations and error estimates on the
//! private functions `compensate_small_n1` / `compensate_small_general`), inlined, with the
//! per-parameter-set constants precomputed; every sample it refuses goes to the solve above.
//!
//! For the dynamic model of seed 000 the map is the force balance: the compensator commands
//!
//! ```text
//! k1·u[k] + h(u[k]) = m0·ẍ_d + c0·ẋ_d + k0·(x_d − x0)
//! ```
//!
//! with the reference's derivatives when they are known ([`Compensator::compensate_with_derivatives`],
//! inverse dynamics) and zero otherwise (quasi-static inverse).
//!
//! # Invertibility (checked when built)
//! The inverse exists and is unique only where the one-step map is strictly monotone in u. Over all
//! reachable hysteresis states and both directions, dy/du must keep one sign and
//! `min|dy/du| / max|dy/du| ≥ MIN_SLOPE_RATIO` (0.01): otherwise [`ParamError::NotInvertible`]. The
//! output window must lie inside the model's validated input range.
//!
//! # Safety of the per-sample path
//! Never panics, never returns NaN, never leaves `[output_min_v, output_max_v]`, never moves by more
//! than `slew_limit_v_per_s · sample_period_s` per sample (unless the window itself moved the last
//! voltage back inside). A non-finite reference holds the last voltage.
//!
//! # Slew limit (checked when built, [`CompensatorSettings::check_slew`])
//! A finite slew limit S must leave a full-window move at least [`MIN_WINDOW_TICKS`] ticks:
//! `S·T·MIN_WINDOW_TICKS ≤ output_max_v − output_min_v`. A faster limit is no limit at all (one
//! tick crosses the window); +∞ says "no limit" explicitly (offline analyses; the firmware's chain
//! refuses it, and bounds a finite one by what the drive can swing,
//! [`crate::io_chain::IoChain::check_limits`]).

use crate::bouc_wen::{
    relax_factor, relax_factor_inline, relax_series, BoucWenParams, HysteresisState,
};
use crate::dynamic_model::DynamicModel;
use crate::error::{finite, positive, ParamError, MIN_SLOPE_RATIO};
use crate::math::{self, clamp};
use crate::static_model::{ModelState, StaticMap, StaticModel};
use crate::Limits;

/// A step that h crosses zero in at the slew limit: direction, limit, q, κ, σ
/// ([`Compensator::slew_limited_n1`]).
type SlewCrossing = (f32, f32, f32, f32, f32);

/// Fewest ticks a full-window move may take at a finite slew limit: with fewer the limit does not
/// limit (a step across the whole window in one tick is what an unlimited command does). A narrow
/// window (say 20 V at 10 V per tick) is legitimate; how fast the drive may swing over its whole
/// span is the chain's bound ([`crate::io_chain::MIN_DRIVE_TICKS`]).
pub const MIN_WINDOW_TICKS: f32 = 2.0;

/// Smallest error factor per sample of the inverse's recursion through an input lag (see
/// [`crate::static_model`]): an error in v may change sign from one sample to the next, but
/// shrinks at least by half when it does.
pub const MIN_LAG_ERROR_FACTOR: f32 = -0.5;

/// Output limits of the compensator: an axis's [`Limits`] at a loop period.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CompensatorSettings {
    /// The window no command ever leaves and the largest rate of change of the commanded
    /// voltage (+∞ for none); the compensator ignores the envelope policy.
    pub limits: Limits,
    /// Loop period \[s\].
    pub sample_period_s: f32,
}

impl CompensatorSettings {
    /// The largest step per tick M \[V\] an exact output guard behind the compensator lets through
    /// for these settings: one f32 below the largest f32 ≤ `slew_limit_v_per_s · sample_period_s`
    /// (the product taken exactly, in f64), so M < S·T whether T is read as the f32 period or as
    /// 1/rate. +∞ for no slew limit; NaN when the limit or the period is not finite.
    pub fn guard_step_v(&self) -> f32 {
        let step = f64::from(self.limits.slew_limit_v_per_s) * f64::from(self.sample_period_s);
        if step.is_infinite() {
            return f32::INFINITY;
        }
        round_down_f32(step).next_down()
    }

    /// These settings for a controller (the compensator, the servo) in front of an exact output
    /// guard of step [`CompensatorSettings::guard_step_v`] M: the slew limit becomes the largest
    /// f32 S_c whose step `fl(S_c·T)` (the core computes `slew_limit_v_per_s * sample_period_s`
    /// in f32) is at most `M − s`, with `s` the f32 spacing at the window's largest magnitude. An
    /// output `u₋ + Δu` with `|Δu| ≤ fl(S_c·T)`, rounded to f32 inside the window, is off by at
    /// most `s/2`, so its steps stay within M and pass the guard unchanged. At 1e5 V/s, 10 kHz
    /// and 0–120 V the controller steps at most 9.99999 V per tick instead of 10 V (10⁻⁶ of its
    /// largest steps). The firmware's loop and `host-sim compensate` both run the compensator
    /// with these settings, so they command the same voltages. Settings without a finite slew
    /// limit or period are returned unchanged.
    pub fn inside_guard(&self) -> Self {
        let t = self.sample_period_s;
        let m = self.guard_step_v();
        if !(m.is_finite() && m > 0.0 && t.is_finite() && t > 0.0) {
            return *self;
        }
        let Limits {
            output_min_v: min,
            output_max_v: max,
            ..
        } = self.limits;
        let top = libm::fabsf(min).max(libm::fabsf(max));
        let spacing = top.next_up() - top;
        let step = round_down_f32(f64::from(m) - f64::from(spacing)).min(m.next_down());
        let mut slew = round_down_f32(f64::from(step) / f64::from(t));
        for _ in 0..2 {
            if slew * t <= step {
                break;
            }
            slew = slew.next_down();
        }
        Self {
            limits: Limits {
                slew_limit_v_per_s: slew,
                ..self.limits
            },
            ..*self
        }
    }

    /// The fastest finite slew limit [`CompensatorSettings::check_slew`] accepts for this window
    /// and period, `(output_max_v − output_min_v) / (MIN_WINDOW_TICKS · T)` \[V/s\].
    pub fn fastest_slew_v_per_s(&self) -> f32 {
        (self.limits.output_max_v - self.limits.output_min_v)
            / (MIN_WINDOW_TICKS * self.sample_period_s)
    }

    /// Checks the window (finite, min < max), the period (> 0) and the slew limit: > 0, and
    /// either +∞ (none) or `S·T·MIN_WINDOW_TICKS ≤ output_max_v − output_min_v`. The one rule
    /// [`Compensator::new`] and [`crate::Servo::new`] apply.
    pub fn check_slew(&self) -> Result<(), ParamError> {
        let min = finite("output_min_v", self.limits.output_min_v)?;
        let max = finite("output_max_v", self.limits.output_max_v)?;
        if max <= min {
            return Err(ParamError::OutOfRange {
                field: "output_max_v",
                value: max,
                requirement: "> output_min_v",
            });
        }
        let period = positive("sample_period_s", self.sample_period_s)?;
        let slew = self.limits.slew_limit_v_per_s;
        if slew.is_nan() || slew <= 0.0 {
            return Err(ParamError::OutOfRange {
                field: "slew_limit_v_per_s",
                value: slew,
                requirement: "> 0 (+inf for no limit)",
            });
        }
        let ticks = (max - min) / (slew * period);
        if slew.is_finite() && ticks < MIN_WINDOW_TICKS {
            return Err(ParamError::Implausible {
                field: "slew_limit_v_per_s",
                value: slew,
                measure: "the share of the window one tick may cross, slew_limit_v_per_s · \
                          sample_period_s / (output_max_v − output_min_v),",
                ratio: 1.0 / ticks,
                limit: 1.0 / MIN_WINDOW_TICKS,
            });
        }
        Ok(())
    }
}

/// What the compensator did with a sample.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CommandStatus {
    /// The commanded voltage reproduces the reference through the model.
    Tracking,
    /// The window or the slew limit stopped the voltage short of the reference.
    Limited,
    /// The reference was not a finite number: the last voltage is held.
    HeldInvalidReference,
}

/// One sample's output.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Command {
    /// Voltage to write to the amplifier \[V\]; always finite and inside the window.
    pub voltage_v: f32,
    /// How it was obtained.
    pub status: CommandStatus,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Target {
    /// y = k1·u + k2·h + y0 is the position.
    Position,
    /// k1·u + h is the force of the mass–spring–damper.
    Force {
        mass_kg: f32,
        damping_n_s_per_m: f32,
        stiffness_n_per_m: f32,
        rest_position_m: f32,
    },
}

/// The validated compensator settings (model + limits). State lives in [`CompensatorState`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Compensator {
    model: StaticModel,
    target: Target,
    settings: CompensatorSettings,
    max_step_v: f32,
    slope_sign: f32,
    /// Newton stops when a correction is below this: 1e-7 of the window (10 µV on 100 V, far
    /// below one step of a 16-bit DAC).
    voltage_tolerance_v: f32,
    /// Which per-sample fast path applies, and its constants, derived once when built.
    fast: FastPath,
}

/// Which small-step path [`Compensator::compensate`] tries before the general solve; chosen once,
/// when the compensator is built.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum FastKind {
    /// Asymmetric terms or the force target: always the general solve.
    None,
    /// n = 1: [`Compensator::small_n1_from`].
    N1,
    /// n ≠ 1: [`Compensator::compensate_small_general`].
    General,
}

/// Per-parameter-set constants of the small-step paths, computed when the compensator is built so
/// that the per-sample code only loads them.
#[derive(Debug, Clone, Copy, PartialEq)]
struct FastPath {
    kind: FastKind,
    k1: f32,
    k2: f32,
    offset_m: f32,
    min_v: f32,
    max_v: f32,
    max_step_v: f32,
    a: f32,
    /// Per branch, indexed by `2·[e < 0] + [h₀ < 0]` (sign bits of the output error e and of h₀),
    /// with the direction s = sgn(e)·sgn(dy/du) and σ = sgn h₀: κ = β·s + γ·σ (n = 1) or
    /// c = β·s·σ + γ (general n).
    branch: [f32; 4],
    /// n = 1: g(κ·Δu) = (1 − e^(−κΔu))/κΔu ([`relax_factor`]) at a step of the slew limit,
    /// Δu = s·M (M = `max_step_v`), per (s, σ), indexed by `2·[s < 0] + [σ < 0]`, with
    /// κ = β·s + γ·σ as [`crate::bouc_wen::BoucWen::n1_branch`] forms it: the same operands, so
    /// the same bits as computing it per sample ([`Compensator::limited_n1_on_branch`]).
    slew_g: [f32; 4],
    /// The bit pattern of the Bouc-Wen state clamp: a step ending beyond it (or across h = 0)
    /// is left to the general solve.
    clamp_bound_bits: u32,
    /// n = 1, the rest of a step past h = 0 ([`Compensator::n1_crossing_toward_zero`]): k2·A,
    /// the slope k1 + k2·A at h = 0, and k2·A/(k1 + k2·A), in the operations and order that
    /// solve forms them per sample, so the same bits.
    k2a: f32,
    slope_at_zero: f32,
    k2a_over_slope: f32,
    /// General n: n, n − 1.
    n: f32,
    n_minus_1: f32,
    /// General n: coefficients of the flow's error estimate, (n−1)|n−2|/24, 4(n−1)/24 and 1/24
    /// (see [`Compensator::compensate_small_general`]).
    err_rho2: f32,
    err_rho: f32,
    err_nu: f32,
    /// General n: largest relative move |f·Δu/h₀| of h the Taylor flow is used for.
    rho_max: f32,
}

impl FastPath {
    fn new(
        model: &StaticModel,
        target: Target,
        settings: &CompensatorSettings,
        max_step_v: f32,
        slope_sign: f32,
    ) -> Self {
        let bw = model.hysteresis();
        let BoucWenParams { a, beta, gamma, n } = bw.params();
        let StaticMap {
            k1_m_per_v: k1,
            k2_m_per_h: k2,
            offset_m,
        } = model.map();
        let kind = if model.has_extra_terms() || target != Target::Position {
            FastKind::None
        } else if bw.is_exponent_one() {
            FastKind::N1
        } else {
            FastKind::General
        };
        // (sgn e, σ) = (+,+), (+,−), (−,+), (−,−); s = sgn(e)·sgn(dy/du).
        let branch = [(1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0)].map(|(e, sigma)| {
            let s = e * slope_sign;
            if kind == FastKind::N1 {
                beta * s + gamma * sigma
            } else {
                beta * s * sigma + gamma
            }
        });
        let slew_g = [(1.0f32, 1.0f32), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0)]
            .map(|(s, sigma)| relax_factor((beta * s + gamma * sigma) * (s * max_step_v)));
        Self {
            kind,
            k1,
            k2,
            offset_m,
            slew_g,
            min_v: settings.limits.output_min_v,
            max_v: settings.limits.output_max_v,
            max_step_v,
            a,
            branch,
            clamp_bound_bits: bw.clamp_bound().to_bits(),
            k2a: k2 * a,
            slope_at_zero: k1 + k2 * a,
            k2a_over_slope: k2 * a / (k1 + k2 * a),
            n,
            n_minus_1: n - 1.0,
            err_rho2: (n - 1.0) * (n - 2.0).abs() / 24.0,
            err_rho: 4.0 * (n - 1.0) / 24.0,
            err_nu: 1.0 / 24.0,
            rho_max: math::min(0.5, 1.5 / math::max(n - 1.0, 1e-3)),
        }
    }
}

/// A memo of a command's step across h = 0 (n = 1): the input increment
/// `Δu₀ = −(h₀/A)·ln(1 + x)/x`, x = −κ·h₀/A, at which h reached zero from h₀ on the branch κ
/// (the model's `n1_zero_reach`), keyed by the bits of h₀, κ and A (Δu₀ is a
/// function of those three alone, so a memo from another tick or model is never taken for
/// this one). [`Compensator::compensate_noting`] writes it, [`Compensator::advance_noted`]
/// reads it: a voltage applied that crosses zero from the same state on the same branch as
/// the command takes Δu₀ from it instead of computing the logarithm again.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ZeroReach {
    h0_bits: u32,
    kappa_bits: u32,
    a_bits: u32,
    du0: f32,
}

impl ZeroReach {
    /// No memo: a key no finite h₀ has (a NaN's bits).
    pub const NONE: Self = Self {
        h0_bits: u32::MAX,
        kappa_bits: u32::MAX,
        a_bits: u32::MAX,
        du0: f32::NAN,
    };

    /// The memo's Δu₀ for (h₀, κ, A), if it is theirs.
    #[inline(always)]
    fn get(&self, h0: f32, kappa: f32, a: f32) -> Option<f32> {
        (self.h0_bits == h0.to_bits()
            && self.kappa_bits == kappa.to_bits()
            && self.a_bits == a.to_bits())
        .then_some(self.du0)
    }
}

impl Default for ZeroReach {
    fn default() -> Self {
        Self::NONE
    }
}

/// The compensator's state: the model state at the last commanded voltage.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct CompensatorState {
    /// Model state; `model.input_v` is the last commanded voltage.
    pub model: ModelState,
}

impl CompensatorState {
    /// At rest with `voltage_v` applied and no hysteretic state.
    pub fn at_rest(voltage_v: f32) -> Self {
        Self {
            model: ModelState::at_rest(voltage_v),
        }
    }

    /// The last commanded voltage \[V\].
    pub fn voltage_v(&self) -> f32 {
        self.model.input_v
    }
}

/// Largest number of bracketed Newton corrections after the first guess (one or two in the smooth
/// case; the rest is room for bisection on kinked maps).
const NEWTON_CORRECTIONS: usize = 12;

/// Most Newton steps of the fast n = 1 solve for a large step (|κΔu| ≥ 0.1).
const LARGE_STEP_NEWTON: usize = 6;

/// Largest estimated relative error of a small step (of Δu, and of the move of h) that the
/// small-step paths accept; beyond it the sample goes to the general solve. 1e-5 of a step is far
/// below one f32 ulp of the output y for a step at a normal loop rate.
const SMALL_STEP_TOLERANCE: f32 = 1e-5;

impl Compensator {
    /// The direction of the step an output error `error` asks for from `u0` (±1: the sign of
    /// error·slope) and the largest step that way: the slew step, or less at the window's edge.
    #[inline(always)]
    fn step_direction(&self, u0: f32, error: f32) -> (f32, f32) {
        let p = &self.fast;
        let direction = if error * self.slope_sign > 0.0 {
            1.0
        } else {
            -1.0
        };
        let limit = if direction > 0.0 {
            math::min(p.max_v - u0, p.max_step_v)
        } else {
            math::max(p.min_v - u0, -p.max_step_v)
        };
        (direction, limit)
    }

    /// A compensator for a static or asymmetric static model (output y in metres).
    pub fn new(model: StaticModel, settings: CompensatorSettings) -> Result<Self, ParamError> {
        Self::build(model, Target::Position, settings)
    }

    /// A compensator for the dynamic model of seed 000 (force balance; see the module doc).
    pub fn for_dynamic(
        model: &DynamicModel,
        settings: CompensatorSettings,
    ) -> Result<Self, ParamError> {
        let p = model.params();
        let force_map = StaticMap {
            k1_m_per_v: p.force_per_volt_n_per_v,
            k2_m_per_h: 1.0,
            offset_m: 0.0,
        };
        let forward = StaticModel::new(*model.hysteresis(), force_map)?;
        Self::build(
            forward,
            Target::Force {
                mass_kg: p.mass_kg,
                damping_n_s_per_m: p.damping_n_s_per_m,
                stiffness_n_per_m: p.stiffness_n_per_m,
                rest_position_m: p.rest_position_m,
            },
            settings,
        )
    }

    fn build(
        model: StaticModel,
        target: Target,
        settings: CompensatorSettings,
    ) -> Result<Self, ParamError> {
        settings.check_slew()?;
        let (min, max) = (settings.limits.output_min_v, settings.limits.output_max_v);
        let (range_min, range_max) = model.hysteresis().input_range_v();
        if min < range_min {
            return Err(ParamError::OutOfRange {
                field: "output_min_v",
                value: min,
                requirement: "inside the model's validated input range",
            });
        }
        if max > range_max {
            return Err(ParamError::OutOfRange {
                field: "output_max_v",
                value: max,
                requirement: "inside the model's validated input range",
            });
        }
        let (period, slew) = (settings.sample_period_s, settings.limits.slew_limit_v_per_s);
        let max_step_v = (slew * period).min(max - min);
        // With a rate-dependent gain the reachable states and slopes depend on the fastest move
        // the slew limit allows (crate::static_model).
        let (lo, hi) = model.slope_range_for_step(max_step_v);
        if !is_invertible_slope_range(lo, hi) {
            // The gain is to blame only where the map is monotone for the slowest steps (gain 1):
            // a map that folds there folds without the gain too, and no slew limit helps.
            let (rest_lo, rest_hi) = model.slope_range_for_step(0.0);
            if model.has_rate_gain() && is_invertible_slope_range(rest_lo, rest_hi) {
                return Err(ParamError::OutOfRange {
                    field: "hysteresis_rate_gain_s_per_v",
                    value: model.rate_gain_s_per_v(),
                    requirement: "a one-step map that stays monotone (dy/du of one sign, \
                                  min/max >= 0.01) at every gain the slew limit allows",
                });
            }
            return Err(ParamError::NotInvertible {
                min_slope: rest_lo,
                max_slope: rest_hi,
            });
        }
        if model.has_input_lag() {
            // The inverse's recursion through the lag (crate::static_model): with
            // r = k2·dh/dv / k1 on each branch, r > −1 and λ = (e^(−x) − r·(c − b))/(1 + r·b)
            // ≥ −1/2 (λ falls as r rises: checked at the largest r).
            let c = model.input_lag_fraction();
            let b = model.input_lag_hold_share();
            let k1 = model.map().k1_m_per_v;
            let (r_lo, r_hi) = (lo / k1 - 1.0, hi / k1 - 1.0);
            let (r_min, r_max) = (r_lo.min(r_hi), r_lo.max(r_hi));
            let lambda = (1.0 - c - r_max * (c - b)) / (1.0 + r_max * b);
            if !(r_min > -1.0 && lambda >= MIN_LAG_ERROR_FACTOR) {
                return Err(ParamError::OutOfRange {
                    field: "hysteresis_lag_s",
                    value: model.input_lag_s(),
                    requirement: "an inverse that does not ring: with r = k2·(dh/dv)/k1 on \
                                  every branch, r > -1 and the lag's error factor \
                                  (e^(-T/tau) - r·(c - b))/(1 + r·b) >= -0.5",
                });
            }
        }
        let slope_sign = if lo > 0.0 { 1.0 } else { -1.0 };
        Ok(Self {
            model,
            target,
            settings,
            max_step_v,
            slope_sign,
            voltage_tolerance_v: 1e-7 * (max - min),
            fast: FastPath::new(&model, target, &settings, max_step_v, slope_sign),
        })
    }

    /// The forward model the compensator inverts (for the dynamic model: its force map).
    pub fn model(&self) -> &StaticModel {
        &self.model
    }

    /// The limits.
    pub fn settings(&self) -> CompensatorSettings {
        self.settings
    }

    /// Whether the model's output is the position (static models), not the dynamic model's force.
    pub(crate) fn is_position(&self) -> bool {
        self.target == Target::Position
    }

    /// The voltage for the desired position `desired_m` \[m\] (quasi-static for the dynamic model).
    ///
    /// The small-step path chosen when built is inlined here; every sample it does not take goes
    /// to the general solve (out of line).
    #[inline(always)]
    pub fn compensate(&self, state: &mut CompensatorState, desired_m: f32) -> Command {
        // The step the small path refuses is settled from scratch out of line: the caller's
        // loop keeps only the small path's registers (see `compensate_noting` for the other
        // trade).
        let small = match self.fast.kind {
            FastKind::N1 => self.compensate_small_n1(state, desired_m),
            FastKind::General => self.compensate_small_general(state, desired_m),
            FastKind::None => None,
        };
        match small {
            Some(command) => command,
            None => self.compensate_general(state, desired_m),
        }
    }

    /// [`Compensator::compensate`], noting in `memo` the Δu₀ of a step across h = 0 (n = 1; an
    /// other step leaves it as it was) for [`Compensator::advance_noted`] from the same state.
    #[inline(always)]
    pub fn compensate_noting(
        &self,
        state: &mut CompensatorState,
        desired_m: f32,
        memo: &mut ZeroReach,
    ) -> Command {
        if self.fast.kind == FastKind::N1 {
            // The start is computed once: a step the small path refuses goes on from it.
            return match self.small_step(state, desired_m) {
                Some(start) => match self.small_n1_from(state, start) {
                    Some(command) => command,
                    None => self.compensate_n1_refused(state, start, desired_m, memo),
                },
                None => self.compensate_general(state, desired_m),
            };
        }
        let small = if self.fast.kind == FastKind::General {
            self.compensate_small_general(state, desired_m)
        } else {
            None
        };
        match small {
            Some(command) => command,
            None => self.compensate_general(state, desired_m),
        }
    }

    /// Advances the model state to the voltage actually applied, `applied_v` \[V\]: the same
    /// state as `self.model().step(&mut state.model, applied_v)` (bit for bit), for a caller whose
    /// output differs from the compensator's command (a servo's correction, a guard's override).
    ///
    /// For n = 1 and a small step it takes the same closed form as [`StaticModel::step`]'s
    /// increment, `h₁ = h₀ + (A − κ·h₀)·Δu·g(κ·Δu)` with κ = β·s + γ·σ (s = sgn Δu, σ = sgn h₀,
    /// or at h₀ = ±0 the sign of A·Δu, as the model's step takes it) and g's series
    /// (|κ·Δu| < 0.1), with κ from the table built once instead of the general step's sanitising
    /// and branch selection: only when the state is consistent and inside the window,
    /// `applied_v` is inside the window, Δu ≠ 0 at h₀ = 0, and h₁ stays on σ's side of zero
    /// within the state clamp (or crosses it from h₀ ≠ 0 by a small step, split where the model
    /// splits it). Every other case (zero crossings, large steps, n ≠ 1, asymmetric terms,
    /// a non-finite voltage) is the model's own step.
    #[inline(always)]
    pub fn advance(&self, state: &mut CompensatorState, applied_v: f32) {
        self.advance_noted(state, applied_v, &ZeroReach::NONE);
    }

    /// [`Compensator::advance`], the same state bit for bit, taking Δu₀ of a step across h = 0
    /// from `memo` when it is the one of this h₀, branch and model
    /// ([`Compensator::compensate_noting`] from the same state).
    #[inline(always)]
    pub fn advance_noted(&self, state: &mut CompensatorState, applied_v: f32, memo: &ZeroReach) {
        if self.fast.kind == FastKind::N1 && self.advance_small_n1(state, applied_v, memo) {
            return;
        }
        self.advance_general(state, applied_v);
    }

    /// [`Compensator::advance`]'s small n = 1 step; false (nothing changed) when it does not apply.
    #[inline(always)]
    fn advance_small_n1(
        &self,
        state: &mut CompensatorState,
        applied_v: f32,
        memo: &ZeroReach,
    ) -> bool {
        let p = &self.fast;
        let u0 = state.model.input_v;
        let h0 = state.model.hysteresis.h;
        let u = applied_v;
        if !(state.model.hysteresis.input_v == u0
            && u0 >= p.min_v
            && u0 <= p.max_v
            && u >= p.min_v
            && u <= p.max_v)
        {
            return false;
        }
        let du = u - u0;
        // σ = sgn h₀; at h₀ = ±0 the sign of A·Δu, as the model's step takes it
        // (`BoucWen::branch_sign`; a zero step there is the model's: h stays, sign included).
        let sigma_bit = if h0 != 0.0 {
            h0.to_bits() >> 31
        } else if du != 0.0 {
            if p.a * du > 0.0 {
                0
            } else {
                1
            }
        } else {
            return false;
        };
        // s = sgn Δu (the sign bit: −0 counts as negative, as `f32::signum`) and σ select
        // κ = β·s + γ·σ in the table indexed by s·sgn(dy/du) (see `FastPath::branch`).
        let index = ((du.to_bits() ^ self.slope_sign.to_bits()) >> 31) << 1 | sigma_bit;
        let kappa = p.branch[index as usize & 3];
        let z = kappa * du;
        let mut h1 = h0 + (p.a - kappa * h0) * du * relax_series(z);
        let h1_on_branch = (h1.to_bits() ^ (sigma_bit << 31)) <= p.clamp_bound_bits;
        let small = z.abs() < 0.1;
        if !(small && h1_on_branch) {
            // h crossed zero (the model splits the step there), or the step is not small.
            if !(small && h1 * h0 < 0.0) {
                return false;
            }
            let kappa_after = p.branch[(index as usize & 3) ^ 1];
            let noted = memo.get(h0, kappa, p.a);
            h1 = match self.advance_crossing_n1(h0, du, kappa, kappa_after, noted) {
                Some(h1) => h1,
                None => return false,
            };
        }
        state.model = ModelState {
            input_v: u,
            hysteresis: HysteresisState { input_v: u, h: h1 },
        };
        true
    }

    /// [`Compensator::advance_small_n1`]'s step when h₁ left h₀'s side of zero (|κ·Δu| < 0.1):
    /// the model's own split ([`crate::bouc_wen::BoucWen::advance`], n = 1), h reaching zero
    /// after `Δu₀ = −(h₀/A)·ln(1 + x)/x`, x = −κ·h₀/A, then `h₁ = A·r·g(κ'·r)` on the other
    /// side, r = Δu − Δu₀ (0 if Δu stops short of Δu₀ in f32), κ' = β·s − γ·σ (`kappa_after`,
    /// the branch table's entry of the same direction and the other σ), the same operations in
    /// the same order, so the same bits. `None` (the model's step) when x ≤ −1 or h₁ lies
    /// beyond the state clamp. `noted`: Δu₀ of this h₀ and κ from a [`ZeroReach`] memo.
    #[inline(always)]
    fn advance_crossing_n1(
        &self,
        h0: f32,
        du: f32,
        kappa: f32,
        kappa_after: f32,
        noted: Option<f32>,
    ) -> Option<f32> {
        let du0 = match noted {
            Some(du0) => du0,
            None => self.model.hysteresis().n1_zero_reach(h0, kappa)?,
        };
        let s = if du < 0.0 { -1.0 } else { 1.0 };
        let rest = if (du - du0) * s > 0.0 { du - du0 } else { 0.0 };
        let h1 = self.fast.a * rest * relax_factor_inline(kappa_after * rest);
        (h1.abs().to_bits() <= self.fast.clamp_bound_bits).then_some(h1)
    }

    /// [`Compensator::advance`] by the model's step (out of line). For n = 1 without asymmetric
    /// terms or input lag (the small paths' models), from a consistent state inside the window to
    /// a voltage inside it, [`StaticModel::step`] reduces to the operator's own increment,
    /// `h₁ = BoucWen::advance(h₀, u − u₀)` (nothing to sanitise, no shift, no δ-term, no lag):
    /// that is called directly, the same operations, so the same bits.
    #[inline(never)]
    fn advance_general(&self, state: &mut CompensatorState, applied_v: f32) {
        let p = &self.fast;
        let u0 = state.model.input_v;
        let u = applied_v;
        if p.kind == FastKind::N1
            && state.model.hysteresis.input_v == u0
            && u0 >= p.min_v
            && u0 <= p.max_v
            && u >= p.min_v
            && u <= p.max_v
        {
            let h1 = self
                .model
                .hysteresis()
                .advance(state.model.hysteresis.h, u - u0);
            state.model = ModelState {
                input_v: u,
                hysteresis: HysteresisState { input_v: u, h: h1 },
            };
            return;
        }
        self.model.step(&mut state.model, applied_v);
    }

    /// [`Compensator::compensate`] without the small-step paths (kept out of line). For n = 1,
    /// from a consistent state inside the window, the step is settled by the fast solves
    /// directly ([`Compensator::n1_edge_head`] and [`Compensator::n1_edge_tail`]), with the direction s = sgn(e)·sgn(dy/du)
    /// and the limit Δu_lim (slew or window, whichever is nearer) as [`Compensator::solve`]
    /// takes them:
    /// - a step the limit stops: when the fast solve's start (below) lies beyond Δu_lim and the
    ///   output at the limit, `Δu_lim·(k1 + k2·q·g(κ·Δu_lim))` (one `relax_factor`), still falls
    ///   short of e, the voltage is u₀ + Δu_lim with `h₁ = h₀ + q·Δu_lim·g(κ·Δu_lim)`, what the
    ///   fast solve's Newton ends on (its iterates stay clamped at the limit), `Limited`
    ///   ([`Compensator::limited_n1_on_branch`]);
    /// - a step that may cross h = 0 within the limit: h₀ ≠ 0, moving toward zero (q·s·σ < 0,
    ///   σ = sgn h₀) and |h₀| < max(A, |q|)·|Δu_lim| (on the way to zero |dh/du| lies between
    ///   A and |q|): [`Compensator::solve_n1_crossing`];
    /// - otherwise [`Compensator::solve_n1_fast`].
    ///
    /// A step clearly beyond the slew limit is tried first at the limit with g from a table
    /// ([`Compensator::compensate_n1_refused`]). What those refuse, and every other model, goes
    /// to the general solve.
    #[inline(never)]
    fn compensate_general(&self, state: &mut CompensatorState, desired_m: f32) -> Command {
        if self.fast.kind == FastKind::N1 {
            if let Some(start) = self.small_step(state, desired_m) {
                let mut memo = ZeroReach::NONE;
                return self.compensate_n1_refused(state, start, desired_m, &mut memo);
            }
        }
        self.compensate_with_derivatives(state, desired_m, 0.0, 0.0)
    }

    /// [`Compensator::compensate_general`] for n = 1 after the small path refused the step
    /// from `(u₀, h₀, e, _)` ([`Compensator::small_step`]): the edge cases, then the general
    /// solve; the same as `compensate_general` without computing the start again.
    ///
    /// A step the small path refused with |x₀| beyond three slew steps (x₀ as it computes it)
    /// is first tried as a slew-limited step ([`Compensator::slew_limited_n1`]); one that h
    /// surely crosses zero in at the slew limit goes on to [`Compensator::n1_edge_tail`].
    #[inline(never)]
    fn compensate_n1_refused(
        &self,
        state: &mut CompensatorState,
        (u0, h0, error, branch): (f32, f32, f32, usize),
        desired_m: f32,
        memo: &mut ZeroReach,
    ) -> Command {
        let p = &self.fast;
        // `branch` is 0..=3 (`small_step`); the mask keeps the index check out of line code.
        let kappa = p.branch[branch & 3];
        let q = p.a - kappa * h0;
        let k2q = p.k2 * q;
        let x0 = error * (1.0 / (p.k1 + k2q));
        let slew = if x0.abs() > 3.0 * p.max_step_v {
            self.slew_limited_n1(state, u0, h0, error, (q, kappa, k2q))
        } else {
            Err(None)
        };
        // One tail for both: the slew-limited step's crossing, or the edge's.
        let head = match slew {
            Ok(command) => return command,
            Err(Some((direction, limit, q, kappa, sigma))) => {
                Err(Some((direction, limit, (q, kappa, sigma))))
            }
            Err(None) => self.n1_edge_head(state, u0, h0, error, (q, kappa, k2q)),
        };
        let tail = match head {
            Ok(command) => Some(command),
            Err(None) => None,
            Err(Some((direction, limit, branch))) => self.n1_edge_tail(
                state,
                (u0, h0, error, desired_m),
                (direction, limit),
                branch,
                memo,
            ),
        };
        match tail {
            Some(command) => command,
            None => self.compensate_with_derivatives(state, desired_m, 0.0, 0.0),
        }
    }

    /// [`Compensator::compensate_general`]'s n = 1 cases, settled without the general solve's
    /// hold and output bookkeeping (the state is consistent and inside the window, so the hold
    /// state is the state itself): the limited step, the crossing, then the fast solve
    /// ([`Compensator::solve_n1_fast`]) as [`Compensator::solve`] calls it, with the status
    /// `solve` gives. `None` when none of them takes the step.
    #[cfg(test)]
    fn compensate_n1_edge(
        &self,
        state: &mut CompensatorState,
        u0: f32,
        h0: f32,
        error: f32,
        desired_m: f32,
    ) -> Option<Command> {
        let p = &self.fast;
        let index = (error.to_bits() >> 31) << 1 | h0.to_bits() >> 31;
        let kappa = p.branch[index as usize & 3];
        let q = p.a - kappa * h0;
        match self.n1_edge_head(state, u0, h0, error, (q, kappa, p.k2 * q)) {
            Ok(command) => Some(command),
            Err(None) => None,
            Err(Some((direction, limit, branch))) => self.n1_edge_tail(
                state,
                (u0, h0, error, desired_m),
                (direction, limit),
                branch,
                &mut ZeroReach::default(),
            ),
        }
    }

    /// The edge's head (the tail is [`Compensator::n1_edge_tail`]): `Ok` the limited step
    /// ([`Compensator::limited_n1_on_branch`]) when the fast solve's start lies beyond the
    /// limit and the limit stops the step; `Err(None)` for an error that is not finite or zero
    /// (the general solve); else `Err(Some((direction, limit, (q, κ, σ))))` for
    /// [`Compensator::n1_edge_tail`].
    ///
    /// `(q, κ, k2·q)`: the branch table's κ at the start's index `2·[e < 0] + [h₀ < 0]`
    /// ([`Compensator::small_step`]) with q = A − κ·h₀. For a finite e ≠ 0 the table's
    /// direction sgn(e)·sgn(dy/du) is `step_direction`'s, and for h₀ ≠ 0 (not NaN) its σ is
    /// sgn h₀, as `n1_branch(h₀, direction)` takes it: the same operands, so the same bits,
    /// taken instead of forming the branch again. At h₀ = ±0 or NaN the branch is `n1_branch`'s.
    #[inline(always)]
    #[allow(clippy::type_complexity)]
    fn n1_edge_head(
        &self,
        state: &mut CompensatorState,
        u0: f32,
        h0: f32,
        error: f32,
        table: (f32, f32, f32),
    ) -> Result<Command, Option<(f32, f32, (f32, f32, f32))>> {
        let p = &self.fast;
        // Finite and nonzero (NaN fails both comparisons): two float compares.
        if !(error.abs() > 0.0 && error.abs() < f32::INFINITY) {
            return Err(None);
        }
        let (direction, limit) = self.step_direction(u0, error);
        let (q, kappa, sigma, k2q) = if h0.abs() > 0.0 {
            let (q, kappa, k2q) = table;
            (q, kappa, if h0 > 0.0 { 1.0 } else { -1.0 }, k2q)
        } else {
            let (q, kappa, sigma) = self.model.hysteresis().n1_branch(h0, direction);
            (q, kappa, sigma, p.k2 * q)
        };
        let slope = p.k1 + k2q;
        let linear = error / slope;
        let w = k2q / slope * kappa * linear;
        // The fast solve's start (see `solve_n1_fast`): beyond the limit, the limit is likely.
        let guess = if w.abs() < 0.9 {
            linear * (1.0 - 0.5 * w) / (1.0 - w)
        } else {
            linear
        };
        let toward_zero = h0 != 0.0 && q * direction * sigma < 0.0;
        // The limited step refuses a step across h = 0 at the limit: not tried when h surely
        // crosses within it (`crosses_within`).
        if guess.abs() > limit.abs() && !(toward_zero && crosses_within(h0, q, kappa, limit)) {
            if let Some(command) = self.limited_n1_on_branch(
                state,
                (u0, h0, error),
                (direction, limit),
                (q, kappa, sigma),
            ) {
                return Ok(command);
            }
        }
        Err(Some((direction, limit, (q, kappa, sigma))))
    }

    /// The edge after the limited step ([`Compensator::n1_edge_head`]): the crossing when h moves
    /// toward zero and may reach it within the limit, else the fast solve, and the status as
    /// [`Compensator::solve`] reports it; `(q, κ, σ)` is `n1_branch(h₀, direction)`.
    #[inline(always)]
    fn n1_edge_tail(
        &self,
        state: &mut CompensatorState,
        (u0, h0, error, desired_m): (f32, f32, f32, f32),
        (direction, limit): (f32, f32),
        branch: (f32, f32, f32),
        memo: &mut ZeroReach,
    ) -> Option<Command> {
        let (q, _, sigma) = branch;
        let toward_zero = h0 != 0.0 && q * direction * sigma < 0.0;
        // The crossing's own entry checks (`solve_n1_crossing`) are these two: inlined here.
        let crossing =
            if toward_zero && h0.abs() < math::max(self.fast.a.abs(), q.abs()) * limit.abs() {
                self.n1_crossing_toward_zero(u0, h0, error, direction, limit, branch)
            } else {
                None
            };
        let (reached, du) = match crossing {
            Some((reached, du, du0)) => {
                // The memo (κ as the branch table gives it: the same bits).
                *memo = ZeroReach {
                    h0_bits: h0.to_bits(),
                    kappa_bits: branch.1.to_bits(),
                    a_bits: self.fast.a.to_bits(),
                    du0,
                };
                (reached, du)
            }
            None => self.solve_n1_fast(&state.model, u0, error, direction, limit)?,
        };
        // The status as `solve` reports it.
        let remaining = self.model.output(&reached) - desired_m;
        let limited = du == limit && remaining * self.slope_sign * direction < 0.0;
        state.model = reached;
        Some(Command {
            voltage_v: reached.input_v,
            status: if limited {
                CommandStatus::Limited
            } else {
                CommandStatus::Tracking
            },
        })
    }

    /// A step the limit stops ([`Compensator::compensate_general`]): `Some` (`Limited`, the
    /// state at u₀ + Δu_lim) when the output at the limit still falls short of the error `error`
    /// and h₁ stays on its side of zero; `None` otherwise.
    #[cfg(test)]
    fn compensate_limited_n1(
        &self,
        state: &mut CompensatorState,
        u0: f32,
        h0: f32,
        error: f32,
        direction: f32,
        limit: f32,
    ) -> Option<Command> {
        let branch = self.model.hysteresis().n1_branch(h0, direction);
        self.limited_n1_on_branch(state, (u0, h0, error), (direction, limit), branch)
    }

    /// [`Compensator::limited_n1_on_branch`] with `(q, κ, σ)` = `n1_branch(h₀, direction)`
    /// as the caller has it.
    #[inline(never)]
    fn limited_n1_on_branch(
        &self,
        state: &mut CompensatorState,
        (u0, h0, error): (f32, f32, f32),
        (direction, limit): (f32, f32),
        (q, kappa, sigma): (f32, f32, f32),
    ) -> Option<Command> {
        let p = &self.fast;
        // At the slew limit itself (not the window's edge) g is the table's.
        let g = if limit == direction * p.max_step_v {
            p.slew_g[usize::from(direction < 0.0) << 1 | usize::from(sigma < 0.0)]
        } else {
            relax_factor(kappa * limit)
        };
        let short = error - limit * (p.k1 + p.k2 * q * g);
        let h1 = h0 + q * limit * g;
        if !(short * self.slope_sign * direction > 0.0 && h1 * sigma >= 0.0 && limit != 0.0) {
            return None;
        }
        let (reached, _) = self.n1_commit(u0, limit, h1);
        state.model = reached;
        Some(Command {
            voltage_v: reached.input_v,
            status: CommandStatus::Limited,
        })
    }

    /// What both small-step paths start from: `None` unless the state is consistent (the
    /// hysteresis input equals the voltage) and inside the window; otherwise `(u₀, h₀, e, i)` with
    /// the output error e = y_d − y(u₀) and the branch index `i = 2·[e < 0] + [h₀ < 0]` (sign
    /// bits): the direction that reduces the error is s = sgn(e)·sgn(dy/du), and the branch is
    /// that of σ = sgn h₀. At h₀ = ±0 the state leaves zero with the sign of A·s; when the sign
    /// bit of h₀ says otherwise, the step ends on the other side of zero and
    /// [`Compensator::small_commit`] refuses it. A non-finite e is caught by the callers' checks.
    #[inline(always)]
    fn small_step(
        &self,
        state: &CompensatorState,
        desired_m: f32,
    ) -> Option<(f32, f32, f32, usize)> {
        let p = &self.fast;
        let u0 = state.model.input_v;
        let h0 = state.model.hysteresis.h;
        if !(state.model.hysteresis.input_v == u0 && u0 >= p.min_v && u0 <= p.max_v) {
            return None;
        }
        let error = desired_m - (p.k1 * u0 + p.k2 * h0 + p.offset_m);
        let index = (error.to_bits() >> 31) << 1 | h0.to_bits() >> 31;
        Some((u0, h0, error, index as usize & 3))
    }

    /// Commits a small step: `Some` when Δu is inside the slew limit, u = u₀ + Δu inside the
    /// window, and h₁ on the side of zero of h₀ (or zero) and inside the state clamp — the last
    /// two as one integer comparison of the bits of h₁·sgn h₀ with those of the clamp — all
    /// false for NaN; else `None` (general solve).
    #[inline(always)]
    fn small_commit(
        &self,
        state: &mut CompensatorState,
        u0: f32,
        h0: f32,
        du: f32,
        h1: f32,
    ) -> Option<Command> {
        let p = &self.fast;
        let u = u0 + du;
        let h1_on_branch = (h1.to_bits() ^ (h0.to_bits() & 0x8000_0000)) <= p.clamp_bound_bits;
        if !(du.abs() <= p.max_step_v && u >= p.min_v && u <= p.max_v && h1_on_branch) {
            return None;
        }
        state.model = ModelState {
            input_v: u,
            hysteresis: HysteresisState { input_v: u, h: h1 },
        };
        Some(Command {
            voltage_v: u,
            status: CommandStatus::Tracking,
        })
    }

    /// [`Compensator::small_n1_from`] from the state.
    #[inline(always)]
    fn compensate_small_n1(&self, state: &mut CompensatorState, desired_m: f32) -> Option<Command> {
        let start = self.small_step(state, desired_m)?;
        self.small_n1_from(state, start)
    }

    /// The common case of a loop at a normal rate, in few instructions: n = 1, no asymmetric terms,
    /// a consistent state inside the window, a finite reference and a small step that the window
    /// and the slew limit leave alone. With the error e = y_d − y(u₀), the branch's κ and
    /// q = A − κ·h₀, S₀ = k1 + k2·q, x₀ = e/S₀, kx = κ·x₀ and w = (k2·q/S₀)·kx, the one-step inverse
    /// is the series reversion
    /// `Δu = x₀·(1 + w/2 + w²/2 − w·kx/6 + 5w³/8 − 5w²·kx/12 + w·kx²/24)`, whose first neglected
    /// term, `x₀·(−w·kx³/120 + 5w²kx²/24 − 7w³kx/8 + 7w⁴/8)`, is below `(7/8)·|w|·(|kx| + |w|)³·|x₀|`:
    /// taken when `|kx| + |w| < 0.055`, so that this is below 0.875·0.055⁴ ≈ 8e-6 of the step
    /// ([`SMALL_STEP_TOLERANCE`]) and the series of g below is exact to 1e-10. Otherwise,
    /// up to |kx| < 0.1 and |w| < 0.2, one Newton step on the closed form follows, with the exact
    /// slope k1 + k2·q·e^(−κΔu) at the end state. Then `h₁ = h₀ + q·Δu·g(κΔu)` exactly (g by its
    /// series to z⁴, in Horner form, |κΔu| < 0.1: truncation < 1.4e-8). `None` hands every other
    /// case (h crossing zero included, see [`Compensator::compensate_general`]) to the general
    /// solve, which gives the same result there (tested).
    ///
    /// A step whose linear estimate |x₀| exceeds three slew steps is refused without the Newton
    /// step (and tried as a slew-limited step, [`Compensator::compensate_n1_refused`]), since the
    /// reversion's Δu lies within 4 % of x₀ and the Newton step's (|kx| < 0.1, |w| < 0.2,
    /// |κΔu| < 0.1: Δu within 13 % of x₀ before it, |k2·q·(g − 1)/S₀| ≤ 0.12 and
    /// |k2·q·(e^(−κΔu) − 1)/S₀| ≤ 0.25 along it) is at least 0.46·|x₀|, so either is beyond
    /// the slew limit, which [`Compensator::small_commit`] would refuse.
    ///
    /// From its start `(u₀, h₀, e, branch)` ([`Compensator::small_step`]).
    #[inline(always)]
    fn small_n1_from(
        &self,
        state: &mut CompensatorState,
        (u0, h0, error, branch): (f32, f32, f32, usize),
    ) -> Option<Command> {
        let p = &self.fast;
        let kappa = p.branch[branch];
        let q = p.a - kappa * h0;
        let k2q = p.k2 * q;
        let inverse_slope = 1.0 / (p.k1 + k2q);
        let x0 = error * inverse_slope;
        let kx = kappa * x0;
        let w = k2q * inverse_slope * kx;
        // Reversion to third order: 1 + w/2 + (w²/2 − w·kx/6) + (5w³/8 − 5w²·kx/12 + w·kx²/24).
        let series = 0.5
            + w * (0.5 + w * (0.625 - kx * (5.0 / 12.0)))
            + kx * (kx * (1.0 / 24.0) - 1.0 / 6.0);
        let mut du = x0 * (1.0 + w * series);
        // NaN (a non-finite reference) fails this and goes to the Newton step, which refuses it.
        let reversion_ok = kx.abs() + w.abs() < 0.055;
        if !reversion_ok {
            if x0.abs() > 3.0 * p.max_step_v {
                return None;
            }
            du = self.n1_newton_step(du, error, kappa, k2q)?;
        }
        let z = kappa * du;
        // g(z) = 1 − z/2 + z²/6 − z³/24 + z⁴/120.
        let g = 1.0 + z * (-0.5 + z * (1.0 / 6.0 + z * (-1.0 / 24.0 + z * (1.0 / 120.0))));
        let h1 = h0 + q * du * g;
        self.small_commit(state, u0, h0, du, h1)
    }

    /// A step the small path refused with |x₀| beyond three slew steps, settled when the
    /// slew limit stops it: [`Compensator::limited_n1_on_branch`] at Δu_lim = s·M with the
    /// table's g(κ·Δu_lim), for h₀ ≠ 0 (σ = sgn h₀, κ and q = A − κ·h₀ of the small path's
    /// branch: the same operands as `n1_branch` gives) and a limit the window does not move.
    /// That is what [`Compensator::n1_edge_head`] and [`Compensator::n1_edge_tail`] does first with such a step: its start
    /// `x₀·(1 − w/2)/(1 − w)` (or x₀) is at least 0.76·|x₀| > M, so it tries the limited step
    /// (a step that surely crosses h = 0, which it does not try, the limited step refuses).
    /// `Err(Some((direction, limit, q, κ, σ)))` when h₁ lies past zero (the limited step's
    /// refusal; h then moves toward zero), `Err(None)` (the edge solves) when the limit does not
    /// stop the step or does not apply.
    #[inline]
    fn slew_limited_n1(
        &self,
        state: &mut CompensatorState,
        u0: f32,
        h0: f32,
        error: f32,
        (q, kappa, k2q): (f32, f32, f32),
    ) -> Result<Command, Option<SlewCrossing>> {
        let p = &self.fast;
        let (direction, limit) = self.step_direction(u0, error);
        if !(limit == direction * p.max_step_v && h0 != 0.0 && error.is_finite()) {
            return Err(None);
        }
        let sigma = if h0 > 0.0 { 1.0 } else { -1.0 };
        let g = p.slew_g[usize::from(direction < 0.0) << 1 | usize::from(h0 < 0.0)];
        let short = error - limit * (p.k1 + k2q * g);
        let h1 = h0 + q * limit * g;
        if h1 * sigma < 0.0 && limit != 0.0 {
            return Err(Some((direction, limit, q, kappa, sigma)));
        }
        if !(short * self.slope_sign * direction > 0.0 && h1 * sigma >= 0.0 && limit != 0.0) {
            return Err(None);
        }
        let (reached, _) = self.n1_commit(u0, limit, h1);
        state.model = reached;
        Ok(Command {
            voltage_v: reached.input_v,
            status: CommandStatus::Limited,
        })
    }

    /// One Newton step on `Δu·(k1 + k2·q·g(κΔu)) = e` from `du` (|κ·Δu| < 0.1, |kx| < 0.1,
    /// |w| < 0.2, else `None`).
    #[inline(always)]
    fn n1_newton_step(&self, du: f32, error: f32, kappa: f32, k2q: f32) -> Option<f32> {
        let p = &self.fast;
        let inverse_slope = 1.0 / (p.k1 + k2q);
        let kx = kappa * error * inverse_slope;
        let w = k2q * inverse_slope * kx;
        let z = kappa * du;
        if !(kx.abs() < 0.1 && w.abs() < 0.2 && z.abs() < 0.1) {
            return None;
        }
        let residual = du * (p.k1 + k2q * relax_series(z)) - error;
        Some(du - residual / (p.k1 + k2q * exp_neg_series(z)))
    }

    /// The common case for n ≠ 1, with one power per sample: n ≠ 1, no asymmetric terms, a
    /// consistent state inside the window away from h = 0, a finite reference and a small step.
    /// Along the branch of h₀ (σ = sgn h₀, s the direction, c = β·s·σ + γ) the flow of (BW-u) is
    /// the Taylor series `h(d) = h₀ + f·d + f·f′·d²/2 + (f″·f² + f′²·f)·d³/6` with
    /// f = A − c·|h₀|^n, f′ = −c·n·|h₀|^n/h₀, f″ = f′·(n−1)/h₀. The output equation
    /// `d·(1 + p₂·d + p₃·d²) = x₀` (S₀ = k1 + k2·f, x₀ = e/S₀, p₂ = k2·f·f′/(2S₀),
    /// p₃ = k2·(f″f² + f′²f)/(6S₀)) is inverted by series reversion,
    /// `d = x₀·(1 − P + (2P² − Q) + (5P·Q − 5P³))` with P = p₂x₀, Q = p₃x₀².
    ///
    /// Error estimate: with ν = |f′·d|, ρ = |f·d/h₀| and μ = c·|h₀|^n/f (so f′d = −nμ·f·d/h₀), the
    /// flow's first neglected term relative to f·d, `(f‴f² + 4f″f′f + f′³)·d³/24`, has size
    /// `E₄ = ν·((n−1)|n−2|·ρ² + 4(n−1)·νρ + ν²)/24`; it enters d through p₄x₀³ ≈ (k2·f/S₀)·E₄,
    /// and the reversion's next terms, `14P⁴ − 21P²Q + 3Q²`, are below `21·(P² + |Q|)²`. The path
    /// is taken when `(1 + |k2·f/S₀|)·E₄ + 21·(P² + |Q|)²` is below [`SMALL_STEP_TOLERANCE`] and
    /// ρ < min(0.5, 1.5/(n − 1)) (well inside the series' radius |h₀|, where h would reach zero);
    /// otherwise `None` hands over to the general solve.
    #[inline(always)]
    fn compensate_small_general(
        &self,
        state: &mut CompensatorState,
        desired_m: f32,
    ) -> Option<Command> {
        let p = &self.fast;
        let (u0, h0, error, branch) = self.small_step(state, desired_m)?;
        let c = p.branch[branch];
        let power = math::pow_nonnegative_inline(h0.abs(), p.n);
        // h₀ = 0 gives ∞ here and NaN below, which the checks refuse.
        let inverse_h = 1.0 / h0;
        let f = p.a - c * power;
        let f1 = -c * p.n * power * inverse_h;
        let f2 = f1 * p.n_minus_1 * inverse_h;
        let k2f = p.k2 * f;
        let inverse_slope = 1.0 / (p.k1 + k2f);
        let x0 = error * inverse_slope;
        let lambda = k2f * inverse_slope;
        let curvature = f2 * f + f1 * f1;
        let px = 0.5 * lambda * f1 * x0;
        let p3xx = (1.0 / 6.0) * lambda * curvature * x0 * x0;
        let px2 = px * px;
        let du = x0 * (1.0 - px + (2.0 * px2 - p3xx) + 5.0 * px * (p3xx - px2));
        let moved = f * du;
        let nu = (f1 * du).abs();
        let rho = (moved * inverse_h).abs();
        let reversion = px2 + p3xx.abs();
        let estimate = (1.0 + lambda.abs())
            * nu
            * (p.err_rho2 * rho * rho + nu * (p.err_rho * rho + p.err_nu * nu))
            + 21.0 * reversion * reversion;
        if !(rho < p.rho_max && estimate < SMALL_STEP_TOLERANCE) {
            return None;
        }
        let h1 = h0 + moved * (1.0 + du * (0.5 * f1 + du * (1.0 / 6.0) * curvature));
        self.small_commit(state, u0, h0, du, h1)
    }

    /// The voltage for the desired position with its known velocity \[m/s\] and acceleration \[m/s²\]
    /// (used by the dynamic model's inverse dynamics; ignored by static models).
    pub fn compensate_with_derivatives(
        &self,
        state: &mut CompensatorState,
        desired_m: f32,
        velocity_m_per_s: f32,
        acceleration_m_per_s2: f32,
    ) -> Command {
        let target = match self.target {
            Target::Position => desired_m,
            Target::Force {
                mass_kg,
                damping_n_s_per_m,
                stiffness_n_per_m,
                rest_position_m,
            } => {
                mass_kg * acceleration_m_per_s2
                    + damping_n_s_per_m * velocity_m_per_s
                    + stiffness_n_per_m * (desired_m - rest_position_m)
            }
        };
        self.solve(state, target)
    }

    fn solve(&self, state: &mut CompensatorState, target: f32) -> Command {
        let Limits {
            output_min_v: min,
            output_max_v: max,
            ..
        } = self.settings.limits;
        let model = &self.model;
        let map = model.map();
        let u0 = if state.model.input_v.is_finite() {
            clamp(state.model.input_v, min, max)
        } else {
            clamp(0.0, min, max)
        };
        // Holding the voltage changes the state only through the asymmetric terms (the input shift
        // lets U catch up with u) or when the stored voltage had to be moved into the window; in
        // the common case the hold state is the current one.
        let unchanged = !model.has_extra_terms()
            && u0 == state.model.input_v
            && state.model.hysteresis.input_v == u0;
        state.model.input_v = u0;
        let hold = if unchanged {
            state.model
        } else {
            model.next_state(&state.model, u0)
        };
        if !target.is_finite() {
            state.model = hold;
            return Command {
                voltage_v: u0,
                status: CommandStatus::HeldInvalidReference,
            };
        }
        let error_at_hold = map.output(u0, hold.hysteresis.h) - target;
        if error_at_hold == 0.0 {
            state.model = hold;
            return Command {
                voltage_v: u0,
                status: CommandStatus::Tracking,
            };
        }
        // Direction in which the output error shrinks.
        let direction = if error_at_hold * self.slope_sign < 0.0 {
            1.0
        } else {
            -1.0
        };
        let limit = if direction > 0.0 {
            math::min(max - u0, self.max_step_v)
        } else {
            math::max(min - u0, -self.max_step_v)
        };
        let (reached, du) = self
            .solve_n1_fast(&state.model, u0, -error_at_hold, direction, limit)
            .unwrap_or_else(|| {
                self.solve_newton(
                    &state.model,
                    &hold,
                    u0,
                    target,
                    error_at_hold,
                    direction,
                    limit,
                )
            });
        let remaining = map.output(reached.input_v, reached.hysteresis.h) - target;
        let limited = du == limit && remaining * self.slope_sign * direction < 0.0;
        state.model = reached;
        Command {
            voltage_v: reached.input_v,
            status: if limited {
                CommandStatus::Limited
            } else {
                CommandStatus::Tracking
            },
        }
    }

    /// The general solve, a bracketed Newton iteration in the progress p = Δu·direction ∈ \[0, |limit|\],
    /// on the error `F(p) = (y(p) − y_d)·sign(dy/du)·direction`, which increases with p and is
    /// negative at p = 0. Each evaluation narrows the bracket \[lo, hi\] that holds the root; the
    /// step is Newton's with the exact path derivative of the one-step map, replaced by the
    /// bracket's midpoint when it would leave the bracket (the asymmetric model's δ-term and its
    /// safety clamp make the map kinked). Returns the state reached and Δu.
    #[allow(clippy::too_many_arguments)]
    fn solve_newton(
        &self,
        from: &ModelState,
        hold: &ModelState,
        u0: f32,
        target: f32,
        error_at_hold: f32,
        direction: f32,
        limit: f32,
    ) -> (ModelState, f32) {
        let Limits {
            output_min_v: min,
            output_max_v: max,
            ..
        } = self.settings.limits;
        let model = &self.model;
        let map = model.map();
        let orient = self.slope_sign * direction;
        let (mut lo, mut hi) = (0.0f32, limit.abs());
        let first = -error_at_hold * orient / model.step_slope(from, hold, direction).abs();
        let mut progress = clamp(first, lo, hi);
        let mut reached = model.next_state(from, clamp(u0 + direction * progress, min, max));
        for _ in 0..NEWTON_CORRECTIONS {
            let error = (map.output(reached.input_v, reached.hysteresis.h) - target) * orient;
            if error < 0.0 {
                lo = progress;
            } else {
                hi = progress;
            }
            let slope = model.step_slope(from, &reached, direction).abs();
            let newton = progress - error / slope;
            let next = if newton >= lo && newton <= hi {
                newton
            } else {
                0.5 * (lo + hi)
            };
            if (next - progress).abs() <= self.voltage_tolerance_v {
                break;
            }
            progress = next;
            reached = model.next_state(from, clamp(u0 + direction * progress, min, max));
        }
        (reached, direction * progress)
    }

    /// The fast solve for n = 1 without asymmetric terms. Along an increment that does not cross
    /// h = 0 the one-step map is `y(Δu) = y_hold + Δu·(k1 + k2·q·g(κΔu))`, q = A − κ·h₀
    /// ([`crate::bouc_wen`]), with the exact derivative `k1 + k2·q·e^(−κΔu)` (the slope at the end
    /// state, whose sign the build-time check fixes). Small steps use the series reversion of this
    /// equation to third order; larger ones two Newton steps on it from `Δu = e/(k1 + k2·q)`, g and
    /// e^(−z) from their series: no libm call and no full forward step.
    /// A step with |κΔu| ≥ 0.1 continues in [`Compensator::solve_n1_large`] (g and e^(−z) from
    /// libm's `expm1f`). A step along which h crosses zero continues in
    /// [`Compensator::solve_n1_crossing`]; what neither takes (`None`) goes to
    /// [`Compensator::solve_newton`].
    fn solve_n1_fast(
        &self,
        from: &ModelState,
        u0: f32,
        error: f32,
        direction: f32,
        limit: f32,
    ) -> Option<(ModelState, f32)> {
        let model = &self.model;
        let bw = model.hysteresis();
        if !bw.is_exponent_one() || model.has_extra_terms() {
            return None;
        }
        let StaticMap {
            k1_m_per_v: k1,
            k2_m_per_h: k2,
            ..
        } = model.map();
        let h0 = from.hysteresis.h;
        let (q, kappa, sigma) = bw.n1_branch(h0, direction);
        let k2q = k2 * q;
        let slope_at_start = k1 + k2q;
        let linear = error / slope_at_start;
        // Small steps (the common case in a loop): series reversion of
        // Δu·(1 − (a·κ/2)·Δu + (a·κ²/6)·Δu² − …) = x₀, a = k2·q/S₀, x₀ = e/S₀:
        // Δu = x₀·(1 + w/2 + w²/2 − w·κx₀/6) with w = a·κ·x₀, error O(z³)·Δu ≤ ~1e-6·Δu here.
        let kx = kappa * linear;
        let w = k2q / slope_at_start * kx;
        if kx.abs() < 0.01 && w.abs() < 0.01 {
            let du = toward(
                linear * (1.0 + w * (0.5 + 0.5 * w - kx / 6.0)),
                direction,
                limit,
            );
            let h1 = h0 + q * du * relax_series(kappa * du);
            if h1 * sigma >= 0.0 {
                return Some(self.n1_commit(u0, du, h1));
            }
            return self.solve_n1_crossing(u0, h0, error, direction, limit, (q, kappa, sigma));
        }
        // The start: the root of the map's second-order expansion S₀·Δu − (k2·q·κ/2)·Δu² = e,
        // 2x₀/(1 + √(1 − 2w)), with the square root by its [1/1] Padé form
        // (1 + 3y/4)/(1 + y/4), y = −2w: `x₀·(1 − w/2)/(1 − w)`, x₀·(1 + w/2 + w²/2 + …) for a
        // small step. On a steep branch (a reversal far from h = 0, w ≈ −0.6) it is within
        // about 1 % where x₀ overshoots by 20–30 %; x₀ itself for |w| ≥ 0.9.
        let guess = if w.abs() < 0.9 {
            linear * (1.0 - 0.5 * w) / (1.0 - w)
        } else {
            linear
        };
        let mut du = toward(guess, direction, limit);
        for _ in 0..2 {
            let z = kappa * du;
            if z.abs() >= 0.1 {
                return self.solve_n1_large(u0, h0, error, direction, limit, du);
            }
            let residual = du * (k1 + k2q * relax_series(z)) - error;
            let slope = k1 + k2q * exp_neg_series(z);
            du = toward(du - residual / slope, direction, limit);
        }
        let z = kappa * du;
        if z.abs() >= 0.1 {
            return self.solve_n1_large(u0, h0, error, direction, limit, du);
        }
        let h1 = h0 + q * du * relax_series(z);
        if h1 * sigma < 0.0 {
            return self.solve_n1_crossing(u0, h0, error, direction, limit, (q, kappa, sigma));
        }
        Some(self.n1_commit(u0, du, h1))
    }

    /// [`Compensator::solve_n1_fast`] for a step with |κΔu| ≥ 0.1: Newton on the same equation
    /// `Δu·(k1 + k2·q·g(κΔu)) = e` from `du`, with g(z) = −expm1(−z)/z and the derivative
    /// `k1 + k2·q·e^(−κΔu)` exact (one libm `expm1f` per step, as the model's own step takes it
    /// above |z| = 0.1), at most [`LARGE_STEP_NEWTON`] steps and until a step moves Δu by no
    /// more than the voltage tolerance ([`Compensator::n1_newton`]). `None` (the general solve)
    /// when it does not settle; a step along which h crosses zero goes to
    /// [`Compensator::solve_n1_crossing`].
    #[allow(clippy::too_many_arguments)]
    fn solve_n1_large(
        &self,
        u0: f32,
        h0: f32,
        error: f32,
        direction: f32,
        limit: f32,
        start: f32,
    ) -> Option<(ModelState, f32)> {
        let k2 = self.model.map().k2_m_per_h;
        let (q, kappa, sigma) = self.model.hysteresis().n1_branch(h0, direction);
        let k2q = k2 * q;
        // h moving toward zero (q·Δu against σ) and past it already at the start: the step
        // crosses h = 0, which this branch's closed form does not follow.
        // (|dh/du| ≥ max(A, |q|) on the way to zero would be needed to reach it within the start:
        // the bound first, without the exponential.)
        if q * start * sigma < 0.0
            && h0.abs() < math::max(self.fast.a.abs(), q.abs()) * start.abs()
            && (h0 + q * start * relax_factor(kappa * start)) * sigma < 0.0
        {
            return self.solve_n1_crossing(u0, h0, error, direction, limit, (q, kappa, sigma));
        }
        let du = self.n1_newton(k2q, kappa, error, direction, limit, start)?;
        // h₁ as the model's own step computes it (`BoucWen::advance` on one branch).
        let h1 = h0 + q * du * relax_factor(kappa * du);
        if h1 * sigma < 0.0 {
            return self.solve_n1_crossing(u0, h0, error, direction, limit, (q, kappa, sigma));
        }
        Some(self.n1_commit(u0, du, h1))
    }

    /// Newton on `Δu·(k1 + k2q·g(κΔu)) = e` from `start`, each iterate kept inside
    /// \[0, limit\] (direction > 0) or \[limit, 0\]: g(z) = (1 − e^(−z))/z and the exact
    /// derivative `k1 + k2q·e^(−κΔu)`, both from g's series below |z| = 0.1 and from libm's
    /// `expm1f` above (as the model's own step, `relax_factor`); at most [`LARGE_STEP_NEWTON`]
    /// steps, until one moves Δu by no more than the voltage tolerance or, by Newton's quadratic
    /// convergence, the next one would (`|F''/(2F')|·m² ≤ tolerance/4` after a step m). `None`
    /// when it does not settle or ends non-finite.
    ///
    /// The first step with |κ·start| < 0.1 is taken here, by the series (no call, so nothing
    /// held across one); the steps after it, and a first step that needs `expm1f`, are
    /// [`Compensator::n1_newton_steps`]' (out of line): the same steps in the same order.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn n1_newton(
        &self,
        k2q: f32,
        kappa: f32,
        error: f32,
        direction: f32,
        limit: f32,
        start: f32,
    ) -> Option<f32> {
        let z = kappa * start;
        if z.abs() < 0.1 {
            let g = relax_series(z);
            let (du, settled) =
                self.n1_newton_update(k2q, kappa, error, (direction, limit), start, (-z * g, g));
            if settled {
                // Finite: |Δu| < ∞ (false for NaN), one float compare.
                return (du.abs() < f32::INFINITY).then_some(du);
            }
            return self.n1_newton_steps(
                k2q,
                kappa,
                error,
                (direction, limit),
                du,
                LARGE_STEP_NEWTON - 1,
            );
        }
        self.n1_newton_steps(
            k2q,
            kappa,
            error,
            (direction, limit),
            start,
            LARGE_STEP_NEWTON,
        )
    }

    /// [`Compensator::n1_newton`]'s steps from `du`, at most `steps` of them.
    #[inline(never)]
    fn n1_newton_steps(
        &self,
        k2q: f32,
        kappa: f32,
        error: f32,
        (direction, limit): (f32, f32),
        mut du: f32,
        steps: usize,
    ) -> Option<f32> {
        let mut settled = false;
        for _ in 0..steps {
            let z = kappa * du;
            // e^(−z) − 1 and g(z) = (1 − e^(−z))/z: the series below |z| = 0.1, as `relax_factor`.
            let (em1, g) = if z.abs() < 0.1 {
                let g = relax_series(z);
                (-z * g, g)
            } else {
                let em1 = libm::expm1f(-z);
                (em1, -em1 / z)
            };
            let (next, done) =
                self.n1_newton_update(k2q, kappa, error, (direction, limit), du, (em1, g));
            du = next;
            if done {
                settled = true;
                break;
            }
        }
        (settled && du.is_finite()).then_some(du)
    }

    /// One step of [`Compensator::n1_newton`] from `du` with `(e^(−z) − 1, g(z))` at z = κ·Δu:
    /// the next iterate, and whether it settles the solve.
    #[inline(always)]
    fn n1_newton_update(
        &self,
        k2q: f32,
        kappa: f32,
        error: f32,
        (direction, limit): (f32, f32),
        du: f32,
        (em1, g): (f32, f32),
    ) -> (f32, bool) {
        let k1 = self.model.map().k1_m_per_v;
        let residual = du * (k1 + k2q * g) - error;
        let slope = k1 + k2q * (1.0 + em1);
        let newton = du - residual / slope;
        let next = toward(newton, direction, limit);
        let moved = (next - du).abs();
        // Newton's error after a step of size m is about |F''/(2F')|·m², with
        // F' = k1 + k2q·e^(−κΔu) and F'' = −κ·k2q·e^(−κΔu): when that is below a quarter
        // of the tolerance, the next step would move Δu by less than the tolerance, so it
        // is not taken (not after a step the limit clamped, whose size says nothing).
        let curvature = (kappa * k2q * (1.0 + em1) / (2.0 * slope)).abs();
        let settled = moved <= self.voltage_tolerance_v
            || (next == newton && moved * moved * curvature <= 0.25 * self.voltage_tolerance_v);
        (next, settled)
    }

    /// The fast n = 1 solve for a step along which h crosses zero (from h₀ ≠ 0 on the side σ,
    /// moving toward zero). The model's step ([`crate::bouc_wen::BoucWen::advance`]) reaches
    /// h = 0 after `Δu₀ = −(h₀/A)·ln(1 + x)/x`, x = −κ·h₀/A, and continues on the other side
    /// from h = 0 with κ' = β·s − γ·σ: `h = A·r·g(κ'·r)`, r = Δu − Δu₀. At the crossing the
    /// output has moved by `k1·Δu₀ − k2·h₀` (h₀ → 0), so the rest r solves the one-branch
    /// equation from h = 0,
    ///
    /// ```text
    /// r·(k1 + k2·A·g(κ'·r)) = e_c,   e_c = e − (k1·Δu₀ − k2·h₀)
    /// ```
    ///
    /// (e = y_d − y(u₀)): series reversion for a small r (|κ'x₀|, |w| < 0.01, as in
    /// [`Compensator::solve_n1_fast`]), else [`Compensator::n1_newton`] from the linear guess.
    /// The state is the model's own step to the voltage u = u₀ + Δu₀ + r, so it is the forward
    /// model's bit for bit. `None` (the general solve) when the root is not past the crossing,
    /// the crossing lies beyond the window or slew limit, or the rest does not settle.
    #[inline(never)]
    fn solve_n1_crossing(
        &self,
        u0: f32,
        h0: f32,
        error: f32,
        direction: f32,
        limit: f32,
        (q, kappa, sigma): (f32, f32, f32),
    ) -> Option<(ModelState, f32)> {
        if !(h0 != 0.0 && q * direction * sigma < 0.0) {
            return None;
        }
        // On the way to zero |dh/du| = |A − κ·h| lies between A and |q|, so h cannot reach zero
        // before |Δu| = |h₀|/max(A, |q|): beyond the limit, no crossing (and no logarithm).
        if h0.abs() >= math::max(self.fast.a.abs(), q.abs()) * limit.abs() {
            return None;
        }
        self.n1_crossing_toward_zero(u0, h0, error, direction, limit, (q, kappa, sigma))
            .map(|(reached, du, _)| (reached, du))
    }

    /// [`Compensator::solve_n1_crossing`] after its entry checks: h₀ ≠ 0 moves toward zero
    /// (q·s·σ < 0) and |h₀| < max(A, |q|)·|Δu_lim| (inlined where the caller has made them).
    /// With the state and the step, the crossing's Δu₀.
    #[inline(always)]
    fn n1_crossing_toward_zero(
        &self,
        u0: f32,
        h0: f32,
        error: f32,
        direction: f32,
        limit: f32,
        (q, kappa, sigma): (f32, f32, f32),
    ) -> Option<(ModelState, f32, f32)> {
        let bw = self.model.hysteresis();
        let du0 = bw.n1_zero_reach(h0, kappa)?;
        if !(du0 * direction > 0.0 && du0.abs() < limit.abs()) {
            return None;
        }
        // The parameters are read after the logarithm's call, not held across it.
        let StaticMap {
            k1_m_per_v: k1,
            k2_m_per_h: k2,
            ..
        } = self.model.map();
        let BoucWenParams { a, beta, gamma, .. } = bw.params();
        let error_after = error - (k1 * du0 - k2 * h0);
        // The root lies past the crossing only if the error left there still asks to go on.
        if error_after * self.slope_sign * direction <= 0.0 || error_after.is_nan() {
            return None;
        }
        // The direction is ±1 (`step_direction`): s = sgn Δu is the direction itself.
        let s = direction;
        let kappa_after = beta * s - gamma * sigma;
        // k2·A, k1 + k2·A and k2·A/(k1 + k2·A) from the table built once (the same bits).
        let FastPath {
            k2a,
            slope_at_zero,
            k2a_over_slope,
            ..
        } = self.fast;
        let rest_limit = limit - du0;
        let linear = error_after / slope_at_zero;
        let kx = kappa_after * linear;
        let w = k2a_over_slope * kx;
        let rest = if kx.abs() < 0.01 && w.abs() < 0.01 {
            toward(
                linear * (1.0 + w * (0.5 + 0.5 * w - kx / 6.0)),
                direction,
                rest_limit,
            )
        } else {
            let start = toward(linear, direction, rest_limit);
            self.n1_newton(k2a, kappa_after, error_after, direction, rest_limit, start)?
        };
        let Limits {
            output_min_v: min,
            output_max_v: max,
            ..
        } = self.settings.limits;
        // At the slew limit the step is the limit itself, as the general solve reports it.
        let du = if rest == rest_limit {
            limit
        } else {
            du0 + rest
        };
        let u = clamp(u0 + du, min, max);
        let moved = u - u0;
        // The model's step (`BoucWen::advance`, n = 1: h₀ + q·Δu·g(κΔu) unless that is past
        // zero, else the split at Δu₀), the same operations on the same operands, with this
        // solve's Δu₀ and, at the slew limit, the table's g(κΔu): the one-branch end is needed
        // only when the step may end short of zero.
        let at_slew = moved == direction * self.fast.max_step_v;
        let one_branch = if at_slew {
            let g = self.fast.slew_g[usize::from(direction < 0.0) << 1 | usize::from(sigma < 0.0)];
            Some(h0 + q * moved * g)
        } else if crosses_within(h0, q, kappa, moved) {
            None
        } else {
            Some(h0 + q * moved * relax_factor(kappa * moved))
        };
        let h1 = match one_branch {
            Some(h1) if h1 * sigma >= 0.0 => h1,
            _ => {
                let rest = if (moved - du0) * s > 0.0 {
                    moved - du0
                } else {
                    0.0
                };
                a * rest * relax_factor_inline(kappa_after * rest)
            }
        };
        let h1 = bw.clamp_state(if h1.is_nan() { h0 } else { h1 });
        Some((
            ModelState {
                input_v: u,
                hysteresis: HysteresisState { input_v: u, h: h1 },
            },
            du,
            du0,
        ))
    }

    /// The state after a fast n = 1 step of `du` from `u0` that reached `h1`.
    #[inline]
    fn n1_commit(&self, u0: f32, du: f32, h1: f32) -> (ModelState, f32) {
        let u = clamp(
            u0 + du,
            self.settings.limits.output_min_v,
            self.settings.limits.output_max_v,
        );
        (
            ModelState {
                input_v: u,
                hysteresis: HysteresisState {
                    input_v: u,
                    h: self.model.hysteresis().clamp_state(h1),
                },
            },
            du,
        )
    }
}

/// e^(−z) by its 5-term series 1 − z + z²/2 − z³/6 + z⁴/24 (|z| < 0.1: truncation < 1e-7).
#[inline]
/// Whether one-step slopes dy/du within `[lo, hi]` make an invertible map: finite, of one sign,
/// and `min|dy/du| / max|dy/du| ≥ MIN_SLOPE_RATIO` (module doc).
pub fn is_invertible_slope_range(lo: f32, hi: f32) -> bool {
    lo.is_finite()
        && hi.is_finite()
        && (lo > 0.0 || hi < 0.0)
        && lo.abs().min(hi.abs()) >= MIN_SLOPE_RATIO * lo.abs().max(hi.abs())
}

/// The fastest slew limit \[V/s\] at which [`Compensator::new`] accepts `model` at the sample
/// period `sample_period_s` over a window of `window_v` \[V\]: for a rate-dependent gain the
/// largest step M (to 1e-4 of the window, by bisection, less 1e-5 of itself) whose states and gains keep the map
/// invertible ([`StaticModel::slope_range_for_step`]), as M/T; +∞ when every step up to the
/// whole window does (every model without a rate gain whose map is invertible), 0 when none does.
pub fn fastest_invertible_slew_v_per_s(
    model: &StaticModel,
    window_v: f32,
    sample_period_s: f32,
) -> f32 {
    let accepts = |step: f32| {
        let (lo, hi) = model.slope_range_for_step(step);
        is_invertible_slope_range(lo, hi)
    };
    if accepts(window_v) {
        return f32::INFINITY;
    }
    if !accepts(0.0) {
        return 0.0;
    }
    let (mut ok, mut bad) = (0.0f32, window_v);
    while bad - ok > 1e-4 * window_v {
        let mid = 0.5 * (ok + bad);
        if accepts(mid) {
            ok = mid;
        } else {
            bad = mid;
        }
    }
    // A hair inside, so that the limit read back as a step (S·T in f32) is accepted.
    ok * (1.0 - 1e-5) / sample_period_s
}

fn exp_neg_series(z: f32) -> f32 {
    1.0 - z * (1.0 - 0.5 * z * (1.0 - z * (1.0 / 3.0) * (1.0 - 0.25 * z)))
}

/// Clamps a voltage step into \[0, limit\] (direction > 0) or \[limit, 0\] (direction < 0).
#[inline]
fn toward(du: f32, direction: f32, limit: f32) -> f32 {
    if direction > 0.0 {
        clamp(du, 0.0, limit)
    } else {
        clamp(du, limit, 0.0)
    }
}

/// Whether the n = 1 model's step `Δu` from `h0` on the branch (q = A − κ·h₀, κ), moving h
/// toward zero, surely ends on the other side of zero, as the model decides it
/// ([`crate::bouc_wen::BoucWen::advance`]: by the sign of `h₀ + q·Δu·g(κΔu)` in f32). Along the
/// branch h moves by `q·Δu·g(z)`, z = κΔu, with g(z) = (1 − e^(−z))/z ≥ 1 − max(z, 0)/2 (g's
/// alternating series for 0 < z ≤ 1/2; g ≥ 1 for z ≤ 0), so for |z| ≤ 1/2 and
/// `|h₀| ≤ 0.999·|q·Δu|·(1 − max(z, 0)/2)` the exact end lies past zero by at least 7.5e-4 of
/// |q·Δu|, far beyond the few f32 roundings (≈ 1e-6 of |q·Δu|) of its evaluation. False (not
/// sure) otherwise, and for NaN.
#[inline(always)]
fn crosses_within(h0: f32, q: f32, kappa: f32, du: f32) -> bool {
    let z = kappa * du;
    z.abs() <= 0.5 && h0.abs() <= 0.999 * (q * du).abs() * (1.0 - 0.5 * math::max(z, 0.0))
}

/// The largest f32 ≤ `x`.
fn round_down_f32(x: f64) -> f32 {
    let f = x as f32;
    if f64::from(f) > x {
        f.next_down()
    } else {
        f
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fixtures::x_stack;

    /// The stage's window, 0–120 V at 1e5 V/s, at the sample period `period_s`.
    fn window(period_s: f32) -> CompensatorSettings {
        CompensatorSettings {
            limits: Limits::new(0.0, 120.0, 1e5),
            sample_period_s: period_s,
        }
    }

    /// The per-sample operands the n = 1 edge and crossing take from the table built once are
    /// those they formed per sample, bit for bit: for h₀ ≠ 0 and a finite e ≠ 0, the branch
    /// table's κ at the start's index `2·[e < 0] + [h₀ < 0]` and q = A − κ·h₀ are
    /// `n1_branch(h₀, step_direction(e))`'s; at h₀ = ±0 they may differ (the head then forms
    /// the branch itself); k2·A, k1 + k2·A and k2·A/(k1 + k2·A) are as the crossing formed them.
    #[test]
    fn n1_table_operands_are_the_per_sample_ones() {
        for (sign, k2_factor) in [
            (1.0f32, 0.241f32),
            (-1.0, 0.241),
            (1.0, 0.123),
            (-1.0, 0.19),
        ] {
            let map = StaticMap {
                k1_m_per_v: sign * 0.357e-6,
                k2_m_per_h: -sign * k2_factor * 1e-6,
                offset_m: 1e-7,
            };
            let compensator = Compensator::new(
                StaticModel::new(x_stack(1.0, 1e3), map).unwrap(),
                window(2e-5),
            )
            .unwrap();
            let p = &compensator.fast;
            let bw = compensator.model.hysteresis();
            let a = bw.params().a;
            let (k1, k2) = (map.k1_m_per_v, map.k2_m_per_h);
            assert_eq!(p.k2a.to_bits(), (k2 * a).to_bits());
            assert_eq!(p.slope_at_zero.to_bits(), (k1 + k2 * a).to_bits());
            let k2a = k2 * a;
            assert_eq!(p.k2a_over_slope.to_bits(), (k2a / (k1 + k2a)).to_bits());
            let mut differ_at_zero = 0;
            for h0 in [3.7f32, -3.7, 1e-30, -1e-30, 0.0, -0.0] {
                for error in [2e-6f32, -2e-6, 1e-40, -1e-40] {
                    let (direction, _) = compensator.step_direction(60.0, error);
                    let index = (error.to_bits() >> 31) << 1 | h0.to_bits() >> 31;
                    let kappa = p.branch[index as usize & 3];
                    let q = p.a - kappa * h0;
                    let (q_model, kappa_model, _) = bw.n1_branch(h0, direction);
                    let same = kappa.to_bits() == kappa_model.to_bits()
                        && q.to_bits() == q_model.to_bits();
                    if h0 != 0.0 {
                        assert!(
                            same,
                            "h0={h0} e={error}: table {kappa} {q}, model {kappa_model} {q_model}"
                        );
                    } else if !same {
                        differ_at_zero += 1;
                    }
                }
            }
            // At h₀ = ±0 the sign bit is not σ for every direction: the head must not take the
            // table's branch there.
            assert!(differ_at_zero > 0);
        }
    }

    /// `advance` gives the model's own step bit for bit, from states along a path through both
    /// branches and zero crossings of h, for small and large steps, both slope signs, the
    /// window's edges and outside it, and non-finite voltages; and it takes its small-step path,
    /// also for small steps across h = 0.
    #[test]
    fn advance_is_the_model_step_bit_for_bit() {
        for sign in [1.0f32, -1.0] {
            let map = StaticMap {
                k1_m_per_v: sign * 0.357e-6,
                k2_m_per_h: -sign * 0.357e-6,
                offset_m: 0.0,
            };
            let compensator = Compensator::new(
                StaticModel::new(x_stack(1.0, 1e3), map).unwrap(),
                window(1e-4),
            )
            .unwrap();
            let mut state = CompensatorState::at_rest(0.0);
            let (mut small, mut crossings, mut seed) = (0, 0, 12345u32);
            for k in 0..200_000 {
                seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                let jitter = (seed >> 8) as f32 / (1u32 << 24) as f32 - 0.5;
                let t = k as f32 * 1e-4;
                let u = match k % 1000 {
                    0 => f32::NAN,
                    1 => 130.0,
                    2 => -5.0,
                    3 => 0.0,
                    4 => 120.0,
                    _ => {
                        60.0 - 59.0 * libm::cosf(7.0 * t)
                            + jitter * if k % 7 == 0 { 20.0 } else { 0.02 }
                    }
                };
                let mut expected = state.model;
                compensator.model().step(&mut expected, u);
                let mut got = state;
                if compensator.advance_small_n1(&mut got, u, &ZeroReach::NONE) {
                    small += 1;
                    if got.model.hysteresis.h * state.model.hysteresis.h < 0.0 {
                        crossings += 1;
                    }
                }
                let mut got = state;
                compensator.advance(&mut got, u);
                assert_eq!(
                    (
                        got.model.input_v.to_bits(),
                        got.model.hysteresis.h.to_bits()
                    ),
                    (expected.input_v.to_bits(), expected.hysteresis.h.to_bits()),
                    "k = {k}, u = {u}, from {state:?}"
                );
                assert_eq!(
                    got.model.hysteresis.input_v.to_bits(),
                    expected.hysteresis.input_v.to_bits()
                );
                state = got;
            }
            assert!(small > 150_000, "small steps taken: {small}");
            assert!(
                crossings > 1_000,
                "small steps across h = 0 taken: {crossings}"
            );
        }
    }

    /// From h = +0 and h = −0 (a stage at rest, or a step that ended on zero), `advance` takes
    /// its small path for every nonzero small step of either sign (σ from the sign of A·Δu, as
    /// the model's `branch_sign`) and gives the model's own step bit for bit, the sign of a
    /// zero h included; a zero step leaves h as it was.
    #[test]
    fn advance_from_h_zero_is_the_model_step_bit_for_bit() {
        for sign in [1.0f32, -1.0] {
            let map = StaticMap {
                k1_m_per_v: sign * 0.357e-6,
                k2_m_per_h: -sign * 0.357e-6,
                offset_m: 0.0,
            };
            let compensator = Compensator::new(
                StaticModel::new(x_stack(1.0, 1e3), map).unwrap(),
                window(2e-5),
            )
            .unwrap();
            let mut small = 0;
            for h0 in [0.0f32, -0.0] {
                for u0 in [0.0f32, 1e-3, 37.5, 60.0, 119.0, 120.0] {
                    for du in [
                        0.0f32, -0.0, 1e-30, -1e-30, 1e-6, -1e-6, 0.013, -0.013, 1.7, -1.7, 2.0,
                        -2.0, 9.0, -9.0,
                    ] {
                        let from = CompensatorState {
                            model: ModelState {
                                input_v: u0,
                                hysteresis: HysteresisState { input_v: u0, h: h0 },
                            },
                        };
                        let u = u0 + du;
                        let mut expected = from.model;
                        compensator.model().step(&mut expected, u);
                        let mut by_small = from;
                        let took = compensator.advance_small_n1(&mut by_small, u, &ZeroReach::NONE);
                        let mut got = from;
                        compensator.advance(&mut got, u);
                        let bits = |m: &ModelState| {
                            [m.input_v, m.hysteresis.input_v, m.hysteresis.h].map(f32::to_bits)
                        };
                        assert_eq!(
                            bits(&got.model),
                            bits(&expected),
                            "h0 {h0:?}, u0 {u0}, du {du:e}"
                        );
                        if took {
                            small += 1;
                            assert_eq!(bits(&by_small.model), bits(&expected));
                        }
                        let step = u - u0;
                        if step == 0.0 {
                            assert!(!took, "a zero step is the model's");
                        } else if (0.0..=120.0).contains(&u) && step.abs() <= 1.7 {
                            assert!(took, "h0 {h0:?}, u0 {u0}, du {du:e}");
                        }
                    }
                }
            }
            assert!(small >= 70, "{small}");
        }
    }

    /// [`Compensator::compensate_noting`] and [`Compensator::advance_noted`] give what
    /// `compensate` and `advance` give, bit for bit, on the loop's per-tick stream
    /// ([`n1_tick_stream`]'s), while the noted Δu₀ is taken for most advances across h = 0;
    /// a memo of another model (another A) or of another h₀ is never taken.
    #[test]
    fn noted_zero_reach_gives_the_same_bits() {
        let settings = window(2e-5).inside_guard();
        let map = StaticMap {
            k1_m_per_v: 3.573_939e-7,
            k2_m_per_h: -3.573_939e-7,
            offset_m: 0.0,
        };
        let compensator =
            Compensator::new(StaticModel::new(x_stack(1.0, 1e3), map).unwrap(), settings).unwrap();
        let mut other_a = x_stack(1.0, 1e3).params();
        other_a.a *= 0.97;
        let other = Compensator::new(
            StaticModel::new(
                crate::bouc_wen::BoucWen::with_input_range(other_a, 0.0, 120.0, 1e3).unwrap(),
                map,
            )
            .unwrap(),
            settings,
        )
        .unwrap();
        let max_step = settings.limits.slew_limit_v_per_s * settings.sample_period_s;
        let mut seed = 7u32;
        let mut rand = || {
            seed = seed.wrapping_mul(1664525).wrapping_add(1013904223);
            (seed >> 8) as f32 / (1u32 << 24) as f32
        };
        let (mut plain, mut noting) = (
            CompensatorState::at_rest(0.0),
            CompensatorState::at_rest(0.0),
        );
        let mut memo = ZeroReach::NONE;
        let (mut correction, mut taken, mut foreign) = (0.0f32, 0u32, 0u32);
        for k in 0..100_000u32 {
            let t = k as f32 * 2e-5;
            let y_d = 21e-6 - 17e-6 * libm::cosf(2.0 * core::f32::consts::PI * 10.0 * t)
                + 2e-9 * (rand() - 0.5);
            let before = plain;
            let a = compensator.compensate(&mut plain, y_d);
            let b = compensator.compensate_noting(&mut noting, y_d, &mut memo);
            assert_eq!(
                (a.voltage_v.to_bits(), a.status),
                (b.voltage_v.to_bits(), b.status),
                "k={k}"
            );
            assert_eq!(plain, noting, "k={k}");
            correction = (correction + 3.0 * (rand() - 0.5)).clamp(-14.0, 14.0);
            let u0 = before.model.input_v;
            let applied = (a.voltage_v + correction)
                .clamp(u0 - max_step, u0 + max_step)
                .clamp(0.0, 120.0);
            let mut advanced = before;
            compensator.advance(&mut advanced, applied);
            let mut by_memo = before;
            compensator.advance_noted(&mut by_memo, applied, &memo);
            assert_eq!(
                advanced.model.hysteresis.h.to_bits(),
                by_memo.model.hysteresis.h.to_bits(),
                "k={k}"
            );
            assert_eq!(advanced, by_memo, "k={k}");
            let h0 = before.model.hysteresis.h;
            let crossed = h0 * advanced.model.hysteresis.h < 0.0;
            if crossed && memo.h0_bits == h0.to_bits() {
                taken += 1;
                // The same memo for a model with another A (same h₀, same κ) is not taken.
                let mut other_state = before;
                other.advance(&mut other_state, applied);
                let mut other_memo = before;
                other.advance_noted(&mut other_memo, applied, &memo);
                assert_eq!(other_state, other_memo, "k={k}");
                foreign += 1;
            }
            plain = advanced;
            noting = advanced;
        }
        assert!(taken > 300 && foreign == taken, "{taken} {foreign}");
    }

    /// The solve's direction and step limit from `u0` for the output error `error_at_hold`, as
    /// `Compensator::solve` takes them, in the 0–120 V window.
    fn direction_and_limit(compensator: &Compensator, u0: f32, error_at_hold: f32) -> (f32, f32) {
        let direction = if error_at_hold * compensator.slope_sign < 0.0 {
            1.0
        } else {
            -1.0
        };
        let limit = if direction > 0.0 {
            (120.0 - u0).min(compensator.max_step_v)
        } else {
            (0.0 - u0).max(-compensator.max_step_v)
        };
        (direction, limit)
    }

    /// Steps along which h crosses zero (every reversal of a 5–45 µm sine at 3 Hz and 10 kHz,
    /// with jitter, and random jumps of up to 40 µm), for both slope signs: the fast n = 1 solve
    /// takes them ([`Compensator::solve_n1_crossing`]) instead of handing them to the general
    /// solve, lands on the general Newton solve's voltage within [`CROSSING_TOLERANCE_V`] (steps
    /// below 1 V) or 1e-4 V (larger steps), and its state is the forward model's step to its voltage, bit
    /// for bit.
    #[test]
    fn zero_crossings_of_the_fast_solve_agree_with_newton() {
        for sign in [1.0f32, -1.0] {
            let bw = x_stack(1.0, 1e3);
            let map = StaticMap {
                k1_m_per_v: sign * 0.53e-6,
                k2_m_per_h: -sign * 0.53e-6,
                offset_m: 0.0,
            };
            let compensator =
                Compensator::new(StaticModel::new(bw, map).unwrap(), window(1e-4)).unwrap();
            let mut state = CompensatorState::at_rest(60.0);
            let mut seed = 4321u32;
            let mut rand = || {
                seed = seed.wrapping_mul(1664525).wrapping_add(1013904223);
                (seed >> 8) as f32 / (1u32 << 24) as f32
            };
            let (mut small, mut jumps, mut worst) = (0, 0, 0.0f32);
            for k in 0..40_000 {
                let t = k as f32 * 1e-4;
                let jump = k % 97 == 0;
                let y_d = if jump {
                    5e-6 + 40e-6 * rand()
                } else {
                    25e-6 - 20e-6 * libm::cosf(2.0 * core::f32::consts::PI * 3.0 * t)
                        + 5e-9 * (rand() - 0.5)
                };
                let y_d = sign * y_d;
                let hold = state.model;
                let u0 = hold.input_v;
                let error_at_hold = compensator.model.output(&hold) - y_d;
                if error_at_hold != 0.0 {
                    let (direction, limit) = direction_and_limit(&compensator, u0, error_at_hold);
                    let newton = compensator.solve_newton(
                        &hold,
                        &hold,
                        u0,
                        y_d,
                        error_at_hold,
                        direction,
                        limit,
                    );
                    let h0 = hold.hysteresis.h;
                    let crosses = h0 != 0.0 && newton.0.hysteresis.h * h0 < 0.0;
                    if crosses {
                        let fast = compensator
                            .solve_n1_fast(&hold, u0, -error_at_hold, direction, limit)
                            .unwrap_or_else(|| panic!("k={k}: a crossing from h {h0} refused"));
                        let difference = (fast.0.input_v - newton.0.input_v).abs();
                        let mut expected = hold;
                        compensator.model().step(&mut expected, fast.0.input_v);
                        assert_eq!(
                            fast.0.hysteresis.h.to_bits(),
                            expected.hysteresis.h.to_bits(),
                            "k={k}: the state is not the model's step"
                        );
                        if (fast.1).abs() >= 1.0 {
                            jumps += 1;
                            assert!(difference < 1e-4, "k={k}: large step off by {difference} V");
                        } else {
                            small += 1;
                            worst = worst.max(difference);
                            let residual =
                                |m: &ModelState| (compensator.model.output(m) - y_d).abs();
                            let ulp = f32::from_bits(y_d.abs().to_bits() + 2) - y_d.abs();
                            assert!(
                                difference < CROSSING_TOLERANCE_V
                                    && residual(&fast.0) <= residual(&newton.0) + ulp,
                                "k={k}: u {} newton {} (from {u0}, h {h0}), residuals {} {}",
                                fast.0.input_v,
                                newton.0.input_v,
                                residual(&fast.0),
                                residual(&newton.0)
                            );
                        }
                    }
                }
                compensator.compensate(&mut state, y_d);
            }
            assert!(
                small >= 20 && jumps >= 20,
                "{small} small (worst {worst} V), {jumps} jumps"
            );
        }
    }

    /// Targets anywhere in the stroke every few ticks, for both slope signs, at 10 and 20 kHz
    /// (slew steps of 10 and 5 V): [`Compensator::compensate`] settles the steps its small path
    /// refuses without the general solve ([`Compensator::compensate_n1_edge`]), many of them
    /// stopped by the slew limit, over three quarters of which [`Compensator::compensate_limited_n1`]
    /// settles alone with the same result (the rest cross h = 0); every voltage is the
    /// general Newton solve's within 1e-4 V, with the same status (`Limited` or `Tracking`), and
    /// the state is the model's at the voltage within f32 rounding of h.
    #[test]
    fn edge_steps_agree_with_newton() {
        for (sign, period) in [(1.0f32, 1e-4f32), (-1.0, 1e-4), (1.0, 5e-5)] {
            let bw = x_stack(1.0, 1e3);
            let map = StaticMap {
                k1_m_per_v: sign * 0.53e-6,
                k2_m_per_h: -sign * 0.53e-6,
                offset_m: 0.0,
            };
            let compensator =
                Compensator::new(StaticModel::new(bw, map).unwrap(), window(period)).unwrap();
            let mut state = CompensatorState::at_rest(0.0);
            let mut seed = 777u32;
            let mut rand = || {
                seed = seed.wrapping_mul(1664525).wrapping_add(1013904223);
                (seed >> 8) as f32 / (1u32 << 24) as f32
            };
            let (mut edge, mut limited, mut limited_alone) = (0, 0, 0);
            let mut y_d = 0.0;
            for k in 0..20_000 {
                if k % 5 == 0 {
                    y_d = sign * (2e-6 + 55e-6 * rand());
                }
                let hold = state.model;
                let u0 = hold.input_v;
                let error_at_hold = compensator.model.output(&hold) - y_d;
                let mut small = state;
                let by_small = compensator.compensate_small_n1(&mut small, y_d).is_some();
                let mut fast = state;
                let by_edge = compensator.compensate_n1_edge(
                    &mut fast,
                    u0,
                    hold.hysteresis.h,
                    -error_at_hold,
                    y_d,
                );
                let command = compensator.compensate(&mut state, y_d);
                if by_small || error_at_hold == 0.0 {
                    continue;
                }
                let by_edge = by_edge.unwrap_or_else(|| panic!("k={k}: refused from {hold:?}"));
                assert_eq!(by_edge, command, "k={k}");
                edge += 1;
                let (direction, limit) = direction_and_limit(&compensator, u0, error_at_hold);
                let newton = compensator.solve_newton(
                    &hold,
                    &hold,
                    u0,
                    y_d,
                    error_at_hold,
                    direction,
                    limit,
                );
                let remaining = compensator.model.output(&newton.0) - y_d;
                let newton_limited =
                    newton.1 == limit && remaining * compensator.slope_sign * direction < 0.0;
                assert!(
                    (command.voltage_v - newton.0.input_v).abs() < 1e-4,
                    "k={k}: u {} newton {}",
                    command.voltage_v,
                    newton.0.input_v
                );
                assert_eq!(
                    command.status == CommandStatus::Limited,
                    newton_limited,
                    "k={k}: {command:?}"
                );
                if newton_limited {
                    limited += 1;
                    // The limited step's own solve takes it, and gives what `compensate` gave.
                    let mut alone = CompensatorState { model: hold };
                    let by_limit = compensator.compensate_limited_n1(
                        &mut alone,
                        u0,
                        hold.hysteresis.h,
                        -error_at_hold,
                        direction,
                        limit,
                    );
                    if let Some(by_limit) = by_limit {
                        assert_eq!(by_limit, command, "k={k}");
                        assert_eq!(alone, state, "k={k}");
                        limited_alone += 1;
                    }
                }
                let mut expected = hold;
                compensator.model().step(&mut expected, command.voltage_v);
                let h = state.model.hysteresis.h;
                assert!(
                    (h - expected.hysteresis.h).abs() <= 1e-5 * (1.0 + h.abs()),
                    "k={k}: h {h} model {}",
                    expected.hysteresis.h
                );
            }
            assert!(
                edge > 2_000 && limited > 500 && limited_alone * 4 > limited * 3,
                "{edge} edge steps, {limited} limited, {limited_alone} by the limited step's solve"
            );
        }
    }

    /// Largest difference between the fast solve's voltage and the general solve's on a small
    /// step across h = 0 \[V\]: the general solve's own tolerance (1e-7 of the 120 V window,
    /// 1.2e-5 V) or two f32 steps of the voltage near 100 V (7.6e-6 V each), whichever is larger;
    /// where they differ, the fast solve's output is as close to the target (within two f32
    /// steps of the output, one of the voltage).
    const CROSSING_TOLERANCE_V: f32 = 1.6e-5;

    /// Targets anywhere in the stroke every tick (steps of up to 50 µm): the fast n = 1 solve
    /// takes its large-step path (|κΔu| ≥ 0.1, exact `expm1f`) more than a thousand times and
    /// lands on the general Newton solve's voltage within 1e-4 V every time.
    #[test]
    fn large_steps_of_the_fast_solve_agree_with_newton() {
        let bw = x_stack(1.0, 1e3);
        let map = StaticMap {
            k1_m_per_v: 0.53e-6,
            k2_m_per_h: -0.53e-6,
            offset_m: 0.0,
        };
        let compensator =
            Compensator::new(StaticModel::new(bw, map).unwrap(), window(1e-4)).unwrap();
        let mut state = CompensatorState::at_rest(0.0);
        let mut large = 0;
        let mut seed = 12345u32;
        let mut rand = || {
            seed = seed.wrapping_mul(1664525).wrapping_add(1013904223);
            (seed >> 8) as f32 / (1u32 << 24) as f32
        };
        for k in 0..20_000 {
            let y_d = 5e-6 + 50e-6 * rand();
            let hold = state.model;
            let u0 = hold.input_v;
            let error_at_hold = compensator.model.output(&hold) - y_d;
            if error_at_hold != 0.0 {
                let (direction, limit) = direction_and_limit(&compensator, u0, error_at_hold);
                let newton = compensator.solve_newton(
                    &hold,
                    &hold,
                    u0,
                    y_d,
                    error_at_hold,
                    direction,
                    limit,
                );
                if let Some(fast) =
                    compensator.solve_n1_fast(&hold, u0, -error_at_hold, direction, limit)
                {
                    let (_, kappa, _) = bw.n1_branch(hold.hysteresis.h, direction);
                    if (kappa * fast.1).abs() >= 0.1 {
                        large += 1;
                    }
                    assert!(
                        (fast.0.input_v - newton.0.input_v).abs() < 1e-4,
                        "k={k}: u {} newton {} (from {u0}, h {}, limit {limit}, du {} / {})",
                        fast.0.input_v,
                        newton.0.input_v,
                        hold.hysteresis.h,
                        fast.1,
                        newton.1
                    );
                }
            }
            compensator.compensate(&mut state, y_d);
        }
        assert!(large > 1000, "{large}");
    }

    /// The small-step paths (n = 1 and general n) and the fast n = 1 solve give the same voltage
    /// and state as the general bracketed Newton solve, and their state is the forward model's.
    #[test]
    fn fast_paths_agree_with_newton() {
        for n in [1.0f32, 1.5, 2.5] {
            // Stage-like: the XY stage's x stack (n = 1); for other n, β and γ scaled to keep H.
            let bw = x_stack(n, 1e3);
            let map = StaticMap {
                k1_m_per_v: 0.53e-6,
                k2_m_per_h: -0.53e-6,
                offset_m: 0.0,
            };
            let compensator =
                Compensator::new(StaticModel::new(bw, map).unwrap(), window(1e-4)).unwrap();
            let mut state = CompensatorState::at_rest(0.0);
            let (mut small_taken, mut compared) = (0, 0);
            for k in 0..20_000 {
                let t = k as f32 * 1e-4;
                let y_d = 30e-6 - 25e-6 * libm::cosf(2.0 * core::f32::consts::PI * 3.0 * t)
                    + 2e-6 * libm::sinf(2.0 * core::f32::consts::PI * 47.0 * t);
                let before = state;
                let u0 = before.model.input_v;
                let hold = before.model;
                let error_at_hold = compensator.model.output(&hold) - y_d;
                let (direction, limit) = direction_and_limit(&compensator, u0, error_at_hold);
                let mut small = before;
                let small_result = if n == 1.0 {
                    compensator.compensate_small_n1(&mut small, y_d)
                } else {
                    compensator.compensate_small_general(&mut small, y_d)
                };
                if error_at_hold != 0.0 {
                    let newton = compensator.solve_newton(
                        &hold,
                        &hold,
                        u0,
                        y_d,
                        error_at_hold,
                        direction,
                        limit,
                    );
                    // Both solve y(u) = y_d to the f32 resolution of y (ulp ≈ 3.6e-12 m at
                    // 40 µm, i.e. ≈ 2e-5 V at this slope): compare residuals in ulps and
                    // voltages to 1e-4 V.
                    let ulp = f32::EPSILON * y_d.abs();
                    let residual_newton = (compensator.model.output(&newton.0) - y_d).abs();
                    let check = |label: &str, reached: ModelState| {
                        let residual = (compensator.model.output(&reached) - y_d).abs();
                        assert!(
                            residual <= residual_newton + 4.0 * ulp,
                            "n={n} k={k} {label}: residual {residual:e}, newton {residual_newton:e}"
                        );
                        assert!(
                            (reached.input_v - newton.0.input_v).abs() < 1e-4,
                            "n={n} k={k} {label}: u {} newton {}",
                            reached.input_v,
                            newton.0.input_v
                        );
                        let forward = compensator.model.next_state(&before.model, reached.input_v);
                        assert!(
                            (reached.hysteresis.h - forward.hysteresis.h).abs()
                                < 1e-5 * bw.state_bound(),
                            "n={n} k={k} {label}: h {} forward {}",
                            reached.hysteresis.h,
                            forward.hysteresis.h
                        );
                    };
                    if small_result.is_some() {
                        small_taken += 1;
                        check("small", small.model);
                    }
                    if n == 1.0 {
                        if let Some(fast) =
                            compensator.solve_n1_fast(&hold, u0, -error_at_hold, direction, limit)
                        {
                            check("fast", fast.0);
                        }
                    }
                    compared += 1;
                }
                compensator.compensate(&mut state, y_d);
            }
            // The small-step path is the common case in a loop at a normal rate.
            assert!(
                small_taken * 10 > compared * 8,
                "n={n}: small path taken {small_taken} of {compared}"
            );
        }
    }

    /// The XY stage's x stack (y = d·(u − h), n = 1) with its operator behind an input lag.
    fn lagged_stage(lag_s: f32, period_s: f32) -> StaticModel {
        let map = StaticMap {
            k1_m_per_v: 3.2e-7,
            k2_m_per_h: -3.2e-7,
            offset_m: 0.0,
        };
        StaticModel::new(x_stack(1.0, crate::STATE_LIMIT), map)
            .unwrap()
            .with_input_lag(lag_s, period_s)
            .unwrap()
    }

    /// With an input lag the compensator's Newton solve (slope k1 + k2·b·dh/dv) is exact: the
    /// forward model driven by its voltages reproduces every reachable reference to f32 rounding,
    /// at 20 and 200 Hz, and the state is the model's own step.
    #[test]
    fn input_lag_inverse_reproduces_the_reference() {
        let period = 1e-4;
        let model = lagged_stage(1e-3, period);
        for freq in [20.0f32, 200.0] {
            let worst = worst_inverse_error(model, period, 3e-6, 9e-6, freq);
            assert!(worst < 1e-11, "{freq} Hz: worst {worst} m");
        }
    }

    /// The largest |y − y_d| of `model` driven by its compensator's voltages (0–120 V at 1e5 V/s)
    /// for y_d = `low_m` + `swing_m`·(1 − cos 2π·`freq`·t) over 2 s at the period `period`,
    /// asserting that every command tracks and that the compensator's state is the model's own.
    fn worst_inverse_error(
        model: StaticModel,
        period: f32,
        low_m: f32,
        swing_m: f32,
        freq: f32,
    ) -> f32 {
        let compensator = Compensator::new(model, window(period)).unwrap();
        let mut state = CompensatorState::at_rest(0.0);
        let mut forward = ModelState::at_rest(0.0);
        let mut worst = 0.0f32;
        for k in 0..20_000 {
            let t = k as f32 * period;
            let y_d = low_m + swing_m * (1.0 - libm::cosf(2.0 * core::f32::consts::PI * freq * t));
            let command = compensator.compensate(&mut state, y_d);
            assert_eq!(
                command.status,
                CommandStatus::Tracking,
                "k = {k} {command:?} {y_d}"
            );
            let y = model.step(&mut forward, command.voltage_v);
            assert_eq!(forward, state.model, "k = {k}");
            worst = worst.max((y - y_d).abs());
        }
        worst
    }

    /// The lag changes the loop with the rate: at 1 Hz the lagged model is the standard one
    /// within 0.2 % of the stroke, at 100 Hz it differs by several per cent.
    #[test]
    fn input_lag_is_rate_dependent() {
        let period = 1e-4;
        let lagged = lagged_stage(1e-3, period);
        let standard = lagged_stage(0.0, period);
        for (freq, lo, hi) in [(1.0f32, 0.0, 0.002), (100.0, 0.02, 0.5)] {
            let (mut a, mut b) = (ModelState::at_rest(0.0), ModelState::at_rest(0.0));
            let mut worst = 0.0f32;
            let n = (3.0 / (freq * period)) as usize;
            for k in 0..n {
                let t = k as f32 * period;
                let u = 60.0 - 60.0 * libm::cosf(2.0 * core::f32::consts::PI * freq * t);
                worst = worst.max((lagged.step(&mut a, u) - standard.step(&mut b, u)).abs());
            }
            let share = worst / (3.2e-7 * 120.0);
            assert!(share >= lo && share <= hi, "{freq} Hz: {share}");
        }
    }

    /// Lags the model cannot run are refused when built, naming the field.
    #[test]
    fn input_lag_refusals_name_the_field() {
        let period = 1e-4;
        let base = lagged_stage(0.0, period);
        for lag in [-1e-3, 0.5e-4, 2.0, f32::NAN, f32::INFINITY] {
            let got = base.with_input_lag(lag, period);
            assert!(
                matches!(
                    got,
                    Err(ParamError::OutOfRange {
                        field: "hysteresis_lag_s",
                        ..
                    }) | Err(ParamError::NonFinite {
                        field: "hysteresis_lag_s"
                    })
                ),
                "{lag}: {got:?}"
            );
        }
        // A k1 too small against the hysteretic gain: the inverse's recursion through the lag
        // would ring (its error factor below −1/2).
        let map = StaticMap {
            k1_m_per_v: 1e-9,
            k2_m_per_h: 3.2e-7,
            offset_m: 0.0,
        };
        let steep = StaticModel::new(*base.hysteresis(), map)
            .unwrap()
            .with_input_lag(1e-4, period)
            .unwrap();
        assert!(matches!(
            Compensator::new(steep, window(period)),
            Err(ParamError::OutOfRange {
                field: "hysteresis_lag_s",
                ..
            })
        ));
        let asymmetric = StaticModel::asymmetric(
            *base.hysteresis(),
            base.map(),
            crate::Asymmetry {
                delta_per_v_s: 1e-3,
                input_shift_s: 0.0,
            },
            period,
        )
        .unwrap();
        assert!(asymmetric.with_input_lag(1e-3, period).is_err());
    }

    /// Hostile references through the lagged inverse: never NaN, never outside the window, never
    /// a step beyond the slew limit.
    #[test]
    fn input_lag_inverse_is_safe_on_hostile_references() {
        let period = 1e-4;
        assert_safe_on_hostile_references(lagged_stage(5e-4, period), period, 7);
    }

    /// Drives a compensator of `model` in the 0–120 V window at 1e5 V/s with 200 000 hostile
    /// references (NaN, ±∞, ±1e30 m, random positions; `seed`): every voltage finite, inside the
    /// window and within the slew limit of the last, every state finite.
    fn assert_safe_on_hostile_references(model: StaticModel, period: f32, seed: u32) {
        let settings = window(period);
        let compensator = Compensator::new(model, settings).unwrap();
        let mut state = CompensatorState::at_rest(0.0);
        let mut seed = seed;
        let mut last = 0.0f32;
        for k in 0..200_000 {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            let r = (seed >> 8) as f32 / (1u32 << 24) as f32;
            let y_d = match k % 11 {
                0 => f32::NAN,
                1 => f32::INFINITY,
                2 => -1e30,
                3 => 1e30,
                _ => (r - 0.2) * 60e-6,
            };
            let u = compensator.compensate(&mut state, y_d).voltage_v;
            assert!(u.is_finite() && (0.0..=120.0).contains(&u), "k = {k}: {u}");
            assert!((u - last).abs() <= settings.limits.slew_limit_v_per_s * period * 1.000_001);
            assert!(state.model.hysteresis.h.is_finite());
            last = u;
        }
    }

    /// The x stack (n = 1) with half its hysteretic gain in the map, its operator's gain rising
    /// with the speed of its input, c = `gain` \[s/V\].
    fn rate_gain_stage(gain: f32, period_s: f32) -> StaticModel {
        let map = StaticMap {
            k1_m_per_v: 3.2e-7,
            k2_m_per_h: -1.6e-7,
            offset_m: 0.0,
        };
        StaticModel::new(x_stack(1.0, crate::STATE_LIMIT), map)
            .unwrap()
            .with_rate_gain(gain, period_s)
            .unwrap()
    }

    /// With a rate-dependent gain (alone and behind an input lag) the compensator's Newton solve
    /// is exact: the forward model driven by its voltages reproduces 20 and 200 Hz references
    /// within 1e-11 m, and its state is the model's own step.
    #[test]
    fn rate_gain_inverse_reproduces_the_reference() {
        let period = 1e-4;
        for lag in [0.0f32, 5e-4] {
            let model = rate_gain_stage(5e-6, period)
                .with_input_lag(lag, period)
                .unwrap();
            for freq in [20.0f32, 200.0] {
                let worst = worst_inverse_error(model, period, 1e-6, 4e-6, freq);
                assert!(worst < 1e-11, "lag {lag}, {freq} Hz: worst {worst} m");
            }
        }
    }

    /// A rate gain whose one-step map would not stay monotone at the speeds the slew limit
    /// allows is refused, naming the field; the same set at a slower slew limit is accepted.
    #[test]
    fn a_rate_gain_too_strong_for_the_slew_limit_is_refused() {
        let period = 1e-4;
        let model = rate_gain_stage(1e-4, period);
        let got = Compensator::new(model, window(period));
        assert!(
            matches!(
                got,
                Err(ParamError::OutOfRange {
                    field: "hysteresis_rate_gain_s_per_v",
                    ..
                })
            ),
            "{:?}",
            got.err()
        );
        // The fastest slew limit it is accepted at: accepted there, refused 1 % above.
        let fastest = fastest_invertible_slew_v_per_s(&model, 120.0, period);
        assert!(fastest > 1e3 && fastest < 1e5, "{fastest}");
        let at = |slew: f32| CompensatorSettings {
            limits: Limits::new(0.0, 120.0, slew),
            sample_period_s: period,
        };
        assert!(Compensator::new(model, at(fastest)).is_ok());
        assert!(Compensator::new(model, at(1.01 * fastest)).is_err());
        // Without a rate gain every slew limit is.
        let plain = rate_gain_stage(0.0, period);
        assert_eq!(
            fastest_invertible_slew_v_per_s(&plain, 120.0, period),
            f32::INFINITY
        );
    }

    /// Hostile references through the rate-gain inverse: never NaN, never outside the window,
    /// never a step beyond the slew limit.
    #[test]
    fn rate_gain_inverse_is_safe_on_hostile_references() {
        let period = 1e-4;
        assert_safe_on_hostile_references(rate_gain_stage(5e-6, period), period, 11);
    }

    /// `crosses_within` never says "crosses" where the model's step (the one-branch end
    /// `h₀ + q·Δu·g(κΔu)` in f32, `BoucWen::advance`'s test) stays on h₀'s side, over random
    /// states and steps toward zero on all four branches, and says it for most steps that end
    /// past zero by more than 1 % of |q·Δu|.
    #[test]
    fn crosses_within_is_the_model_s_crossing() {
        let bw = x_stack(1.0, 1e3);
        let mut seed = 99u32;
        let mut rand = || {
            seed = seed.wrapping_mul(1664525).wrapping_add(1013904223);
            (seed >> 8) as f32 / (1u32 << 24) as f32
        };
        let (mut sure, mut clear) = (0u32, 0u32);
        for _ in 0..200_000 {
            let h0 = 30.0 * (rand() - 0.5);
            let direction = if rand() < 0.5 { -1.0 } else { 1.0 };
            let (q, kappa, sigma) = bw.n1_branch(h0, direction);
            if !(h0 != 0.0 && q * direction * sigma < 0.0) {
                continue;
            }
            let du = direction * 12.0 * rand();
            let end = h0 + q * du * relax_factor(kappa * du);
            if crosses_within(h0, q, kappa, du) {
                sure += 1;
                assert!(end * sigma < 0.0, "h0 {h0} du {du}: ends at {end}");
            }
            if end * sigma < -0.01 * (q * du).abs() && (kappa * du).abs() <= 0.5 {
                clear += 1;
            }
        }
        assert!(sure * 10 > clear * 9 && clear > 3_000, "{sure} of {clear}");
    }

    /// FNV-1a (64 bit) of a stream of words.
    fn fnv1a(hash: &mut u64, word: u32) {
        for byte in word.to_le_bytes() {
            *hash = (*hash ^ u64::from(byte)).wrapping_mul(0x0100_0000_01b3);
        }
    }

    /// What [`n1_tick_stream`] hashed and how often it took the paths it is there for.
    #[derive(Debug, Default)]
    struct StreamSummary {
        hash: u64,
        limited: u32,
        crossings: u32,
        advance_crossings: u32,
    }

    /// A loop's per-tick n = 1 work as the firmware runs it with feedback: the compensator on a
    /// reference (a 10 Hz sine over most of the stroke with reversals, noise and a jump every
    /// 211 ticks), then a servo-like correction (a bounded random walk, inside the slew limit
    /// and the window; none every third tick) and [`Compensator::advance`] by the voltage so
    /// applied from the state before the tick. Every voltage, status and state, as f32 bits.
    fn n1_tick_stream(sign: f32, rate_hz: f32, ticks: u32) -> StreamSummary {
        let bw = x_stack(1.0, 1e3);
        let map = StaticMap {
            k1_m_per_v: sign * 3.573_939e-7,
            k2_m_per_h: -sign * 3.573_939e-7,
            offset_m: 0.0,
        };
        let settings = window(1.0 / rate_hz).inside_guard();
        let compensator = Compensator::new(StaticModel::new(bw, map).unwrap(), settings).unwrap();
        let max_step = settings.limits.slew_limit_v_per_s * settings.sample_period_s;
        let mut seed = 2024u32;
        let mut rand = || {
            seed = seed.wrapping_mul(1664525).wrapping_add(1013904223);
            (seed >> 8) as f32 / (1u32 << 24) as f32
        };
        let mut state = CompensatorState::at_rest(0.0);
        let mut correction = 0.0f32;
        let mut out = StreamSummary {
            hash: 0xcbf2_9ce4_8422_2325,
            ..StreamSummary::default()
        };
        let mut jump = 0.0f32;
        for k in 0..ticks {
            let t = k as f32 / rate_hz;
            if k % 211 == 0 {
                jump = 8e-6 * (rand() - 0.5);
            }
            let y_d = sign
                * (21e-6 - 17e-6 * libm::cosf(2.0 * core::f32::consts::PI * 10.0 * t)
                    + jump
                    + 2e-9 * (rand() - 0.5));
            let before = state;
            let command = compensator.compensate(&mut state, y_d);
            if command.status == CommandStatus::Limited {
                out.limited += 1;
            }
            if before.model.hysteresis.h * state.model.hysteresis.h < 0.0 {
                out.crossings += 1;
            }
            for word in [
                command.voltage_v.to_bits(),
                command.status as u32,
                state.model.hysteresis.h.to_bits(),
            ] {
                fnv1a(&mut out.hash, word);
            }
            if k % 3 != 0 {
                correction = (correction + 3.0 * (rand() - 0.5)).clamp(-14.0, 14.0);
                let u0 = before.model.input_v;
                let applied = (command.voltage_v + correction)
                    .clamp(u0 - max_step, u0 + max_step)
                    .clamp(0.0, 120.0);
                let mut advanced = before;
                compensator.advance(&mut advanced, applied);
                if before.model.hysteresis.h * advanced.model.hysteresis.h < 0.0 {
                    out.advance_crossings += 1;
                }
                state = advanced;
                for word in [
                    state.model.input_v.to_bits(),
                    state.model.hysteresis.h.to_bits(),
                ] {
                    fnv1a(&mut out.hash, word);
                }
            }
        }
        out
    }

    /// The n = 1 per-tick work (compensate, then advance by a corrected voltage) on a long
    /// stream at 10, 20 and 50 kHz and both slope signs gives the voltages, statuses and states
    /// recorded before that work was cut down, bit for bit (their FNV-1a hash), through
    /// thousands of slew-limited steps and of steps across h = 0 in both.
    #[test]
    fn n1_tick_stream_matches_its_record() {
        let expected: [(f32, f32, u64); 6] = [
            (1.0, 1e4, 0xfee8_6ed8_67b5_1ba4),
            (-1.0, 1e4, 0xfee8_6ed8_67b5_1ba4),
            (1.0, 2e4, 0x79de_f046_5fda_dc0c),
            (-1.0, 2e4, 0x79de_f046_5fda_dc0c),
            (1.0, 5e4, 0xdc53_c3e6_f8d7_aab0),
            (-1.0, 5e4, 0xdc53_c3e6_f8d7_aab0),
        ];
        let got = expected.map(|(sign, rate, _)| n1_tick_stream(sign, rate, 100_000));
        for ((sign, rate, hash), s) in expected.iter().zip(&got) {
            assert!(
                s.limited > 1_000 && s.crossings > 300 && s.advance_crossings > 300,
                "{sign} {rate}: {s:?}"
            );
            assert_eq!(s.hash, *hash, "{sign} {rate}: {got:#x?}");
        }
    }
}
