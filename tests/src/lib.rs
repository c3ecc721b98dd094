//! Shared helpers of the integration tests.
//!
//! [`reference`] is the independent reference the core is checked against: it integrates the
//! continuous-time model *in time*, in f64, with classical RK4 at a step many times finer than the
//! sample period, and it does not call any code of `piezo-core`. Between two samples the input is
//! the straight line through them (first-order hold): a sampled model cannot know more about the
//! input between samples, and for the rate-independent Bouc-Wen state the hold type does not matter
//! at the sample instants.

pub mod reference {
    /// Bouc-Wen parameters in f64: ḣ = A·u̇ − β·|u̇|·|h|^(n−1)·h − γ·u̇·|h|^n.
    #[derive(Debug, Clone, Copy)]
    pub struct BoucWen64 {
        pub a: f64,
        pub beta: f64,
        pub gamma: f64,
        pub n: f64,
    }

    impl BoucWen64 {
        /// ḣ for input rate `du_dt`.
        pub fn rate(&self, h: f64, du_dt: f64) -> f64 {
            let hn = h.abs().powf(self.n);
            self.a * du_dt - self.beta * du_dt.abs() * hn * h.signum() - self.gamma * du_dt * hn
        }
    }

    /// Mass–spring–damper m·ẍ + c·ẋ + k·(x − x0) = k1·u + h.
    #[derive(Debug, Clone, Copy)]
    pub struct Msd64 {
        pub mass: f64,
        pub damping: f64,
        pub stiffness: f64,
        pub rest: f64,
        pub k1: f64,
    }

    /// h at every sample of `inputs` (sampled at `period`), from h = 0 at the first sample,
    /// integrating in time with `substeps` RK4 steps per sample.
    pub fn bouc_wen_states(
        bw: BoucWen64,
        inputs: &[f64],
        period: f64,
        substeps: usize,
    ) -> Vec<f64> {
        asymmetric_states(bw, 0.0, inputs, period, substeps)
    }

    /// h at every sample for seed 001's asymmetric law read literally, with φ = 0:
    /// ḣ = A·u̇ − β·|u̇|·|h|^(n−1)·h − γ·u̇·|h|^n + δ·u·sgn(u̇), from h = 0 at the first sample.
    pub fn asymmetric_states(
        bw: BoucWen64,
        delta: f64,
        inputs: &[f64],
        period: f64,
        substeps: usize,
    ) -> Vec<f64> {
        let mut h = 0.0;
        let mut out = Vec::with_capacity(inputs.len());
        out.push(h);
        let dt = period / substeps as f64;
        for w in inputs.windows(2) {
            let du_dt = (w[1] - w[0]) / period;
            let rate = |t: f64, h: f64| {
                let u = w[0] + du_dt * t;
                bw.rate(h, du_dt) + delta * u * du_dt.signum()
            };
            let mut t = 0.0;
            for _ in 0..substeps {
                let k1 = rate(t, h);
                let k2 = rate(t + 0.5 * dt, h + 0.5 * dt * k1);
                let k3 = rate(t + 0.5 * dt, h + 0.5 * dt * k2);
                let k4 = rate(t + dt, h + dt * k3);
                h += dt / 6.0 * (k1 + 2.0 * (k2 + k3) + k4);
                t += dt;
            }
            out.push(h);
        }
        out
    }

    /// x at every sample for the dynamic model, starting at rest (x = x0 + k1·u0/k, ẋ = 0, h = 0).
    pub fn dynamic_positions(
        bw: BoucWen64,
        msd: Msd64,
        inputs: &[f64],
        period: f64,
        substeps: usize,
    ) -> Vec<f64> {
        let mut state = [msd.rest + msd.k1 * inputs[0] / msd.stiffness, 0.0, 0.0];
        let mut out = Vec::with_capacity(inputs.len());
        out.push(state[0]);
        let dt = period / substeps as f64;
        for w in inputs.windows(2) {
            let du_dt = (w[1] - w[0]) / period;
            let rhs = |t: f64, s: [f64; 3]| -> [f64; 3] {
                let u = w[0] + du_dt * t;
                let force = msd.k1 * u + s[2];
                [
                    s[1],
                    (force - msd.damping * s[1] - msd.stiffness * (s[0] - msd.rest)) / msd.mass,
                    bw.rate(s[2], du_dt),
                ]
            };
            let mut t = 0.0;
            for _ in 0..substeps {
                let add = |s: [f64; 3], k: [f64; 3], f: f64| {
                    [s[0] + f * k[0], s[1] + f * k[1], s[2] + f * k[2]]
                };
                let k1 = rhs(t, state);
                let k2 = rhs(t + 0.5 * dt, add(state, k1, 0.5 * dt));
                let k3 = rhs(t + 0.5 * dt, add(state, k2, 0.5 * dt));
                let k4 = rhs(t + dt, add(state, k3, dt));
                for i in 0..3 {
                    state[i] += dt / 6.0 * (k1[i] + 2.0 * (k2[i] + k3[i]) + k4[i]);
                }
                t += dt;
            }
            out.push(state[0]);
        }
        out
    }

