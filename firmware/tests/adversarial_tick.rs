//! Adversarial run of the whole two-axis tick (`xy_loop::TwoAxisLoop::tick`, the code the images
//! run): [`TICKS`] ticks from a fixed seed, between and during which everything that can happen
//! to the loop happens at random —
//!
//! - references: streamed setpoints and wave tables of ordinary values, NaN, ±∞, ±10³⁰ and
//!   full-scale jumps; periodic programs and rasters with random (also absurd) amplitudes and
//!   frequencies; program switches;
//! - sensor readings that follow the voltage, random ADC codes, NaN, ±∞, frozen readings, read
//!   errors; DAC write errors; overruns;
//! - feed-forward switches (compensator, linear baseline, open-loop excitation), control-mode
//!   switches (all four), rearms;
//! - parameter swaps (`set_settings`) with random valid sets built on the stage files of
//!   `firmware/params/` (either axis of either file): random windows inside the hardware range
//!   0–120 V (DAC 0–5 V × 24 V/V), random slew limits 1 V/s – 1 MV/s, with and without the servo
//!   and the effects, random frame decimation.
//!
//! Checked on every tick and both axes, on the voltage the tick applied (the DAC's input):
//! finite; inside 0–120 V; inside the window in force, or, after a swap to a window that
//! excludes it, moving monotonically towards it (never further away, and never out again once
//! in); and `|u_k − u_{k−1}| ≤ slew_limit_v_per_s · T` **in exact arithmetic** (the difference of
//! the two f32 as an exact f64 sum, against the f64 product; T the smaller of the firmware's f32
//! period and 1/rate), with the slew limit of the settings in force in tick k (after a swap: the
//! new set's).
//!
//! `cargo test -p piezo-firmware --test adversarial_tick -- --nocapture` prints the figures.

#[path = "../build/params.rs"]
#[allow(dead_code)]
mod stage_file;

use piezo_core::effects::EffectParams;
use piezo_core::ServoMode;
use piezo_firmware::codes::{AdcCode, DacCode, SensorScale};
use piezo_firmware::converter::{DacWrite, Error, ErrorKind, ErrorType};
use piezo_firmware::params::{AxisParams, AMPLIFIER_GAIN_V_PER_V, LOOP_RATE_HZ, SAMPLE_PERIOD_S};
use piezo_firmware::reference::{Program, ReferenceGenerator, Wave};
use piezo_firmware::xy_loop::{
    Axis, AxisConfig, Feedforward, LoopSettings, Mode, PositionSensor, StuckPolicy, TwoAxisLoop,
    XyIo,
};

/// Ticks of the run (1 000 s of loop time at 10 kHz).
const TICKS: u64 = 10_000_000;
const SEED: u64 = 0x9e37_79b9_7f4a_7c15;
/// The hardware's voltage range: DAC 0–5 V times the amplifier's 24 V/V.
const HARDWARE_V: (f32, f32) = (0.0, 120.0);

/// SplitMix64: a small deterministic generator.
struct Rng(u64);

impl Rng {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    fn chance(&mut self, p: f64) -> bool {
        self.unit() < p
    }

    fn below(&mut self, n: u64) -> u64 {
        self.next_u64() % n
    }

    fn uniform(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.unit() as f32
    }

    fn log_uniform(&mut self, lo: f32, hi: f32) -> f32 {
        (lo.ln() + (hi.ln() - lo.ln()) * self.unit() as f32).exp()
    }

    /// A value a hostile host might send, in metres or (excitation) volts.
    fn hostile_value(&mut self) -> f32 {
        match self.below(12) {
            0 => f32::NAN,
            1 => f32::INFINITY,
            2 => f32::NEG_INFINITY,
            3 => 1e30,
            4 => -1e30,
            5 => [0.0, 120.0, 119.999_99, 1e-30, -0.0][self.below(5) as usize],
            6 => f32::from_bits(self.next_u64() as u32),
            7 | 8 => self.uniform(-50.0, 200.0),
            _ => self.uniform(-20e-6, 60e-6),
        }
    }

