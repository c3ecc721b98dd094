//! `close-loop` on data with an undeclared effect: host-sim's f64 plants carry the effect, the base
//! model (symmetric Bouc-Wen) does not. For each effect the right one must be named first and the RMS
//! must fall to at most a quarter of the base model's; on effect-free data nothing may be added; with
//! two effects both are found.

use clap::Parser;
use host_sim::cli::{run, Cli};
use host_sim::close_loop::{close_loop, parameter_file, read_records, CloseLoopSettings, Outcome};
use std::path::PathBuf;

fn temp(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("host_sim_close_loop_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

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

/// Seed 001's Case I stage (symmetric, the base model's own family) under `signal`, 2 nm sensor
/// noise, plus `effects`; close-loop scored from `start_s`.
fn stage(name: &str, signal: &str, start_s: f64, effects: &[&str]) -> Outcome {
    let mut all = vec!["noise:rms_m=2e-9,seed=7"];
    all.extend_from_slice(effects);
    let path = simulate(name, "stage-case1", signal, &all);
    let records = read_records(&path, None, None, None, None).unwrap();
    let settings = CloseLoopSettings {
        start_s,
        ..Default::default()
    };
    close_loop(&records, &settings).unwrap()
}

fn rms(o: &Outcome, which: &str) -> f64 {
    o.report[which]["rms"].as_f64().unwrap()
}

fn added(o: &Outcome) -> Vec<String> {
    o.report["effects_added"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_str().unwrap().to_string())
        .collect()
}

fn check_single(o: &Outcome, effect: &str) {
    let report = serde_json::to_string_pretty(&o.report["steps"]).unwrap();
    let names = added(o);
    assert_eq!(
        names.first().map(String::as_str),
        Some(effect),
        "first effect named: {names:?}\n{report}"
    );
    let (before, after) = (rms(o, "before"), rms(o, "after"));
    eprintln!("{effect}: rms {before:.4e} -> {after:.4e} m, added {names:?}");
    assert!(
        after <= 0.25 * before,
        "{effect}: rms {before:.4e} -> {after:.4e} (must be <= 0.25x)\n{report}"
    );
}

#[test]
fn creep_is_named_and_removed() {
    let o = stage(
        "creep.csv",
        COSINE,
        0.0,
        &["creep:tau=0.05/0.5,weight=0.03/0.03"],
    );
    check_single(&o, "creep");
}

#[test]
fn drift_is_named_and_removed() {
    let o = stage("drift.csv", TWO_TONE, 0.5, &["drift:rate=1e-7"]);
    check_single(&o, "drift");
}

#[test]
fn delay_is_named_and_removed() {
    let o = stage("delay.csv", TWO_TONE, 0.5, &["delay:s=2e-3"]);
    check_single(&o, "delay");
}

#[test]
fn asymmetry_is_named_and_removed() {
    let o = stage("asym.csv", COSINE, 0.0, &["electrostriction:per_v=0.004"]);
    check_single(&o, "asymmetry");
}

#[test]
fn nothing_is_added_to_effect_free_data() {
    let o = stage("clean.csv", TWO_TONE, 0.5, &[]);
    assert!(
        added(&o).is_empty(),
        "added {:?}\n{}",
        added(&o),
        serde_json::to_string_pretty(&o.report["steps"]).unwrap()
    );
    // The base model reaches the noise floor (2 nm) on its own family.
    assert!(rms(&o, "after") < 2.5e-9, "{}", rms(&o, "after"));
}

#[test]
fn two_effects_are_both_found() {
    // With a constant-mean input a creep element of long τ is exactly a drift (x ≈ mean(u)·t/τ);
    // the two-tone's slow component moves the mean, which tells them apart.
    let o = stage(
        "creep_drift.csv",
        TWO_TONE,
        0.5,
        &["creep:tau=0.05/0.5,weight=0.03/0.03", "drift:rate=1e-7"],
    );
    let names = added(&o);
    assert!(
        names.contains(&"creep".to_string()) && names.contains(&"drift".to_string()),
        "{names:?}\n{}",
        serde_json::to_string_pretty(&o.report["steps"]).unwrap()
    );
    assert!(rms(&o, "after") <= 0.25 * rms(&o, "before"));
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
    check_single(&o, "dynamics");
}

/// Two-axis raster on the XY stage with cross-axis coupling in the measurement.
#[test]
fn coupling_is_named_and_removed() {
    let path = simulate(
        "coupling.csv",
        "xy-stage",
        "raster:x_low=0,x_high=100,line_freq=5,y_low=0,y_high=100,duration=1,rate=5000",
        &["coupling:xy=0.03,yx=0.03", "noise:rms_m=2e-9,seed=4"],
    );
    let records = read_records(&path, None, Some("ux_V,uy_V"), Some("x_m,y_m"), None).unwrap();
    // Firmware-invertible base sets, so that the parameter file is one the firmware builds.
    let settings = CloseLoopSettings {
        invertible: true,
        ..Default::default()
    };
    let o = close_loop(&records, &settings).unwrap();
    check_single(&o, "coupling");
    // The final model's parameter file, with its [x.effects]/[y.effects] tables, passes the
    // firmware's own check.
    let text = parameter_file(&o, "coupling.csv", 0.0);
    assert!(text.contains("[y.effects]"), "{text}");
    host_sim::identify::firmware_check("coupling.toml", text.as_bytes()).unwrap();
}
