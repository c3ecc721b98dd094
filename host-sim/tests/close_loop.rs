//! `close-loop` on data with an undeclared effect: host-sim's f64 plants carry the effect, the base
//! model (symmetric Bouc-Wen) does not. For each effect the right one must be named first and the RMS
//! must fall well below the base model's; a slow thermal settling (independent of u) must be named
//! drift, not creep; on effect-free data with a small structured misfit nothing may be added; a fit
//! that runs to the bound of an effect's plausible range must be refused; the stage file written
//! must be one the firmware accepts. The command keeps its report whatever becomes of the stage
//! file, and with `--invertible` writes only sets `host-sim compensate` runs.

use clap::Parser;
use host_sim::cli::{run, Cli};
use host_sim::close_loop::diagnose::EffectKind;
use host_sim::close_loop::report::StepOutcome;
use host_sim::close_loop::select::{Decision, Refusal, Stop};
use host_sim::close_loop::{
    close_loop, read_records, stage_and_io_for, write_stage_file, CloseLoopSettings, Outcome,
};
use host_sim::stage_file::Verdict;
use std::path::{Path, PathBuf};

mod common;
use common::temp;

fn simulate(name: &str, plant: &str, signal: &str, effects: &[&str]) -> PathBuf {
    let out = temp(name);
    let mut args = vec!["host-sim", "simulate", "--plant", plant, "--signal", signal];
    for e in effects {
        args.extend(["--effect", e]);
    }
    let o = out.to_str().unwrap().to_string();
    args.extend(["--out", &o]);
    run(Cli::try_parse_from(args).unwrap()).unwrap();
    out
}

/// A 1 Hz cosine 0–20 V for 3 s at 4 kHz: plant and model both start at rest at 0 V.
const COSINE: &str = "sine:amp=10,offset=10,freq=1,phase_deg=-90,duration=3,rate=4000";

/// A two-tone input around 10 V (6 V at 0.4 Hz, 3 V at 3 Hz: large loops with minor loops inside,
/// and input rates that differ between the tones, so that a rate effect cannot pass for hysteresis),
/// 5 s at 2 kHz. The plant starts its hysteresis from a virgin loading to u(0) = 10 V, the model at
/// rest at 10 V: the first half second (up to the first large reversal) warms the model up, unscored.
const TWO_TONE: &str = "multisine:offset=10,amps=6/3,freqs=0.4/3,duration=5,rate=2000";

/// Sines, ramps and 3 s holds around 10 V (2–18 V), 28 s, written at 1 kHz (first-order hold);
/// returns the signal spec sampling it at 500 Hz.
fn sines_ramps_holds() -> String {
    let fs = 1000.0;
    let mut u: Vec<f64> = Vec::new();
    let hold = |u: &mut Vec<f64>, v: f64, d: f64| u.extend((0..(d * fs) as usize).map(|_| v));
    let ramp = |u: &mut Vec<f64>, a: f64, b: f64, d: f64| {
        let n = (d * fs) as usize;
        u.extend((1..=n).map(|i| a + (b - a) * i as f64 / n as f64));
    };
    let sine = |u: &mut Vec<f64>, amp: f64, f: f64, d: f64| {
        let n = (d * fs) as usize;
        u.extend(
            (1..=n).map(|i| 10.0 + amp * (2.0 * std::f64::consts::PI * f * i as f64 / fs).sin()),
        );
    };
    hold(&mut u, 10.0, 0.2);
    for _ in 0..2 {
        sine(&mut u, 8.0, 1.0, 3.0);
        ramp(&mut u, 10.0, 17.0, 0.7);
        hold(&mut u, 17.0, 3.0);
        ramp(&mut u, 17.0, 3.0, 1.5);
        hold(&mut u, 3.0, 3.0);
        ramp(&mut u, 3.0, 10.0, 0.7);
        sine(&mut u, 6.0, 2.0, 2.0);
    }
    let path = temp("sines_ramps_holds.csv");
    let mut text = String::from("t_s,u_V\n");
    for (k, v) in u.iter().enumerate() {
        text.push_str(&format!("{},{v}\n", k as f64 / fs));
    }
    std::fs::write(&path, text).unwrap();
    format!("csv:path={},duration=28,rate=500", path.display())
}

/// Seed 001's Case I stage (symmetric, the base model's own family) under `signal` with sensor
/// noise `noise_m` and `effects`; close-loop scored from `start_s`.
fn stage(
    name: &str,
    signal: &str,
    start_s: f64,
    noise_m: f64,
    effects: &[&str],
    allowed: Option<Vec<EffectKind>>,
) -> Outcome {
    let noise = format!("noise:rms_m={noise_m},seed=7");
    let mut all = vec![noise.as_str()];
    all.extend_from_slice(effects);
    let path = simulate(name, "stage-case1", signal, &all);
    let records = read_records(&path, None, None, None, None).unwrap();
    let mut settings = CloseLoopSettings {
        start_s,
        invertible: true,
        ..Default::default()
    };
    if let Some(allowed) = allowed {
        settings.allowed = allowed;
    }
    close_loop(&records, &settings).unwrap()
}

fn log_of(o: &Outcome) -> String {
    o.axes
        .iter()
        .flat_map(|a| a.steps.iter().map(|s| s.words()))
        .collect::<Vec<_>>()
        .join("\n")
}

fn check_single(o: &Outcome, effect: &str, ratio: f64) {
    let names = o.effects_added();
    let (before, after) = (o.before.rms, o.after.rms);
    eprintln!("{effect}: rms {before:.4e} -> {after:.4e} m, added {names:?}");
    assert_eq!(
        names.first().copied(),
        Some(effect),
        "first effect named: {names:?}\n{}",
        log_of(o)
    );
    assert!(
        after <= ratio * before,
        "{effect}: rms {before:.4e} -> {after:.4e} (must be <= {ratio}x)\n{}",
        log_of(o)
    );
}

#[test]
fn creep_is_named_and_removed() {
    let o = stage(
        "creep.csv",
        COSINE,
        0.0,
        2e-9,
        &["creep:tau=0.05/0.5,weight=0.03/0.03"],
        None,
    );
    check_single(&o, "creep", 0.25);
    // The final fit's uncertainty: its creep parameters among them, in the report as in params.
    let axis = &o.axes[0];
    let u = axis.uncertainty.as_ref().unwrap();
    let names: Vec<&str> = u.parameters.iter().map(|p| p.name.as_str()).collect();
    for name in [
        "bouc_wen.beta",
        "static_map.k1_m_per_v",
        "effects.creep_gain_m_per_v[0]",
        "effects.creep_time_constant_s[0]",
    ] {
        assert!(names.contains(&name), "{name} not in {names:?}");
    }
    assert!(u.standard_errors.iter().all(|s| s.is_finite() && *s > 0.0));
    let ratio = u.prediction_band_rms_m / axis.fit_after.rms;
    assert!((0.9..1.5).contains(&ratio), "band / in-sample rms {ratio}");
    let report = host_sim::to_json(&o.report()).unwrap();
    let r = &report["axes"][0];
    assert!(r["params"]["effects"]["creep_gain_m_per_v"][0].is_number());
    assert!(
        r["uncertainty"]["effects"]["creep_gain_m_per_v"][0]
            .as_f64()
            .unwrap()
            > 0.0
    );
    assert_eq!(
        r["correlation"]["names"].as_array().unwrap().len(),
        names.len()
    );
}

