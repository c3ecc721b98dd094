//! The files the tools read: stage files validated as the firmware's check validates them (errors
//! with file, line and key), a record's time column checked where it is read (by every command
//! that reads a record), a leading byte-order mark, values beyond f32, results that are not finite,
//! and a `csv:` signal played to its end.

use clap::Parser;
use host_sim::cli::{run, Cli};
use std::path::{Path, PathBuf};

/// A directory of the test's own, removed when dropped.
fn scratch(name: &str) -> tempfile::TempDir {
    tempfile::Builder::new()
        .prefix(&format!("host_sim_files_{name}_"))
        .tempdir()
        .unwrap()
}

fn cli(args: &[&str]) -> Result<String, String> {
    let mut v = vec!["host-sim"];
    v.extend_from_slice(args);
    run(Cli::try_parse_from(v).map_err(|e| e.to_string())?).map_err(|e| e.to_string())
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

const XY_STAGE: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../firmware/params/xy-stage.toml"
);

/// A two-axis record `t_s,ux_V,uy_V,x_m,y_m`, 400 samples at 10 kHz (a 25 Hz raised cosine
/// 0–120 V, the output 0.3 µm/V), with `edit(row, cells)` applied to each row's cells.
fn record(path: &Path, edit: impl Fn(usize, &mut Vec<String>)) -> PathBuf {
    let mut text = String::from("t_s,ux_V,uy_V,x_m,y_m\n");
    for k in 0..400 {
        let t = k as f64 * 1e-4;
        let u = 60.0 - 60.0 * (2.0 * std::f64::consts::PI * 25.0 * t).cos();
        let mut cells: Vec<String> = [t, u, u, 3e-7 * u, 3e-7 * u]
            .iter()
            .map(|v| v.to_string())
            .collect();
        edit(k, &mut cells);
        text.push_str(&cells.join(","));
        text.push('\n');
    }
    std::fs::write(path, text).unwrap();
    path.into()
}

fn predict(stage: &Path, data: &Path, report: &Path) -> Result<String, String> {
    cli(&[
        "predict",
        "--params",
        s(stage),
        "--data",
        s(data),
        "--u",
        "ux_V,uy_V",
        "--y",
        "x_m,y_m",
        "--report",
        s(report),
    ])
}

/// `XY_STAGE` with the line starting `key = ` replaced by `line`, written to `dir/name`; with the
/// 1-based line number of the change.
fn edited_stage(dir: &Path, name: &str, key: &str, line: &str) -> (PathBuf, usize) {
    let text = std::fs::read_to_string(XY_STAGE).unwrap();
    let at = text
        .lines()
        .position(|l| l.starts_with(&format!("{key} = ")))
        .unwrap();
    let edited: Vec<&str> = text
        .lines()
        .enumerate()
        .map(|(i, l)| if i == at { line } else { l })
        .collect();
    let path = dir.join(name);
    std::fs::write(&path, edited.join("\n")).unwrap();
    (path, at + 1)
}

#[test]
fn predict_refuses_stage_files_the_firmware_refuses() {
    let dir = scratch("stage");
    let dir = dir.path();
    let data = record(&dir.join("rec.csv"), |_, _| {});
    let report = dir.join("p.json");
    predict(Path::new(XY_STAGE), &data, &report).unwrap();
    for (key, line, path) in [
        (
            "sensor_m_per_v",
            "sensor_m_per_v = -1e39",
            "io.sensor_m_per_v",
        ),
        (
            "transfer_time_constant_s",
            "transfer_time_constant_s = nan",
            "x.servo.transfer_time_constant_s",
        ),
        (
            "adc_range_v",
            "adc_range_v = [nan, 10.24]",
            "io.adc_range_v",
        ),
    ] {
        let (stage, at) = edited_stage(dir, "bad.toml", key, line);
        let e = predict(&stage, &data, &report).unwrap_err();
        assert!(
            e.contains(&format!("bad.toml:{at}:")) && e.contains(&format!("`{path}`")),
            "{line}: {e}"
        );
    }
}

