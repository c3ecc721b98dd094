//! The inverse compensator against the independent f64 reference (tests/src/lib.rs), and the
//! build-time checks that decide which parameter sets it accepts.

use integration_tests::fixtures;
use integration_tests::reference::{self, BoucWen64};
use piezo_core::{
    BoucWen, BoucWenParams, CommandStatus, Compensator, CompensatorSettings, CompensatorState,
    DynamicModel, Limits, ParamError, StaticMap, StaticModel,
};
use std::f64::consts::PI;

/// A stage-like set: 0–100 V, y = 0.4 µm/V·u − 0.4 µm·h, n = 1, |h| ≤ 12 (≈ 12 % of the stroke).
fn stage_params() -> (BoucWenParams, StaticMap) {
    (
        BoucWenParams {
            a: 0.3,
            beta: 0.02,
            gamma: 0.005,
            n: 1.0,
        },
        StaticMap {
            k1_m_per_v: 0.4e-6,
            k2_m_per_h: -0.4e-6,
            offset_m: 0.0,
        },
    )
}

fn stage_settings() -> CompensatorSettings {
    CompensatorSettings {
        limits: Limits::new(0.0, 100.0, 1e5),
        sample_period_s: 1e-4,
    }
}

/// The reference plant's output for the commanded voltages (f64, RK4 in time, no core code),
/// starting at rest at 0 V one sample before the first command.
fn reference_stage_output(
    p: BoucWenParams,
    map: StaticMap,
    volts: &[f64],
    period: f64,
) -> Vec<f64> {
    let bw = BoucWen64 {
        a: f64::from(p.a),
        beta: f64::from(p.beta),
        gamma: f64::from(p.gamma),
        n: f64::from(p.n),
    };
    let from_rest: Vec<f64> = std::iter::once(0.0).chain(volts.iter().copied()).collect();
    let h = reference::bouc_wen_states(bw, &from_rest, period, 32);
    volts
        .iter()
        .zip(&h[1..])
        .map(|(&u, &h)| f64::from(map.k1_m_per_v) * u + f64::from(map.k2_m_per_h) * h)
        .collect()
}

#[test]
fn compensated_stage_tracks_the_independent_plant() {
    let (params, map) = stage_params();
    let model = StaticModel::new(BoucWen::new(params).unwrap(), map).unwrap();
    let compensator = Compensator::new(model, stage_settings()).unwrap();
    let period = 1e-4;
    let stroke = 40e-6;
    // 2 Hz cosine between 15 % and 85 % of the stroke, 3 periods, from rest at 0 V. (Beyond that
    // the window edge limits: at 100 V with h ≈ 11 the stage reaches only 35.6 µm = 89 %.)
    let desired: Vec<f64> = (0..15_000)
        .map(|k| stroke * (0.5 - 0.35 * (2.0 * PI * 2.0 * k as f64 * period).cos()))
        .collect();
    let mut state = CompensatorState::at_rest(0.0);
    let volts: Vec<f64> = desired
        .iter()
        .map(|&y| f64::from(compensator.compensate(&mut state, y as f32).voltage_v))
        .collect();
    let plant = reference_stage_output(params, map, &volts, period);
    // Uncompensated: the best linear feed-forward, u = y_d / k1.
    let linear: Vec<f64> = desired.iter().map(|&y| y / 0.4e-6).collect();
    let plant_linear = reference_stage_output(params, map, &linear, period);
    let skip = 5_000; // after the first period (the virgin curve)
    let rms = |a: &[f64], b: &[f64]| piezo_core::metrics::rms(&a[skip..], &b[skip..]).unwrap();
    let compensated = rms(&plant, &desired);
    let uncompensated = rms(&plant_linear, &desired);
    println!(
        "stage compensation: RMS error {:.3} nm compensated, {:.1} nm uncompensated ({:.2e} vs {:.2e} of stroke)",
        compensated * 1e9,
        uncompensated * 1e9,
        compensated / stroke,
        uncompensated / stroke
    );
    assert!(
        compensated <= 1e-5 * stroke,
        "compensated RMS {compensated:e} m"
    );
    assert!(
        uncompensated >= 0.02 * stroke,
        "hysteresis too weak to test: {uncompensated:e} m"
    );
}

