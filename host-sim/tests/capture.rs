//! `host-sim capture` on a real QEMU log excerpt and on defmt (probe-rs) output: columns, time base,
//! values as printed, and gap, restart and malformed-line handling.

use clap::Parser;
use host_sim::capture::{parse_log, run, AxisChoice, CaptureArgs, CaptureError};
use host_sim::cli::{Cli, Command};
use host_sim::csv::read_csv;
use std::path::{Path, PathBuf};

/// Output of the QEMU image built with `--features qemu,frames-all`, run by `firmware/run-qemu.sh`
/// (the boot line, frames 0–9, then the image's closing lines; frames 10–3999 cut out).
const QEMU_EXCERPT: &str = "\
piezo-firmware qemu: parameters xy-stage 2 (params/xy-stage.toml), fnv1a32 0x6d433f5b, loop 10000 Hz, one frame every 1 ticks
frame 0: x ref 0.000019 m cmd 10 V sensor 0 m | y ref 0.0000039999995 m cmd 10 V sensor 0 m
frame 1: x ref 0.000019094246 m cmd 20 V sensor 0.0000025437498 m | y ref 0.00000406 m cmd 13.582346 V sensor 0.0000025781248 m
frame 2: x ref 0.00001918849 m cmd 30 V sensor 0.000005475 m | y ref 0.00000412 m cmd 13.781105 V sensor 0.000003859375 m
frame 3: x ref 0.000019282726 m cmd 40 V sensor 0.000008503124 m | y ref 0.0000041799995 m cmd 13.979803 V sensor 0.0000040843747 m
frame 4: x ref 0.00001937695 m cmd 50 V sensor 0.000011584375 m | y ref 0.000004239999 m cmd 14.178449 V sensor 0.000004165625 m
frame 5: x ref 0.000019471161 m cmd 60 V sensor 0.000014706249 m | y ref 0.000004299999 m cmd 14.377044 V sensor 0.00000423125 m
frame 6: x ref 0.000019565352 m cmd 63.763157 V sensor 0.00001786875 m | y ref 0.0000043599994 m cmd 14.575584 V sensor 0.000004290625 m
frame 7: x ref 0.000019659521 m cmd 64.05757 V sensor 0.000019334375 m | y ref 0.0000044199996 m cmd 14.774072 V sensor 0.00000435 m
frame 8: x ref 0.000019753665 m cmd 64.3518 V sensor 0.000019615625 m | y ref 0.00000448 m cmd 14.972507 V sensor 0.000004409375 m
frame 9: x ref 0.000019847777 m cmd 64.64587 V sensor 0.000019734374 m | y ref 0.0000045399993 m cmd 15.170885 V sensor 0.000004471875 m
frames: 4000 received, 0 gaps (0 lost)
compensated  : x rms 11.78027 nm max 18.078936 nm | y rms 10.635003 nm max 12.458259 nm | faults 0 guard after settle 0 limited 7
uncompensated: x rms 2749.6973 nm max 3989.2813 nm | y rms 2554.2773 nm max 3664.626 nm | faults 0 guard after settle 0 limited 0
ratio compensated/uncompensated rms: x 0.0042842063 y 0.004163605 (limit 0.2); limits rms 50 nm, max 100 nm
overrun drill: injected at tick 150: overruns 1, safe entries 1, mode Safe(Overrun), output [99.176346, 42.46912] V held (was [99.176346, 42.46912] V)
PASS
";

/// The board image's log as `probe-rs run` prints it (timestamp, level, location lines), with the
/// board's decimation of 10; the default QEMU image's sample line with its `| wire` suffix.
const PROBE_RS_EXCERPT: &str = "\
      Erasing ✔ 100% [####################] 128.00 KiB
 Finished in 1.9s
0.000000 INFO  parameters xy-stage 2 (params/xy-stage.toml), fnv1a32 0x6d433f5b, loop 10000 Hz, one frame every 10 ticks
└─ board::image::__cortex_m_rt_main @ src/bin/board.rs:41
0.000122 INFO  loop running at 10000 Hz
0.008000 INFO  frame 4294967294: x ref 0.000019 m cmd 10 V sensor 0 m | y ref 0.000004 m cmd 10 V sensor 0 m
└─ board::image::__cortex_m_rt_main @ src/bin/board.rs:110
0.008000 INFO  frame 4294967295: x ref 1.9094246e-5 m cmd 20 V sensor 2.5437498e-6 m | y ref 4.06e-6 m cmd 13.582346 V sensor 2.5781248e-6 m
└─ board::image::__cortex_m_rt_main @ src/bin/board.rs:110
0.008000 INFO  frame 0: x ref 0.00001918849 m cmd 30 V sensor 0.000005475 m | y ref 0.00000412 m cmd 13.781105 V sensor 0.000003859375 m | wire [00, 00, 00, 00]
0.008000 INFO  counters LoopCounters { ticks: 10000, overruns: 0 }
";

