//! QEMU image for `mps2-an386` (Cortex-M4F): runs the fixed self-check of
//! [`piezo_firmware::demo`] (the loop body [`piezo_firmware::control::tick`] against a simulated
//! stage), prints the result over semihosting and exits QEMU with success or failure.
//!
//! Build and run (from `firmware/`): `cargo qemu`, or `./ci.sh`, or
//! `cargo build --release --features qemu --bin qemu` then
//! `./run-qemu.sh ../target/thumbv7em-none-eabihf/release/qemu` (path under `CARGO_TARGET_DIR`).
//!
//! Nothing can hang CI: the panic handler, HardFault and every unhandled exception exit QEMU with
//! failure through semihosting, and the run script adds a timeout.
//!
//! After the self-check a bench window runs [`BENCH_TICKS`] ticks between the markers
//! `bench_mark_start`/`bench_mark_end`, for `/work/shared/tools/qemu-insn-count/count.sh`
//! (instructions per tick = window 1 / BENCH_TICKS, minus window 2, the empty window).
//!
//! On the host this file builds to a stub `main` (only with `--features qemu`), so
//! `cargo clippy --all-features` on the host still works.
#![cfg_attr(target_os = "none", no_std)]
#![cfg_attr(target_os = "none", no_main)]

#[cfg(target_os = "none")]
mod image {
    use core::cell::Cell;
    use core::fmt::Write as _;
    use core::hint::black_box;

    use cortex_m_rt::{entry, exception, ExceptionFrame};
    use cortex_m_semihosting::{debug, hio, hprintln};

    use piezo_firmware::control::{tick, LoopIo};
    use piezo_firmware::demo::{self, linear_feedforward};
    use piezo_firmware::plant::{PlantAdc, PlantDac, SimPlant};

    /// Ticks in the instruction-count window.
    pub const BENCH_TICKS: u32 = 1_000;

    #[entry]
    fn main() -> ! {
        hprintln!(
            "piezo-firmware qemu: {} ticks at {} Hz, linear feed-forward on the simulated stage",
            demo::DEMO_TICKS,
            demo::LOOP_RATE_HZ
        );
        // The feed-forward is the one thing to swap: pass the compensator's step here.
        let report = demo::run_demo(linear_feedforward);
        hprintln!(
            "tracking error after settling: rms {} nm (limit {}), max {} nm (limit {})",
            report.stats.rms_m() * 1e9,
            demo::RMS_ERROR_LIMIT_M * 1e9,
            report.stats.max_abs_m() * 1e9,
            demo::MAX_ERROR_LIMIT_M * 1e9
        );
        hprintln!(
            "guard faults: non_finite {} window_clamped {} slew_limited {} (after settling: {})",
            report.counters.non_finite,
            report.counters.window_clamped,
            report.counters.slew_limited,
            report.faults_after_settle
        );
        let passed = report.passed();

        bench();

        if passed {
            hprintln!("PASS");
            debug::exit(debug::EXIT_SUCCESS);
        } else {
            hprintln!("FAIL");
            debug::exit(debug::EXIT_FAILURE);
        }
        #[allow(clippy::empty_loop)]
        loop {}
    }

    /// [`BENCH_TICKS`] ticks of the loop body (with the simulated stage behind the traits)
    /// between the markers, then an empty window.
    fn bench() {
        let plant = Cell::new(SimPlant::new(demo::plant_params()));
        let config = demo::loop_config();
        let mut io = LoopIo {
            dac: PlantDac(&plant),
            dac_channel: (),
            adc: PlantAdc(&plant),
            adc_channel: (),
        };
        let mut guard = config.limits().state(50.0);
        bench_mark_start();
        for k in 0..BENCH_TICKS {
            let reference_m = demo::REFERENCE_OFFSET_M + k as f32 * 1e-10;
            let out = tick(
                &mut io,
                &config,
                &mut guard,
                black_box(reference_m),
                linear_feedforward,
            );
            black_box(out.ok());
        }
        bench_mark_end();
        bench_mark_start();
        bench_mark_end();
    }

    // The markers are found by name (`nm`), so they must keep their symbol and not be merged.
    #[allow(unsafe_code)] // `no_mangle` only; no unsafe operation.
    #[no_mangle]
    #[inline(never)]
    extern "C" fn bench_mark_start() {
        black_box(0x5741_5254_u32);
    }

    #[allow(unsafe_code)] // `no_mangle` only; no unsafe operation.
    #[no_mangle]
    #[inline(never)]
    extern "C" fn bench_mark_end() {
        black_box(0x0045_4e44_u32);
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
