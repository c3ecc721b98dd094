//! On target and settling over the command link, against the QEMU image's simulated stage.
//!
//! The stage file is the built-in one with the simulated stage's mechanics declared: its
//! first-order lag τ = 50 µs (`firmware/src/plant.rs`, `LAG_TIME_CONSTANT_S`) as an overdamped
//! mode with poles at 1/τ and 5/τ (ω = √5/τ, ζ = 3/√5), in `[x.effects]` and `[y.effects]`.
//! After its upload `link step` moves both axes to 2 µm, then to 18 µm, then to 6 µm
//! (feed-forward) with every frame recorded: each move ends on target, the firmware's flags in
//! the frames (bits 2 and 3) are exactly the on-target rule evaluated on the frames' readings
//! and references (|y\[k\] − r\[k−1\]| ≤ tolerance for N ticks, from the first reading outside
//! the band), the status reports the same settling time, and the settling times of the 18 µm
//! and 6 µm steps are within 20 % of `host-sim settle`'s prediction from the stage file.
//!
//! Skipped, with a message, when `qemu-system-arm` or the thumbv7em-none-eabihf target is
//! missing.

#![allow(clippy::needless_range_loop)] // axis indices run over parallel per-axis arrays

mod common;

use common::{build_link_image, connect, firmware_dir, run_link_image, shut_down, TempDir};
use host_sim::link::{upload, Client};
use host_sim::link_step::{link_step_cmd, StepArgs};
use integration_tests::qemu::{missing_tools, say};
use piezo_core::{OnTarget, OnTargetState};
use piezo_link::Frame;
use std::path::Path;

/// One frame of `link step --frames`: sequence, references, voltages, readings, flags.
struct Row {
    reference_m: [f32; 2],
    sensor_m: [f32; 2],
    flags: u8,
}

fn read_frames(path: &Path) -> Vec<Row> {
    let text = std::fs::read_to_string(path).expect("frames CSV");
    let mut lines = text.lines();
    assert_eq!(
        lines.next(),
        Some("sequence,rx_m,ry_m,ux_V,uy_V,x_m,y_m,flags")
    );
    lines
        .map(|l| {
            let c: Vec<&str> = l.split(',').collect();
            let f = |i: usize| c[i].parse::<f32>().expect("number");
            Row {
                reference_m: [f(1), f(2)],
                sensor_m: [f(5), f(6)],
                flags: c[7].parse().expect("flags"),
            }
        })
        .collect()
}

/// Steps to `to_m` with the frames in `dir`; checks the flags against the frames and returns
/// the settling time per axis \[ticks\] and the band.
fn step(client: &mut Client, dir: &Path, name: &str, to_m: f32) -> ([u32; 2], [OnTarget; 2]) {
    let frames = dir.join(format!("{name}.csv"));
    let args = StepArgs {
        to: format!("{to_m:e}"),
        tolerance: None,
        timeout: 0.5,
        frames: Some(frames.clone()),
    };
    let out = link_step_cmd(client, &args).expect("link step");
    say(&format!("link_step: {name}: {out}"));
    let json: serde_json::Value = serde_json::from_str(&out).unwrap();
    let settle = [0, 1].map(|i| json["settle_ticks"][i].as_u64().expect("settled") as u32);
    let status = client.status().unwrap();
    let band = status
        .on_target
        .map(|s| OnTarget::new(s.tolerance_m, s.ticks).unwrap());
    for i in 0..2 {
        let s = status.on_target[i];
        assert!(s.on_target, "{name}: axis {i} on target after the move");
        assert_eq!(s.settle_ticks, Some(settle[i]), "{name}: axis {i}");
    }
    // The flags are the rule on the frames: frame k's reading against frame k − 1's reference,
    // from the first reading outside the band (before it the device's run carries over from
    // the previous hold).
    let rows = read_frames(&frames);
    assert!(rows.len() > 20, "{name}: {} frames", rows.len());
    for i in 0..2 {
        let mut state = OnTargetState::default();
        let mut outside_seen = false;
        let mut flagged = 0;
        for k in 1..rows.len() {
            let r = rows[k - 1].reference_m[i];
            let y = rows[k].sensor_m[i];
            let host = band[i].observe(&mut state, y, r);
            outside_seen |= (y - r).abs() > band[i].tolerance_m;
            let device = rows[k].flags & Frame::on_target_flag(i) != 0;
            if outside_seen {
                assert_eq!(host, device, "{name}: axis {i}, frame {k}: y {y:e} r {r:e}");
                flagged += u32::from(device);
            }
        }
        assert!(outside_seen, "{name}: axis {i} never left the band");
        assert!(flagged >= 1, "{name}: axis {i} never flagged");
        assert_eq!(state.settle_ticks(), settle[i], "{name}: axis {i}");
    }
    (settle, band)
}

/// The built-in stage file with the simulated stage's 50 µs lag as an overdamped mode (poles at
/// 1/τ and 5/τ: ω² = 5/τ², 2ζω = 6/τ).
fn stage_file() -> String {
    let text = std::fs::read_to_string(firmware_dir().join("params/xy-stage.toml")).unwrap();
    let tau = 50e-6f64;
    let omega = 5f64.sqrt() / tau;
    let zeta = 3.0 / 5f64.sqrt();
    let effects = |axis: &str| {
        format!(
            "\n[{axis}.effects]\nmode_frequency_hz = {:?}\nmode_damping = {:?}\n",
            (omega / (2.0 * std::f64::consts::PI)) as f32,
            zeta as f32
        )
    };
    format!("{text}{}{}", effects("x"), effects("y"))
}

#[test]
fn a_step_settles_as_the_stage_file_predicts() {
    if let Some(why) = missing_tools() {
        say(&format!("link_step: SKIPPED: {why}"));
        return;
    }
    let elf = build_link_image();
    let dir = TempDir(std::env::temp_dir().join(format!("link_step_{}", std::process::id())));
    std::fs::create_dir_all(&dir.0).expect("temporary directory");
    let (mut qemu, port) = run_link_image(&elf);
    let mut client = connect(port);

    let params = dir.0.join("xy-stage-lag.toml");
    std::fs::write(&params, stage_file()).unwrap();
    upload(&mut client, &params).expect("upload");
    let bytes = std::fs::read(&params).unwrap();
    let set = piezo_stage::FirmwareSet::from_bytes("xy-stage-lag.toml", &bytes).unwrap();

    let mut from_m = 2e-6f32;
    step(&mut client, &dir.0, "to-2um", from_m);
    for to_m in [18e-6f32, 6e-6] {
        let name = format!("to-{}um", (to_m * 1e6).round());
        let (measured, band) = step(&mut client, &dir.0, &name, to_m);
        let predicted = host_sim::settle::predict(&set, [from_m; 2], [to_m; 2], None, 0.5, false)
            .expect("prediction");
        for i in 0..2 {
            assert_eq!(
                predicted.band[i], band[i],
                "the firmware runs the file's band"
            );
            let p = predicted.settle_ticks[i].expect("predicted to settle");
            let m = measured[i];
            say(&format!(
                "link_step: {from_m:e} -> {to_m:e} m, axis {i}: settling {m} ticks on QEMU, \
                 {p} predicted ({:+.1} %)",
                100.0 * (f64::from(m) - f64::from(p)) / f64::from(p)
            ));
            assert!(
                (f64::from(m) - f64::from(p)).abs() <= 0.2 * f64::from(p),
                "{name}, axis {i}: {m} ticks measured, {p} predicted"
            );
        }
        from_m = to_m;
    }
    shut_down(&mut client, &mut qemu);
}
