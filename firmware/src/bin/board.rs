//! STM32F4-Discovery image: the two-axis compensator loop on real converters (DAC8563 channel A/B
//! → x/y piezo amplifiers, displacement sensors → one ADS8681 per axis), paced by TIM2 at the
//! stage file's loop rate, and the command link ([`piezo_firmware::session`], the same endpoint
//! the QEMU image serves) over USB CDC-ACM. Wiring and clocks are in `piezo_firmware::board`,
//! the loop in `piezo_firmware::xy_loop`. The RTIC application is `src/bin/board/app.rs`, which
//! `src/bin/board_emu.rs` builds too, on QEMU's netduinoplus2 (feature `board-emu`).
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
//! request's application with a copy of its reply, one reply's bytes queued, one batch of ≤ 64
//! bytes out or one status, and those locks delay the tick. The link decodes and prepares each
//! request before it locks (`session::prepare`: an upload's validation runs there, preempted by
//! the tick) and encodes each reply after it unlocks (`board::serve`), so requests are applied
//! between two ticks, as `Session` requires, and none holds the loop for long: the longest hold
//! per kind of request is measured and logged (`link lock held worst …`).
//!
//! # Deadline and its measurement
//! Deadline: one loop period, T = 1/`loop_rate_hz` (50 µs, 8 400 core cycles at the default file's 20 kHz), from
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
#[path = "board/app.rs"]
mod app;

#[cfg(not(target_os = "none"))]
fn main() {
    eprintln!("the board image runs on thumbv7em-none-eabihf: see firmware/ci.sh");
}
