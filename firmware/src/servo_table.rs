//! The servo table of the image: the four control modes (`piezo_core::ServoMode`) of the
//! two-axis loop on the simulated stage of [`crate::plant`] with creep, drift and sensor noise
//! ([`table_disturbances`]), the built-in parameter set and its `[x.servo]`/`[y.servo]`: tracking
//! error at 1, 10 and 100 Hz triangles and sines, and the closed-loop bandwidth of each mode —
//! the table `host-sim servo-bench` gives for host-sim's XY stage, here for the image's own
//! plant (which has a 50 µs lag where the XY stage has its modes).
//!
//! **Tracking** ([`tracking`]): references between [`LOW_FRACTION`] and [`HIGH_FRACTION`] of the
//! axis's stroke (its first loading over the window), triangles rising from the low end, sines
//! starting at mid-stroke, from the stage at rest at the lower end of the window; error at tick k
//! = true position after the tick's voltage has acted (the plant advanced one period) − the
//! reference of tick k, from [`SETTLE_S`] on over at least one period; RMS and largest |error|
//! in % of the stroke, the worse axis.
//!
//! **Bandwidth** ([`bandwidth_hz`]): stepped sines of ±[`BANDWIDTH_AMPLITUDE_FRACTION`] of the
//! stroke around mid-stroke at [`BANDWIDTH_POINTS`] frequencies, log-spaced from 10 Hz to 0.45 of
//! the loop rate; per point the first harmonic of the true position over whole periods after
//! two periods of settling (lock-in: Σ y·sin, Σ y·cos); |Y/R| relative to the lowest frequency's;
//! the −3 dB frequency by log-log interpolation between the two points around it (the highest
//! frequency if it never falls that far), the lower axis.
//!
//! No allocation, no panic; the image prints the rows, a host test checks the ratios.

use core::cell::Cell;

use piezo_core::ServoMode;

use crate::codes::SensorScale;
use crate::control::TrackingStats;
use crate::params::{self, AMPLIFIER_GAIN_V_PER_V, AXES, SAMPLE_PERIOD_S, SENSOR_M_PER_V};
use crate::plant::{plant_io, Disturbances, XyPlant};
use crate::reference::{Program, ReferenceGenerator, Wave};
use crate::xy_loop::{
    Axis, ConfigError, ControlError, Feedforward, LoopSettings, Mode, TwoAxisLoop,
};

/// Lower end of the tracking references \[fraction of the stroke\].
pub const LOW_FRACTION: f32 = 0.2;
/// Upper end of the tracking references \[fraction of the stroke\].
pub const HIGH_FRACTION: f32 = 0.9;
/// Time excluded from the error (start-up from rest) \[s\].
pub const SETTLE_S: f32 = 0.1;
/// Frequencies of the table \[Hz\].
pub const FREQUENCIES_HZ: [f32; 3] = [1.0, 10.0, 100.0];
/// Amplitude of the bandwidth sines \[fraction of the stroke\].
pub const BANDWIDTH_AMPLITUDE_FRACTION: f32 = 0.05;
/// Points of the stepped-sine sweep.
pub const BANDWIDTH_POINTS: u32 = 24;
/// Lowest frequency of the sweep \[Hz\].
pub const BANDWIDTH_LOW_HZ: f32 = 10.0;

/// Creep, drift and sensor noise of the table's plant: creep 2 % of the stroke per 120 V with
/// τ = 0.1 s, drift 0.1 µm/s, 2 nm RMS sensor noise (the ADC adds its 3.1 nm quantisation).
pub fn table_disturbances() -> Disturbances {
    let stroke_per_volt = stroke_m(0) / (AXES[0].limits.output_max_v - AXES[0].limits.output_min_v);
    Disturbances {
        creep_gain_m_per_v: 0.02 * stroke_per_volt,
        creep_time_constant_s: 0.1,
        drift_m_per_s: 1e-7,
        sensor_noise_rms_m: 2e-9,
    }
}

/// Shape of a tracking reference.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Shape {
    /// Rising from the low end.
    Triangle,
    /// Starting at mid-stroke.
    Sine,
}

impl Shape {
    /// `triangle`, `sine`.
    pub fn name(self) -> &'static str {
        match self {
            Shape::Triangle => "triangle",
            Shape::Sine => "sine",
        }
    }
}

/// One row of the table.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Row {
    /// Control mode.
    pub mode: ServoMode,
    /// Reference shape.
    pub shape: Shape,
    /// Reference frequency \[Hz\].
    pub frequency_hz: f32,
    /// RMS error, worse axis \[% of stroke\].
    pub rms_percent: f32,
    /// Largest |error|, worse axis \[% of stroke\].
    pub max_percent: f32,
    /// Faults seen during the run (overruns, sensor, DAC; 0 in a good run).
    pub faults: u32,
}