/// A directory of its own for one test, removed when dropped.
fn dir(name: &str) -> tempfile::TempDir {
    tempfile::Builder::new()
        .prefix(&format!("host_sim_capture_{name}_"))
        .tempdir()
        .unwrap()
}

/// A file in a test's own directory; the directory goes when this is dropped.
struct Scratch {
    _dir: tempfile::TempDir,
    path: PathBuf,
}

impl std::ops::Deref for Scratch {
    type Target = Path;
    fn deref(&self) -> &Path {
        &self.path
    }
}

fn args(log: &Path, out: &Path) -> CaptureArgs {
    CaptureArgs {
        log: log.into(),
        out: out.into(),
        axis: AxisChoice::Both,
        rate: None,
        decimation: None,
        allow_gaps: false,
    }
}

/// Runs capture on `text`; returns (result, stderr lines).
fn capture(
    text: &str,
    name: &str,
    tweak: impl FnOnce(&mut CaptureArgs),
) -> (Result<String, String>, Vec<String>, Scratch) {
    let d = dir(name);
    let log = d.path().join("decoded.txt");
    std::fs::write(&log, text).unwrap();
    let out = d.path().join("data.csv");
    let mut a = args(&log, &out);
    tweak(&mut a);
    let mut stderr = Vec::new();
    let r = run(&a, &mut |l: &str| stderr.push(l.to_string())).map_err(|e| e.to_string());
    (r, stderr, Scratch { _dir: d, path: out })
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-12 * b.abs().max(1e-30)
}

#[test]
fn qemu_log_excerpt_becomes_a_two_axis_csv() {
    let d = dir("cli");
    let log = d.path().join("qemu.log");
    std::fs::write(&log, QEMU_EXCERPT).unwrap();
    let out = d.path().join("xy.csv");
    let cli = Cli::try_parse_from([
        "host-sim",
        "capture",
        "--log",
        log.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ])
    .unwrap();
    assert!(matches!(cli.command, Command::Capture(_)));
    let summary = host_sim::cli::run(cli).unwrap();
    assert!(
        summary.contains("10 frames 0..=9")
            && summary.contains("xy-stage 2")
            && summary.contains("0x6d433f5b")
            && summary.contains("0 gaps"),
        "{summary}"
    );
    let t = read_csv(&out).unwrap();
    assert_eq!(
        t.names,
        ["t_s", "ux_V", "uy_V", "x_m", "y_m", "rx_m", "ry_m"]
    );
    // Each voltage with the next frame's reading (the one that answers it): 9 rows of 10 frames.
    assert_eq!(t.rows(), 9);
    for (k, &ts) in t.column("t_s").unwrap().iter().enumerate() {
        assert!(close(ts, k as f64 * 1e-4), "t_s[{k}] = {ts}");
    }
    // Values exactly as printed: the CSV text reads back to the same f32.
    let f = |s: &str| s.parse::<f32>().unwrap();
    assert_eq!(t.column("uy_V").unwrap()[1] as f32, f("13.582346"));
    assert_eq!(t.column("x_m").unwrap()[3] as f32, f("0.000011584375"));
    assert_eq!(t.column("y_m").unwrap()[8] as f32, f("0.000004471875"));
    assert_eq!(t.column("rx_m").unwrap()[6] as f32, f("0.000019565352"));
    assert_eq!(t.column("ry_m").unwrap()[0] as f32, f("0.0000039999995"));
    assert_eq!(t.column("ux_V").unwrap()[5], 60.0);
    // The file says where it came from.
    let text = std::fs::read_to_string(&out).unwrap();
    assert!(
        text.starts_with("# host-sim capture of") && text.contains("t_s = sequence * 0.0001 s")
    );
}

