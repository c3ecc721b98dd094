//! Accuracy of the f32 core against the independent f64 reference (tests/src/lib.rs: RK4 in time at
//! a step 64–100× finer than the sample period, no core code).
//!
//! Criterion: relative RMS error ≤ 1e-4 of the output span at the loop period, for n = 1,
//! 1.5, 2, 3 and for the dynamic NAC2024 model sampled at 2.56 MHz with 10–200 kHz sines.
//! Run with `-- --nocapture` to see the measured figures (the README quotes them).

use integration_tests::fixtures;
use integration_tests::reference::{self, BoucWen64};
use piezo_core::{BoucWen, BoucWenParams, DynamicModel, ModelState, StaticMap, StaticModel};
use std::f64::consts::PI;

const TOLERANCE: f64 = 1e-4;

struct StaticCase {
    name: &'static str,
    params: BoucWenParams,
    map: StaticMap,
}

/// Stage-like sets: 0–100 V, k1 = 0.4 µm/V, hysteresis state bounded near 12 V-equivalents
/// (≈ 12 % of the stroke), one per exponent, plus seed 001's published Case I set.
fn static_cases() -> Vec<StaticCase> {
    let map = |k2: f32| StaticMap {
        k1_m_per_v: 0.4e-6,
        k2_m_per_h: k2,
        offset_m: 0.0,
    };
    let p = |a, beta, gamma, n| BoucWenParams { a, beta, gamma, n };
    vec![
        StaticCase {
            name: "n=1",
            params: p(0.3, 0.02, 0.005, 1.0),
            map: map(-0.4e-6),
        },
        StaticCase {
            name: "n=1.5",
            params: p(0.3, 0.006, 0.001_22, 1.5),
            map: map(-0.4e-6),
        },
        StaticCase {
            name: "n=2",
            params: p(0.3, 0.0015, 0.000_583, 2.0),
            map: map(-0.4e-6),
        },
        StaticCase {
            name: "n=3 (A<0)",
            params: p(-0.3, 1.5e-4, -2.36e-5, 3.0),
            map: map(0.4e-6),
        },
    ]
}

fn run_static(model: &StaticModel, inputs: &[f64]) -> Vec<f64> {
    let mut state = ModelState::at_rest(inputs[0] as f32);
    inputs
        .iter()
        .map(|&u| f64::from(model.step(&mut state, u as f32)))
        .collect()
}

fn reference_static(case: &StaticCase, inputs: &[f64], period: f64, substeps: usize) -> Vec<f64> {
    let bw = BoucWen64 {
        a: f64::from(case.params.a),
        beta: f64::from(case.params.beta),
        gamma: f64::from(case.params.gamma),
        n: f64::from(case.params.n),
    };
    let h = reference::bouc_wen_states(bw, inputs, period, substeps);
    inputs
        .iter()
        .zip(&h)
        .map(|(&u, &h)| f64::from(case.map.k1_m_per_v) * u + f64::from(case.map.k2_m_per_h) * h)
        .collect()
}

/// Loop period 100 µs (10 kHz). Three inputs: a 1 Hz full-stroke sine (slow, 10 000 samples per
/// period), a decaying 50 Hz sine (200 samples per period, nested inner loops, zero crossings of h
/// inside samples) and a three-tone multisine.
fn static_inputs(period: f64) -> Vec<(&'static str, Vec<f64>)> {
    let sine: Vec<f64> = (0..20_000)
        .map(|k| 50.0 - 50.0 * (2.0 * PI * 1.0 * k as f64 * period).cos())
        .collect();
    let decaying: Vec<f64> = (0..4_000)
        .map(|k| {
            let t = k as f64 * period;
            50.0 + 50.0 * (-t / 0.15).exp() * (2.0 * PI * 50.0 * t).sin()
        })
        .collect();
    let multisine: Vec<f64> = (0..10_000)
        .map(|k| {
            let t = k as f64 * period;
            50.0 + 25.0 * (2.0 * PI * 3.0 * t).sin()
                + 15.0 * (2.0 * PI * 17.0 * t + 1.0).sin()
                + 8.0 * (2.0 * PI * 61.0 * t + 2.0).sin()
        })
        .collect();
    vec![
        ("1 Hz sine", sine),
        ("decaying 50 Hz", decaying),
        ("multisine", multisine),
    ]
}

#[test]
fn static_models_match_the_f64_reference_at_the_loop_period() {
    let period = 1e-4;
    let mut worst = 0.0f64;
    for case in static_cases() {
        let model = StaticModel::new(BoucWen::new(case.params).unwrap(), case.map).unwrap();
        for (input_name, inputs) in static_inputs(period) {
            let core = run_static(&model, &inputs);
            let reference = reference_static(&case, &inputs, period, 64);
            let error = reference::relative_rms_error(&core, &reference);
            println!(
                "accuracy static {:<10} {:<15} relative RMS error {:.2e}",
                case.name, input_name, error
            );
            assert!(
                error <= TOLERANCE,
                "{} / {}: relative RMS error {error:.3e} > {TOLERANCE:e}",
                case.name,
                input_name
            );
            worst = worst.max(error);
        }
    }
    println!("accuracy static worst relative RMS error {worst:.2e}");
}

