//! QEMU image for `mps2-an386` (Cortex-M4F): the self-check of [`piezo_firmware::demo`] — the
//! two-axis loop [`piezo_firmware::xy_loop::TwoAxisLoop`] with `piezo_core::Compensator` against
//! the simulated stage (independent f32 Bouc-Wen + lag), once compensated and once with the
//! linear baseline — then an overrun drill. Prints the parameter set (version, FNV-1a), RMS and
//! peak error of both runs, a few sample frames, and exits QEMU with success only if the
//! compensated RMS error is below 0.2 × the uncompensated one and below the absolute limits.
//!
//! With the feature `frames-all` it prints every frame of the compensated run instead of four
//! (4 000 lines, one per tick, in the text form of `piezo_firmware::frames`), for
//! `host-sim capture`: `cargo build --release --features qemu,frames-all --bin qemu`, then
//! `./run-qemu.sh $CARGO_TARGET_DIR/thumbv7em-none-eabihf/release/qemu > qemu.log` and
//! `host-sim capture --log qemu.log --out qemu.csv`.
//!
//! Build and run (from `firmware/`): `cargo qemu`, or `./ci.sh`, or
//! `cargo build --release --features qemu --bin qemu` then
//! `./run-qemu.sh $CARGO_TARGET_DIR/thumbv7em-none-eabihf/release/qemu`.
//!
//! Nothing can hang CI: the panic handler, HardFault and every unhandled exception exit QEMU with
//! failure through semihosting, and the run script adds a timeout. (Instruction counts and the
//! no-panic link check are in the `check` image, `src/bin/check.rs`.)
//!
//! On the host this file builds to a stub `main` (only with `--features qemu`), so
//! `cargo clippy --all-features` on the host still works.
#![cfg_attr(target_os = "none", no_std)]
#![cfg_attr(target_os = "none", no_main)]

#[cfg(target_os = "none")]
mod image {
    use core::fmt::Write as _;

    use cortex_m_rt::{entry, exception, ExceptionFrame};
    use cortex_m_semihosting::{debug, hio, hprintln};

    use piezo_firmware::demo::{self, DemoComparison, DemoReport};
    use piezo_firmware::frames::{SampleFrame, SequenceChecker};
    use piezo_firmware::params;
    use piezo_firmware::xy_loop::{Feedforward, Mode};

    /// Frames printed from the compensated run (one batch, starting at this tick).
    const PRINT_FRAMES_AT_TICK: u32 = 2_000;
    /// Frames in the printed batch.
    const PRINT_FRAMES: usize = 4;
    /// Print every frame of the compensated run as it is drained (feature `frames-all`).
    const PRINT_ALL_FRAMES: bool = cfg!(feature = "frames-all");

