//! The fixed self-check run of the QEMU image (and of a host test): the two-axis loop
//! [`crate::xy_loop::TwoAxisLoop`] with the built-in parameter set ([`crate::params`]) on the
//! simulated stage of [`crate::plant`] (an independent f32 Euler Bouc-Wen with the same
//! parameters, plus a 50 µs lag), once with the core's compensator and once with the linear
//! baseline.
//!
//! Reference: x `19 µm + 15 µm · sin(2π · 10 Hz · t)`, y `19 µm + 15 µm · tri(10 Hz · t)`, for
//! [`DEMO_TICKS`] ticks at the file's loop rate (4 periods at 10 kHz). The error at tick k is the
//! sensor reading at tick k minus the reference of tick k − 1 (the command that reading answers),
//! counted after [`SETTLE_TICKS`].
//!
//! Pass ([`DemoComparison::passed`]): on each axis the compensated RMS error is below
//! [`RATIO_LIMIT`] × the uncompensated one and below [`RMS_ERROR_LIMIT_M`], its peak below
//! [`MAX_ERROR_LIMIT_M`], and neither run saw a fault or a guard intervention after settling.

use core::cell::Cell;

use crate::codes::SensorScale;
use crate::control::TrackingStats;
use crate::params::{self, AMPLIFIER_GAIN_V_PER_V, AXES, SAMPLE_PERIOD_S, SENSOR_M_PER_V};
use crate::plant::{plant_io, XyPlant};
use crate::reference::{Program, ReferenceGenerator, Wave};
use crate::xy_loop::{Axis, ConfigError, Counters, Feedforward, LoopSettings, Mode, TwoAxisLoop};

/// Ticks in one run.
pub const DEMO_TICKS: u32 = 4_000;
/// Ticks excluded from the error statistics (start-up transient).
pub const SETTLE_TICKS: u32 = 1_000;
/// Reference centre \[m\].
pub const REFERENCE_OFFSET_M: f32 = 19.0e-6;
/// Reference amplitude \[m\].
pub const REFERENCE_AMPLITUDE_M: f32 = 15.0e-6;
/// Reference frequency \[Hz\].
pub const REFERENCE_FREQUENCY_HZ: f32 = 10.0;
/// Compensated RMS error must be below this fraction of the uncompensated one.
pub const RATIO_LIMIT: f32 = 0.2;
/// Compensated RMS error limit \[m\].
pub const RMS_ERROR_LIMIT_M: f32 = 50e-9;
/// Compensated peak error limit \[m\].
pub const MAX_ERROR_LIMIT_M: f32 = 100e-9;

/// The demo reference program.
pub fn program() -> Program {
    Program::PerAxis([
        Wave::Sine {
            offset: REFERENCE_OFFSET_M,
            amplitude: REFERENCE_AMPLITUDE_M,
            frequency_hz: REFERENCE_FREQUENCY_HZ,
        },
        Wave::Triangle {
            offset: REFERENCE_OFFSET_M,
            amplitude: REFERENCE_AMPLITUDE_M,
            frequency_hz: REFERENCE_FREQUENCY_HZ,
        },
    ])
}

/// Loop settings from the built-in parameter file.
pub fn settings() -> Result<LoopSettings, ConfigError> {
    LoopSettings::from_params(&AXES, AMPLIFIER_GAIN_V_PER_V, SAMPLE_PERIOD_S)
}

/// The loop a powered-up image starts: the built-in set's compensator, each axis at rest at its
/// window's lower end (the rest voltage of a stage left unpowered, and the reference its rest
/// output `rest_output_m`) until a request says otherwise.
pub fn at_rest(settings: LoopSettings) -> TwoAxisLoop {
    let rest = [0, 1].map(|i| Wave::Constant {
        offset: AXES[i].rest_output_m,
    });
    let reference = ReferenceGenerator::new(Program::PerAxis(rest), SAMPLE_PERIOD_S, [0.0; 2]);
    let initial = [AXES[0].limits.output_min_v, AXES[1].limits.output_min_v];
    TwoAxisLoop::new(settings, Feedforward::Compensator, reference, initial)
}

/// The sensor gain of the parameter file.
pub fn sensor_scale() -> Option<SensorScale> {
    SensorScale::new(SENSOR_M_PER_V)
}

/// Outcome of one run.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DemoReport {
    /// Feed-forward used.
    pub feedforward: Feedforward,
    /// Tracking error per axis after [`SETTLE_TICKS`].
    pub stats: [TrackingStats; 2],
    /// Loop counters at the end.
    pub counters: Counters,
    /// Guard interventions (all kinds, both axes) after settling.
    pub guard_faults_after_settle: u32,
    /// Mode at the end.
    pub mode: Mode,
}

/// Why the demo could not run.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum DemoError {
    /// The parameter set was refused at boot.
    Config(ConfigError),
    /// The sensor gain is zero or not finite.
    Sensor,
}

