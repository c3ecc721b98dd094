//! The board image's RTIC application under QEMU's netduinoplus2 (STM32F405; the `board-emu`
//! variant: TIM2 at the stage file's loop rate, the deadline monitor, the session, the link on
//! USART1, the simulated stage behind the converter traits), over its command link, against the
//! mps2-an386 link image on the same session.
//!
//! Builds both images with the built-in stage file at [`EMULATED_RATE_HZ`]
//! (`<target dir>/board-emu-10000`), and on each, with host-sim's link client: status (the built-in set, the stage file's loop rate) →
//! upload a model set (the built-in models under another version string) → track a 19 ± 12 µm,
//! 10 Hz sine for 0.5 s with every frame recorded → status → shutdown. Checks on the emulated
//! board: the frames have no gap and none was dropped, no deadline was missed (no overrun, no
//! late tick, no skipped update), TIM2's rate as the tick served it (measured with SysTick,
//! printed at shutdown) is the stage file's, and the tracking error — the firmware's own
//! statistics and the one computed from the frames — is the mps2 image's to within a margin
//! (the same loop, session and simulated stage, paced by another timer).
//!
//! A second session on the emulated board serves 300 requests while the loop records at
//! decimation 1 and checks that none made a tick late (the link's lock holds, printed at
//! shutdown per kind of request, stay far inside the period).
//!
//! Every read has a timeout; QEMU is stopped at the end (shutdown request, then SIGTERM).
//! Skipped, with a message, when `qemu-system-arm` or the thumbv7em-none-eabihf target is
//! missing.

use std::io::Read as _;
use std::path::Path;
use std::sync::mpsc;
use std::time::Instant;

mod common;

use common::{
    build_images_at_rate, connect, run_board_emu_image, run_link_image, shut_down, Qemu, TempDir,
};
use host_sim::link::{fnv1a32, upload, Client, Recording};
use integration_tests::qemu::{missing_tools, say};
use piezo_link::{Control, Mode, Program, Request, Response, Status, Wave};

/// The loop rate the emulated board runs the built-in stage file at \[Hz\]. Its simulated stage
/// (Euler sub-steps of the stacks, in the tick on the emulated core; the board has sensors
/// instead) takes up to ≈ 4 500 cycles in a tick after a large step, more than the 20 kHz
/// period leaves beside the loop (8 400 cycles), so at the default file's 20 kHz the emulated
/// tick overruns; the board's own tick is measured by `firmware/bench.sh`.
const EMULATED_RATE_HZ: u32 = 10_000;

/// Settling time the firmware leaves out of its tracking statistics (`session::SETTLE_S`) \[s\].
const SETTLE_S: f64 = 0.1;

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
    qemu: Qemu,
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
    assert_eq!(
        recording.frames.len(),
        (0.5 * f64::from(before.loop_rate_hz)).round() as usize
    );
    assert_eq!((recording.gaps, recording.lost), (0, 0));

    let settle = (SETTLE_S * f64::from(loaded.loop_rate_hz)).round() as usize;
    let mut frames_rms_m = [0.0; 2];
    for (axis, rms) in frames_rms_m.iter_mut().enumerate() {
        // Each row: a tick's reference with the reading that answers its command.
        let errors: Vec<f64> = recording
            .record()
            .rows
            .iter()
            .skip(settle)
            .map(|row| f64::from(row.sensor_m[axis]) - f64::from(row.reference_m[axis]))
            .collect();
        *rms = (errors.iter().map(|e| e * e).sum::<f64>() / errors.len() as f64).sqrt();
    }

    let stdout = shut_down_reading(client, qemu, lines);
    Outcome {
        before,
        after,
        recording,
        frames_rms_m,
        stdout,
    }
}

/// Sends `shutdown`, waits for QEMU to exit (10 s at most) with success, and returns its stdout
/// (from `lines` when the caller's thread reads it).
fn shut_down_reading(
    mut client: Client,
    mut qemu: Qemu,
    lines: Option<mpsc::Receiver<String>>,
) -> String {
    shut_down(&mut client, &mut qemu);
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
    stdout
}

