//! The round trip: simulated stage → identify → close-loop → firmware image → captured frames →
//! identify again.
//!
//! 1. host-sim's f64 XY stage (`simulate --plant xy-stage`) with creep no model declares and 2 nm
//!    sensor noise, both axes driven by the same raised cosine 0–120 V;
//! 2. `identify --u ux_V,uy_V --y x_m,y_m --invertible` on that record: the first fit;
//! 3. `close-loop` on the same record: the base model refitted with the effect it lacks (creep);
//! 4. the firmware's `replay` image built with that stage file (`PIEZO_PARAMS`) and a two-axis
//!    reference record (`PIEZO_REFERENCE`) runs under QEMU: its loop (inverse effect chain,
//!    compensators, guard, DAC codes) drives the in-firmware plant (`firmware/src/plant.rs`) and
//!    reads it back through the ADC codes and the sensor scale, printing a frame every tick;
//! 5. `capture` turns the QEMU output into the CSV `identify` reads;
//! 6. `identify` on the capture.
//!
//! The in-firmware plant is not host-sim's: it is the stage file's own base model (Bouc-Wen, static
//! map) integrated by explicit Euler sub-steps, behind a 50 µs lag, 16-bit DAC and ADC codes, and
//! without creep. So the capture fit is compared with what the two plants share: the base loop and
//! the static gain. The tolerances, and what each one catches, are at the constants below.
//! The tracking error of the captured frames is checked too, sensor against reference.
//!
//! Everything runs in the test's own temporary directory (removed at the end). The image is built
//! in `<target dir>/round-trip` (its own target directory: the outer `cargo test` holds the lock of
//! the workspace's). Skipped, with a message on stderr, when `qemu-system-arm` or the
//! thumbv7em-none-eabihf target is not installed (`.ci/run` installs both).

use clap::Parser;
use host_sim::cli::{run, Cli};
use host_sim::csv::read_csv;
use piezo_core::effects::EffectParams;
use piezo_core::{BoucWen, BoucWenParams, ModelState, StaticMap, StaticModel};
use piezo_stage::StageFile;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use integration_tests::qemu::{build_replay, missing_tools, say, workspace};

/// The stage file whose `[stage]` and `[io]` (20 kHz loop, DAC8563 + 24 V/V, ADS8681 + 10 µm/V)
/// the fits carry over.
const STAGE: &str = "firmware/params/xy-stage.toml";
/// Identification record: raised cosine 0–120 V at 1 Hz on both axes, 6 s at 5 kHz (30 000
/// samples per axis: six seconds let close-loop's held-out blocks see the creep settle).
const ID_SIGNAL: &str = "sine:amp=60,offset=60,freq=1,phase_deg=-90,duration=6,rate=5000";
/// The reference the image tracks: 1.5 s at the stage file's loop rate.
const REFERENCE_S: f64 = 1.5;

/// The stage file's loop rate \[Hz\].
fn rate_hz() -> f64 {
    let (file, _) = piezo_stage::StageFile::load(&workspace().join(STAGE)).expect(STAGE);
    f64::from(file.stage.loop_rate_hz)
}

/// Runs a host-sim command line as the binary would.
fn host_sim(args: &[&str]) -> String {
    let mut v = vec!["host-sim"];
    v.extend_from_slice(args);
    let cli = Cli::try_parse_from(&v).unwrap_or_else(|e| panic!("{}: {e}", v.join(" ")));
    run(cli).unwrap_or_else(|e| panic!("{}: {e}", v.join(" ")))
}

fn s(p: &Path) -> &str {
    p.to_str().expect("UTF-8 path")
}

/// `identify` or `close-loop` on a two-axis record, `[stage]` and `[io]` from `stage`.
fn fit_two_axes(command: &str, data: &Path, stage: &Path, out: &Path, report: &Path) -> String {
    let mut args = vec![command, "--data", s(data)];
    if command == "identify" {
        args.extend(["--model", "symmetric"]);
    }
    args.extend(["--u", "ux_V,uy_V", "--y", "x_m,y_m", "--invertible"]);
    args.extend(["--stage", s(stage), "--out", s(out), "--report", s(report)]);
    host_sim(&args)
}

