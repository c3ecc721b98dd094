//! Iterative learning control: `host-sim learn` against host-sim's XY stage (piezo-reference,
//! which never calls the core), its refusals, and the cut-off rule's margin checked on the
//! learning step itself.

use clap::Parser;
use host_sim::cli::{run, Cli};
use host_sim::csv::{read_csv, write_csv, Table};
use host_sim::demo::run_xy_stage;
use host_sim::effects::Effects;
use host_sim::plant::XyStage;
use piezo_core::{Learning, LearningParams, Trial};
use piezo_stage::StageFile;
use std::path::{Path, PathBuf};

const STACK_FILE: &str = include_str!("../../firmware/params/xy-stage.toml");
const RATE_HZ: f64 = 10_000.0;

/// A directory of the test's own, removed when dropped.
fn scratch(name: &str) -> tempfile::TempDir {
    tempfile::Builder::new()
        .prefix(&format!("host_sim_learn_{name}_"))
        .tempdir()
        .unwrap()
}

/// xy-stage.toml at the tests' loop rate [`RATE_HZ`] (the file's own is 20 kHz) with its maps
/// scaled by `gain` per axis and, per axis, the mode (Hz, ζ) and delay \[s\] given; written to
/// `dir/name`.
fn stage_file(
    dir: &Path,
    name: &str,
    gain: [f64; 2],
    mode: [(f32, f32); 2],
    delay_s: f32,
) -> PathBuf {
    let mut file = StageFile::parse("xy-stage.toml", STACK_FILE).unwrap();
    file.stage.loop_rate_hz = RATE_HZ as f32;
    let axes = [Some(&mut file.x), file.y.as_mut()];
    for ((axis, g), (f, zeta)) in axes.into_iter().zip(gain).zip(mode) {
        let axis = axis.unwrap();
        let map = axis.static_map.as_mut().unwrap();
        map.k1_m_per_v = (f64::from(map.k1_m_per_v) * g) as f32;
        map.k2_m_per_h = (f64::from(map.k2_m_per_h) * g) as f32;
        axis.effects.mode_frequency_hz = f;
        axis.effects.mode_damping = zeta;
        axis.effects.delay_s = delay_s;
    }
    let path = dir.join(name);
    std::fs::write(&path, file.to_toml("learn test stage")).unwrap();
    path
}

fn write_table(path: &Path, names: &[&str], columns: Vec<Vec<f64>>) {
    let table = Table {
        path: path.into(),
        names: names.iter().map(|s| s.to_string()).collect(),
        columns,
    };
    write_csv(path, &table).unwrap();
}

fn cli(args: &[&str]) -> Result<String, String> {
    let mut v = vec!["host-sim"];
    v.extend_from_slice(args);
    run(Cli::try_parse_from(v).map_err(|e| e.to_string())?).map_err(|e| e.to_string())
}

/// One `host-sim learn` step: `command` and `measured` to `next`, its report to `report`
/// (`--periodic` when `periodic`).
fn learn_step(
    params: &Path,
    reference: &Path,
    [command, measured]: [&Path; 2],
    [next, report]: [&Path; 2],
    periodic: bool,
) -> Result<String, String> {
    let mut args = vec![
        "learn",
        "--params",
        p(params),
        "--reference",
        p(reference),
        "--command",
        p(command),
        "--measured",
        p(measured),
        "--out",
        p(next),
        "--report",
        p(report),
    ];
    if periodic {
        args.push("--periodic");
    }
    cli(&args)
}

/// [`learn_step`] with `--periodic`, which must succeed.
fn learn_periodic(
    params: &Path,
    reference: &Path,
    command: &Path,
    measured: &Path,
    next: &Path,
    report: &Path,
) {
    learn_step(params, reference, [command, measured], [next, report], true).unwrap();
}

fn p(path: &Path) -> &str {
    path.to_str().unwrap()
}