/// Why the table could not run.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum TableError {
    /// The built-in parameter set was refused.
    Config(ConfigError),
    /// The mode needs a servo the parameter set does not have.
    Control(ControlError),
    /// The sensor gain is zero or not finite.
    Sensor,
}

/// An axis's stroke: the first loading over the window \[m\].
pub fn stroke_m(axis: usize) -> f32 {
    let p = &AXES[axis];
    (p.linear_gain_m_per_v * (p.limits.output_max_v - p.limits.output_min_v)).abs()
}

/// Runs `ticks` ticks of `program` in `mode` on the table's plant; `each(k, reference, truth)`
/// sees every tick's reference and the true positions after it. Returns the loop's faults.
fn run(
    mode: ServoMode,
    program: Program,
    ticks: u32,
    mut each: impl FnMut(u32, [f32; 2], [f32; 2]),
) -> Result<u32, TableError> {
    let settings = LoopSettings::from_params(&AXES, AMPLIFIER_GAIN_V_PER_V, SAMPLE_PERIOD_S)
        .map_err(TableError::Config)?;
    let scale = SensorScale::new(SENSOR_M_PER_V).ok_or(TableError::Sensor)?;
    let plant = XyPlant::from_params(SAMPLE_PERIOD_S)
        .ok_or(TableError::Sensor)?
        .with_disturbances(&table_disturbances(), SAMPLE_PERIOD_S);
    let plant = Cell::new(plant);
    let mut io = plant_io(&plant, scale);
    let initial = [
        params::AXES[0].limits.output_min_v,
        params::AXES[1].limits.output_min_v,
    ];
    let rest = [AXES[0].rest_output_m, AXES[1].rest_output_m];
    let reference = ReferenceGenerator::new(program, SAMPLE_PERIOD_S, rest);
    let mut lp = TwoAxisLoop::new(settings, Feedforward::Compensator, reference, initial);
    lp.set_control_mode(mode).map_err(TableError::Control)?;
    for k in 0..ticks {
        let report = lp.tick(&mut io, false);
        let mut p = plant.get();
        p.advance();
        plant.set(p);
        lp.frames.discard();
        let truth = [
            p.axis(Axis::X).displacement_m(),
            p.axis(Axis::Y).displacement_m(),
        ];
        if report.mode == Mode::Running {
            each(k, report.reference_m, truth);
        }
    }
    Ok(lp.counters().faults())
}

/// Offset and amplitude of the tracking references of axis `i` \[m\].
fn band(i: usize) -> (f32, f32) {
    let s = stroke_m(i);
    let rest = AXES[i].rest_output_m;
    (
        rest + 0.5 * (LOW_FRACTION + HIGH_FRACTION) * s,
        0.5 * (HIGH_FRACTION - LOW_FRACTION) * s,
    )
}

fn waveform(shape: Shape, offset_m: f32, amplitude_m: f32, frequency_hz: f32) -> Wave {
    match shape {
        Shape::Triangle => Wave::Triangle {
            offset: offset_m,
            amplitude: amplitude_m,
            frequency_hz,
        },
        Shape::Sine => Wave::Sine {
            offset: offset_m,
            amplitude: amplitude_m,
            frequency_hz,
        },
    }
}

/// Ticks of a tracking run: [`SETTLE_S`] then one period (at least 50 ms).
pub fn tracking_ticks(frequency_hz: f32) -> u32 {
    let measured_s = (1.0 / frequency_hz).max(0.05);
    libm::ceilf((SETTLE_S + measured_s) / SAMPLE_PERIOD_S) as u32
}

/// One tracking row.
pub fn tracking(mode: ServoMode, shape: Shape, frequency_hz: f32) -> Result<Row, TableError> {
    let program = Program::PerAxis([0, 1].map(|i| {
        let (offset, amplitude) = band(i);
        waveform(shape, offset, amplitude, frequency_hz)
    }));
    let settle = libm::ceilf(SETTLE_S / SAMPLE_PERIOD_S) as u32;
    let mut stats = [TrackingStats::default(); 2];
    let faults = run(
        mode,
        program,
        tracking_ticks(frequency_hz),
        |k, reference, truth| {
            if k >= settle {
                for i in 0..2 {
                    stats[i].push(truth[i] - reference[i]);
                }
            }
        },
    )?;
    let percent = |f: fn(&TrackingStats) -> f32| {
        (0..2)
            .map(|i| 100.0 * f(&stats[i]) / stroke_m(i))
            .fold(0.0f32, f32::max)
    };
    Ok(Row {
        mode,
        shape,
        frequency_hz,
        rms_percent: percent(TrackingStats::rms_m),
        max_percent: percent(TrackingStats::max_abs_m),
        faults,
    })
}

