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
//! **Link mode** (`./run-qemu.sh --link PORT ELF`, which passes `--link` on the semihosting
//! command line and serves UART0 on 127.0.0.1:PORT): instead of the self-check, the loop runs
//! against the simulated stage until a `Shutdown` request, paced by SysTick at the stage file's
//! loop rate (QEMU's virtual clock), and serves the command link
//! ([`piezo_firmware::session`]) on UART0 between ticks. While frames are on and the transmit
//! buffer is short of room, the tick waits for the link (the simulated stage's time stops with
//! it), so no frame is lost under QEMU. Deadlines are not checked here (QEMU's timing is not
//! the board's): an overrun is injected with the `InjectOverrun` request.
//!
//! **Servo table** (`./run-qemu.sh --servo-table ELF`): instead of the self-check, the four
//! control modes on the simulated stage with creep, drift and sensor noise
//! ([`piezo_firmware::servo_table`]): one `servo-row` line per mode, signal and frequency (RMS
//! and largest error in % of the stroke, the mode's closed-loop bandwidth), then PASS if
//! feedforward + feedback beats feedback alone by 5× at 100 Hz and feedforward alone by 5× at
//! 1 Hz, for both signals, with no fault in any run.
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

    use cortex_m_rt::{entry, exception};
    use cortex_m_semihosting::{debug, hprintln};

    use piezo_firmware::demo::{self, DemoComparison, DemoReport};
    use piezo_firmware::frames::{Frame, SequenceChecker};
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
        if command_line_has(b"--link") {
            link::run()
        }
        if command_line_has(b"--servo-table") {
            servo_table()
        }
        self_check()
    }

    /// True if the semihosting command line holds `flag` (`run-qemu.sh --link`,
    /// `--servo-table`).
    #[allow(unsafe_code)]
    fn command_line_has(flag: &[u8]) -> bool {
        let mut line = [0u8; 128];
        // SAFETY: SYS_GET_CMDLINE writes at most `line.len()` bytes (NUL included) into `line`,
        // which outlives the call; the argument block is the two words the call takes.
        let status = unsafe {
            cortex_m_semihosting::syscall!(GET_CMDLINE, line.as_mut_ptr(), line.len() - 1)
        };
        status == 0 && line.windows(flag.len()).any(|w| w == flag)
    }

    /// The servo table (see the crate docs); exits with success if the ratios hold.
    fn servo_table() -> ! {
        use piezo_core::ServoMode;
        use piezo_firmware::servo_table::{self, Shape, FREQUENCIES_HZ};
        hprintln!(
            "piezo-firmware qemu servo table: parameters {} ({}), fnv1a32 {:#010x}, loop {} Hz, plant {:?}",
            params::VERSION,
            params::SOURCE,
            params::FNV1A32,
            params::LOOP_RATE_HZ,
            servo_table::table_disturbances()
        );
        let mut rms = [[[0.0f32; 3]; 2]; 4];
        let mut faults = 0u32;
        for (m, mode) in ServoMode::ALL.into_iter().enumerate() {
            let bandwidth = match servo_table::bandwidth_hz(mode) {
                Ok(b) => b,
                Err(e) => fail(format_args!("servo table: {}: {e:?}", mode.name())),
            };
            for (s, shape) in [Shape::Triangle, Shape::Sine].into_iter().enumerate() {
                for (f, &hz) in FREQUENCIES_HZ.iter().enumerate() {
                    let row = match servo_table::tracking(mode, shape, hz) {
                        Ok(r) => r,
                        Err(e) => fail(format_args!("servo table: {}: {e:?}", mode.name())),
                    };
                    hprintln!(
                        "servo-row mode={} signal={} freq_hz={} rms_percent={} max_percent={} bandwidth_hz={} faults={}",
                        mode.name(),
                        shape.name(),
                        hz,
                        row.rms_percent,
                        row.max_percent,
                        bandwidth,
                        row.faults
                    );
                    rms[m][s][f] = row.rms_percent;
                    faults += row.faults;
                }
            }
        }
        // Modes in ServoMode::ALL order: open loop, feedforward, feedback, both.
        let mut ok = faults == 0;
        for s in 0..2 {
            let slow = rms[1][s][0] / rms[3][s][0];
            let fast = rms[2][s][2] / rms[3][s][2];
            hprintln!(
                "{}: both vs feedforward at 1 Hz {}x, both vs feedback at 100 Hz {}x (limit 5x)",
                ["triangle", "sine"][s],
                slow,
                fast
            );
            ok &= slow >= 5.0 && fast >= 5.0;
        }
        if ok {
            hprintln!("PASS");
            debug::exit(debug::EXIT_SUCCESS);
        } else {
            hprintln!("FAIL ({} faults)", faults);
            debug::exit(debug::EXIT_FAILURE);
        }
        #[allow(clippy::empty_loop)]
        loop {}
    }

    fn self_check() -> ! {
        let frame_decimation = demo::settings().map_or(1, |s| s.frame_decimation);
        hprintln!(
            "piezo-firmware qemu: parameters {} ({}), fnv1a32 {:#010x}, fingerprint {:#010x}, loop {} Hz, one frame every {} ticks",
            params::VERSION,
            params::SOURCE,
            params::FNV1A32,
            piezo_firmware::session::built_in_fingerprint(),
            params::LOOP_RATE_HZ,
            frame_decimation
        );
        let mut receiver = SequenceChecker::default();
        let mut received: u32 = 0;
        let mut printed = heapless::Vec::<Frame, PRINT_FRAMES>::new();
        let compensated = demo::run_demo(Feedforward::Compensator, |k, lp| {
            // The sender: drain every tick (the receiver checks the sequence); print one batch.
            let mut batch = heapless::Vec::<Frame, 8>::new();
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
            hprintln!("{}", f);
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
        let failures = cmp.failures();
        if failures.is_empty() && drill_ok && receiver.gaps == 0 {
            hprintln!("PASS");
            debug::exit(debug::EXIT_SUCCESS);
        } else {
            hprintln!("FAIL ({})", params::SOURCE);
            for failure in &failures {
                hprintln!("  {}", failure);
            }
            if !drill_ok {
                hprintln!("  overrun drill: the injected overrun did not hold the outputs");
            }
            if receiver.gaps > 0 {
                hprintln!(
                    "  frames: {} gaps ({} lost) in the compensated run",
                    receiver.gaps,
                    receiver.lost
                );
            }
            debug::exit(debug::EXIT_FAILURE);
        }
        #[allow(clippy::empty_loop)]
        loop {}
    }

    /// The command link on UART0 around the loop and the simulated stage.
    mod link {
        use core::cell::Cell;

        use cortex_m::interrupt::InterruptNumber;
        use cortex_m::peripheral::syst::SystClkSource;
        use cortex_m::peripheral::NVIC;
        use cortex_m_semihosting::{debug, hprintln};

        use piezo_firmware::cmsdk_uart::{self, Uart0};
        use piezo_firmware::demo;
        use piezo_firmware::params;
        use piezo_firmware::plant::{plant_io, XyPlant};
        use piezo_firmware::session::{self, Session};

        /// mps2-an386's CPU clock, SysTick's source \[Hz\].
        const CPU_CLOCK_HZ: u32 = 25_000_000;

        #[derive(Clone, Copy)]
        struct Irq(u16);

        // SAFETY: the numbers are UART0's NVIC lines on mps2-an386 (0 and 1), valid interrupts.
        #[allow(unsafe_code)]
        unsafe impl InterruptNumber for Irq {
            fn number(self) -> u16 {
                self.0
            }
        }

        pub fn run() -> ! {
            let Some(mut core) = cortex_m::Peripherals::take() else {
                super::fail(format_args!("core peripherals already taken"))
            };
            let settings = demo::settings().unwrap_or_else(|e| {
                super::fail(format_args!("parameter set refused at boot: {e:?}"))
            });
            let (Some(scale), Some(stage)) = (
                demo::sensor_scale(),
                XyPlant::from_params(params::SAMPLE_PERIOD_S),
            ) else {
                super::fail(format_args!("sensor scale refused at boot"))
            };
            let plant = Cell::new(stage);
            let mut io = plant_io(&plant, scale);
            let lp = demo::at_rest(settings);
            let mut session = Session::new(
                lp,
                params::VERSION,
                params::FNV1A32,
                session::built_in_fingerprint(),
            );

            let mut uart = Uart0::init();
            for irq in [cmsdk_uart::RX_IRQ, cmsdk_uart::TX_IRQ] {
                // SAFETY: the handler for these lines (DefaultHandler) only acknowledges them;
                // no critical section depends on them being masked.
                #[allow(unsafe_code)]
                unsafe {
                    NVIC::unmask(Irq(irq))
                };
            }
            let syst = &mut core.SYST;
            syst.set_clock_source(SystClkSource::Core);
            syst.set_reload(CPU_CLOCK_HZ / params::LOOP_RATE_HZ as u32 - 1);
            syst.clear_current();
            syst.enable_interrupt();
            syst.enable_counter();
            hprintln!(
                "piezo-firmware qemu: link on UART0, parameters {} ({}), fnv1a32 {:#010x}, fingerprint {:#010x}, loop {} Hz",
                params::VERSION,
                params::SOURCE,
                params::FNV1A32,
                session::built_in_fingerprint(),
                params::LOOP_RATE_HZ
            );

            let mut tick_due = false;
            loop {
                let mut busy = false;
                while let Some(byte) = uart.read() {
                    session.receive(&[byte]);
                    busy = true;
                }
                busy |= session.transmit(|b| uart.write(b)) > 0;
                if session.shutdown_requested() && session.pending_tx() == 0 {
                    hprintln!("piezo-firmware qemu: shutdown");
                    debug::exit(debug::EXIT_SUCCESS);
                }
                tick_due |= syst.has_wrapped();
                if tick_due && session.has_room_for_frame() {
                    tick_due = false;
                    session.tick(&mut io, false);
                    let mut p = plant.get();
                    p.advance();
                    plant.set(p);
                    busy = true;
                }
                if !busy {
                    // SysTick, or a UART byte in or out, wakes the loop.
                    cortex_m::asm::wfi();
                }
            }
        }

        /// SysTick only wakes the loop (which polls its wrap flag).
        #[cortex_m_rt::exception]
        fn SysTick() {}
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

    use piezo_firmware::semihosting_exit::fail;

    piezo_firmware::semihosting_fault_handlers!("");

    #[allow(unsafe_code)] // cortex-m-rt requires DefaultHandler to be an `unsafe fn`.
    #[exception]
    unsafe fn DefaultHandler(irqn: i16) {
        use piezo_firmware::cmsdk_uart;
        let line = u16::try_from(irqn).ok();
        if line == Some(cmsdk_uart::RX_IRQ) || line == Some(cmsdk_uart::TX_IRQ) {
            // Link mode: a UART0 byte in or out only wakes the main loop.
            cmsdk_uart::Uart0::clear_interrupts();
            return;
        }
        fail(format_args!("unhandled exception or interrupt {irqn}"))
    }
}

#[cfg(not(target_os = "none"))]
fn main() {
    eprintln!("the qemu image runs on thumbv7em-none-eabihf: see firmware/ci.sh");
}
