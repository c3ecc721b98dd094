//! The board's converter timing budget: the datasheet figures of the ADS8681 and DAC8563, the
//! STM32F407's SPI clocks, and what they cost the control tick. One owner of these numbers: the
//! timing budget in `board/discovery.rs` refers to them and `firmware/bench.sh` reads
//! [`CONVERTER_CYCLES_IN_TICK`] and [`CONVERTER_CYCLES_IN_TICK_BLOCKING`] from this file.
//!
//! A frame of `b` bits at the SPI clock f_SCLK lasts `t = b / f_SCLK`; in core cycles at
//! [`SYSCLK_HZ`], `n = b · SYSCLK_HZ / f_SCLK` ([`frame_cycles`]; 8 core cycles per bit at
//! 21 MHz). Sources: ADS8681 datasheet (TI SBAS633, "Timing Requirements"), DAC8563 datasheet
//! (TI SLAS719, "Timing Requirements" and "Electrical Characteristics"), STM32F407 reference
//! manual RM0090 (SPI baud-rate prescaler f_PCLK / 2^(BR+1)).
//!
//! Host code: no hardware here, only numbers and their relations, checked at compile time.

/// Core clock \[Hz\] (also the DWT cycle counter's rate).
pub const SYSCLK_HZ: u32 = 168_000_000;

/// APB2 clock \[Hz\] (SPI1's kernel clock).
pub const APB2_HZ: u32 = 84_000_000;

/// APB1 clock \[Hz\] (SPI2's and SPI3's kernel clock).
pub const APB1_HZ: u32 = 42_000_000;

/// SPI1's baud-rate divider (BR = 001: f_PCLK2 / 4).
pub const SPI1_DIVIDER: u32 = 4;

/// SPI2's and SPI3's baud-rate divider (BR = 000: f_PCLK1 / 2).
pub const SPI23_DIVIDER: u32 = 2;

/// SCLK of all three buses \[Hz\]: 84 MHz / 4 = 42 MHz / 2 = 21 MHz.
pub const SPI_SCLK_HZ: u32 = APB2_HZ / SPI1_DIVIDER;

const _: () = assert!(
    APB1_HZ / SPI23_DIVIDER == SPI_SCLK_HZ,
    "the three SPI buses run at one SCLK"
);

/// ADS8681 frame: one 32-bit input command, the conversion result in its first 16 bits out.
pub const ADC_FRAME_BITS: u32 = 32;

/// DAC8563 frame: 24 bits per SYNC low period.
pub const DAC_FRAME_BITS: u32 = 24;

/// ADS8681 conversion time, maximum \[ns\]: CONVST/CS rising edge to the result being ready.
pub const ADS8681_T_CONV_MAX_NS: u32 = 665;

/// ADS8681 cycle time, minimum \[ns\] (1 MSPS): from one CONVST/CS rising edge to the next.
pub const ADS8681_T_CYC_MIN_NS: u32 = 1_000;

/// ADS8681 acquisition time, minimum \[ns\]: `t_acq = t_cyc − t_conv` (the sample-and-hold
/// tracks the input while CS is low for the next frame).
pub const ADS8681_T_ACQ_MIN_NS: u32 = ADS8681_T_CYC_MIN_NS - ADS8681_T_CONV_MAX_NS;

/// Time SYNC is held high between the two DAC8563 frames \[ns\]: above the datasheet's minimum
/// SYNC high time (tens of nanoseconds), with margin.
pub const DAC8563_SYNC_HIGH_NS: u32 = 100;

/// DAC8563 output settling to ±½ LSB after a full-scale step, typical \[ns\].
pub const DAC8563_SETTLING_NS: u32 = 7_000;

/// Core cycles of an SPI frame of `bits` bits at [`SPI_SCLK_HZ`]: `bits · SYSCLK_HZ / f_SCLK`,
/// rounded up.
pub const fn frame_cycles(bits: u32) -> u32 {
    (bits as u64 * SYSCLK_HZ as u64).div_ceil(SPI_SCLK_HZ as u64) as u32
}

/// Core cycles of `ns` nanoseconds at [`SYSCLK_HZ`], rounded up.
pub const fn ns_to_cycles(ns: u32) -> u32 {
    // 168 cycles per µs: ns · 168 / 1000 (no overflow below 25 ms).
    (ns * (SYSCLK_HZ / 1_000_000)).div_ceil(1_000)
}

