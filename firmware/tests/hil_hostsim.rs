//! Hardware-in-the-loop against host-sim's plant: the firmware's two-axis loop
//! (`xy_loop::TwoAxisLoop::tick`, the same code the images run) on the host, with mock DAC and ADC
//! implementations backed by host-sim's independent f64 two-axis flexure stage
//! (`host_sim::plant::XyStage`: Bouc-Wen stacks driving a 4-DOF lever/flexure chain per axis,
//! integrated with host-sim's adaptive Dormand–Prince 5(4)), not by the firmware's own f32 plant
//! (`tests/hil.rs`).
//!
//! Per tick: `loop.tick(..)` reads the ADC (the plant's platform position now) and writes the DAC
//! codes; the mock DAC turns each code back into actuator volts (`code · LSB · G_amp`) and holds
//! it; then the plant moves on one loop period under that zero-order hold — the input jump
//! first (`Plant::input_jump`: the hysteresis state moves along its rate-independent path),
//! then the ODE with the input held (`Dp45::advance` to the next sample instant).
//!
//! **Frame of the measurement.** The parameter file (`params/xy-stage.toml`) models each stack's
//! free elongation, `y = d·(u − h)` with `d` set for 38 µm at 120 V; the XY stage's platform moves
//! `G = XyStage::static_gain()` (≈ 1.68, the lever/flexure transmission) times that at rest. The
//! sensor here is calibrated in the file's frame: the mock ADC reports the platform position
//! divided by `G` (the calibration constant of the measurement chain, a static number of the
//! plant's geometry, not of its hysteresis), through the file's sensor gain and the ADS8681
//! code. Everything the compensator does not model stays in: the flexure modes (≈ 3.2 kHz x,
//! 2.2 kHz y) rung by every ZOH step, f64 vs f32 hysteresis, DAC and ADC quantisation.
//!
//! The error at tick k is the true (f64, unquantised, referred) platform position at tick k minus
//! the reference of tick k − 1 (the command that position answers), counted after
//! [`SETTLE_TICKS`]; the reference is the firmware demo's program (x sine, y triangle,
//! 19 ± 15 µm, i.e. 10.5–89.5 % of the 38 µm stroke, at 10 Hz).

use std::cell::Cell;
use std::convert::Infallible;

use host_sim::ode::{Dp45, Dp45Settings, OdeSystem};
use host_sim::plant::{InputAt, Plant, XyStage};
use piezo_firmware::codes::{AdcCode, DacCode, SensorScale};
use piezo_firmware::converter::{AdcRead, DacWrite, ErrorType};
use piezo_firmware::demo;
use piezo_firmware::params::{AMPLIFIER_GAIN_V_PER_V, AXES, LOOP_RATE_HZ, SAMPLE_PERIOD_S};
use piezo_firmware::reference::ReferenceGenerator;
use piezo_firmware::xy_loop::{AdcSensor, Axis, Counters, Feedforward, Mode, TwoAxisLoop, XyIo};

/// Ticks in one run: 0.5 s at 10 kHz (five periods of the 10 Hz reference).
const TICKS: u32 = 5_000;
/// Ticks left out of the error statistics (start-up step from rest to 19 µm and its transient).
const SETTLE_TICKS: u32 = 1_000;
/// Compensated RMS error must be below this fraction of the uncompensated one.
const RATIO_LIMIT: f64 = 0.25;
/// Compensated RMS error limit per axis [m]. Measured: 31.96 nm (x), 30.51 nm (y), zero mean.
/// That is the zero-order hold, not the hysteresis: the flexure's first modes (3.2 / 2.2 kHz) lie
/// below the 10 kHz loop rate, so the platform follows the average of the held staircase, i.e.
/// the command delayed by T/2 = 50 µs (plus 2ζ/ω ≈ 3 µs of the mode), which the feed-forward does
/// not model. Predicted error: RMS slope × 50 µs = 666 µm/s × 50 µs = 33.3 nm for the x sine
/// (2π·10 Hz·15 µm/√2) and 600 µm/s × 50 µs = 30.0 nm for the y triangle (4·15 µm·10 Hz): the
/// measurement sits on it. 40 nm is that floor plus ≈ 20 % (x) / 33 % (y) for the residual model
/// error, the DAC step (0.65 nm) and the ringing; the uncompensated RMS error is ≈ 85× larger.
const RMS_ERROR_LIMIT_M: f64 = 40e-9;

/// host-sim's XY stage, stepped one held-input period at a time.
struct HostStage {
    stage: XyStage,
    /// Platform displacement per unit free stack elongation, per axis (the sensor calibration).
    referral: [f64; 2],
    x: Vec<f64>,
    held_v: [f64; 2],
    ticks: u64,
    ode: Dp45,
}

