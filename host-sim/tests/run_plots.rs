//! The figures of a run (`compensate --plot`, `link track --plot`, `link excite --plot`) and the
//! effects and the set `predict` names: each figure is written, non-empty, and names its series;
//! a figure path that is neither `.svg` nor `.png` is refused naming `--plot` before anything is
//! written.

use clap::Parser;
use host_sim::cli::{run, Cli};
use host_sim::record::RecordTable;
use std::path::{Path, PathBuf};

fn params(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../firmware/params")
        .join(name)
}

/// A directory of the test's own, removed when dropped.
fn scratch(name: &str) -> tempfile::TempDir {
    tempfile::Builder::new()
        .prefix(&format!("host_sim_run_plots_{name}_"))
        .tempdir()
        .unwrap()
}

fn run_args(args: &[&str]) -> Result<String, String> {
    run(Cli::try_parse_from(args).map_err(|e| e.to_string())?).map_err(|e| e.to_string())
}

/// `compensate` of a triangle on the XY stage file with effects, drawn to `plot`.
fn compensate(dir: &Path, plot: &str, extra: &[&str]) -> Result<String, String> {
    let stage = params("xy-stage-effects.toml");
    let (reference, out, plot) = (dir.join("ref.csv"), dir.join("u.csv"), dir.join(plot));
    let mut args = vec![
        "host-sim",
        "compensate",
        "--params",
        stage.to_str().unwrap(),
        "--signal",
        "triangle:low=6,high=30,freq=5,duration=0.4",
        "--reference",
        reference.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--plot",
        plot.to_str().unwrap(),
    ];
    args.extend(extra);
    run_args(&args)
}

fn svg_text(path: &Path) -> String {
    let svg = std::fs::read_to_string(path).unwrap();
    assert!(
        svg.starts_with("<svg") && svg.len() > 10_000,
        "{}",
        svg.len()
    );
    svg
}

#[test]
fn compensate_draws_reference_voltages_prediction_and_error() {
    let scratch = scratch("compensate");
    let dir = scratch.path();
    let summary = compensate(dir, "c.svg", &["--settle", "0.05"]).unwrap();
    // The model's own prediction of its compensator's voltages lies on the reference to f32
    // rounding once the start from rest is over.
    let rms: Vec<f64> = summary
        .split(" rms ")
        .skip(1)
        .map(|s| {
            s.split(' ')
                .next()
                .unwrap()
                .trim_end_matches(',')
                .parse()
                .unwrap()
        })
        .collect();
    assert_eq!(rms.len(), 2, "{summary}");
    assert!(rms.iter().all(|&e| e < 1e-9), "{summary}");
    let svg = svg_text(&dir.join("c.svg"));
    for name in [
        "x axis: reference and predicted position",
        "y axis: stack voltage commanded",
        "tracking error (predicted − reference)",
        "reference",
        "predicted",
        "stack voltage",
        "transient (not scored)",
    ] {
        assert!(svg.contains(name), "the figure lacks {name}");
    }
    // PNG: the same figure rasterised.
    compensate(dir, "c.png", &[]).unwrap();
    let png = std::fs::read(dir.join("c.png")).unwrap();
    assert!(png.starts_with(b"\x89PNG\r\n\x1a\n") && png.len() > 20_000);
}

#[test]
fn a_figure_that_is_neither_svg_nor_png_is_refused_naming_the_option() {
    let scratch = scratch("refused");
    let dir = scratch.path();
    let e = compensate(dir, "c.pdf", &[]).unwrap_err();
    assert!(e.starts_with("--plot") && e.contains(".pdf"), "{e}");
    assert!(!dir.join("u.csv").exists() && !dir.join("c.pdf").exists());
    for sub in ["track", "excite"] {
        let (record, plot) = (dir.join("r.csv"), dir.join("r.jpg"));
        // Refused before connecting (nothing listens on port 1).
        let e = run_args(&[
            "host-sim",
            "link",
            "--connect",
            "127.0.0.1:1",
            sub,
            "--signal",
            "sine",
            "--duration",
            "0.1",
            "--record",
            record.to_str().unwrap(),
            "--plot",
            plot.to_str().unwrap(),
        ])
        .unwrap_err();
        assert!(e.starts_with("--plot") && e.contains(".jpg"), "{sub}: {e}");
        assert!(!record.exists());
    }
}

/// A link record of `n` samples at 10 kHz: `t_s, ux_V, uy_V, x_m, y_m` and, when `tracking`,
/// `rx_m, ry_m`.
fn link_record(n: usize, tracking: bool) -> RecordTable {
    let t_s: Vec<f64> = (0..n).map(|k| k as f64 * 1e-4).collect();
    let wave = |a: f32, b: f32| -> Vec<f32> {
        t_s.iter()
            .map(|&t| a + b * (2.0 * std::f64::consts::PI * 5.0 * t).sin() as f32)
            .collect()
    };
    let mut names = vec!["t_s", "ux_V", "uy_V", "x_m", "y_m"];
    let mut data = vec![
        wave(60.0, 50.0),
        wave(60.0, 40.0),
        wave(15e-6, 12e-6),
        wave(15e-6, 10e-6),
    ];
    if tracking {
        names.extend(["rx_m", "ry_m"]);
        data.extend([wave(15.1e-6, 12e-6), wave(14.9e-6, 10e-6)]);
    }
    RecordTable {
        names: names.into_iter().map(String::from).collect(),
        t_s,
        data,
        segment: None,
    }
}