#[test]
fn drift_is_named_and_removed() {
    let o = stage("drift.csv", TWO_TONE, 0.5, 2e-9, &["drift:rate=1e-7"], None);
    check_single(&o, "drift", 0.25);
}

#[test]
fn delay_is_named_and_removed() {
    let o = stage("delay.csv", TWO_TONE, 0.5, 2e-9, &["delay:s=2e-3"], None);
    check_single(&o, "delay", 0.25);
}

#[test]
fn asymmetry_is_named_and_removed() {
    let o = stage(
        "asym.csv",
        COSINE,
        0.0,
        2e-9,
        &["electrostriction:per_v=0.004"],
        None,
    );
    check_single(&o, "asymmetry", 0.25);
}

/// A thermal settling of 0.3 µm with τ = 10 s, independent of u, under sines, ramps and holds:
/// drift (settling), not creep, which would need the input's steps to move.
#[test]
fn thermal_settling_is_named_drift_not_creep() {
    let o = stage(
        "settling.csv",
        &sines_ramps_holds(),
        1.0,
        5e-9,
        &["drift:rate=0,amplitude=3e-7,tau=10"],
        None,
    );
    check_single(&o, "drift", 0.25);
    assert!(
        !o.effects_added().contains(&"creep"),
        "creep added to a drift: {:?}\n{}",
        o.effects_added(),
        log_of(&o)
    );
    let form = o.axes[0].model.form(EffectKind::Drift);
    assert_eq!(form, "exponential settling", "{}", log_of(&o));
    let tau = f64::from(o.axes[0].model.effects.drift_settling_time_constant_s);
    assert!((5.0..20.0).contains(&tau), "tau {tau} s\n{}", log_of(&o));
}

/// No effect in the plant, but a 10-bit DAC (20 mV steps) between command and stage: a structured
/// misfit no effect describes. Nothing may be added, and the report says why.
#[test]
fn nothing_is_added_to_effect_free_data_with_a_small_structured_misfit() {
    let o = stage(
        "clean.csv",
        &sines_ramps_holds(),
        1.0,
        5e-9,
        &["dac:bits=10,min=0,max=20,rate_hz=500"],
        None,
    );
    let a = &o.axes[0];
    eprintln!(
        "effect-free: rms {:.4e} m, noise estimate {:.4e} m, added {:?}",
        o.after.rms,
        a.noise_m,
        o.effects_added()
    );
    assert!(
        o.effects_added().is_empty(),
        "added {:?}\n{}",
        o.effects_added(),
        log_of(&o)
    );
    // The noise estimate is the sensor's (5 nm) within a quarter.
    assert!((a.noise_m / 5e-9 - 1.0).abs() < 0.25, "{}", a.noise_m);
    let last = a.steps.last().unwrap();
    assert!(
        matches!(
            last.outcome,
            StepOutcome::Stopped(Stop::NoiseFloor | Stop::NothingHolds)
        ),
        "{}",
        log_of(&o)
    );
}

/// A 100 ms sensor delay under a 1 Hz cosine: more than the 5 % of the input period a delay may be.
/// The fit runs to that bound, and the delay is refused as implausible.
#[test]
fn a_fit_at_the_bound_of_its_plausible_range_is_refused() {
    let o = stage(
        "late.csv",
        COSINE,
        0.0,
        2e-9,
        &["delay:s=0.1"],
        Some(vec![EffectKind::Delay]),
    );
    let trials: Vec<_> = o.axes[0]
        .steps
        .iter()
        .flat_map(|s| s.trials.iter())
        .filter(|t| t.effect == EffectKind::Delay)
        .collect();
    assert!(!trials.is_empty(), "{}", log_of(&o));
    for t in &trials {
        assert_eq!(
            t.decision,
            Decision::Refused(Refusal::Implausible),
            "{}",
            t.words()
        );
        assert!(
            t.plausibility.checks.iter().any(|c| c.at_bound),
            "{}",
            t.words()
        );
    }
    assert!(o.effects_added().is_empty(), "{}", log_of(&o));
}

/// The XY stage's x axis (first flexure mode ≈ 3.2 kHz, ζ ≈ 3.5 %) under a staircase whose steps ring
/// the mode, sampled at 20 kHz: the static base model has no dynamics.
#[test]
fn dynamics_is_named_and_removed() {
    let path = simulate(
        "dyn.csv",
        "xy-stage",
        "staircase:low=0,high=120,step=20,hold=0.01,rate=20000",
        &["noise:rms_m=2e-9,seed=3"],
    );
    let records = read_records(&path, None, Some("ux_V"), Some("x_m"), None).unwrap();
    let o = close_loop(&records, &CloseLoopSettings::default()).unwrap();
    check_single(&o, "dynamics", 0.4);
    // The stage file carries a servo tuned on the mode close-loop found.
    let out = temp("dynamics.toml");
    let (stage, io) = stage_and_io_for(&records, &path, None).unwrap();
    write_stage_file(&o, &out, "dyn.csv", stage, io).unwrap();
    let (file, _) = piezo_stage::StageFile::load(&out).unwrap();
    let mode_hz = file.x.effects.mode_frequency_hz;
    assert!((2800.0..3600.0).contains(&mode_hz), "{mode_hz}");
    let servo = file.x.servo.expect("a servo tuned on the mode");
    assert_eq!(servo.notch_frequency_hz, mode_hz);
    assert!(servo.ki_v_per_m_s > 0.0);
}

/// Two-axis raster on the XY stage with cross-axis coupling in the measurement; the stage file of
/// the final model has both axes and passes the firmware's check.
#[test]
fn coupling_is_named_and_removed() {
    let path = simulate(
        "coupling.csv",
        "xy-stage",
        "raster:x_low=0,x_high=100,line_freq=5,y_low=0,y_high=100,duration=1,rate=5000",
        &["coupling:xy=0.03,yx=0.03", "noise:rms_m=2e-9,seed=4"],
    );
    let records = read_records(&path, None, Some("ux_V,uy_V"), Some("x_m,y_m"), None).unwrap();
    // Firmware-invertible base sets, so that the stage file is one the firmware builds.
    let settings = CloseLoopSettings {
        invertible: true,
        ..Default::default()
    };
    let o = close_loop(&records, &settings).unwrap();
    check_single(&o, "coupling", 0.25);
    let out = temp("coupling.toml");
    let (stage, io) = stage_and_io_for(&records, &path, None).unwrap();
    let written = write_stage_file(&o, &out, "coupling.csv", stage, io).unwrap();
    assert_eq!(written.verdict, Verdict::Accepted, "{:?}", written);
    let (file, _) = piezo_stage::StageFile::load(&out).unwrap();
    assert!(file.y.is_some());
    assert_eq!(file.x.effects, o.axes[0].model.effects);
    assert_eq!(
        file.x.identified.as_ref().map(|p| p.method.as_str()),
        Some("close-loop")
    );
}

