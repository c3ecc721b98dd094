//! The firmware's two-axis loop (`xy_loop::TwoAxisLoop`, the code the images run) with effects in
//! its parameter set, on the host, against a stage that has those effects: piezo-core's forward
//! chain per axis (`StaticModel` of the xy-stage parameters, then `Effects::forward_z`, the delayed
//! z, drift, and the other axis's delayed z times κ), driven through mock converters (the DAC's
//! 16-bit codes and the amplifier gain as on the board).
//!
//! Per tick k: the loop reads the sensor (the stage output of sample k − 1), computes and writes
//! the command u\[k\]; then the stage takes u\[k\] (as the DAC code gives it) and produces y\[k\].
//! The error of tick k is y\[k\] − r\[k\], r\[k\] the reference the loop reports for tick k.
//!
//! The same loop is run twice on the same stage: with the effects in its parameter set (the
//! inverse chain around the compensator) and ignoring them (the parameter file without
//! `[x.effects]`: the compensator alone). The first must track far better.

use std::cell::Cell;

use piezo_core::effects::{EffectParams, Effects, EffectsState};
use piezo_core::{ModelState, StaticModel};
use piezo_firmware::codes::DacCode;
use piezo_firmware::converter::{DacWrite, ErrorType};
use piezo_firmware::params::{AxisParams, AMPLIFIER_GAIN_V_PER_V, AXES, SAMPLE_PERIOD_S};
use piezo_firmware::reference::{Program, ReferenceGenerator, Wave};
use piezo_firmware::xy_loop::{
    Axis, Feedforward, LoopSettings, Mode, PositionSensor, TwoAxisLoop, XyIo,
};

/// Ticks per run (3 s at 10 kHz) and ticks left out of the statistics (start-up, 0.5 s).
const TICKS: usize = 30_000;
const SETTLE: usize = 5_000;

/// The stage: per axis the core's static model and effect chain, plus the coupling.
struct Stage {
    model: [StaticModel; 2],
    model_state: [ModelState; 2],
    effects: [Effects; 2],
    state: [EffectsState; 2],
}

impl Stage {
    fn new(axes: &[AxisParams; 2]) -> Self {
        let model = [
            axes[0].model(SAMPLE_PERIOD_S).unwrap(),
            axes[1].model(SAMPLE_PERIOD_S).unwrap(),
        ];
        let model_state = [
            ModelState::at_rest(axes[0].limits.output_min_v),
            ModelState::at_rest(axes[1].limits.output_min_v),
        ];
        Self {
            model,
            model_state,
            effects: [
                axes[0].effect_chain(SAMPLE_PERIOD_S).unwrap(),
                axes[1].effect_chain(SAMPLE_PERIOD_S).unwrap(),
            ],
            // At rest at the rest voltage, as the loop assumes (the start rule of every tool).
            state: [
                EffectsState::at_rest(axes[0].limits.output_min_v),
                EffectsState::at_rest(axes[1].limits.output_min_v),
            ],
        }
    }

    /// The output at rest, before the first sample [m].
    fn rest_m(&self) -> [f32; 2] {
        [0, 1].map(|i| self.model[i].output(&self.model_state[i]))
    }

    /// One sample with the DAC codes `codes`: returns y [m] per axis.
    fn advance(&mut self, codes: [DacCode; 2]) -> [f32; 2] {
        for (i, code) in codes.iter().enumerate() {
            let u = code.to_volts() * AMPLIFIER_GAIN_V_PER_V;
            let w = self.model[i].step(&mut self.model_state[i], u);
            self.effects[i].forward_z(&mut self.state[i], self.model_state[i].input_v, w);
        }
        let [ex, ey] = &self.effects;
        let [sx, sy] = &self.state;
        [
            ex.delayed_z(sx) + ex.drift_m(sx) + ex.params().coupling * ex.delayed_z(sy),
            ey.delayed_z(sy) + ey.drift_m(sy) + ey.params().coupling * ey.delayed_z(sx),
        ]
    }
}

struct StageDac<'a>(&'a [Cell<DacCode>; 2]);
struct StageSensor<'a>(&'a [Cell<f32>; 2]);

impl ErrorType for StageDac<'_> {
    type Error = core::convert::Infallible;
}