#[test]
fn link_track_and_excite_draw_their_record() {
    let scratch = scratch("link");
    let dir = scratch.path();
    let track = dir.join("track.svg");
    host_sim::link::plot_record(&track, &link_record(2000, true), true).unwrap();
    let svg = svg_text(&track);
    for name in [
        "x axis: reference and sensor position",
        "y axis: stack voltage commanded",
        "y axis: tracking error (sensor − reference)",
        "sensor",
        "reference",
    ] {
        assert!(svg.contains(name), "the track figure lacks {name}");
    }
    // 0.2 s: too short to leave out the firmware's 0.1 s of settling, scored whole.
    assert!(!svg.contains("transient (not scored)"));
    // 0.5 s: scored as the firmware scores a track, from 0.1 s on, the start-up shaded.
    let long = dir.join("track-long.svg");
    host_sim::link::plot_record(&long, &link_record(5000, true), true).unwrap();
    assert!(svg_text(&long).contains("transient (not scored)"));
    let excite = dir.join("excite.png");
    host_sim::link::plot_record(&excite, &link_record(2000, false), false).unwrap();
    let png = std::fs::read(&excite).unwrap();
    assert!(png.starts_with(b"\x89PNG\r\n\x1a\n") && png.len() > 20_000);
    let excite = dir.join("excite.svg");
    host_sim::link::plot_record(&excite, &link_record(2000, false), false).unwrap();
    let svg = svg_text(&excite);
    for name in [
        "x axis: stack voltage commanded",
        "y axis: sensor",
        "x axis: loop (sensor against commanded voltage)",
        "commanded",
    ] {
        assert!(svg.contains(name), "the excite figure lacks {name}");
    }
    // A track record without its reference columns is refused, naming the option and column.
    let e = host_sim::link::plot_record(&track, &link_record(2000, false), true)
        .unwrap_err()
        .to_string();
    assert!(e.starts_with("--plot") && e.contains("rx_m"), "{e}");
}

/// `predict` of `stage` on a two-axis record; returns stdout and the report.
fn predict(dir: &Path, stage: &str) -> (String, serde_json::Value) {
    let data = dir.join("record.csv");
    let mut text = String::from("t_s,ux_V,uy_V,x_m,y_m\n");
    for k in 0..2000 {
        let t = k as f64 * 1e-4;
        let s = (2.0 * std::f64::consts::PI * 5.0 * t).sin();
        text.push_str(&format!(
            "{t},{},{},{},{}\n",
            60.0 + 50.0 * s,
            60.0 + 40.0 * s,
            15e-6 + 12e-6 * s,
            15e-6 + 10e-6 * s
        ));
    }
    std::fs::write(&data, text).unwrap();
    let (stage, report) = (params(stage), dir.join("predict.json"));
    let out = run_args(&[
        "host-sim",
        "predict",
        "--params",
        stage.to_str().unwrap(),
        "--data",
        data.to_str().unwrap(),
        "--u",
        "ux_V,uy_V",
        "--y",
        "x_m,y_m",
        "--report",
        report.to_str().unwrap(),
    ])
    .unwrap();
    let report = std::fs::read_to_string(report).unwrap();
    (out, serde_json::from_str(&report).unwrap())
}

#[test]
fn predict_names_the_effects_it_ran() {
    let scratch = scratch("predict");
    let dir = scratch.path();
    let (out, report) = predict(dir, "xy-stage-effects.toml");
    assert!(
        out.contains(
            "x: symmetric with effects [creep (Kelvin-Voigt, 1 element), drift (linear), delay, \
             asymmetry, coupling]"
        ),
        "{out}"
    );
    let effects = &report["axes"][0]["effects_ran"];
    assert_eq!(
        effects[0],
        serde_json::json!({"effect": "creep", "form": "Kelvin-Voigt, 1 element"})
    );
    let names: Vec<&str> = effects
        .as_array()
        .unwrap()
        .iter()
        .map(|e| e["effect"].as_str().unwrap())
        .collect();
    assert_eq!(
        names,
        ["creep", "drift", "delay", "asymmetry", "coupling"],
        "{effects}"
    );
    // Without effects: an empty list on each axis, and on stdout.
    let (out, report) = predict(dir, "xy-stage.toml");
    assert!(out.contains("x: symmetric with effects []"), "{out}");
    for axis in 0..2 {
        assert_eq!(report["axes"][axis]["effects_ran"], serde_json::json!([]));
    }
}

/// `predict` names the set it ran first, as the firmware's boot line names its set (capture reads
/// it back), and its report carries the same values under `link status`'s keys.
#[test]
fn predict_names_the_set_it_ran() {
    let scratch = scratch("predict-set");
    let dir = scratch.path();
    let (out, report) = predict(dir, "xy-stage.toml");
    let first = out.lines().next().unwrap();
    let boot = host_sim::capture::parse_boot_line(first, 1)
        .expect("a boot line")
        .unwrap();
    let path = params("xy-stage.toml");
    let set = host_sim::link::model_set(&path).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    assert_eq!(boot.version, "xy-stage 4", "{first}");
    assert_eq!(
        boot.fingerprint,
        Some(host_sim::link::hex32(set.fingerprint())),
        "{first}"
    );
    assert_eq!(
        boot.fnv1a32,
        host_sim::link::hex32(host_sim::link::fnv1a32(&bytes))
    );
    assert_eq!(report["params_version"], "xy-stage 4");
    assert_eq!(report["params_fingerprint"], boot.fingerprint.unwrap());
    assert_eq!(report["params_fnv1a32"], boot.fnv1a32);
}