/// Nanoseconds of `cycles` core cycles at [`SYSCLK_HZ`], rounded up.
pub const fn cycles_to_ns(cycles: u32) -> u32 {
    (cycles * 1_000).div_ceil(SYSCLK_HZ / 1_000_000)
}

/// One ADS8681 frame \[core cycles\]: 32 bits at 21 MHz = 1.52 µs.
pub const ADC_FRAME_CYCLES: u32 = frame_cycles(ADC_FRAME_BITS);

/// One DAC8563 frame \[core cycles\]: 24 bits at 21 MHz = 1.14 µs.
pub const DAC_FRAME_CYCLES: u32 = frame_cycles(DAC_FRAME_BITS);

/// Cycles the SYNC high time between the two DAC frames takes ([`DAC8563_SYNC_HIGH_NS`]).
pub const DAC8563_SYNC_HIGH_CYCLES: u32 = ns_to_cycles(DAC8563_SYNC_HIGH_NS);

/// The converter time that still lies inside the tick \[core cycles\], at least: the two ADC
/// frames run at once on SPI1 and SPI3 (one frame's time, [`ADC_FRAME_CYCLES`]); the two DAC
/// frames go out by DMA after the tick has started them (none). The instructions the tick runs
/// meanwhile (polling the two buses, starting the DMA) are not in it: they run inside this time
/// or are the tick's own instructions on the board, which QEMU's count does not include.
pub const CONVERTER_CYCLES_IN_TICK: u32 = 256;

/// The same with blocking transfers, one after the other: `2 · ADC frame + 2 · DAC frame`
/// (before the DMA and concurrent reads; a lower bound, the HAL's byte-by-byte transfers add
/// a gap after each byte).
pub const CONVERTER_CYCLES_IN_TICK_BLOCKING: u32 = 896;

const _: () = assert!(CONVERTER_CYCLES_IN_TICK == ADC_FRAME_CYCLES);
const _: () =
    assert!(CONVERTER_CYCLES_IN_TICK_BLOCKING == 2 * ADC_FRAME_CYCLES + 2 * DAC_FRAME_CYCLES);

/// Core cycles from the first DAC frame's start to the second's end, without interrupt latency:
/// `2 · DAC frame + SYNC high time`.
pub const DAC_PAIR_CYCLES: u32 = 2 * DAC_FRAME_CYCLES + DAC8563_SYNC_HIGH_CYCLES;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_times_match_the_datasheet_arithmetic() {
        // 32 bits / 21 MHz = 1.5238 µs; 24 bits / 21 MHz = 1.1429 µs.
        assert_eq!(ADC_FRAME_CYCLES, 256);
        assert_eq!(cycles_to_ns(ADC_FRAME_CYCLES), 1_524);
        assert_eq!(DAC_FRAME_CYCLES, 192);
        assert_eq!(cycles_to_ns(DAC_FRAME_CYCLES), 1_143);
        assert_eq!(SPI_SCLK_HZ, 21_000_000);
        assert_eq!(ADS8681_T_ACQ_MIN_NS, 335);
        assert_eq!(DAC8563_SYNC_HIGH_CYCLES, 17);
        assert_eq!(DAC_PAIR_CYCLES, 401);
    }

    #[test]
    fn the_tick_holds_a_third_of_the_blocking_converter_time() {
        assert_eq!(cycles_to_ns(CONVERTER_CYCLES_IN_TICK_BLOCKING), 5_334);
        assert_eq!(cycles_to_ns(CONVERTER_CYCLES_IN_TICK), 1_524);
        // At 50 kHz (3 360 cycles a period) the converters held 26.7 % of it, now 7.6 %.
        assert_eq!(CONVERTER_CYCLES_IN_TICK_BLOCKING * 1000 / 3_360, 266);
        assert_eq!(CONVERTER_CYCLES_IN_TICK * 1000 / 3_360, 76);
    }

    #[test]
    fn conversion_and_acquisition_fit_between_two_ticks_at_50_khz() {
        // CONVST/CS rises at the end of one tick's frame and the next frame starts one period
        // later (20 µs at 50 kHz): the conversion (665 ns) and the ADC's minimum cycle are far
        // inside it.
        let period_ns = 1_000_000_000 / 50_000;
        assert!(ADS8681_T_CYC_MIN_NS + cycles_to_ns(ADC_FRAME_CYCLES) < period_ns);
        // The DAC pair ends and settles inside one period too.
        assert!(cycles_to_ns(DAC_PAIR_CYCLES) + DAC8563_SETTLING_NS < period_ns);
    }
}