/// A 20 Hz triangle between 10 % and 90 % of each axis's stroke, faded in from rest over 5 ms,
/// 0.1 s at 10 kHz: `t_s,rx_m,ry_m`.
fn write_reference(path: &Path, stroke_m: [f64; 2]) -> [Vec<f64>; 2] {
    let n = 1000;
    let t: Vec<f64> = (0..n).map(|k| k as f64 / RATE_HZ).collect();
    let r = [0, 1].map(|a| {
        t.iter()
            .map(|&t| {
                let fade = if t < 5e-3 {
                    0.5 - 0.5 * (std::f64::consts::PI * t / 5e-3).cos()
                } else {
                    1.0
                };
                fade * host_sim::demo::triangle(0.1 * stroke_m[a], 0.9 * stroke_m[a], 20.0, t)
            })
            .collect::<Vec<f64>>()
    });
    write_table(
        path,
        &["t_s", "rx_m", "ry_m"],
        vec![t, r[0].clone(), r[1].clone()],
    );
    r
}

/// Plays the command file `u` on the XY stage (from rest, zero-order hold, no effects); writes
/// `t_s,ux_V,uy_V,x_m,y_m` to `y`; returns the RMS error of the worse axis \[m\].
fn play(plant: &XyStage, u: &Path, y: &Path, r: &[Vec<f64>; 2]) -> f64 {
    play_with(plant, &Effects::default(), u, y, r)
}

/// As [`play`], the record measured with the plant's `effects` (e.g. sensor noise); the RMS
/// returned is the true position's.
fn play_with(plant: &XyStage, effects: &Effects, u: &Path, y: &Path, r: &[Vec<f64>; 2]) -> f64 {
    let table = read_csv(u).unwrap();
    let voltages = [
        table.column("ux_V").unwrap().to_vec(),
        table.column("uy_V").unwrap().to_vec(),
    ];
    let truth = run_xy_stage(plant, &voltages, RATE_HZ, &Effects::default()).unwrap();
    let out = run_xy_stage(plant, &voltages, RATE_HZ, effects).unwrap();
    let t = table.column("t_s").unwrap().to_vec();
    let rms = (0..2)
        .map(|a| {
            let sq: f64 = truth[a]
                .iter()
                .zip(&r[a])
                .map(|(y, r)| (y - r).powi(2))
                .sum();
            (sq / r[a].len() as f64).sqrt()
        })
        .fold(0.0, f64::max);
    write_table(
        y,
        &["t_s", "ux_V", "uy_V", "x_m", "y_m"],
        vec![
            t,
            voltages[0].clone(),
            voltages[1].clone(),
            out[0].clone(),
            out[1].clone(),
        ],
    );
    rms
}

/// No trial from `first` on is more than 1.1 × the one before.
fn assert_no_rise(errors: &[f64], first: usize) {
    for k in first.max(1)..errors.len() {
        assert!(
            errors[k] <= 1.1 * errors[k - 1],
            "trial {k}: {:.3e} m after {:.3e} m: {errors:?}",
            errors[k],
            errors[k - 1]
        );
    }
}

/// Ten learning steps on `plant` with the stage file `params`: trial 0 plays `compensate`'s
/// command for a 20 Hz triangle (`write_reference`), each next trial the table `host-sim learn`
/// wrote from the last; each step's report must give the error of the trial just played. Returns
/// the RMS error of each of the 11 trials (worse axis) \[m\].
fn learning_trials(plant: &XyStage, dir: &Path, params: &Path) -> Vec<f64> {
    learning_trials_measured(plant, dir, params, None)
}

/// As [`learning_trials`], each trial measured with a sensor noise of this RMS \[m\] (a new
/// seed per trial) when given; the errors returned are the true position's.
fn learning_trials_measured(
    plant: &XyStage,
    dir: &Path,
    params: &Path,
    noise_rms_m: Option<f64>,
) -> Vec<f64> {
    let stroke_m = plant.static_gain().map(|g| g * 38e-6);
    let reference = dir.join("r.csv");
    let r = write_reference(&reference, stroke_m);
    let mut command = dir.join("u0.csv");
    cli(&[
        "compensate",
        "--params",
        p(params),
        "--reference",
        p(&reference),
        "--out",
        p(&command),
    ])
    .unwrap();
    let mut errors = Vec::new();
    for k in 0..=10 {
        let measured = dir.join(format!("y{k}.csv"));
        let mut effects = Effects::default();
        if let Some(rms) = noise_rms_m {
            effects
                .add_spec(&format!("noise:rms_m={rms},seed={}", k + 7))
                .unwrap();
        }
        errors.push(play_with(plant, &effects, &command, &measured, &r));
        if k == 10 {
            break;
        }
        let next = dir.join(format!("u{}.csv", k + 1));
        let report = dir.join(format!("step{k}.json"));
        learn_step(
            params,
            &reference,
            [&command, &measured],
            [&next, &report],
            false,
        )
        .unwrap();
        // The report's error is that of the trial just played.
        let json: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
        let reported = (0..2)
            .map(|a| json[["x", "y"][a]]["rms_m"].as_f64().unwrap())
            .fold(0.0, f64::max);
        if noise_rms_m.is_none() {
            assert!(
                (reported / errors[k] - 1.0).abs() < 1e-3,
                "{reported} vs {}",
                errors[k]
            );
        }
        assert_eq!(json["iteration"], k + 1);
        command = next;
    }
    println!("RMS error per trial [m]: {errors:?}");
    errors
}

