//! What the link sessions under QEMU share: the firmware folder, QEMU stopped when dropped, a
//! temporary directory removed when dropped, a link client that waits for the image to answer,
//! and the shutdown that QEMU must exit from with success.

use std::io::{BufRead as _, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use host_sim::link::Client;
use integration_tests::qemu::{outer_target_dir, workspace, TARGET};
use piezo_link::{Request, Response};

/// How long one request may take.
pub const TIMEOUT: Duration = Duration::from_secs(20);

/// Sends `shutdown` and waits for QEMU to exit (10 s at most); the exit must be a success.
pub fn shut_down(client: &mut Client, qemu: &mut Qemu) {
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
}

/// The firmware's folder.
pub fn firmware_dir() -> PathBuf {
    workspace().join("firmware")
}

/// QEMU, stopped when dropped (SIGTERM to `timeout`, which passes it on to QEMU).
pub struct Qemu(pub Child);

impl Drop for Qemu {
    fn drop(&mut self) {
        if let Ok(None) = self.0.try_wait() {
            let _ = Command::new("kill").arg(self.0.id().to_string()).status();
        }
        let _ = self.0.wait();
    }
}

/// A temporary directory, removed when dropped.
pub struct TempDir(pub PathBuf);

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// A client on 127.0.0.1:`port` once the image answers a status request (15 s at most).
pub fn connect(port: u16) -> Client {
    let started = Instant::now();
    loop {
        match Client::connect(&format!("tcp:127.0.0.1:{port}"), TIMEOUT) {
            Ok(mut c) => match c.status() {
                Ok(_) => return c,
                Err(e) if started.elapsed() > Duration::from_secs(15) => {
                    panic!("QEMU on port {port} does not answer: {e}")
                }
                Err(_) => std::thread::sleep(Duration::from_millis(100)),
            },
            Err(_) if started.elapsed() < Duration::from_secs(15) => {
                std::thread::sleep(Duration::from_millis(100))
            }
            Err(e) => panic!("cannot connect to QEMU: {e}"),
        }
    }
}

/// Builds the `qemu` image with its built-in stage file in `<outer target dir>/link-session` (the
/// link tests share it; the test binaries of one `cargo test` run one after the other); returns
/// the ELF. Panics with cargo's stderr if the build fails.
#[allow(dead_code)] // not every test binary runs every image
pub fn build_link_image() -> PathBuf {
    build_image("qemu", "qemu")
}

/// Builds the emulated board image (`board-emu`: the board image's RTIC application on QEMU's
/// netduinoplus2) with its built-in stage file, as [`build_link_image`] does; returns the ELF.
#[allow(dead_code)] // not every test binary runs every image
pub fn build_board_emu_image() -> PathBuf {
    build_image("board-emu", "board-emu")
}

/// The built-in stage file at `rate_hz` instead of its own rate, and the board-emu and mps2 link
/// images built with it in `<outer target dir>/board-emu-<rate>`: (the file, board-emu's ELF,
/// mps2's ELF). The file is rewritten only when its text changes, so a second call builds
/// nothing.
#[allow(dead_code)] // not every test binary runs every image
pub fn build_images_at_rate(rate_hz: u32) -> (PathBuf, PathBuf, PathBuf) {
    let dir = format!("board-emu-{rate_hz}");
    let built_in = std::fs::read_to_string(firmware_dir().join("params/xy-stage.toml"))
        .expect("the built-in stage file");
    let stage =
        piezo_stage::StageFile::parse("xy-stage.toml", &built_in).expect("the built-in stage file");
    let from = format!("loop_rate_hz = {:?}", stage.stage.loop_rate_hz);
    assert!(built_in.contains(&from), "{from}");
    let text = built_in.replace(&from, &format!("loop_rate_hz = {:?}", rate_hz as f32));
    let folder = outer_target_dir().join(&dir);
    std::fs::create_dir_all(&folder).expect("image folder");
    let params = folder.join(format!("xy-stage-{rate_hz}.toml"));
    if std::fs::read_to_string(&params).ok().as_deref() != Some(text.as_str()) {
        std::fs::write(&params, &text).expect("write the stage file");
    }
    let emu = build_image_with("board-emu", "board-emu", Some(&params), &dir);
    let mps2 = build_image_with("qemu", "qemu", Some(&params), &dir);
    (params, emu, mps2)
}

/// Builds `bin` of the firmware with `feature` and the built-in stage file in
/// `<outer target dir>/link-session`; returns the ELF.
fn build_image(feature: &str, bin: &str) -> PathBuf {
    build_image_with(feature, bin, None, "link-session")
}

/// Builds `bin` of the firmware with `feature` and the stage file `params` (the built-in one
/// for `None`) in `<outer target dir>/<dir>`; returns the ELF.
fn build_image_with(feature: &str, bin: &str, params: Option<&Path>, dir: &str) -> PathBuf {
    let target_dir = outer_target_dir().join(dir);
    let mut command = Command::new(std::env::var("CARGO").unwrap_or_else(|_| "cargo".into()));
    command
        .current_dir(firmware_dir())
        .args(["build", "--release", "--features", feature, "--bin", bin])
        .env("CARGO_TARGET_DIR", &target_dir);
    match params {
        Some(p) => command.env("PIEZO_PARAMS", p),
        None => command.env_remove("PIEZO_PARAMS"),
    };
    let build = command.output().expect("run cargo");
    assert!(
        build.status.success(),
        "building the {bin} image failed:\n{}",
        String::from_utf8_lossy(&build.stderr)
    );
    target_dir.join(TARGET).join("release").join(bin)
}

/// Runs `elf` with `firmware/run-qemu.sh --link PORT` on a free loopback port (its stdout piped,
/// at most 300 s); returns QEMU and the port.
#[allow(dead_code)] // not every test binary runs every image
pub fn run_link_image(elf: &Path) -> (Qemu, u16) {
    run_image("run-qemu.sh", elf)
}

/// Runs the emulated board image `elf` with `firmware/run-board-emu.sh --link PORT` (QEMU
/// netduinoplus2, USART1 on the port) as [`run_link_image`] does, and waits (60 s at most) for
/// its line saying the link receives (QEMU drops bytes that reach USART1 before the image has
/// enabled it). Returns QEMU, the port and QEMU's stdout, line by line (read by a thread).
#[allow(dead_code)] // not every test binary runs every image
pub fn run_board_emu_image(elf: &Path) -> (Qemu, u16, mpsc::Receiver<String>) {
    let (mut qemu, port) = run_image("run-board-emu.sh", elf);
    let stdout = qemu.0.stdout.take().expect("QEMU's stdout is piped");
    let (lines, received) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines() {
            let Ok(line) = line else { break };
            if lines.send(line).is_err() {
                break;
            }
        }
    });
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        match received.recv_timeout(left) {
            Ok(line) if line.contains("command link on USART1") => break,
            Ok(_) => {}
            Err(e) => panic!("the emulated board did not say its link receives: {e}"),
        }
    }
    (qemu, port, received)
}

/// Runs `elf` with `firmware/<script> --link PORT` on a free loopback port (its stdout piped, at
/// most 300 s); returns QEMU and the port.
fn run_image(script: &str, elf: &Path) -> (Qemu, u16) {
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("a free port")
        .port();
    let qemu = Qemu(
        Command::new(firmware_dir().join(script))
            .args(["--link", &port.to_string()])
            .arg(elf)
            .env("QEMU_TIMEOUT", "300")
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .unwrap_or_else(|e| panic!("run firmware/{script}: {e}")),
    );
    (qemu, port)
}