/// The line of `stdout` that starts with `start`.
fn line_of<'a>(stdout: &'a str, start: &str) -> &'a str {
    stdout
        .lines()
        .find(|l| l.starts_with(start))
        .unwrap_or_else(|| panic!("no line `{start}` from the emulated board: {stdout:?}"))
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
    let (stage_file, emu_elf, mps2_elf) = build_images_at_rate(EMULATED_RATE_HZ);
    let built = started.elapsed();

    let dir = TempDir(std::env::temp_dir().join(format!("board_emu_{}", std::process::id())));
    std::fs::create_dir_all(&dir.0).expect("temporary directory");
    let built_in = std::fs::read(&stage_file).unwrap();
    let (stage, _) = piezo_stage::StageFile::load(&stage_file).expect("the built-in stage file");
    // The built-in models under another version: an upload the status tells apart.
    let text = String::from_utf8(built_in.clone()).unwrap();
    let version = format!("version = \"{}\"", stage.stage.version);
    assert!(text.contains(&version), "{version}");
    let set = dir.0.join("uploaded.toml");
    std::fs::write(
        &set,
        text.replace(
            &version,
            &format!("version = \"{}-upload\"", stage.stage.version),
        ),
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
    let line = line_of(&emu.stdout, "board-emu: TIM2");
    say(&format!("board_emu: {line}"));
    say(&format!(
        "board_emu: {}",
        line_of(&emu.stdout, "board-emu: link lock")
    ));
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
        // between the last frame and the status request). Under load the status comes later
        // and the statistics also count the ticks after the program, held at its end, whose
        // error is near zero: their RMS is diluted by at most √(n_frames / n) with n_frames
        // about the count of the run whose status came sooner.
        let from_frames = emu.frames_rms_m[axis];
        let dilution = |n: u32| (f64::from(e.count.min(m.count)) / f64::from(n)).sqrt();
        let stats = f64::from(e.rms_m);
        assert!(
            stats <= 1.02 * from_frames && stats >= 0.98 * from_frames * dilution(e.count),
            "axis {axis}: frames {from_frames} m vs statistics {e:?} (mps2 {m:?})"
        );
        // The same loop on the same simulated stage tracks as on the mps2 image: the frames
        // (the same ticks of the same program) to 1 % (measured: equal to 0.01 nm).
        let mps2_frames = mps2.frames_rms_m[axis];
        assert!(
            (from_frames - mps2_frames).abs() <= 0.01 * mps2_frames,
            "axis {axis}: frames board-emu {from_frames} m vs mps2 {mps2_frames} m"
        );
        // The mps2 image's statistics against its frames, by the same rule (the frames of the
        // two images agree to 1 %, above).
        let mps2_stats = f64::from(m.rms_m);
        assert!(
            mps2_stats <= 1.02 * mps2_frames
                && mps2_stats >= 0.98 * mps2_frames * dilution(m.count),
            "axis {axis}: mps2 frames {mps2_frames} m vs statistics {m:?} (board-emu {e:?})"
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

/// Requests served while the loop records at decimation 1 (a frame encoded every tick, the
/// tick's most expensive kind) never make a tick late: the link holds the session's lock only
/// for a bounded copy in or out, never while it decodes a request or encodes an answer.
///
/// On the emulated board: a 19 ± 12 µm, 10 Hz sine tracked with every frame sent, and meanwhile
/// [`REQUESTS`] requests one after the other — `status` mostly (its ≈ 100-byte answer is the
/// largest of the usual ones), `control feedforward` every 10th, the wave table cleared and
/// refilled with 64 entries every 25th (an upload of the built-in models comes before). Then no late tick, no skipped update, no overrun, no frame dropped or missing, and
/// the worst latency (update to tick entry) well inside the period.
#[test]
fn requests_served_during_a_recording_never_make_a_tick_late() {
    if let Some(why) = missing_tools() {
        say(&format!("board_emu: SKIPPED: {why}"));
        return;
    }
    let (stage_file, elf, _) = build_images_at_rate(EMULATED_RATE_HZ);
    let (qemu, port, lines) = run_board_emu_image(&elf);
    let mut client = connect(port);
    let before = client.status().expect("status");
    assert_eq!(before.mode, Mode::Running);
    // An upload (its lock hold is measured too) before the recording: its validation keeps the
    // link task busy for ≈ 2 400 periods, in which the transmit buffer fills and frames are
    // dropped (counted), so it is not sent during one.
    upload(&mut client, &stage_file).expect("upload");

    let sine = Wave::Sine {
        offset: 19e-6,
        amplitude: 12e-6,
        frequency_hz: 10.0,
    };
    client.expect(Request::Frames { decimation: 1 }).unwrap();
    let first = match client.expect(Request::Track(Program::PerAxis([sine; 2]))) {
        Ok(Response::Started { first_frame }) => first_frame,
        other => panic!("track: {other:?}"),
    };
    let table: Vec<[f32; 2]> = (0..64).map(|j| [19e-6 + 1e-7 * j as f32; 2]).collect();
    let started = Instant::now();
    let mut statuses = 0;
    // The first status that found the loop in its safe state.
    let mut safe_at = None;
    for i in 1..=REQUESTS {
        if i % 25 == 0 {
            // The wave table, idle while a per-axis program plays: cleared and refilled.
            client
                .load_table(&table, false)
                .expect("table during the recording");
        } else if i % 10 == 0 {
            assert_eq!(
                client
                    .request(Request::Control(Control::Feedforward))
                    .map_err(|e| e.to_string()),
                Ok(Response::Done)
            );
        } else {
            let s = client.status().expect("status during the recording");
            if s.mode != Mode::Running && safe_at.is_none() {
                safe_at = Some((i, s.mode, s.counters));
            }
            statuses += 1;
        }
    }
    let served = started.elapsed();
    let last = match client.expect(Request::Frames { decimation: 0 }) {
        Ok(Response::Streaming { next_frame, .. }) => next_frame,
        other => panic!("frames off: {other:?}"),
    };
    let after = client.status().expect("status");
    let frames = client.take_frames();
    let stdout = shut_down_reading(client, qemu, Some(lines));

    let deadline = line_of(&stdout, "board-emu: TIM2");
    let holds = line_of(&stdout, "board-emu: link lock");
    say(&format!(
        "board_emu: {REQUESTS} requests ({statuses} status) in {:.1} s while {} frames were recorded at decimation 1",
        served.as_secs_f64(),
        frames.len()
    ));
    say(&format!("board_emu: {deadline}"));
    say(&format!("board_emu: {holds}"));

    assert_eq!(safe_at, None, "(request, mode, counters)");
    // Every frame from the start of the track to frames off arrived, in order.
    let recorded = last.wrapping_sub(first) as usize;
    assert!(recorded >= 2 * REQUESTS, "{recorded} frames");
    let numbers: Vec<u32> = frames
        .iter()
        .map(|f| f.sequence)
        .filter(|n| n.wrapping_sub(first) < recorded as u32)
        .collect();
    assert_eq!(
        numbers.len(),
        recorded,
        "frames {first}..{last}: {:?}",
        after.counters
    );
    assert!(numbers.windows(2).all(|w| w[1] == w[0].wrapping_add(1)));
    assert_eq!(after.counters.frames_dropped, 0);
    assert_eq!(after.mode, Mode::Running, "{:?}", after.counters);
    assert_eq!(after.counters.overruns, 0);
    // No deadline missed while the requests were served.
    for key in ["late ", "skipped ", "overruns "] {
        assert_eq!(field(deadline, key), 0.0, "{key}in {deadline}");
    }
    let period = field(deadline, "cycles per period ");
    let cost = field(deadline, "worst cost ");
    let latency = field(deadline, "worst latency ");
    assert!(field(deadline, "worst completion ") < period, "{deadline}");
    // The latency is at most the longest hold of the session's lock by the link (measured:
    // 805–1 127 cycles of latency; holds: status 1 002–1 269, the upload before the recording
    // 4 284–5 645;
    // 12 255 and 12 391 when the link encoded its answers under the lock, with a late tick at
    // the second status); a tick recording at decimation 1 that sends a frame held back by a
    // reply (measured: 7 174–7 997 cycles) still ends inside the period after the longest.
    assert!(latency <= MAX_LATENCY_CYCLES, "{deadline}");
    assert!(latency + cost < period, "{deadline}");
    assert!(field(holds, "worst ") <= MAX_LATENCY_CYCLES, "{holds}");
}

/// Requests served during the recording.
const REQUESTS: usize = 300;
/// The bound on the worst tick latency and on the longest lock hold \[core cycles\]: 1.4 × the
/// longest hold measured when it was set (4 284, an upload's swap; 5 645 now that an axis's
/// chain is larger, the relaxation's spread among it), a third of the period.
const MAX_LATENCY_CYCLES: f64 = 6_000.0;
