//! The RTIC 2 application of the board image and of its emulated variant: the tasks, their
//! priorities and bodies (see the crate docs of `src/bin/board.rs`). The hardware behind them is
//! `piezo_firmware::board`: the STM32F407 with its converters and USB (feature `board`), or
//! QEMU's netduinoplus2 with the simulated stage and USART1 (feature `board-emu`). The two
//! differ here only in the link task's interrupt (`usb_link` on OTG_FS, `usart_link` on USART1),
//! in what `usart_link` does on a `shutdown` request (exits QEMU), and in the board's DMA task
//! for the DAC's frames (`dac_frame_done` on DMA1_STREAM3, with its counters in the telemetry;
//! the emulated board's DAC is the simulated stage's).

#[rtic::app(device = stm32f4xx_hal::pac, peripherals = true, dispatchers = [USART6])]
mod app {
    use core::fmt::Write as _;
    use core::mem::MaybeUninit;

    use piezo_firmware::board::deadline::{DeadlineMonitor, TickStats};
    use piezo_firmware::board::{
        self, CycleCounter, Io, Link, LinkCounters, LoopTimer, Statics, CYCLES_PER_TIMER_TICK,
        LINK_INTERRUPT, PERIOD_CYCLES, SYSCLK_HZ,
    };
    use piezo_firmware::demo;
    use piezo_firmware::params;
    use piezo_firmware::session::{RequestKind, Session};

    /// The link's state as telemetry reports it.
    #[derive(Clone, Copy, Default)]
    pub struct LinkReport {
        counters: LinkCounters,
        configured: bool,
    }

    #[shared]
    struct Shared {
        session: &'static mut Session,
        tick_stats: TickStats,
        link_report: LinkReport,
    }

    #[local]
    struct Local {
        io: Io,
        loop_timer: LoopTimer,
        cycles: CycleCounter,
        monitor: DeadlineMonitor,
        #[cfg(feature = "board")]
        usb: Link,
        #[cfg(feature = "board-emu")]
        usart: Link,
    }

