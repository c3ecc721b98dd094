//! STM32F4-Discovery image: the compensator loop on real converters (DAC8563 → piezo amplifier,
//! displacement sensor → ADS8681), paced by TIM2 at 10 kHz. Wiring, clocks and deadline are in
//! `piezo_firmware::board`.
//!
//! Build: `cd firmware && cargo build --release --features board --bin board`.
//! Flash and run (probe-rs, the runner in `firmware/.cargo/config.toml`):
//! `cd firmware && cargo run --release --features board --bin board`. Logs are defmt over RTT.
//!
//! The loop tracks the same reference as the QEMU self-check ([`piezo_firmware::demo`]) with the
//! linear feed-forward; replace the closure with the `piezo-core` compensator. On any converter
//! error the loop tries once to put the DAC at 0 V, logs, and parks (no retry at 10 kHz into a
//! broken bus).
//!
//! On the host this file builds to a stub `main` (only with `--features board`).
#![cfg_attr(target_os = "none", no_std)]
#![cfg_attr(target_os = "none", no_main)]

#[cfg(target_os = "none")]
mod image {
    use defmt_rtt as _;
    use panic_probe as _;

    use cortex_m_rt::entry;
    use stm32f4xx_hal::pac;

    use piezo_firmware::board::Board;
    use piezo_firmware::codes::DacCode;
    use piezo_firmware::control::{tick, LoopIo};
    use piezo_firmware::converter::DacWrite;
    use piezo_firmware::dac8563::Dac8563Channel;
    use piezo_firmware::demo::{self, linear_feedforward};

    #[entry]
    fn main() -> ! {
        let Some(dp) = pac::Peripherals::take() else {
            defmt::panic!("peripherals already taken");
        };
        let board = match Board::init(dp) {
            Ok(board) => board,
            Err(e) => defmt::panic!("bring-up failed: {}", defmt::Debug2Format(&e)),
        };
        let Board {
            dac,
            adc,
            mut loop_timer,
        } = board;
        let mut io = LoopIo {
            dac,
            dac_channel: Dac8563Channel::A,
            adc,
            adc_channel: (),
        };
        let config = demo::loop_config();
        let mut guard = config.limits().state(0.0);
        defmt::info!("loop running at {} Hz", piezo_firmware::board::LOOP_RATE_HZ);

        let mut k: u32 = 0;
        loop {
            while loop_timer.wait().is_err() {}
            let reference_m = demo::reference_m(k % demo::DEMO_TICKS);
            match tick(
                &mut io,
                &config,
                &mut guard,
                reference_m,
                linear_feedforward,
            ) {
                Ok(out) => {
                    if k.is_multiple_of(piezo_firmware::board::LOOP_RATE_HZ) {
                        defmt::info!(
                            "tick {}: error {} nm, out {} V, faults {}",
                            k,
                            out.tracking_error_m * 1e9,
                            out.applied_volts,
                            guard.counters().total()
                        );
                    }
                }
                Err(e) => {
                    let safe = io.dac.write_code(Dac8563Channel::A, DacCode::SAFE);
                    defmt::error!(
                        "tick {} failed: {}; DAC to 0 V: {}; parked",
                        k,
                        defmt::Debug2Format(&e),
                        safe.is_ok()
                    );
                    loop {
                        cortex_m::asm::wfi();
                    }
                }
            }
            k = k.wrapping_add(1);
        }
    }
}

#[cfg(not(target_os = "none"))]
fn main() {
    eprintln!("the board image runs on thumbv7em-none-eabihf: see firmware/ci.sh");
}