#[test]
fn learning_converges_on_the_reference_plant() {
    let scratch = scratch("converges");
    let plant = XyStage::default();
    // The platform model with the stage's first modes (±10 % of what the plant has is well
    // inside the rule's ±20 %).
    let params = stage_file(
        scratch.path(),
        "stage.toml",
        plant.static_gain(),
        [(3200.0, 0.03), (2200.0, 0.03)],
        0.0,
    );
    let errors = learning_trials(&plant, scratch.path(), &params);
    assert!(
        errors[10] <= 0.2 * errors[0],
        "after 10 steps {:.3e} m, first {:.3e} m",
        errors[10],
        errors[0]
    );
}

/// A stage file without a mode (as close-loop writes one when its records showed none) on a
/// stage that has its flexure modes (3.2 and 2.2 kHz): the file's claim of no dynamics is not
/// trusted up to the Nyquist frequency, the rule assumes a mode may lie at or above 1/20 of the
/// loop rate. Trusting the claim, the second trial was 5.4× the first and the tenth 500×.
#[test]
fn a_mode_the_stage_file_lacks_does_not_make_the_learning_diverge() {
    let scratch = scratch("unmodelled");
    let plant = XyStage::default();
    let params = stage_file(
        scratch.path(),
        "stage.toml",
        plant.static_gain(),
        [(0.0, 0.0), (0.0, 0.0)],
        0.0,
    );
    let errors = learning_trials(&plant, scratch.path(), &params);
    assert_no_rise(&errors, 1);
    // What stays is the ring of the modes at the triangle's corners, which the file lacks.
    assert!(errors[10] <= 0.5 * errors[0], "{errors:?}");
}

/// A sensor noise of 20 nm RMS, a new draw each trial, on a stage whose error after learning is
/// about 13 nm: learned at full gain, the noise went into the table and trial 3 rose 1.45× above
/// trial 2 (true position); each step now learns the share of the error that stands above the
/// noise it estimates.
#[test]
fn a_trial_at_the_sensor_noise_does_not_fill_the_table_with_it() {
    let scratch = scratch("noise");
    let plant = XyStage::default();
    let params = stage_file(
        scratch.path(),
        "stage.toml",
        plant.static_gain(),
        [(3200.0, 0.03), (2200.0, 0.03)],
        0.0,
    );
    let errors = learning_trials_measured(&plant, scratch.path(), &params, Some(2e-8));
    assert_no_rise(&errors, 2);
    assert!(errors[10] <= 0.2 * errors[0], "{errors:?}");
}