/// The four broken time columns, each with the line its error must name: reversed (line 3 is
/// not after line 2), constant, tiny (1e-12 s steps, named at the first, line 3) and a 3 ms gap
/// after row 199
/// (line 201 → 202).
/// A broken time column: its name, t(row) \[s\] and the line its error names.
type BrokenTime = (&'static str, fn(usize) -> f64, usize);

fn broken_time_columns() -> Vec<BrokenTime> {
    vec![
        ("reversed", |k: usize| (400 - k) as f64 * 1e-4, 3),
        ("constant", |_| 0.5, 3),
        ("tiny", |k| k as f64 * 1e-12, 3),
        (
            "gap",
            |k| k as f64 * 1e-4 + if k >= 200 { 3e-3 } else { 0.0 },
            202,
        ),
    ]
}

#[test]
fn time_columns_are_checked_where_every_command_reads_them() {
    let dir = scratch("time");
    let dir = dir.path();
    let out = dir.join("out");
    for (what, time, line) in broken_time_columns() {
        let data = record(&dir.join(format!("{what}.csv")), |k, cells| {
            cells[0] = time(k).to_string();
        });
        let named = |e: &str| e.contains(&format!("{what}.csv:{line}: column 1 (`t_s`)"));
        let e = predict(Path::new(XY_STAGE), &data, &dir.join("p.json")).unwrap_err();
        assert!(named(&e), "predict, {what}: {e}");
        let common = ["--data", s(&data), "--u", "ux_V", "--y", "x_m"];
        let report = dir.join("r.json");
        let mut identify = vec!["identify", "--model", "symmetric"];
        identify.extend(common);
        identify.extend(["--out", s(&out), "--report", s(&report)]);
        let e = cli(&identify).unwrap_err();
        assert!(named(&e), "identify, {what}: {e}");
        let mut close_loop = vec!["close-loop"];
        close_loop.extend(common);
        close_loop.extend(["--out", s(&out), "--report", s(&report)]);
        let e = cli(&close_loop).unwrap_err();
        assert!(named(&e), "close-loop, {what}: {e}");
        let signal = format!("csv:path={}", data.display());
        let e = cli(&[
            "simulate",
            "--plant",
            "xy-stage",
            "--signal",
            &signal,
            "--out",
            s(&out),
        ])
        .unwrap_err();
        assert!(named(&e), "simulate, {what}: {e}");
        // compensate's reference: the same rows as `t_s,rx_m,ry_m`.
        let reference = dir.join(format!("{what}-ref.csv"));
        let text = std::fs::read_to_string(&data).unwrap();
        let rows: Vec<String> = text
            .lines()
            .skip(1)
            .map(|l| {
                let c: Vec<&str> = l.split(',').collect();
                format!("{},{},{}", c[0], c[3], c[4])
            })
            .collect();
        std::fs::write(&reference, format!("t_s,rx_m,ry_m\n{}\n", rows.join("\n"))).unwrap();
        let e = cli(&[
            "compensate",
            "--params",
            XY_STAGE,
            "--reference",
            s(&reference),
            "--out",
            s(&out),
        ])
        .unwrap_err();
        assert!(
            e.contains(&format!("{what}-ref.csv:{line}: column 1 (`t_s`)")),
            "compensate, {what}: {e}"
        );
    }
}

#[test]
fn a_byte_order_mark_is_skipped() {
    let dir = scratch("bom");
    let dir = dir.path();
    let plain = record(&dir.join("plain.csv"), |_, _| {});
    let bom = dir.join("bom.csv");
    let mut bytes = "\u{feff}".as_bytes().to_vec();
    bytes.extend(std::fs::read(&plain).unwrap());
    std::fs::write(&bom, bytes).unwrap();
    let (a, b) = (dir.join("a.json"), dir.join("b.json"));
    predict(Path::new(XY_STAGE), &plain, &a).unwrap();
    predict(Path::new(XY_STAGE), &bom, &b).unwrap();
    let json = |p: &Path| -> serde_json::Value {
        serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap()
    };
    assert_eq!(json(&a)["axes"], json(&b)["axes"]);
}

#[test]
fn values_and_results_that_are_not_finite_are_refused() {
    let dir = scratch("finite");
    let dir = dir.path();
    let report = dir.join("p.json");
    // A measured 1e308 m at sample 5: its squared residual overflows the f64 sum.
    let data = record(&dir.join("huge.csv"), |k, cells| {
        if k == 5 {
            cells[3] = "1e308".into();
        }
    });
    let e = predict(Path::new(XY_STAGE), &data, &report).unwrap_err();
    assert!(
        e.starts_with("x:") && e.contains("sample 5 (t = 0.0005 s") && e.contains("overflows"),
        "{e}"
    );
    assert!(!report.exists(), "no report of a refused score");
    // An input beyond f32 (the core's precision) on line 8, column 3.
    let data = record(&dir.join("wide.csv"), |k, cells| {
        if k == 6 {
            cells[2] = "-1e39".into();
        }
    });
    let e = predict(Path::new(XY_STAGE), &data, &report).unwrap_err();
    assert!(e.contains("wide.csv:8: column 3 (`uy_V`)"), "{e}");
    // NaN and infinite cells.
    for cell in ["NaN", "inf"] {
        let data = record(&dir.join("nan.csv"), |k, cells| {
            if k == 9 {
                cells[4] = cell.into();
            }
        });
        let e = predict(Path::new(XY_STAGE), &data, &report).unwrap_err();
        assert!(e.contains("nan.csv:11: column 5 (`y_m`)"), "{e}");
    }
}

#[test]
fn the_score_refuses_predictions_and_sums_that_are_not_finite() {
    use host_sim::identify::fit_block;
    let t: Vec<f64> = (0..8).map(|k| f64::from(k) * 0.5).collect();
    let measured = vec![1.0; 8];
    let mut predicted = vec![1.5; 8];
    let ok = fit_block(&t, &measured, &predicted, 2).unwrap();
    assert!((ok.rms - 0.5).abs() < 1e-12);
    // A prediction that is not finite: named by index and time, also before the scored range.
    predicted[6] = f64::NAN;
    let e = fit_block(&t, &measured, &predicted, 2).unwrap_err();
    assert_eq!((e.index, e.t_s), (6, 3.0), "{e}");
    assert!(e.to_string().contains("sample 6 (t = 3 s"), "{e}");
    predicted[6] = 1.5;
    // Sums that overflow f64: the squared residual, and the measured outputs' sum.
    let mut huge = predicted.clone();
    huge[4] = -1e300;
    let e = fit_block(&t, &measured, &huge, 2).unwrap_err();
    assert_eq!(e.index, 4, "{e}");
    assert!(e.to_string().contains("overflows"), "{e}");
    let big = vec![f64::MAX; 8];
    let e = fit_block(&t, &big, &big, 0).unwrap_err();
    assert_eq!(e.index, 1, "{e}");
}

#[test]
fn a_csv_signal_plays_the_whole_file() {
    let dir = scratch("signal");
    let dir = dir.path();
    // 2 s of voltages at 1 kHz (2000 samples, the last at 1.999 s).
    let voltages = dir.join("voltages.csv");
    let text: String = (0..2000)
        .map(|k| format!("{},{}\n", f64::from(k) * 1e-3, f64::from(k) * 1e-2))
        .collect();
    std::fs::write(&voltages, format!("t_s,u_V\n{text}")).unwrap();
    let out = dir.join("out.csv");
    let run = |signal: String| {
        cli(&[
            "simulate",
            "--plant",
            "stage",
            "--signal",
            &signal,
            "--out",
            s(&out),
        ])
        .unwrap();
        let table = host_sim::csv::read_csv(&out).unwrap();
        *table.column("t_s").unwrap().last().unwrap()
    };
    let whole = run(format!("csv:path={},rate=1000", voltages.display()));
    assert_eq!(whole, 1.999);
    let cut = run(format!(
        "csv:path={},rate=1000,duration=1",
        voltages.display()
    ));
    assert_eq!(cut, 0.999);
}

/// Column units: the suffixes of every quantity (ms, mV, µm, …) are converted; a suffix that is
/// unknown, missing or of another quantity is refused naming the column and what the suffix is;
/// metres written under a `_um` header make a 36 pm stroke, which the reader warns of and the
/// stage file's check refuses (naming the stroke and asking for the unit).
#[test]
fn column_units_are_converted_checked_and_a_wrong_unit_is_refused() {
    let dir = scratch("units");
    let dir = dir.path();
    let identify = |data: &Path, t: &str, u: &str, y: &str, out: &Path| {
        let report = out.with_extension("json");
        cli(&[
            "identify",
            "--data",
            s(data),
            "--t",
            t,
            "--u",
            u,
            "--y",
            y,
            "--model",
            "symmetric",
            "--out",
            s(out),
            "--report",
            s(&report),
        ])
    };
    // `record` with a header of its own.
    let with_header = |name: &str, header: &str, scale: [f64; 5]| {
        let path = record(&dir.join(name), |_, cells| {
            for (c, f) in cells.iter_mut().zip(scale) {
                *c = (c.parse::<f64>().unwrap() * f).to_string();
            }
        });
        let text = std::fs::read_to_string(&path).unwrap();
        let (_, rest) = text.split_once('\n').unwrap();
        std::fs::write(&path, format!("{header}\n{rest}")).unwrap();
        path
    };
    // Milliseconds, millivolts and micrometres: the same set as seconds, volts and metres.
    let si = with_header("si.csv", "t_s,ux_V,uy_V,x_m,y_m", [1.0; 5]);
    let scaled = with_header(
        "scaled.csv",
        "t_ms,ux_mV,uy_mV,x_µm,y_µm",
        [1e3, 1e3, 1e3, 1e6, 1e6],
    );
    let (a, b) = (dir.join("si.toml"), dir.join("scaled.toml"));
    identify(&si, "t_s", "ux_V", "x_m", &a).unwrap();
    identify(&scaled, "t_ms", "ux_mV", "x_µm", &b).unwrap();
    let k1 = |p: &Path| {
        let (file, _) = piezo_stage::StageFile::load(p).unwrap();
        file.x.static_map.unwrap().k1_m_per_v
    };
    assert!(
        (k1(&a) / k1(&b) - 1.0).abs() < 1e-3,
        "{} vs {}",
        k1(&a),
        k1(&b)
    );
    // Unknown, missing, of another quantity: refused, naming the column and why.
    for (header, y, says) in [
        (
            "t_s,ux_V,uy_V,x_furlong,y_m",
            "x_furlong",
            "has an unknown unit suffix `furlong`",
        ),
        ("t_s,ux_V,uy_V,xpos,y_m", "xpos", "has no unit suffix"),
        (
            "t_s,ux_V,uy_V,x_V,y_m",
            "x_V",
            "its unit is a voltage, --y needs a length or a force",
        ),
    ] {
        let path = with_header(&format!("{y}.csv"), header, [1.0; 5]);
        let err = identify(&path, "t_s", "ux_V", y, &dir.join("bad.toml")).unwrap_err();
        assert!(
            err.contains(says) && err.contains(&format!("`{y}`")) && err.contains("µm"),
            "{err}"
        );
    }
    // Metres under a micrometre header: a 36 pm stroke, refused by the stage file's check.
    let wrong = with_header("wrong.csv", "t_s,ux_V,uy_V,x_um,y_um", [1.0; 5]);
    let err = identify(&wrong, "t_s", "ux_V", "x_um", &dir.join("wrong.toml")).unwrap_err();
    assert!(
        err.contains("x.static_map.k1_m_per_v") && err.contains("outside the 1e-8–1e-2 m"),
        "{err}"
    );
    let warnings =
        host_sim::identify::scale_warnings(&wrong, "ux_V", &[0.0, 120.0], "x_um", &[0.0, 3.6e-11]);
    assert!(
        warnings.len() == 1 && warnings[0].contains("`x_um` spans 3.600e-11 m"),
        "{warnings:?}"
    );
}