fn cli(args: &[&str]) -> Result<String, String> {
    let mut v = vec!["host-sim"];
    v.extend_from_slice(args);
    run(Cli::try_parse_from(v).map_err(|e| e.to_string())?).map_err(|e| e.to_string())
}

fn json(path: &std::path::Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

/// The XY stage's x axis with strong creep (Kelvin–Voigt τ 0.1/1 s, weights 0.2/0.2 of the
/// stroke): a raised cosine 0–120 V at 2 Hz, 1.5 s at 4 kHz. Moving the creep's share of the
/// static gain out of k1 makes the map turn back after a reversal.
fn strong_creep(name: &str) -> PathBuf {
    simulate(
        name,
        "xy-stage",
        "sine:amp=60,offset=60,freq=2,phase_deg=-90,duration=1.5,rate=4000",
        &["creep:tau=0.1/1,weight=0.2/0.2", "noise:rms_m=2e-9,seed=5"],
    )
}

/// A final set the firmware refuses (here: the record needs 0-120 V and `--stage` carries an io
/// chain that drives 0-50 V): the command fails, but only after writing the stage file and the
/// report, which holds the verdict, the refusal and what to do. A stage file that cannot be
/// written (`--out` is a directory) and plots that cannot be made (`--plots` is a file) still
/// leave the report, which says what was not written.
#[test]
fn a_refused_set_keeps_its_report_with_the_verdict() {
    let data = strong_creep("refused.csv");
    let (out, report) = (temp("refused.toml"), temp("refused.json"));
    let stage = temp("weak-amplifier.toml");
    let text = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../firmware/params/xy-stage.toml"),
    )
    .unwrap()
    .replace(
        "amplifier_gain_v_per_v = 24.0",
        "amplifier_gain_v_per_v = 10.0",
    )
    .replace("output_max_v = 120.0", "output_max_v = 50.0");
    std::fs::write(&stage, text).unwrap();
    let common = [
        "close-loop",
        "--data",
        data.to_str().unwrap(),
        "--u",
        "ux_V",
        "--y",
        "x_m",
        "--stage",
        stage.to_str().unwrap(),
        // Every kept set invertible: the io window is what the firmware refuses.
        "--invertible",
    ];
    let mut args = common.to_vec();
    args.extend(["--out", out.to_str().unwrap()]);
    args.extend(["--report", report.to_str().unwrap()]);
    let e = cli(&args).expect_err("the set is refused");
    assert!(e.contains("would be refused by the firmware"), "{e}");
    assert!(e.contains("io.dac_range_v"), "{e}");
    assert!(out.exists(), "the stage file is written all the same");
    assert!(report.exists(), "the report is written all the same: {e}");
    let r = json(&report);
    assert_eq!(r["verdict"], "refused", "{r:#}");
    assert_eq!(r["stage_file_written"], true);
    let reason = r["refusal"]["reason"].as_str().unwrap();
    assert!(
        reason.contains("exceeds what the DAC and amplifier drive"),
        "{reason}"
    );
    assert!(r["refusal"]["remedy"]
        .as_str()
        .unwrap()
        .contains("io.dac_range_v"));
    assert!(!r["steps"].as_array().unwrap().is_empty());

    // --out a directory, --plots a file: neither can be written; the report is.
    let (dir_out, file_plots, report2) = (temp("out_dir"), temp("plots_file"), temp("r2.json"));
    std::fs::create_dir_all(&dir_out).unwrap();
    std::fs::write(&file_plots, "not a directory").unwrap();
    let mut args = common.to_vec();
    args.extend(["--out", dir_out.to_str().unwrap()]);
    args.extend(["--plots", file_plots.to_str().unwrap()]);
    args.extend(["--report", report2.to_str().unwrap()]);
    let e = cli(&args).expect_err("nothing but the report can be written");
    assert!(e.contains("--out") && e.contains("not written"), "{e}");
    assert!(e.contains("--plots"), "{e}");
    let r = json(&report2);
    assert_eq!(r["stage_file_written"], false, "{r:#}");
    assert!(r["stage_file_not_written"].is_string());
    assert!(r["plots_not_written"].is_string());
    assert_eq!(r["verdict"], "refused");
}

/// With `--invertible`, the set close-loop writes for the strong-creep record is one `host-sim
/// compensate` runs: read back and checked as `compensate` checks it, and `compensate` itself
/// computes voltages from it. Every candidate kept to (or refused for) the constraint.
#[test]
fn invertible_holds_for_the_whole_set_with_effects() {
    let data = strong_creep("invertible.csv");
    let (out, report) = (temp("invertible.toml"), temp("invertible.json"));
    let msg = cli(&[
        "close-loop",
        "--data",
        data.to_str().unwrap(),
        "--u",
        "ux_V",
        "--y",
        "x_m",
        "--invertible",
        "--out",
        out.to_str().unwrap(),
        "--report",
        report.to_str().unwrap(),
    ])
    .unwrap();
    assert!(msg.contains("accepted by the firmware"), "{msg}");
    let r = json(&report);
    assert_eq!(r["verdict"], "accepted", "{r:#}");
    assert_eq!(r["invertible"]["holds"], true);
    // The check `compensate` makes, on the file as written.
    let (file, valid) = piezo_stage::StageFile::load(&out).unwrap();
    assert!(valid.axes[0].compensator.is_some());
    host_sim::compensate::feedforward_axes(&file, &valid, &out).unwrap();
    // Every candidate's final set too.
    for step in r["steps"].as_array().unwrap() {
        for c in step["candidates"].as_array().unwrap() {
            let refused_as = c["decision"].as_str().unwrap();
            assert!(
                c["not_invertible"].is_null() || refused_as == "refused-not-invertible",
                "{c:#}"
            );
        }
    }
    // And compensate runs it.
    let (reference, voltages) = (temp("reference.csv"), temp("voltages.csv"));
    cli(&[
        "compensate",
        "--params",
        out.to_str().unwrap(),
        "--signal",
        "triangle:low=5,high=25,freq=2,duration=0.5",
        "--reference",
        reference.to_str().unwrap(),
        "--out",
        voltages.to_str().unwrap(),
    ])
    .unwrap();
    assert!(voltages.exists());
}

/// The XY stage's x axis with the stacks' dielectric lag (τ_v = 1 ms) under a rising-amplitude
/// raised sine 0–120 V at `f` Hz for `duration_s` at 10 kHz, from rest, 2 nm sensor noise.
fn lag_record(name: &str, f: u32, duration_s: f64) -> PathBuf {
    xy_record(name, f, duration_s, &["dielectric-lag:tau=1e-3"])
}

/// The XY stage's x axis with the plant effects `effects` under a rising-amplitude raised sine
/// 0–120 V at `f` Hz for `duration_s` at 10 kHz, from rest, 2 nm sensor noise (seeded by `f`).
fn xy_record(name: &str, f: u32, duration_s: f64, effects: &[&str]) -> PathBuf {
    let noise = format!("noise:rms_m=2e-9,seed={f}");
    let mut all = effects.to_vec();
    all.push(&noise);
    simulate(
        &format!("{name}{f}.csv"),
        "xy-stage",
        &format!(
            "rising-sine:amp=60,offset=0,freq={f},phase_deg=-90,raised=1,duration={duration_s},rate=10000"
        ),
        &all,
    )
}

