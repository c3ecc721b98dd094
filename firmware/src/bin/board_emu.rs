//! The board image under emulation: QEMU 7.2's `netduinoplus2` machine (STM32F405, Cortex-M4F;
//! `firmware/run-board-emu.sh`). It runs the board image's RTIC 2 application
//! (`src/bin/board/app.rs`, the same file `src/bin/board.rs` builds: the tasks `control_tick`
//! on TIM2 at priority 3, the link at 2, `telemetry` at 1, the deadline monitor, the session and
//! the loop) on the hardware edge `piezo_firmware::board` gives it with the feature `board-emu`.
//!
//! What it changes from the real image, and nothing else:
//!
//! 1. **Clocks**: no RCC set-up (QEMU does not model the RCC; the HAL's `freeze` would wait for
//!    ready bits that never come). SYSCLK is taken as QEMU's 168 MHz `sysclk`, and TIM2's
//!    counting rate as the 1 GHz of QEMU's timer model.
//! 2. **TIM2** is started through its registers (DIER.UIE, CR1.CEN, then ARR = 10⁹/loop rate),
//!    not through stm32f4xx-hal, whose PSC and EGR writes move QEMU's count origin and with it
//!    the period (`piezo_firmware::board` module `emu`). It updates at the stage file's
//!    `loop_rate_hz` under QEMU's model; the rate the tick served, measured with SysTick, is
//!    printed at shutdown.
//! 3. **Cycle counter**: SysTick at 168 MHz extended to 32 bits instead of the DWT's CYCCNT
//!    (QEMU does not model the DWT).
//! 4. **Converters**: the firmware's simulated stage (`piezo_firmware::plant`, `plant_io`, as in
//!    the mps2-an386 QEMU image) behind the same converter traits instead of the DAC8563 and the
//!    two ADS8681 on SPI; it moves one loop period on after each tick.
//! 5. **Link**: USART1 (QEMU's first `-serial`), task `usart_link` bound to USART1, instead of
//!    USB CDC-ACM on OTG_FS (QEMU does not model OTG_FS). Same decoding, preparation and reply
//!    encoding outside the lock and batches of 64 bytes out.
//! 6. **Shutdown**: after answering `shutdown` the link task prints the deadline figures,
//!    TIM2's measured rate and the link's longest lock hold per kind of request over semihosting and exits QEMU with success (the board keeps
//!    running).
//! 7. **Logging**: the defmt calls are compiled and run as on the board, into defmt-rtt's RAM
//!    buffer, which nothing reads under QEMU (non-blocking: records are dropped once it is
//!    full), so they are silent. A panic or a HardFault prints its message over semihosting and
//!    exits QEMU with failure instead of panic-probe's probe-rs report.
//!
//! Memory: QEMU's STM32F405 has the F407's 1 MiB flash at 0x0800_0000 (aliased at 0) and 128 KiB
//! SRAM at 0x2000_0000 (plus 64 KiB CCM, unused), so the image links with the root `memory.x`.
//!
//! Build and run (from `firmware/`): `cargo build --release --features board-emu --bin
//! board-emu`, then `./run-board-emu.sh --link PORT ELF` and `host-sim link --connect
//! tcp:127.0.0.1:PORT …`.
//!
//! On the host this file builds to a stub `main` (only with `--features board-emu`).
#![cfg_attr(target_os = "none", no_std)]
#![cfg_attr(target_os = "none", no_main)]

#[cfg(target_os = "none")]
use defmt_rtt as _;

#[cfg(target_os = "none")]
#[path = "board/app.rs"]
mod app;

#[cfg(target_os = "none")]
mod exits {
    piezo_firmware::semihosting_fault_handlers!("board-emu: ");
}

#[cfg(not(target_os = "none"))]
fn main() {
    eprintln!("the emulated board image runs on thumbv7em-none-eabihf: see firmware/ci.sh");
}
