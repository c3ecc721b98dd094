//! STM32F4-Discovery (STM32F407VG) bring-up: clocks, the two SPI buses, chip selects, the loop
//! timer, the USB OTG_FS peripheral, and the DAC8563/ADS8681 drivers on them. Target only
//! (`board` feature). The tasks that use them are in `src/bin/board.rs` (RTIC 2).
//!
//! Wiring (RM0090 / STM32F407 datasheet alternate-function table, AF5 for SPI1/SPI2; the
//! Discovery user manual UM1472 for pins already used on the board):
//!
//! | signal                | MCU pin | notes                                                   |
//! |-----------------------|---------|---------------------------------------------------------|
//! | SPI1 SCK → ADS8681    | PA5     | SPI mode 0, 21 MHz (84 MHz APB2 / 4)                    |
//! | SPI1 MISO ← ADS8681   | PA6     | ADS8681 SDO-0                                           |
//! | SPI1 MOSI → ADS8681   | PA7     | ADS8681 SDI                                             |
//! | ADS8681 CONVST/CS     | PE7     | chip select; rising edge starts a conversion            |
//! | LIS3DSH CS (on board) | PE3     | held high so the on-board accelerometer stays off SPI1  |
//! | SPI3 SCK → ADS8681 y  | PC10    | second sensor (y axis), SPI mode 0, 21 MHz (42 MHz / 2)  |
//! | SPI3 MISO ← ADS8681 y | PC11    | AF6                                                     |
//! | SPI3 MOSI → ADS8681 y | PC12    | AF6                                                     |
//! | ADS8681 y CONVST/CS   | PD0     | chip select                                             |
//! | CS43L22 RESET (board) | PD4     | held low: the on-board audio DAC shares PC10/PC12 (I2S3) |
//! | SPI2 SCK → DAC8563    | PB13    | SPI mode 1, 21 MHz (42 MHz APB1 / 2)                    |
//! | SPI2 MOSI → DAC8563   | PB15    | DAC8563 DIN (the DAC has no data output; PB14 unused)   |
//! | DAC8563 SYNC          | PB12    | chip select                                             |
//! | DAC8563 LDAC, CLR     | —       | tie LDAC low, CLR high (LDAC register set to ignore pin) |
//! | OTG_FS D− / D+ (board)| PA11/PA12 | AF10, the micro-USB socket CN5: the command link (USB CDC-ACM) |
//! | OTG_FS VBUS (board)   | PA9     | not used: the USB core's VBUS sensing is off (synopsys-usb-otg) |
//! | VBUS switch EN (board)| PC0     | held high: the STMPS2141's active-low enable, so the board never drives VBUS |
//!
//! DAC8563 channel A drives the x amplifier, channel B the y amplifier.
//!
//! The two converters sit on separate buses because they need different SPI modes (ADS8681
//! mode 0 at power-on, DAC8563 mode 1).
//!
//! Clocks: 8 MHz HSE crystal → PLL (VCO 336 MHz) → SYSCLK 168 MHz (/2), 48 MHz for USB (/7);
//! AHB 168 MHz, APB2 84 MHz, APB1 42 MHz (TIM2 kernel clock 84 MHz). The DWT cycle counter runs
//! at SYSCLK ([`SYSCLK_HZ`]).
//!
//! Loop timer: TIM2 counts at [`TIMER_HZ`] and updates every [`TIMER_TICKS_PER_PERIOD`] counts,
//! at [`LOOP_RATE_HZ`], the stage file's loop rate (10 kHz for the default file; a rate that
//! does not divide 84 MHz stops the build). Each update raises the TIM2 interrupt, the control
//! tick. Deadline: a tick must have written both DAC codes within one period
//! ([`PERIOD_CYCLES`] core cycles, 100 µs at 10 kHz) of the update that started it; [`deadline`]
//! measures that with the DWT cycle counter. Expected cost: two 32-bit ADC frames (1.5 µs each at
//! 21 MHz), two 24-bit DAC frames (1.1 µs each) and the loop body (2 375 instructions for the
//! two-axis tick under QEMU, `firmware/bench.sh`), i.e. roughly 15–25 µs at 168 MHz; the measured
//! worst case is logged once a second (`src/bin/board.rs`).

pub mod deadline;
pub mod usb_link;