/// `close-loop --data DATA --free-offset` on the x axis: its report and the stage file written.
fn close_loop_records(name: &str, data: &str) -> (serde_json::Value, PathBuf) {
    let (done, report, stage) = close_loop_run(name, data, &["--u", "ux_V", "--y", "x_m"]);
    done.unwrap();
    (report, stage)
}

/// `close-loop --data DATA --free-offset EXTRA…`: whether it succeeded, its report and the stage
/// file's path (the report is written whether or not the firmware's check accepts the file).
fn close_loop_run(
    name: &str,
    data: &str,
    extra: &[&str],
) -> (Result<String, String>, serde_json::Value, PathBuf) {
    let (done, report, stage) = close_loop_cli(name, data, extra);
    (done, json(&report), stage)
}

/// `close-loop --data DATA --free-offset EXTRA…`: whether it succeeded and the paths of its report
/// and stage file (neither is written when the command line is refused).
fn close_loop_cli(
    name: &str,
    data: &str,
    extra: &[&str],
) -> (Result<String, String>, PathBuf, PathBuf) {
    let (report, stage) = (temp(&format!("{name}.json")), temp(&format!("{name}.toml")));
    let mut args = vec!["close-loop", "--data", data, "--free-offset"];
    args.extend_from_slice(extra);
    args.extend_from_slice(&[
        "--report",
        report.to_str().unwrap(),
        "--out",
        stage.to_str().unwrap(),
    ]);
    (cli(&args), report, stage)
}

/// The zeroed RMS with which `stage` predicts the x axis of a two-axis `record` from rest, its
/// offset re-estimated \[m\].
fn predicted_rms(stage: &Path, record: &Path) -> f64 {
    predicted_zeroed_rms(stage, record, &["--u", "ux_V", "--y", "x_m"])
}

/// The zeroed RMS with which `stage` predicts `record` from rest (`predict --free-offset`, with
/// `columns` naming its u and y when they are not `u_V` and `y_m`) \[m\].
fn predicted_zeroed_rms(stage: &Path, record: &Path, columns: &[&str]) -> f64 {
    let report = temp(&format!(
        "{}-predict.json",
        stage.file_stem().unwrap().to_str().unwrap()
    ));
    let mut args = vec![
        "predict",
        "--params",
        stage.to_str().unwrap(),
        "--data",
        record.to_str().unwrap(),
    ];
    args.extend_from_slice(columns);
    args.extend(["--free-offset", "--report", report.to_str().unwrap()]);
    cli(&args).unwrap();
    json(&report)["rms_zeroed_m"][0].as_f64().unwrap()
}

/// Asserts that close-loop's first step added the rate-dependent hysteresis, in `form`.
fn assert_rate_dependent_first(r: &serde_json::Value, form: &str) {
    let words = r["words"].to_string();
    assert_eq!(
        added(r).first().map(String::as_str),
        Some("rate-dependent hysteresis"),
        "{words}"
    );
    assert_eq!(r["steps"][0]["form"], form, "{words}");
}

/// The effects a close-loop report added, in order.
fn added(report: &serde_json::Value) -> Vec<String> {
    report["effects_added"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| e.as_str().unwrap().to_string())
        .collect()
}

/// The XY stage's x axis with the stacks' dielectric lag (τ_v = 1 ms: the Bouc-Wen operator
/// driven by a first-order lag of the voltage), two records of rising-amplitude raised sines
/// 0-120 V at 40 and 100 Hz (0.25 s at 10 kHz each, from rest), fitted together with their own
/// offsets: close-loop names the rate-dependent hysteresis first (as the operator's input lag),
/// lowers the RMS fiftyfold, then adds the stage's first mode, predicts a 20 Hz record it did
/// not see within 1.3x its fit, and
/// its report fits the phase effects the screening cannot separate (delay and
/// dynamics with it) and says why each other effect was not fitted.
#[test]
fn rate_dependent_hysteresis_is_named_across_two_records() {
    let record = |f: u32| lag_record("lag", f, 0.25);
    let data = format!("{},{}", record(40).display(), record(100).display());
    let (r, stage) = close_loop_records("lag", &data);
    let words = r["words"].to_string();
    let added = added(&r);
    assert_eq!(
        added.first().map(String::as_str),
        Some("rate-dependent hysteresis"),
        "{words}"
    );
    let (before, after) = (
        r["before"]["rms"].as_f64().unwrap(),
        r["after"]["rms"].as_f64().unwrap(),
    );
    assert!(
        after <= 0.02 * before,
        "rms {before:.4e} -> {after:.4e}\n{words}"
    );
    assert_eq!(r["steps"][0]["form"], "input lag", "{words}");
    // Then the stage's first mode (≈ 3.4 kHz): at 100 Hz its response is a few nm, at 40 Hz below
    // the noise, so the two records' held-out gains differ and the two-record rule judges it.
    assert_eq!(
        added.get(1).map(String::as_str),
        Some("dynamics"),
        "{words}"
    );
    let (file, _) = piezo_stage::StageFile::load(&stage).unwrap();
    let mode_hz = file.x.effects.mode_frequency_hz;
    assert!(
        (3000.0..3800.0).contains(&mode_hz),
        "mode {mode_hz} Hz\n{words}"
    );
    // The stage file predicts the rate it did not see (20 Hz) from rest, its offset re-estimated,
    // within 1.3x its fit: the rate dependence is the plant's, not a fit of two records.
    let rms_unseen = predicted_rms(&stage, &record(20));
    assert!(
        rms_unseen <= 1.3 * after && rms_unseen <= 0.02 * before,
        "20 Hz predicted at {rms_unseen:.4e} m, fit {after:.4e} m, base {before:.4e} m"
    );
    let first = &r["steps"][0];
    let fitted: Vec<&str> = first["candidates"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["effect"].as_str().unwrap())
        .collect();
    for e in ["creep", "delay", "rate-dependent hysteresis", "dynamics"] {
        assert!(fitted.contains(&e), "{e} not fitted: {fitted:?}\n{words}");
    }
    let not_tried = first["not_tried"].as_array().unwrap();
    for e in ["asymmetry", "coupling"] {
        let n = not_tried.iter().find(|n| n["effect"] == e);
        assert!(
            n.is_some_and(|n| !n["reason"].as_str().unwrap().is_empty()),
            "{e}: no reason given: {not_tried:?}"
        );
    }
}

