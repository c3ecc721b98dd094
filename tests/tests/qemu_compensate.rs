//! The firmware under QEMU and `host-sim compensate` command the same voltages for the same stage
//! file and reference record.
//!
//! The test writes a two-axis reference record (x a triangle, y a sine, 400 ticks at the stage's
//! 10 kHz) to its own temporary directory, builds the firmware's `replay` image for
//! thumbv7em-none-eabihf with `PIEZO_PARAMS=firmware/params/xy-stage-effects.toml` (creep, even
//! term, delay, drift, coupling) and `PIEZO_REFERENCE=` that record, runs it under QEMU
//! (mps2-an386, `firmware/run-qemu.sh`), reads the commanded voltage of every tick from its frame
//! lines (`frame <k>: x ref … cmd <V> V … | y ref … cmd <V> V …`, printed in Rust's shortest
//! round-trip form, so exact), runs `host_sim::compensate::compensate` on the same files, and
//! compares tick by tick: |Δu| ≤ 4 f32 ulps of the voltage (the same core code on both sides;
//! only the compiler's instruction choice may differ).
//!
//! The image is built in `<target dir>/qemu-compensate` (its own target directory: the outer
//! `cargo test` holds the lock of the workspace's), so after the first build only the firmware
//! crate is rebuilt (≈ 5 s; the first build ≈ 25 s on two cores).
//!
//! Skipped, with a message on stderr, when `qemu-system-arm` or the thumbv7em-none-eabihf target
//! is not installed (`.ci/run` installs both).

use std::path::Path;
use std::process::Command;
use std::time::Instant;

use integration_tests::qemu::{build_replay, missing_tools, say, workspace};

const TICKS: usize = 400;
const RATE_HZ: f64 = 10_000.0;

fn write_reference(path: &Path) {
    let mut text = String::from("t_s,rx_m,ry_m\n");
    for k in 0..TICKS {
        let t = k as f64 / RATE_HZ;
        // x: 5 → 30 µm triangle at 25 Hz; y: 17 ± 12 µm sine at 25 Hz.
        let p = (t * 25.0).rem_euclid(1.0);
        let tri = if p < 0.5 { 2.0 * p } else { 2.0 - 2.0 * p };
        let x = 5e-6 + 25e-6 * tri;
        let y = 17e-6 + 12e-6 * (2.0 * std::f64::consts::PI * 25.0 * t).sin();
        text.push_str(&format!("{t},{x},{y}\n"));
    }
    std::fs::write(path, text).expect("write the reference record");
}

/// The two `cmd <V> V` fields of each `frame` line.
fn voltages_of(log: &str) -> Vec<[f32; 2]> {
    log.lines()
        .filter(|l| l.starts_with("frame "))
        .map(|l| {
            let mut fields = l.split(" cmd ").skip(1).map(|rest| {
                let value = rest.split(' ').next().unwrap_or("");
                value
                    .parse::<f32>()
                    .unwrap_or_else(|_| panic!("no voltage in `{l}`"))
            });
            let x = fields.next().unwrap_or_else(|| panic!("no x in `{l}`"));
            let y = fields.next().unwrap_or_else(|| panic!("no y in `{l}`"));
            [x, y]
        })
        .collect()
}

#[test]
fn qemu_image_commands_the_voltages_of_host_sim_compensate() {
    if let Some(why) = missing_tools() {
        say(&format!("qemu_compensate: SKIPPED: {why}"));
        return;
    }
    let root = workspace();
    let dir = std::env::temp_dir().join(format!("qemu_compensate_{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temporary directory");
    let reference = dir.join("reference.csv");
    write_reference(&reference);
    let params = root.join("firmware/params/xy-stage-effects.toml");

    let started = Instant::now();
    let elf = build_replay(&params, &reference, "qemu-compensate");
    let built = started.elapsed();

    let run = Command::new(root.join("firmware/run-qemu.sh"))
        .arg(&elf)
        .output()
        .expect("run firmware/run-qemu.sh");
    let log = String::from_utf8_lossy(&run.stdout);
    assert!(
        run.status.success(),
        "the replay image failed ({}):\n{log}\n{}",
        run.status,
        String::from_utf8_lossy(&run.stderr)
    );
    let ran = started.elapsed() - built;
    let firmware = voltages_of(&log);

    let host = host_sim::compensate::compensate(&params, &reference).expect("host-sim compensate");
    assert_eq!(host.voltages_v.len(), 2);
    let [(_, ux), (_, uy)] = [&host.voltages_v[0], &host.voltages_v[1]];
    assert_eq!(firmware.len(), TICKS, "frames in the QEMU log:\n{log}");
    assert_eq!(ux.len(), TICKS);

    let (mut max_v, mut max_ulps) = (0.0f32, 0.0f32);
    for (k, (f, h)) in firmware.iter().zip(ux.iter().zip(uy.iter())).enumerate() {
        for (axis, (a, b)) in [(f[0], *h.0), (f[1], *h.1)].into_iter().enumerate() {
            let ulp = f32::EPSILON * a.abs().max(b.abs()).max(f32::MIN_POSITIVE);
            let d = (a - b).abs();
            (max_v, max_ulps) = (max_v.max(d), max_ulps.max(d / ulp));
            assert!(
                d <= 4.0 * ulp,
                "tick {k}, axis {}: QEMU {a} V, host-sim {b} V",
                ["x", "y"][axis]
            );
        }
    }
    say(&format!(
        "qemu_compensate: {TICKS} ticks × 2 axes, max |Δu| {max_v:e} V ({max_ulps} ulps); \
         limited {} samples, lead {} ticks; build {:.1} s, QEMU {:.2} s",
        host.counts.limited,
        host.lead_ticks,
        built.as_secs_f64(),
        ran.as_secs_f64()
    ));
    let _ = std::fs::remove_dir_all(&dir);
}