#[test]
fn learn_refuses_records_and_tables_that_do_not_belong() {
    let scratch = scratch("refuses");
    let dir = scratch.path();
    let plant = XyStage::default();
    let gain = plant.static_gain();
    let modes = [(3200.0, 0.03), (2200.0, 0.03)];
    let params = stage_file(dir, "stage.toml", gain, modes, 0.0);
    let reference = dir.join("r.csv");
    let r = write_reference(&reference, gain.map(|g| g * 38e-6));
    let u0 = dir.join("u0.csv");
    cli(&[
        "compensate",
        "--params",
        p(&params),
        "--reference",
        p(&reference),
        "--out",
        p(&u0),
    ])
    .unwrap();
    let y0 = dir.join("y0.csv");
    play(&plant, &u0, &y0, &r);
    let (next, report) = (dir.join("next.csv"), dir.join("step.json"));
    let learn = |params: &Path, reference: &Path, command: &Path, measured: &Path| {
        learn_step(
            params,
            reference,
            [command, measured],
            [&next, &report],
            false,
        )
    };
    let u1 = dir.join("u1.csv");
    learn(&params, &reference, &u0, &y0).unwrap();
    std::fs::rename(dir.join("next.csv"), &u1).unwrap();
    let names_both = |e: &str, a: &Path, b: &Path| {
        let (a, b) = (a.file_name().unwrap(), b.file_name().unwrap());
        assert!(
            e.contains(a.to_str().unwrap()) && e.contains(b.to_str().unwrap()),
            "{e}"
        );
    };
    // A measured record one sample short.
    let y0_table = read_csv(&y0).unwrap();
    let short = dir.join("short.csv");
    write_table(
        &short,
        &["t_s", "x_m", "y_m"],
        [0, 3, 4]
            .iter()
            .map(|&c| y0_table.columns[c][..999].to_vec())
            .collect(),
    );
    let e = learn(&params, &reference, &u0, &short).unwrap_err();
    names_both(&e, &short, &u0);
    assert!(e.contains("999") && e.contains("1000"), "{e}");
    // A measured record at another sample period (same length).
    let slow = dir.join("slow.csv");
    let mut columns: Vec<Vec<f64>> = [0, 3, 4]
        .iter()
        .map(|&c| y0_table.columns[c].clone())
        .collect();
    columns[0].iter_mut().for_each(|t| *t *= 2.0);
    write_table(&slow, &["t_s", "x_m", "y_m"], columns);
    let e = learn(&params, &reference, &u0, &slow).unwrap_err();
    names_both(&e, &slow, &u0);
    assert!(e.contains("period"), "{e}");
    // The learned table with another stage file: one digit of the mode differs.
    let other = stage_file(
        dir,
        "other.toml",
        gain,
        [(3300.0, 0.03), (2200.0, 0.03)],
        0.0,
    );
    let e = learn(&other, &reference, &u1, &y0).unwrap_err();
    names_both(&e, &u1, &other);
    assert!(e.contains("stage.toml") && e.contains("fnv1a32"), "{e}");
    // The learned table with another reference (1 nm higher at one sample).
    let moved = dir.join("moved.csv");
    let r_table = read_csv(&reference).unwrap();
    let mut columns = r_table.columns.clone();
    columns[1][500] += 1e-9;
    write_table(&moved, &["t_s", "rx_m", "ry_m"], columns);
    let e = learn(&params, &moved, &u1, &y0).unwrap_err();
    names_both(&e, &u1, &moved);
    assert!(e.contains("rx_m") && e.contains("0.05"), "{e}");
    // The same table, reference and stage file: accepted, and the next iteration is 2.
    learn(&params, &reference, &u1, &y0).unwrap();
    let text = std::fs::read_to_string(dir.join("next.csv")).unwrap();
    assert!(
        text.starts_with("# host-sim learn: iteration 2\n"),
        "{text:.80}"
    );
}

