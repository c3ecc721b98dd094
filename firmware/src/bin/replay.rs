//! QEMU image for `mps2-an386` (Cortex-M4F) that replays a reference record through the two-axis
//! loop [`piezo_firmware::xy_loop::TwoAxisLoop`] — the inverse effect chain, the compensators and
//! the guard, as on the board — and prints the voltage it commands at every tick: what
//! `host-sim compensate` computes on the host from the same stage file and record
//! (`tests/tests/qemu_compensate.rs` compares the two).
//!
//! The record is built in: `PIEZO_REFERENCE=ref.csv` (columns `t_s` and `r_m`, or `rx_m` and
//! `ry_m`, at the stage file's loop rate; read by `build.rs`) and the stage file by
//! `PIEZO_PARAMS`, e.g. from `firmware/`:
//! `PIEZO_PARAMS=params/xy-stage-effects.toml PIEZO_REFERENCE=/tmp/ref.csv cargo build --release
//! --features qemu --bin replay`, then
//! `./run-qemu.sh $CARGO_TARGET_DIR/thumbv7em-none-eabihf/release/replay`.
//!
//! The loop starts at rest at each axis's `output_min_v` and its sensor reads the simulated stage
//! of [`piezo_firmware::plant`] (the voltages do not depend on it: the loop is feed-forward). The
//! samples reach the loop as streamed setpoints, the queue kept full; after the last one the
//! stream holds it (the chain's lead reads past the end). Output: the boot line `host-sim capture`
//! takes its time base from (`parameters <version> (<file>), fnv1a32 0x…, loop <rate> Hz, one
//! frame every 1 ticks`), `replay: reference <file> (<n> ticks, <axes> axes)`, one line per tick in
//! the frame text of [`piezo_firmware::frames`] (`frame <tick>: x ref <m> m cmd <V> V sensor <m> m
//! | y …`; the sensor reads the stage at the start of the tick, before that tick's command),
//! then `replay: <n> ticks, lead <L> ticks, limited <n>, held <n>, guard <n>, faults <n>` and
//! `PASS` (exit 0) when the run had no fault and the guard never overrode the compensator, `FAIL`
//! (exit 1) otherwise or without a table.
#![cfg_attr(target_os = "none", no_std)]
#![cfg_attr(target_os = "none", no_main)]

#[cfg(target_os = "none")]
mod image {
    use core::cell::Cell;

    use cortex_m_rt::{entry, exception};
    use cortex_m_semihosting::{debug, hprintln};

    use piezo_firmware::demo;
    use piezo_firmware::frames::Frame;
    use piezo_firmware::params::{self, SAMPLE_PERIOD_S};
    use piezo_firmware::plant::{plant_io, XyPlant};
    use piezo_firmware::reference::{Program, ReferenceGenerator, STREAM_CAPACITY};
    use piezo_firmware::xy_loop::{Axis, Feedforward, Mode, TwoAxisLoop};

    include!(concat!(env!("OUT_DIR"), "/reference.rs"));

    #[entry]
    fn main() -> ! {
        // The boot line in the form `host-sim capture` reads for its time base; the record apart.
        hprintln!(
            "piezo-firmware replay: parameters {} ({}), fnv1a32 {:#010x}, loop {} Hz, one frame every 1 ticks",
            params::VERSION,
            params::SOURCE,
            params::FNV1A32,
            params::LOOP_RATE_HZ
        );
        hprintln!(
            "replay: reference {} ({} ticks, {} axes)",
            REFERENCE_SOURCE,
            REFERENCE_M.len(),
            REFERENCE_AXES
        );
        let Some(&first) = REFERENCE_M.first() else {
            fail(format_args!(
                "no reference table: build with PIEZO_REFERENCE=record.csv"
            ))
        };
        let Ok(settings) = demo::settings() else {
            fail(format_args!("parameter set refused at boot"))
        };
        let (Some(scale), Some(stage)) =
            (demo::sensor_scale(), XyPlant::from_params(SAMPLE_PERIOD_S))
        else {
            fail(format_args!("sensor gain refused at boot"))
        };
        let plant = Cell::new(stage);
        let mut io = plant_io(&plant, scale);
        let reference = ReferenceGenerator::new(Program::Streamed, SAMPLE_PERIOD_S, first);
        let initial = [
            params::AXES[0].limits.output_min_v,
            params::AXES[1].limits.output_min_v,
        ];
        let mut lp = TwoAxisLoop::new(settings, Feedforward::Compensator, reference, initial);
        // The first tick takes L + 1 setpoints from a queue that holds STREAM_CAPACITY − 1.
        if lp.lead_ticks() as usize + 1 >= STREAM_CAPACITY {
            fail(format_args!(
                "the chain's lead ({} ticks) exceeds the setpoint queue",
                lp.lead_ticks()
            ))
        }
        let mut queued = 0;
        let mut batch = heapless::Vec::<Frame, 8>::new();
        for _ in 0..REFERENCE_M.len() {
            while let Some(&sample) = REFERENCE_M.get(queued) {
                if lp.reference.push_setpoint(sample).is_err() {
                    break;
                }
                queued += 1;
            }
            lp.tick(&mut io, false);
            let mut p = plant.get();
            p.advance();
            plant.set(p);
            lp.frames.drain_into(&mut batch);
            for f in &batch {
                hprintln!("{}", f);
            }
        }
        let counters = lp.counters();
        let guard = Axis::ALL
            .iter()
            .map(|&a| lp.guard(a).counters().total())
            .fold(0, u32::saturating_add);
        hprintln!(
            "replay: {} ticks, lead {} ticks, limited {}, held {}, guard {}, faults {}, dropped frames {}",
            counters.ticks,
            lp.lead_ticks(),
            counters.compensator_limited,
            counters.held_references,
            guard,
            counters.faults(),
            lp.frames.dropped()
        );
        if counters.faults() == 0 && guard == 0 && lp.mode() == Mode::Running {
            hprintln!("PASS");
            debug::exit(debug::EXIT_SUCCESS);
        } else {
            hprintln!("FAIL");
            debug::exit(debug::EXIT_FAILURE);
        }
        #[allow(clippy::empty_loop)]
        loop {}
    }

    use piezo_firmware::semihosting_exit::fail;

    piezo_firmware::semihosting_fault_handlers!("");

    #[allow(unsafe_code)] // cortex-m-rt requires DefaultHandler to be an `unsafe fn`.
    #[exception]
    unsafe fn DefaultHandler(irqn: i16) {
        fail(format_args!("unhandled exception or interrupt {irqn}"))
    }
}

#[cfg(not(target_os = "none"))]
fn main() {
    eprintln!("the replay image runs on thumbv7em-none-eabihf: see its module doc");
}