use embedded_hal_bus::spi::{ExclusiveDevice, NoDelay};
use stm32f4xx_hal::gpio::{Output, PB12, PD0, PE7};
use stm32f4xx_hal::otg_fs::USB;
use stm32f4xx_hal::pac;
use stm32f4xx_hal::prelude::*;
use stm32f4xx_hal::rcc::Config;
use stm32f4xx_hal::spi::{Mode, Phase, Polarity, Spi};
use stm32f4xx_hal::timer::{Counter, Event, Flag};

use crate::ads8681::{Ads8681, InputRange};
use crate::converter::DriverError;
use crate::dac8563::Dac8563;

/// Loop rate, hertz (TIM2 update rate): the stage file's `stage.loop_rate_hz`, a whole number of
/// hertz checked by `build.rs`.
pub const LOOP_RATE_HZ: u32 = crate::params::LOOP_RATE_HZ as u32;

/// Core clock, the DWT cycle counter's rate \[Hz\].
pub const SYSCLK_HZ: u32 = 168_000_000;

/// TIM2's counting rate: its kernel clock, prescaler 1 \[Hz\].
pub const TIMER_HZ: u32 = 84_000_000;

/// TIM2 counts per loop period.
pub const TIMER_TICKS_PER_PERIOD: u32 = TIMER_HZ / LOOP_RATE_HZ;

/// Core cycles per TIM2 count.
pub const CYCLES_PER_TIMER_TICK: u32 = SYSCLK_HZ / TIMER_HZ;

/// The loop period, the tick's deadline \[core cycles\] (16 800 at 10 kHz).
pub const PERIOD_CYCLES: u32 = TIMER_TICKS_PER_PERIOD * CYCLES_PER_TIMER_TICK;

const _: () = assert!(
    LOOP_RATE_HZ > 0 && TIMER_HZ.is_multiple_of(LOOP_RATE_HZ),
    "the stage file's loop rate must divide TIM2's 84 MHz (the board's tick would run at another rate than the model's sample period)"
);

/// TIM2 as the loop timer: counts at [`TIMER_HZ`].
pub type LoopTimer = Counter<pac::TIM2, TIMER_HZ>;

/// The ADS8681 as an SPI device on SPI1 with CS on PE7.
pub type AdcSpi = ExclusiveDevice<Spi<pac::SPI1>, PE7<Output>, NoDelay>;
/// The y-axis ADS8681 as an SPI device on SPI3 with CS on PD0.
pub type AdcYSpi = ExclusiveDevice<Spi<pac::SPI3>, PD0<Output>, NoDelay>;
/// The DAC8563 as an SPI device on SPI2 with SYNC on PB12.
pub type DacSpi = ExclusiveDevice<Spi<pac::SPI2>, PB12<Output>, NoDelay>;

/// SPI error of the board's devices (GPIO chip selects are infallible on this MCU).
pub type AdcError = DriverError<<AdcSpi as embedded_hal::spi::ErrorType>::Error>;
/// SPI error of the y-axis ADC (same kind as [`AdcError`]).
pub type AdcYError = DriverError<<AdcYSpi as embedded_hal::spi::ErrorType>::Error>;
/// SPI error of the board's DAC.
pub type DacError = DriverError<<DacSpi as embedded_hal::spi::ErrorType>::Error>;

/// Why bring-up failed.
#[derive(Debug)]
pub enum BoardError {
    /// The DAC init sequence failed.
    Dac(DacError),
    /// The x ADC init (range write and readback) failed.
    Adc(AdcError),
    /// The y ADC init failed.
    AdcY(AdcYError),
    /// TIM2's kernel clock is not [`TIMER_HZ`], or the timer could not be started.
    Timer,
    /// The PLL's 48 MHz output is off by more than USB's ±0.25 %.
    UsbClock,
}

/// Everything the loop needs.
pub struct Board {
    /// Piezo amplifier DAC (channel A).
    pub dac: Dac8563<DacSpi>,
    /// Displacement sensor ADC, x axis.
    pub adc: Ads8681<AdcSpi>,
    /// Displacement sensor ADC, y axis.
    pub adc_y: Ads8681<AdcYSpi>,
    /// TIM2, counting at [`TIMER_HZ`], not started ([`start_loop_timer`]).
    pub loop_timer: LoopTimer,
    /// The OTG_FS peripheral and its pins, for the USB bus.
    pub usb: USB,
}