/// Frequency of sweep point `j` \[Hz\].
pub fn sweep_frequency_hz(j: u32) -> f32 {
    let high = 0.45 / SAMPLE_PERIOD_S;
    let x = j as f32 / (BANDWIDTH_POINTS - 1) as f32;
    BANDWIDTH_LOW_HZ * libm::powf(high / BANDWIDTH_LOW_HZ, x)
}

/// |Y/R| of both axes at `frequency_hz` (first harmonic, lock-in over whole periods).
pub fn gain_at(mode: ServoMode, frequency_hz: f32) -> Result<[f32; 2], TableError> {
    let mid = [0, 1].map(|i| AXES[i].rest_output_m + 0.5 * stroke_m(i));
    let amplitude = [0, 1].map(|i| BANDWIDTH_AMPLITUDE_FRACTION * stroke_m(i));
    let program = Program::PerAxis([0, 1].map(|i| Wave::Sine {
        offset: mid[i],
        amplitude: amplitude[i],
        frequency_hz,
    }));
    let period_ticks = 1.0 / (frequency_hz * SAMPLE_PERIOD_S);
    // From rest to mid-stroke first (a step), then two periods of settling, then four measured.
    let start = libm::ceilf(SETTLE_S / SAMPLE_PERIOD_S + 2.0 * period_ticks) as u32;
    let measured = libm::floorf(4.0 * period_ticks).max(1.0) as u32;
    let mut sums = [[0.0f32; 2]; 2];
    run(mode, program, start + measured, |k, _, truth| {
        if k >= start {
            // The reference of tick k is offset + a·sin(2π f k T); the truth after it is at
            // time (k + 1)·T of the same clock.
            let phase =
                2.0 * core::f32::consts::PI * frequency_hz * (k + 1) as f32 * SAMPLE_PERIOD_S;
            let (s, c) = (libm::sinf(phase), libm::cosf(phase));
            for i in 0..2 {
                let y = truth[i] - mid[i];
                sums[i][0] += y * s;
                sums[i][1] += y * c;
            }
        }
    })?;
    Ok([0, 1].map(|i| {
        let [s, c] = sums[i];
        2.0 * libm::sqrtf(s * s + c * c) / (measured as f32 * amplitude[i])
    }))
}