/// The plant with its inputs held (ZOH between jumps: u̇ = 0).
struct Held<'a> {
    stage: &'a XyStage,
    u_v: [f64; 2],
}

impl InputAt for Held<'_> {
    fn input(&self, channel: usize, _t_s: f64) -> (f64, f64) {
        (self.u_v[channel.min(1)], 0.0)
    }
}

impl OdeSystem for Held<'_> {
    fn dim(&self) -> usize {
        self.stage.state_dim()
    }
    fn rhs(&self, t: f64, x: &[f64], dx: &mut [f64]) {
        self.stage.rhs(t, x, self, dx);
    }
}

impl HostStage {
    fn new() -> Self {
        let stage = XyStage::default();
        let mut x = vec![0.0; stage.state_dim()];
        stage.initial_state(&mut x);
        // host-sim's own default tolerances (`SimSettings::new`): suited to nm-scale outputs.
        let ode = Dp45::new(
            x.len(),
            Dp45Settings {
                rtol: 1e-8,
                atol: 1e-14,
                ..Default::default()
            },
        );
        Self {
            referral: stage.static_gain(),
            stage,
            x,
            held_v: [0.0; 2],
            ticks: 0,
            ode,
        }
    }

    /// Platform positions, referred to the stack's free elongation (the parameter file's frame).
    fn position_m(&self) -> [f64; 2] {
        let mut y = [0.0; 2];
        self.stage.output(&self.x, &self.held_v, &mut y);
        [y[0] / self.referral[0], y[1] / self.referral[1]]
    }

    /// One loop period with `u_v` held: the ZOH jump, then the ODE to the next sample instant.
    fn advance(&mut self, u_v: [f64; 2]) {
        self.stage
            .check_input_span(u_v[0].min(u_v[1]), u_v[0].max(u_v[1]))
            .unwrap();
        for (ch, (&from, &to)) in self.held_v.iter().zip(&u_v).enumerate() {
            if from != to {
                self.stage.input_jump(&mut self.x, ch, from, to);
            }
        }
        self.held_v = u_v;
        let period_s = 1.0 / f64::from(LOOP_RATE_HZ);
        let mut t = self.ticks as f64 * period_s;
        self.ticks += 1;
        let held = Held {
            stage: &self.stage,
            u_v,
        };
        self.ode
            .advance(&held, &mut t, &mut self.x, self.ticks as f64 * period_s)
            .unwrap();
        self.stage.check_state(&self.x).unwrap();
    }
}

/// The DAC: codes back to actuator volts through the amplifier gain, held for the plant.
struct MockDac<'a> {
    held_v: &'a Cell<[f64; 2]>,
    amplifier_gain_v_per_v: f32,
}

impl ErrorType for MockDac<'_> {
    type Error = Infallible;
}

impl DacWrite for MockDac<'_> {
    type Channel = Axis;
    fn write_code(&mut self, axis: Axis, code: DacCode) -> Result<(), Infallible> {
        let mut v = self.held_v.get();
        v[axis.index()] = f64::from(code.to_volts() * self.amplifier_gain_v_per_v);
        self.held_v.set(v);
        Ok(())
    }
}

/// The ADC: the plant's (referred) position through the sensor gain, as an ADS8681 code.
struct MockAdc<'a> {
    position_m: &'a Cell<[f64; 2]>,
    scale: SensorScale,
}

impl ErrorType for MockAdc<'_> {
    type Error = Infallible;
}

impl AdcRead for MockAdc<'_> {
    type Channel = Axis;
    fn read_code(&mut self, axis: Axis) -> Result<AdcCode, Infallible> {
        let m = self.position_m.get()[axis.index()] as f32;
        Ok(AdcCode::from_volts(self.scale.volts(m)))
    }
}

/// Tracking error of one axis.
#[derive(Clone, Copy, Debug, Default)]
struct Stats {
    sum: f64,
    sum_sq: f64,
    max_abs: f64,
    n: u32,
}

impl Stats {
    fn push(&mut self, e: f64) {
        self.sum += e;
        self.sum_sq += e * e;
        self.max_abs = self.max_abs.max(e.abs());
        self.n += 1;
    }
    fn mean(&self) -> f64 {
        self.sum / f64::from(self.n)
    }
    fn rms(&self) -> f64 {
        (self.sum_sq / f64::from(self.n)).sqrt()
    }
}

struct Outcome {
    /// True referred position vs reference.
    truth: [Stats; 2],
    /// The loop's own ADC reading vs reference.
    sensed: [Stats; 2],
    counters: Counters,
    /// Guard interventions (both axes) after [`SETTLE_TICKS`].
    guard_interventions: u32,
    mode: Mode,
    /// Lowest and highest voltage the plant was driven with, per axis.
    span_v: [(f64, f64); 2],
}

