//! Output safety guard: the last stage before the DAC, so no controller output can drive the
//! piezo outside its rated window, step it faster than the slew limit, or pass on a NaN.
//!
//! Per tick, with `u` the requested actuator voltage and `y₋` the last applied one:
//!
//! ```text
//! u not finite  →  y = y₋                                   (counted: non_finite)
//! u' = clamp(u, V_min, V_max)                               (counted: window_clamped if u' ≠ u)
//! y  = y₋ + clamp(u' − y₋, −ΔV_max, +ΔV_max)                (counted: slew_limited if y ≠ u')
//! y  = clamp(y, V_min, V_max)                               (guards float rounding)
//! ```
//!
//! Settings ([`SafetyLimits`], validated once by [`SafetyLimits::new`]) are kept apart from the
//! run-time state ([`GuardState`]: last output and [`FaultCounters`]), so limits can be swapped
//! between two ticks. [`SafetyLimits::apply`] never panics and its output is always inside the
//! window, for every `f32` input including NaN and ±∞ (tests below: proptest on arbitrary f32
//! sequences, and a strided sweep over all bit patterns).

/// Why a set of limits was refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LimitsError {
    /// A limit is NaN or infinite.
    NotFinite,
    /// `min_volts` is not below `max_volts`.
    EmptyWindow,
    /// The slew limit is not positive.
    NonPositiveSlew,
}

/// Validated output limits, in actuator volts.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SafetyLimits {
    min_volts: f32,
    max_volts: f32,
    max_step_volts: f32,
}

/// How many ticks hit each fault; saturating counters.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FaultCounters {
    /// Requests that were NaN or ±∞ (output held).
    pub non_finite: u32,
    /// Requests outside `[min_volts, max_volts]` (clamped).
    pub window_clamped: u32,
    /// Requests further than `max_step_volts` from the last output (slew-limited).
    pub slew_limited: u32,
}

impl FaultCounters {
    /// Total of all fault counts (saturating).
    pub fn total(&self) -> u32 {
        self.non_finite
            .saturating_add(self.window_clamped)
            .saturating_add(self.slew_limited)
    }
}

/// Run-time state of the guard: the last applied output and the fault counters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GuardState {
    last_safe_volts: f32,
    counters: FaultCounters,
}

impl GuardState {
    /// The last output the guard let through (always inside the window it was applied with).
    pub fn last_safe_volts(&self) -> f32 {
        self.last_safe_volts
    }

    /// Fault counters since this state was made.
    pub fn counters(&self) -> FaultCounters {
        self.counters
    }

    /// This state under other limits: the last output moved into their window, the counters
    /// kept (for a swap of limits between two ticks).
    pub fn within(&self, limits: &SafetyLimits) -> Self {
        Self {
            last_safe_volts: self
                .last_safe_volts
                .clamp(limits.min_volts, limits.max_volts),
            counters: self.counters,
        }
    }
}

impl SafetyLimits {
    /// Limits: output window `[min_volts, max_volts]` and at most `max_step_volts` change per tick.
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
        Ok(Self {
            min_volts,
            max_volts,
            max_step_volts,
        })
    }

    /// Lower end of the output window.
    pub fn min_volts(&self) -> f32 {
        self.min_volts
    }

    /// Upper end of the output window.
    pub fn max_volts(&self) -> f32 {
        self.max_volts
    }

    /// Largest change of output per tick.
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
            counters: FaultCounters::default(),
        }
    }

    /// The output to apply for a requested voltage (see module docs). Never panics; the result
    /// is always in `[min_volts, max_volts]` provided `state` came from [`SafetyLimits::state`]
    /// of limits with the same window (a state from another window is pulled into this one).
    ///
    /// Fast path (inlined): a request inside the window and within `max_step_volts` of the last
    /// output passes unchanged, exactly what the full rules give (clamping the last output into
    /// the window can only bring it closer to a request inside the window); every other request
    /// (and NaN, which fails the comparisons) takes the full rules out of line.
    #[inline(always)]
    pub fn apply(&self, state: &mut GuardState, requested_volts: f32) -> f32 {
        let delta = requested_volts - state.last_safe_volts;
        if requested_volts >= self.min_volts
            && requested_volts <= self.max_volts
            && delta.abs() <= self.max_step_volts
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
        let counters = &mut state.counters;
        // Also repairs a state built for another window.
        let last = into_window(state.last_safe_volts, self.min_volts, self.max_volts);
        if !requested_volts.is_finite() {
            counters.non_finite = counters.non_finite.saturating_add(1);
            state.last_safe_volts = last;
            return last;
        }
        let target = into_window(requested_volts, self.min_volts, self.max_volts);
        if target != requested_volts {
            counters.window_clamped = counters.window_clamped.saturating_add(1);
        }
        let delta = target - last;
        let out = if delta.abs() <= self.max_step_volts {
            target
        } else {
            counters.slew_limited = counters.slew_limited.saturating_add(1);
            into_window(
                last + self.max_step_volts.copysign(delta),
                self.min_volts,
                self.max_volts,
            )
        };
        state.last_safe_volts = out;
        out
    }
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
    }

    #[test]
    fn in_window_small_steps_pass_through_unchanged() {
        let g = limits();
        let mut s = g.state(10.0);
        assert_eq!(g.apply(&mut s, 11.5), 11.5);
        assert_eq!(g.apply(&mut s, 10.0), 10.0);
        assert_eq!(s.counters(), FaultCounters::default());
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
        assert_eq!(
            s.counters(),
            FaultCounters {
                non_finite: 2,
                window_clamped: 1,
                slew_limited: 3
            }
        );
        assert_eq!(s.counters().total(), 6);
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

    fn any_f32_mostly_nearby() -> impl Strategy<Value = f32> {
        prop_oneof![
            proptest::num::f32::ANY,
            -200.0f32..200.0,
            Just(f32::NAN),
            Just(f32::INFINITY),
            Just(f32::NEG_INFINITY),
            Just(f32::MAX),
            Just(f32::MIN),
        ]
    }

    proptest! {
        /// For any valid limits, any start, and any sequence of f32 requests: output in the
        /// window, each step at most max_step, and non-finite requests hold the output.
        #[test]
        fn output_in_window_and_slew_bounded(
            lo in -1e3f32..1e3,
            width in 1e-3f32..1e3,
            step in 1e-4f32..1e2,
            start in proptest::num::f32::ANY,
            inputs in proptest::collection::vec(any_f32_mostly_nearby(), 1..200),
        ) {
            let g = SafetyLimits::new(lo, lo + width, step).unwrap();
            let mut s = g.state(start);
            let mut prev = s.last_safe_volts();
            for u in inputs {
                let before = s.counters();
                let y = g.apply(&mut s, u);
                prop_assert!(y >= g.min_volts() && y <= g.max_volts(), "u={u} y={y}");
                // Float rounding of `last ± step` may exceed step by an ulp of the operands.
                let ulp = f32::EPSILON * (prev.abs() + step);
                prop_assert!((y - prev).abs() <= step + ulp, "step {prev} -> {y}");
                if !u.is_finite() {
                    prop_assert_eq!(y, prev);
                    prop_assert_eq!(s.counters().non_finite, before.non_finite + 1);
                }
                prop_assert_eq!(y, s.last_safe_volts());
                prev = y;
            }
        }
    }
}