#[test]
fn one_axis_files_have_u_y_r_columns() {
    for (axis, u, y, r) in [
        // Row 3: frame 3's voltage and reference, frame 4's reading.
        (AxisChoice::X, 40.0, "0.000011584375", "0.000019282726"),
        (
            AxisChoice::Y,
            13.979803,
            "0.000004165625",
            "0.0000041799995",
        ),
    ] {
        let (res, _, out) = capture(QEMU_EXCERPT, &format!("{axis:?}"), |a| a.axis = axis);
        res.unwrap();
        let t = read_csv(&out).unwrap();
        assert_eq!(t.names, ["t_s", "u_V", "y_m", "r_m"]);
        let f = |s: &str| s.parse::<f32>().unwrap();
        assert_eq!(t.column("u_V").unwrap()[3] as f32, u as f32);
        assert_eq!(t.column("y_m").unwrap()[3] as f32, f(y));
        assert_eq!(t.column("r_m").unwrap()[3] as f32, f(r));
    }
}

#[test]
fn probe_rs_defmt_output_with_decimation_and_wrap() {
    let (res, stderr, out) = capture(PROBE_RS_EXCERPT, "probe", |_| {});
    let summary = res.unwrap();
    // At decimation 10 the reading that answers a voltage is not in the log: said once.
    assert_eq!(stderr.len(), 1, "{stderr:?}");
    assert!(
        stderr[0].contains("at decimation 10") && stderr[0].contains("1 tick (0.0001 s)"),
        "{stderr:?}"
    );
    assert!(summary.contains("1000 Hz per frame"), "{summary}");
    let t = read_csv(&out).unwrap();
    assert_eq!(t.rows(), 3);
    // One frame every 10 ticks at 10 kHz: 1 ms per sequence number; the u32 wrap is no gap.
    let ts = t.column("t_s").unwrap();
    assert!(
        close(ts[0], 4294967294.0e-3) && close(ts[2], 4294967296.0e-3),
        "{ts:?}"
    );
    assert_eq!(t.column("x_m").unwrap()[1] as f32, 2.5437498e-6f32);
    assert_eq!(t.column("uy_V").unwrap()[2] as f32, 13.781105f32);
}

#[test]
fn a_gap_stops_the_capture_at_its_line() {
    // Drop frame 4 (line 6).
    let text: String = QEMU_EXCERPT
        .lines()
        .filter(|l| !l.starts_with("frame 4:"))
        .map(|l| format!("{l}\n"))
        .collect();
    let (res, _, out) = capture(&text, "gap", |_| {});
    let e = res.unwrap_err();
    assert!(
        e.contains("decoded.txt:6:")
            && e.contains("expected frame 4, found 5")
            && e.contains("--allow-gaps"),
        "{e}"
    );
    assert!(!out.exists(), "a CSV was written despite the gap");
    match parse_log(Path::new("decoded.txt"), &text, false) {
        Err(CaptureError::Gap {
            line: 6,
            expected: 4,
            found: 5,
            ..
        }) => {}
        other => panic!("{other:?}"),
    }
}

#[test]
fn allow_gaps_keeps_true_time_marks_segments_and_reports() {
    // Drop frames 4 and 7; frame 9's y sensor is NaN (a failed read).
    let text: String = QEMU_EXCERPT
        .lines()
        .filter(|l| !["frame 4:", "frame 7:"].iter().any(|p| l.starts_with(p)))
        .map(|l| {
            if l.starts_with("frame 9:") {
                format!("{}\n", l.replace("sensor 0.000004471875 m", "sensor NaN m"))
            } else {
                format!("{l}\n")
            }
        })
        .collect();
    let (res, _, out) = capture(&text, "nan_strict", |_| {});
    let e = res.unwrap_err();
    assert!(e.contains("decoded.txt:6:"), "gap first: {e}");

    let (res, stderr, out2) = capture(&text, "allow", |a| a.allow_gaps = true);
    let summary = res.unwrap();
    assert!(!out.exists());
    assert!(
        summary.contains("3 gaps (3 frames lost)")
            && summary.contains("decoded.txt:6: 1 missing from frame 4")
            && summary.contains("decoded.txt:8: 1 missing from frame 7")
            && summary.contains("decoded.txt:9: 1 missing from frame 9")
            && summary.contains("4 rows written"),
        "{summary}"
    );
    // Each gap on stderr, then the summary.
    assert_eq!(stderr.len(), 4, "{stderr:?}");
    assert!(
        stderr[0].contains("decoded.txt:6: gap, 1 frames missing from frame 4"),
        "{stderr:?}"
    );
    let t = read_csv(&out2).unwrap();
    assert_eq!(t.names.last().unwrap(), "segment_1");
    let ts: Vec<f64> = t
        .column("t_s")
        .unwrap()
        .iter()
        .map(|v| (v * 1e4).round())
        .collect();
    // Frames 0, 1, 2, 3, 5, 6, 8 are there: a row for each frame followed by the next one
    // (0, 1, 2 and 5), its voltage with that next frame's reading.
    assert_eq!(ts, [0.0, 1.0, 2.0, 5.0]);
    assert_eq!(t.column("segment_1").unwrap(), &[0.0, 0.0, 0.0, 1.0]);
    assert_eq!(t.column("ux_V").unwrap()[3], 60.0);
    assert_eq!(
        t.column("x_m").unwrap()[3] as f32,
        "0.00001786875".parse::<f32>().unwrap()
    );

    // NaN alone, without --allow-gaps: an error naming the line and the field.
    let nan_only = QEMU_EXCERPT.replace("sensor 0.000004471875 m", "sensor NaN m");
    let (res, ..) = capture(&nan_only, "nan", |_| {});
    let e = res.unwrap_err();
    assert!(
        e.contains("decoded.txt:11:") && e.contains("y sensor"),
        "{e}"
    );
}

