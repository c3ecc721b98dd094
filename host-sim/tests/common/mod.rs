//! What host-sim's integration tests share: each test's own temporary directory.

use std::path::PathBuf;

thread_local! {
    /// Each test's own directory (libtest runs every test on a thread of its own), removed when
    /// the test's thread ends.
    static TEST_DIR: tempfile::TempDir = tempfile::Builder::new()
        .prefix("host_sim_test_")
        .tempdir()
        .unwrap();
}

/// `name` inside the running test's own temporary directory.
pub fn temp(name: &str) -> PathBuf {
    TEST_DIR.with(|dir| dir.path().join(name))
}