/// The cut-off rule's promise, checked on the step itself: on a linear plant with the model's
/// delay, the mode at (1 ± t)·f_mode and the gain at either end of the band, one step shrinks
/// every sinusoidal deviation from the compensator's command by at least 1 − margin.
#[test]
fn the_q_rule_margin_holds_for_the_model() {
    let scratch = scratch("rule");
    let dir = scratch.path();
    let (f_mode, zeta, delay_samples) = (2200.0f64, 0.03f64, 1.5f64);
    // A linear stage model: k2 = 0, y = k1·u.
    let path = stage_file(
        dir,
        "linear.toml",
        [1.0; 2],
        [(f_mode as f32, zeta as f32); 2],
        (delay_samples / RATE_HZ) as f32,
    );
    let text = std::fs::read_to_string(&path).unwrap();
    let mut file = StageFile::parse("linear.toml", &text).unwrap();
    file.x.static_map.as_mut().unwrap().k2_m_per_h = 0.0;
    let valid = file.validate().unwrap();
    let axis = valid.axes[0];
    let piezo_stage::AxisChain::Static { effects, .. } = axis.chain else {
        unreachable!()
    };
    let compensator = axis.compensator.unwrap();
    let k1 = f64::from(compensator.model().map().k1_m_per_v);
    let params = LearningParams::default();
    let learning = Learning::new(&compensator, &effects, params).unwrap();
    println!("cut-off {:.0} Hz", learning.cutoff_hz());
    let n = 1000; // 0.1 s: whole periods of every multiple of 10 Hz
    let (offset_v, amplitude_v) = (60.0, 1.0);
    let base = vec![offset_v as f32; n];
    let t = 1.0 / RATE_HZ;
    let mut worst: f64 = 0.0;
    for f in (1..=490).map(|i| 10.0 * i as f64) {
        let w = 2.0 * std::f64::consts::PI * f;
        let command: Vec<f32> = (0..n)
            .map(|j| (offset_v + amplitude_v * (w * j as f64 * t).sin()) as f32)
            .collect();
        let t_tol = f64::from(params.mode_frequency_tolerance);
        for gamma in [params.gain_min, params.gain_max].map(f64::from) {
            for mu in [
                1.0 - t_tol,
                1.0 - t_tol / 2.0,
                1.0,
                1.0 + t_tol / 2.0,
                1.0 + t_tol,
            ] {
                // The plant's steady response: gain γ·k1, the mode at μ·f_mode, delay D.
                let wm = mu * 2.0 * std::f64::consts::PI * f_mode;
                let (re, im) = (wm * wm - w * w, 2.0 * zeta * wm * w);
                let magnitude = wm * wm / (re * re + im * im).sqrt();
                let phase = -im.atan2(re) - w * delay_samples * t;
                let measured: Vec<f32> = (0..n)
                    .map(|j| {
                        let s = (w * j as f64 * t + phase).sin();
                        (gamma * k1 * (offset_v + amplitude_v * magnitude * s)) as f32
                    })
                    .collect();
                // r = what the compensator's command gives the plant: the deviation is the error.
                let reference: Vec<f32> = vec![(gamma * k1 * offset_v) as f32; n];
                let mut next = vec![0.0f32; n];
                learning
                    .step(
                        &Trial {
                            reference_m: &reference,
                            command_v: &command,
                            measured_m: &measured,
                            base_v: &base,
                            periodic: true,
                            noise: None,
                            previous: None,
                            table_v: None,
                        },
                        &mut next,
                    )
                    .unwrap();
                let rms = |v: &[f32]| {
                    (v.iter()
                        .map(|&u| (f64::from(u) - offset_v).powi(2))
                        .sum::<f64>()
                        / n as f64)
                        .sqrt()
                };
                let ratio = rms(&next) / rms(&command);
                worst = worst.max(ratio);
                assert!(
                    ratio <= 1.0 - f64::from(params.margin) + 2e-3,
                    "{f} Hz, gain {gamma}, mode x{mu}: |u_next - u0| / |u - u0| = {ratio:.4}, \
                     rule {:.4}",
                    learning.convergence_factor(f)
                );
            }
        }
    }
    println!("largest contraction {worst:.3}");
    // The rule is not vacuous: somewhere it is close to its bound.
    assert!(worst > 0.5, "{worst}");
}

/// The stage's hysteresis is rate-dependent (the stacks' dielectric lag, τ_v = 2 ms, in the plant)
/// and the stage file says so (`hysteresis_lag_s`, as close-loop writes it). The learning's gain
/// inverts the lag's dynamics (its memory of earlier corrections), not only the one-sample slope
/// (≈ k1: the part of the hysteresis that follows within a sample is b ≈ T/(2τ_v)).
#[test]
fn learning_converges_on_a_stage_with_rate_dependent_hysteresis() {
    let scratch = scratch("lag");
    let mut plant = XyStage::default();
    plant.dielectric_lag_s = 2e-3;
    let params = stage_file(
        scratch.path(),
        "stage.toml",
        plant.static_gain(),
        [(3200.0, 0.03), (2200.0, 0.03)],
        0.0,
    );
    let mut file = StageFile::load(&params).unwrap().0;
    file.x.effects.hysteresis_lag_s = 2e-3;
    file.y.as_mut().unwrap().effects.hysteresis_lag_s = 2e-3;
    std::fs::write(&params, file.to_toml("learn test stage, rate-dependent")).unwrap();
    let errors = learning_trials(&plant, scratch.path(), &params);
    // The first step takes the lag's memory into account: 0.17 of trial 0's error here (0.29
    // with the one-sample slope alone, which is ≈ k1 behind the lag).
    assert!(errors[1] <= 0.25 * errors[0], "{errors:?}");
    assert_no_rise(&errors, 1);
    assert!(
        errors[10] <= 0.2 * errors[0],
        "after 10 steps {:.3e} m, first {:.3e} m: {errors:?}",
        errors[10],
        errors[0]
    );
}

