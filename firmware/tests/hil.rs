//! Hardware-in-the-loop through a mock HAL: the firmware's two-axis loop
//! (`xy_loop::TwoAxisLoop`, the same code the images run) on the host, with mock DAC and ADC
//! implementations backed by the firmware's simulated stage (`plant::XyPlant`, independent f32
//! Euler Bouc-Wen + lag), and injected faults: SPI error on an ADC read, a stuck ADC reading, a
//! non-finite reading, a failing DAC write, an overrun. Each must put the loop in the safe state
//! in the tick it happens (outputs held at the last guarded voltage, codes unchanged in the
//! plant) and be counted exactly once.

use std::cell::Cell;

use piezo_firmware::codes::{AdcCode, DacCode};
use piezo_firmware::converter::{AdcRead, DacWrite, DriverError, ErrorType};
use piezo_firmware::demo;
use piezo_firmware::params::SAMPLE_PERIOD_S;
use piezo_firmware::plant::{plant_io, PlantAdc, PlantDac, XyPlant};
use piezo_firmware::reference::{Program, ReferenceGenerator, Wave};
use piezo_firmware::xy_loop::{
    AdcSensor, Axis, Counters, Fault, Feedforward, Mode, PositionSensor, TickReport, TwoAxisLoop,
    XyIo,
};

/// The driver error type the real ADS8681/DAC8563 drivers return.
type SpiError = DriverError<embedded_hal::spi::ErrorKind>;

/// Faults to inject, by tick.
#[derive(Clone, Copy, Default)]
struct Faults {
    adc_spi_error: Option<(u32, Axis)>,
    adc_stuck_from: Option<(u32, Axis)>,
    non_finite: Option<(u32, Axis)>,
    dac_fails: Option<(u32, Axis)>,
    overrun: Option<u32>,
}

/// Shared by the mocks: the current tick and the fault plan.
struct Bench {
    now: Cell<u32>,
    faults: Faults,
}

impl Bench {
    fn hits(&self, at: Option<(u32, Axis)>, axis: Axis) -> bool {
        at == Some((self.now.get(), axis))
    }
}

struct MockDac<'a> {
    plant: PlantDac<'a>,
    bench: &'a Bench,
}

impl ErrorType for MockDac<'_> {
    type Error = SpiError;
}

impl DacWrite for MockDac<'_> {
    type Channel = Axis;
    fn write_code(&mut self, axis: Axis, code: DacCode) -> Result<(), SpiError> {
        if self.bench.hits(self.bench.faults.dac_fails, axis) {
            return Err(DriverError::Spi(embedded_hal::spi::ErrorKind::ModeFault));
        }
        self.plant.write_code(axis, code).map_err(|e| match e {})
    }
}

struct MockAdc<'a> {
    plant: PlantAdc<'a>,
    bench: &'a Bench,
    frozen: Option<AdcCode>,
}

impl ErrorType for MockAdc<'_> {
    type Error = SpiError;
}

impl AdcRead for MockAdc<'_> {
    type Channel = Axis;
    fn read_code(&mut self, axis: Axis) -> Result<AdcCode, SpiError> {
        if self.bench.hits(self.bench.faults.adc_spi_error, axis) {
            return Err(DriverError::Spi(embedded_hal::spi::ErrorKind::Overrun));
        }
        let code = self.plant.read_code(axis).unwrap_or_else(|e| match e {});
        match self.bench.faults.adc_stuck_from {
            Some((k, a)) if a == axis && self.bench.now.get() >= k => {
                Ok(*self.frozen.get_or_insert(code))
            }
            _ => Ok(code),
        }
    }
}

/// Sensor front end that can turn a reading into NaN (a broken linearisation, say).
struct MaybeNan<'a, S> {
    inner: S,
    bench: &'a Bench,
}

impl<S: PositionSensor> ErrorType for MaybeNan<'_, S> {
    type Error = S::Error;
}

