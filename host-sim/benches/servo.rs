//! Per-tick cost of the hybrid controller on the host: the servo's step alone, and the whole
//! feedforward + feedback tick of one axis (compensator, then servo), as the firmware runs it.
//!
//! `cargo bench -p host-sim --bench servo -- --quick` (elem/s: ticks per second).

use criterion::{black_box, criterion_group, criterion_main, Criterion, Throughput};
use piezo_core::servo::{tune, StageDynamics, TuningGoal};
use piezo_core::{CompensatorState, Servo, ServoMode, ServoState};
use piezo_stage::StageFile;

const STACK_FILE: &str = include_str!("../../firmware/params/xy-stage.toml");
const TICKS: usize = 100_000;

fn servo(c: &mut Criterion) {
    let file = StageFile::parse("xy-stage.toml", STACK_FILE).unwrap();
    let valid = file.validate().unwrap();
    let compensator = valid.axes[0].compensator.unwrap();
    let dynamics = StageDynamics::from_model(compensator.model(), 3200.0, 0.035, 1.5e-4);
    let tuning = tune(&dynamics, &TuningGoal::default(), compensator.settings()).unwrap();
    let servo = Servo::new(tuning.params, compensator.settings()).unwrap();
    let gain = valid.axes[0].linear_gain_m_per_v;
    // A 100 Hz sine over 10-90 % of the stroke, the stage following with a small lag.
    let reference: Vec<f32> = (0..=TICKS)
        .map(|k| gain * 120.0 * (0.5 - 0.4 * (k as f32 * 2.0 * std::f32::consts::PI * 0.01).cos()))
        .collect();
    let mut g = c.benchmark_group("servo");
    g.throughput(Throughput::Elements(TICKS as u64));
    g.bench_function("step", |b| {
        b.iter(|| {
            let mut state = ServoState::at_rest(0.0, ServoMode::FeedforwardFeedback);
            let mut acc = 0.0;
            for k in 0..TICKS {
                let ff = reference[k + 1] / gain;
                acc += servo
                    .step(&mut state, reference[k], reference[k] * 0.999, ff)
                    .voltage_v;
            }
            black_box(acc)
        })
    });
    g.bench_function("compensator_then_servo", |b| {
        b.iter(|| {
            let mut cs = CompensatorState::at_rest(0.0);
            let mut state = ServoState::at_rest(0.0, ServoMode::FeedforwardFeedback);
            let mut acc = 0.0;
            for k in 0..TICKS {
                let ff = compensator.compensate(&mut cs, reference[k + 1]).voltage_v;
                acc += servo
                    .step(&mut state, reference[k], reference[k] * 0.999, ff)
                    .voltage_v;
            }
            black_box(acc)
        })
    });
    g.finish();
}

criterion_group!(benches, servo);
criterion_main!(benches);