    fn waveform(&mut self) -> Wave {
        let offset_m = if self.chance(0.7) {
            self.uniform(0.0, 40e-6)
        } else {
            self.hostile_value()
        };
        let amplitude_m = if self.chance(0.7) {
            self.uniform(0.0, 30e-6)
        } else {
            self.hostile_value()
        };
        let frequency_hz = if self.chance(0.8) {
            self.log_uniform(0.1, 4_000.0)
        } else {
            self.hostile_value()
        };
        match self.below(4) {
            0 => Wave::Constant { offset: offset_m },
            1 => Wave::Sine {
                offset: offset_m,
                amplitude: amplitude_m,
                frequency_hz,
            },
            2 => Wave::Triangle {
                offset: offset_m,
                amplitude: amplitude_m,
                frequency_hz,
            },
            _ => Wave::Steps {
                offset: offset_m,
                amplitude: amplitude_m,
                frequency_hz,
            },
        }
    }
}

/// A converter error.
#[derive(Clone, Copy, Debug)]
struct Injected;

impl Error for Injected {
    fn kind(&self) -> ErrorKind {
        ErrorKind::Other
    }
}

/// The DAC: fails when told to, otherwise keeps the code.
struct Dac {
    fail: [bool; 2],
    codes: [DacCode; 2],
}

impl ErrorType for Dac {
    type Error = Injected;
}

impl DacWrite for Dac {
    type Channel = Axis;
    fn write_code(&mut self, axis: Axis, code: DacCode) -> Result<(), Injected> {
        if self.fail[axis.index()] {
            return Err(Injected);
        }
        self.codes[axis.index()] = code;
        Ok(())
    }
}

/// The sensor: this tick's reading per axis (`None`: a read error).
struct Sensor {
    readings: [Option<f32>; 2],
}

impl ErrorType for Sensor {
    type Error = Injected;
}

impl PositionSensor for Sensor {
    fn read_m(&mut self, axis: Axis) -> Result<f32, Injected> {
        self.readings[axis.index()].ok_or(Injected)
    }
}

/// Either axis of every stage file in `firmware/params/`.
fn base_axes() -> Vec<AxisParams> {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("params");
    let mut axes = Vec::new();
    for file in [
        "xy-stage.toml",
        "xy-stage-effects.toml",
        "xy-stage-lag.toml",
    ] {
        let bytes = std::fs::read(dir.join(file)).unwrap();
        let set = stage_file::load(file, &bytes).unwrap();
        // The loop runs every file's axes at the built file's rate (the default file's, 20 kHz;
        // the others are written for 10 kHz): the slew step per tick only gets smaller.
        assert!(
            set.loop_rate_hz <= LOOP_RATE_HZ,
            "{file}: {}",
            set.loop_rate_hz
        );
        assert_eq!(set.amplifier_gain_v_per_v, AMPLIFIER_GAIN_V_PER_V);
        for a in set.axes {
            axes.push(AxisParams {
                bouc_wen: a.bouc_wen,
                static_map: a.static_map,
                asymmetry: a.asymmetry,
                limits: a.limits,
                linear_gain_m_per_v: a.linear_gain_m_per_v,
                rest_output_m: a.rest_output_m,
                effects: a.effects,
                servo: a.servo,
                envelope: a.envelope,
                on_target: a.on_target,
            });
        }
    }
    assert!(axes.iter().any(|a| a.servo.is_some()));
    assert!(axes.iter().any(|a| a.effects != EffectParams::default()));
    axes
}

/// Per axis: the window and the step bound in force.
#[derive(Clone, Copy, Debug)]
struct InForce {
    window: (f32, f32),
    /// `slew_limit_v_per_s · T` of the stage values the axis was built from \[V\].
    bound_v: f64,
}

/// `slew · T` in f64, for T the firmware's f32 period and for T = 1/rate: the smaller.
fn step_bound_v(slew_v_per_s: f32) -> f64 {
    let slew = f64::from(slew_v_per_s);
    (slew * f64::from(SAMPLE_PERIOD_S)).min(slew / f64::from(LOOP_RATE_HZ))
}

