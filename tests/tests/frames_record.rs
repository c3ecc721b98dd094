//! Frames → record through both of host-sim's paths, `link excite|track --record`
//! ([`Recording`]) and `capture` (the images' text log), which share `host_sim::record`'s rule:
//! row j holds the voltage of tick j and the reading that answers it, tick j + 1's.
//!
//! 1. Host level: frames of a loop around a plant with a pure delay of [`DELAY_TICKS`] (tick j
//!    reads x_j = g·u_{j−1−D}: the loop's own tick, then D more) go through both paths, with a
//!    sequence wrap, a gap and a decimation; the rows are the same, and the delay identified on
//!    them (the lag of the largest cross-correlation of the voltage's and the reading's steps) is
//!    D in both. Pairing a frame's voltage with its own reading would show D + 1.
//! 2. QEMU: the `qemu` image tracks a staircase over its command link; its simulated stage moves
//!    within a tick (a 50 µs lag at the 10 kHz loop: 1 − e^(−2) = 86.5 % of a step in the first
//!    reading after it), so the record shows delay 0. The same run's frames, printed in the
//!    images' text form, go through `capture`: the same rows and the same delay. Skipped, with
//!    a message, when `qemu-system-arm` or the thumbv7em-none-eabihf target is missing.
//!
//! Every file goes into the test's own temporary directory, removed at the end.

use std::fmt::Write as _;
use std::path::Path;

mod common;

use common::{build_link_image, connect, run_link_image, shut_down, TempDir};
use host_sim::capture::{AxisChoice, CaptureArgs};
use host_sim::csv::{read_csv, Table};
use host_sim::link::Recording;
use integration_tests::qemu::{missing_tools, say};
use piezo_link::Frame;

/// The host-level plant's pure delay beyond the loop's tick \[ticks\].
const DELAY_TICKS: usize = 3;
/// The host-level plant's gain \[m/V\].
const GAIN_M_PER_V: f32 = 0.3e-6;
/// Loop rate of both \[Hz\].
const RATE_HZ: f32 = 10_000.0;

/// The lag L in 0..=8 (rows) at which the reading's steps follow the voltage's most:
/// argmax Σ_k Δu_k·Δy_{k+L}, Δ the change from the row before, over the rows of `table`.
fn delay_rows(table: &Table, u: &str, y: &str) -> usize {
    let diff = |name: &str| -> Vec<f64> {
        let c = table.column(name).expect("column");
        c.windows(2).map(|w| w[1] - w[0]).collect()
    };
    let (du, dy) = (diff(u), diff(y));
    let score = |lag: usize| -> f64 { (0..du.len() - lag).map(|k| du[k] * dy[k + lag]).sum() };
    (0..=8)
        .max_by(|&a, &b| score(a).total_cmp(&score(b)))
        .expect("lags")
}

/// A temporary directory of this test, removed when dropped.
fn scratch(name: &str) -> TempDir {
    let dir =
        TempDir(std::env::temp_dir().join(format!("frames_record_{name}_{}", std::process::id())));
    std::fs::create_dir_all(&dir.0).expect("temporary directory");
    dir
}

/// The frames as the images print them: the boot line, then one text line per frame.
fn log_text(frames: &[Frame], decimation: u32, rate_hz: f64) -> String {
    let mut text = format!(
        "piezo-firmware qemu: parameters frames-record 1 (test), fnv1a32 0x00000000, loop {rate_hz} Hz, \
         one frame every {decimation} ticks\n"
    );
    for f in frames {
        writeln!(text, "{f}").unwrap();
    }
    text
}

/// Both paths on `recording`: (link's CSV, capture's CSV), read back. Capture's t counts from
/// boot (frame 0), link's from the run's first frame.
fn both_paths(dir: &Path, name: &str, recording: &Recording, tracking: bool) -> (Table, Table) {
    let link_csv = dir.join(format!("{name}-link.csv"));
    recording
        .columns(tracking)
        .write(&link_csv, &[])
        .expect("write the link record");
    let log = dir.join(format!("{name}.log"));
    std::fs::write(
        &log,
        log_text(
            &recording.frames,
            recording.decimation,
            recording.loop_rate_hz,
        ),
    )
    .unwrap();
    let capture_csv = dir.join(format!("{name}-capture.csv"));
    let args = CaptureArgs {
        log,
        out: capture_csv.clone(),
        axis: AxisChoice::Both,
        rate: None,
        decimation: None,
        allow_gaps: recording.gaps > 0,
    };
    host_sim::capture::run(&args, &mut |_| {}).expect("capture");
    (
        read_csv(&link_csv).expect("link CSV"),
        read_csv(&capture_csv).expect("capture CSV"),
    )
}

/// The same rows: every column equal, t once the time origins (run start, boot) are aligned.
fn assert_same_rows(link: &Table, capture: &Table, recording: &Recording) {
    let (first_frame, decimation) = (recording.first_frame, recording.decimation);
    assert_eq!(link.names, capture.names);
    assert_eq!(link.rows(), capture.rows());
    assert!(link.rows() > 0);
    let origin_s = f64::from(first_frame) * f64::from(decimation) / recording.loop_rate_hz;
    for (name, (a, b)) in link
        .names
        .iter()
        .zip(link.columns.iter().zip(&capture.columns))
    {
        if name == "t_s" {
            for (k, (ta, tb)) in a.iter().zip(b).enumerate() {
                assert!((ta + origin_s - tb).abs() < 1e-9, "row {k}: t {ta} vs {tb}");
            }
        } else {
            assert_eq!(a, b, "column {name}");
        }
    }
}