    /// The NAC2024 actuator of seed 000, Table 1 (k1 = 1 N/V, x0 = 0).
    pub fn nac2024() -> (BoucWen64, Msd64) {
        (
            BoucWen64 {
                a: 0.192,
                beta: 0.034,
                gamma: -0.0463,
                n: 1.419,
            },
            Msd64 {
                mass: 3.419e-4,
                damping: 491.03,
                stiffness: 3.725e8,
                rest: 0.0,
                k1: 1.0,
            },
        )
    }

    /// RMS of `a − b` divided by the span (max − min) of `b`.
    pub fn relative_rms_error(a: &[f64], b: &[f64]) -> f64 {
        assert_eq!(a.len(), b.len(), "series lengths differ");
        let sse: f64 = a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum();
        let max = b.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
        let min = b.iter().cloned().fold(f64::INFINITY, f64::min);
        (sse / a.len() as f64).sqrt() / (max - min)
    }
}

/// The same published parameter sets in the core's types.
pub mod fixtures {
    use piezo_core::{BoucWenParams, MassSpringDamperParams, StaticMap};

    /// The asymmetric stage of seed 001, Case I (y in metres: the paper's mm × 1e-3).
    pub fn seed001_case1() -> (BoucWenParams, StaticMap) {
        (
            BoucWenParams {
                a: -7.02182e-2,
                beta: 4.45753,
                gamma: 3.49259,
                n: 3.05869,
            },
            StaticMap {
                k1_m_per_v: -3.51711e-7,
                k2_m_per_h: -1.94566e-6,
                offset_m: 0.0,
            },
        )
    }

    /// The NAC2024 actuator of seed 000, Table 1 (k1 = 1 N/V, x0 = 0).
    pub fn nac2024() -> (BoucWenParams, MassSpringDamperParams) {
        (
            BoucWenParams {
                a: 0.192,
                beta: 0.034,
                gamma: -0.0463,
                n: 1.419,
            },
            MassSpringDamperParams {
                mass_kg: 3.419e-4,
                damping_n_s_per_m: 491.03,
                stiffness_n_per_m: 3.725e8,
                rest_position_m: 0.0,
                force_per_volt_n_per_v: 1.0,
            },
        )
    }
}

/// What the tests that build and run a firmware image under QEMU share: whether the tools are
/// here, where to build (a target directory of its own beside the outer `cargo test`'s, so the two
/// never wait for each other's lock), and a line on the real stderr.
pub mod readme;

pub mod qemu {
    use std::io::Write as _;
    use std::path::{Path, PathBuf};
    use std::process::Command;

    /// The firmware's target.
    pub const TARGET: &str = "thumbv7em-none-eabihf";

    /// A line on the real stderr (not captured by the test harness).
    pub fn say(line: &str) {
        let _ = writeln!(std::io::stderr(), "{line}");
    }

    /// The workspace root.
    pub fn workspace() -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .parent()
            .expect("tests/ is inside the workspace")
            .to_path_buf()
    }

    /// Why an image cannot be built and run here, if it cannot (QEMU or the Rust target missing).
    pub fn missing_tools() -> Option<String> {
        let qemu = Command::new("qemu-system-arm").arg("--version").output();
        if !qemu.is_ok_and(|o| o.status.success()) {
            return Some("qemu-system-arm not found (apt-get install qemu-system-arm)".to_string());
        }
        let sysroot = Command::new(std::env::var("RUSTC").unwrap_or_else(|_| "rustc".into()))
            .args(["--print", "sysroot"])
            .output()
            .ok()
            .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string());
        let installed = sysroot.is_some_and(|s| {
            Path::new(&s)
                .join("lib/rustlib")
                .join(TARGET)
                .join("lib")
                .is_dir()
        });
        (!installed)
            .then(|| format!("Rust target {TARGET} not installed (rustup target add {TARGET})"))
    }

    /// Builds the `replay` image with the stage file `params` and the reference table `reference`
    /// in `<outer target dir>/<subdir>` (panics with cargo's stderr if the build fails); returns
    /// the ELF.
    pub fn build_replay(params: &Path, reference: &Path, subdir: &str) -> PathBuf {
        let target_dir = outer_target_dir().join(subdir);
        let build = Command::new(std::env::var("CARGO").unwrap_or_else(|_| "cargo".into()))
            .current_dir(workspace().join("firmware"))
            .args([
                "build",
                "--release",
                "--features",
                "qemu",
                "--bin",
                "replay",
            ])
            .env("PIEZO_PARAMS", params)
            .env("PIEZO_REFERENCE", reference)
            .env("CARGO_TARGET_DIR", &target_dir)
            .output()
            .expect("run cargo");
        assert!(
            build.status.success(),
            "building the replay image failed:\n{}",
            String::from_utf8_lossy(&build.stderr)
        );
        target_dir.join(TARGET).join("release/replay")
    }

    /// The target directory the running test binary was built in (`<dir>/debug/deps/<test>`).
    pub fn outer_target_dir() -> PathBuf {
        std::env::current_exe()
            .ok()
            .and_then(|exe| Some(exe.parent()?.parent()?.parent()?.to_path_buf()))
            .unwrap_or_else(|| workspace().join("target"))
    }
}