impl DacWrite for StageDac<'_> {
    type Channel = Axis;
    fn write_code(&mut self, axis: Axis, code: DacCode) -> Result<(), Self::Error> {
        self.0[axis.index()].set(code);
        Ok(())
    }
}

impl ErrorType for StageSensor<'_> {
    type Error = core::convert::Infallible;
}

impl PositionSensor for StageSensor<'_> {
    fn read_m(&mut self, axis: Axis) -> Result<f32, Self::Error> {
        Ok(self.0[axis.index()].get())
    }
}

/// The xy-stage parameter set with `effects(axis, k1)` added to each axis.
fn with_effects(effects: impl Fn(usize, f32) -> EffectParams) -> [AxisParams; 2] {
    let mut axes = AXES;
    for (i, a) in axes.iter_mut().enumerate() {
        a.effects = effects(i, a.static_map.k1_m_per_v);
    }
    axes
}

/// Creep g = 0.03·k1 at τ = 0.2 s, a 2-sample delay, coupling 0.02 (−0.015 on y), an even term
/// 1e-10 m/V² around 60 V and a drift of −0.2 µm/s (the effects lift the output at low voltage:
/// with a positive drift the bottom of the x sine would need less than 0 V by the end).
fn stage_effects(axis: usize, k1: f32) -> EffectParams {
    EffectParams {
        creep_gain_m_per_v: [0.03 * k1, 0.0, 0.0],
        creep_time_constant_s: [0.2, 0.0, 0.0],
        even_coefficient_m_per_v2: 1e-10,
        even_center_v: 60.0,
        delay_s: 2.0 * SAMPLE_PERIOD_S,
        drift_rate_m_per_s: -0.2e-6,
        coupling: if axis == 0 { 0.02 } else { -0.015 },
        ..EffectParams::default()
    }
}

/// x: sine, y: triangle, 20 ± 14 µm at 10 Hz (the QEMU self-check's reference, 1 µm further
/// from 0 V: the effects add up to ≈ 1.5 µm at the bottom, which the window must allow).
fn program() -> Program {
    Program::PerAxis([
        Wave::Sine {
            offset: 20e-6,
            amplitude: 14e-6,
            frequency_hz: 10.0,
        },
        Wave::Triangle {
            offset: 20e-6,
            amplitude: 14e-6,
            frequency_hz: 10.0,
        },
    ])
}

struct Run {
    /// RMS and peak of y[k] − r[k] after SETTLE, per axis [m].
    rms_m: [f64; 2],
    max_m: [f64; 2],
    lead_ticks: u32,
    held: u32,
    limited: u32,
    mode: Mode,
    faults: u32,
}

/// The loop with `loop_axes` (its parameter set) on a stage with `stage_axes`' effects.
fn run(loop_axes: &[AxisParams; 2], stage_axes: &[AxisParams; 2]) -> Run {
    let settings =
        LoopSettings::from_params(loop_axes, AMPLIFIER_GAIN_V_PER_V, SAMPLE_PERIOD_S).unwrap();
    let mut stage = Stage::new(stage_axes);
    let initial = [
        loop_axes[0].limits.output_min_v,
        loop_axes[1].limits.output_min_v,
    ];
    let reference = ReferenceGenerator::new(program(), SAMPLE_PERIOD_S, [0.0; 2]);
    let mut lp = TwoAxisLoop::new(settings, Feedforward::Compensator, reference, initial);
    let codes = [Cell::new(DacCode::SAFE), Cell::new(DacCode::SAFE)];
    let outputs = stage.rest_m().map(Cell::new);
    let mut io = XyIo {
        dac: StageDac(&codes),
        dac_channels: Axis::ALL,
        sensor: StageSensor(&outputs),
    };
    let (mut sum_sq, mut max) = ([0.0f64; 2], [0.0f64; 2]);
    for k in 0..TICKS {
        let report = lp.tick(&mut io, false);
        let y = stage.advance([codes[0].get(), codes[1].get()]);
        for i in 0..2 {
            outputs[i].set(y[i]);
        }
        if k >= SETTLE {
            for i in 0..2 {
                let e = f64::from(y[i]) - f64::from(report.reference_m[i]);
                sum_sq[i] += e * e;
                max[i] = max[i].max(e.abs());
            }
        }
    }
    let n = (TICKS - SETTLE) as f64;
    let counters = lp.counters();
    Run {
        rms_m: sum_sq.map(|s| (s / n).sqrt()),
        max_m: max,
        lead_ticks: lp.lead_ticks(),
        held: counters.held_references,
        limited: counters.compensator_limited,
        mode: lp.mode(),
        faults: counters.faults(),
    }
}

