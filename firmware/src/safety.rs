//! Output safety guard: the last stage before the DAC, so no controller output can drive the
//! piezo outside its rated window, step it by more than the slew limit, or pass on a NaN.
//!
//! Per tick, with `u` the requested actuator voltage, `y₋` the last applied one, the window
//! `[V_min, V_max]` and the step bound `M` (volts per tick; from a stage file `M ≤ S·T`, see
//! [`SafetyLimits::from_limits`]):
//!
//! ```text
//! y₋ outside the window (a new window was swapped in)            (counted: window_entry)
//!     → slew into it: the rules below with y₋ kept where it is
//! u not finite, y₋ inside   →  y = y₋                            (counted: non_finite)
//! u not finite, y₋ outside  →  target = the window's edge nearest y₋   (counted: non_finite)
//! target = clamp(u, V_min, V_max)                                (counted: window_clamped if ≠ u)
//! y = target                          if |target − y₋| ≤ M       (exact arithmetic)
//!   = y₋ + M·sgn(target − y₋) in f32, moved an ulp back towards y₋ while |y − y₋| > M
//!                                                                (counted: slew_limited)
//! ```
//!
//! So, for every `f32` input including NaN and ±∞: the output is finite; `|y − y₋| ≤ M` holds
//! **in exact arithmetic**, not only up to the rounding of `y₋ ± M` (the check in the slow path
//! is exact: the difference of two f32 as an unevaluated sum, Knuth's TwoSum); the output stays
//! in the window while `y₋` is in it, and a last output outside the window (left there by a swap
//! of limits between two ticks, [`TwoAxisLoop::set_settings`](crate::xy_loop::TwoAxisLoop::set_settings))
//! moves monotonically towards the window at the slew limit until it is inside — a new window is
//! never reached by a jump (should M be below the f32 spacing at `y₋`, no step within M exists
//! and `y₋` is held: M ≥ 7.7 µV suffices up to 120 V, a slew limit ≥ 0.08 V/s at 10 kHz).
//! A request inside the window whose step is at most `M` passes unchanged (a controller that
//! limits its own steps is never overridden: see [`piezo_core::CompensatorSettings::inside_guard`]).
//!
//! Settings ([`SafetyLimits`], validated once by [`SafetyLimits::new`]) are kept apart from the
//! run-time state ([`GuardState`]: last output and [`GuardCounters`]), so limits can be swapped
//! between two ticks. [`SafetyLimits::apply`] never panics (tests below: proptest on arbitrary
//! f32 sequences with an f64 check of every step, and a strided sweep over all bit patterns).

/// Why a set of limits was refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LimitsError {
    /// A limit (or the slew limit or loop period it is made from) is NaN or infinite.
    NotFinite,
    /// `min_volts` is not below `max_volts`.
    EmptyWindow,
    /// The step bound (the slew limit times the loop period) is not positive.
    NonPositiveSlew,
    /// The step bound is below four f32 spacings at the window's largest magnitude: the output
    /// could not move by a representable step within it.
    StepBelowResolution,
}

/// Validated output limits, in actuator volts.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SafetyLimits {
    min_volts: f32,
    max_volts: f32,
    /// M: the largest change of output per tick, in exact arithmetic.
    max_step_volts: f32,
    /// The fast path's bound on the *rounded* |u − y₋|: the f32 below M. Rounding to nearest
    /// moves the difference by less than half a spacing, so a rounded difference of at most
    /// this is an exact one below M.
    fast_step_volts: f32,
}

use piezo_core::Limits;
/// The guard's interventions per cause: the link's type, carried as it is.
pub use piezo_link::GuardCounters;

/// Run-time state of the guard: the last applied output and the fault counters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GuardState {
    /// Finite: made by [`SafetyLimits::state`], then only ever an output of [`SafetyLimits::apply`].
    last_safe_volts: f32,
    counters: GuardCounters,
}

impl GuardState {
    /// The last output the guard let through: inside the window it was applied with, or on the
    /// way into it after a swap of limits.
    pub fn last_safe_volts(&self) -> f32 {
        self.last_safe_volts
    }

    /// Fault counters since this state was made.
    pub fn counters(&self) -> GuardCounters {
        self.counters
    }
}

/// Nudges of the slew-limited output towards the last one (one always suffices: the nearest f32
/// to `y₋ ± M` lies less than a spacing beyond it).
const NUDGES: usize = 2;

