//! Iterative learning over the command link, against the QEMU image's simulated stage.
//!
//! Builds the `qemu` image with its built-in stage file (in `<target dir>/link-session`, the
//! directory `link_session` builds the same image in: the test binaries of one `cargo test` run
//! one after the other), runs it with `firmware/run-qemu.sh --link PORT` on a free loopback
//! port, and runs `host-sim link learn` on it: one period of a 20 Hz sine (500 wave table
//! entries), 6 learning steps, 2 periods averaged per trial. Checks that the error falls (the
//! best trial at most 0.5 × iteration 0's), that the saved table resumes (and is refused for
//! another stage file, naming both), that a table beyond the slew limit is refused and not
//! played, and that tracking with the learned table afterwards gives the learned error (the
//! firmware's own statistics). Prints the per-iteration table (`--nocapture`).
//!
//! QEMU is stopped at the end (shutdown request, then SIGTERM). Skipped, with a message, when
//! `qemu-system-arm` or the thumbv7em-none-eabihf target is missing.

use std::path::Path;
use std::time::{Duration, Instant};

mod common;

use clap::Parser as _;
use common::{
    build_link_image, connect, firmware_dir, run_link_image, shut_down, TempDir, TIMEOUT,
};
use host_sim::link::{fnv1a32, Client};
use integration_tests::qemu::{missing_tools, say};
use piezo_link::{Control, Feedforward, Program, RefusalKind, Request, Response};

const SIGNAL: &str = "sine:amp=12e-6,offset=19e-6,freq=20,phase_deg=-90";
const ITERATIONS: usize = 6;

/// `host-sim link --connect tcp:127.0.0.1:PORT learn ARGS...` as the command line runs it.
fn link_learn(port: u16, args: &[String]) -> Result<String, String> {
    let mut line = vec![
        "host-sim".to_string(),
        "link".into(),
        "--connect".into(),
        format!("tcp:127.0.0.1:{port}"),
        "learn".into(),
    ];
    line.extend(args.iter().cloned());
    let cli = host_sim::cli::Cli::try_parse_from(line).map_err(|e| e.to_string())?;
    host_sim::cli::run(cli).map_err(|e| e.to_string())
}

fn arg(p: &Path) -> String {
    p.display().to_string()
}