#[test]
fn seed001_set_is_a_valid_model_but_not_invertible() {
    // Seed 001, Case I: A < 0 is valid and accepted as a forward model ...
    let (params, map) = fixtures::seed001_case1();
    let model = StaticModel::new(BoucWen::new(params).unwrap(), map).unwrap();
    // ... but its output is not monotone in u right after a reversal: on unloading at the bound,
    // dh/du·k2 = +1.26e-6 m/V outweighs k1 = −0.35e-6 m/V, so y(u) turns back. No inverse exists there.
    let settings = CompensatorSettings {
        limits: Limits::new(0.0, 20.0, 1e4),
        sample_period_s: 1e-4,
    };
    match Compensator::new(model, settings) {
        Err(ParamError::NotInvertible {
            min_slope,
            max_slope,
        }) => {
            assert!(
                min_slope < 0.0 && max_slope > 0.0,
                "{min_slope} {max_slope}"
            );
        }
        other => panic!("expected NotInvertible, got {other:?}"),
    }
    // The forward model shows the turn-back on the published input: y decreases right after the
    // reversal at u = 20 V although k1 < 0 would make it increase.
    let mut state = piezo_core::ModelState::at_rest(0.0);
    let mut previous = 0.0;
    let mut turned_back = false;
    for k in 0..5000 {
        let u = 10.0 - 10.0 * (4.0 * std::f32::consts::PI * k as f32 * 1e-4).cos();
        let y = model.step(&mut state, u);
        if k > 2500 && k < 2700 && y < previous {
            turned_back = true;
        }
        previous = y;
    }
    assert!(
        turned_back,
        "expected a non-monotone branch after the reversal"
    );
}

#[test]
fn nac2024_published_set_is_refused_unbounded_and_accepted_range_limited() {
    let (params, msd) = fixtures::nac2024();
    assert!(matches!(
        BoucWen::new(params),
        Err(ParamError::UnboundedWithoutRange { .. })
    ));
    let message = BoucWen::with_input_range(params, 0.0, 200.0, 10.0)
        .unwrap_err()
        .to_string();
    println!("NAC2024 over 0-200 V: {message}");
    assert!(
        message.contains("spans up to 33.6 V"),
        "the error should state the admissible span: {message}"
    );
    let bw = BoucWen::with_input_range(params, -10.0, 10.0, 10.0).unwrap();
    let model = DynamicModel::new(bw, msd, 1.0 / 2.56e6).unwrap();
    // A window wider than the validated range is refused.
    let wide = CompensatorSettings {
        limits: Limits::new(-20.0, 20.0, f32::INFINITY),
        sample_period_s: 1.0 / 2.56e6,
    };
    assert!(matches!(
        Compensator::for_dynamic(&model, wide),
        Err(ParamError::OutOfRange {
            field: "output_min_v",
            ..
        })
    ));
}

#[test]
fn nac2024_inverse_dynamics_track_a_50_khz_sine_on_the_independent_plant() {
    let (params, msd) = fixtures::nac2024();
    let period = 1.0 / 2.56e6;
    let bw = BoucWen::with_input_range(params, -10.0, 10.0, 10.0).unwrap();
    let model = DynamicModel::new(bw, msd, period as f32).unwrap();
    let settings = CompensatorSettings {
        limits: Limits::new(-10.0, 10.0, f32::INFINITY),
        sample_period_s: period as f32,
    };
    let compensator = Compensator::for_dynamic(&model, settings).unwrap();
    let f = 50e3;
    let amplitude = 15e-9; // about 5.6 V of drive
    let w = 2.0 * PI * f;
    let samples = 2048;
    let time = |k: usize| k as f64 * period;
    let desired: Vec<f64> = (0..samples)
        .map(|k| amplitude * (w * time(k)).sin())
        .collect();
    let mut with_dynamics = CompensatorState::at_rest(0.0);
    let mut quasi_static = CompensatorState::at_rest(0.0);
    let mut volts_dynamic = Vec::with_capacity(samples);
    let mut volts_static = Vec::with_capacity(samples);
    for k in 0..samples {
        let t = time(k);
        let x = amplitude * (w * t).sin();
        let v = amplitude * w * (w * t).cos();
        let a = -amplitude * w * w * (w * t).sin();
        let command = compensator.compensate_with_derivatives(
            &mut with_dynamics,
            x as f32,
            v as f32,
            a as f32,
        );
        assert_eq!(command.status, CommandStatus::Tracking);
        volts_dynamic.push(f64::from(command.voltage_v));
        volts_static.push(f64::from(
            compensator
                .compensate(&mut quasi_static, x as f32)
                .voltage_v,
        ));
    }
    let linear: Vec<f64> = desired.iter().map(|&x| x * 3.725e8).collect();
    let (bw64, msd64) = reference::nac2024();
    let skip = samples / 4;
    let error = |volts: &[f64]| {
        let x = reference::dynamic_positions(bw64, msd64, volts, period, 50);
        piezo_core::metrics::rms(&x[skip..], &desired[skip..]).unwrap() / amplitude
    };
    let (e_dynamic, e_static, e_linear) =
        (error(&volts_dynamic), error(&volts_static), error(&linear));
    println!(
        "NAC2024 50 kHz tracking, RMS error / amplitude: inverse dynamics {e_dynamic:.2e}, \
         quasi-static inverse {e_static:.2e}, linear {e_linear:.2e}"
    );
    // The inverse dynamics use the continuous-time derivatives while the plant sees a sampled
    // voltage held linearly between samples: a small residual remains.
    assert!(e_dynamic < 0.02, "inverse dynamics: {e_dynamic:e}");
    assert!(
        e_dynamic < 0.1 * e_static,
        "dynamics {e_dynamic:e} vs static {e_static:e}"
    );
    assert!(
        e_static < e_linear * 1.5,
        "static {e_static:e} vs linear {e_linear:e}"
    );
}

