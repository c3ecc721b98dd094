//! The loop's tick against a record of what it commanded before its per-tick work was cut down:
//! `tests/data/tick_record.txt` holds, for four runs of [`TwoAxisLoop::tick`] on the simulated
//! stage (`plant::XyPlant`, the bench's stage) from rest, every tick's two sensor codes, the
//! reference of the tick and the two voltages the tick applied (f32 bits). The test feeds the
//! same sensor codes and references to today's loop (the readings replayed, the references
//! streamed, so that both see the same inputs) and compares the voltages.
//!
//! Runs (2 000 ticks each, the demo program: x sine, y triangle, 15 µm at 10 Hz):
//! - `feedforward`: the compensator alone;
//! - `switching`: feedforward, feedback on at tick 400, off at 1 200 (the fade-out), on at 1 600;
//! - `effects`: creep, even term, 2-sample delay, drift and coupling (as
//!   `params/xy-stage-effects.toml`), feedforward + feedback;
//! - `mode`: the same with a 2.2 kHz mode (ζ = 0.05) on x, feedforward + feedback.
//!
//! Tolerance: the voltages agree within [`TOLERANCE_V`] (0.5 % of one DAC step at the stack:
//! 24 V/V × 76.3 µV = 1.83 mV). What may differ from the recorded code is f32 rounding in the
//! model advanced by the applied voltage (the small-step series instead of the closed form:
//! a few f32 ulps of h). A change of the compensator's solve that moves its voltage within the
//! solve's own tolerance (1e-7 of the window, 1.2e-5 V) is not covered: the `effects` and `mode`
//! runs pass ticks ≈ 1 150–1 180, near the top of x's stroke, where such differences grow to
//! ≈ 0.4 V (taking the general Newton solve's last iterate instead of the one before it moves
//! them by 0.32 V there). Such a change is checked per solve against the general solve
//! (`piezo_core` compensator tests) and the record rewritten. The reference generator is checked on its own
//! (`reference::tests::sine_in_cycles_is_within_its_stated_error`). `PIEZO_TICK_RECORD_WRITE=1`
//! rewrites the record with the loop as it is.

use std::cell::Cell;
use std::fmt::Write as _;

use piezo_core::effects::EffectParams;
use piezo_core::ServoMode;
use piezo_firmware::codes::{AdcCode, DacCode};
use piezo_firmware::converter::{AdcRead, DacWrite, ErrorType};
use piezo_firmware::demo;
use piezo_firmware::params::{AxisParams, AMPLIFIER_GAIN_V_PER_V, AXES, SAMPLE_PERIOD_S};
use piezo_firmware::plant::{plant_io, XyPlant};
use piezo_firmware::reference::{Program, ReferenceGenerator};
use piezo_firmware::xy_loop::{AdcSensor, Axis, Feedforward, LoopSettings, TwoAxisLoop, XyIo};

/// Ticks per run.
const TICKS: usize = 2_000;
/// Largest difference accepted between a recorded and a recomputed voltage \[V\].
const TOLERANCE_V: f32 = 1e-5;
/// Ticks at the end of a record left out of the comparison: the inverse effect chain reads the
/// reference up to its lead (2 ticks here) ahead of the tick.
const TAIL: usize = 8;

const RECORD: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/tick_record.txt");

fn effects(axis: usize, k1: f32, mode: bool) -> EffectParams {
    EffectParams {
        creep_gain_m_per_v: [0.03 * k1, 0.0, 0.0],
        creep_time_constant_s: [0.2, 0.0, 0.0],
        even_coefficient_m_per_v2: 1e-10,
        even_center_v: 60.0,
        delay_s: 2.0 * SAMPLE_PERIOD_S,
        drift_rate_m_per_s: -0.2e-6,
        coupling: if axis == 0 { 0.02 } else { -0.015 },
        mode_frequency_hz: if mode && axis == 0 { 2200.0 } else { 0.0 },
        mode_damping: if mode && axis == 0 { 0.05 } else { 0.0 },
        ..EffectParams::default()
    }
}

