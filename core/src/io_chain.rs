//! The hardware chain of an axis: DAC → amplifier → stack for the drive, stage → sensor → ADC for
//! the measurement. The stack voltages the chain can produce are
//! `[dac_min·G, dac_max·G]` (G the amplifier gain, stack volts per DAC volt, > 0); the sensor's
//! output span must lie inside the ADC's input span.
//!
//! [`IoChain::check_limits`] is the one rule for an output window and slew limit against the
//! chain, called by the stage file's validation, the firmware's build, `host-sim link upload` and
//! the firmware's session alike: the window inside what the chain drives, the slew limit finite
//! (a drive has one; +∞ is only for offline analyses), within [`CompensatorSettings::check_slew`],
//! and slow enough that a swing over the whole drive span takes at least [`MIN_DRIVE_TICKS`] ticks:
//! `S·T·MIN_DRIVE_TICKS ≤ drive_max − drive_min` (at 0–120 V and 10 kHz: S ≤ 3·10⁵ V/s, 30 V per
//! tick, about what a piezo amplifier's current limit allows into a stack's capacitance).

use crate::compensator::CompensatorSettings;
use crate::error::{positive, ParamError};

/// Fewest ticks a swing over the whole drive span (`dac_range_v × amplifier_gain_v_per_v`) may
/// take at an axis's slew limit.
pub const MIN_DRIVE_TICKS: f32 = 4.0;

/// The drive and sensing chain of a stage (both axes share it). SI units: volts, metres per volt.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct IoChain {
    /// DAC output span \[V\].
    pub dac_range_v: [f32; 2],
    /// Stack volts per DAC volt \[V/V\], > 0.
    pub amplifier_gain_v_per_v: f32,
    /// ADC input span \[V\].
    pub adc_range_v: [f32; 2],
    /// Displacement sensor output span \[V\], inside `adc_range_v`.
    pub sensor_range_v: [f32; 2],
    /// Displacement per sensor volt \[m/V\], > 0.
    pub sensor_m_per_v: f32,
}

/// Checks that a span is finite and ordered.
fn span(field: &'static str, [lo, hi]: [f32; 2]) -> Result<(), ParamError> {
    if !(lo.is_finite() && hi.is_finite()) {
        return Err(ParamError::NonFinite { field });
    }
    if lo < hi {
        Ok(())
    } else {
        Err(ParamError::OutOfRange {
            field,
            value: hi,
            requirement: "> the span's lower end",
        })
    }
}

impl IoChain {
    /// The chain's own consistency: finite positive gains, finite ordered spans, the sensor span
    /// inside the ADC's.
    pub fn check(&self) -> Result<(), ParamError> {
        positive("amplifier_gain_v_per_v", self.amplifier_gain_v_per_v)?;
        positive("sensor_m_per_v", self.sensor_m_per_v)?;
        span("dac_range_v", self.dac_range_v)?;
        span("adc_range_v", self.adc_range_v)?;
        span("sensor_range_v", self.sensor_range_v)?;
        let ([s0, s1], [a0, a1]) = (self.sensor_range_v, self.adc_range_v);
        if s0 < a0 || s1 > a1 {
            return Err(ParamError::SensorOutsideAdc {
                sensor_range_v: self.sensor_range_v,
                adc_range_v: self.adc_range_v,
            });
        }
        Ok(())
    }

    /// The stack voltages the DAC and the amplifier produce, `dac_range_v × amplifier_gain_v_per_v`
    /// \[V\].
    pub fn drive_range_v(&self) -> (f32, f32) {
        let g = self.amplifier_gain_v_per_v;
        (self.dac_range_v[0] * g, self.dac_range_v[1] * g)
    }

    /// The fastest slew limit [`IoChain::check_limits`] accepts at loop period `sample_period_s`:
    /// a swing over the whole drive span in [`MIN_DRIVE_TICKS`] ticks,
    /// `(drive_max − drive_min) / (MIN_DRIVE_TICKS · T)` \[V/s\].
    pub fn fastest_slew_v_per_s(&self, sample_period_s: f32) -> f32 {
        let (d0, d1) = self.drive_range_v();
        (d1 - d0) / (MIN_DRIVE_TICKS * sample_period_s)
    }