impl SafetyLimits {
    /// Limits: output window `[min_volts, max_volts]` and at most `max_step_volts` (M) change
    /// per tick, exactly. M must be at least four f32 spacings at `max(|min_volts|, |max_volts|)`.
    pub fn new(min_volts: f32, max_volts: f32, max_step_volts: f32) -> Result<Self, LimitsError> {
        if !(min_volts.is_finite() && max_volts.is_finite() && max_step_volts.is_finite()) {
            return Err(LimitsError::NotFinite);
        }
        if min_volts >= max_volts {
            return Err(LimitsError::EmptyWindow);
        }
        if max_step_volts <= 0.0 {
            return Err(LimitsError::NonPositiveSlew);
        }
        if max_step_volts < 4.0 * spacing(min_volts.abs().max(max_volts.abs())) {
            return Err(LimitsError::StepBelowResolution);
        }
        Ok(Self {
            min_volts,
            max_volts,
            max_step_volts,
            fast_step_volts: max_step_volts.next_down(),
        })
    }

    /// The guard of an axis's [`Limits`] (the stage file's `[x.limits]`: window and slew limit
    /// S \[V/s\]) at the loop period T \[s\]: the step bound M is the f32 below the largest
    /// f32 ≤ S·T (the product exact in f64,
    /// [`piezo_core::CompensatorSettings::guard_step_v`]). The extra f32 makes M ≤ S·T also for
    /// T = 1/f_loop exactly, which the f32 period rounds by at most 2⁻²⁴ of itself: at 1e5 V/s
    /// and 10 kHz, M = 9.999998 V.
    pub fn from_limits(limits: &Limits, sample_period_s: f32) -> Result<Self, LimitsError> {
        let slew = limits.slew_limit_v_per_s;
        if !(slew.is_finite() && sample_period_s.is_finite()) {
            return Err(LimitsError::NotFinite);
        }
        if !(slew > 0.0 && sample_period_s > 0.0) {
            return Err(LimitsError::NonPositiveSlew);
        }
        let step = piezo_core::CompensatorSettings {
            limits: *limits,
            sample_period_s,
        }
        .guard_step_v();
        Self::new(limits.output_min_v, limits.output_max_v, step)
    }

    /// Lower end of the output window.
    pub fn min_volts(&self) -> f32 {
        self.min_volts
    }

    /// Upper end of the output window.
    pub fn max_volts(&self) -> f32 {
        self.max_volts
    }

    /// Largest change of output per tick, M (exact).
    pub fn max_step_volts(&self) -> f32 {
        self.max_step_volts
    }

    /// A fresh state whose last output is `initial_volts` forced into the window (NaN gives
    /// `min_volts`), with zeroed counters.
    pub fn state(&self, initial_volts: f32) -> GuardState {
        let last_safe_volts = if initial_volts.is_nan() {
            self.min_volts
        } else {
            into_window(initial_volts, self.min_volts, self.max_volts)
        };
        GuardState {
            last_safe_volts,
            counters: GuardCounters::default(),
        }
    }

    /// The output to apply for a requested voltage (see module docs). Never panics; the result
    /// is finite, at most M from the last output (exactly), and inside the window unless the
    /// last output lay outside it (a state from limits with another window), when it moves
    /// towards the window.
    ///
    /// Fast path (inlined, as cheap as a plain clamp test): a request inside the window whose
    /// rounded distance from the last output is at most the f32 below M passes unchanged —
    /// exactly what the full rules give, its exact distance being below M. Every other request
    /// (and NaN, which fails the comparisons) takes the full rules out of line, where the step is
    /// checked exactly.
    #[inline(always)]
    pub fn apply(&self, state: &mut GuardState, requested_volts: f32) -> f32 {
        let delta = requested_volts - state.last_safe_volts;
        if requested_volts >= self.min_volts
            && requested_volts <= self.max_volts
            && delta.abs() <= self.fast_step_volts
        {
            state.last_safe_volts = requested_volts;
            return requested_volts;
        }
        self.apply_limited(state, requested_volts)
    }