/// The XY stage's x axis with a Bouc-Wen gain that grows with the voltage's speed
/// (`rate-bouc-wen:rate=1e5`, α·(1 + |u̇|/10⁵ V/s); the fit is not told of it), rising-amplitude
/// raised sines 0–120 V at 20 and 40 Hz (0.5 s at 10 kHz, 2 nm noise), fitted together with their
/// own offsets: close-loop names the rate-dependent hysteresis first, as the operator's
/// rate-dependent gain, finds the plant's c = 1/ṙ₀ = 1e-5 s/V within 5 %, and lowers the RMS
/// twentyfold; then the stage's 3.2 kHz mode, whose quasi-static response (a gain of
/// 1 + (f/f_mode)², a few nm at 40 Hz) the screening's stack-driven form sees. The stage file
/// predicts the 100 Hz record it did not see within 1.3× the fit (the rate-independent model and
/// the lag and relaxation forms: 0.51 and 0.37 µm there; without the mode 0.010 µm, 4.9× the fit).
#[test]
fn a_gain_that_grows_with_speed_is_named_and_predicted_at_a_rate_it_did_not_see() {
    let record = |f: u32| xy_record("speed", f, 0.5, &["rate-bouc-wen:rate=1e5"]);
    let data = format!("{},{}", record(20).display(), record(40).display());
    let (r, stage) = close_loop_records("speed", &data);
    let words = r["words"].to_string();
    assert_rate_dependent_first(&r, "rate-dependent gain");
    let (file, _) = piezo_stage::StageFile::load(&stage).unwrap();
    let gain = file.x.effects.hysteresis_rate_gain_s_per_v;
    assert!((gain - 1e-5).abs() <= 0.05e-5, "c = {gain} s/V\n{words}");
    let (before, after) = (
        r["before"]["rms"].as_f64().unwrap(),
        r["after"]["rms"].as_f64().unwrap(),
    );
    assert!(
        after <= 0.05 * before,
        "rms {before:.4e} -> {after:.4e}\n{words}"
    );
    assert_eq!(
        added(&r).get(1).map(String::as_str),
        Some("dynamics"),
        "{words}"
    );
    let rms_unseen = predicted_rms(&stage, &record(100));
    assert!(
        rms_unseen <= 1.3 * after,
        "100 Hz predicted at {rms_unseen:.4e} m, fit {after:.4e} m"
    );
    // The written slew limit is the fastest at which the compensator can invert the gain.
    let slew = file.x.limits.slew_limit_v_per_s;
    assert!(slew > 1e3 && slew < 1e5, "slew {slew} V/s");
    // The servo is tuned on the mode at that slew limit: its integral gain has the sign of the
    // stage's dy/du (positive here), as the firmware's check asks.
    let servo = file.x.servo.as_ref().expect("a servo tuned on the mode");
    assert!(servo.ki_v_per_m_s > 0.0, "{servo:?}");
}

/// A long 20 Hz record (0.5 s) and a short 40 Hz one (0.1 s, a fifth of its samples) of the XY
/// stage with a 1 ms dielectric lag: leaving the long record out would refit on the short one
/// alone, so close-loop holds out interleaved segments of both records instead, says so with the
/// short record's name, and still names the rate-dependent hysteresis first.
#[test]
fn records_of_very_unequal_length_are_judged_on_blocks_within_them() {
    let long = xy_record("unequal", 20, 0.5, &["dielectric-lag:tau=1e-3"]);
    let short = xy_record("unequal", 40, 0.1, &["dielectric-lag:tau=1e-3"]);
    let data = format!("{},{}", long.display(), short.display());
    let (r, _) = close_loop_records("unequal", &data);
    let words = r["words"].to_string();
    let method = r["axes"][0]["held_out"]["method"].as_str().unwrap();
    assert!(
        method.starts_with("blocks within the records")
            && method.contains(&format!("{} holds 1000 scored samples", short.display()))
            && method.contains("longest record's 5000"),
        "{method}"
    );
    assert_eq!(
        added(&r).first().map(String::as_str),
        Some("rate-dependent hysteresis"),
        "{words}"
    );
}

/// The asymmetric stage of seed 001 (its gains negative, n ≈ 3, and a map that folds: no
/// compensator inverts it, so it is fitted without `--invertible`) with a Bouc-Wen gain growing
/// with the voltage's speed (`rate-bouc-wen:rate=1.5e4`, A up to 1.17× at 40 Hz), rising raised
/// sines 0–20 V at 20 and 40 Hz (0.5 s, 2 nm noise, offsets 0 and +2.5 µm): close-loop names the
/// rate-dependent gain first, though the compensator refuses the stage's set with or without it,
/// finds c = 1/ṙ₀ within 5 %, and the stage file predicts the 100 Hz record within 1.3× the fit.
#[test]
fn a_gain_that_grows_with_speed_is_named_on_a_stage_no_compensator_inverts() {
    let record = |f: u32, offset_m: f64| {
        let raw = simulate(
            &format!("fold-raw{f}.csv"),
            "stage",
            &format!(
                "rising-sine:amp=10,offset=0,freq={f},phase_deg=-90,raised=1,duration=0.5,rate=10000"
            ),
            &["rate-bouc-wen:rate=1.5e4", &format!("noise:rms_m=2e-9,seed={f}")],
        );
        with_offset(&raw, &format!("fold{f}"), offset_m)
    };
    let data = format!(
        "{},{}",
        record(20, 0.0).display(),
        record(40, 2.5e-6).display()
    );
    let (done, r, stage) = close_loop_run("fold", &data, &[]);
    let words = r["words"].to_string();
    // The stage's own map folds: the set is written with the firmware's refusal.
    assert!(done.is_err(), "{words}");
    assert_rate_dependent_first(&r, "rate-dependent gain");
    // The file is written with the firmware's refusal, so it is read as text, not loaded.
    let text = std::fs::read_to_string(&stage).unwrap();
    let gain: f64 = text
        .lines()
        .find_map(|l| l.strip_prefix("hysteresis_rate_gain_s_per_v = "))
        .unwrap()
        .parse()
        .unwrap();
    assert!(
        (gain - 1.0 / 1.5e4).abs() <= 0.05 / 1.5e4,
        "c = {gain} s/V\n{words}"
    );
    let after = r["after"]["rms"].as_f64().unwrap();
    let rms_unseen = predicted_zeroed_rms(&stage, &record(100, -1.5e-6), &[]);
    assert!(
        rms_unseen <= 1.3 * after,
        "100 Hz predicted at {rms_unseen:.4e} m, fit {after:.4e} m"
    );
}

/// The XY stage's x axis with both rate dependences at once, the stacks' dielectric lag (τ_v =
/// 1 ms) and a Bouc-Wen gain growing with the lagged voltage's speed (ṙ₀ = 1e5 V/s), from 20 and
/// 40 Hz records (0.5 s, 2 nm noise): close-loop names the rate-dependent hysteresis first as the
/// input lag with the rate-dependent gain (a lag alone levels off with the rate, a gain alone has no
/// phase lag), finds both (τ_v within 5 % of 1 ms, c within 5 % of 1e-5 s/V) and predicts the
/// 100 Hz record it did not see within 1.3× its fit (1.15× measured).
#[test]
fn a_lag_and_a_gain_that_grows_with_speed_are_named_together() {
    let record = |f: u32| {
        xy_record(
            "lag-speed",
            f,
            0.5,
            &["dielectric-lag:tau=1e-3", "rate-bouc-wen:rate=1e5"],
        )
    };
    let data = format!("{},{}", record(20).display(), record(40).display());
    let (r, stage) = close_loop_records("lag-speed", &data);
    let words = r["words"].to_string();
    assert_rate_dependent_first(&r, "input lag and rate-dependent gain");
    let (file, _) = piezo_stage::StageFile::load(&stage).unwrap();
    let (lag, gain) = (
        file.x.effects.hysteresis_lag_s,
        file.x.effects.hysteresis_rate_gain_s_per_v,
    );
    assert!((lag - 1e-3).abs() <= 0.05e-3, "tau_v = {lag} s\n{words}");
    assert!((gain - 1e-5).abs() <= 0.05e-5, "c = {gain} s/V\n{words}");
    let after = r["after"]["rms"].as_f64().unwrap();
    let rms_unseen = predicted_rms(&stage, &record(100));
    assert!(
        rms_unseen <= 1.3 * after,
        "100 Hz predicted at {rms_unseen:.4e} m, fit {after:.4e} m"
    );
}