/// The firmware's tracking statistics once `ticks` ticks of the running program have counted.
fn tracking_after(client: &mut Client, ticks: u32) -> [piezo_link::Tracking; 2] {
    let started = Instant::now();
    loop {
        let status = client.status().expect("status");
        if status.tracking[0].count >= ticks {
            return status.tracking;
        }
        assert!(started.elapsed() < TIMEOUT, "{status:?}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

#[test]
fn learning_over_the_link_lowers_the_error() {
    if let Some(why) = missing_tools() {
        say(&format!("link_learn: SKIPPED: {why}"));
        return;
    }
    let started = Instant::now();
    let elf = build_link_image();
    let built = started.elapsed();
    let dir = TempDir(std::env::temp_dir().join(format!("link_learn_{}", std::process::id())));
    std::fs::create_dir_all(&dir.0).expect("temporary directory");
    let (mut qemu, port) = run_link_image(&elf);
    // QEMU serves one connection at a time: each client is dropped before the next connects.
    let stage = firmware_dir().join("params/xy-stage.toml");
    assert_eq!(
        connect(port).status().unwrap().params_fnv1a32,
        fnv1a32(&std::fs::read(&stage).unwrap())
    );
    let session_started = Instant::now();

    // 1. Learn: 6 steps, patience enough that all run.
    let out = dir.0.join("learn");
    let learn_args = |extra: &[&str]| -> Vec<String> {
        let mut v: Vec<String> = [
            "--params",
            &arg(&stage),
            "--signal",
            SIGNAL,
            "--duration-per-trial",
            "0.05",
            "--out",
            &arg(&out),
            "--periods",
            "2",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        v.extend(extra.iter().map(|s| s.to_string()));
        v
    };
    let iterations = ITERATIONS.to_string();
    let summary = link_learn(
        port,
        &learn_args(&["--iterations", &iterations, "--patience", "10"]),
    )
    .expect("link learn");
    say(&format!("link_learn: {summary}"));
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("learn.json")).unwrap()).unwrap();
    let trials = report["iterations"].as_array().unwrap();
    assert_eq!(trials.len(), ITERATIONS + 1);
    say(&format!(
        "link_learn: Q cut-off x {:.0} Hz, y {:.0} Hz; {} entries, {} periods per trial",
        report["q_cutoff_hz"]["x"].as_f64().unwrap(),
        report["q_cutoff_hz"]["y"].as_f64().unwrap(),
        report["entries"],
        report["periods_per_trial"]
    ));
    say("link_learn: iteration | x rms nm | x max nm | y rms nm | y max nm | rms nm");
    let nm = |v: &serde_json::Value| v.as_f64().unwrap() * 1e9;
    for t in trials {
        say(&format!(
            "link_learn: {:>9} | {:>8.2} | {:>8.2} | {:>8.2} | {:>8.2} | {:>6.2}",
            t["iteration"],
            nm(&t["x"]["rms_m"]),
            nm(&t["x"]["max_abs_m"]),
            nm(&t["y"]["rms_m"]),
            nm(&t["y"]["max_abs_m"]),
            nm(&t["rms_m"])
        ));
    }
    // Two passes per trial: each step's noise comes from the spread between them (on the link
    // image's stage, which has no sensor noise, only what the loop has not settled).
    let mut noise_nm = Vec::new();
    for t in trials {
        for axis in ["x", "y"] {
            assert_eq!(t[axis]["noise_from_passes"], true, "{axis}: {t}");
            let noise = t[axis]["noise_rms_m"].as_f64().unwrap();
            assert!(noise.is_finite() && noise >= 0.0, "{axis}: noise {noise}");
            noise_nm.push(1e9 * noise);
        }
    }
    say(&format!(
        "link_learn: noise from the passes, x and y per iteration [nm]: {noise_nm:.3?}"
    ));
    let rms = |k: usize| trials[k]["rms_m"].as_f64().unwrap();
    let best = report["best_iteration"].as_u64().unwrap() as usize;
    assert!(
        rms(best) <= 0.5 * rms(0),
        "best {} nm vs iteration 0 {} nm",
        rms(best) * 1e9,
        rms(0) * 1e9
    );
    assert!(rms(ITERATIONS) <= 0.5 * rms(0), "{report}");
    assert!(out.join("learn.png").is_file() && out.join("reference.csv").is_file());

    // 2. The saved table resumes: played again it gives its error (no learning step).
    let table = out.join("table.csv");
    let again = dir.0.join("again");
    let mut resume_args = learn_args(&["--iterations", "0"]);
    resume_args.extend(["--resume".to_string(), arg(&table)]);
    for a in resume_args.iter_mut() {
        if *a == arg(&out) {
            *a = arg(&again);
        }
    }
    // The reference must be the saved table's: the same signal sampled again.
    link_learn(port, &resume_args).expect("resume");
    let resumed: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(again.join("learn.json")).unwrap()).unwrap();
    let replayed = resumed["iterations"][0]["rms_m"].as_f64().unwrap();
    say(&format!(
        "link_learn: the saved table (iteration {best}) played again: rms {:.2} nm (learned {:.2} nm)",
        replayed * 1e9,
        rms(best) * 1e9
    ));
    assert_eq!(resumed["iterations"][0]["iteration"], best as u64);
    assert!(replayed <= 1.3 * rms(best) + 0.5e-9, "{resumed}");
    // ... and is refused for another stage file, naming both.
    let other = dir.0.join("other.toml");
    let mut text = std::fs::read_to_string(&stage).unwrap();
    text.push_str("\n# another file\n");
    std::fs::write(&other, text).unwrap();
    let mut other_args = resume_args.clone();
    for a in other_args.iter_mut() {
        if *a == arg(&stage) {
            *a = arg(&other);
        }
    }
    upload(&mut connect(port), &other);
    let e = link_learn(port, &other_args).unwrap_err();
    say(&format!("link_learn: refused: {e}"));
    assert!(
        e.contains(&arg(&table)) && e.contains(&arg(&other)) && e.contains("xy-stage.toml"),
        "{e}"
    );
    let mut client = connect(port);
    upload(&mut client, &stage);
    drop(client);
    // ... and for another reference, naming both.
    let mut moved = resume_args.clone();
    for a in moved.iter_mut() {
        if a == SIGNAL {
            *a = SIGNAL.replace("amp=12e-6", "amp=11e-6");
        }
    }
    let e = link_learn(port, &moved).unwrap_err();
    say(&format!("link_learn: refused: {e}"));
    assert!(
        e.contains(&arg(&table))
            && e.contains("learned for another reference than")
            && e.contains(&arg(&again.join("reference.csv"))),
        "{e}"
    );
    let mut client = connect(port);

    // 3. A table beyond the slew limit is refused and not played.
    let saved = read_table(&table);
    let mut spiked = saved.clone();
    spiked[250][0] = (spiked[249][0] + 25.0).min(119.0);
    spiked[251][0] = spiked[250][0];
    client
        .expect(Request::Control(Control::Feedforward))
        .unwrap();
    client.load_table(&spiked, true).unwrap();
    match client.request(Request::Control(Control::Learned)).unwrap() {
        Response::Refused(r) => {
            say(&format!("link_learn: refused: {}", r.reason));
            assert_eq!((r.kind, r.axis), (RefusalKind::Learned, Some(0)));
            assert!(
                r.reason.contains("learned table entry 250, x: step"),
                "{}",
                r.reason
            );
        }
        other => panic!("a table beyond the slew limit was accepted: {other:?}"),
    }
    let status = client.status().unwrap();
    assert_eq!(status.feedforward, Feedforward::Compensator);
    assert_eq!(status.control, Control::Feedforward);

    // 4. The learned table afterwards: tracking (the firmware's statistics, from 1 000 ticks
    // after the start) gives the learned error; the compensator's for comparison.
    client.expect(Request::Track(table_program())).unwrap();
    let compensated = tracking_after(&mut client, 3000);
    client.load_table(&saved, true).unwrap();
    client.expect(Request::Control(Control::Learned)).unwrap();
    client.expect(Request::Track(table_program())).unwrap();
    let learned = tracking_after(&mut client, 3000);
    let status = client.status().unwrap();
    assert_eq!(status.feedforward, Feedforward::Learned);
    // The start from entry 0 is a step the guard slews; while the table plays it never acts.
    let guard = status.counters.guard_interventions();
    tracking_after(&mut client, 6000);
    let status = client.status().unwrap();
    assert_eq!(status.counters.guard_interventions(), guard);
    let trial = &trials[best];
    for (i, axis) in ["x", "y"].iter().enumerate() {
        let raw = trial[*axis]["rms_raw_m"].as_f64().unwrap();
        say(&format!(
            "link_learn: tracking {axis}: learned table rms {:.2} nm max {:.2} nm (its trial: \
             {:.2} nm unaveraged); compensator rms {:.2} nm max {:.2} nm",
            learned[i].rms_m * 1e9,
            learned[i].max_abs_m * 1e9,
            raw * 1e9,
            compensated[i].rms_m * 1e9,
            compensated[i].max_abs_m * 1e9
        ));
        assert!(
            f64::from(learned[i].rms_m) <= 1.3 * raw + 0.5e-9,
            "{axis}: {:?} vs {raw}",
            learned[i]
        );
        assert!(
            learned[i].rms_m < 0.5 * compensated[i].rms_m,
            "{axis}: {:?} vs {:?}",
            learned[i],
            compensated[i]
        );
    }
    assert_eq!(status.counters.frames_dropped, 0);
    let session = session_started.elapsed();

    // 5. Shutdown.
    shut_down(&mut client, &mut qemu);
    say(&format!(
        "link_learn: image built in {:.1} s, session {:.1} s",
        built.as_secs_f64(),
        session.as_secs_f64()
    ));
}

fn table_program() -> Program {
    Program::Table {
        ticks_per_entry: 1,
        repeat: true,
    }
}

fn upload(client: &mut Client, path: &Path) {
    host_sim::link::upload(client, path).expect("upload");
}

/// The voltages of a table `link learn` wrote.
fn read_table(path: &Path) -> Vec<[f32; 2]> {
    let table = host_sim::csv::read_csv(path).expect("table.csv");
    let (x, y) = (table.column("ux_V").unwrap(), table.column("uy_V").unwrap());
    x.iter()
        .zip(y)
        .map(|(&a, &b)| [a as f32, b as f32])
        .collect()
}
