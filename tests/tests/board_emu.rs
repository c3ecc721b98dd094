//! The board image's RTIC application under QEMU's netduinoplus2 (STM32F405; the `board-emu`
//! variant: TIM2 at the stage file's loop rate, the deadline monitor, the session, the link on
//! USART1, the simulated stage behind the converter traits), over its command link, against the
//! mps2-an386 link image on the same session.
//!
//! Builds both images (`<target dir>/link-session`, shared with the other link tests), and on
//! each, with host-sim's link client: status (the built-in set, the stage file's loop rate) →
//! upload a model set (the built-in models under another version string) → track a 19 ± 12 µm,
//! 10 Hz sine for 0.5 s with every frame recorded → status → shutdown. Checks on the emulated
//! board: the frames have no gap and none was dropped, no deadline was missed (no overrun, no
//! late tick, no skipped update), TIM2's rate as the tick served it (measured with SysTick,
//! printed at shutdown) is the stage file's, and the tracking error — the firmware's own
//! statistics and the one computed from the frames — is the mps2 image's to within a margin
//! (the same loop, session and simulated stage, paced by another timer).
//!
//! Every read has a timeout; QEMU is stopped at the end (shutdown request, then SIGTERM).
//! Skipped, with a message, when `qemu-system-arm` or the thumbv7em-none-eabihf target is
//! missing.

use std::io::Read as _;
use std::path::Path;
use std::sync::mpsc;
use std::time::{Duration, Instant};

mod common;

use common::{
    build_board_emu_image, build_link_image, connect, firmware_dir, run_board_emu_image,
    run_link_image, Qemu, TempDir,
};
use host_sim::link::{fnv1a32, upload, Recording};
use integration_tests::qemu::{missing_tools, say};
use piezo_link::{Mode, Request, Response, Status};

/// Settling ticks the firmware leaves out of its tracking statistics (`session::SETTLE_TICKS`).
const SETTLE_TICKS: usize = 1_000;

/// What one image did in the session.
struct Outcome {
    before: Status,
    after: Status,
    recording: Recording,
    /// RMS of sensor(k) − reference(k − 1) over the recorded frames after settling, per axis [m].
    frames_rms_m: [f64; 2],
    /// QEMU's stdout after it exited.
    stdout: String,
}

/// The session on a running image: status, upload `set`, track, status, shutdown. `lines` is
/// QEMU's stdout when the caller already reads it.
fn session(
    mut qemu: Qemu,
    port: u16,
    lines: Option<mpsc::Receiver<String>>,
    built_in: &[u8],
    set: &Path,
) -> Outcome {
    let mut client = connect(port);
    let before = client.status().expect("status");
    assert_eq!(before.params_fnv1a32, fnv1a32(built_in));
    assert_eq!(before.mode, Mode::Running);

    let fnv = upload(&mut client, set).expect("upload");
    assert_eq!(fnv, fnv1a32(&std::fs::read(set).unwrap()));
    let loaded = client.status().expect("status");
    assert_eq!(loaded.params_fnv1a32, fnv);
    assert_eq!(loaded.counters.uploads, 1);

    let recording = client
        .run(
            "sine:amp=12e-6,offset=19e-6,freq=10,phase_deg=-90",
            0.5,
            1,
            false,
        )
        .expect("track");
    let after = client.status().expect("status");
    assert_eq!(after.mode, Mode::Running, "{:?}", after.counters);
    assert_eq!(recording.frames.len(), 5_000);
    assert_eq!((recording.gaps, recording.lost), (0, 0));

    let mut frames_rms_m = [0.0; 2];
    for (axis, rms) in frames_rms_m.iter_mut().enumerate() {
        let errors: Vec<f64> = recording
            .frames
            .windows(2)
            .skip(SETTLE_TICKS)
            .map(|w| f64::from(w[1].sensor_m[axis]) - f64::from(w[0].reference_m[axis]))
            .collect();
        *rms = (errors.iter().map(|e| e * e).sum::<f64>() / errors.len() as f64).sqrt();
    }

    assert_eq!(client.request(Request::Shutdown).unwrap(), Response::Done);
    let deadline = Instant::now() + Duration::from_secs(10);
    let exit = loop {
        if let Some(status) = qemu.0.try_wait().unwrap() {
            break status;
        }
        assert!(
            Instant::now() < deadline,
            "QEMU did not exit after shutdown"
        );
        std::thread::sleep(Duration::from_millis(50));
    };
    assert!(exit.success(), "QEMU exit {exit:?}");
    let mut stdout = String::new();
    if let Some(lines) = lines {
        // The reader thread ends with QEMU's stdout.
        for line in lines.iter() {
            stdout.push_str(&line);
            stdout.push('\n');
        }
    } else if let Some(mut out) = qemu.0.stdout.take() {
        out.read_to_string(&mut stdout).expect("QEMU's stdout");
    }
    Outcome {
        before,
        after,
        recording,
        frames_rms_m,
        stdout,
    }
}

/// The number after `key` in `line` (up to the next space, comma, colon or semicolon).
fn field(line: &str, key: &str) -> f64 {
    let rest = &line[line
        .find(key)
        .unwrap_or_else(|| panic!("no `{key}` in {line:?}"))
        + key.len()..];
    let end = rest.find([' ', ',', ';', ':']).unwrap_or(rest.len());
    rest[..end]
        .parse()
        .unwrap_or_else(|e| panic!("`{key}` in {line:?}: {e}"))
}