/// The runs: name, parameter set, control mode from each tick on.
/// A run: name, parameter set, the control mode to switch to before a tick.
type Run = (
    &'static str,
    [AxisParams; 2],
    fn(usize) -> Option<ServoMode>,
);

fn runs() -> Vec<Run> {
    let with = |mode: bool| {
        let mut axes = AXES;
        for (i, a) in axes.iter_mut().enumerate() {
            a.effects = effects(i, a.static_map.k1_m_per_v, mode);
        }
        axes
    };
    let both = |k: usize| (k == 0).then_some(ServoMode::FeedforwardFeedback);
    vec![
        ("feedforward", AXES, |_| None),
        ("switching", AXES, |k| match k {
            400 | 1_600 => Some(ServoMode::FeedforwardFeedback),
            1_200 => Some(ServoMode::Feedforward),
            _ => None,
        }),
        ("effects", with(false), both),
        ("mode", with(true), both),
    ]
}

/// Sensor codes replayed from a record (x then y each tick).
struct Replay<'a> {
    codes: &'a [[u16; 2]],
    next: usize,
}

impl ErrorType for Replay<'_> {
    type Error = core::convert::Infallible;
}

impl AdcRead for Replay<'_> {
    type Channel = Axis;
    fn read_code(&mut self, channel: Axis) -> Result<AdcCode, Self::Error> {
        let code = self.codes[self.next][channel.index()];
        if channel == Axis::Y {
            self.next += 1;
        }
        Ok(AdcCode(code))
    }
}

struct Kept;

impl ErrorType for Kept {
    type Error = core::convert::Infallible;
}

impl DacWrite for Kept {
    type Channel = Axis;
    fn write_code(&mut self, _: Axis, _: DacCode) -> Result<(), Self::Error> {
        Ok(())
    }
}

fn new_loop(axes: &[AxisParams; 2]) -> TwoAxisLoop {
    let settings = LoopSettings::from_params(axes, AMPLIFIER_GAIN_V_PER_V, SAMPLE_PERIOD_S)
        .expect("the run's parameter set is valid");
    let reference = ReferenceGenerator::new(demo::program(), SAMPLE_PERIOD_S, [0.0; 2]);
    TwoAxisLoop::new(settings, Feedforward::Compensator, reference, [0.0; 2])
}

/// One tick of a record: sensor codes, reference \[m\], applied voltages \[V\].
type Row = ([u16; 2], [f32; 2], [f32; 2]);

/// A run on the simulated stage.
fn record(axes: &[AxisParams; 2], mode: fn(usize) -> Option<ServoMode>) -> Vec<Row> {
    let plant = Cell::new(XyPlant::from_params(SAMPLE_PERIOD_S).unwrap());
    let mut io = plant_io(&plant, demo::sensor_scale().unwrap());
    let mut lp = new_loop(axes);
    (0..TICKS)
        .map(|k| {
            if let Some(m) = mode(k) {
                lp.set_control_mode(m).unwrap();
            }
            let codes = [Axis::X, Axis::Y].map(|a| plant.get().sensor_code(a).0);
            let report = lp.tick(&mut io, false);
            let mut p = plant.get();
            p.advance();
            plant.set(p);
            lp.frames.discard();
            (codes, report.reference_m, report.applied_v)
        })
        .collect()
}

/// The voltages of a replay of a record's readings and references.
fn replay(
    axes: &[AxisParams; 2],
    mode: fn(usize) -> Option<ServoMode>,
    rows: &[Row],
) -> Vec<[f32; 2]> {
    let codes: Vec<[u16; 2]> = rows.iter().map(|r| r.0).collect();
    let codes = &codes[..];
    let mut io = XyIo {
        dac: Kept,
        dac_channels: Axis::ALL,
        sensor: AdcSensor {
            adc: Replay { codes, next: 0 },
            channels: Axis::ALL,
            scale: demo::sensor_scale().unwrap(),
        },
    };
    let mut lp = new_loop(axes);
    lp.reference.set_program(Program::Streamed);
    let mut streamed = 0;
    (0..codes.len() - TAIL)
        .map(|k| {
            if let Some(m) = mode(k) {
                lp.set_control_mode(m).unwrap();
            }
            // The references up to the chain's lead ahead of this tick.
            while streamed <= k + lp.lead_ticks() as usize {
                lp.reference.push_setpoint(rows[streamed].1).unwrap();
                streamed += 1;
            }
            let report = lp.tick(&mut io, false);
            assert_eq!(report.reference_m, rows[k].1, "tick {k}: the reference");
            lp.frames.discard();
            assert_eq!(lp.counters().faults(), 0, "tick {k}: a fault");
            report.applied_v
        })
        .collect()
}