fn report(name: &str, r: &Run) {
    println!(
        "{name}: x rms {:.2} nm max {:.2} nm | y rms {:.2} nm max {:.2} nm | lead {} ticks, \
         held {}, limited {}, faults {}, {:?}",
        r.rms_m[0] * 1e9,
        r.max_m[0] * 1e9,
        r.rms_m[1] * 1e9,
        r.max_m[1] * 1e9,
        r.lead_ticks,
        r.held,
        r.limited,
        r.faults,
        r.mode
    );
}

#[test]
fn loop_with_the_effects_tracks_a_stage_that_has_them() {
    let stage = with_effects(stage_effects);
    let with = run(&stage, &stage);
    let ignoring = run(&AXES, &stage);
    report("loop with the effects", &with);
    report("loop ignoring them  ", &ignoring);
    for r in [&with, &ignoring] {
        assert_eq!(r.mode, Mode::Running);
        assert_eq!(r.faults, 0);
        assert_eq!(r.held, 0);
    }
    assert_eq!(with.lead_ticks, 2);
    assert_eq!(ignoring.lead_ticks, 0);
    for i in 0..2 {
        // With: the DAC's 16-bit code (1.8 mV, 0.65 nm) and f32 rounding are what is left.
        assert!(
            with.rms_m[i] < 2e-9 && with.max_m[i] < 5e-9,
            "axis {i}: {:e} {:e}",
            with.rms_m[i],
            with.max_m[i]
        );
        assert!(
            ignoring.rms_m[i] > 100e-9,
            "axis {i}: {:e}",
            ignoring.rms_m[i]
        );
        assert!(
            with.rms_m[i] < 0.05 * ignoring.rms_m[i],
            "axis {i}: {:e} vs {:e}",
            with.rms_m[i],
            ignoring.rms_m[i]
        );
    }
}

#[test]
fn loop_with_a_mode_and_a_fractional_delay_tracks_too() {
    // A 1.5 kHz ζ = 0.3 mode and 2.5 samples of delay on top (lead 1 + 3 = 4 ticks).
    let stage = with_effects(|i, k1| EffectParams {
        mode_frequency_hz: 1500.0,
        mode_damping: 0.3,
        delay_s: 2.5 * SAMPLE_PERIOD_S,
        ..stage_effects(i, k1)
    });
    let with = run(&stage, &stage);
    let ignoring = run(&AXES, &stage);
    report("mode, loop with the effects", &with);
    report("mode, loop ignoring them  ", &ignoring);
    assert_eq!(with.lead_ticks, 4);
    assert_eq!((with.faults, with.held), (0, 0));
    for i in 0..2 {
        // The triangle's corners excite the mode inverse's central differences: a looser bound.
        assert!(with.rms_m[i] < 5e-9, "axis {i}: {:e}", with.rms_m[i]);
        assert!(with.rms_m[i] < 0.05 * ignoring.rms_m[i]);
    }
}

#[test]
fn identity_effects_run_no_chain() {
    let settings =
        LoopSettings::from_params(&AXES, AMPLIFIER_GAIN_V_PER_V, SAMPLE_PERIOD_S).unwrap();
    assert!(settings.axes.iter().all(|a| a.effects().is_identity()));
    let reference = ReferenceGenerator::new(program(), SAMPLE_PERIOD_S, [0.0; 2]);
    let lp = TwoAxisLoop::new(settings, Feedforward::Compensator, reference, [0.0; 2]);
    assert!(lp.inverse_chain().is_none());
    // The linear baseline ignores the effects.
    let stage = with_effects(stage_effects);
    let settings =
        LoopSettings::from_params(&stage, AMPLIFIER_GAIN_V_PER_V, SAMPLE_PERIOD_S).unwrap();
    let reference = ReferenceGenerator::new(program(), SAMPLE_PERIOD_S, [0.0; 2]);
    let lp = TwoAxisLoop::new(settings, Feedforward::Linear, reference, [0.0; 2]);
    assert!(lp.inverse_chain().is_none());
}
