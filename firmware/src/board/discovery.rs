//! STM32F4-Discovery (STM32F407VG) bring-up: clocks, the two SPI buses, chip selects, the loop
//! timer, the USB OTG_FS peripheral, and the DAC8563/ADS8681 drivers on them. Target only
//! (`board` feature; its items are re-exported as `piezo_firmware::board::*`). The tasks that use
//! them are in `src/bin/board/app.rs` (RTIC 2).
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
//! at [`LOOP_RATE_HZ`], the stage file's loop rate (20 kHz for the default file; a rate that
//! does not divide 84 MHz stops the build). Each update raises the TIM2 interrupt, the control
//! tick. Deadline: a tick must have staged both DAC codes and started their transfer within
//! one period ([`PERIOD_CYCLES`] core cycles, 50 µs at 20 kHz) of the update that started it;
//! [`super::deadline`] measures that with the DWT cycle counter; the measured worst case is
//! logged once a second (`src/bin/board/app.rs`).
//!
//! # Converters: what the tick waits for
//!
//! The two ADS8681 are read at once ([`crate::concurrent_adc`]): both CONVST/CS low, a 32-bit
//! NOP frame clocked on SPI1 and SPI3 together, both high. The DAC8563's two 24-bit frames go
//! out by DMA ([`crate::dac_dma`]): DMA1 stream 4 channel 0 feeds SPI2's TX, stream 3 channel 0
//! drains its RX; staging the tick's second DAC code lowers SYNC and starts frame A, and the RX
//! stream's transfer-complete interrupt (`DMA1_STREAM3`, [`dac_frame_done`], at the tick's
//! priority) raises SYNC, holds it high, lowers it and starts frame B, then raises it at B's
//! end. A tick whose DAC write finds the previous pair still going out gets `Busy`: the loop
//! counts a DAC error and holds its outputs (safe state). The buffers are in `.bss` (SRAM,
//! which DMA1 reaches; not the CCM).
//!
//! Budget, all figures in [`crate::converter_timing`] (its tests check the arithmetic):
//!
//! | item | datasheet / clock tree | time | core cycles (168 MHz) |
//! |---|---|---|---|
//! | SPI1 SCLK | APB2 84 MHz / 4 (RM0090 BR = 001) | 21 MHz | 8 per bit |
//! | SPI2, SPI3 SCLK | APB1 42 MHz / 2 (BR = 000) | 21 MHz | 8 per bit |
//! | ADS8681 frame | 32 bits (SBAS633, data transfer frame) | 1.52 µs | 256 |
//! | ADS8681 t_conv | ≤ 665 ns after CONVST/CS rises | — | — |
//! | ADS8681 t_cyc, t_acq | ≥ 1 µs (1 MSPS), t_acq ≥ t_cyc − t_conv = 335 ns | — | — |
//! | DAC8563 frame | 24 bits per SYNC low (SLAS719) | 1.14 µs | 192 |
//! | DAC8563 SYNC high between frames | above the datasheet minimum (tens of ns) | 100 ns | 17 |
//! | DAC8563 settling | 7 µs to ±½ LSB (full-scale step, typical) | — | — |
//!
//! What the tick holds, per tick: before, the four frames one after the other, 2 · 256 + 2 · 192
//! = 896 cycles (5.33 µs; [`converter_timing::CONVERTER_CYCLES_IN_TICK_BLOCKING`], a lower
//! bound: the HAL's blocking transfers leave a gap after every byte). Now one ADC frame time,
//! 256 cycles (1.52 µs, [`converter_timing::CONVERTER_CYCLES_IN_TICK`]): the x and y frames
//! overlap and each bus keeps two bytes in flight, so SCLK runs without gaps; the DAC frames
//! cost the tick only the instructions that stage the codes and start the two streams (a
//! critical section, two stream reprogrammings). At 50 kHz (3 360 cycles a period) that is 7.6 %
//! of the period instead of 26.7 %. `firmware/bench.sh` counts the loop's instructions under
//! QEMU with simulated converters; it adds [`converter_timing::CONVERTER_CYCLES_IN_TICK`] to the
//! worst tick for the board's share of the period.
//!
//! Sample and output times: a tick reads the conversions started when the previous tick raised
//! both CS (pipelined, one period earlier; t_conv + t_acq ≪ one period at 50 kHz); channel A (x)
//! updates at the end of frame A, 1.14 µs after the tick's DAC step; channel B (y) one SYNC high
//! time and one frame after the frame-A interrupt, which runs when the tick returns (it has the
//! tick's priority), so about 1.3 µs after the tick ends. Both are inside the period; the pair
//! is [`converter_timing::DAC_PAIR_CYCLES`] = 401 cycles of bus time plus the interrupt's latency.
//!
//! Only a board verifies: that the DMA streams, their interrupt and SYNC produce the frames on
//! the pins (a logic analyser on PB12/PB13/PB15: SYNC low for exactly 24 SCLK edges, high ≥ the
//! DAC8563's minimum between the frames) and that the DAC8563 takes both; that the two ADC
//! frames run gap-free at 21 MHz with no overrun (the polling round must stay under one byte
//! time, 64 cycles; an overrun is reported as a sensor error); the tick's cycles with the
//! converters (DWT, logged once a second), the `dac dma` counters (pairs sent, refused busy,
//! aborted) in the log, and the sample-to-output latency. The host tests check the sequencer,
//! the frames and the byte pipelining against a model of the SPI peripheral; this image's build
//! checks the DMA stream/channel mapping (the HAL's `DMASet` for SPI2 TX and RX) and the
//! interrupt binding.
//!
//! Not done: starting the conversions from TIM2 in hardware. CONVST/CS is PE7 and PD0, which are
//! no TIM2 outputs, and the same pin is the frame's chip select; a timer-driven CONVST needs a
//! rewiring (a TIM2 channel on CS) and a DMA-driven ADC frame, so the sample instant is still
//! the previous tick's end of frame, a fixed point of the tick's code path after its start.