/// A random valid axis on one of `bases`, or `None` if the firmware refuses it.
fn random_axis(rng: &mut Rng, bases: &[AxisParams]) -> Option<(AxisConfig, InForce)> {
    let mut p = bases[rng.below(bases.len() as u64) as usize];
    if rng.chance(0.7) {
        let a = rng.uniform(HARDWARE_V.0, HARDWARE_V.1);
        let b = rng.uniform(HARDWARE_V.0, HARDWARE_V.1);
        p.limits.output_min_v = a.min(b);
        p.limits.output_max_v = a.max(b).max(p.limits.output_min_v + 0.5).min(HARDWARE_V.1);
    }
    if rng.chance(0.7) {
        p.limits.slew_limit_v_per_s = rng.log_uniform(1.0, 1e6);
    }
    if rng.chance(0.3) {
        p.servo = None;
    }
    if rng.chance(0.3) {
        p.effects = EffectParams::default();
    }
    // The linear baseline's first loading over this window (as an upload computes it).
    let (rest, gain) = p
        .model(SAMPLE_PERIOD_S)
        .ok()?
        .first_loading(p.limits.output_min_v, p.limits.output_max_v);
    p.rest_output_m = rest;
    p.linear_gain_m_per_v = gain;
    let config = AxisConfig::from_params(&p, SAMPLE_PERIOD_S).ok()?;
    let in_force = InForce {
        window: (p.limits.output_min_v, p.limits.output_max_v),
        bound_v: step_bound_v(p.limits.slew_limit_v_per_s),
    };
    Some((config, in_force))
}

/// Random valid settings, their windows and bounds, and how many axes were refused on the way.
fn random_settings(rng: &mut Rng, bases: &[AxisParams]) -> (LoopSettings, [InForce; 2], u32) {
    let mut refused = 0;
    let mut axis = |rng: &mut Rng| loop {
        match random_axis(rng, bases) {
            Some(a) => return a,
            None => refused += 1,
        }
    };
    let (x, y) = (axis(rng), axis(rng));
    let settings = LoopSettings::new(
        [x.0, y.0],
        AMPLIFIER_GAIN_V_PER_V,
        StuckPolicy::DEFAULT,
        1 + rng.below(10) as u32,
    )
    .expect("the file's amplifier gain");
    (settings, [x.1, y.1], refused)
}

/// Whether `|a − b| > bound` in exact arithmetic: in f64, `a − b = s + e` exactly (TwoSum; f32
/// operands cannot overflow), so `|s| ≠ bound` decides (rounding is monotone), else the sign of
/// `e`.
fn exceeds(a: f32, b: f32, bound: f64) -> bool {
    let (a, b) = (f64::from(a), f64::from(b));
    let s = a - b;
    let a_part = s + b;
    let b_part = s - a_part;
    let e = (a - a_part) + (-b - b_part);
    if s.abs() != bound {
        s.abs() > bound
    } else {
        e != 0.0 && (e > 0.0) == (s > 0.0)
    }
}

/// How far `v` lies outside `window` (0 inside).
fn distance(window: (f32, f32), v: f32) -> f64 {
    let v = f64::from(v);
    (f64::from(window.0) - v)
        .max(v - f64::from(window.1))
        .max(0.0)
}

/// What the run saw.
#[derive(Default, Debug)]
struct Tally {
    window_violations: u64,
    slew_violations: u64,
    other_violations: u64,
    first: Vec<String>,
    swaps: u32,
    refused_axes: u32,
    ticks_slewing_in: u64,
    safe_ticks: u64,
    ticks_by_feedforward: [u64; 3],
    ticks_with_feedback: u64,
    largest_step_fraction: f64,
}

impl Tally {
    fn violation(&mut self, what: String) {
        if self.first.len() < 10 {
            self.first.push(what);
        }
    }
}