/// The same stage from 20 and 40 Hz records (0.5 s each): after the rate-dependent hysteresis the
/// residual is within 1.2× the noise in RMS but not white (the 3.2 kHz mode's quasi-static
/// response, a few nm at 40 Hz), so close-loop goes on and adds the mode, in the form whose
/// damping acts on the motion relative to the drive (the stage's own: stiffness-proportional
/// damping, no phase lag below the mode); the 100 Hz record it did not see is then predicted
/// within 1.3× the fit (1.1× measured; 1.8× with the force-driven mode alone, 5.2× without a mode).
#[test]
fn a_residual_at_the_noise_rms_that_is_not_white_is_still_explained() {
    let record = |f: u32| lag_record("white", f, 0.5);
    let data = format!("{},{}", record(20).display(), record(40).display());
    let (r, stage) = close_loop_records("white", &data);
    let words = r["words"].to_string();
    assert_eq!(
        added(&r),
        ["rate-dependent hysteresis", "dynamics"],
        "{words}"
    );
    let (file, _) = piezo_stage::StageFile::load(&stage).unwrap();
    assert_eq!(file.x.effects.mode_relative_damping, 1.0, "{words}");
    let fit = r["after"]["rms"].as_f64().unwrap();
    let unseen = predicted_rms(&stage, &record(100));
    assert!(
        unseen <= 1.3 * fit,
        "100 Hz predicted at {unseen:.4e} m, fit {fit:.4e} m\n{words}"
    );
}

/// piezo-reference's bipolar stack (its Bouc-Wen operator driven through three dielectric
/// relaxations, 0.2 / 1 / 5 ms, none of the core's rate-dependent forms; a force-driven 740 Hz
/// mode) under a rising-amplitude sine ±`amp_v` at `f` Hz, 0.25 s at 10 kHz from rest, 1 nm
/// sensor noise (seed `seed`), the sensor's zero at `offset_m` (each session its own).
fn stack_record(name: &str, f: u32, amp_v: f64, seed: u32, offset_m: f64) -> PathBuf {
    plant_record("bipolar-stack", name, f, amp_v, seed, offset_m, 0.25)
}

/// [`stack_record`] on `plant`, `duration_s` long.
fn plant_record(
    plant: &str,
    name: &str,
    f: u32,
    amp_v: f64,
    seed: u32,
    offset_m: f64,
    duration_s: f64,
) -> PathBuf {
    let raw = simulate(
        &format!("{name}-raw.csv"),
        plant,
        &format!(
            "rising-sine:amp={amp_v},offset=0,freq={f},phase_deg=0,raised=0,duration={duration_s},rate=10000"
        ),
        &[&format!("noise:rms_m=1e-9,seed={seed}")],
    );
    with_offset(&raw, name, offset_m)
}

/// The one-axis record `raw` (t, u, y) with the sensor offset `offset_m` added to y, written as
/// `{name}.csv`.
fn with_offset(raw: &Path, name: &str, offset_m: f64) -> PathBuf {
    let text = std::fs::read_to_string(raw).unwrap();
    let mut lines = text.lines();
    let mut out = format!("{}\n", lines.next().unwrap());
    for line in lines {
        let mut cols: Vec<String> = line.split(',').map(str::to_string).collect();
        let y: f64 = cols[2].parse().unwrap();
        cols[2] = format!("{:e}", y + offset_m);
        out.push_str(&cols.join(","));
        out.push('\n');
    }
    let path = temp(&format!("{name}.csv"));
    std::fs::write(&path, out).unwrap();
    path
}

/// An actuator whose rate dependence is none of the core's forms: fitted on 20 and 40 Hz records
/// (`--free-offset`, the 100 Hz record of one session as `--validate`), close-loop adds the
/// rate-dependent hysteresis first, in the form that predicts that 100 Hz record best: the
/// relaxation of the hysteretic output with its time constants spread over about a decade (the
/// input lag with one or two relaxations fits 20 and 40 Hz closer, but one first-order lag before
/// the operator does not follow a spread of relaxation times across rates). It lowers that 100 Hz record's zeroed RMS by more than half
/// (65 % measured), and the stage file predicts the 100 Hz records of both sessions (the second at
/// another amplitude and offset) at under 40 % of the base model's error. The prediction is still
/// a few times the fit's RMS: the 100 Hz loops lie outside what 20 and 40 Hz fix.
#[test]
fn an_actuator_with_a_spread_of_relaxation_times_is_predicted_at_a_rate_it_did_not_see() {
    let r20 = stack_record("s20", 20, 90.0, 20, 0.0);
    let r40 = stack_record("s40", 40, 90.0, 40, 2.5e-6);
    let r100a = stack_record("s100a", 100, 90.0, 100, -1.5e-6);
    let r100b = stack_record("s100b", 100, 80.0, 101, 3.2e-6);
    let (report, stage) = (temp("stack.json"), temp("stack.toml"));
    let data = format!("{},{}", r20.display(), r40.display());
    cli(&[
        "close-loop",
        "--data",
        &data,
        "--free-offset",
        "--validate",
        r100a.to_str().unwrap(),
        "--report",
        report.to_str().unwrap(),
        "--out",
        stage.to_str().unwrap(),
    ])
    .unwrap();
    let r = json(&report);
    let words = r["words"].to_string();
    assert_rate_dependent_first(&r, "spread relaxation");
    // The plant's relaxation times span 0.2 to 5 ms, 1.4 decades.
    let spread = r["steps"][0]["candidates"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["decision"] == "added")
        .and_then(|c| {
            c["plausibility"]["checks"]
                .as_array()?
                .iter()
                .find(|k| k["parameter"] == "relaxation_spread_decades")?["value"]
                .as_f64()
        })
        .unwrap();
    assert!(
        (0.5..=2.5).contains(&spread),
        "spread {spread} decades\n{words}"
    );
    let (without, with) = added_zeroed_rms(&r);
    assert!(
        with <= 0.5 * without,
        "100 Hz zeroed RMS {without:.4e} -> {with:.4e} m\n{words}"
    );
    for record in [&r100a, &r100b] {
        let p = predicted_zeroed_rms(&stage, record, &[]);
        assert!(
            p <= 0.4 * without,
            "{}: predicted at {p:.4e} m, base {without:.4e} m\n{words}",
            record.display()
        );
    }
}

