//! The fixed self-check run of the QEMU image (and of a host test): the loop of
//! [`crate::control::tick`] on the simulated stage of [`crate::plant`], tracking a sine.
//!
//! Reference: `x_ref(k) = 7.5 µm + 5 µm · sin(2π · 10 Hz · k / 10 kHz)`, for [`DEMO_TICKS`]
//! ticks (4 periods). Stage: 20 V/V amplifier, 0.15 µm/V stroke (15 µm at 100 V), play
//! half-width 3 V, lag τ = 0.2 ms, sensor 1.5 µm/V. Guard: 0–100 V, 2 V per tick (20 kV/s).
//! At tick [`NAN_TICK`] the feed-forward output is replaced by NaN to exercise the guard.
//!
//! The run passes ([`DemoReport::passed`]) when, after [`SETTLE_TICKS`], the tracking error
//! stays under [`MAX_ERROR_LIMIT_M`] (peak) and [`RMS_ERROR_LIMIT_M`] (RMS), and the guard
//! counted exactly the one injected NaN and no fault after settling (the start-up ramp from 0 V
//! is slew-limited, as it should be). The limits are set for the plain
//! linear feed-forward [`linear_feedforward`], which leaves the play (≈ ±0.45 µm) uncompensated;
//! with the inverse hysteresis compensator of `piezo-core` they should be tightened.

use core::cell::Cell;

use crate::codes::SensorScale;
use crate::control::{tick, LoopConfig, LoopIo, TickError, TrackingStats};
use crate::plant::{PlantAdc, PlantDac, PlantParams, SimPlant};
use crate::safety::{FaultCounters, SafetyLimits};

/// Loop rate, hertz.
pub const LOOP_RATE_HZ: f32 = 10_000.0;
/// Ticks in the run.
pub const DEMO_TICKS: u32 = 4_000;
/// Ticks excluded from the error statistics (start-up transient).
pub const SETTLE_TICKS: u32 = 1_000;
/// Tick whose feed-forward output is replaced by NaN.
pub const NAN_TICK: u32 = 500;
/// Reference offset, metres.
pub const REFERENCE_OFFSET_M: f32 = 7.5e-6;
/// Reference amplitude, metres.
pub const REFERENCE_AMPLITUDE_M: f32 = 5.0e-6;
/// Reference frequency, hertz.
pub const REFERENCE_FREQUENCY_HZ: f32 = 10.0;
/// Static stroke of the simulated stage, metres per actuator volt.
pub const STROKE_M_PER_V: f32 = 0.15e-6;
/// Peak tracking error allowed after settling, metres.
pub const MAX_ERROR_LIMIT_M: f32 = 0.8e-6;
/// RMS tracking error allowed after settling, metres.
pub const RMS_ERROR_LIMIT_M: f32 = 0.6e-6;

/// Parameters of the simulated stage.
pub fn plant_params() -> PlantParams {
    PlantParams {
        amplifier_gain_v_per_v: 20.0,
        stroke_m_per_v: STROKE_M_PER_V,
        play_half_width_v: 3.0,
        // α = 1 − exp(−T/τ) with T = 0.1 ms, τ = 0.2 ms.
        lag_alpha: 1.0 - libm::expf(-0.5),
        sensor: sensor(),
    }
}

fn sensor() -> SensorScale {
    // 1.5 µm/V is finite and non-zero.
    SensorScale::new(1.5e-6).unwrap_or_else(|| unreachable!())
}

/// Loop settings of the run.
pub fn loop_config() -> LoopConfig {
    let limits = SafetyLimits::new(0.0, 100.0, 2.0).unwrap_or_else(|_| unreachable!());
    LoopConfig::new(sensor(), 20.0, limits).unwrap_or_else(|| unreachable!())
}

/// Reference displacement at tick `k`, metres.
pub fn reference_m(k: u32) -> f32 {
    let phase = 2.0 * core::f32::consts::PI * REFERENCE_FREQUENCY_HZ * (k as f32 / LOOP_RATE_HZ);
    REFERENCE_OFFSET_M + REFERENCE_AMPLITUDE_M * libm::sinf(phase)
}