fn nm(s: &Status, frames_rms_m: [f64; 2]) -> String {
    format!(
        "x rms {:.2} nm max {:.2} nm, y rms {:.2} nm max {:.2} nm ({} samples); from the frames x {:.2} nm, y {:.2} nm",
        s.tracking[0].rms_m * 1e9,
        s.tracking[0].max_abs_m * 1e9,
        s.tracking[1].rms_m * 1e9,
        s.tracking[1].max_abs_m * 1e9,
        s.tracking[0].count,
        frames_rms_m[0] * 1e9,
        frames_rms_m[1] * 1e9
    )
}

#[test]
fn the_board_image_under_emulation_tracks_as_the_qemu_image() {
    if let Some(why) = missing_tools() {
        say(&format!("board_emu: SKIPPED: {why}"));
        return;
    }
    let started = Instant::now();
    let emu_elf = build_board_emu_image();
    let mps2_elf = build_link_image();
    let built = started.elapsed();

    let dir = TempDir(std::env::temp_dir().join(format!("board_emu_{}", std::process::id())));
    std::fs::create_dir_all(&dir.0).expect("temporary directory");
    let stage_file = firmware_dir().join("params/xy-stage.toml");
    let built_in = std::fs::read(&stage_file).unwrap();
    let (stage, _) = piezo_stage::StageFile::load(&stage_file).expect("the built-in stage file");
    // The built-in models under another version: an upload the status tells apart.
    let text = String::from_utf8(built_in.clone()).unwrap();
    assert!(text.contains("version = \"3\""));
    let set = dir.0.join("uploaded.toml");
    std::fs::write(
        &set,
        text.replace("version = \"3\"", "version = \"3-upload\""),
    )
    .unwrap();

    let session_started = Instant::now();
    let (qemu, port, lines) = run_board_emu_image(&emu_elf);
    let emu = session(qemu, port, Some(lines), &built_in, &set);
    let emu_time = session_started.elapsed();
    let (qemu, port) = run_link_image(&mps2_elf);
    let mps2 = session(qemu, port, None, &built_in, &set);

    // The loop rate the board reports is the stage file's, and TIM2 served it.
    assert_eq!(emu.before.loop_rate_hz, stage.stage.loop_rate_hz);
    let line = emu
        .stdout
        .lines()
        .find(|l| l.starts_with("board-emu: TIM2"))
        .unwrap_or_else(|| panic!("no shutdown line from the emulated board: {:?}", emu.stdout));
    say(&format!("board_emu: {line}"));
    // The rate is measured from the first tick's entry to the last's, so it may be off by
    // their latencies: at most the worst latency over the span (plus 1 ppm of rounding).
    let rate = field(line, "cycles: ");
    let want = f64::from(stage.stage.loop_rate_hz);
    let tolerance = field(line, "worst latency ") / field(line, "over ") + 1e-6;
    assert!(
        (rate - want).abs() <= tolerance * want,
        "TIM2 served {rate} Hz, the stage file says {want} Hz (tolerance {tolerance:e})"
    );
    // No deadline missed: TIM2's updates all got their tick, each ended inside its period.
    let served = field(line, "served ");
    assert!(served >= f64::from(emu.after.counters.ticks), "{line}");
    for key in ["late ", "skipped ", "overruns "] {
        assert_eq!(field(line, key), 0.0, "{key}in {line}");
    }
    let period = field(line, "cycles per period ");
    assert!(field(line, "worst completion ") < period, "{line}");
    assert_eq!(emu.after.counters.overruns, 0);
    assert_eq!(emu.after.counters.frames_dropped, 0);
    assert!(emu.after.tick_cycles_max > 0 && f64::from(emu.after.tick_cycles_max) < period);

    say(&format!(
        "board_emu: board-emu tracking: {}",
        nm(&emu.after, emu.frames_rms_m)
    ));
    say(&format!(
        "board_emu: mps2 tracking: {}",
        nm(&mps2.after, mps2.frames_rms_m)
    ));
    for axis in 0..2 {
        let (e, m) = (emu.after.tracking[axis], mps2.after.tracking[axis]);
        assert!(e.count >= 3_900, "axis {axis}: {e:?}");
        // The statistics and the frames agree (the same samples, give or take the ticks
        // between the last frame and the status request).
        let from_frames = emu.frames_rms_m[axis];
        assert!(
            (from_frames - f64::from(e.rms_m)).abs() <= 0.02 * from_frames,
            "axis {axis}: frames {from_frames} m vs statistics {e:?}"
        );
        // The same loop on the same simulated stage tracks as on the mps2 image: the frames
        // (the same ticks of the same program) to 1 % (measured: equal to 0.01 nm), the
        // statistics (their window starts and ends a few ticks apart) to 5 % (measured: 0.5 %).
        let mps2_frames = mps2.frames_rms_m[axis];
        assert!(
            (from_frames - mps2_frames).abs() <= 0.01 * mps2_frames,
            "axis {axis}: frames board-emu {from_frames} m vs mps2 {mps2_frames} m"
        );
        assert!(
            (f64::from(e.rms_m) - f64::from(m.rms_m)).abs() <= 0.05 * f64::from(m.rms_m),
            "axis {axis}: board-emu {e:?} vs mps2 {m:?}"
        );
        assert!(e.rms_m < 20e-9 && e.max_abs_m < 40e-9, "axis {axis}: {e:?}");
    }
    assert_eq!(
        emu.recording.frames.len(),
        mps2.recording.frames.len(),
        "frames"
    );
    say(&format!(
        "board_emu: images built in {:.1} s; board-emu session {:.1} s, {} ticks",
        built.as_secs_f64(),
        emu_time.as_secs_f64(),
        emu.after.counters.ticks
    ));
}