fn guard_faults(lp: &TwoAxisLoop) -> u32 {
    Axis::ALL
        .iter()
        .map(|&a| lp.guard(a).counters().total())
        .fold(0, u32::saturating_add)
}

/// Runs [`DEMO_TICKS`] ticks of the loop on the simulated stage. `on_tick` sees the loop after
/// each tick (for draining frames).
pub fn run_demo(
    feedforward: Feedforward,
    mut on_tick: impl FnMut(u32, &mut TwoAxisLoop),
) -> Result<DemoReport, DemoError> {
    let settings = settings().map_err(DemoError::Config)?;
    let scale = sensor_scale().ok_or(DemoError::Sensor)?;
    let plant = Cell::new(XyPlant::from_params(SAMPLE_PERIOD_S).ok_or(DemoError::Sensor)?);
    let mut io = plant_io(&plant, scale);
    let reference = ReferenceGenerator::new(program(), SAMPLE_PERIOD_S, [0.0; 2]);
    let initial = [
        params::AXES[0].limits.output_min_v,
        params::AXES[1].limits.output_min_v,
    ];
    let mut lp = TwoAxisLoop::new(settings, feedforward, reference, initial);
    let mut stats = [TrackingStats::default(); 2];
    let mut previous_reference = [f32::NAN; 2];
    let mut guard_at_settle = 0;
    for k in 0..DEMO_TICKS {
        if k == SETTLE_TICKS {
            guard_at_settle = guard_faults(&lp);
        }
        let report = lp.tick(&mut io, false);
        let mut p = plant.get();
        p.advance();
        plant.set(p);
        if k >= SETTLE_TICKS {
            for i in 0..2 {
                stats[i].push(report.measured_m[i] - previous_reference[i]);
            }
        }
        previous_reference = report.reference_m;
        on_tick(k, &mut lp);
    }
    Ok(DemoReport {
        feedforward,
        stats,
        counters: lp.counters(),
        guard_faults_after_settle: guard_faults(&lp) - guard_at_settle,
        mode: lp.mode(),
    })
}

/// The two runs side by side.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DemoComparison {
    /// With `piezo_core::Compensator`.
    pub compensated: DemoReport,
    /// With the linear baseline.
    pub uncompensated: DemoReport,
}

impl DemoComparison {
    /// Compensated RMS / uncompensated RMS, per axis.
    pub fn ratio(&self) -> [f32; 2] {
        [0, 1].map(|i| self.compensated.stats[i].rms_m() / self.uncompensated.stats[i].rms_m())
    }

    /// See the module docs.
    pub fn passed(&self) -> bool {
        self.failures().is_empty()
    }

    /// Every check that failed, in the order of the module docs.
    pub fn failures(&self) -> heapless::Vec<Failure, 16> {
        let mut out = heapless::Vec::new();
        for r in [&self.compensated, &self.uncompensated] {
            let ff = r.feedforward;
            let checks = [
                (r.counters.faults() != 0).then_some(Failure::Faults(ff, r.counters.faults())),
                (r.mode != Mode::Running).then_some(Failure::NotRunning(ff, r.mode)),
                (r.guard_faults_after_settle != 0)
                    .then_some(Failure::GuardAfterSettle(ff, r.guard_faults_after_settle)),
                (r.counters.ticks != DEMO_TICKS).then_some(Failure::Ticks(ff, r.counters.ticks)),
            ];
            for failure in checks.into_iter().flatten() {
                let _ = out.push(failure);
            }
        }
        let ratio = self.ratio();
        // NaN fails every check.
        let below = |x: f32, limit: f32| x < limit;
        for axis in Axis::ALL {
            let s = &self.compensated.stats[axis.index()];
            let checks = [
                (!below(ratio[axis.index()], RATIO_LIMIT))
                    .then_some(Failure::Ratio(axis, ratio[axis.index()])),
                (!below(s.rms_m(), RMS_ERROR_LIMIT_M)).then_some(Failure::Rms(axis, s.rms_m())),
                (!below(s.max_abs_m(), MAX_ERROR_LIMIT_M))
                    .then_some(Failure::Peak(axis, s.max_abs_m())),
            ];
            for failure in checks.into_iter().flatten() {
                let _ = out.push(failure);
            }
        }
        out
    }
}

/// One check of [`DemoComparison::passed`] that failed, with the numbers.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Failure {
    /// A run saw faults (count).
    Faults(Feedforward, u32),
    /// A run ended in the safe state.
    NotRunning(Feedforward, Mode),
    /// The guard intervened after settling (count).
    GuardAfterSettle(Feedforward, u32),
    /// A run did not complete its ticks.
    Ticks(Feedforward, u32),
    /// Compensated / uncompensated RMS not below [`RATIO_LIMIT`].
    Ratio(Axis, f32),
    /// Compensated RMS error \[m\] not below [`RMS_ERROR_LIMIT_M`].
    Rms(Axis, f32),
    /// Compensated peak error \[m\] not below [`MAX_ERROR_LIMIT_M`].
    Peak(Axis, f32),
}