fn run(feedforward: Feedforward) -> Outcome {
    let held_v = Cell::new([0.0; 2]);
    let position_m = Cell::new([0.0; 2]);
    let mut plant = HostStage::new();
    let mut io = XyIo {
        dac: MockDac {
            held_v: &held_v,
            amplifier_gain_v_per_v: AMPLIFIER_GAIN_V_PER_V,
        },
        dac_channels: Axis::ALL,
        sensor: AdcSensor {
            adc: MockAdc {
                position_m: &position_m,
                scale: demo::sensor_scale().unwrap(),
            },
            channels: Axis::ALL,
            scale: demo::sensor_scale().unwrap(),
        },
    };
    let reference = ReferenceGenerator::new(demo::program(), SAMPLE_PERIOD_S, [0.0; 2]);
    let initial = [AXES[0].limits.output_min_v, AXES[1].limits.output_min_v];
    let mut lp = TwoAxisLoop::new(demo::settings().unwrap(), feedforward, reference, initial);
    let mut truth = [Stats::default(); 2];
    let mut sensed = [Stats::default(); 2];
    let mut span_v = [(f64::INFINITY, f64::NEG_INFINITY); 2];
    let mut previous_reference = [f32::NAN; 2];
    let guard_total = |lp: &TwoAxisLoop| -> u32 {
        Axis::ALL
            .iter()
            .map(|&a| lp.guard(a).counters().total())
            .sum()
    };
    let mut guard_at_settle = 0;
    for k in 0..TICKS {
        if k == SETTLE_TICKS {
            guard_at_settle = guard_total(&lp);
        }
        let now = plant.position_m();
        position_m.set(now);
        let report = lp.tick(&mut io, false);
        for i in 0..2 {
            let (lo, hi) = (AXES[i].limits.output_min_v, AXES[i].limits.output_max_v);
            assert!(
                (lo..=hi).contains(&report.applied_v[i]),
                "tick {k} axis {i}: {} V",
                report.applied_v[i]
            );
            let v = held_v.get()[i];
            assert!(
                (f64::from(lo)..=f64::from(hi)).contains(&v),
                "tick {k} axis {i}: plant driven at {v} V"
            );
            span_v[i] = (span_v[i].0.min(v), span_v[i].1.max(v));
            if k >= SETTLE_TICKS {
                let r = f64::from(previous_reference[i]);
                truth[i].push(now[i] - r);
                sensed[i].push(f64::from(report.measured_m[i]) - r);
            }
        }
        previous_reference = report.reference_m;
        plant.advance(held_v.get());
        lp.frames.drain_into(&mut heapless::Vec::<_, 4>::new());
    }
    Outcome {
        truth,
        sensed,
        counters: lp.counters(),
        guard_interventions: guard_total(&lp) - guard_at_settle,
        mode: lp.mode(),
        span_v,
    }
}

#[test]
fn two_axis_loop_tracks_host_sim_xy_stage_through_mock_dac_adc() {
    let compensated = run(Feedforward::Compensator);
    let linear = run(Feedforward::Linear);
    for (name, o) in [("compensator", &compensated), ("linear", &linear)] {
        for (i, axis) in ["x", "y"].iter().enumerate() {
            println!(
                "{name:>11} {axis}: RMS {:7.2} nm, mean {:7.2} nm, peak {:7.2} nm (ADC reading: RMS {:7.2} nm), \
                 drive {:6.2}..{:6.2} V",
                o.truth[i].rms() * 1e9,
                o.truth[i].mean() * 1e9,
                o.truth[i].max_abs * 1e9,
                o.sensed[i].rms() * 1e9,
                o.span_v[i].0,
                o.span_v[i].1,
            );
        }
        println!(
            "{name:>11}: {:?}, guard interventions after settling {}",
            o.counters, o.guard_interventions
        );
        assert_eq!(o.counters.faults(), 0, "{name}: {:?}", o.counters);
        assert_eq!(o.counters.safe_entries, 0, "{name}");
        assert_eq!(o.counters.ticks, TICKS, "{name}");
        assert_eq!(o.mode, Mode::Running, "{name}");
        assert_eq!(o.guard_interventions, 0, "{name}");
        assert_eq!(o.truth[0].n, TICKS - SETTLE_TICKS);
    }
    for i in 0..2 {
        let (c, l) = (compensated.truth[i].rms(), linear.truth[i].rms());
        println!("axis {i}: compensated/linear RMS = {:.4}", c / l);
        assert!(c < RATIO_LIMIT * l, "axis {i}: {c:e} vs {l:e}");
        assert!(c < RMS_ERROR_LIMIT_M, "axis {i}: {c:e} m");
    }
}