impl<S: PositionSensor> PositionSensor for MaybeNan<'_, S> {
    fn read_m(&mut self, axis: Axis) -> Result<f32, S::Error> {
        let m = self.inner.read_m(axis)?;
        Ok(if self.bench.hits(self.bench.faults.non_finite, axis) {
            f32::NAN
        } else {
            m
        })
    }
}

/// Runs `ticks` ticks of the compensated loop with `program`; returns the reports and the DAC
/// codes the plant held after each tick.
struct Run {
    reports: Vec<TickReport>,
    codes: Vec<[DacCode; 2]>,
    counters: Counters,
    mode: Mode,
    max_error_after_rearm_m: f32,
}

fn run(program: Program, ticks: u32, faults: Faults, rearm_at: Option<u32>) -> Run {
    let bench = Bench {
        now: Cell::new(0),
        faults,
    };
    let plant = Cell::new(XyPlant::from_params(SAMPLE_PERIOD_S).unwrap());
    let mut io = XyIo {
        dac: MockDac {
            plant: PlantDac(&plant),
            bench: &bench,
        },
        dac_channels: Axis::ALL,
        sensor: MaybeNan {
            inner: AdcSensor {
                adc: MockAdc {
                    plant: PlantAdc(&plant),
                    bench: &bench,
                    frozen: None,
                },
                channels: Axis::ALL,
                scale: demo::sensor_scale().unwrap(),
            },
            bench: &bench,
        },
    };
    let reference = ReferenceGenerator::new(program, SAMPLE_PERIOD_S, [0.0; 2]);
    let mut lp = TwoAxisLoop::new(
        demo::settings().unwrap(),
        Feedforward::Compensator,
        reference,
        [0.0; 2],
    );
    let mut out = Run {
        reports: Vec::new(),
        codes: Vec::new(),
        counters: Counters::default(),
        mode: Mode::Running,
        max_error_after_rearm_m: 0.0,
    };
    let mut previous_reference = [f32::NAN; 2];
    for k in 0..ticks {
        bench.now.set(k);
        if rearm_at == Some(k) {
            lp.rearm();
        }
        let report = lp.tick(&mut io, faults.overrun == Some(k));
        let mut p = plant.get();
        out.codes.push([p.code(Axis::X), p.code(Axis::Y)]);
        p.advance();
        plant.set(p);
        if let Some(r) = rearm_at {
            if k > r + 500 {
                for (m, r) in report.measured_m.iter().zip(previous_reference) {
                    out.max_error_after_rearm_m = out.max_error_after_rearm_m.max((m - r).abs());
                }
            }
        }
        previous_reference = report.reference_m;
        out.reports.push(report);
        lp.frames.drain_into(&mut heapless::Vec::<_, 4>::new());
    }
    out.counters = lp.counters();
    out.mode = lp.mode();
    out
}

const FAULT_TICK: u32 = 1_234;

/// In the fault tick the loop is safe, every axis's output equals the previous tick's, and the
/// plant's codes did not change; the loop stays safe and holds afterwards.
fn assert_safe_from(run: &Run, tick: u32, fault: Fault) {
    let k = tick as usize;
    assert_eq!(run.reports[k - 1].mode, Mode::Running);
    assert_eq!(run.reports[k].mode, Mode::Safe(fault));
    assert_eq!(run.reports[k].applied_v, run.reports[k - 1].applied_v);
    assert_eq!(run.codes[k], run.codes[k - 1]);
    assert_eq!(*run.codes.last().unwrap(), run.codes[k - 1]);
    assert_eq!(run.mode, Mode::Safe(fault));
    assert_eq!(run.counters.safe_entries, 1);
    // The outputs were moving before the fault (the check is not vacuous).
    assert_ne!(run.reports[k - 2].applied_v, run.reports[k - 1].applied_v);
}

fn sine() -> Program {
    demo::program()
}