/// A random program; a table or stream gets random entries.
fn random_program(rng: &mut Rng, reference: &mut ReferenceGenerator) -> Program {
    match rng.below(6) {
        0 | 1 => Program::PerAxis([rng.waveform(), rng.waveform()]),
        2 => Program::Raster {
            x_min: rng.hostile_value(),
            x_max: rng.uniform(0.0, 40e-6),
            y_min: rng.uniform(0.0, 40e-6),
            y_max: rng.hostile_value(),
            lines: 2 + rng.below(100) as u16,
            line_rate_hz: rng.log_uniform(0.1, 5_000.0),
        },
        3 => {
            reference.table_clear();
            let entries: Vec<[f32; 2]> = (0..1 + rng.below(64))
                .map(|_| [rng.hostile_value(), rng.hostile_value()])
                .collect();
            reference.table_append(&entries).unwrap();
            Program::Table {
                ticks_per_entry: rng.below(20) as u32,
                repeat: rng.chance(0.5),
            }
        }
        _ => Program::Streamed,
    }
}

/// This tick's sensor reading of an axis: mostly one that follows the voltage applied last
/// tick (so that the stuck detector sees a live stage), else garbage, frozen, or an error.
fn random_reading(
    rng: &mut Rng,
    applied_v: f32,
    tick: u64,
    frozen: &mut (u32, f32),
) -> Option<f32> {
    if frozen.0 > 0 {
        frozen.0 -= 1;
        return Some(frozen.1);
    }
    let live = applied_v * 0.3e-6 + (tick % 1_000) as f32 * 1e-12;
    match rng.below(100_000) {
        0..=9 => None,
        10..=19 => Some([f32::NAN, f32::INFINITY, f32::NEG_INFINITY, 1e30][rng.below(4) as usize]),
        20..=29 => {
            *frozen = (20 + rng.below(200) as u32, live);
            Some(live)
        }
        30..=4_999 => {
            let scale = SensorScale::new(10e-6).unwrap();
            Some(scale.metres(AdcCode(rng.next_u64() as u16).to_volts()))
        }
        _ => Some(live),
    }
}