impl Board {
    /// Clocks, pins, buses, timer, USB peripheral; then the DAC init (outputs to 0 V) and the
    /// ADC init (range ±10.24 V, read back).
    pub fn init(dp: pac::Peripherals) -> Result<Self, BoardError> {
        let mut rcc = dp.RCC.freeze(
            Config::hse(8.MHz())
                .sysclk(SYSCLK_HZ.Hz())
                .pclk1(42.MHz())
                .pclk2(84.MHz())
                .require_pll48clk(),
        );
        if !rcc.clocks.is_pll48clk_valid() {
            return Err(BoardError::UsbClock);
        }
        if rcc.clocks.timclk1().raw() != TIMER_HZ || rcc.clocks.sysclk().raw() != SYSCLK_HZ {
            return Err(BoardError::Timer);
        }
        let gpioa = dp.GPIOA.split(&mut rcc);
        let gpiob = dp.GPIOB.split(&mut rcc);
        let gpioc = dp.GPIOC.split(&mut rcc);
        let gpiod = dp.GPIOD.split(&mut rcc);
        let gpioe = dp.GPIOE.split(&mut rcc);
        // Keep the board's VBUS power switch off (active-low enable): the host powers VBUS.
        let mut vbus_switch = gpioc.pc0.into_push_pull_output();
        vbus_switch.set_high();
        // Keep the on-board CS43L22 audio DAC in reset: its I2S3 pins are SPI3's.
        let mut audio_reset = gpiod.pd4.into_push_pull_output();
        audio_reset.set_low();

        // Keep the on-board LIS3DSH deselected for good; it shares SPI1. Dropping the pin
        // handle leaves the pin configured and high.
        let mut accel_cs = gpioe.pe3.into_push_pull_output();
        accel_cs.set_high();

        let mode0 = Mode {
            polarity: Polarity::IdleLow,
            phase: Phase::CaptureOnFirstTransition,
        };
        let mode1 = Mode {
            polarity: Polarity::IdleLow,
            phase: Phase::CaptureOnSecondTransition,
        };
        let spi1 = Spi::new(
            dp.SPI1,
            (Some(gpioa.pa5), Some(gpioa.pa6), Some(gpioa.pa7)),
            mode0,
            21.MHz(),
            &mut rcc,
        );
        let spi2 = Spi::new(
            dp.SPI2,
            (Some(gpiob.pb13), Some(gpiob.pb14), Some(gpiob.pb15)),
            mode1,
            21.MHz(),
            &mut rcc,
        );
        let spi3 = Spi::new(
            dp.SPI3,
            (Some(gpioc.pc10), Some(gpioc.pc11), Some(gpioc.pc12)),
            mode0,
            21.MHz(),
            &mut rcc,
        );
        // Chip selects start high (ExclusiveDevice sets them high; GPIO errors are Infallible).
        let adc_cs = gpioe.pe7.into_push_pull_output();
        let dac_sync = gpiob.pb12.into_push_pull_output();
        let Ok(adc_spi) = ExclusiveDevice::new_no_delay(spi1, adc_cs);
        let Ok(dac_spi) = ExclusiveDevice::new_no_delay(spi2, dac_sync);
        let adc_y_cs = gpiod.pd0.into_push_pull_output();
        let Ok(adc_y_spi) = ExclusiveDevice::new_no_delay(spi3, adc_y_cs);

        let mut dac = Dac8563::new(dac_spi);
        dac.init().map_err(BoardError::Dac)?;
        let range = InputRange::from_range_v(crate::params::ADC_RANGE_V);
        let mut adc = Ads8681::new(adc_spi, range);
        adc.init().map_err(BoardError::Adc)?;
        let mut adc_y = Ads8681::new(adc_y_spi, range);
        adc_y.init().map_err(BoardError::AdcY)?;

        let usb = USB::new(
            (dp.OTG_FS_GLOBAL, dp.OTG_FS_DEVICE, dp.OTG_FS_PWRCLK),
            (gpioa.pa11, gpioa.pa12),
            &rcc.clocks,
        );
        Ok(Self {
            dac,
            adc,
            adc_y,
            loop_timer: dp.TIM2.counter(&mut rcc),
            usb,
        })
    }
}

/// Starts TIM2 at the loop rate with its update interrupt on: the first tick comes one period
/// later (starting it raises no update flag).
pub fn start_loop_timer(timer: &mut LoopTimer) -> Result<(), BoardError> {
    timer
        .start(fugit::TimerDurationU32::<TIMER_HZ>::from_ticks(
            TIMER_TICKS_PER_PERIOD,
        ))
        .map_err(|_| BoardError::Timer)?;
    timer.clear_flags(Flag::Update);
    timer.listen(Event::Update);
    Ok(())
}
