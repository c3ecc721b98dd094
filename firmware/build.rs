//! Three jobs: turn the parameter file into Rust consts, turn the reference record of the
//! `replay` image into a const table, and put the right `memory.x` on the linker search path
//! (thumb targets only).
//!
//! # Parameters
//! The stage file is `firmware/params/xy-stage.toml`, or the file named by the environment
//! variable `PIEZO_PARAMS` (absolute, or relative to `firmware/`). It is read and validated by
//! `piezo-stage` (the reader every tool uses, with `piezo-core`'s own constructors), checked
//! against what this firmware drives (`build/params.rs`) and written to `OUT_DIR/params.rs`,
//! which `src/params.rs` includes. A refused file stops the build with a message naming the
//! file, line, column and key. The version string (`name version`) and an FNV-1a
//! checksum of the file's bytes are part of the consts and are logged at boot.
//!
//! # Reference table
//! The record named by the environment variable `PIEZO_REFERENCE` (a CSV with `t_s` and `r_m`,
//! or `rx_m` and `ry_m`, at the stage file's loop rate; path absolute or relative to
//! `firmware/`; `build/reference.rs`) is written to `OUT_DIR/reference.rs`, which the `replay`
//! image includes. Unset: an empty table.
//!
//! # Memory layout
//!
//! cortex-m-rt's `link.x` does `INCLUDE memory.x`. In a workspace the linker runs from the
//! workspace root, so the file has to be put on the search path explicitly:
//! - feature `board` (or no image feature): `../memory.x` at the repository root (STM32F407);
//! - feature `board-emu`: the same root `memory.x` (QEMU netduinoplus2's STM32F405 has the
//!   F407's 1 MiB flash at 0x0800_0000 and 128 KiB SRAM at 0x2000_0000);
//! - feature `qemu`: `firmware/memory-mps2-an386.x` (QEMU mps2-an386).
//!
//! The chosen file is copied to `OUT_DIR/memory.x` and `OUT_DIR` is added to the search path.
//! Catch: cargo runs the linker in the workspace root, and rust-lld resolves `INCLUDE memory.x`
//! against the current directory before any `-L` path, so the root (board) `memory.x` would
//! always win. For the QEMU image this script therefore also passes
//! `--remap-inputs=memory.x=OUT_DIR/memory.x` (an ld.lld option, LLVM ≥ 17) so the linker reads
//! the mps2-an386 layout instead. Check with `readelf -S`: `.vector_table` at 0x00000000 (QEMU)
//! or 0x08000000 (board).
//!
//! Enabling more than one image feature on a thumb target is an error. On the host (`cargo test` at
//! the root) this script does nothing.
use std::env;
use std::fs;
use std::path::PathBuf;

#[path = "build/params.rs"]
mod params;
#[path = "build/reference.rs"]
mod reference;

/// Default parameter file, relative to `firmware/`.
const DEFAULT_PARAMS: &str = "params/xy-stage.toml";

fn main() {
    let manifest_dir =
        PathBuf::from(env::var("CARGO_MANIFEST_DIR").expect("cargo sets CARGO_MANIFEST_DIR"));
    let out_dir = PathBuf::from(env::var("OUT_DIR").expect("cargo sets OUT_DIR"));
    let loop_rate_hz = generate_params(&manifest_dir, &out_dir);
    generate_reference(&manifest_dir, &out_dir, loop_rate_hz);
    let board_layout = manifest_dir.join("..").join("memory.x");
    let qemu_layout = manifest_dir.join("memory-mps2-an386.x");
    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rerun-if-changed={}", board_layout.display());
    println!("cargo:rerun-if-changed={}", qemu_layout.display());

    let target = env::var("TARGET").unwrap_or_default();
    if !target.starts_with("thumb") {
        return;
    }
    let qemu = env::var_os("CARGO_FEATURE_QEMU").is_some();
    let board = env::var_os("CARGO_FEATURE_BOARD").is_some();
    let board_emu = env::var_os("CARGO_FEATURE_BOARD_EMU").is_some();
    if usize::from(qemu) + usize::from(board) + usize::from(board_emu) > 1 {
        panic!("features `qemu`, `board` and `board-emu` select different images: enable only one");
    }
    let chosen = if qemu { qemu_layout } else { board_layout };
    fs::copy(&chosen, out_dir.join("memory.x"))
        .unwrap_or_else(|e| panic!("cannot copy {}: {e}", chosen.display()));
    println!("cargo:rustc-link-search={}", out_dir.display());
    if qemu {
        println!(
            "cargo:rustc-link-arg-bins=--remap-inputs=memory.x={}",
            out_dir.join("memory.x").display()
        );
    }
    // defmt's linker script is only needed (and only found) where defmt is linked: the board
    // image and its emulated variant.
    if board || board_emu {
        println!("cargo:rustc-link-arg-bins=-Tdefmt.x");
    }
}

/// Parses and validates the parameter file and writes `OUT_DIR/params.rs`; exits with a message
/// naming the file and field if the file is refused. Returns the loop rate \[Hz\].
fn generate_params(manifest_dir: &std::path::Path, out_dir: &std::path::Path) -> f32 {
    println!("cargo:rerun-if-env-changed=PIEZO_PARAMS");
    println!("cargo:rerun-if-changed=build/params.rs");
    let given = env::var("PIEZO_PARAMS").unwrap_or_else(|_| DEFAULT_PARAMS.to_string());
    let path = manifest_dir.join(&given);
    println!("cargo:rerun-if-changed={}", path.display());
    let bytes = fs::read(&path).unwrap_or_else(|e| {
        eprintln!(
            "error: parameter file {} (PIEZO_PARAMS={given}): {e}",
            path.display()
        );
        std::process::exit(1);
    });
    let set = params::load(&given, &bytes).unwrap_or_else(|message| {
        eprintln!("error: {message}");
        std::process::exit(1);
    });
    for warning in &set.warnings {
        println!("cargo:warning={warning}");
    }
    fs::write(out_dir.join("params.rs"), params::generate(&set, &given))
        .unwrap_or_else(|e| panic!("cannot write OUT_DIR/params.rs: {e}"));
    set.loop_rate_hz
}

/// Reads the record named by `PIEZO_REFERENCE` (if set) and writes `OUT_DIR/reference.rs`;
/// exits with a message naming the file, line and column if it is refused.
fn generate_reference(manifest_dir: &std::path::Path, out_dir: &std::path::Path, rate_hz: f32) {
    println!("cargo:rerun-if-env-changed=PIEZO_REFERENCE");
    println!("cargo:rerun-if-changed=build/reference.rs");
    let (table, given) = match env::var("PIEZO_REFERENCE") {
        Ok(given) if !given.is_empty() => {
            let path = manifest_dir.join(&given);
            println!("cargo:rerun-if-changed={}", path.display());
            let text = fs::read_to_string(&path).unwrap_or_else(|e| {
                eprintln!(
                    "error: reference record {} (PIEZO_REFERENCE={given}): {e}",
                    path.display()
                );
                std::process::exit(1);
            });
            let table = reference::parse(&given, &text, rate_hz).unwrap_or_else(|message| {
                eprintln!("error: {message}");
                std::process::exit(1);
            });
            (table, given)
        }
        _ => (
            reference::Table {
                samples_m: Vec::new(),
                axes: 1,
            },
            String::new(),
        ),
    };
    fs::write(
        out_dir.join("reference.rs"),
        reference::generate(&table, &given),
    )
    .unwrap_or_else(|e| panic!("cannot write OUT_DIR/reference.rs: {e}"));
}
