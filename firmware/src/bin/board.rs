//! STM32F4-Discovery image: the two-axis compensator loop on real converters (DAC8563 channel A/B
//! → x/y piezo amplifiers, displacement sensors → one ADS8681 per axis), paced by TIM2 at the
//! stage file's loop rate, and the command link ([`piezo_firmware::session`], the same endpoint
//! the QEMU image serves) over USB CDC-ACM. Wiring and clocks are in `piezo_firmware::board`,
//! the loop in `piezo_firmware::xy_loop`.
//!
//! # Tasks (RTIC 2, NVIC priorities: higher preempts lower)
//!
//! | task            | priority | runs on                       | does                                             |
//! |-----------------|----------|-------------------------------|--------------------------------------------------|
//! | `control_tick`  | 3        | TIM2 update (the loop rate)   | `Session::tick`: sensor → reference → compensator → guard → DAC, frame encoding; deadline measurement, `Session::note_tick_cycles` |
//! | `usb_link`      | 2        | OTG_FS interrupt, or pended by the tick when bytes wait | USB poll, received bytes → `Session::receive`, `Session::transmit` → serial port |
//! | `telemetry`     | 1        | spawned by the tick once a second | defmt log of the tick's measured cost, the loop's and the link's counters, safe-state entries |
//! | idle            | 0        | —                             | nothing (busy loop)                              |
//!
//! The session (the loop inside it) is one RTIC shared resource. The tick has the highest
//! priority of its users, so it never waits for it; the link and telemetry lock it for one
//! request's application, one batch of ≤ 64 bytes out or one status, and those locks delay the
//! tick. The link decodes and prepares each request before it locks (`session::prepare`: an
//! upload's validation runs there, preempted by the tick), so requests are applied between two
//! ticks, as `Session` requires, and none holds the loop for long.
//!
//! # Deadline and its measurement
//! Deadline: one loop period, T = 1/`loop_rate_hz` (100 µs, 16 800 core cycles at 10 kHz), from
//! the TIM2 update to the end of the tick (both DAC codes written). The tick stamps its entry and
//! end with the DWT cycle counter (CYCCNT, 168 MHz) and reads TIM2's counter to date the update
//! it serves (`piezo_firmware::board::deadline`). If the update flag is set again when the tick
//! ends (or update-to-end exceeds T), the next tick is told `deadline_missed`; if a whole period
//! passed without a tick (a lock held longer than T), the tick
//! that comes is told so. The loop counts each as an overrun (`counters.overruns` in `status`)
//! and latches its safe state (outputs held) until `rearm`.
//!
//! Each tick's cost (entry to end, DWT cycles) goes to `Session::note_tick_cycles`, so `status`
//! over the link reports the worst (`tick_cycles_max`). With the update-to-entry latency and the
//! update-to-end completion it is also logged once a second with defmt (`tick: last … cycles,
//! worst … cycles (… µs), latency worst …, completion worst … of … per period; late …,
//! skipped …`).
//!
//! Build: `cd firmware && cargo build --release --features board --bin board`.
//! Flash and run (probe-rs, the runner in `firmware/.cargo/config.toml`):
//! `cd firmware && cargo run --release --features board --bin board`; the USB serial device
//! then appears on the host (`/dev/ttyACM0` on Linux), driven by
//! `host-sim link --connect serial:/dev/ttyACM0 …` (firmware/README.md).
//!
//! At boot the loop holds each axis at rest at the lower end of its output window, compensated,
//! until a request says otherwise (as the QEMU image's link mode).
//!
//! On the host this file builds to a stub `main` (only with `--features board`).
#![cfg_attr(target_os = "none", no_std)]
#![cfg_attr(target_os = "none", no_main)]

#[cfg(target_os = "none")]
use defmt_rtt as _;
#[cfg(target_os = "none")]
use panic_probe as _;

#[cfg(target_os = "none")]
#[rtic::app(device = stm32f4xx_hal::pac, peripherals = true, dispatchers = [USART6])]
mod app {
    use core::fmt::Write as _;
    use core::mem::MaybeUninit;

    use cortex_m::peripheral::DWT;
    use stm32f4xx_hal::otg_fs::UsbBus;
    use stm32f4xx_hal::pac;
    use stm32f4xx_hal::prelude::*;
    use stm32f4xx_hal::timer::Flag;
    use usb_device::bus::UsbBusAllocator;

    use piezo_firmware::ads8681::Ads8681;
    use piezo_firmware::board::deadline::{DeadlineMonitor, TickStats};
    use piezo_firmware::board::usb_link::{Bus as UsbBusType, UsbCounters, UsbLink};
    use piezo_firmware::board::{
        self, AdcSpi, AdcYSpi, Board, DacSpi, LoopTimer, CYCLES_PER_TIMER_TICK, PERIOD_CYCLES,
        SYSCLK_HZ,
    };
    use piezo_firmware::dac8563::{Dac8563, Dac8563Channel};
    use piezo_firmware::demo;
    use piezo_firmware::params;
    use piezo_firmware::reference::{Program, ReferenceGenerator, Waveform};
    use piezo_firmware::session::Session;
    use piezo_firmware::xy_loop::{AdcPair, Feedforward, TwoAxisLoop, XyIo};