#[test]
fn no_fault_no_trip_on_every_program() {
    let programs = [
        sine(),
        Program::Raster {
            x_min: 5e-6,
            x_max: 30e-6,
            y_min: 5e-6,
            y_max: 30e-6,
            lines: 8,
            line_rate_hz: 50.0,
        },
        Program::PerAxis([
            Wave::Steps {
                offset: 18e-6,
                amplitude: 10e-6,
                frequency_hz: 20.0,
            },
            Wave::Constant { offset: 12e-6 },
        ]),
    ];
    for p in programs {
        let r = run(p, 5_000, Faults::default(), None);
        assert_eq!(r.counters.faults(), 0, "{p:?}: {:?}", r.counters);
        assert_eq!(r.mode, Mode::Running);
        assert_eq!(r.counters.ticks, 5_000);
    }
}

#[test]
fn adc_spi_error_holds_in_the_same_tick() {
    let faults = Faults {
        adc_spi_error: Some((FAULT_TICK, Axis::X)),
        ..Faults::default()
    };
    let r = run(sine(), FAULT_TICK + 100, faults, None);
    assert_safe_from(&r, FAULT_TICK, Fault::SensorError(Axis::X));
    assert!(r.reports[FAULT_TICK as usize].measured_m[0].is_nan());
    assert_eq!(r.counters.sensor_errors, 1);
    assert_eq!(r.counters.faults(), 1);
}

#[test]
fn stuck_adc_reading_is_detected_and_holds() {
    let faults = Faults {
        adc_stuck_from: Some((FAULT_TICK, Axis::Y)),
        ..Faults::default()
    };
    let r = run(sine(), FAULT_TICK + 200, faults, None);
    // Detected after StuckPolicy::DEFAULT.ticks identical readings with ≥ 1 V of motion.
    let detected = r
        .reports
        .iter()
        .position(|t| t.mode != Mode::Running)
        .unwrap() as u32;
    assert!(
        (FAULT_TICK + 10..FAULT_TICK + 60).contains(&detected),
        "{detected}"
    );
    assert_safe_from(&r, detected, Fault::StuckReading(Axis::Y));
    assert_eq!(r.counters.stuck_readings, 1);
    assert_eq!(r.counters.faults(), 1);
}

#[test]
fn non_finite_reading_holds_in_the_same_tick() {
    let faults = Faults {
        non_finite: Some((FAULT_TICK, Axis::Y)),
        ..Faults::default()
    };
    let r = run(sine(), FAULT_TICK + 100, faults, None);
    assert_safe_from(&r, FAULT_TICK, Fault::NonFiniteReading(Axis::Y));
    assert_eq!(r.counters.non_finite_readings, 1);
    assert_eq!(r.counters.faults(), 1);
}

#[test]
fn failing_dac_write_on_x_holds_both_axes() {
    let faults = Faults {
        dac_fails: Some((FAULT_TICK, Axis::X)),
        ..Faults::default()
    };
    let r = run(sine(), FAULT_TICK + 100, faults, None);
    assert_safe_from(&r, FAULT_TICK, Fault::DacError(Axis::X));
    assert_eq!(r.counters.dac_errors, 1);
    assert_eq!(r.counters.faults(), 1);
}

#[test]
fn failing_dac_write_on_y_holds_from_that_tick() {
    let faults = Faults {
        dac_fails: Some((FAULT_TICK, Axis::Y)),
        ..Faults::default()
    };
    let r = run(sine(), FAULT_TICK + 100, faults, None);
    let k = FAULT_TICK as usize;
    // x was written before y failed: its new code stands and is held from then on.
    assert_eq!(r.reports[k].mode, Mode::Safe(Fault::DacError(Axis::Y)));
    assert_ne!(r.codes[k][0], r.codes[k - 1][0]);
    assert_eq!(r.codes[k][1], r.codes[k - 1][1]);
    assert_eq!(r.reports[k].applied_v[1], r.reports[k - 1].applied_v[1]);
    assert_eq!(*r.codes.last().unwrap(), r.codes[k]);
    assert_eq!(r.counters.dac_errors, 1);
    assert_eq!(r.counters.safe_entries, 1);
}