use core::cell::RefCell;
use core::convert::Infallible;
use core::mem::MaybeUninit;

use cortex_m::interrupt::Mutex;
use cortex_m::peripheral::DWT;
use embedded_hal_bus::spi::{DeviceError, ExclusiveDevice};
use stm32f4xx_hal::dma::config::{DmaConfig, Priority};
use stm32f4xx_hal::dma::{
    DmaFlag, MemoryToPeripheral, PeripheralToMemory, Stream3, Stream4, StreamsTuple, Transfer,
};
use stm32f4xx_hal::gpio::{Output, PB12, PD0, PE7};
use stm32f4xx_hal::otg_fs::{UsbBus, USB};
use stm32f4xx_hal::pac;
use stm32f4xx_hal::prelude::*;
use stm32f4xx_hal::rcc::Config;
use stm32f4xx_hal::spi::{self, Mode, Phase, Polarity, Spi};
use stm32f4xx_hal::timer::{Counter, Event, Flag};
use usb_device::bus::UsbBusAllocator;

use super::usb_link::{Bus as UsbBusType, UsbLink};
use super::LOOP_RATE_HZ;
use crate::ads8681::{Ads8681, InputRange};
use crate::codes::SensorScale;
use crate::concurrent_adc::ConcurrentAdcPair;
use crate::converter::DriverError;
use crate::converter_timing;
use crate::dac8563::{Dac8563, Dac8563Channel};
use crate::dac_dma::{DacSequencer, DmaDac, FramePort, PortAccess};
use crate::xy_loop::XyIo;

/// Core clock, the DWT cycle counter's rate \[Hz\].
pub const SYSCLK_HZ: u32 = converter_timing::SYSCLK_HZ;

/// TIM2's counting rate: its kernel clock, prescaler 1 \[Hz\].
pub const TIMER_HZ: u32 = 84_000_000;

/// TIM2 counts per loop period.
pub const TIMER_TICKS_PER_PERIOD: u32 = TIMER_HZ / LOOP_RATE_HZ;

/// Core cycles per TIM2 count.
pub const CYCLES_PER_TIMER_TICK: u32 = SYSCLK_HZ / TIMER_HZ;

/// The loop period, the tick's deadline \[core cycles\] (8 400 at the default file's 20 kHz).
pub const PERIOD_CYCLES: u32 = TIMER_TICKS_PER_PERIOD * CYCLES_PER_TIMER_TICK;