/// Removes the test's directory when dropped (also when an assertion fails).
struct TempDir(PathBuf);

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// One axis's base model as fitted.
#[derive(Clone, Copy, Debug)]
struct Base {
    bouc_wen: BoucWenParams,
    map: StaticMap,
    fit_rms_m: f64,
    /// The axis carries effects (creep, …) besides the base model.
    effects: bool,
}

fn bases(path: &Path) -> [Base; 2] {
    let text = std::fs::read_to_string(path).expect("read a stage file");
    let file = StageFile::parse(s(path), &text).unwrap_or_else(|e| panic!("{e}"));
    let axis = |a: &piezo_stage::Axis| Base {
        bouc_wen: a.bouc_wen.expect("a Bouc-Wen axis"),
        map: a.static_map.expect("a static map"),
        fit_rms_m: a.identified.as_ref().map_or(f64::NAN, |p| p.fit_rms_m),
        effects: a.effects != EffectParams::default(),
    };
    [
        axis(&file.x),
        axis(file.y.as_ref().expect("a two-axis stage file")),
    ]
}

/// The model's output along `u_v`, from rest at its first input.
fn run_model(base: &Base, u_v: &[f32]) -> Vec<f32> {
    let bw = BoucWen::with_input_range(base.bouc_wen, 0.0, 120.0, 1e3).expect("Bouc-Wen set");
    let model = StaticModel::new(bw, base.map).expect("static model");
    let mut state = ModelState::at_rest(u_v[0]);
    u_v.iter().map(|&u| model.step(&mut state, u)).collect()
}

/// A test path over the identified range: major loop 0–120 V, then minor loops of decreasing
/// amplitude around 60 V (1 V steps).
fn loop_path() -> Vec<f32> {
    let mut corners = vec![0.0f32, 120.0, 0.0, 120.0];
    for amplitude in [40.0, 20.0, 10.0] {
        corners.extend([60.0 - amplitude, 60.0 + amplitude]);
    }
    let mut path = vec![0.0];
    for pair in corners.windows(2) {
        let (from, to) = (pair[0], pair[1]);
        let n = (to - from).abs().ceil() as usize;
        path.extend((1..=n).map(|i| from + (to - from) * i as f32 / n as f32));
    }
    path
}

/// Max |Δy| between two models over [`loop_path`] and the loop's stroke (of `a`).
fn model_distance(a: &Base, b: &Base) -> (f64, f64) {
    let path = loop_path();
    let (ya, yb) = (run_model(a, &path), run_model(b, &path));
    let d = ya
        .iter()
        .zip(&yb)
        .map(|(p, q)| f64::from((p - q).abs()))
        .fold(0.0, f64::max);
    let lo = ya.iter().copied().fold(f32::INFINITY, f32::min);
    let hi = ya.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    (d, f64::from(hi - lo))
}

/// Two-axis reference at the loop rate: per axis a raised cosine between 10 % and 90 % of the
/// stroke whose amplitude shrinks (nested loops), x at 2 Hz, y at 1.4 Hz from a lower start.
fn write_reference(path: &Path, strokes: [(f64, f64); 2]) -> usize {
    let ticks = (REFERENCE_S * rate_hz()).round() as usize;
    let mut text = String::from("t_s,rx_m,ry_m\n");
    let shape = |t: f64, f: f64, (lo, hi): (f64, f64)| {
        let envelope = 1.0 - 0.6 * t / REFERENCE_S;
        let c = 0.5 * (1.0 - (2.0 * std::f64::consts::PI * f * t).cos());
        // From rest at the bottom of the stroke (0 V) up to 10 % in the first 0.1 s.
        let ramp = 0.5 * (1.0 - (std::f64::consts::PI * (t / 0.1).min(1.0)).cos());
        lo + (hi - lo) * (0.1 * ramp + 0.8 * envelope * c)
    };
    for k in 0..ticks {
        let t = k as f64 / rate_hz();
        let x = shape(t, 2.0, strokes[0]);
        let y = shape(t, 1.4, strokes[1]);
        text.push_str(&format!("{t},{x},{y}\n"));
    }
    std::fs::write(path, text).expect("write the reference record");
    ticks
}