#[test]
fn overrun_holds_in_the_same_tick() {
    let faults = Faults {
        overrun: Some(FAULT_TICK),
        ..Faults::default()
    };
    let r = run(sine(), FAULT_TICK + 100, faults, None);
    assert_safe_from(&r, FAULT_TICK, Fault::Overrun);
    assert_eq!(r.counters.overruns, 1);
    assert_eq!(r.counters.faults(), 1);
}

#[test]
fn every_fault_at_once_is_counted_once_each() {
    let faults = Faults {
        adc_spi_error: Some((FAULT_TICK, Axis::X)),
        non_finite: Some((FAULT_TICK, Axis::Y)),
        dac_fails: Some((FAULT_TICK, Axis::X)),
        overrun: Some(FAULT_TICK),
        ..Faults::default()
    };
    let r = run(sine(), FAULT_TICK + 50, faults, None);
    // The first detected (the overrun, told at the start of the tick) is the one latched.
    assert_safe_from(&r, FAULT_TICK, Fault::Overrun);
    let c = r.counters;
    assert_eq!(
        (
            c.overruns,
            c.sensor_errors,
            c.non_finite_readings,
            c.dac_errors
        ),
        (1, 1, 1, 1)
    );
}

#[test]
fn rearm_resumes_tracking_without_a_jump() {
    let faults = Faults {
        overrun: Some(FAULT_TICK),
        ..Faults::default()
    };
    let rearm = FAULT_TICK + 300;
    let r = run(sine(), rearm + 3_000, faults, Some(rearm));
    assert_eq!(r.mode, Mode::Running);
    assert_eq!(r.counters.safe_entries, 1);
    // The first tick after rearming moves by at most one slew step from the held voltage.
    let k = rearm as usize;
    for i in 0..2 {
        assert!((r.reports[k].applied_v[i] - r.reports[k - 1].applied_v[i]).abs() <= 10.01);
    }
    // Back on track (the compensated error is ~20 nm; the limit is generous).
    assert!(
        r.max_error_after_rearm_m < 0.1e-6,
        "{}",
        r.max_error_after_rearm_m
    );
}

#[test]
fn streamed_setpoints_play_and_a_nan_setpoint_is_held_not_a_fault() {
    let bench_program = Program::Streamed;
    let plant = Cell::new(XyPlant::from_params(SAMPLE_PERIOD_S).unwrap());
    let mut io = plant_io(&plant, demo::sensor_scale().unwrap());
    let reference = ReferenceGenerator::new(bench_program, SAMPLE_PERIOD_S, [10e-6, 10e-6]);
    let mut lp = TwoAxisLoop::new(
        demo::settings().unwrap(),
        Feedforward::Compensator,
        reference,
        [0.0; 2],
    );
    let mut last = [0.0; 2];
    for k in 0..2_000u32 {
        if lp.reference.queued() < 8 {
            let s = if k == 1_000 {
                [f32::NAN, 12e-6]
            } else {
                [10e-6 + 1e-9 * k as f32, 12e-6]
            };
            lp.reference.push_setpoint(s).unwrap();
        }
        let report = lp.tick(&mut io, false);
        let mut p = plant.get();
        p.advance();
        plant.set(p);
        last = report.measured_m;
    }
    assert_eq!(lp.mode(), Mode::Running);
    assert_eq!(lp.counters().held_references, 1);
    assert_eq!(lp.counters().faults(), 0);
    assert_eq!(lp.reference.underruns(), 0);
    assert!((last[1] - 12e-6).abs() < 20e-9, "{last:?}");
}