const _: () = assert!(
    LOOP_RATE_HZ > 0 && TIMER_HZ.is_multiple_of(LOOP_RATE_HZ),
    "the stage file's loop rate must divide TIM2's 84 MHz (the board's tick would run at another rate than the model's sample period)"
);

/// TIM2 as the loop timer: counts at [`TIMER_HZ`], from 0 at each update.
pub struct LoopTimer(Counter<pac::TIM2, TIMER_HZ>);

impl LoopTimer {
    /// True if TIM2's update flag is set (an update the tick has not served yet).
    #[inline]
    pub fn update_pending(&self) -> bool {
        self.0.flags().contains(Flag::Update)
    }

    /// Clears the update flag (the tick serves the update).
    #[inline]
    pub fn clear_update(&mut self) {
        self.0.clear_flags(Flag::Update);
    }

    /// TIM2's counter: timer counts since the latest update ([`CYCLES_PER_TIMER_TICK`] core
    /// cycles each).
    #[inline]
    pub fn count(&mut self) -> u32 {
        self.0.now().ticks()
    }
}

/// The DWT cycle counter (CYCCNT, [`SYSCLK_HZ`]), enabled by [`bring_up`].
pub struct CycleCounter(());

impl CycleCounter {
    /// Core cycles, wrapping every 2³² (25.6 s).
    #[inline]
    pub fn now(&mut self) -> u32 {
        DWT::cycle_count()
    }
}

/// Bits of [`stamp`]'s count: the DWT's 32.
pub const STAMP_MASK: u32 = u32::MAX;

/// The DWT cycle counter, free-running, for differences from any task ([`super::timed_lock`]).
#[inline]
pub fn stamp() -> u32 {
    DWT::cycle_count()
}

/// The board's converters as the loop sees them: the DAC8563 written by DMA, the two ADS8681
/// read at once.
pub type Io = XyIo<DmaDac<DacDma>, AdcPair>;

/// The two ADS8681: x on SPI1 (CS PE7), y on SPI3 (CS PD0), read at once.
pub type AdcPair = ConcurrentAdcPair<Spi<pac::SPI1>, Spi<pac::SPI3>, PE7<Output>, PD0<Output>>;

/// The command link's transport: USB CDC-ACM.
pub type Link = UsbLink;

/// The interrupt the link task is bound to; the tick pends it when bytes wait.
pub const LINK_INTERRUPT: pac::Interrupt = pac::Interrupt::OTG_FS;

/// How the boot log names the link.
pub const LINK_DESCRIPTION: &str = "USB CDC-ACM";

/// Words of OTG_FS endpoint memory (the HAL's examples' size).
const EP_MEMORY_WORDS: usize = 1024;

/// Memory the bring-up hands out for the rest of the run (an RTIC `init` local).
pub struct Statics {
    ep_memory: [u32; EP_MEMORY_WORDS],
    usb_bus: MaybeUninit<UsbBusAllocator<UsbBusType>>,
    dac_buffers: DacBuffers,
}

impl Statics {
    /// Not yet used.
    pub const fn new() -> Self {
        Self {
            ep_memory: [0; EP_MEMORY_WORDS],
            usb_bus: MaybeUninit::uninit(),
            dac_buffers: DacBuffers {
                tx: [[0; 3]; 2],
                rx: [[0; 3]; 2],
            },
        }
    }
}

impl Default for Statics {
    fn default() -> Self {
        Self::new()
    }
}

/// What the RTIC tasks own after [`bring_up`].
pub struct Parts {
    /// The loop's converters.
    pub io: Io,
    /// TIM2, not started ([`start_loop_timer`]).
    pub loop_timer: LoopTimer,
    /// The command link's transport.
    pub link: Link,
    /// The deadline monitor's clock.
    pub cycles: CycleCounter,
}