/// Frames of a loop at `decimation` around the delayed plant: tick j reads
/// x_j = g·u_{j−1−D} (0 before the start), then applies u_j, a staircase of 2 V steps held for
/// 7 ticks (x) and 11 ticks (y); the first frame is numbered `first`.
fn delayed_plant_frames(first: u32, ticks: usize, decimation: usize) -> Vec<Frame> {
    let u = |j: usize, hold: usize| 10.0 + 2.0 * ((j / hold) % 30) as f32;
    let x = |j: usize, hold: usize| {
        j.checked_sub(1 + DELAY_TICKS)
            .map_or(0.0, |i| GAIN_M_PER_V * u(i, hold))
    };
    (0..ticks)
        .step_by(decimation)
        .enumerate()
        .map(|(k, j)| Frame {
            sequence: first.wrapping_add(k as u32),
            reference_m: [GAIN_M_PER_V * u(j, 7), GAIN_M_PER_V * u(j, 11)],
            commanded_v: [u(j, 7), u(j, 11)],
            sensor_m: [x(j, 7), x(j, 11)],
            trial: 0,
            flags: 0,
        })
        .collect()
}

fn recording(frames: Vec<Frame>, first_frame: u32, decimation: u32) -> Recording {
    Recording {
        loop_rate_hz: f64::from(RATE_HZ),
        decimation,
        first_frame,
        frames,
        gaps: 0,
        lost: 0,
        table: [1, 1],
    }
}

#[test]
fn the_same_frames_give_the_same_rows_and_delay_through_link_and_capture() {
    let dir = scratch("host");
    // Numbered across the u32 wrap.
    let first = u32::MAX - 150;
    let whole = recording(delayed_plant_frames(first, 600, 1), first, 1);
    let (link, capture) = both_paths(&dir.0, "whole", &whole, true);
    assert_same_rows(&link, &capture, &whole);
    // 600 frames, 599 rows: the last frame's voltage has no answer in the record.
    assert_eq!(link.rows(), 599);
    for (u, y) in [("ux_V", "x_m"), ("uy_V", "y_m")] {
        assert_eq!(delay_rows(&link, u, y), DELAY_TICKS, "link {y}");
        assert_eq!(delay_rows(&capture, u, y), DELAY_TICKS, "capture {y}");
    }
    // Row k: frame k's voltage and reference, frame k + 1's reading.
    // (The CSV holds f32 values in their shortest form.)
    let f = &whole.frames;
    let at = |name: &str| link.column(name).unwrap()[200] as f32;
    assert_eq!(at("ux_V"), f[200].commanded_v[0]);
    assert_eq!(at("rx_m"), f[200].reference_m[0]);
    assert_eq!(at("x_m"), f[201].sensor_m[0]);

    // Frames 300 and 301 lost: no row for frame 299 (its answer is lost) nor 300, 301.
    let mut gappy = whole.clone();
    gappy.frames.drain(300..302);
    gappy.gaps = 1;
    gappy.lost = 2;
    let (link, capture) = both_paths(&dir.0, "gap", &gappy, true);
    assert_same_rows(&link, &capture, &gappy);
    assert_eq!(link.rows(), 596);
    assert_eq!(link.names.last().unwrap(), "segment_1");
    let segment = link.column("segment_1").unwrap();
    assert_eq!((segment[298], segment[299]), (0.0, 1.0));

    // One frame every 10 ticks: the answering reading is not sent; both take the frame's own.
    let decimated = recording(delayed_plant_frames(first, 6000, 10), first, 10);
    let (link, capture) = both_paths(&dir.0, "decimated", &decimated, true);
    assert_same_rows(&link, &capture, &decimated);
    assert_eq!(link.rows(), 600);
}

/// Entries of the staircase the image tracks: 0.4 µm steps (≈ 1.2 V at the stage's ≈ 0.35 µm/V,
/// inside the guard's step per tick) every 3 ms, 10–30 µm and back, 0.2 s at the built-in file's
/// loop rate (one table entry per tick).
const STAIRCASE: &str = "staircase:low=10e-6,high=30e-6,step=0.4e-6,hold=0.003";
const STAIRCASE_S: f64 = 0.2;

#[test]
fn a_qemu_run_shows_the_stages_delay_through_link_and_capture() {
    if let Some(why) = missing_tools() {
        say(&format!("frames_record: SKIPPED: {why}"));
        return;
    }
    let elf = build_link_image();
    let dir = scratch("qemu");
    let (mut qemu, port) = run_link_image(&elf);
    let mut client = connect(port);
    let run = client
        .run(STAIRCASE, STAIRCASE_S, 1, false)
        .expect("track the staircase");
    shut_down(&mut client, &mut qemu);
    assert_eq!((run.gaps, run.lost), (0, 0));
    assert_eq!(
        run.frames.len(),
        (STAIRCASE_S * run.loop_rate_hz).round() as usize
    );

    let (link, capture) = both_paths(&dir.0, "qemu", &run, true);
    assert_same_rows(&link, &capture, &run);
    for (u, y) in [("ux_V", "x_m"), ("uy_V", "y_m")] {
        let (a, b) = (delay_rows(&link, u, y), delay_rows(&capture, u, y));
        say(&format!(
            "frames_record: {y}: delay {a} ticks from the link's record, {b} from the capture's ({} rows)",
            link.rows()
        ));
        assert_eq!((a, b), (0, 0), "{y}: the stage answers within one tick");
    }
}