#[test]
fn seed001_case1_matches_the_f64_reference() {
    // Seed 001: u = 10 − 10·cos(4πt), N = 10 000 samples over 1 s, Case I parameters (y in metres).
    let (params, map) = fixtures::seed001_case1();
    let case = StaticCase {
        name: "seed 001 I",
        params,
        map,
    };
    let period = 1e-4;
    let inputs: Vec<f64> = (0..10_000)
        .map(|k| 10.0 - 10.0 * (4.0 * PI * k as f64 * period).cos())
        .collect();
    let model = StaticModel::new(BoucWen::new(case.params).unwrap(), case.map).unwrap();
    let core = run_static(&model, &inputs);
    let reference = reference_static(&case, &inputs, period, 64);
    let error = reference::relative_rms_error(&core, &reference);
    println!("accuracy static seed-001-I    2 Hz cosine    relative RMS error {error:.2e}");
    assert!(error <= TOLERANCE, "relative RMS error {error:.3e}");
}

#[test]
fn nac2024_dynamic_model_matches_the_f64_reference_at_2_56_mhz() {
    let (bw_params, msd) = fixtures::nac2024();
    let period = 1.0 / 2.56e6;
    // The published set has β + γ < 0: valid over ±10 V, where |h| stays below 10.
    let bw = BoucWen::with_input_range(bw_params, -10.0, 10.0, 10.0).unwrap();
    let model = DynamicModel::new(bw, msd, period as f32).unwrap();
    let (bw64, msd64) = reference::nac2024();
    let mut worst = 0.0f64;
    for f_khz in [
        10.0f64, 20.0, 40.0, 60.0, 80.0, 100.0, 120.0, 140.0, 160.0, 180.0, 200.0,
    ] {
        let f = f_khz * 1e3;
        let samples = ((6.0 / f) / period).max(1024.0_f64) as usize;
        let inputs: Vec<f64> = (0..samples)
            .map(|k| 9.738 * (2.0 * PI * f * k as f64 * period).sin())
            .collect();
        let mut state = model.at_rest(0.0);
        let core: Vec<f64> = inputs
            .iter()
            .map(|&u| f64::from(model.step(&mut state, u as f32)))
            .collect();
        let reference = reference::dynamic_positions(bw64, msd64, &inputs, period, 100);
        let error = reference::relative_rms_error(&core, &reference);
        println!("accuracy dynamic NAC2024 {f_khz:>5} kHz sine at 2.56 MHz relative RMS error {error:.2e}");
        assert!(
            error <= TOLERANCE,
            "{f_khz} kHz: relative RMS error {error:.3e}"
        );
        worst = worst.max(error);
    }
    println!("accuracy dynamic worst relative RMS error {worst:.2e}");
}

#[test]
fn nac2024_dynamic_model_matches_at_a_quasi_static_rate() {
    // 1 kHz sine sampled at 100 kHz: ωn·T ≈ 10, far from the 2.56 MHz regime.
    let (bw_params, msd) = fixtures::nac2024();
    let period = 1e-5;
    let bw = BoucWen::with_input_range(bw_params, -10.0, 10.0, 10.0).unwrap();
    let model = DynamicModel::new(bw, msd, period as f32).unwrap();
    let inputs: Vec<f64> = (0..300)
        .map(|k| 9.738 * (2.0 * PI * 1e3 * k as f64 * period).sin())
        .collect();
    let mut state = model.at_rest(0.0);
    let core: Vec<f64> = inputs
        .iter()
        .map(|&u| f64::from(model.step(&mut state, u as f32)))
        .collect();
    let (bw64, msd64) = reference::nac2024();
    // 2000 reference steps per sample keep ωn·dt ≈ 0.005.
    let reference = reference::dynamic_positions(bw64, msd64, &inputs, period, 2000);
    let error = reference::relative_rms_error(&core, &reference);
    println!("accuracy dynamic NAC2024 1 kHz sine at 100 kHz relative RMS error {error:.2e}");
    assert!(error <= TOLERANCE, "relative RMS error {error:.3e}");
}

#[test]
fn seed001_asymmetric_model_matches_the_f64_reference() {
    // Case II: δ = −1.95e-2 (φ = 0), the published input. The δ-term carries h past the plain
    // Bouc-Wen bound (|h| = 0.4245); the model must follow it there.
    let (params, map) = fixtures::seed001_case1();
    let delta = -1.95e-2;
    let period = 1e-4;
    let inputs: Vec<f64> = (0..10_000)
        .map(|k| 10.0 - 10.0 * (4.0 * PI * k as f64 * period).cos())
        .collect();
    let model = StaticModel::asymmetric(
        BoucWen::new(params).unwrap(),
        map,
        piezo_core::Asymmetry {
            delta_per_v_s: delta,
            input_shift_s: 0.0,
        },
        period as f32,
    )
    .unwrap();
    let core = run_static(&model, &inputs);
    let bw = BoucWen64 {
        a: f64::from(params.a),
        beta: f64::from(params.beta),
        gamma: f64::from(params.gamma),
        n: f64::from(params.n),
    };
    let h = reference::asymmetric_states(bw, f64::from(delta), &inputs, period, 64);
    let peak = h.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let reference: Vec<f64> = inputs
        .iter()
        .zip(&h)
        .map(|(&u, &h)| f64::from(map.k1_m_per_v) * u + f64::from(map.k2_m_per_h) * h)
        .collect();
    let error = reference::relative_rms_error(&core, &reference);
    println!(
        "accuracy asymmetric seed-001-II 2 Hz cosine relative RMS error {error:.2e} (reference peak |h| {peak:.4})"
    );
    assert!(
        peak > 0.4245,
        "the reference should pass the plain bound: {peak}"
    );
    assert!(error <= TOLERANCE, "relative RMS error {error:.3e}");
}
