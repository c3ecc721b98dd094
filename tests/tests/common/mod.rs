//! What the link sessions under QEMU share: the firmware folder, QEMU stopped when dropped, a
//! temporary directory removed when dropped, and a link client that waits for the image to
//! answer.

use std::path::PathBuf;
use std::process::{Child, Command};
use std::time::{Duration, Instant};

use host_sim::link::Client;
use integration_tests::qemu::workspace;

/// How long one request may take.
pub const TIMEOUT: Duration = Duration::from_secs(20);

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
