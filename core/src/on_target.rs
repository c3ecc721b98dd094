//! On target and settling of one axis (what a stage controller reports as "on target").
//!
//! With the reading y\[k\] of tick k and the reference r\[k−1\] it answers (the reference of the
//! tick before, whose voltage the reading follows), the error is `e[k] = y[k] − r[k−1]` (positive:
//! the stage is beyond the reference). The axis is **on target** at tick k when
//!
//! ```text
//! |e[j]| ≤ tolerance_m   for every j in k − N + 1 … k          (N = OnTarget::ticks)
//! ```
//!
//! i.e. N consecutive readings inside the band. A non-finite reading or reference is outside.
//! The reference **changes** at tick k when r\[k−1\] ≠ r\[k−2\] (bitwise f32 compare): the ticks
//! since then are counted, and the **settling time** of that move is the ticks from the change
//! to the first tick of the in-band run that made the axis on target (the time after which the
//! error stayed inside the band), `settle = (since_change + 1) − run` when the flag rises, 0 if
//! the run began before the change (recorded at the flag's rise; a change while on target sets
//! it to 0, overwritten if the flag then drops and rises again). A move that never settles keeps
//! the previous value.
//!
//! Defaults ([`OnTarget::default_for`]): tolerance = [`DEFAULT_TOLERANCE_LSB`] ADC steps in
//! metres, `8 · (adc_span_v / 2^ADC_BITS) · sensor_m_per_v` (the board's ADS8681 has
//! [`ADC_BITS`] = 16 bits: 8 × 312.5 µV × 10 µm/V = 25 nm for the default chain), and N = the
//! ticks in 1 ms, `⌈1e-3 s / T⌉` (20 at 20 kHz).
//!
//! The per-tick step [`OnTarget::observe`] is one subtraction, one compare and a count since
//! the reference changed; the run (capped at N), the flag and the settling time are touched only
//! while a run is going or the reading is inside (a tick clearly off target, outside the band
//! with no run, stores nothing else): no division, no panic.

use crate::error::ParamError;
use crate::IoChain;

/// Bits of the board's position ADC (ADS8681): its step is `adc_span / 2^ADC_BITS`.
pub const ADC_BITS: u32 = 16;
/// The default tolerance in ADC steps.
pub const DEFAULT_TOLERANCE_LSB: f32 = 8.0;
/// The default time the error must stay inside the band \[s\].
pub const DEFAULT_DWELL_S: f32 = 1e-3;
/// Most ticks accepted for N (10 s at 100 kHz).
pub const MAX_TICKS: u32 = 1_000_000;
/// The settling time reported before any move has settled.
pub const NOT_SETTLED: u32 = u32::MAX;

/// The on-target band of an axis (see the module doc).
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct OnTarget {
    /// Largest |y − r| on target \[m\], > 0.
    pub tolerance_m: f32,
    /// Consecutive ticks inside the band before the axis is on target, 1 … [`MAX_TICKS`].
    pub ticks: u32,
}

/// The per-tick state of [`OnTarget::observe`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OnTargetState {
    /// The reference the last reading was compared with (its bits; NaN at rest: any first
    /// reference is a change).
    reference_bits: u32,
    /// Consecutive readings inside the band (saturating at N; 0 whenever the axis is not on
    /// target and the last reading was outside).
    run: u32,
    /// Ticks observed since the reference last changed (wrapping, as a difference of two
    /// wrapping tick counts).
    since_change: u32,
    /// Settling time of the last move that settled \[ticks\] ([`NOT_SETTLED`]: none yet).
    settle_ticks: u32,
    /// The last tick was on target.
    on_target: bool,
}

impl Default for OnTargetState {
    fn default() -> Self {
        Self {
            reference_bits: f32::NAN.to_bits(),
            run: 0,
            since_change: 0,
            settle_ticks: NOT_SETTLED,
            on_target: false,
        }
    }
}

impl OnTargetState {
    /// The last tick was on target.
    pub fn on_target(&self) -> bool {
        self.on_target
    }

    /// Ticks since the reference last changed.
    pub fn ticks_since_change(&self) -> u32 {
        self.since_change
    }

    /// Settling time of the last move that settled \[ticks\] ([`NOT_SETTLED`] before the first).
    pub fn settle_ticks(&self) -> u32 {
        self.settle_ticks
    }

    /// Not on target, the run cleared (the loop is not tracking: safe state, excitation); the
    /// reference is forgotten, so the next tracked reference is a move.
    pub fn reset(&mut self) {
        let settle_ticks = self.settle_ticks;
        *self = Self {
            settle_ticks,
            ..Self::default()
        };
    }
}