/// The baseline feed-forward: static inverse of the stroke, ignoring hysteresis and lag.
pub fn linear_feedforward(reference_m: f32, _measured_m: f32) -> f32 {
    reference_m / STROKE_M_PER_V
}

/// Outcome of [`run_demo`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DemoReport {
    /// Ticks run.
    pub ticks: u32,
    /// Tracking error after [`SETTLE_TICKS`].
    pub stats: TrackingStats,
    /// Guard fault counters over the whole run (the start-up ramp from 0 V is slew-limited).
    pub counters: FaultCounters,
    /// Guard faults after [`SETTLE_TICKS`] (none expected).
    pub faults_after_settle: u32,
    /// Final displacement of the stage, metres.
    pub final_displacement_m: f32,
}

impl DemoReport {
    /// True if the error is within the limits, the guard saw exactly the one injected NaN and
    /// no fault at all after settling.
    pub fn passed(&self) -> bool {
        self.ticks == DEMO_TICKS
            && self.stats.max_abs_m() < MAX_ERROR_LIMIT_M
            && self.stats.rms_m() < RMS_ERROR_LIMIT_M
            && self.counters.non_finite == 1
            && self.faults_after_settle == 0
    }
}

/// Runs [`DEMO_TICKS`] ticks of the loop on the simulated stage with `feedforward`.
pub fn run_demo<F: FnMut(f32, f32) -> f32>(mut feedforward: F) -> DemoReport {
    let plant = Cell::new(SimPlant::new(plant_params()));
    let config = loop_config();
    let mut io = LoopIo {
        dac: PlantDac(&plant),
        dac_channel: (),
        adc: PlantAdc(&plant),
        adc_channel: (),
    };
    let mut guard = config.limits().state(0.0);
    let mut stats = TrackingStats::default();
    let mut faults_at_settle = 0;
    for k in 0..DEMO_TICKS {
        if k == SETTLE_TICKS {
            faults_at_settle = guard.counters().total();
        }
        let ff = |r: f32, m: f32| {
            if k == NAN_TICK {
                f32::NAN
            } else {
                feedforward(r, m)
            }
        };
        let out = match tick(&mut io, &config, &mut guard, reference_m(k), ff) {
            Ok(out) => out,
            Err(TickError::Adc(e) | TickError::Dac(e)) => match e {},
        };
        if k >= SETTLE_TICKS {
            // The reading at tick k answers the command of tick k − 1: compare with its reference.
            stats.push(reference_m(k - 1) - out.measured_m);
        }
    }
    DemoReport {
        ticks: DEMO_TICKS,
        stats,
        counters: guard.counters(),
        faults_after_settle: guard.counters().total() - faults_at_settle,
        final_displacement_m: plant.get().displacement_m(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn linear_feedforward_demo_passes() {
        let report = run_demo(linear_feedforward);
        println!(
            "rms {:.3} µm, max {:.3} µm, counters {:?}",
            report.stats.rms_m() * 1e6,
            report.stats.max_abs_m() * 1e6,
            report.counters
        );
        assert!(report.passed(), "{report:?}");
        assert_eq!(report.stats.count(), DEMO_TICKS - SETTLE_TICKS);
    }

    #[test]
    fn demo_fails_without_feedforward() {
        // A check that cannot fail is no check: zero output must fail it.
        assert!(!run_demo(|_, _| 0.0).passed());
    }

    #[test]
    fn demo_fails_if_the_guard_sees_more_faults() {
        // Asking for 200 V once (window clamp) must fail the counters check.
        let mut k = 0;
        let report = run_demo(|r, m| {
            k += 1;
            if k == 2000 {
                200.0
            } else {
                linear_feedforward(r, m)
            }
        });
        assert!(!report.passed());
        assert_eq!(report.counters.window_clamped, 1);
        assert_eq!(report.faults_after_settle, 2); // clamped, then slew-limited back
    }
}