#[test]
fn swapping_parameters_between_two_samples_keeps_the_voltage_continuous() {
    let (params, map) = stage_params();
    let settings = stage_settings();
    let first = Compensator::new(
        StaticModel::new(BoucWen::new(params).unwrap(), map).unwrap(),
        settings,
    )
    .unwrap();
    let changed = BoucWenParams {
        a: params.a * 1.05,
        beta: params.beta * 0.95,
        ..params
    };
    let second = Compensator::new(
        StaticModel::new(BoucWen::new(changed).unwrap(), map).unwrap(),
        settings,
    )
    .unwrap();
    let mut state = CompensatorState::at_rest(0.0);
    let mut last = 0.0f32;
    let mut largest_step = 0.0f32;
    let mut step_at_swap = 0.0f32;
    for k in 0..4000 {
        let y = 20e-6 - 15e-6 * (2.0 * std::f32::consts::PI * 2.0 * k as f32 * 1e-4).cos();
        let compensator = if k < 2000 { &first } else { &second };
        let v = compensator.compensate(&mut state, y).voltage_v;
        if k > 100 && k != 2000 {
            // Ordinary steps, after the start-up from rest.
            largest_step = largest_step.max((v - last).abs());
        }
        if k == 2000 {
            step_at_swap = (v - last).abs();
        }
        last = v;
    }
    // The swap itself moves the voltage by no more than a few ordinary samples' worth: the state
    // (h and the last voltage) carries over and only the model's small difference shows.
    println!("swap: voltage step {step_at_swap:.4} V, largest ordinary step {largest_step:.4} V");
    assert!(
        step_at_swap <= 2.0 * largest_step,
        "jump of {step_at_swap} V at the swap"
    );
    assert!(step_at_swap <= settings.limits.slew_limit_v_per_s * settings.sample_period_s);
}

#[test]
fn xy_stage_stack_sets_are_invertible_over_their_0_to_120_v_range() {
    // The two-axis stage's stacks (host-sim `XyStage`): n = 1, y = d·(u − h). Over the whole bounded
    // class the unloading slope at |h| = A/(β+γ) exceeds 1 and dy/du would change sign; over 0–120 V
    // the state only reaches the first-loading level, where the map stays monotone.
    for (a, beta, gamma) in [
        (0.18522f32, 0.029586f32, -0.020710f32),
        (0.16792, 0.025721, -0.018005),
    ] {
        let params = BoucWenParams {
            a,
            beta,
            gamma,
            n: 1.0,
        };
        let unrestricted = BoucWen::new(params).unwrap();
        let ranged = BoucWen::with_input_range(params, 0.0, 120.0, 1e3).unwrap();
        let full_bound = a / (beta + gamma);
        assert!((unrestricted.state_bound() - full_bound).abs() < 1e-4 * full_bound);
        // Loading sweep over 120 V from rest: h = (A/κ)(1 − e^(−κ·120)), κ = β + γ.
        let kappa = f64::from(beta + gamma);
        let sweep = f64::from(a) / kappa * (1.0 - (-kappa * 120.0).exp());
        assert!(
            (f64::from(ranged.state_bound()) - sweep).abs() < 1e-4 * sweep,
            "bound {} vs loading sweep {sweep}",
            ranged.state_bound()
        );
        let d = 0.4e-6;
        let map = StaticMap {
            k1_m_per_v: d,
            k2_m_per_h: -d,
            offset_m: 0.0,
        };
        let settings = CompensatorSettings {
            limits: Limits::new(0.0, 120.0, 1e5),
            sample_period_s: 1e-4,
        };
        assert!(matches!(
            Compensator::new(StaticModel::new(unrestricted, map).unwrap(), settings),
            Err(ParamError::NotInvertible { .. })
        ));
        assert!(Compensator::new(StaticModel::new(ranged, map).unwrap(), settings).is_ok());
    }
}