/// A periodic trial learns from the compensator's command of the period it settles to, played
/// in a loop: from rest the command's first quarter period rides the first-loading branch, so
/// the table would jump at the wrap (1.1 V here); the settled period closes on itself (2 mV),
/// and a trial that measured no error gives it back unchanged.
#[test]
fn a_periodic_trial_starts_from_the_settled_period() {
    let scratch = scratch("periodic");
    let dir = scratch.path();
    let params = stage_file(dir, "stage.toml", [1.0; 2], [(0.0, 0.0); 2], 0.0);
    let n = 500;
    let t: Vec<f64> = (0..n).map(|k| k as f64 / RATE_HZ).collect();
    let r: Vec<f64> = t
        .iter()
        .map(|&t| f64::from((19e-6 - 12e-6 * (std::f64::consts::TAU * 20.0 * t).cos()) as f32))
        .collect();
    let reference = dir.join("r.csv");
    write_table(
        &reference,
        &["t_s", "rx_m", "ry_m"],
        vec![t.clone(), r.clone(), r.clone()],
    );
    let from_rest = host_sim::learn::base_command(&params, &reference, false).unwrap();
    let settled = host_sim::learn::base_command(&params, &reference, true).unwrap();
    let wrap = |u: &[f32]| (u[0] - u[n - 1]).abs();
    let largest_step = |u: &[f32]| {
        u.windows(2)
            .map(|w| (w[1] - w[0]).abs())
            .fold(0.0, f32::max)
    };
    for axis in 0..2 {
        let (rest, periodic) = (&from_rest.voltages_v[axis].1, &settled.voltages_v[axis].1);
        println!(
            "axis {axis}: wrap from rest {} V, settled {} V (largest step {} V)",
            wrap(rest),
            wrap(periodic),
            largest_step(periodic)
        );
        assert!(wrap(rest) > 0.5, "{}", wrap(rest));
        assert!(wrap(periodic) < 0.05, "{}", wrap(periodic));
    }
    let command = dir.join("u0.csv");
    write_csv(&command, &settled.to_table()).unwrap();
    let measured = dir.join("y0.csv");
    write_table(&measured, &["t_s", "x_m", "y_m"], vec![t, r.clone(), r]);
    let next = dir.join("u1.csv");
    learn_periodic(
        &params,
        &reference,
        &command,
        &measured,
        &next,
        &dir.join("step.json"),
    );
    let table = read_csv(&next).unwrap();
    for (axis, name) in ["ux_V", "uy_V"].iter().enumerate() {
        let got = table.column(name).unwrap();
        for (j, (&g, &u)) in got.iter().zip(&settled.voltages_v[axis].1).enumerate() {
            assert!((g - f64::from(u)).abs() < 1e-3, "{name}[{j}]: {g} vs {u}");
        }
    }
}

/// A stage file whose gain is 0.6 × the stage's: the compensator's command asks for 1.67 × the
/// voltage and is held at the window. Each step reads the stage's gain from the trial (the
/// model's own output for the command against the measured one), re-solves u_0 for it and
/// divides L's gain by it: the tenth trial is at the nominal file's error (11.4 nm), where it
/// was 476 nm with the file's gain.
#[test]
fn a_stage_file_whose_gain_is_off_learns_as_fast_as_a_right_one() {
    let plant = XyStage::default();
    let modes = [(3200.0, 0.03), (2200.0, 0.03)];
    let run = |scale: f64| {
        let scratch = scratch("gain");
        let gain = plant.static_gain().map(|g| g * scale);
        let params = stage_file(scratch.path(), "stage.toml", gain, modes, 0.0);
        let errors = learning_trials(&plant, scratch.path(), &params);
        let json: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(scratch.path().join("step0.json")).unwrap(),
        )
        .unwrap();
        (errors, json)
    };
    let (nominal, _) = run(1.0);
    let (off, step0) = run(0.6);
    for axis in ["x", "y"] {
        let ratio = step0[axis]["model_gain_ratio"].as_f64().unwrap();
        assert!((ratio - 1.0 / 0.6).abs() < 0.02, "{axis}: {ratio}");
        assert_eq!(step0[axis]["base_resolved"], true);
    }
    assert!(
        off[10] <= 2.0 * nominal[10],
        "gain x0.6: {:.3e} m after 10 steps, nominal {:.3e} m: {off:?}",
        off[10],
        nominal[10]
    );
}