/// piezo-reference's relaxing stack (its whole strain follows the voltage through the drive's RC
/// lag and two dielectric relaxations, so its loops widen with rate, unlike the bipolar stack's;
/// a stiffening strain no static form has; a force-driven 740 Hz mode), 0.5 s records: fitted on
/// 20 and 40 Hz (`--free-offset`, one session's 100 Hz record as `--validate`), close-loop adds the
/// rate-dependent hysteresis first as a relaxation of the whole output (the hysteretic part alone
/// relaxing, or lagging, cannot open the loops), which lowers that 100 Hz record's zeroed RMS by
/// at least 20 %; the stage file predicts the 100 Hz records of both sessions (the second at
/// another amplitude and offset) at under 60 % of the base model's error on the first (56 % and
/// 38 % measured; with a delay in its place, the best the hysteretic forms allow, 66 % and 54 %).
#[test]
fn an_actuator_whose_loops_widen_with_rate_is_predicted_at_a_rate_it_did_not_see() {
    let run = widening_loops_run("relaxing-stack", "widen");
    for (record, p) in &run.predicted {
        assert!(
            *p <= 0.6 * run.zeroed_without,
            "{record}: predicted at {p:.4e} m, base {:.4e} m\n{}",
            run.zeroed_without,
            run.words
        );
    }
}

/// piezo-reference's shaped relaxing stack: the relaxing stack with a second, fast-saturating
/// switching population, a rate-independent loop-shape error no core form has (one Bouc-Wen
/// element bends each reversal curve at one scale only), so that, as on a measured actuator, the
/// fit leaves about 0.7 % of the 35 µm span, in the fit and in every prediction alike. 0.5 s
/// records fitted on 20 and 40 Hz as above: close-loop still adds the rate-dependent hysteresis
/// first as a relaxation of the whole output, the 100 Hz record's zeroed RMS falls by at least
/// 20 %, and the stage file predicts the 100 Hz records of both sessions within 1.45× the fit's
/// RMS (1.31 and 0.99 measured; without the added effect the first is 2.2× the fit's).
#[test]
fn an_actuator_with_a_shape_error_whose_loops_widen_is_predicted_at_a_rate_it_did_not_see() {
    let run = widening_loops_run("relaxing-stack-shaped", "shaped");
    // The shape error is there: the fit leaves more than half a per cent of the span.
    assert!(
        run.fit > 0.005 * 35e-6,
        "fit RMS {:.4e} m\n{}",
        run.fit,
        run.words
    );
    run.assert_predicted_within_fit(1.45);
}

/// The relaxing stack on a mount ten times stiffer (its mode at 7.4 kHz, which raises the 100 Hz
/// gain by 0.02 % where the 740 Hz mode raises it by 1.9 %), 0.5 s records fitted on 20 and
/// 40 Hz as above: what is left is the rate dependence itself, and the stage file predicts the
/// 100 Hz records of both sessions within 1.3× the fit's RMS (1.17 and 0.76 measured; 1.55 and
/// 1.05 with the 740 Hz mode, which 20 and 40 Hz sines barely excite).
#[test]
fn an_actuator_whose_loops_widen_is_predicted_within_1_3x_its_fit_where_no_mode_is_near() {
    let run = widening_loops_run("relaxing-stack-stiff", "stiff");
    run.assert_predicted_within_fit(1.3);
}

/// What close-loop made of a stand-in whose loops widen with rate, and how its stage file predicts
/// the 100 Hz records it did not see.
struct WideningRun {
    /// close-loop's words, for the messages.
    words: String,
    /// The fit's RMS (m).
    fit: f64,
    /// The 100 Hz record's zeroed RMS without the added effect (m).
    zeroed_without: f64,
    /// Per 100 Hz record (two sessions): its path and the stage file's zeroed RMS on it (m).
    predicted: Vec<(String, f64)>,
}

impl WideningRun {
    /// Asserts that each 100 Hz record is predicted within `factor` times the fit's RMS.
    fn assert_predicted_within_fit(&self, factor: f64) {
        for (record, p) in &self.predicted {
            assert!(
                *p <= factor * self.fit,
                "{record}: predicted at {p:.4e} m, fit {:.4e} m\n{}",
                self.fit,
                self.words
            );
        }
    }
}

/// Records 0.5 s rising sines of `plant` at 20, 40 and 100 Hz (two 100 Hz sessions, the second at
/// another amplitude and offset, the sensor zero moved per record), runs `close-loop --data
/// r20,r40 --free-offset --validate r100a` and `predict --free-offset` on both 100 Hz records.
/// Checks what both stand-ins share: the rate-dependent hysteresis is added first, as a relaxation
/// of the whole output, and lowers the 100 Hz record's zeroed RMS by at least 20 %.
fn widening_loops_run(plant: &str, tag: &str) -> WideningRun {
    let rec = |f: u32, session: &str, amp_v: f64, seed: u32, offset_m: f64| {
        let name = format!("{tag}{f}{session}");
        plant_record(plant, &name, f, amp_v, seed, offset_m, 0.5)
    };
    let r20 = rec(20, "", 90.0, 20, 0.0);
    let r40 = rec(40, "", 90.0, 40, 2.5e-6);
    let r100a = rec(100, "a", 90.0, 100, -1.5e-6);
    let r100b = rec(100, "b", 80.0, 101, 3.2e-6);
    let data = format!("{},{}", r20.display(), r40.display());
    // The file is written whether or not the firmware's check accepts it; the figures are judged.
    let (_, r, stage) = close_loop_run(tag, &data, &["--validate", r100a.to_str().unwrap()]);
    let words = r["words"].to_string();
    assert_rate_dependent_first(&r, "relaxation of the whole output");
    let (without, with) = added_zeroed_rms(&r);
    assert!(
        with <= 0.8 * without,
        "100 Hz zeroed RMS {without:.4e} -> {with:.4e} m\n{words}"
    );
    let predicted = [&r100a, &r100b]
        .iter()
        .map(|record| {
            let p = predicted_zeroed_rms(&stage, record, &[]);
            (record.display().to_string(), p)
        })
        .collect();
    WideningRun {
        fit: r["after"]["rms"].as_f64().unwrap(),
        words,
        zeroed_without: without,
        predicted,
    }
}

/// The relaxing stack under a 20 Hz record to 90 V and a shorter 40 Hz record that rises to 54 V
/// only, with one session's 100 Hz record to 90 V as `--validate`: creep and the relaxation of the
/// whole output both hold on the held-out records, but amplitude and rate change together across
/// the two records, and the forms extrapolate to the 100 Hz record very differently (one predicts
/// it worse and is refused there). close-loop adds the candidate that predicts the `--validate`
/// record best, not the one with the largest held-out gain: with the held-out gain deciding, it
/// added a one-element Kelvin-Voigt creep that lowered the 100 Hz zeroed RMS by 5 %; now the
/// logarithmic creep, 11 %.
#[test]
fn with_a_validate_record_the_form_that_predicts_it_best_is_added() {
    let r20 = plant_record("relaxing-stack", "pick20", 20, 90.0, 20, 0.0, 0.5);
    let r40 = plant_record("relaxing-stack", "pick40", 40, 54.0, 40, 2.5e-6, 0.3);
    let r100 = plant_record("relaxing-stack", "pick100", 100, 90.0, 100, -1.5e-6, 0.5);
    let data = format!("{},{}", r20.display(), r40.display());
    let (_, r, _) = close_loop_run("pick", &data, &["--validate", r100.to_str().unwrap()]);
    let words = r["words"].to_string();
    let run_gain = |c: &serde_json::Value| {
        let run = &c["another_run"];
        1.0 - (run["rms_zeroed_with"].as_f64().unwrap()
            / run["rms_zeroed_without"].as_f64().unwrap())
        .powi(2)
    };
    let held_out_gain =
        |c: &serde_json::Value| c["out_of_sample"]["relative_gain"].as_f64().unwrap();
    let holding: Vec<&serde_json::Value> = r["steps"][0]["candidates"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|c| c["decision"] == "added" || c["decision"] == "holds-not-best")
        .collect();
    let chosen = first_step_candidate(&r, |c| c["decision"] == "added");
    // The rule mattered: another candidate that holds has the larger held-out gain.
    assert!(
        holding
            .iter()
            .any(|c| held_out_gain(c) > held_out_gain(chosen) + 0.02),
        "{words}"
    );
    // And the one added predicts the other run best.
    for c in &holding {
        assert!(
            run_gain(chosen) >= run_gain(c) - 0.02,
            "{} predicts the 100 Hz record better than {}\n{words}",
            c["form"],
            chosen["form"]
        );
    }
    let (without, with) = added_zeroed_rms(&r);
    assert!(
        with <= 0.92 * without,
        "100 Hz zeroed RMS {without:.4e} -> {with:.4e} m\n{words}"
    );
}