/// The DWT cycle counter, then [`Board::init`] (clocks, pins, converters), the converters as
/// the loop's I/O (DAC channel A → x, B → y; one ADS8681 per axis through `scale`) and the USB
/// CDC-ACM device. `statics` is used once (RTIC's `init` runs once).
pub fn bring_up(
    mut core: cortex_m::Peripherals,
    dp: pac::Peripherals,
    statics: &'static mut Statics,
    scale: SensorScale,
) -> Result<Parts, BoardError> {
    core.DCB.enable_trace();
    core.DWT.enable_cycle_counter();
    let Statics {
        ep_memory,
        usb_bus,
        dac_buffers,
    } = statics;
    let Board {
        dac,
        sensor,
        loop_timer,
        usb,
    } = Board::init(dp, dac_buffers, scale)?;
    let io = XyIo {
        dac,
        dac_channels: [Dac8563Channel::A, Dac8563Channel::B],
        sensor,
    };
    let bus: &'static UsbBusAllocator<UsbBusType> = usb_bus.write(UsbBus::new(usb, ep_memory));
    let link = UsbLink::new(bus).map_err(BoardError::Usb)?;
    Ok(Parts {
        io,
        loop_timer,
        link,
        cycles: CycleCounter(()),
    })
}

/// After each tick: nothing (the real stage moves on its own).
#[inline(always)]
pub fn end_of_tick(_io: &mut Io) {}

/// Error of the converters' init sequences, run with the blocking drivers on an
/// [`ExclusiveDevice`] before the buses are handed to the concurrent reads and the DMA.
pub type InitError = DriverError<DeviceError<spi::Error, Infallible>>;

/// Why bring-up failed.
#[derive(Debug)]
pub enum BoardError {
    /// The DAC init sequence failed.
    Dac(InitError),
    /// The x ADC init (range write and readback) failed.
    Adc(InitError),
    /// The y ADC init failed.
    AdcY(InitError),
    /// TIM2's kernel clock is not [`TIMER_HZ`], or the timer could not be started.
    Timer,
    /// The PLL's 48 MHz output is off by more than USB's ±0.25 %.
    UsbClock,
    /// usb-device refused the CDC-ACM device's descriptors.
    Usb(usb_device::prelude::BuilderError),
}

/// Everything the loop needs.
pub struct Board {
    /// The piezo amplifiers' DAC (channel A x, B y), written by DMA.
    pub dac: DmaDac<DacDma>,
    /// The displacement sensors' ADCs, read at once.
    pub sensor: AdcPair,
    /// TIM2, counting at [`TIMER_HZ`], not started ([`start_loop_timer`]).
    pub loop_timer: LoopTimer,
    /// The OTG_FS peripheral and its pins, for the USB bus.
    pub usb: USB,
}

impl Board {
    /// Clocks, pins, buses, timer, USB peripheral; then the DAC init (outputs to 0 V) and the
    /// ADC init (range ±10.24 V, read back), both with the blocking drivers; then SPI2 goes to
    /// DMA1 (stream 4 channel 0 TX, stream 3 channel 0 RX, with `buffers`) and SPI1/SPI3 to the
    /// concurrent reads.
    pub fn init(
        dp: pac::Peripherals,
        buffers: &'static mut DacBuffers,
        scale: SensorScale,
    ) -> Result<Self, BoardError> {
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
        let mut spi1 = Spi::new(
            dp.SPI1,
            (Some(gpioa.pa5), Some(gpioa.pa6), Some(gpioa.pa7)),
            mode0,
            21.MHz(),
            &mut rcc,
        );
        let mut spi2 = Spi::new(
            dp.SPI2,
            (Some(gpiob.pb13), Some(gpiob.pb14), Some(gpiob.pb15)),
            mode1,
            21.MHz(),
            &mut rcc,
        );
        let mut spi3 = Spi::new(
            dp.SPI3,
            (Some(gpioc.pc10), Some(gpioc.pc11), Some(gpioc.pc12)),
            mode0,
            21.MHz(),
            &mut rcc,
        );
        // Chip selects start high (ExclusiveDevice sets them high; GPIO errors are Infallible).
        let mut adc_cs = gpioe.pe7.into_push_pull_output();
        let mut dac_sync = gpiob.pb12.into_push_pull_output();
        let mut adc_y_cs = gpiod.pd0.into_push_pull_output();

        let Ok(dac_spi) = ExclusiveDevice::new_no_delay(&mut spi2, &mut dac_sync);
        Dac8563::new(dac_spi).init().map_err(BoardError::Dac)?;
        let range = InputRange::from_range_v(crate::params::ADC_RANGE_V);
        let Ok(adc_spi) = ExclusiveDevice::new_no_delay(&mut spi1, &mut adc_cs);
        Ads8681::new(adc_spi, range)
            .init()
            .map_err(BoardError::Adc)?;
        let Ok(adc_y_spi) = ExclusiveDevice::new_no_delay(&mut spi3, &mut adc_y_cs);
        Ads8681::new(adc_y_spi, range)
            .init()
            .map_err(BoardError::AdcY)?;

        let streams = StreamsTuple::new(dp.DMA1, &mut rcc);
        install_dac_dma(spi2, dac_sync, streams.3, streams.4, buffers);
        let sensor = ConcurrentAdcPair {
            bus_x: spi1,
            bus_y: spi3,
            cs_x: adc_cs,
            cs_y: adc_y_cs,
            scale,
        };

        let usb = USB::new(
            (dp.OTG_FS_GLOBAL, dp.OTG_FS_DEVICE, dp.OTG_FS_PWRCLK),
            (gpioa.pa11, gpioa.pa12),
            &rcc.clocks,
        );
        Ok(Self {
            dac: DmaDac::new(DacDma(())),
            sensor,
            loop_timer: LoopTimer(dp.TIM2.counter(&mut rcc)),
            usb,
        })
    }
}

