//! A whole session over the command link, against the QEMU image's simulated stage.
//!
//! Builds the `qemu` image (its own target directory, `<target dir>/link-session`: the outer
//! `cargo test` holds the workspace's lock), runs it with `firmware/run-qemu.sh --link PORT` on a
//! free loopback port, and drives it with host-sim's link client:
//! status (the built-in set, its fingerprint the host's of the stage file) → excite 0.5–119.5 V
//! (every tick) and record → `identify` on the record → upload the identified set (its
//! fingerprint) → reload the wave table under the finished excitation (held: not played, the
//! guard untouched) → track a 10 Hz sine with the compensator, then with the linear
//! baseline → inject an overrun (safe state, outputs held) → rearm and track → a set the core
//! refuses (β < 0) leaves the running one → shutdown. The tracking error (the firmware's own
//! statistics: sensor of tick k minus reference of tick k − 1, after settling) is checked at
//! each stage; the output guard's interventions per axis and cause are printed per stage.
//!
//! Every read has a timeout; QEMU is stopped at the end (shutdown request, then SIGTERM).
//! Skipped, with a message, when `qemu-system-arm` or the thumbv7em-none-eabihf target is
//! missing.

use std::path::Path;
use std::time::{Duration, Instant};

mod common;

use clap::Parser as _;
use common::{build_link_image, connect, firmware_dir, run_link_image, shut_down, TempDir};
use host_sim::link::{fnv1a32, model_set, upload, Client};
use integration_tests::qemu::{missing_tools, say};
use piezo_link::{
    Control, Counters, Fault, Feedforward, GuardCounters, Mode, Request, Response, Status,
};

/// The output guard's interventions between two statuses, per axis and cause.
fn guard(before: &Counters, after: &Counters) -> String {
    let d = |a: &GuardCounters, b: &GuardCounters| GuardCounters {
        non_finite: b.non_finite - a.non_finite,
        window_clamped: b.window_clamped - a.window_clamped,
        slew_limited: b.slew_limited - a.slew_limited,
        window_entry: b.window_entry - a.window_entry,
    };
    let axis = |i: usize| {
        let g = d(&before.guard[i], &after.guard[i]);
        format!(
            "non_finite {} window_clamped {} slew_limited {} window_entry {}",
            g.non_finite, g.window_clamped, g.slew_limited, g.window_entry
        )
    };
    format!(
        "x {}; y {} (over {} ticks)",
        axis(0),
        axis(1),
        after.ticks - before.ticks
    )
}

/// Tracks the demo's reference for 1 s and returns the firmware's status after it.
fn track(client: &mut Client) -> Status {
    // 19 ± 12 µm sine, 10 Hz, on both axes (inside the identified set's window).
    client
        .run(
            "sine:amp=12e-6,offset=19e-6,freq=10,phase_deg=-90",
            1.0,
            10,
            false,
        )
        .expect("track");
    client.status().expect("status")
}

fn nm(s: &Status) -> String {
    format!(
        "x rms {:.1} nm max {:.1} nm, y rms {:.1} nm max {:.1} nm ({} samples)",
        s.tracking[0].rms_m * 1e9,
        s.tracking[0].max_abs_m * 1e9,
        s.tracking[1].rms_m * 1e9,
        s.tracking[1].max_abs_m * 1e9,
        s.tracking[0].count
    )
}