    #[init(local = [
        statics: Statics = Statics::new(),
        session: MaybeUninit<Session> = MaybeUninit::uninit(),
    ])]
    fn init(cx: init::Context) -> (Shared, Local) {
        defmt::info!(
            "parameters {=str} ({=str}), fnv1a32 {=u32:#010x}, fingerprint {=u32:#010x}, loop {} Hz; command link on {=str}",
            params::VERSION,
            params::SOURCE,
            params::FNV1A32,
            piezo_firmware::session::built_in_fingerprint(),
            params::LOOP_RATE_HZ,
            board::LINK_DESCRIPTION
        );
        let settings = match demo::settings() {
            Ok(s) => s,
            Err(e) => defmt::panic!("parameter set refused: {}", defmt::Debug2Format(&e)),
        };
        let Some(scale) = demo::sensor_scale() else {
            defmt::panic!("sensor scale refused");
        };
        let board::Parts {
            io,
            mut loop_timer,
            link,
            cycles,
        } = match board::bring_up(cx.core, cx.device, cx.local.statics, scale) {
            Ok(parts) => parts,
            Err(e) => defmt::panic!("bring-up failed: {}", defmt::Debug2Format(&e)),
        };
        // At rest at the lower end of each window until told otherwise. The DAC init left both
        // outputs at 0 V; the first tick writes the window's lower end (0 V in the default file).
        let lp = demo::at_rest(settings);
        // Moved into its static slot (in .bss: the wave table makes it large); init runs once.
        let session: &'static mut Session = cx.local.session.write(Session::new(
            lp,
            params::VERSION,
            params::FNV1A32,
            piezo_firmware::session::built_in_fingerprint(),
        ));

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
                link_report: LinkReport::default(),
            },
            Local {
                io,
                loop_timer,
                cycles,
                monitor: DeadlineMonitor::new(PERIOD_CYCLES, CYCLES_PER_TIMER_TICK),
                #[cfg(feature = "board")]
                usb: link,
                #[cfg(feature = "board-emu")]
                usart: link,
            },
        )
    }

    /// The control tick, at each TIM2 update. Deadline: one loop period from the update (see
    /// the crate docs); measured here with the core cycle counter.
    #[task(
        binds = TIM2,
        priority = 3,
        shared = [session, tick_stats],
        local = [io, loop_timer, cycles, monitor, missed: bool = false, ticks_to_telemetry: u32 = 0]
    )]
    fn control_tick(mut cx: control_tick::Context) {
        let entry_cycles = cx.local.cycles.now();
        let timer = cx.local.loop_timer;
        if !timer.update_pending() {
            // A re-entry with no update behind it (the flag was cleared after the NVIC latched it).
            return;
        }
        timer.clear_update();
        let monitor = cx.local.monitor;
        let (start, skipped) = monitor.start(entry_cycles, timer.count());
        let missed = core::mem::take(cx.local.missed) || skipped;
        let io = cx.local.io;
        let pending_tx = cx.shared.session.lock(|session| {
            session.tick(io, missed);
            session.pending_tx()
        });
        if pending_tx > 0 {
            rtic::pend(LINK_INTERRUPT);
        }
        let end_cycles = cx.local.cycles.now();
        *cx.local.missed = monitor.finish(start, end_cycles, timer.update_pending());
        board::end_of_tick(io);
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

    /// The end of a DAC frame sent by DMA (SPI2's receive stream has clocked its last bit):
    /// SYNC high, and the second frame of the tick's pair starts. At the tick's priority, so it
    /// never lengthens a tick: the end of the pair's first frame is served when the tick
    /// returns.
    #[cfg(feature = "board")]
    #[task(binds = DMA1_STREAM3, priority = 3)]
    fn dac_frame_done(_cx: dac_frame_done::Context) {
        board::dac_frame_done();
    }

    /// The command link on USB: USB events, and bytes the tick queued.
    #[cfg(feature = "board")]
    #[task(binds = OTG_FS, priority = 2, shared = [session, link_report], local = [usb])]
    fn usb_link(mut cx: usb_link::Context) {
        let link = cx.local.usb;
        link.service(&mut cx.shared.session);
        let report = LinkReport {
            counters: link.counters(),
            configured: link.configured(),
        };
        cx.shared.link_report.lock(|r| *r = report);
    }

    /// The command link on USART1 (the emulated board): a received byte, and bytes the tick
    /// queued. After a `shutdown` request has been answered it prints the deadline figures and
    /// TIM2's measured rate and exits QEMU.
    #[cfg(feature = "board-emu")]
    #[task(binds = USART1, priority = 2, shared = [session, link_report, tick_stats], local = [usart])]
    fn usart_link(mut cx: usart_link::Context) {
        let link = cx.local.usart;
        link.service(&mut cx.shared.session);
        let report = LinkReport {
            counters: link.counters(),
            configured: link.configured(),
        };
        cx.shared.link_report.lock(|r| *r = report);
        let shutdown = cx.shared.session.lock(|s| {
            (s.shutdown_requested() && s.pending_tx() == 0).then(|| s.lp.counters().overruns)
        });
        if let (Some(overruns), 0) = (shutdown, link.staged()) {
            let stats = cx.shared.tick_stats.lock(|t| *t);
            board::exit(&stats, overruns, &report.counters.lock_holds);
        }
    }

    /// Once a second: the tick's measured cost and the counters, over defmt. Each record is
    /// a few integers (defmt-rtt writes a record with interrupts off, so no text formatting
    /// happens inside one, except the rare safe-state line, formatted before).
    #[task(
        priority = 1,
        shared = [session, tick_stats, link_report],
        local = [reported_safe: bool = false, reported_configured: bool = false]
    )]
    async fn telemetry(mut cx: telemetry::Context) {
        let t = cx.shared.tick_stats.lock(|t| *t);
        let status = cx.shared.session.lock(|s| s.status());
        let link = cx.shared.link_report.lock(|u| *u);
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
            "loop: ticks {=u32} overruns {=u32} safe entries {=u32} sensor errors {=u32} dac errors {=u32}; link: requests {=u32} rejected {=u32} frames sent {=u32} dropped {=u32}; link in {=u32} out {=u32} errors {=u32}",
            c.ticks,
            c.overruns,
            c.safe_entries,
            c.sensor_errors,
            c.dac_errors,
            c.requests,
            c.rejected_packets,
            c.frames_sent,
            c.frames_dropped,
            link.counters.bytes_in,
            link.counters.bytes_out,
            link.counters.errors
        );
        let holds = |kind: RequestKind| link.counters.lock_holds.worst(kind);
        defmt::info!(
            "link lock held worst (cycles): status {=u32} upload {=u32} table {=u32} control {=u32} track {=u32} other {=u32} transmit {=u32}",
            holds(RequestKind::Status),
            holds(RequestKind::Upload),
            holds(RequestKind::Table),
            holds(RequestKind::Control),
            holds(RequestKind::Track),
            holds(RequestKind::Other),
            holds(RequestKind::Transmit)
        );
        #[cfg(feature = "board")]
        {
            let d = board::dac_counters();
            defmt::info!(
                "dac dma: pairs {=u32} refused busy {=u32} aborted {=u32} spurious ends {=u32}",
                d.pairs_sent,
                d.busy_refusals,
                d.aborted,
                d.spurious_ends
            );
        }
        if link.configured != *cx.local.reported_configured {
            *cx.local.reported_configured = link.configured;
            defmt::info!("link: configured {=bool}", link.configured);
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