/// Starts TIM2 at the loop rate with its update interrupt on: the first tick comes one period
/// later (starting it raises no update flag).
pub fn start_loop_timer(timer: &mut LoopTimer) -> Result<(), BoardError> {
    let timer = &mut timer.0;
    timer
        .start(fugit::TimerDurationU32::<TIMER_HZ>::from_ticks(
            TIMER_TICKS_PER_PERIOD,
        ))
        .map_err(|_| BoardError::Timer)?;
    timer.clear_flags(Flag::Update);
    timer.listen(Event::Update);
    Ok(())
}

/// The DMA buffers of the DAC's frames: two to send (one going out, one being filled) and two
/// to receive into (SPI2 receives while it sends; the receive stream's end marks a frame's end).
pub struct DacBuffers {
    tx: [[u8; 3]; 2],
    rx: [[u8; 3]; 2],
}

/// SPI2's TX DMA: DMA1 stream 4, channel 0.
type DacTx =
    Transfer<Stream4<pac::DMA1>, 0, spi::Tx<pac::SPI2>, MemoryToPeripheral, &'static mut [u8; 3]>;
/// SPI2's RX DMA: DMA1 stream 3, channel 0 (its transfer-complete interrupt ends a frame).
type DacRx =
    Transfer<Stream3<pac::DMA1>, 0, spi::Rx<pac::SPI2>, PeripheralToMemory, &'static mut [u8; 3]>;

/// The DAC8563's frames on SPI2 by DMA, SYNC on PB12: the [`FramePort`] of the sequencer.
pub struct DacPort {
    tx: DacTx,
    rx: DacRx,
    tx_spare: Option<&'static mut [u8; 3]>,
    rx_spare: Option<&'static mut [u8; 3]>,
    sync: PB12<Output>,
}

impl FramePort for DacPort {
    /// SYNC low, then the receive stream and the send stream on the spare buffers (receive
    /// first, so that no received byte finds it off). A buffer the HAL does not hand back (only
    /// possible with double buffering, which is off) leaves the frame unsent: the sequencer
    /// then waits, and the next tick's write is refused (`Busy`), a DAC fault.
    fn begin_frame(&mut self, frame: [u8; 3]) {
        self.sync.set_low();
        let (Some(tx), Some(rx)) = (self.tx_spare.take(), self.rx_spare.take()) else {
            return;
        };
        *tx = frame;
        match self.rx.next_transfer(rx) {
            Ok((old, _)) => self.rx_spare = Some(old),
            Err(_) => return,
        }
        if let Ok((old, _)) = self.tx.next_transfer(tx) {
            self.tx_spare = Some(old);
        }
    }

    fn end_frame(&mut self) {
        self.sync.set_high();
    }

    fn hold_sync_high(&mut self) {
        cortex_m::asm::delay(converter_timing::DAC8563_SYNC_HIGH_CYCLES);
    }
}