#[test]
fn a_whole_session_over_the_link() {
    if let Some(why) = missing_tools() {
        say(&format!("link_session: SKIPPED: {why}"));
        return;
    }
    let started = Instant::now();
    let elf = build_link_image();
    let built = started.elapsed();
    let dir = TempDir(std::env::temp_dir().join(format!("link_session_{}", std::process::id())));
    std::fs::create_dir_all(&dir.0).expect("temporary directory");

    let (mut qemu, port) = run_link_image(&elf);
    let mut client = connect(port);

    // 1. Status: the built-in set, running.
    let built_in = std::fs::read(firmware_dir().join("params/xy-stage.toml")).unwrap();
    let status = client.status().unwrap();
    assert_eq!(status.params_fnv1a32, fnv1a32(&built_in));
    let built_in_set = model_set(&firmware_dir().join("params/xy-stage.toml")).unwrap();
    assert_eq!(status.params_fingerprint, built_in_set.fingerprint());
    assert_eq!(status.mode, Mode::Running);
    // Ticks per second: the built-in file's loop rate (20 kHz).
    let rate = status.loop_rate_hz;
    let session_started = Instant::now();

    // 2. Excite 0.5–119.5 V (5 Hz, both axes) and record every tick.
    let excitation = client
        .run("sine:amp=59.5,offset=60,freq=5,phase_deg=-90", 1.2, 1, true)
        .expect("excite");
    assert_eq!(excitation.frames.len(), (1.2 * rate).round() as usize);
    assert_eq!((excitation.gaps, excitation.lost), (0, 0));
    let excited = client.status().unwrap();
    say(&format!(
        "link_session: guard during the excitation: {}",
        guard(&status.counters, &excited.counters)
    ));
    let record = dir.0.join("excite.csv");
    host_sim::csv::write_csv(&record, &excitation.table(false)).unwrap();

    // 3. Identify on the record (two axes, symmetric, invertible; [stage] and [io] carried).
    let identified = dir.0.join("identified.toml");
    let arg = |p: &Path| p.display().to_string();
    let cli = host_sim::cli::Cli::try_parse_from([
        "host-sim".to_string(),
        "identify".into(),
        "--data".into(),
        arg(&record),
        "--model".into(),
        "symmetric".into(),
        "--invertible".into(),
        "--u".into(),
        "ux_V,uy_V".into(),
        "--y".into(),
        "x_m,y_m".into(),
        "--start".into(),
        "0.2".into(),
        "--stage".into(),
        arg(&firmware_dir().join("params/xy-stage.toml")),
        "--out".into(),
        arg(&identified),
        "--report".into(),
        arg(&dir.0.join("identified.json")),
    ])
    .expect("identify arguments");
    let summary = host_sim::cli::run(cli).expect("identify");
    say(&format!("link_session: identify: {summary}"));

    // 4. Upload it: the firmware runs the identified set.
    let fnv = upload(&mut client, &identified).expect("upload");
    assert_eq!(fnv, fnv1a32(&std::fs::read(&identified).unwrap()));
    let uploaded = client.status().unwrap();
    assert_eq!(uploaded.params_fnv1a32, fnv);
    let identified_set = model_set(&identified).unwrap();
    assert_eq!(uploaded.params_fingerprint, identified_set.fingerprint());
    assert_ne!(uploaded.params_fingerprint, status.params_fingerprint);
    say(&format!(
        "link_session: fingerprint {:#010x} (built-in) -> {:#010x} (identified); windows x [{}, {}] V, y [{}, {}] V -> x [{}, {}] V, y [{}, {}] V; applied after the excitation {:?} V",
        status.params_fingerprint,
        uploaded.params_fingerprint,
        built_in_set.axes[0].limits.output_min_v,
        built_in_set.axes[0].limits.output_max_v,
        built_in_set.axes[1].limits.output_min_v,
        built_in_set.axes[1].limits.output_max_v,
        identified_set.axes[0].limits.output_min_v,
        identified_set.axes[0].limits.output_max_v,
        identified_set.axes[1].limits.output_min_v,
        identified_set.axes[1].limits.output_max_v,
        uploaded.applied_v,
    ));
    say(&format!(
        "link_session: guard from the excitation's end to the upload: {}",
        guard(&excited.counters, &uploaded.counters)
    ));

    // 4b. The wave table reloaded under the finished excitation: clearing a table that a
    // finished program still holds makes the reference hold where it stands, so the new
    // entries (a track's metres) are never played as stack volts: no guard intervention, the
    // output unmoved.
    let before_load = client.status().unwrap();
    client.load_table(&[[19e-6; 2]; 256], false).unwrap();
    let loaded = client.status().unwrap();
    say(&format!(
        "link_session: guard while the table is reloaded under the finished excitation: {}; applied {:?} V -> {:?} V",
        guard(&before_load.counters, &loaded.counters),
        before_load.applied_v,
        loaded.applied_v
    ));
    assert_eq!(loaded.applied_v, before_load.applied_v, "held, not moved");
    assert_eq!(
        loaded.counters.guard, before_load.counters.guard,
        "the reload is not played"
    );

    // 5. Track with the compensator, then with the linear baseline.
    let uploaded = client.status().unwrap();
    let compensated = track(&mut client);
    say(&format!(
        "link_session: guard over the first track (compensator): {}",
        guard(&uploaded.counters, &compensated.counters)
    ));
    assert_eq!(compensated.feedforward, Feedforward::Compensator);
    assert_eq!(compensated.mode, Mode::Running);
    client.expect(Request::Control(Control::OpenLoop)).unwrap();
    let linear = track(&mut client);
    assert_eq!(linear.feedforward, Feedforward::Linear);
    say(&format!(
        "link_session: guard over the linear baseline's track: {}",
        guard(&compensated.counters, &linear.counters)
    ));
    client
        .expect(Request::Control(Control::Feedforward))
        .unwrap();
    say(&format!(
        "link_session: compensated (identified set): {}",
        nm(&compensated)
    ));
    say(&format!("link_session: linear baseline: {}", nm(&linear)));
    for i in 0..2 {
        let (c, l) = (compensated.tracking[i], linear.tracking[i]);
        // 1 s of track is `rate` ticks, the first 0.1 s of them settling (`session::SETTLE_S`);
        // the status that reads the statistics arrives within a few ticks of the last frame,
        // before or after it.
        assert!(f64::from(c.count) >= 0.9 * rate as f64 - 100.0, "{c:?}");
        assert!(c.rms_m < 0.5 * l.rms_m, "axis {i}: {c:?} vs {l:?}");
        assert!(c.rms_m < 600e-9 && c.max_abs_m < 1.5e-6, "axis {i}: {c:?}");
    }

    // 5b. Feedback: refused while the set has no servo; with the servo `servo-tune` writes into
    // the identified file, feedforward + feedback tracks closer than the feedforward alone; an
    // upload without a servo is refused while feedback runs.
    match client
        .request(Request::Control(Control::FeedforwardFeedback))
        .unwrap()
    {
        Response::Refused(r) => assert!(r.reason.contains("servo"), "{}", r.reason),
        other => panic!("{other:?}"),
    }
    let tuned = dir.0.join("tuned.toml");
    let cli = host_sim::cli::Cli::try_parse_from([
        "host-sim".to_string(),
        "servo-tune".into(),
        "--stage".into(),
        arg(&identified),
        "--mode-hz".into(),
        "3221,2197".into(),
        "--damping".into(),
        "0.03".into(),
        "--out".into(),
        arg(&tuned),
    ])
    .expect("servo-tune arguments");
    host_sim::cli::run(cli).expect("servo-tune");
    upload(&mut client, &tuned).expect("upload with servo");
    client
        .expect(Request::Control(Control::FeedforwardFeedback))
        .unwrap();
    let both = track(&mut client);
    assert_eq!(both.control, Control::FeedforwardFeedback);
    say(&format!(
        "link_session: feedforward + feedback (servo-tune): {}",
        nm(&both)
    ));
    for i in 0..2 {
        let (b, c) = (both.tracking[i], compensated.tracking[i]);
        assert!(b.rms_m < 0.5 * c.rms_m, "axis {i}: {b:?} vs {c:?}");
    }
    match client
        .request(Request::Upload(model_set(&identified).unwrap()))
        .unwrap()
    {
        Response::Refused(r) => assert!(r.reason.contains("servo"), "{}", r.reason),
        other => panic!("{other:?}"),
    }
    client
        .expect(Request::Control(Control::Feedforward))
        .unwrap();
    assert_eq!(upload(&mut client, &identified).expect("upload"), fnv);

    // 6. A fault: the outputs are held until rearm.
    client.expect(Request::InjectOverrun).unwrap();
    std::thread::sleep(Duration::from_millis(50));
    let safe = client.status().unwrap();
    assert_eq!(safe.mode, Mode::Safe(Fault::Overrun));
    std::thread::sleep(Duration::from_millis(50));
    let later = client.status().unwrap();
    assert_eq!(later.applied_v, safe.applied_v, "outputs held while safe");
    assert!(later.counters.ticks > safe.counters.ticks);
    assert_eq!(later.counters.overruns, 1);

    // 7. Rearm: tracking resumes as before.
    assert_eq!(client.request(Request::Rearm).unwrap(), Response::Done);
    let rearmed = track(&mut client);
    assert_eq!(rearmed.mode, Mode::Running);
    say(&format!("link_session: after rearm: {}", nm(&rearmed)));
    for i in 0..2 {
        assert!(
            rearmed.tracking[i].rms_m < 600e-9,
            "{:?}",
            rearmed.tracking[i]
        );
    }

    // 8. A set the core refuses leaves the running one.
    let mut bad = model_set(&identified).unwrap();
    bad.axes[1].bouc_wen.beta = -1.0;
    bad.fnv1a32 = 1;
    match client.request(Request::Upload(bad)).unwrap() {
        Response::Refused(r) => {
            say(&format!("link_session: refused: {}", r.reason));
            assert_eq!(r.axis, Some(1));
            assert!(r.reason.contains("beta"), "{}", r.reason);
        }
        other => panic!("{other:?}"),
    }
    let kept = track(&mut client);
    assert_eq!(kept.params_fnv1a32, fnv);
    assert_eq!(kept.counters.refused_uploads, 2);
    for i in 0..2 {
        assert!(kept.tracking[i].rms_m < 600e-9, "{:?}", kept.tracking[i]);
    }
    assert_eq!(kept.counters.frames_dropped, 0);
    assert_eq!(client.packets.gaps, 0);
    let session = session_started.elapsed();

    // 9. Shutdown: QEMU exits with success.
    shut_down(&mut client, &mut qemu);
    say(&format!(
        "link_session: image built in {:.1} s, session {:.1} s, {} ticks",
        built.as_secs_f64(),
        session.as_secs_f64(),
        kept.counters.ticks
    ));
}