impl OnTarget {
    /// A band of `tolerance_m` \[m\] (finite, > 0) held for `ticks` (1 … [`MAX_TICKS`]).
    pub fn new(tolerance_m: f32, ticks: u32) -> Result<Self, ParamError> {
        if !tolerance_m.is_finite() {
            return Err(ParamError::NonFinite {
                field: "tolerance_m",
            });
        }
        if tolerance_m <= 0.0 {
            return Err(ParamError::OutOfRange {
                field: "tolerance_m",
                value: tolerance_m,
                requirement: "> 0",
            });
        }
        if !(1..=MAX_TICKS).contains(&ticks) {
            return Err(ParamError::OutOfRange {
                field: "ticks",
                value: ticks as f32,
                requirement: "in 1 … 1 000 000",
            });
        }
        Ok(Self { tolerance_m, ticks })
    }

    /// The default band for the chain `io` at the loop period `sample_period_s` \[s\] (module
    /// doc): [`DEFAULT_TOLERANCE_LSB`] ADC steps in metres, held for ⌈[`DEFAULT_DWELL_S`]/T⌉
    /// ticks.
    pub fn default_for(io: &IoChain, sample_period_s: f32) -> Result<Self, ParamError> {
        let lsb_v = (io.adc_range_v[1] - io.adc_range_v[0]) / (1u32 << ADC_BITS) as f32;
        let tolerance_m = DEFAULT_TOLERANCE_LSB * lsb_v * io.sensor_m_per_v;
        if !(sample_period_s.is_finite() && sample_period_s > 0.0) {
            return Err(ParamError::OutOfRange {
                field: "sample_period_s",
                value: sample_period_s,
                requirement: "> 0",
            });
        }
        // ⌈1 ms / T⌉ without libm, a quotient within 1e-4 of a whole number taken as it (T is
        // 1/rate in f32: 1 ms at 20 kHz is 20.000002 periods). Saturates at u32::MAX (refused).
        let q = DEFAULT_DWELL_S / sample_period_s;
        let nearest = (q + 0.5) as u32;
        let ticks = if (q - nearest as f32).abs() <= 1e-4 * q {
            nearest
        } else {
            let whole = q as u32;
            if (whole as f32) < q {
                whole.saturating_add(1)
            } else {
                whole
            }
        };
        Self::new(tolerance_m, ticks.max(1))
    }

    /// This axis's check (this band), validated ([`OnTarget::new`]).
    pub fn validated(self) -> Result<Self, ParamError> {
        Self::new(self.tolerance_m, self.ticks)
    }

    /// One tick: the reading `sensor_m` \[m\] against the reference it answers `reference_m`
    /// \[m\] (module doc); returns whether the axis is on target.
    ///
    /// A state machine: a tick outside the band with no run going (not on target) only keeps
    /// the count since the reference changed; the run, the flag and the settling time are
    /// touched only by a reading inside the band or one that ends a run.
    #[inline(always)]
    pub fn observe(&self, state: &mut OnTargetState, sensor_m: f32, reference_m: f32) -> bool {
        let bits = reference_m.to_bits();
        let changed = bits != state.reference_bits;
        if changed {
            state.reference_bits = bits;
            state.since_change = 0;
        } else {
            state.since_change = state.since_change.wrapping_add(1);
        }
        // NaN compares false: outside.
        let inside = (sensor_m - reference_m).abs() <= self.tolerance_m;
        if !inside && state.run == 0 {
            // Clearly off target (run 0 means the flag is down): nothing else changes.
            return false;
        }
        self.observe_run(state, inside, changed)
    }