    /// The full rules of [`SafetyLimits::apply`] (module docs), for requests the fast path does
    /// not let through.
    #[inline(never)]
    fn apply_limited(&self, state: &mut GuardState, requested_volts: f32) -> f32 {
        let (min, max) = (self.min_volts, self.max_volts);
        let last = state.last_safe_volts;
        let counters = &mut state.counters;
        let inside = last >= min && last <= max;
        let target = if requested_volts.is_finite() {
            let target = into_window(requested_volts, min, max);
            if target != requested_volts {
                counters.window_clamped = counters.window_clamped.saturating_add(1);
            }
            target
        } else {
            counters.non_finite = counters.non_finite.saturating_add(1);
            if inside {
                return last;
            }
            into_window(last, min, max)
        };
        let out = if step_exceeds(target, last, self.max_step_volts) {
            counters.slew_limited = counters.slew_limited.saturating_add(1);
            self.step_towards(last, target)
        } else {
            target
        };
        // A request passed unchanged is no intervention, as on the fast path (NaN ≠ NaN counts).
        if !inside && out != requested_volts {
            counters.window_entry = counters.window_entry.saturating_add(1);
        }
        state.last_safe_volts = out;
        out
    }

    /// The f32 nearest `last + M·sgn(target − last)` that is at most M from `last` exactly (the
    /// nearest one may lie up to half a spacing beyond; then the next one towards `last`).
    /// Between `last` and `target` when `|target − last| > M` (rounding is monotone and both
    /// are f32); `last` itself, a hold, should no nudge do (not reached).
    #[inline(never)]
    fn step_towards(&self, last: f32, target: f32) -> f32 {
        let m = self.max_step_volts;
        let up = target > last;
        let mut out = if up { last + m } else { last - m };
        for _ in 0..NUDGES {
            if !step_exceeds(out, last, m) {
                return out;
            }
            out = if up { out.next_down() } else { out.next_up() };
        }
        if step_exceeds(out, last, m) {
            last
        } else {
            out
        }
    }
}

/// Whether `|a − b| > m` in exact arithmetic, for finite `a`, `b` and `m ≥ 0`. The rounded
/// difference `d = fl(a − b)` decides unless `|d| = m`: rounding to nearest is monotone and m is
/// an f32, so `|d| < m` means `|a − b| < m` and `|d| > m` (or an overflow to ±∞) means
/// `|a − b| > m`. At `|d| = m` the rounding error `e`, with `a − b = d + e` exactly (Knuth's
/// TwoSum, six f32 operations), decides: `|a − b| > m` iff `e ≠ 0` has the sign of `d`.
#[inline]
fn step_exceeds(a: f32, b: f32, m: f32) -> bool {
    let d = a - b;
    if d.abs() != m {
        // Finite operands: d is finite or ±∞ on overflow, never NaN.
        return d.abs() > m;
    }
    let c = -b;
    let a_part = d - c;
    let c_part = d - a_part;
    let e = (a - a_part) + (c - c_part);
    if d > 0.0 {
        e > 0.0
    } else {
        e < 0.0
    }
}

/// The distance from `x ≥ 0` to the next f32 above it (∞ at `f32::MAX`).
fn spacing(x: f32) -> f32 {
    x.next_up() - x
}