/// The first candidate of close-loop's first step (its report `r`) for which `is` holds.
fn first_step_candidate(
    r: &serde_json::Value,
    is: impl Fn(&serde_json::Value) -> bool,
) -> &serde_json::Value {
    r["steps"][0]["candidates"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| is(c))
        .unwrap()
}

/// The zeroed RMS of the validation record without and with the first effect close-loop added
/// (its report's first step) \[m\].
fn added_zeroed_rms(r: &serde_json::Value) -> (f64, f64) {
    let first = first_step_candidate(r, |c| c["decision"] == "added");
    (
        first["another_run"]["rms_zeroed_without"].as_f64().unwrap(),
        first["another_run"]["rms_zeroed_with"].as_f64().unwrap(),
    )
}

/// piezo-reference's relaxing stack (a force-driven 740 Hz mode) recorded under 20 and 40 Hz
/// rising-amplitude sines and under voltage steps, fitted together (`--free-offset`): only the
/// step record rings the mode, so leaving a record out cannot confirm it (refitted on the sines
/// alone the mode is not identified, and the sines gain nothing: the t-test over the three records
/// refuses it). Judged again on blocks within the records, each refit seeing part of every
/// record, it holds: close-loop adds the mode first, at the stack's frequency, where before it
/// added nothing although the residual was a thousand times the noise; every later effect is
/// judged within the records too.
#[test]
fn a_mode_only_a_step_record_rings_is_judged_within_the_records() {
    let r20 = plant_record("relaxing-stack", "ring20", 20, 90.0, 20, 0.0, 0.5);
    let r40 = plant_record("relaxing-stack", "ring40", 40, 90.0, 40, 2.5e-6, 0.5);
    let steps = simulate(
        "ring-steps.csv",
        "relaxing-stack",
        "steps:levels=0/40/-30/60/-60/20/-80/80/0,hold=0.05,rate=10000",
        &["noise:rms_m=1e-9,seed=7"],
    );
    let data = format!("{},{},{}", r20.display(), r40.display(), steps.display());
    let (_, r, _) = close_loop_run("ring", &data, &[]);
    let words = r["words"].to_string();
    assert_eq!(
        added(&r).first().map(String::as_str),
        Some("dynamics"),
        "{words}"
    );
    let trial = first_step_candidate(&r, |t| t["effect"] == "dynamics");
    // The figures (`-- --nocapture`).
    println!("{}", trial["words"]);
    assert_eq!(trial["out_of_sample"]["holds"], false, "{words}");
    assert_eq!(trial["within_records"]["holds"], true, "{words}");
    let f = trial["parameters"]["mode_frequency_hz"].as_f64().unwrap();
    assert!((f / 740.0 - 1.0).abs() < 0.05, "mode at {f} Hz\n{words}");
    // Every later effect is judged within the records (four blocks), not by leaving one of the
    // three records out: refitted without the step record, the model would lose the mode too.
    for step in &r["steps"].as_array().unwrap()[1..] {
        for c in step["candidates"].as_array().unwrap() {
            if let Some(blocks) = c["out_of_sample"]["log_ratios"].as_array() {
                assert_eq!(blocks.len(), 4, "{}\n{words}", c["words"]);
                assert!(c["within_records"].is_null(), "{words}");
            }
        }
    }
}

/// A `--validate` record at another sample period than the fitted records' is refused before any
/// fit, naming the file and both periods: the discrete models would not describe it, and every
/// effect would be refused on a run predicted at the wrong rate.
#[test]
fn a_validate_record_at_another_sample_period_is_refused_by_name() {
    let fitted = plant_record("relaxing-stack", "period20", 20, 90.0, 20, 0.0, 0.1);
    let other = simulate(
        "period100.csv",
        "relaxing-stack",
        "rising-sine:amp=90,offset=0,freq=100,phase_deg=0,raised=0,duration=0.1,rate=5000",
        &[],
    );
    let report = temp("period.json");
    let err = cli(&[
        "close-loop",
        "--data",
        fitted.to_str().unwrap(),
        "--validate",
        other.to_str().unwrap(),
        "--report",
        report.to_str().unwrap(),
    ])
    .unwrap_err();
    assert!(!report.exists(), "no report for a refused command line");
    assert!(
        err.contains("--validate") && err.contains("period100.csv") && err.contains("2.000000e-4"),
        "{err}"
    );
}

/// A `--validate` record that is one of the `--data` records (by name, or its samples under
/// another name) is refused before any fit when the samples it is scored on were fitted: fitted
/// whole, or validated from before `--end`. The same file fitted up to `--end` and validated from
/// there on is another run's stand-in and is accepted.
#[test]
fn a_validate_record_the_fit_has_seen_is_refused_by_name() {
    let fitted = plant_record("relaxing-stack", "seen20", 20, 90.0, 20, 0.0, 0.1);
    let copy = temp("seen-copy.csv");
    std::fs::copy(&fitted, &copy).unwrap();
    let run = |validate: &Path, extra: &[&str]| {
        let mut args = vec!["--validate", validate.to_str().unwrap()];
        args.extend_from_slice(extra);
        close_loop_cli("seen", fitted.to_str().unwrap(), &args)
    };
    for (validate, extra, said) in [
        (&fitted, &[][..], "fitted whole"),
        (&copy, &[][..], "fitted whole"),
        (
            &fitted,
            &["--end", "0.06", "--validate-start", "0.05"][..],
            "fitted up to --end 0.06 s and validated from --validate-start 0.05 s",
        ),
    ] {
        let (done, report, _) = run(validate, extra);
        let err = done.unwrap_err();
        assert!(!report.exists(), "no report for a refused command line");
        assert!(
            err.contains(&format!(
                "--validate: {} is the --data record {}, {said}",
                validate.display(),
                fitted.display()
            )),
            "{err}"
        );
    }
    let (done, report, _) = run(&fitted, &["--end", "0.06", "--validate-start", "0.06"]);
    done.unwrap();
    assert!(json(&report)["steps"].is_array());
}