    #[entry]
    fn main() -> ! {
        let frame_decimation = demo::settings().map_or(1, |s| s.frame_decimation);
        hprintln!(
            "piezo-firmware qemu: parameters {} ({}), fnv1a32 {:#010x}, loop {} Hz, one frame every {} ticks",
            params::VERSION,
            params::SOURCE,
            params::FNV1A32,
            params::LOOP_RATE_HZ,
            frame_decimation
        );
        let mut receiver = SequenceChecker::default();
        let mut received: u32 = 0;
        let mut printed = heapless::Vec::<SampleFrame, PRINT_FRAMES>::new();
        let compensated = demo::run_demo(Feedforward::Compensator, |k, lp| {
            // The sender: drain every tick (the receiver checks the sequence); print one batch.
            let mut batch = heapless::Vec::<SampleFrame, 8>::new();
            lp.frames.drain_into(&mut batch);
            for f in &batch {
                receiver.accept(f.sequence);
                received += 1;
                if PRINT_ALL_FRAMES {
                    hprintln!("{}", f);
                } else if k >= PRINT_FRAMES_AT_TICK && printed.len() < PRINT_FRAMES {
                    let _ = printed.push(*f);
                }
            }
        });
        let uncompensated = demo::run_demo(Feedforward::Linear, |_, _| {});
        let (compensated, uncompensated) = match (compensated, uncompensated) {
            (Ok(c), Ok(u)) => (c, u),
            (Err(e), _) | (_, Err(e)) => fail(format_args!("parameter set refused at boot: {e:?}")),
        };
        for f in &printed {
            hprintln!("{} | wire {:02x?}", f, &f.to_bytes()[..8]);
        }
        hprintln!(
            "frames: {} received, {} gaps ({} lost)",
            received,
            receiver.gaps,
            receiver.lost
        );
        let cmp = DemoComparison {
            compensated,
            uncompensated,
        };
        print_run("compensated  ", &compensated);
        print_run("uncompensated", &uncompensated);
        let ratio = cmp.ratio();
        hprintln!(
            "ratio compensated/uncompensated rms: x {} y {} (limit {}); limits rms {} nm, max {} nm",
            ratio[0],
            ratio[1],
            demo::RATIO_LIMIT,
            demo::RMS_ERROR_LIMIT_M * 1e9,
            demo::MAX_ERROR_LIMIT_M * 1e9
        );
        let drill = demo::overrun_drill();
        let drill_ok = match drill {
            Ok((counters, mode, before, at_fault)) => {
                hprintln!(
                    "overrun drill: injected at tick {}: overruns {}, safe entries {}, mode {:?}, output {:?} V held (was {:?} V)",
                    demo::DRILL_OVERRUN_TICK,
                    counters.overruns,
                    counters.safe_entries,
                    mode,
                    at_fault,
                    before
                );
                counters.overruns == 1 && matches!(mode, Mode::Safe(_)) && before == at_fault
            }
            Err(e) => {
                hprintln!("overrun drill could not run: {:?}", e);
                false
            }
        };
        if cmp.passed() && drill_ok && receiver.gaps == 0 {
            hprintln!("PASS");
            debug::exit(debug::EXIT_SUCCESS);
        } else {
            hprintln!("FAIL");
            debug::exit(debug::EXIT_FAILURE);
        }
        #[allow(clippy::empty_loop)]
        loop {}
    }

    fn print_run(name: &str, r: &DemoReport) {
        hprintln!(
            "{}: x rms {} nm max {} nm | y rms {} nm max {} nm | faults {} guard after settle {} limited {}",
            name,
            r.stats[0].rms_m() * 1e9,
            r.stats[0].max_abs_m() * 1e9,
            r.stats[1].rms_m() * 1e9,
            r.stats[1].max_abs_m() * 1e9,
            r.counters.faults(),
            r.guard_faults_after_settle,
            r.counters.compensator_limited
        );
    }

    fn fail(what: core::fmt::Arguments<'_>) -> ! {
        // Best effort: an error while printing must not stop the exit.
        if let Ok(mut err) = hio::hstderr() {
            let _ = err.write_fmt(what);
            let _ = err.write_str("\n");
        }
        debug::exit(debug::EXIT_FAILURE);
        #[allow(clippy::empty_loop)]
        loop {}
    }

    #[panic_handler]
    fn panic(info: &core::panic::PanicInfo<'_>) -> ! {
        fail(format_args!("panic: {info}"))
    }

    #[allow(unsafe_code)] // cortex-m-rt requires HardFault to be an `unsafe fn`.
    #[exception]
    unsafe fn HardFault(frame: &ExceptionFrame) -> ! {
        fail(format_args!("HardFault at pc {:#010x}", frame.pc()))
    }

    #[allow(unsafe_code)] // cortex-m-rt requires DefaultHandler to be an `unsafe fn`.
    #[exception]
    unsafe fn DefaultHandler(irqn: i16) {
        fail(format_args!("unhandled exception or interrupt {irqn}"))
    }
}

#[cfg(not(target_os = "none"))]
fn main() {
    eprintln!("the qemu image runs on thumbv7em-none-eabihf: see firmware/ci.sh");
}