impl core::fmt::Display for Failure {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match *self {
            Failure::Faults(ff, n) => write!(f, "{ff:?} run: {n} faults"),
            Failure::NotRunning(ff, mode) => write!(f, "{ff:?} run ended in {mode:?}"),
            Failure::GuardAfterSettle(ff, n) => write!(
                f,
                "{ff:?} run: the output guard intervened {n} times after settling (window or slew)"
            ),
            Failure::Ticks(ff, n) => write!(f, "{ff:?} run: {n} of {DEMO_TICKS} ticks"),
            Failure::Ratio(axis, r) => write!(
                f,
                "{axis:?}: compensated/uncompensated RMS {r} is not below {RATIO_LIMIT}"
            ),
            Failure::Rms(axis, m) => write!(
                f,
                "{axis:?}: compensated RMS error {} nm is not below {} nm",
                m * 1e9,
                RMS_ERROR_LIMIT_M * 1e9
            ),
            Failure::Peak(axis, m) => write!(
                f,
                "{axis:?}: compensated peak error {} nm is not below {} nm",
                m * 1e9,
                MAX_ERROR_LIMIT_M * 1e9
            ),
        }
    }
}

/// Overrun drill: [`DRILL_TICKS`] compensated ticks with a missed deadline injected at tick
/// [`DRILL_OVERRUN_TICK`]; returns the counters, the mode at the end and the outputs written
/// in the tick before and the tick of the fault (equal: the fault holds the output at once).
pub fn overrun_drill() -> Result<(Counters, Mode, [f32; 2], [f32; 2]), DemoError> {
    let settings = settings().map_err(DemoError::Config)?;
    let scale = sensor_scale().ok_or(DemoError::Sensor)?;
    let plant = Cell::new(XyPlant::from_params(SAMPLE_PERIOD_S).ok_or(DemoError::Sensor)?);
    let mut io = plant_io(&plant, scale);
    let reference = ReferenceGenerator::new(program(), SAMPLE_PERIOD_S, [0.0; 2]);
    let mut lp = TwoAxisLoop::new(settings, Feedforward::Compensator, reference, [0.0; 2]);
    let mut before = [0.0; 2];
    let mut at_fault = [0.0; 2];
    for k in 0..DRILL_TICKS {
        let report = lp.tick(&mut io, k == DRILL_OVERRUN_TICK);
        let mut p = plant.get();
        p.advance();
        plant.set(p);
        if k + 1 == DRILL_OVERRUN_TICK {
            before = report.applied_v;
        }
        if k == DRILL_OVERRUN_TICK {
            at_fault = report.applied_v;
        }
    }
    Ok((lp.counters(), lp.mode(), before, at_fault))
}

/// Ticks of [`overrun_drill`].
pub const DRILL_TICKS: u32 = 200;
/// Tick told that the previous one missed its deadline.
pub const DRILL_OVERRUN_TICK: u32 = 150;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn compensator_beats_the_linear_baseline() {
        let compensated = run_demo(Feedforward::Compensator, |_, _| {}).unwrap();
        let uncompensated = run_demo(Feedforward::Linear, |_, _| {}).unwrap();
        let cmp = DemoComparison {
            compensated,
            uncompensated,
        };
        for i in 0..2 {
            println!(
                "axis {i}: compensated rms {:.1} nm max {:.1} nm; linear rms {:.1} nm max {:.1} nm; ratio {:.3}",
                compensated.stats[i].rms_m() * 1e9,
                compensated.stats[i].max_abs_m() * 1e9,
                uncompensated.stats[i].rms_m() * 1e9,
                uncompensated.stats[i].max_abs_m() * 1e9,
                cmp.ratio()[i]
            );
        }
        println!("{:?}", compensated.counters);
        assert!(cmp.passed(), "{cmp:?}");
    }

    #[test]
    fn overrun_drill_holds_in_the_same_tick() {
        let (counters, mode, before, at_fault) = overrun_drill().unwrap();
        assert_eq!(counters.overruns, 1);
        assert_eq!(counters.safe_entries, 1);
        assert_eq!(mode, Mode::Safe(crate::xy_loop::Fault::Overrun));
        assert_eq!(before, at_fault);
        assert!(before[0] > 10.0);
    }

    #[test]
    fn the_check_can_fail() {
        // Linear against linear: ratio 1, must fail.
        let linear = run_demo(Feedforward::Linear, |_, _| {}).unwrap();
        let cmp = DemoComparison {
            compensated: linear,
            uncompensated: linear,
        };
        assert!(!cmp.passed());
        let failures = cmp.failures();
        assert!(
            matches!(failures[0], Failure::Ratio(Axis::X, r) if r == 1.0),
            "{failures:?}"
        );
        let text = std::format!("{}", failures[1]);
        assert!(text.starts_with("X: compensated RMS error"), "{text}");
    }
}