/// The loop a user runs with one file per trial, `--periodic`: a 50 Hz triangle played in a
/// loop on a stage with what its file lacks (the stacks' dielectric lag, τ_v = 2 ms, and a
/// 5 nm sensor noise, a new draw each trial), each trial recording four whole passes after four
/// settling ones; `learn` averages the passes and reads their noise from the spread between them
/// (a measured record of several passes was refused). After ten steps the error is at most
/// 0.2 × the first trial's (or within twice the sensor noise), and no trial rises more than 10 %
/// above the one before, the learning above the cut-off on (its default).
#[test]
fn a_periodic_file_per_trial_loop_converges_on_a_stage_its_file_does_not_describe() {
    let scratch = scratch("periodic_loop");
    let dir = scratch.path();
    let mut plant = XyStage::default();
    plant.dielectric_lag_s = 2e-3;
    let noise_rms_m = 5e-9;
    let params = stage_file(
        dir,
        "stage.toml",
        plant.static_gain(),
        [(3200.0, 0.03), (2200.0, 0.03)],
        0.0,
    );
    let stroke_m = plant.static_gain().map(|g| g * 38e-6);
    let n = 200; // one 50 Hz period at 10 kHz
    let t: Vec<f64> = (0..n).map(|k| k as f64 / RATE_HZ).collect();
    let r = [0, 1].map(|a| {
        t.iter()
            .map(|&t| {
                let v = host_sim::demo::triangle(0.1 * stroke_m[a], 0.9 * stroke_m[a], 50.0, t);
                f64::from(v as f32)
            })
            .collect::<Vec<f64>>()
    });
    let reference = dir.join("r.csv");
    write_table(
        &reference,
        &["t_s", "rx_m", "ry_m"],
        vec![t.clone(), r[0].clone(), r[1].clone()],
    );
    let base = host_sim::learn::base_command(&params, &reference, true).unwrap();
    let mut command = dir.join("u0.csv");
    write_csv(&command, &base.to_table()).unwrap();
    let (settle, record) = (4, 4);
    let mut errors = Vec::new();
    let mut pass_noise = Vec::new();
    for k in 0..=10 {
        let table = read_csv(&command).unwrap();
        let voltages = ["ux_V", "uy_V"].map(|name| {
            let u = table.column(name).unwrap();
            (0..(settle + record) * n)
                .map(|i| u[i % n])
                .collect::<Vec<f64>>()
        });
        let mut effects = Effects::default();
        effects
            .add_spec(&format!("noise:rms_m={noise_rms_m},seed={}", k + 11))
            .unwrap();
        let truth = run_xy_stage(&plant, &voltages, RATE_HZ, &Effects::default()).unwrap();
        let read = run_xy_stage(&plant, &voltages, RATE_HZ, &effects).unwrap();
        let kept = settle * n..(settle + record) * n;
        let rms = (0..2)
            .map(|a| {
                let sq: f64 = kept
                    .clone()
                    .map(|i| (truth[a][i] - r[a][i % n]).powi(2))
                    .sum();
                (sq / (record * n) as f64).sqrt()
            })
            .fold(0.0, f64::max);
        errors.push(rms);
        if k == 10 {
            break;
        }
        let measured = dir.join(format!("y{k}.csv"));
        write_table(
            &measured,
            &["t_s", "x_m", "y_m"],
            vec![
                kept.clone().map(|i| i as f64 / RATE_HZ).collect(),
                read[0][kept.clone()].to_vec(),
                read[1][kept].to_vec(),
            ],
        );
        let next = dir.join(format!("u{}.csv", k + 1));
        let report = dir.join(format!("step{k}.json"));
        learn_periodic(&params, &reference, &command, &measured, &next, &report);
        let json: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
        assert_eq!(json["x"]["noise_from_passes"], true);
        pass_noise.push(json["x"]["noise_rms_m"].as_f64().unwrap());
        command = next;
    }
    println!(
        "RMS error per trial [m]: {errors:?}; noise of the averaged passes [m]: {pass_noise:?}"
    );
    // The averaged record's noise: σ/√(passes) = 2.5 nm (within a third).
    for &s in &pass_noise {
        assert!(
            (s / (noise_rms_m / 2.0) - 1.0).abs() < 0.33,
            "{pass_noise:?}"
        );
    }
    assert_no_rise(&errors, 1);
    assert!(
        errors[10] <= (0.2 * errors[0]).max(2.0 * noise_rms_m),
        "after 10 steps {:.3e} m, first {:.3e} m: {errors:?}",
        errors[10],
        errors[0]
    );
}