    /// An axis's output window and slew limit against this chain: the chain itself
    /// ([`IoChain::check`]), the window and slew by [`CompensatorSettings::check_slew`], the slew
    /// limit finite, and the window inside [`IoChain::drive_range_v`] (1 mV of rounding allowed).
    pub fn check_limits(&self, settings: &CompensatorSettings) -> Result<(), ParamError> {
        self.check()?;
        settings.check_slew()?;
        let slew = settings.limits.slew_limit_v_per_s;
        if !slew.is_finite() {
            return Err(ParamError::OutOfRange {
                field: "slew_limit_v_per_s",
                value: slew,
                requirement: "finite: the drive needs a slew limit",
            });
        }
        let (d0, d1) = self.drive_range_v();
        let swing_ticks = (d1 - d0) / (slew * settings.sample_period_s);
        if swing_ticks.is_nan() || swing_ticks < MIN_DRIVE_TICKS {
            return Err(ParamError::Implausible {
                field: "slew_limit_v_per_s",
                value: slew,
                measure: "the share of the drive span one tick may swing, slew_limit_v_per_s · \
                          sample_period_s / (drive_max − drive_min),",
                ratio: 1.0 / swing_ticks,
                limit: 1.0 / MIN_DRIVE_TICKS,
            });
        }
        let (u0, u1) = (settings.limits.output_min_v, settings.limits.output_max_v);
        if u0 < d0 - 1e-3 || u1 > d1 + 1e-3 {
            return Err(ParamError::WindowOutsideDrive {
                window_v: [u0, u1],
                drive_v: [d0, d1],
            });
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const CHAIN: IoChain = IoChain {
        dac_range_v: [0.0, 5.0],
        amplifier_gain_v_per_v: 24.0,
        adc_range_v: [-10.24, 10.24],
        sensor_range_v: [0.0, 10.0],
        sensor_m_per_v: 1e-5,
    };

    fn window(min: f32, max: f32, slew: f32) -> CompensatorSettings {
        CompensatorSettings {
            limits: crate::Limits::new(min, max, slew),
            sample_period_s: 1e-4,
        }
    }

    #[test]
    fn the_window_must_lie_inside_what_the_chain_drives() {
        assert_eq!(CHAIN.check_limits(&window(0.0, 120.0, 1e5)), Ok(()));
        for (lo, hi) in [(0.0, 200.0), (-50.0, 120.0), (-0.01, 100.0)] {
            assert!(
                matches!(
                    CHAIN.check_limits(&window(lo, hi, 1e5)),
                    Err(ParamError::WindowOutsideDrive {
                        drive_v: [_, 120.0],
                        ..
                    })
                ),
                "[{lo}, {hi}]"
            );
        }
        extern crate std;
        use std::string::ToString;
        let message = CHAIN
            .check_limits(&window(0.0, 200.0, 1e5))
            .unwrap_err()
            .to_string();
        assert!(message.contains("[0, 120] V"), "{message}");
    }

    #[test]
    fn the_slew_limit_is_finite_and_leaves_a_full_window_move_a_few_ticks() {
        for slew in [1e38, f32::INFINITY, 3.1e5] {
            assert!(
                matches!(
                    CHAIN.check_limits(&window(0.0, 120.0, slew)),
                    Err(ParamError::Implausible { .. } | ParamError::OutOfRange { .. })
                ),
                "{slew}"
            );
        }
        assert_eq!(CHAIN.check_limits(&window(0.0, 120.0, 3.0e5)), Ok(()));
    }

    #[test]
    fn the_sensor_span_must_lie_inside_the_adc_span() {
        let mut chain = CHAIN;
        chain.sensor_range_v = [0.0, 12.0];
        assert!(matches!(
            chain.check(),
            Err(ParamError::SensorOutsideAdc { .. })
        ));
        chain.sensor_range_v = [0.0, 10.0];
        chain.amplifier_gain_v_per_v = f32::INFINITY;
        assert!(chain.check().is_err());
    }
}
