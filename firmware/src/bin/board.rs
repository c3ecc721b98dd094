//! STM32F4-Discovery image: the two-axis compensator loop on real converters (DAC8563 channel A/B
//! → x/y piezo amplifiers, displacement sensors → one ADS8681 per axis), paced by TIM2 at 10 kHz.
//! Wiring, clocks and deadline are in `piezo_firmware::board`; the loop in
//! `piezo_firmware::xy_loop`.
//!
//! Build: `cd firmware && cargo build --release --features board --bin board`.
//! Flash and run (probe-rs, the runner in `firmware/.cargo/config.toml`):
//! `cd firmware && cargo run --release --features board --bin board`. Logs are defmt over RTT:
//! at boot the parameter set (version, FNV-1a of the file, loop rate, frame decimation), then
//! sample frames (one every 10th tick) in batches of 8, one record per frame
//! (`frame <n>: x ref … m cmd … V sensor … m | y ref …`, see `piezo_firmware::frames`), and the
//! loop's counters once a second. `host-sim capture` turns that log into CSV (firmware/README.md). A fault puts the loop in its safe state
//! (outputs held, logged once); it stays there (rearm needs a command link, not built yet).
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

    use piezo_firmware::board::{self, Board};
    use piezo_firmware::dac8563::Dac8563Channel;
    use piezo_firmware::demo;
    use piezo_firmware::frames::SampleFrame;
    use piezo_firmware::params;
    use piezo_firmware::reference::ReferenceGenerator;
    use piezo_firmware::xy_loop::{AdcPair, Feedforward, Mode, TwoAxisLoop, XyIo};

    /// Frames are produced every this many ticks (1 kHz of frames at a 10 kHz loop).
    const FRAME_DECIMATION: u32 = 10;

    #[entry]
    fn main() -> ! {
        // `host-sim capture` reads the loop rate and the decimation from this line.
        defmt::info!(
            "parameters {=str} ({=str}), fnv1a32 {=u32:#010x}, loop {} Hz, one frame every {} ticks",
            params::VERSION,
            params::SOURCE,
            params::FNV1A32,
            params::LOOP_RATE_HZ,
            FRAME_DECIMATION
        );
        let Some(dp) = pac::Peripherals::take() else {
            defmt::panic!("peripherals already taken");
        };
        let mut settings = match demo::settings() {
            Ok(s) => s,
            Err(e) => defmt::panic!("parameter set refused: {}", defmt::Debug2Format(&e)),
        };
        settings.frame_decimation = FRAME_DECIMATION;
        let Some(scale) = demo::sensor_scale() else {
            defmt::panic!("sensor scale refused");
        };
        let board = match Board::init(dp) {
            Ok(board) => board,
            Err(e) => defmt::panic!("bring-up failed: {}", defmt::Debug2Format(&e)),
        };
        let Board {
            dac,
            adc,
            adc_y,
            mut loop_timer,
        } = board;
        let mut io = XyIo {
            dac,
            dac_channels: [Dac8563Channel::A, Dac8563Channel::B],
            sensor: AdcPair {
                x: adc,
                y: adc_y,
                scale,
            },
        };
        let reference = ReferenceGenerator::new(demo::program(), params::SAMPLE_PERIOD_S, [0.0; 2]);
        // The DAC init left both outputs at 0 V.
        let mut lp = TwoAxisLoop::new(settings, Feedforward::Compensator, reference, [0.0; 2]);
        defmt::info!("loop running at {} Hz", board::LOOP_RATE_HZ);

        let mut batch = heapless::Vec::<SampleFrame, 8>::new();
        let mut k: u32 = 0;
        let mut reported_safe = false;
        loop {
            let late = board::wait_for_tick(&mut loop_timer);
            let report = lp.tick(&mut io, late);
            if let (Mode::Safe(fault), false) = (report.mode, reported_safe) {
                reported_safe = true;
                defmt::error!(
                    "tick {}: safe state ({}), outputs held at {} V",
                    k,
                    defmt::Debug2Format(&fault),
                    report.applied_v
                );
            }
            // Send frames in batches of 8 (every 80 ticks), one defmt record per frame in the
            // text form `host-sim capture` reads; a full queue drops frames, which the receiver
            // sees as a sequence gap.
            if lp.frames.len() >= batch.capacity() {
                lp.frames.drain_into(&mut batch);
                for f in &batch {
                    defmt::info!("{}", f);
                }
            }
            if k.is_multiple_of(board::LOOP_RATE_HZ) {
                defmt::info!("counters {}", defmt::Debug2Format(&lp.counters()));
            }
            k = k.wrapping_add(1);
        }
    }
}

#[cfg(not(target_os = "none"))]
fn main() {
    eprintln!("the board image runs on thumbv7em-none-eabihf: see firmware/ci.sh");
}