/// A close-loop stage file without a mode (`tests/data/relaxing-stack-close-loop.toml`, fitted
/// on 20 and 40 Hz sines of piezo-reference's relaxing stack) learns a 50 Hz triangle on that
/// stack's loop-shaped variant, one file per trial through `learn --periodic` (four passes per
/// trial after one that settles). The triangle's corners ring the stack's 740 Hz mode, and the
/// error gathers at the harmonic nearest it, 700 Hz. The harmonic step's model gate accepted
/// only modes at the cut-off rule's 33 frequencies (12 % apart), none within the mode's width
/// of 740 Hz, so it refused that harmonic every step and the table kept its component: the
/// loop stalled at 0.32× the first trial's error. The gate's set is now 1 % apart.
#[test]
fn a_mode_between_the_rule_s_frequencies_is_learned_at_its_harmonics() {
    let scratch = scratch("mode_between");
    let dir = scratch.path();
    let params =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/relaxing-stack-close-loop.toml");
    let n = 200; // one 50 Hz period at 10 kHz
    let amplitude_m = 12e-6;
    let t: Vec<f64> = (0..n).map(|k| k as f64 / RATE_HZ).collect();
    // A triangle about 0 (the stack is driven ±90 V), rising first.
    let r: Vec<f64> = (0..n)
        .map(|j| {
            let x = 4.0 * j as f64 / n as f64;
            let unit = if x < 1.0 {
                x
            } else if x < 3.0 {
                2.0 - x
            } else {
                x - 4.0
            };
            f64::from((amplitude_m * unit) as f32)
        })
        .collect();
    let reference = dir.join("r.csv");
    write_table(&reference, &["t_s", "r_m"], vec![t.clone(), r.clone()]);
    let base = host_sim::learn::base_command(&params, &reference, true).unwrap();
    let mut command = dir.join("u0.csv");
    write_csv(&command, &base.to_table()).unwrap();
    let (settle, record) = (1, 4);
    let mut errors = Vec::new();
    for k in 0..=10 {
        let u = read_csv(&command).unwrap().column("u_V").unwrap().to_vec();
        let play = dir.join("play.csv");
        let passes = settle + record;
        write_table(
            &play,
            &["t_s", "u_V"],
            vec![
                (0..passes * n).map(|i| i as f64 / RATE_HZ).collect(),
                (0..passes * n).map(|i| u[i % n]).collect(),
            ],
        );
        let raw = dir.join("raw.csv");
        cli(&[
            "simulate",
            "--plant",
            "relaxing-stack-shaped",
            "--signal",
            &format!("csv:path={},hold=zoh,rate=10000", p(&play)),
            "--effect",
            &format!("noise:rms_m=2e-9,seed={}", 100 + k),
            "--out",
            p(&raw),
        ])
        .unwrap();
        let y = read_csv(&raw).unwrap().column("y_m").unwrap().to_vec();
        let kept = settle * n..passes * n;
        let sq: f64 = kept.clone().map(|i| (y[i] - r[i % n]).powi(2)).sum();
        errors.push((sq / (record * n) as f64).sqrt());
        if k == 10 {
            break;
        }
        let measured = dir.join(format!("y{k}.csv"));
        write_table(
            &measured,
            &["t_s", "y_m"],
            vec![
                kept.clone()
                    .map(|i| (i - settle * n) as f64 / RATE_HZ)
                    .collect(),
                y[kept].to_vec(),
            ],
        );
        let next = dir.join(format!("u{}.csv", k + 1));
        learn_periodic(
            &params,
            &reference,
            &command,
            &measured,
            &next,
            &dir.join(format!("step{k}.json")),
        );
        command = next;
    }
    println!("RMS error per trial [m]: {errors:?}");
    assert_no_rise(&errors, 1);
    assert!(
        errors[10] <= 0.2 * errors[0],
        "after 10 steps {:.3e} m, first {:.3e} m: {errors:?}",
        errors[10],
        errors[0]
    );
}