/// `name -> rows` of the record file.
fn read_record() -> Vec<(String, Vec<Row>)> {
    let text = std::fs::read_to_string(RECORD).unwrap_or_else(|e| panic!("{RECORD}: {e}"));
    let mut runs: Vec<(String, Vec<_>)> = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let at = || format!("{RECORD}:{}", n + 1);
        if let Some(name) = line.strip_prefix("run ") {
            runs.push((name.to_string(), Vec::new()));
            continue;
        }
        if line.starts_with('#') || line.is_empty() {
            continue;
        }
        let f: Vec<&str> = line.split_whitespace().collect();
        assert_eq!(f.len(), 6, "{}: expected 6 fields", at());
        let code = |s: &str| u16::from_str_radix(s, 16).unwrap_or_else(|e| panic!("{}: {e}", at()));
        let volts = |s: &str| {
            f32::from_bits(u32::from_str_radix(s, 16).unwrap_or_else(|e| panic!("{}: {e}", at())))
        };
        let run = runs
            .last_mut()
            .unwrap_or_else(|| panic!("{}: row before a run", at()));
        run.1.push((
            [code(f[0]), code(f[1])],
            [volts(f[2]), volts(f[3])],
            [volts(f[4]), volts(f[5])],
        ));
    }
    runs
}

#[test]
fn the_tick_commands_the_recorded_voltages() {
    if std::env::var_os("PIEZO_TICK_RECORD_WRITE").is_some() {
        let mut text = String::from(
            "# firmware/tests/tick_exact.rs: per tick the x and y sensor codes (hex), the x and y\n\
             # reference (m) and the x and y applied voltages (V), f32 bits in hex\n",
        );
        for (name, axes, mode) in runs() {
            writeln!(text, "run {name}").unwrap();
            for (c, r, u) in record(&axes, mode) {
                let [r0, r1, u0, u1] = [r[0], r[1], u[0], u[1]].map(f32::to_bits);
                writeln!(
                    text,
                    "{:04x} {:04x} {r0:08x} {r1:08x} {u0:08x} {u1:08x}",
                    c[0], c[1]
                )
                .unwrap();
            }
        }
        std::fs::create_dir_all(std::path::Path::new(RECORD).parent().unwrap()).unwrap();
        std::fs::write(RECORD, text).unwrap();
    }
    let recorded = read_record();
    let runs = runs();
    assert_eq!(recorded.len(), runs.len(), "{RECORD}: runs");
    for ((name, axes, mode), (recorded_name, rows)) in runs.iter().zip(&recorded) {
        assert_eq!(name, recorded_name);
        assert_eq!(rows.len(), TICKS, "{name}: ticks in the record");
        let now = replay(axes, *mode, rows);
        let (mut worst, mut at, mut differ) = (0.0f32, 0, 0);
        for (k, (u, (_, _, old))) in now.iter().zip(rows).enumerate() {
            for i in 0..2 {
                let d = (u[i] - old[i]).abs();
                differ += usize::from(u[i].to_bits() != old[i].to_bits());
                if d > worst || d.is_nan() {
                    (worst, at) = (d, k);
                }
            }
        }
        println!(
            "{name}: max |Δu| = {worst:.3e} V (tick {at}), {differ} of {} voltages not bit-identical",
            2 * now.len()
        );
        assert!(
            worst <= TOLERANCE_V,
            "{name}: tick {at} commands {:?}, the record {:?} (|Δu| = {worst:e} V > {TOLERANCE_V} V)",
            now[at],
            rows[at].2
        );
    }
}
