//! The exact propagation over zero-order holds (`sim` with `exact_holds`) against the Dormand–Prince
//! path at tight tolerances, and the runs that must keep the Dormand–Prince path.

use piezo_reference::effects::Effects;
use piezo_reference::plant::{AsymmetricStage, Nac2024, Plant, StageCase, XyStage};
use piezo_reference::signal::{Piecewise, Signal, Sine};
use piezo_reference::sim::{simulate, SimOutput, SimSettings};

const FS: f64 = 10_000.0;

/// Per-sample voltages like a compensator's: a raised cosine 0–120 V plus a deterministic
/// pseudo-random ±1.5 V dither, so that every hold starts with a jump on both axes.
fn zoh_voltages(n: usize, freq_hz: f64, seed: u64) -> Vec<f64> {
    let mut state = seed;
    (0..n)
        .map(|k| {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            let r = (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5;
            let t = k as f64 / FS;
            (60.0 - 58.0 * (2.0 * std::f64::consts::PI * freq_hz * t).cos() + 3.0 * r)
                .clamp(0.0, 120.0)
        })
        .collect()
}

fn zoh(v: Vec<f64>) -> Box<dyn Signal> {
    let times = (0..v.len()).map(|k| k as f64 / FS).collect();
    Box::new(Piecewise::new(times, v, true).unwrap())
}

fn effects(specs: &[&str]) -> Effects {
    let mut e = Effects::default();
    for s in specs {
        e.add_spec(s).unwrap();
    }
    e
}

fn run(
    plant: &dyn Plant,
    signals: Vec<Box<dyn Signal>>,
    effects: &Effects,
    n: usize,
    exact: bool,
    rtol: f64,
    atol: f64,
) -> SimOutput {
    let mut settings = SimSettings::new(FS, n as f64 / FS);
    settings.exact_holds = exact;
    settings.ode.rtol = rtol;
    settings.ode.atol = atol;
    simulate(plant, signals, effects, &settings).unwrap()
}

/// Largest |exact − Dormand–Prince| per output over the record, m.
fn max_difference(a: &SimOutput, b: &SimOutput) -> Vec<f64> {
    a.outputs_m
        .iter()
        .zip(&b.outputs_m)
        .map(|(x, y)| {
            x.iter()
                .zip(y)
                .map(|(p, q)| (p - q).abs())
                .fold(0.0, f64::max)
        })
        .collect()
}

/// The exact path against the Dormand–Prince path at rtol 1e-11 on a ZOH record of both axes, and
/// returns the largest difference per axis.
fn compare_xy(stage: &XyStage, specs: &[&str], n: usize, holds_per_sample: u64) -> Vec<f64> {
    let e = effects(specs);
    let signals = || vec![zoh(zoh_voltages(n, 7.0, 1)), zoh(zoh_voltages(n, 5.0, 2))];
    let exact = run(stage, signals(), &e, n, true, 1e-8, 1e-14);
    let dp = run(stage, signals(), &e, n, false, 1e-11, 1e-18);
    assert_eq!(exact.exact_segments, holds_per_sample * (n as u64 - 1));
    assert_eq!(exact.stats.accepted, 0);
    assert_eq!(dp.exact_segments, 0);
    assert!(dp.stats.accepted > 100 * n as u64);
    assert_eq!(exact.inputs_v, dp.inputs_v);
    let d = max_difference(&exact, &dp);
    // For scale: the default tolerances (rtol 1e-8, atol 1e-14) against the tight run.
    let dp_default = run(stage, signals(), &e, n, false, 1e-8, 1e-14);
    let d_default = max_difference(&dp_default, &dp);
    eprintln!(
        "xy-stage {specs:?}: max |exact − DP45(rtol 1e-11)| = {:.2e} m (x), {:.2e} m (y); \
         DP45 rtol 1e-11: {} steps for {} samples; DP45 at the defaults (rtol 1e-8, {} steps): \
         {:.2e} m (x), {:.2e} m (y)",
        d[0], d[1], dp.stats.accepted, n, dp_default.stats.accepted, d_default[0], d_default[1]
    );
    d
}

#[test]
fn xy_stage_with_creep_exact_holds_match_tight_dormand_prince() {
    // 0.2 s: both axes sweep ≈ 80 V and every sample jumps; the outputs reach ≈ 60 µm.
    let d = compare_xy(
        &XyStage::default(),
        &["creep:tau=0.1/1,weight=0.02/0.02"],
        2000,
        1,
    );
    for (axis, d) in d.iter().enumerate() {
        assert!(*d < 1e-15, "axis {axis}: {d:e} m");
    }
}

#[test]
fn xy_stage_variant_and_plant_effects_exact_holds_match_tight_dormand_prince() {
    // Field-dependent stack gain, electrostriction, coupling, a DAC, drift: all still linear over a
    // hold (the DAC is itself a zero-order hold; the rest act on the held drive or the outputs).
    let mut stage = XyStage::paper_opening_at_80v();
    stage.electrostriction_per_v = 1e-3;
    stage.coupling = [0.01, -0.02];
    let specs = [
        "creep:tau=0.05/0.5/5,weight=0.01/0.02/0.01",
        "dac:bits=16,rate_hz=20000",
        "drift:rate=1e-8,amplitude=1e-8,tau=0.1",
    ];
    let d = compare_xy(&stage, &specs, 1000, 2);
    for (axis, d) in d.iter().enumerate() {
        assert!(*d < 1e-15, "axis {axis}: {d:e} m");
    }
}

#[test]
fn nac2024_with_second_mode_exact_holds_match_tight_dormand_prince() {
    let mut plant = Nac2024::published();
    plant.second_mode = Some(Default::default());
    let n = 400;
    let v: Vec<f64> = zoh_voltages(n, 50.0, 3).iter().map(|u| u / 10.0).collect();
    let e = effects(&["creep:tau=1e-3,weight=0.05"]);
    let fs_settings = |exact: bool, rtol: f64, atol: f64| {
        let mut s = SimSettings::new(2.56e6, n as f64 / 2.56e6);
        s.exact_holds = exact;
        s.ode.rtol = rtol;
        s.ode.atol = atol;
        s
    };
    let signal = || {
        let times = (0..n).map(|k| k as f64 / 2.56e6).collect();
        vec![Box::new(Piecewise::new(times, v.clone(), true).unwrap()) as Box<dyn Signal>]
    };
    let exact = simulate(&plant, signal(), &e, &fs_settings(true, 1e-8, 1e-14)).unwrap();
    let dp = simulate(&plant, signal(), &e, &fs_settings(false, 1e-11, 1e-20)).unwrap();
    assert_eq!(exact.exact_segments, n as u64 - 1);
    let d = max_difference(&exact, &dp)[0];
    let peak = dp.outputs_m[0].iter().fold(0.0f64, |m, y| m.max(y.abs()));
    eprintln!("nac2024 + second mode: max |exact − DP45| = {d:.2e} m of {peak:.2e} m");
    assert!(d < 1e-10 * peak, "{d:e} of {peak:e}");
}

#[test]
fn runs_that_are_not_holds_of_a_linear_plant_keep_dormand_prince() {
    let stage = XyStage::default();
    let n = 200;
    let zoh2 = || vec![zoh(zoh_voltages(n, 7.0, 1)), zoh(zoh_voltages(n, 5.0, 2))];
    let creep = "creep:tau=0.1/1,weight=0.02/0.02";
    // The amplifier moves the plant's input during a hold.
    let amp = run(
        &stage,
        zoh2(),
        &effects(&[creep, "amplifier:bandwidth_hz=5000"]),
        n,
        true,
        1e-8,
        1e-14,
    );
    // A smooth input is no hold at all.
    let sine = || {
        Box::new(Sine {
            amplitude_v: 50.0,
            offset_v: 60.0,
            frequency_hz: 20.0,
            phase_rad: 0.0,
        }) as Box<dyn Signal>
    };
    let smooth = run(
        &stage,
        vec![sine(), sine()],
        &effects(&[creep]),
        n,
        true,
        1e-8,
        1e-14,
    );
    // One held input and one smooth one: not every segment is a hold.
    let mixed = run(
        &stage,
        vec![zoh(zoh_voltages(n, 7.0, 1)), sine()],
        &effects(&[creep]),
        n,
        true,
        1e-8,
        1e-14,
    );
    // A plant without a linear form over holds (static Bouc-Wen stage with input shift).
    let asym = AsymmetricStage::new(StageCase::III);
    let v: Vec<f64> = zoh_voltages(n, 7.0, 1).iter().map(|u| u / 20.0).collect();
    let static_stage = run(
        &asym,
        vec![zoh(v)],
        &Effects::default(),
        n,
        true,
        1e-8,
        1e-14,
    );
    for (name, out) in [
        ("amplifier", &amp),
        ("sine", &smooth),
        ("mixed", &mixed),
        ("asymmetric stage", &static_stage),
    ] {
        assert_eq!(out.exact_segments, 0, "{name}");
        assert!(out.stats.accepted > 0, "{name}");
    }
    // Switched off, an eligible run integrates too.
    let off = run(&stage, zoh2(), &effects(&[creep]), n, false, 1e-8, 1e-14);
    assert_eq!(off.exact_segments, 0);
    assert!(off.stats.accepted > 0);
}
