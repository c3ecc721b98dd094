//! Samples per second, single core: the f64 reference plants (`host_sim::sim::simulate`) and the
//! `piezo-core` f32 models and compensator over long records.
//!
//! `cargo bench -p host-sim --bench throughput -- --quick` (criterion's throughput line, elem/s,
//! is samples per second). The static-model records and sets are the ones
//! `host-sim/evidence/peer_static.py` runs in numba (`host-sim/evidence/host_speed.sh` prints both).

use criterion::{black_box, criterion_main, Criterion, Throughput};
use host_sim::effects::Effects;
use host_sim::plant::{Nac2024, XyStage};
use host_sim::signal::{PeriodicPiecewise, Signal, Sine};
use host_sim::sim::{simulate, SimSettings};
use piezo_core::{BoucWen, BoucWenParams, CompensatorState, ModelState, StaticMap, StaticModel};

const CORE_SAMPLES: usize = 1_000_000;

fn plants(c: &mut Criterion) {
    let mut g = c.benchmark_group("plant");
    g.sample_size(10);
    // XY stage: 2 Hz triangle 10-110 V on both axes, 0.5 s at 10 kHz.
    let xy = XyStage::default();
    let n = 5_000;
    g.throughput(Throughput::Elements(n as u64));
    g.bench_function("xy_stage_triangle_10kHz", |b| {
        b.iter(|| {
            let sig = || {
                Box::new(PeriodicPiecewise::triangle(10.0, 110.0, 2.0).unwrap()) as Box<dyn Signal>
            };
            simulate(
                &xy,
                vec![sig(), sig()],
                &Effects::default(),
                &SimSettings::new(10_000.0, 0.5),
            )
            .unwrap()
        })
    });
    // NAC2024: 100 kHz sine of 9.738 V, 1 ms at 2.56 MHz.
    let nac = Nac2024::published();
    let n = 2_560;
    g.throughput(Throughput::Elements(n as u64));
    g.bench_function("nac2024_sine_100kHz_2.56MHz", |b| {
        b.iter(|| {
            let s = Sine {
                amplitude_v: 9.738,
                offset_v: 0.0,
                frequency_hz: 100e3,
                phase_rad: 0.0,
            };
            simulate(
                &nac,
                vec![Box::new(s)],
                &Effects::default(),
                &SimSettings::new(2.56e6, 1e-3),
            )
            .unwrap()
        })
    });
    g.finish();
}

fn triangle_record(n: usize, low: f32, high: f32, period: usize) -> Vec<f32> {
    (0..n)
        .map(|k| {
            let p = (k % period) as f32 / period as f32;
            let tri = if p < 0.5 { 2.0 * p } else { 2.0 - 2.0 * p };
            low + (high - low) * tri
        })
        .collect()
}

fn core_models(c: &mut Criterion) {
    let mut g = c.benchmark_group("core");
    g.sample_size(10);
    g.throughput(Throughput::Elements(CORE_SAMPLES as u64));
    let u = triangle_record(CORE_SAMPLES, 0.0, 100.0, 5_000);
    let n1 = StaticModel::new(
        BoucWen::new(BoucWenParams {
            a: 0.18522,
            beta: 0.029586,
            gamma: -0.020710,
            n: 1.0,
        })
        .unwrap(),
        StaticMap {
            k1_m_per_v: 6.0e-7,
            k2_m_per_h: -6.0e-7,
            offset_m: 0.0,
        },
    )
    .unwrap();
    g.bench_function("static_n1", |b| {
        b.iter(|| {
            let mut s = ModelState::default();
            let mut acc = 0.0f32;
            for &v in &u {
                acc += n1.step(&mut s, black_box(v));
            }
            acc
        })
    });
    let u20 = triangle_record(CORE_SAMPLES, 0.0, 20.0, 5_000);
    let general = StaticModel::new(
        BoucWen::new(BoucWenParams {
            a: -7.02182e-2,
            beta: 4.45753,
            gamma: 3.49259,
            n: 3.05869,
        })
        .unwrap(),
        StaticMap {
            k1_m_per_v: -3.51711e-7,
            k2_m_per_h: -1.94566e-6,
            offset_m: 0.0,
        },
    )
    .unwrap();
    let n15 = StaticModel::new(
        BoucWen::new(BoucWenParams {
            a: 0.8,
            beta: 0.5,
            gamma: 0.2,
            n: 1.5,
        })
        .unwrap(),
        StaticMap {
            k1_m_per_v: 4.0e-7,
            k2_m_per_h: -4.0e-7,
            offset_m: 0.0,
        },
    )
    .unwrap();
    g.bench_function("static_general_n1.5", |b| {
        b.iter(|| {
            let mut s = ModelState::default();
            let mut acc = 0.0f32;
            for &v in &u20 {
                acc += n15.step(&mut s, black_box(v));
            }
            acc
        })
    });
    g.bench_function("static_general_n3.06", |b| {
        b.iter(|| {
            let mut s = ModelState::default();
            let mut acc = 0.0f32;
            for &v in &u20 {
                acc += general.step(&mut s, black_box(v));
            }
            acc
        })
    });
    let dynamic = host_sim::reproduce::nac_core_model().unwrap();
    let us: Vec<f32> = (0..CORE_SAMPLES)
        .map(|k| 9.738 * (2.0 * std::f32::consts::PI * (k % 256) as f32 / 256.0).sin())
        .collect();
    g.bench_function("dynamic_nac2024_n1.419", |b| {
        b.iter(|| {
            let mut s = dynamic.at_rest(0.0);
            let mut acc = 0.0f32;
            for &v in &us {
                acc += dynamic.step(&mut s, black_box(v));
            }
            acc
        })
    });
    // The compensator's exact bounded inverse (n = 1), on the invertible y axis fallback set of the demo.
    let (comp, _) = host_sim::demo::axis_compensator(&XyStage::default(), 1, 10_000.0).unwrap();
    let r = triangle_record(CORE_SAMPLES, 6.4e-6, 57.6e-6, 5_000);
    g.bench_function("compensator_n1", |b| {
        b.iter(|| {
            let mut s = CompensatorState::at_rest(0.0);
            let mut acc = 0.0f32;
            for &y in &r {
                acc += comp.compensate(&mut s, black_box(y)).voltage_v;
            }
            acc
        })
    });
    g.finish();
}

#[allow(missing_docs)] // generated by the macro
mod group {
    criterion::criterion_group!(benches, super::plants, super::core_models);
}
criterion_main!(group::benches);