#[test]
fn identify_close_loop_firmware_capture_identify() {
    if let Some(why) = missing_tools() {
        say(&format!("round_trip: SKIPPED: {why}"));
        return;
    }
    let started = Instant::now();
    let root = workspace();
    let dir = TempDir(std::env::temp_dir().join(format!("round_trip_{}", std::process::id())));
    std::fs::create_dir_all(&dir.0).expect("temporary directory");
    let file = |name: &str| dir.0.join(name);
    let stage = root.join(STAGE);

    // 1. The simulated stage with undeclared creep and 2 nm noise.
    let record = file("identification.csv");
    host_sim(&[
        "simulate",
        "--plant",
        "xy-stage",
        "--signal",
        ID_SIGNAL,
        "--effect",
        "creep:tau=0.1/1,weight=0.02/0.02",
        "--effect",
        "noise:rms_m=2e-9,seed=5",
        "--out",
        s(&record),
    ]);
    let simulated = started.elapsed();

    // 2. The first fit.
    let first = file("first.toml");
    fit_two_axes("identify", &record, &stage, &first, &file("first.json"));
    let first_fit = bases(&first);
    let identified = started.elapsed();

    // 3. close-loop: the base model and the effects it lacks.
    let closed = file("closed.toml");
    let closed_summary = fit_two_axes("close-loop", &record, &stage, &closed, &file("closed.json"));
    say(&format!("round_trip: close-loop: {closed_summary}"));
    let closed_fit = bases(&closed);
    let looped = started.elapsed();

    // 4. The replay image with that stage file tracks a reference drawn over 10–90 % of each
    //    axis's stroke (of the image's own model).
    let strokes = closed_fit.map(|b| {
        let path = loop_path();
        let y = run_model(&b, &path);
        let lo = y.iter().copied().fold(f32::INFINITY, f32::min);
        let hi = y.iter().copied().fold(f32::NEG_INFINITY, f32::max);
        (f64::from(lo), f64::from(hi))
    });
    let reference = file("reference.csv");
    let ticks = write_reference(&reference, strokes);
    let elf = build_replay(&closed, &reference, "round-trip");
    let built = started.elapsed();
    let run_qemu = Command::new(root.join("firmware/run-qemu.sh"))
        .arg(&elf)
        .env("QEMU_TIMEOUT", "300")
        .output()
        .expect("run firmware/run-qemu.sh");
    let log_text = String::from_utf8_lossy(&run_qemu.stdout).to_string();
    let log = file("qemu.log");
    std::fs::write(&log, &log_text).expect("write the QEMU log");
    let tail: Vec<&str> = log_text.lines().rev().take(3).collect();
    assert!(
        run_qemu.status.success(),
        "the replay image failed ({}): {tail:?}\n{}",
        run_qemu.status,
        String::from_utf8_lossy(&run_qemu.stderr)
    );
    let emulated = started.elapsed();

    // 5. Capture.
    let capture = file("capture.csv");
    let summary = host_sim(&["capture", "--log", s(&log), "--out", s(&capture)]);
    say(&format!("round_trip: capture: {summary}"));
    let table = read_csv(&capture).expect("read the capture");
    let col = |name: &str| table.column(name).expect("capture column").to_vec();
    // One frame per tick; each row a tick's voltage with the next tick's reading, so one row
    // fewer than frames.
    assert_eq!(table.rows(), ticks - 1, "one frame per tick");

    // 6. identify on the capture.
    let again = file("capture.toml");
    fit_two_axes("identify", &capture, &stage, &again, &file("capture.json"));
    let capture_fit = bases(&again);
    let refitted = started.elapsed();

    let ux = col("ux_V");
    assert!(
        ux.iter().all(|u| (0.0..=120.0).contains(u)) && ux.iter().any(|&u| u > 60.0),
        "ux_V holds stack volts (0–120 V), not DAC volts or codes"
    );
    for (i, name) in ["x", "y"].into_iter().enumerate() {
        let (r, y) = (col(&format!("r{name}_m")), col(&format!("{name}_m")));
        let (lo, hi) = strokes[i];
        let stroke = hi - lo;
        // Tracking: each row holds r_k with the reading that answers tick k's command
        // (sensor_{k+1}); the first 10 ms (the rise from rest) are left out.
        let skip = (0.01 * rate_hz()) as usize;
        let e: Vec<f64> = (skip..r.len()).map(|k| y[k] - r[k]).collect();
        let rms = (e.iter().map(|v| v * v).sum::<f64>() / e.len() as f64).sqrt();
        let max = e.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        // The capture's own floor: the 50 µs lag (≈ 0.5 ticks of the sensor's motion; the
        // rows pair each command with the reading that answers it) and the ADC's 3.125 nm step
        // (10.24 V / 2¹⁵ · 10 µm/V, uniform).
        let motion = ((1..y.len()).map(|k| (y[k] - y[k - 1]).powi(2)).sum::<f64>()
            / (y.len() - 1) as f64)
            .sqrt();
        let floor = ((0.5 * motion).powi(2) + (3.125e-9f64).powi(2) / 12.0).sqrt();
        let (f, c, a) = (first_fit[i], closed_fit[i], capture_fit[i]);
        // The image's plant runs the image's stage file: the other axis of that file is what a
        // swap of the axes would show.
        let other = closed_fit[1 - i];
        let (d_first, loop_stroke) = model_distance(&f, &a);
        let (d_closed, _) = model_distance(&c, &a);
        let (d_other, _) = model_distance(&other, &a);
        let (d_first_closed, _) = model_distance(&f, &c);
        let rel = |p: f32, q: f32| f64::from((p - q).abs() / q.abs());
        let k2a = |b: &Base| b.map.k2_m_per_h * b.bouc_wen.a;
        say(&format!(
            "round_trip {name}: stroke {:.2} µm; tracking rms {:.2} nm, max {:.1} nm ({:.3} % / {:.3} % of the stroke{})\n  \
             first fit   {:?} {:?} fit rms {:.2} nm\n  \
             close-loop  {:?} {:?} fit rms {:.2} nm, effects: {}\n  \
             capture fit {:?} {:?} fit rms {:.2} nm (capture floor {:.2} nm)\n  \
             capture vs first: k1 {:+.3} %, k2·A {:+.3} %, loop {:.1} nm ({:.3} % of the {:.2} µm loop); \
             vs close-loop: k1 {:+.3} %, loop {:.1} nm ({:.3} %); vs the image's other axis: loop {:.1} nm; \
             close-loop vs first: loop {:.1} nm",
            stroke * 1e6,
            rms * 1e9,
            max * 1e9,
            100.0 * rms / stroke,
            100.0 * max / stroke,
            if c.effects { "; the image inverts effects its plant lacks" } else { "" },
            f.bouc_wen,
            f.map,
            f.fit_rms_m * 1e9,
            c.bouc_wen,
            c.map,
            c.fit_rms_m * 1e9,
            c.effects,
            a.bouc_wen,
            a.map,
            a.fit_rms_m * 1e9,
            floor * 1e9,
            100.0 * (a.map.k1_m_per_v / f.map.k1_m_per_v - 1.0),
            100.0 * (k2a(&a) / k2a(&f) - 1.0),
            d_first * 1e9,
            100.0 * d_first / loop_stroke,
            loop_stroke * 1e6,
            100.0 * (a.map.k1_m_per_v / c.map.k1_m_per_v - 1.0),
            d_closed * 1e9,
            100.0 * d_closed / loop_stroke,
            d_other * 1e9,
            d_first_closed * 1e9,
        ));

        // The image tracks its reference. Its plant is its own base model behind a 50 µs lag:
        // the error is the lag and the Euler integration, ≤ 0.2 % RMS, 1 % max. Where the stage
        // file also carries effects (close-loop's creep), the image inverts them and its plant
        // has none, so the error is that effect's displacement: creep of 2 + 2 % of the stack's
        // motion, ≤ 3 % RMS, 6 % max.
        let (rms_limit, max_limit) = if c.effects {
            (0.03, 0.06)
        } else {
            (0.002, 0.01)
        };
        assert!(
            rms <= rms_limit * stroke && max <= max_limit * stroke,
            "{name}: tracking error rms {rms:e} m, max {max:e} m over a {stroke:e} m stroke"
        );
        // The capture fit reaches the capture's floor: the sensor a 50 µs lag behind the command
        // (which the symmetric model does not declare; the fit absorbs part of it into the loop)
        // and the ADC step. Measured 0.16–0.19 × that floor.
        assert!(
            a.fit_rms_m <= floor,
            "{name}: capture fit rms {:e} m, floor {floor:e} m",
            a.fit_rms_m
        );
        // The capture fit is the image's plant: its static gain within 1 % of the stage file's
        // (a wrong sensor scale, or volts against codes, moves it by the whole factor), its
        // loop within 0.5 % of the stroke over 0–120 V and nested minor loops.
        assert!(
            rel(a.map.k1_m_per_v, c.map.k1_m_per_v) <= 0.01,
            "{name}: k1 {:e} from the capture, {:e} in the image's stage file",
            a.map.k1_m_per_v,
            c.map.k1_m_per_v
        );
        assert!(
            d_closed <= 0.005 * loop_stroke,
            "{name}: capture loop {d_closed:e} m from the image's model"
        );
        // … and within the first fit's: the same base loop and static gain. When close-loop
        // adds creep it refits the base beside it: the first fit had absorbed part of the creep
        // (weights 0.02 + 0.02 of the stroke) into k1 and the loop. So k1 within 5 %, and the
        // loop within 2 % of the stroke, or 5 % when the image's set carries effects.
        assert!(
            rel(a.map.k1_m_per_v, f.map.k1_m_per_v) <= 0.05,
            "{name}: k1 {:e} from the capture, {:e} from the first fit",
            a.map.k1_m_per_v,
            f.map.k1_m_per_v
        );
        let first_limit = if c.effects { 0.05 } else { 0.02 };
        assert!(
            d_first <= first_limit * loop_stroke,
            "{name}: capture loop {d_first:e} m from the first fit's (limit {first_limit} of \
             the {loop_stroke:e} m stroke)"
        );
        // The axes are not swapped: each capture axis is nearer its own axis of the image's
        // stage file than the other one.
        assert!(
            d_closed < d_other,
            "{name}: the capture's {name} loop is nearer the image's other axis \
             ({d_other:e} m) than its own ({d_closed:e} m)"
        );
    }
    say(&format!(
        "round_trip: {:.1} s: simulate {:.1} s, identify {:.1} s, close-loop {:.1} s, build {:.1} s, QEMU {:.1} s, capture + identify {:.1} s",
        started.elapsed().as_secs_f64(),
        simulated.as_secs_f64(),
        (identified - simulated).as_secs_f64(),
        (looped - identified).as_secs_f64(),
        (built - looped).as_secs_f64(),
        (emulated - built).as_secs_f64(),
        (refitted - emulated).as_secs_f64()
    ));
}