/// `x` forced into `[min, max]` (NaN gives `min`). Not `f32::clamp`: that asserts `min ≤ max`,
/// a panic path the optimiser cannot remove (the limits are run-time values), and the `check`
/// image refuses any reachable panic. `SafetyLimits::new` guarantees `min < max`.
#[inline]
fn into_window(x: f32, min: f32, max: f32) -> f32 {
    if x > max {
        max
    } else if x >= min {
        x
    } else {
        min
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn limits() -> SafetyLimits {
        SafetyLimits::new(0.0, 100.0, 2.0).unwrap()
    }

    /// The stage file's axis: 0–120 V, 1e5 V/s at 10 kHz.
    const STAGE_SLEW_V_PER_S: f32 = 1e5;
    const STAGE_PERIOD_S: f32 = 1.0 / 10_000.0;

    fn stage() -> SafetyLimits {
        SafetyLimits::from_limits(&Limits::new(0.0, 120.0, STAGE_SLEW_V_PER_S), STAGE_PERIOD_S)
            .unwrap()
    }

    /// |a − b| in f64, as a checker outside the firmware computes it (exact for two f32 whose
    /// exponents differ by less than 29).
    fn step_f64(a: f32, b: f32) -> f64 {
        (f64::from(a) - f64::from(b)).abs()
    }

    /// |a − b| > m in exact arithmetic, for any finite f32: in f64, `a − b = s + e` exactly
    /// (TwoSum; f32 operands cannot overflow f64), so `|s| ≠ m` decides, else the sign of `e`.
    fn exceeds(a: f32, b: f32, m: f32) -> bool {
        let (a, b, m) = (f64::from(a), f64::from(b), f64::from(m));
        let s = a - b;
        let a_part = s + b;
        let b_part = s - a_part;
        let e = (a - a_part) + (-b - b_part);
        if s.abs() != m {
            s.abs() > m
        } else {
            e != 0.0 && (e > 0.0) == (s > 0.0)
        }
    }

    #[test]
    fn limits_are_validated() {
        assert_eq!(
            SafetyLimits::new(f32::NAN, 1.0, 1.0),
            Err(LimitsError::NotFinite)
        );
        assert_eq!(
            SafetyLimits::new(0.0, f32::INFINITY, 1.0),
            Err(LimitsError::NotFinite)
        );
        assert_eq!(
            SafetyLimits::new(0.0, 1.0, f32::NAN),
            Err(LimitsError::NotFinite)
        );
        assert_eq!(
            SafetyLimits::new(1.0, 1.0, 1.0),
            Err(LimitsError::EmptyWindow)
        );
        assert_eq!(
            SafetyLimits::new(2.0, 1.0, 1.0),
            Err(LimitsError::EmptyWindow)
        );
        assert_eq!(
            SafetyLimits::new(0.0, 1.0, 0.0),
            Err(LimitsError::NonPositiveSlew)
        );
        assert_eq!(
            SafetyLimits::new(0.0, 1.0, -1.0),
            Err(LimitsError::NonPositiveSlew)
        );
        // Four spacings at 120 V are 3.05e-5 V.
        assert_eq!(
            SafetyLimits::new(0.0, 120.0, 3.0e-5),
            Err(LimitsError::StepBelowResolution)
        );
        assert!(SafetyLimits::new(0.0, 120.0, 3.1e-5).is_ok());
        assert_eq!(
            SafetyLimits::from_limits(&Limits::new(0.0, 120.0, f32::INFINITY), 1e-4),
            Err(LimitsError::NotFinite)
        );
        assert_eq!(
            SafetyLimits::from_limits(&Limits::new(0.0, 120.0, 1e5), 0.0),
            Err(LimitsError::NonPositiveSlew)
        );
    }

    /// M is below S·T for both readings of T (the f32 period and 1/f exactly), by one f32.
    #[test]
    fn the_stage_step_bound_is_below_slew_times_period() {
        let m = f64::from(stage().max_step_volts());
        let with_f32_period = f64::from(STAGE_SLEW_V_PER_S) * f64::from(STAGE_PERIOD_S);
        let with_exact_period = f64::from(STAGE_SLEW_V_PER_S) / 10_000.0;
        assert!(m <= with_f32_period && m <= with_exact_period, "{m}");
        assert!(
            m > with_f32_period * (1.0 - 4.0 * f64::from(f32::EPSILON)),
            "{m}"
        );
        // Rates whose f32 period rounds up: still below 1/f.
        for rate in [3.0f32, 7.0, 12_345.0, 20_000.0, 33_333.0] {
            let l = SafetyLimits::from_limits(&Limits::new(0.0, 120.0, 1e5), 1.0 / rate).unwrap();
            assert!(
                f64::from(l.max_step_volts()) <= 1e5 / f64::from(rate),
                "{rate}"
            );
        }
    }

    /// The controllers' own steps, with their f32 rounding at the top of the window, pass the
    /// guard unchanged.
    #[test]
    fn a_controller_step_with_its_rounding_passes_unchanged() {
        let g = stage();
        let slew = piezo_core::CompensatorSettings {
            limits: Limits::new(g.min_volts(), g.max_volts(), STAGE_SLEW_V_PER_S),
            sample_period_s: STAGE_PERIOD_S,
        }
        .inside_guard()
        .limits
        .slew_limit_v_per_s;
        let step = slew * STAGE_PERIOD_S;
        assert!(f64::from(step) < f64::from(g.max_step_volts()));
        assert!(step > 9.9999 && slew < STAGE_SLEW_V_PER_S, "{slew} {step}");
        for from in [0.0f32, 55.5, 110.000_01, 119.999_99, 120.0] {
            for to in [from + step, from - step] {
                let mut s = g.state(from);
                let u = to.clamp(0.0, 120.0);
                assert_eq!(g.apply(&mut s, u), u, "{from} -> {to}");
                assert_eq!(s.counters(), GuardCounters::default());
            }
        }
    }

    #[test]
    fn in_window_small_steps_pass_through_unchanged() {
        let g = limits();
        let mut s = g.state(10.0);
        assert_eq!(g.apply(&mut s, 11.5), 11.5);
        assert_eq!(g.apply(&mut s, 10.0), 10.0);
        // A step of exactly M takes the slow path and passes too.
        assert_eq!(g.apply(&mut s, 12.0), 12.0);
        assert_eq!(s.counters(), GuardCounters::default());
    }

    #[test]
    fn each_fault_kind_is_counted() {
        let g = limits();
        let mut s = g.state(50.0);
        assert_eq!(g.apply(&mut s, f32::NAN), 50.0);
        assert_eq!(g.apply(&mut s, f32::NEG_INFINITY), 50.0);
        assert_eq!(g.apply(&mut s, 60.0), 52.0);
        assert_eq!(g.apply(&mut s, 40.0), 50.0);
        assert_eq!(g.apply(&mut s, 1e9), 52.0);
        let narrow = SafetyLimits::new(60.0, 100.0, 2.0).unwrap();
        assert_eq!(narrow.apply(&mut s, 70.0), 54.0);
        assert_eq!(
            s.counters(),
            GuardCounters {
                non_finite: 2,
                window_clamped: 1,
                slew_limited: 4,
                window_entry: 1,
            }
        );
        assert_eq!(s.counters().total(), 8);
    }

    #[test]
    fn slew_limited_ramp_reaches_clamped_target() {
        let g = limits();
        let mut s = g.state(0.0);
        let mut y = 0.0;
        for _ in 0..60 {
            y = g.apply(&mut s, 150.0);
        }
        assert_eq!(y, 100.0);
    }

    /// Near the top of the window, `y₋ + M` rounds up past M (100 + 9.999998 → 110.0); the
    /// output is the f32 below, and a request in the window exactly M away passes.
    #[test]
    fn a_slew_limited_step_is_within_the_bound_exactly() {
        let g = stage();
        let m = g.max_step_volts();
        for (from, request) in [
            (100.0f32, 120.0f32),
            (110.0, 120.0),
            (120.0, 0.0),
            (119.999_99, 100.0),
            (9.999_999, 0.0),
            (0.0, 1e30),
        ] {
            let mut s = g.state(from);
            let y = g.apply(&mut s, request);
            assert!(step_f64(y, from) <= f64::from(m), "{from} -> {y}");
            // As far as the bound allows: the next f32 outwards would exceed it.
            let further = if request > from {
                y.next_up()
            } else {
                y.next_down()
            };
            assert!(step_f64(further, from) > f64::from(m), "{from} -> {y}");
            assert_eq!(s.counters().slew_limited, 1);
        }
        let mut s = g.state(100.0);
        let rounded = 100.0 + m; // rounds to 110.0: more than M
        assert_eq!(rounded, 110.0);
        assert!(g.apply(&mut s, rounded) < rounded);
        // Within M: passes unchanged (slow path: more than the fast path's f32 below M).
        for (from, request) in [(110.0f32, 119.999_99f32), (110.000_01, 120.0)] {
            let mut s = g.state(from);
            assert_eq!(g.apply(&mut s, request), request);
            assert_eq!(s.counters(), GuardCounters::default());
        }
    }

    /// A state from the old window at 0 V, applied with a window of 100–120 V: the output climbs
    /// at the slew limit, one count per tick outside, and never jumps.
    #[test]
    fn a_new_window_is_entered_at_the_slew_limit() {
        let old = stage();
        let new =
            SafetyLimits::from_limits(&Limits::new(100.0, 120.0, 1e5), STAGE_PERIOD_S).unwrap();
        let m = f64::from(new.max_step_volts());
        let mut s = old.state(0.0);
        let mut last = 0.0f32;
        let mut ticks_outside = 0;
        for tick in 0..20 {
            let request = if tick % 3 == 0 { f32::NAN } else { 110.0 };
            let y = new.apply(&mut s, request);
            assert!(step_f64(y, last) <= m, "tick {tick}: {last} -> {y}");
            assert!(y >= last, "tick {tick}: {last} -> {y}");
            if last < 100.0 {
                ticks_outside += 1;
            } else {
                assert!((100.0..=120.0).contains(&y), "tick {tick}: {y}");
            }
            last = y;
        }
        assert_eq!(last, 110.0);
        assert_eq!(ticks_outside, 11);
        assert_eq!(s.counters().window_entry, ticks_outside);
        // Down into 0–20 V from 120 V, the same way.
        let low = SafetyLimits::from_limits(&Limits::new(0.0, 20.0, 1e5), STAGE_PERIOD_S).unwrap();
        let mut s = old.state(120.0);
        let mut last = 120.0f32;
        for _ in 0..12 {
            let y = low.apply(&mut s, 5.0);
            assert!(step_f64(y, last) <= m && y <= last, "{last} -> {y}");
            last = y;
        }
        assert_eq!(last, 5.0);
    }

    #[test]
    fn step_exceeds_is_exact() {
        let m = 9.999_998f32;
        for (a, b, exact) in [
            (110.0f32, 100.0f32, true),
            (100.0, 110.0, true),
            (109.999_99, 100.0, false),
            (m, 0.0, false),
            (0.0, m, false),
            (-0.0, m, false),
            // m + 10⁻³⁰ exactly (f64 would round it to m).
            (1e-30, -m, true),
            (-m, 1e-30, true),
            (m, 1e-30, false),
            (f32::MAX, -f32::MAX, true),
        ] {
            assert_eq!(step_exceeds(a, b, m), exact, "{a} {b}");
            assert_eq!(exceeds(a, b, m), exact, "{a} {b}");
        }
    }

    #[test]
    fn initial_state_is_forced_into_window() {
        let g = limits();
        assert_eq!(g.state(f32::NAN).last_safe_volts(), 0.0);
        assert_eq!(g.state(-5.0).last_safe_volts(), 0.0);
        assert_eq!(g.state(f32::INFINITY).last_safe_volts(), 100.0);
    }

    #[test]
    fn counters_saturate() {
        let g = limits();
        let mut s = g.state(0.0);
        s.counters.non_finite = u32::MAX;
        g.apply(&mut s, f32::NAN);
        assert_eq!(s.counters().non_finite, u32::MAX);
    }

    /// Every 61st bit pattern of f32 (70 million inputs, every class: NaNs with any payload,
    /// ±∞, subnormals, ±0), applied in sequence from one state, and once more from a fresh state
    /// at each end of the window: the output never leaves the window.
    #[test]
    fn output_stays_in_window_over_f32_sweep() {
        let g = SafetyLimits::new(-3.0, 97.5, 0.25).unwrap();
        let mut chained = g.state(10.0);
        let mut bits = 0u32;
        loop {
            let u = f32::from_bits(bits);
            for y in [
                g.apply(&mut chained, u),
                g.apply(&mut g.state(g.min_volts()), u),
                g.apply(&mut g.state(g.max_volts()), u),
            ] {
                assert!(
                    (g.min_volts()..=g.max_volts()).contains(&y),
                    "u={u:e} ({bits:#x}) gave {y}"
                );
            }
            match bits.checked_add(61) {
                Some(b) => bits = b,
                None => break,
            }
        }
    }

    /// A request: an absolute voltage, or the last output plus k·M moved by a few f32 (the
    /// values where rounding decides).
    #[derive(Clone, Copy, Debug)]
    enum Request {
        Absolute(f32),
        FromLast(f32, i32),
    }

    fn request() -> impl Strategy<Value = Request> {
        prop_oneof![
            proptest::num::f32::ANY.prop_map(Request::Absolute),
            (-200.0f32..200.0).prop_map(Request::Absolute),
            prop_oneof![
                Just(119.999_99f32),
                Just(120.0),
                Just(120.000_01),
                Just(0.0),
                Just(-1e-30),
                Just(f32::NAN),
                Just(f32::INFINITY),
                Just(f32::NEG_INFINITY),
                Just(1e30),
                Just(f32::MAX),
                Just(f32::MIN),
            ]
            .prop_map(Request::Absolute),
            (
                prop_oneof![Just(1.0f32), Just(-1.0), -3.0f32..3.0],
                -3i32..=3
            )
                .prop_map(|(k, n)| Request::FromLast(k, n)),
        ]
    }

    fn resolve(r: Request, last: f32, m: f32) -> f32 {
        match r {
            Request::Absolute(u) => u,
            Request::FromLast(k, n) => {
                let mut u = last + k * m;
                for _ in 0..n.unsigned_abs() {
                    u = if n > 0 { u.next_up() } else { u.next_down() };
                }
                u
            }
        }
    }

    /// The stage's limits, or a random window (up to ±10 kV wide) and step bound.
    fn any_limits() -> impl Strategy<Value = SafetyLimits> {
        prop_oneof![
            Just(stage()),
            (-1e4f32..1e4, 1e-3f32..2e4, 1e-3f32..1e3)
                .prop_filter_map("step below the window's resolution", |(lo, width, step)| {
                    SafetyLimits::new(lo, lo + width, step).ok()
                }),
        ]
    }

    proptest! {
        /// For any valid limits, any start, and any sequence of f32 requests, with a second
        /// set of limits swapped in part way: every step at most M in exact arithmetic (checked
        /// in f64); the output in the window, or, after the swap until it is in, monotonically
        /// closer to it; a request in the window at most M away passes unchanged; non-finite
        /// requests hold the output inside the window.
        #[test]
        fn every_step_is_within_the_bound_exactly(
            first in any_limits(),
            second in any_limits(),
            start in proptest::num::f32::ANY,
            swap_at in 0usize..200,
            requests in proptest::collection::vec(request(), 1..200),
        ) {
            let mut s = first.state(start);
            let mut g = first;
            let mut prev = s.last_safe_volts();
            let distance = |g: &SafetyLimits, y: f32| {
                (f64::from(g.min_volts()) - f64::from(y))
                    .max(f64::from(y) - f64::from(g.max_volts()))
                    .max(0.0)
            };
            for (k, r) in requests.into_iter().enumerate() {
                if k == swap_at {
                    g = second;
                }
                let m = g.max_step_volts();
                let u = resolve(r, prev, m);
                let before = s.counters();
                let inside = distance(&g, prev) == 0.0;
                let y = g.apply(&mut s, u);
                prop_assert!(y.is_finite());
                prop_assert!(!exceeds(y, prev, m), "step {prev} -> {y} (M {m})");
                prop_assert!(step_f64(y, prev) <= f64::from(m), "step {prev} -> {y} (M {m})");
                if inside {
                    prop_assert!(distance(&g, y) == 0.0, "left the window: {prev} -> {y}");
                } else {
                    prop_assert!(distance(&g, y) < distance(&g, prev), "{prev} -> {y}");
                    let counted = u32::from(y != u);
                    prop_assert_eq!(s.counters().window_entry, before.window_entry + counted);
                }
                let passes = u >= g.min_volts() && u <= g.max_volts() && !exceeds(u, prev, m);
                if passes {
                    prop_assert_eq!(y, u);
                    prop_assert_eq!(s.counters(), before);
                }
                if !u.is_finite() {
                    prop_assert_eq!(s.counters().non_finite, before.non_finite + 1);
                    if inside {
                        prop_assert_eq!(y, prev);
                    }
                }
                prop_assert_eq!(y, s.last_safe_volts());
                prev = y;
            }
        }

        /// `step_exceeds` (f32) against the exact comparison in f64, near `|a − b| = m` and
        /// for arbitrary f32.
        #[test]
        fn step_exceeds_matches_the_exact_difference(
            b in prop_oneof![-1e4f32..1e4, proptest::num::f32::NORMAL | proptest::num::f32::SUBNORMAL],
            m in prop_oneof![1e-4f32..1e3, proptest::num::f32::POSITIVE],
            k in prop_oneof![Just(1.0f32), Just(-1.0), -2.0f32..2.0],
            n in -4i32..=4,
            other in proptest::num::f32::ANY,
        ) {
            prop_assume!(b.is_finite() && m.is_finite());
            let a = resolve(Request::FromLast(k, n), b, m);
            for a in [a, other] {
                if a.is_finite() {
                    prop_assert_eq!(step_exceeds(a, b, m), exceeds(a, b, m), "{} {} {}", a, b, m);
                    prop_assert_eq!(step_exceeds(b, a, m), exceeds(a, b, m), "{} {} {}", b, a, m);
                }
            }
        }
    }
}