    /// [`OnTarget::observe`] with a run going or a reading inside: the run (capped at N), the
    /// flag, and the settling time when the flag rises (the ticks from the change to the first
    /// tick of the run, 0 if the run began before it) or when a new reference keeps the axis
    /// on target (0, overwritten if the flag drops and rises again).
    #[inline(always)]
    fn observe_run(&self, state: &mut OnTargetState, inside: bool, changed: bool) -> bool {
        let was_on = state.on_target;
        if changed && was_on {
            state.settle_ticks = 0;
        }
        // The run stops counting at N (no overflow).
        let run = if inside {
            state.run + u32::from(state.run < self.ticks)
        } else {
            0
        };
        state.run = run;
        let on = run >= self.ticks;
        state.on_target = on;
        if on && !was_on {
            state.settle_ticks = state.since_change.saturating_add(1).saturating_sub(run);
        }
        on
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn band() -> OnTarget {
        OnTarget::new(1e-8, 3).unwrap()
    }

    #[test]
    fn refused_when_built() {
        assert!(OnTarget::new(f32::NAN, 3).is_err());
        assert!(OnTarget::new(0.0, 3).is_err());
        assert!(OnTarget::new(-1e-9, 3).is_err());
        assert!(OnTarget::new(1e-9, 0).is_err());
        assert!(OnTarget::new(1e-9, MAX_TICKS + 1).is_err());
    }

    #[test]
    fn default_is_eight_adc_steps_and_a_millisecond() {
        let io = IoChain {
            dac_range_v: [0.0, 5.0],
            amplifier_gain_v_per_v: 24.0,
            adc_range_v: [-10.24, 10.24],
            sensor_range_v: [0.0, 10.0],
            sensor_m_per_v: 1e-5,
        };
        let d = OnTarget::default_for(&io, 1.0 / 20_000.0).unwrap();
        assert!((d.tolerance_m - 25e-9).abs() < 1e-12, "{}", d.tolerance_m);
        assert_eq!(d.ticks, 20);
        assert_eq!(OnTarget::default_for(&io, 1.0 / 3_000.0).unwrap().ticks, 3);
    }

    #[test]
    fn a_step_settles_after_n_ticks_inside() {
        let b = band();
        let mut s = OnTargetState::default();
        // At rest on 0.
        for _ in 0..5 {
            b.observe(&mut s, 0.0, 0.0);
        }
        assert!(s.on_target());
        // Step to 1 µm: the reading arrives at tick 4 after the change.
        let readings = [
            0.0, 0.3e-6, 0.9e-6, 1.02e-6, 1.005e-6, 1.0e-6, 0.995e-6, 1.0e-6,
        ];
        let flags: [bool; 8] = core::array::from_fn(|k| b.observe(&mut s, readings[k], 1e-6));
        assert_eq!(
            flags,
            [false, false, false, false, false, false, true, true]
        );
        // Inside from tick 4 (1.005 µm), flagged at tick 6.
        assert_eq!(s.settle_ticks(), 4);
        assert_eq!(s.ticks_since_change(), 7);
        // One reading outside clears it; NaN is outside.
        assert!(!b.observe(&mut s, 1.1e-6, 1e-6));
        assert!(!b.observe(&mut s, f32::NAN, 1e-6));
        assert_eq!(s.settle_ticks(), 4, "the same move keeps its settling time");
    }

    #[test]
    fn a_move_inside_the_band_settles_at_once() {
        let b = band();
        let mut s = OnTargetState::default();
        for _ in 0..5 {
            b.observe(&mut s, 0.0, 0.0);
        }
        assert!(b.observe(&mut s, 0.0, 5e-9));
        assert_eq!(s.settle_ticks(), 0);
        assert_eq!(s.ticks_since_change(), 0);
        s.reset();
        assert!(!s.on_target());
        assert_eq!(s.settle_ticks(), 0);
    }

    /// The state machine against the definition evaluated from the whole history (module doc):
    /// on target when the last N errors are all inside, the ticks since the last change of the
    /// reference's bits, and the settling time set when the flag rises (the ticks from the
    /// change to the run's first tick, 0 if before) or to 0 by a change while on target; over a
    /// random stream with readings around the band's edge, held and moving references, NaN
    /// readings and references, and resets.
    #[test]
    fn state_machine_is_the_definition() {
        let b = OnTarget::new(1e-8, 4).unwrap();
        let mut seed = 99u32;
        let mut rand = || {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (seed >> 8) as f32 / (1u32 << 24) as f32
        };
        let mut s = OnTargetState::default();
        // The definition's memory: since the last reset, (reference bits, inside) per tick.
        extern crate std;
        let mut history: std::vec::Vec<(u32, bool)> = std::vec::Vec::new();
        let (mut settle, mut was_on) = (NOT_SETTLED, false);
        let mut reference = 0.0f32;
        let (mut rises, mut changes_on) = (0, 0);
        for k in 0..200_000 {
            if rand() < 0.002 {
                s.reset();
                history.clear();
                was_on = false;
            }
            if rand() < 0.05 {
                reference = if rand() < 0.02 {
                    f32::NAN
                } else {
                    (rand() - 0.5) * 1e-6
                };
            }
            // Mostly moves by less than the band (a change that keeps the axis on target).
            if rand() < 0.02 {
                reference += 2e-9;
            }
            let error = (rand() - 0.5) * if rand() < 0.5 { 2.2e-8 } else { 1e-6 };
            let reading = if rand() < 0.003 {
                f32::NAN
            } else {
                reference + error
            };
            let flag = b.observe(&mut s, reading, reference);

            let bits = reference.to_bits();
            let inside = (reading - reference).abs() <= b.tolerance_m;
            let previous_bits = history.last().map_or(f32::NAN.to_bits(), |h| h.0);
            history.push((bits, inside));
            let n = b.ticks as usize;
            let on = history.len() >= n && history[history.len() - n..].iter().all(|h| h.1);
            let since = history
                .iter()
                .rev()
                .zip(
                    history
                        .iter()
                        .rev()
                        .skip(1)
                        .map(|h| h.0)
                        .chain([f32::NAN.to_bits()]),
                )
                .position(|(h, before)| h.0 != before)
                // No change since the reset: counted from the reset (a NaN reference).
                .unwrap_or(history.len()) as u32;
            if bits != previous_bits && was_on {
                settle = 0;
                changes_on += 1;
            }
            if on && !was_on {
                settle = (since + 1).saturating_sub(b.ticks);
                rises += 1;
            }
            was_on = on;
            assert_eq!(flag, on, "k={k}");
            assert_eq!(s.on_target(), on, "k={k}");
            assert_eq!(s.ticks_since_change(), since, "k={k}");
            assert_eq!(s.settle_ticks(), settle, "k={k}");
        }
        assert!(rises > 1_000 && changes_on > 100, "{rises} {changes_on}");
    }
}