#[test]
fn malformed_frame_lines_name_file_and_line() {
    for (bad, what) in [
        (
            "frame 3: x ref 0.0x1 m cmd 40 V sensor 0 m | y ref 0 m cmd 1 V sensor 0 m",
            "x ref",
        ),
        ("frame 3: x ref 0 m cmd 40 V sensor 0 m", "y axis missing"),
        ("frame 3: x ref 0 m cmd 40 V sens", "x axis"),
        (
            "frame 3: x ref 0 m cmd 40 mV sensor 0 m | y ref 0 m cmd 1 V sensor 0 m",
            "x axis",
        ),
        (
            "frame 99999999999: x ref 0 m cmd 40 V sensor 0 m | y ref 0 m cmd 1 V sensor 0 m",
            "sequence",
        ),
    ] {
        let text = QEMU_EXCERPT.replacen(QEMU_EXCERPT.lines().nth(4).unwrap(), bad, 1);
        let (res, ..) = capture(&text, "malformed", |_| {});
        let e = res.unwrap_err();
        assert!(
            e.contains("decoded.txt:5: malformed frame line") && e.contains(what),
            "{bad}: {e}"
        );
    }
}

#[test]
fn restart_no_rate_and_no_frames_are_errors() {
    let twice = format!("{QEMU_EXCERPT}{QEMU_EXCERPT}");
    let (res, ..) = capture(&twice, "twice", |_| {});
    let e = res.unwrap_err();
    assert!(
        e.contains("decoded.txt:18:") && e.contains("second boot line"),
        "{e}"
    );
    let no_boot: String = QEMU_EXCERPT
        .lines()
        .skip(1)
        .map(|l| format!("{l}\n"))
        .collect();
    let back = format!("{no_boot}{no_boot}");
    let (res, ..) = capture(&back, "back", |a| a.rate = Some(1e4));
    let e = res.unwrap_err();
    assert!(
        e.contains("decoded.txt:17:") && e.contains("goes back from 9 to 0"),
        "{e}"
    );
    let (res, ..) = capture(&no_boot, "norate", |_| {});
    assert!(res.unwrap_err().contains("--rate"));
    let (res, stderr, out) = capture(&no_boot, "rate", |a| {
        a.rate = Some(2e4);
        a.decimation = Some(2);
    });
    res.unwrap();
    assert!(
        stderr.len() == 1 && stderr[0].contains("at decimation 2"),
        "{stderr:?}"
    );
    assert!(close(
        read_csv(&out).unwrap().column("t_s").unwrap()[9],
        9.0e-4
    ));
    let (res, ..) = capture("PASS\n", "none", |_| {});
    assert!(res.unwrap_err().contains("no frame lines"));
    // One frame at decimation 1: no reading answers its voltage, so no row.
    let one: String = QEMU_EXCERPT
        .lines()
        .take(2)
        .map(|l| format!("{l}\n"))
        .collect();
    let (res, _, out) = capture(&one, "one", |_| {});
    let e = res.unwrap_err();
    assert!(
        e.contains("decoded.txt: 1 frames but no two consecutive"),
        "{e}"
    );
    assert!(!out.exists());
}
