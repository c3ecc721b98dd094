//! The host's whole-run figures, timed by criterion (10 samples each):
//! * **oscillator identify**: the Bouc-Wen benchmark oscillator identified on
//!   `train_multisine_forgione.csv` (read in place from `../shared/data/boucwen_benchmark/`; the
//!   bench says so and skips it when the file is absent), `vp-de-lm`, seed 1 — what
//!   `host-sim identify --data …/train_multisine_forgione.csv --model oscillator` runs after reading
//!   the file;
//! * **demo**: the main job's computation (`run_demo` with the defaults: identification record,
//!   identify, close-loop, the uncompensated and compensated runs), without writing its files.
//!
//! `cargo bench -p host-sim --bench whole_runs`. Each figure's result is printed once before the
//! criterion loop (the oscillator's training RMS, the demo's tracking RMS), so that a faster run
//! that fits worse shows.

use criterion::{black_box, Criterion};
use host_sim::demo::{run_demo, DemoSettings};
use host_sim::identify::model::ModelKind;
use host_sim::identify::{identify, IdentifySettings, Record};
use std::path::Path;
use std::time::Instant;

/// The training record, from the workspace root's sibling `shared` folder.
const FORGIONE: &str = "../shared/data/boucwen_benchmark/train_multisine_forgione.csv";

fn oscillator_settings() -> IdentifySettings {
    IdentifySettings::new(ModelKind::Oscillator)
}

/// The training record, or why not (criterion runs benches from the package's folder).
fn forgione() -> Result<Record, String> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join(FORGIONE);
    if !path.exists() {
        return Err(format!("{} not found", path.display()));
    }
    Record::read(&path, None, None, None).map_err(|e| e.to_string())
}

fn benches(c: &mut Criterion) {
    let mut g = c.benchmark_group("whole_runs");
    g.sample_size(10);
    match forgione() {
        Ok(rec) => {
            let started = Instant::now();
            let id = identify(&rec, &oscillator_settings()).expect("identify");
            eprintln!(
                "oscillator identify (train_multisine_forgione, N = {}): {:.2} s, training RMS {:.4e} m",
                rec.u.len(),
                started.elapsed().as_secs_f64(),
                id.summary.fit.rms
            );
            g.bench_function("oscillator_identify_forgione", |b| {
                b.iter(|| identify(black_box(&rec), &oscillator_settings()).expect("identify"))
            });
        }
        Err(e) => eprintln!("oscillator identify skipped: {e}"),
    }
    let settings = DemoSettings::default();
    let started = Instant::now();
    let demo = run_demo(&settings, &mut |_| {}).expect("demo");
    eprintln!(
        "demo: {:.2} s; tracking\n{}",
        started.elapsed().as_secs_f64(),
        demo.table()
    );
    g.bench_function("demo", |b| {
        b.iter(|| run_demo(black_box(&settings), &mut |_| {}).expect("demo"))
    });
    g.finish();
}

fn main() {
    let mut c = Criterion::default().configure_from_args();
    benches(&mut c);
    c.final_summary();
}