    /// The board's converters as the loop sees them.
    type Io = XyIo<Dac8563<DacSpi>, AdcPair<Ads8681<AdcSpi>, Ads8681<AdcYSpi>>>;

    /// Words of OTG_FS endpoint memory (the HAL's examples' size).
    const EP_MEMORY_WORDS: usize = 1024;

    /// The USB link's state as telemetry reports it.
    #[derive(Clone, Copy, Default)]
    pub struct UsbReport {
        counters: UsbCounters,
        configured: bool,
    }

    #[shared]
    struct Shared {
        session: &'static mut Session,
        tick_stats: TickStats,
        usb_report: UsbReport,
    }

    #[local]
    struct Local {
        io: Io,
        loop_timer: LoopTimer,
        monitor: DeadlineMonitor,
        link: UsbLink,
    }

    #[init(local = [
        ep_memory: [u32; EP_MEMORY_WORDS] = [0; EP_MEMORY_WORDS],
        usb_bus: MaybeUninit<UsbBusAllocator<UsbBusType>> = MaybeUninit::uninit(),
        session: MaybeUninit<Session> = MaybeUninit::uninit(),
    ])]
    fn init(cx: init::Context) -> (Shared, Local) {
        let mut core = cx.core;
        core.DCB.enable_trace();
        core.DWT.enable_cycle_counter();
        defmt::info!(
            "parameters {=str} ({=str}), fnv1a32 {=u32:#010x}, loop {} Hz; command link on USB CDC-ACM",
            params::VERSION,
            params::SOURCE,
            params::FNV1A32,
            params::LOOP_RATE_HZ
        );
        let settings = match demo::settings() {
            Ok(s) => s,
            Err(e) => defmt::panic!("parameter set refused: {}", defmt::Debug2Format(&e)),
        };
        let Some(scale) = demo::sensor_scale() else {
            defmt::panic!("sensor scale refused");
        };
        let Board {
            dac,
            adc,
            adc_y,
            mut loop_timer,
            usb,
        } = match Board::init(cx.device) {
            Ok(board) => board,
            Err(e) => defmt::panic!("bring-up failed: {}", defmt::Debug2Format(&e)),
        };
        let io = XyIo {
            dac,
            dac_channels: [Dac8563Channel::A, Dac8563Channel::B],
            sensor: AdcPair {
                x: adc,
                y: adc_y,
                scale,
            },
        };
        // At rest at the lower end of each window until told otherwise. The DAC init left both
        // outputs at 0 V; the first tick writes the window's lower end (0 V in the default file).
        let rest = [0, 1].map(|i| Waveform::Constant {
            offset_m: params::AXES[i].rest_output_m,
        });
        let reference =
            ReferenceGenerator::new(Program::PerAxis(rest), params::SAMPLE_PERIOD_S, [0.0; 2]);
        let initial = [params::AXES[0].output_min_v, params::AXES[1].output_min_v];
        let lp = TwoAxisLoop::new(settings, Feedforward::Compensator, reference, initial);
        // Moved into its static slot (in .bss: the wave table makes it large); init runs once.
        let session: &'static mut Session =
            cx.local
                .session
                .write(Session::new(lp, params::VERSION, params::FNV1A32));

        let bus: &'static UsbBusAllocator<UsbBusType> =
            cx.local.usb_bus.write(UsbBus::new(usb, cx.local.ep_memory));
        let link = match UsbLink::new(bus) {
            Ok(link) => link,
            Err(e) => defmt::panic!("USB device refused: {}", defmt::Debug2Format(&e)),
        };

        if let Err(e) = board::start_loop_timer(&mut loop_timer) {
            defmt::panic!("loop timer: {}", defmt::Debug2Format(&e));
        }
        defmt::info!(
            "loop running at {} Hz, deadline {} cycles ({} us)",
            board::LOOP_RATE_HZ,
            PERIOD_CYCLES,
            PERIOD_CYCLES / (SYSCLK_HZ / 1_000_000)
        );
        (
            Shared {
                session,
                tick_stats: TickStats::default(),
                usb_report: UsbReport::default(),
            },
            Local {
                io,
                loop_timer,
                monitor: DeadlineMonitor::new(PERIOD_CYCLES, CYCLES_PER_TIMER_TICK),
                link,
            },
        )
    }

    /// The control tick, at each TIM2 update. Deadline: one loop period from the update (see
    /// the crate docs); measured here with the DWT cycle counter.
    #[task(
        binds = TIM2,
        priority = 3,
        shared = [session, tick_stats],
        local = [io, loop_timer, monitor, missed: bool = false, ticks_to_telemetry: u32 = 0]
    )]
    fn control_tick(mut cx: control_tick::Context) {
        let entry_cycles = DWT::cycle_count();
        let timer = cx.local.loop_timer;
        if !timer.flags().contains(Flag::Update) {
            // A re-entry with no update behind it (the flag was cleared after the NVIC latched it).
            return;
        }
        timer.clear_flags(Flag::Update);
        let monitor = cx.local.monitor;
        let (start, skipped) = monitor.start(entry_cycles, timer.now().ticks());
        let missed = core::mem::take(cx.local.missed) || skipped;
        let io = cx.local.io;
        let pending_tx = cx.shared.session.lock(|session| {
            session.tick(io, missed);
            session.pending_tx()
        });
        if pending_tx > 0 {
            rtic::pend(pac::Interrupt::OTG_FS);
        }
        let end_cycles = DWT::cycle_count();
        *cx.local.missed = monitor.finish(start, end_cycles, timer.flags().contains(Flag::Update));
        let stats = monitor.stats();
        cx.shared
            .session
            .lock(|session| session.note_tick_cycles(stats.last_cycles));
        cx.shared.tick_stats.lock(|t| *t = stats);

        let countdown = cx.local.ticks_to_telemetry;
        if *countdown == 0 {
            *countdown = board::LOOP_RATE_HZ;
            // Err: the last report is still running; this one is skipped.
            let _ = telemetry::spawn();
        }
        *countdown -= 1;
    }

    /// The command link: USB events, and bytes the tick queued.
    #[task(binds = OTG_FS, priority = 2, shared = [session, usb_report], local = [link])]
    fn usb_link(mut cx: usb_link::Context) {
        let link = cx.local.link;
        link.service(&mut cx.shared.session);
        let report = UsbReport {
            counters: link.counters(),
            configured: link.configured(),
        };
        cx.shared.usb_report.lock(|r| *r = report);
    }

    /// Once a second: the tick's measured cost and the counters, over defmt. Each record is
    /// a few integers (defmt-rtt writes a record with interrupts off, so no text formatting
    /// happens inside one, except the rare safe-state line, formatted before).
    #[task(
        priority = 1,
        shared = [session, tick_stats, usb_report],
        local = [reported_safe: bool = false, reported_configured: bool = false]
    )]
    async fn telemetry(mut cx: telemetry::Context) {
        let t = cx.shared.tick_stats.lock(|t| *t);
        let status = cx.shared.session.lock(|s| s.status());
        let usb = cx.shared.usb_report.lock(|u| *u);
        let us = |cycles: u32| cycles / (SYSCLK_HZ / 1_000_000);
        defmt::info!(
            "tick: last {=u32} cycles, worst {=u32} cycles ({=u32} us), latency worst {=u32}, completion worst {=u32} of {=u32} per period; late {=u32}, skipped {=u32}",
            t.last_cycles,
            t.worst_cycles,
            us(t.worst_cycles),
            t.worst_latency_cycles,
            t.worst_completion_cycles,
            PERIOD_CYCLES,
            t.late_ticks,
            t.skipped_updates
        );
        let c = &status.counters;
        defmt::info!(
            "loop: ticks {=u32} overruns {=u32} safe entries {=u32} sensor errors {=u32} dac errors {=u32}; link: requests {=u32} rejected {=u32} frames sent {=u32} dropped {=u32}; usb in {=u32} out {=u32} errors {=u32}",
            c.ticks,
            c.overruns,
            c.safe_entries,
            c.sensor_errors,
            c.dac_errors,
            c.requests,
            c.rejected_packets,
            c.frames_sent,
            c.frames_dropped,
            usb.counters.bytes_in,
            usb.counters.bytes_out,
            usb.counters.errors
        );
        if usb.configured != *cx.local.reported_configured {
            *cx.local.reported_configured = usb.configured;
            defmt::info!("usb: configured {=bool}", usb.configured);
        }
        match status.mode {
            piezo_link::Mode::Safe(fault) if !*cx.local.reported_safe => {
                *cx.local.reported_safe = true;
                let mut why = heapless::String::<48>::new();
                let _ = write!(why, "{fault:?}");
                defmt::error!(
                    "safe state ({=str}), outputs held at {} V (rearm over the link)",
                    why.as_str(),
                    status.applied_v
                );
            }
            piezo_link::Mode::Running => *cx.local.reported_safe = false,
            piezo_link::Mode::Safe(_) => {}
        }
    }
}

#[cfg(not(target_os = "none"))]
fn main() {
    eprintln!("the board image runs on thumbv7em-none-eabihf: see firmware/ci.sh");
}