#[test]
fn adversarial_two_axis_ticks_keep_window_and_slew() {
    let mut rng = Rng(SEED);
    let bases = base_axes();
    let mut tally = Tally::default();
    let (settings, mut limits, refused) = random_settings(&mut rng, &bases);
    tally.refused_axes += refused;
    let initial = limits.map(|l| rng.uniform(l.window.0, l.window.1));
    let mut lp = TwoAxisLoop::new(
        settings,
        Feedforward::Compensator,
        ReferenceGenerator::new(Program::Streamed, SAMPLE_PERIOD_S, [0.0; 2]),
        initial,
    );
    let mut io = XyIo {
        dac: Dac {
            fail: [false; 2],
            codes: [DacCode::SAFE; 2],
        },
        dac_channels: Axis::ALL,
        sensor: Sensor {
            readings: [Some(0.0); 2],
        },
    };
    let mut last_v = initial;
    let mut frozen = [(0u32, 0.0f32); 2];
    let started = std::time::Instant::now();
    for tick in 0..TICKS {
        // Between two ticks.
        if rng.chance(5e-5) {
            let (settings, in_force, refused) = random_settings(&mut rng, &bases);
            tally.refused_axes += refused;
            tally.swaps += 1;
            lp.set_settings(settings);
            limits = in_force;
        }
        if rng.chance(2e-4) {
            let mode = [
                ServoMode::OpenLoop,
                ServoMode::Feedforward,
                ServoMode::Feedback,
                ServoMode::FeedforwardFeedback,
            ][rng.below(4) as usize];
            // Refused without a servo on both axes: nothing changes.
            let _ = lp.set_control_mode(mode);
        }
        if rng.chance(2e-4) {
            lp.set_feedforward(
                [
                    Feedforward::Compensator,
                    Feedforward::Linear,
                    Feedforward::OpenLoop,
                ][rng.below(3) as usize],
            );
        }
        if rng.chance(5e-4) {
            let program = random_program(&mut rng, &mut lp.reference);
            lp.reference.set_program(program);
        }
        if lp.reference.program() == Program::Streamed && rng.chance(0.95) {
            let _ = lp
                .reference
                .push_setpoint([rng.hostile_value(), rng.hostile_value()]);
        }
        let safe = lp.mode() != Mode::Running;
        if (safe && rng.chance(0.02)) || rng.chance(1e-5) {
            lp.rearm();
        }
        // The tick.
        for i in 0..2 {
            io.sensor.readings[i] = random_reading(&mut rng, last_v[i], tick, &mut frozen[i]);
            io.dac.fail[i] = rng.chance(1e-4);
        }
        let report = lp.tick(&mut io, rng.chance(1e-5));
        lp.frames.discard();

        tally.safe_ticks += u64::from(report.mode != Mode::Running);
        tally.ticks_by_feedforward[lp.feedforward() as usize] += 1;
        tally.ticks_with_feedback += u64::from(lp.control_mode().feedback());
        for i in 0..2 {
            let (was, now) = (last_v[i], report.applied_v[i]);
            let InForce { window, bound_v } = limits[i];
            if !(now.is_finite() && (HARDWARE_V.0..=HARDWARE_V.1).contains(&now)) {
                tally.other_violations += 1;
                tally.violation(format!(
                    "tick {tick} axis {i}: {now} V outside the hardware"
                ));
            }
            let (before, after) = (distance(window, was), distance(window, now));
            if after > before || (before == 0.0 && after > 0.0) {
                tally.window_violations += 1;
                tally.violation(format!(
                    "tick {tick} axis {i}: {was} -> {now} V, window {window:?}"
                ));
            }
            tally.ticks_slewing_in += u64::from(before > 0.0);
            if exceeds(now, was, bound_v) || (f64::from(now) - f64::from(was)).abs() > bound_v {
                tally.slew_violations += 1;
                tally.violation(format!(
                    "tick {tick} axis {i}: {was} -> {now} V, bound {bound_v} V"
                ));
            }
            let fraction = (f64::from(now) - f64::from(was)).abs() / bound_v;
            tally.largest_step_fraction = tally.largest_step_fraction.max(fraction);
        }
        last_v = report.applied_v;
    }
    let counters = lp.counters();
    let guard = Axis::ALL.map(|a| lp.guard(a).counters());
    println!(
        "adversarial tick run: {TICKS} ticks, {} window violations, {} slew violations",
        tally.window_violations, tally.slew_violations
    );
    println!(
        "  {:.1} s; {} parameter swaps ({} random axes refused), {} ticks slewing into a new \
         window, {} ticks safe, ticks by feed-forward (compensator, linear, open loop) {:?}, \
         with feedback {}, largest step {:.7} of slew·T",
        started.elapsed().as_secs_f64(),
        tally.swaps,
        tally.refused_axes,
        tally.ticks_slewing_in,
        tally.safe_ticks,
        tally.ticks_by_feedforward,
        tally.ticks_with_feedback,
        tally.largest_step_fraction,
    );
    println!("  loop {counters:?}");
    println!("  guard x {:?}", guard[0]);
    println!("  guard y {:?}", guard[1]);
    assert!(
        tally.window_violations == 0 && tally.slew_violations == 0 && tally.other_violations == 0,
        "{tally:#?}"
    );
    // The run reached what it is meant to: every kind of event, slews into new windows, steps
    // at the limit.
    assert!(
        tally.swaps > 100 && tally.ticks_slewing_in > 1_000,
        "{tally:?}"
    );
    assert!(tally.ticks_by_feedforward.iter().all(|&t| t > TICKS / 20));
    assert!(tally.ticks_with_feedback > TICKS / 50);
    assert!(tally.largest_step_fraction > 0.999_99);
    assert!(counters.overruns > 0 && counters.sensor_errors > 0 && counters.dac_errors > 0);
    assert!(counters.stuck_readings > 0 && counters.non_finite_readings > 0);
    for g in guard {
        assert!(g.non_finite > 0 && g.window_clamped > 0 && g.slew_limited > 0);
        assert!(g.window_entry > 0);
    }
}