/// The −3 dB frequency of position/reference in `mode`, the lower axis \[Hz\].
pub fn bandwidth_hz(mode: ServoMode) -> Result<f32, TableError> {
    let mut low = [0.0f32; 2];
    let mut previous = [(0.0f32, 0.0f32); 2];
    let mut found = [None::<f32>; 2];
    for j in 0..BANDWIDTH_POINTS {
        let f = sweep_frequency_hz(j);
        let g = gain_at(mode, f)?;
        for i in 0..2 {
            if found[i].is_some() {
                continue;
            }
            if j == 0 {
                low[i] = g[i];
            } else {
                let rel = g[i] / low[i];
                if rel < core::f32::consts::FRAC_1_SQRT_2 {
                    let (f0, r0) = previous[i];
                    let target = libm::logf(core::f32::consts::FRAC_1_SQRT_2);
                    let (l0, l1) = (libm::logf(r0), libm::logf(rel));
                    let x = if l1 < l0 {
                        (target - l0) / (l1 - l0)
                    } else {
                        1.0
                    };
                    found[i] = Some(f0 * libm::powf(f / f0, x.clamp(0.0, 1.0)));
                }
            }
            previous[i] = (f, g[i] / low[i].max(f32::MIN_POSITIVE));
        }
        if found.iter().all(Option::is_some) {
            break;
        }
    }
    let high = sweep_frequency_hz(BANDWIDTH_POINTS - 1);
    Ok(found
        .iter()
        .map(|f| f.unwrap_or(high))
        .fold(f32::INFINITY, f32::min))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(mode: ServoMode, shape: Shape, f: f32) -> Row {
        let r = tracking(mode, shape, f).unwrap();
        std::println!(
            "{:<22} {:<8} {:>5} Hz  rms {:.4} %  max {:.4} %  faults {}",
            mode.name(),
            shape.name(),
            f,
            r.rms_percent,
            r.max_percent,
            r.faults
        );
        assert_eq!(r.faults, 0, "{r:?}");
        r
    }

    /// Feedforward + feedback beats feedforward alone at 1 Hz (creep and drift) and feedback
    /// alone at 100 Hz (the feedback's bandwidth), on the image's plant.
    #[test]
    fn both_together_beat_each_alone_where_each_is_weak() {
        for shape in [Shape::Triangle, Shape::Sine] {
            let ff = row(ServoMode::Feedforward, shape, 1.0);
            let both = row(ServoMode::FeedforwardFeedback, shape, 1.0);
            assert!(
                both.rms_percent * 5.0 < ff.rms_percent,
                "{shape:?} 1 Hz: {both:?} vs {ff:?}"
            );
            let fb = row(ServoMode::Feedback, shape, 100.0);
            let both = row(ServoMode::FeedforwardFeedback, shape, 100.0);
            assert!(
                both.rms_percent * 5.0 < fb.rms_percent,
                "{shape:?} 100 Hz: {both:?} vs {fb:?}"
            );
        }
    }

    #[test]
    fn feedback_bandwidth_is_below_the_feedforward_one_and_finite() {
        let fb = bandwidth_hz(ServoMode::Feedback).unwrap();
        let ff = bandwidth_hz(ServoMode::Feedforward).unwrap();
        std::println!("bandwidth: feedback {fb} Hz, feedforward {ff} Hz");
        assert!(fb > 100.0 && fb < 2000.0, "{fb}");
        assert!(ff > fb, "{ff} vs {fb}");
    }

    /// Switching modes while tracking: no step in the voltage beyond what the reference itself
    /// asks per tick, and a mode with feedback is refused (nothing changed) without a servo.
    #[test]
    fn mode_switches_are_bumpless_and_feedback_needs_a_servo() {
        let settings =
            LoopSettings::from_params(&AXES, AMPLIFIER_GAIN_V_PER_V, SAMPLE_PERIOD_S).unwrap();
        let scale = SensorScale::new(SENSOR_M_PER_V).unwrap();
        let plant = XyPlant::from_params(SAMPLE_PERIOD_S)
            .unwrap()
            .with_disturbances(&table_disturbances(), SAMPLE_PERIOD_S);
        let plant = Cell::new(plant);
        let mut io = plant_io(&plant, scale);
        let (offset, amplitude) = band(0);
        let program = Program::PerAxis([waveform(Shape::Sine, offset, amplitude, 2.0); 2]);
        let reference = ReferenceGenerator::new(program, SAMPLE_PERIOD_S, [0.0; 2]);
        let mut lp = TwoAxisLoop::new(settings, Feedforward::Compensator, reference, [0.0; 2]);
        // 2 Hz sine of 35 % of the stroke: ≈ 0.3 V per 100 µs at most on the feed-forward.
        // The switches at fixed times (0.2 s … 0.7 s), so that they meet the same phase of the
        // sine, and the same errors, at any loop rate.
        let tick = |t_s: f32| (t_s / SAMPLE_PERIOD_S).round() as u32;
        let switches = [
            (tick(0.2), ServoMode::FeedforwardFeedback),
            (tick(0.3), ServoMode::Feedback),
            (tick(0.4), ServoMode::Feedforward),
            (tick(0.5), ServoMode::OpenLoop),
            (tick(0.6), ServoMode::FeedforwardFeedback),
            (tick(0.7), ServoMode::Feedforward),
        ];
        let mut last = [0.0f32; 2];
        for k in 0..tick(0.8) {
            if let Some(&(_, mode)) = switches.iter().find(|(at, _)| *at == k) {
                lp.set_control_mode(mode).unwrap();
                assert_eq!(lp.control_mode(), mode);
            }
            let r = lp.tick(&mut io, false);
            let mut p = plant.get();
            p.advance();
            plant.set(p);
            lp.frames.discard();
            if k > tick(0.1) {
                // At a switch the voltage moves as the feed-forward alone would; after it, the
                // feedback closes what error the previous mode left (the open loop's: several
                // % of the stroke) at its own pace, well inside the slew limit (10 V per tick
                // at 10 kHz, 5 V at 20 kHz).
                let limit = if switches.iter().any(|(at, _)| *at == k) {
                    0.5
                } else {
                    2.0
                };
                for (i, (u, before)) in r.applied_v.iter().zip(&last).enumerate() {
                    let step = (u - before).abs();
                    assert!(step < limit, "tick {k} axis {i}: step {step} V");
                }
            }
            last = r.applied_v;
        }
        assert_eq!(lp.counters().faults(), 0);
        // Open loop → feed-forward + feedback at 0.6 s switched the model feed-forward in: the baseline's
        // error was several % of the stroke, so the hand-over itself is what kept the step small.
        let mut without = settings;
        without.axes[1] = without.axes[1].without_servo();
        lp.set_control_mode(ServoMode::Feedforward).unwrap();
        lp.set_settings(without);
        assert_eq!(
            lp.set_control_mode(ServoMode::Feedback),
            Err(ControlError::NoServo(Axis::Y))
        );
        assert_eq!(lp.control_mode(), ServoMode::Feedforward);
    }

    #[test]
    fn the_open_loop_has_the_hysteresis_error() {
        let ol = row(ServoMode::OpenLoop, Shape::Triangle, 10.0);
        let ff = row(ServoMode::Feedforward, Shape::Triangle, 10.0);
        assert!(ol.rms_percent > 2.0 && ff.rms_percent < ol.rms_percent / 3.0);
    }
}