/// The sequencer and its port, shared by the tick's DAC writes and the DMA interrupt.
struct DacState {
    sequencer: DacSequencer,
    port: DacPort,
}

static DAC_STATE: Mutex<RefCell<Option<DacState>>> = Mutex::new(RefCell::new(None));

/// SPI2 to DMA (TX and RX requests on), the two streams configured (direct mode, memory
/// increment; the RX stream with its transfer-complete and transfer-error interrupts), SYNC
/// high; installed for [`DacDma`] and [`dac_frame_done`].
fn install_dac_dma(
    spi2: Spi<pac::SPI2>,
    mut sync: PB12<Output>,
    rx_stream: Stream3<pac::DMA1>,
    tx_stream: Stream4<pac::DMA1>,
    buffers: &'static mut DacBuffers,
) {
    sync.set_high();
    let (tx, rx) = spi2.use_dma().txrx();
    let [tx0, tx1] = &mut buffers.tx;
    let [rx0, rx1] = &mut buffers.rx;
    let rx = Transfer::init_peripheral_to_memory(
        rx_stream,
        rx,
        rx0,
        None,
        DmaConfig::default()
            .priority(Priority::VeryHigh)
            .memory_increment(true)
            .transfer_complete_interrupt(true)
            .transfer_error_interrupt(true),
    );
    let tx = Transfer::init_memory_to_peripheral(
        tx_stream,
        tx,
        tx0,
        None,
        DmaConfig::default()
            .priority(Priority::High)
            .memory_increment(true),
    );
    let state = DacState {
        sequencer: DacSequencer::new(),
        port: DacPort {
            tx,
            rx,
            tx_spare: Some(tx1),
            rx_spare: Some(rx1),
            sync,
        },
    };
    cortex_m::interrupt::free(|cs| DAC_STATE.borrow(cs).replace(Some(state)));
}

/// The loop's access to the DAC's sequencer: a critical section around each write (the DMA
/// interrupt shares it).
#[derive(Debug)]
pub struct DacDma(());

impl PortAccess for DacDma {
    type Port = DacPort;

    #[inline]
    fn with_port<R>(&mut self, f: impl FnOnce(&mut DacSequencer, &mut DacPort) -> R) -> Option<R> {
        cortex_m::interrupt::free(|cs| {
            let mut state = DAC_STATE.borrow(cs).try_borrow_mut().ok()?;
            let state = state.as_mut()?;
            Some(f(&mut state.sequencer, &mut state.port))
        })
    }
}

/// The interrupt of DMA1 stream 3 (SPI2 RX): a DAC frame's last bit has been clocked. Ends it
/// and starts the next one ([`DacSequencer::frame_done`]); on a transfer error of either
/// stream, aborts the pair ([`DacSequencer::abort`]).
pub fn dac_frame_done() {
    cortex_m::interrupt::free(|cs| {
        let Ok(mut state) = DAC_STATE.borrow(cs).try_borrow_mut() else {
            return;
        };
        let Some(DacState { sequencer, port }) = state.as_mut() else {
            return;
        };
        let all = DmaFlag::TransferComplete
            | DmaFlag::TransferError
            | DmaFlag::HalfTransfer
            | DmaFlag::FifoError
            | DmaFlag::DirectModeError;
        let rx = port.rx.flags();
        let tx = port.tx.flags();
        port.rx.clear_flags(all);
        port.tx.clear_flags(all);
        let failed = DmaFlag::TransferError | DmaFlag::DirectModeError;
        if rx.intersects(failed) || tx.intersects(failed) {
            sequencer.abort(port);
        } else if rx.contains(DmaFlag::TransferComplete) {
            sequencer.frame_done(port);
        }
    });
}

/// What the DAC's sequencer has counted (pairs sent, writes refused while busy, aborts).
pub fn dac_counters() -> crate::dac_dma::DmaDacCounters {
    cortex_m::interrupt::free(|cs| {
        DAC_STATE
            .borrow(cs)
            .try_borrow()
            .ok()
            .and_then(|s| s.as_ref().map(|s| s.sequencer.counters()))
            .unwrap_or_default()
    })
}
