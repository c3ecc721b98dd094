//! The board image's hardware edge under QEMU 7.2's `netduinoplus2` machine (STM32F405,
//! Cortex-M4F; feature `board-emu`, target only; re-exported as `piezo_firmware::board::*`).
//! What QEMU models and how this variant uses it:
//!
//! | the board                                   | under QEMU                                           |
//! |---------------------------------------------|------------------------------------------------------|
//! | RCC: HSE → PLL, SYSCLK 168 MHz (HAL `freeze`, which waits for the ready bits) | no RCC model (its ready bits never set): no clock set-up at all; the peripheral clock enables are written (QEMU ignores them) |
//! | DAC8563 + two ADS8681 over SPI              | the firmware's simulated stage ([`crate::plant`], `plant_io`) behind the same converter traits, one loop period on per tick ([`end_of_tick`]) |
//! | TIM2 through stm32f4xx-hal (PSC, ARR, EGR)  | TIM2 through its registers: PSC left at 0, only ARR written (below)                 |
//! | DWT cycle counter                           | SysTick, extended to 32 bits ([`CycleCounter`])      |
//! | command link on USB CDC-ACM (OTG_FS)        | on USART1, the machine's first `-serial` (`usart_link`) |
//!
//! Clocks assumed: SYSCLK = 168 MHz ([`SYSCLK_HZ`]), the `sysclk` QEMU's netduinoplus2 gives
//! the CPU and so SysTick's processor clock; TIM2 counts at [`TIMER_HZ`] = 1 GHz, the
//! `clock-frequency` of QEMU's `stm32f2xx_timer` (not derived from any bus clock).
//!
//! # TIM2 under QEMU 7.2 (`hw/timer/stm32f2xx_timer.c`)
//! With `T(t) = ⌊t·f/10⁹⌋/(PSC+1)` the model's count at virtual time `t` \[ns\] and `O` the count
//! origin (`tick_offset`, set at reset and by any write of PSC, CNT or EGR.UG):
//!
//! ```text
//! CNT            = T(t) − O                       never reset at an update (not reduced mod ARR)
//! ARR write at t: first update at t + H,  H = (ARR + O)·(PSC+1)·10⁹/f   [ns]
//! each update:   UIF = 1 (if DIER.UIE and CR1.CEN), IRQ pulsed, next update H later
//! ```
//!
//! `H` is the virtual time at which the count since the origin reaches ARR (an absolute time),
//! and the model schedules each update `H` after the previous one (`timer_mod(now + hit_time)`).
//! It is the period only while `O = 0`: the origin is the reset (virtual time 0) and PSC, CNT and
//! EGR are never written, so the period is `ARR·10⁹/f` = [`TIMER_TICKS_PER_PERIOD`] ns — ARR, not
//! ARR + 1 as on the silicon. A HAL `start` (which writes PSC, ARR and EGR.UG) moves the origin
//! and would give a period of about the boot time instead. The update is checked when it comes:
//! with UIE or CEN off at that moment the model stops scheduling, so DIER and CR1 are written
//! before ARR. The time since the latest update is `(CNT − CNT₀) mod ARR`, with `CNT₀` read when
//! ARR is written (CNT is 32 bits wide here and wraps every 4.3 s: [`LoopTimer`] extends it).

use core::cell::Cell;
use core::convert::Infallible;
use core::mem::MaybeUninit;
use core::sync::atomic::{AtomicU32, Ordering};

use cortex_m::peripheral::syst::SystClkSource;
use cortex_m::peripheral::SYST;
use stm32f4xx_hal::pac;

use super::usart_link::UsartLink;
use super::LOOP_RATE_HZ;
use crate::codes::{AdcCode, DacCode, SensorScale};
use crate::converter::{AdcRead, DacWrite, ErrorType};
use crate::plant::{plant_io, PlantAdc, PlantDac, XyPlant};
use crate::xy_loop::{AdcSensor, Axis, XyIo};

/// Core clock assumed: QEMU netduinoplus2's `sysclk`, SysTick's processor clock \[Hz\].
pub const SYSCLK_HZ: u32 = 168_000_000;

/// TIM2's counting rate in QEMU's model (`clock-frequency`, PSC = 0) \[Hz\].
pub const TIMER_HZ: u32 = 1_000_000_000;

/// TIM2 counts per loop period: the value written to ARR (QEMU's period is ARR counts).
pub const TIMER_TICKS_PER_PERIOD: u32 = TIMER_HZ / LOOP_RATE_HZ;

/// [`LoopTimer::count`] already counts core cycles.
pub const CYCLES_PER_TIMER_TICK: u32 = 1;

/// The loop period, the tick's deadline \[core cycles\] (8 400 at the default file's 20 kHz).
pub const PERIOD_CYCLES: u32 = SYSCLK_HZ / LOOP_RATE_HZ;

const _: () = assert!(
    LOOP_RATE_HZ > 0
        && TIMER_HZ.is_multiple_of(LOOP_RATE_HZ)
        && SYSCLK_HZ.is_multiple_of(LOOP_RATE_HZ),
    "the stage file's loop rate must divide QEMU's 1 GHz TIM2 clock and 168 MHz core clock"
);

/// SysTick's reload: the whole 24-bit range.
const SYST_RELOAD: u32 = 0x00FF_FFFF;

/// The loop's converters: the simulated stage's DAC and ADC.
pub type Io = XyIo<StageDac, AdcSensor<StageAdc>>;

/// The simulated stage's DAC side ([`PlantDac`] on the stage [`bring_up`] made).
pub struct StageDac(PlantDac<'static>);

/// The simulated stage's ADC side ([`PlantAdc`] on the stage [`bring_up`] made).
pub struct StageAdc(PlantAdc<'static>);

// SAFETY: the one `StageDac` and the one `StageAdc` are the two halves of the `Io` that
// `bring_up` returns (their constructors are private), the only references to the stage's
// `Cell`, which lives in the `Statics` RTIC's `init` hands over once. RTIC moves that `Io` whole
// from `init` into the control tick, the only context that uses it, on a single core: the
// `Cell` is never reached from two contexts.
#[allow(unsafe_code)]
unsafe impl Send for StageDac {}
// SAFETY: as for `StageDac`.
#[allow(unsafe_code)]
unsafe impl Send for StageAdc {}

impl ErrorType for StageDac {
    type Error = Infallible;
}

impl ErrorType for StageAdc {
    type Error = Infallible;
}

impl DacWrite for StageDac {
    type Channel = Axis;

    #[inline]
    fn write_code(&mut self, channel: Axis, code: DacCode) -> Result<(), Infallible> {
        self.0.write_code(channel, code)
    }
}

impl AdcRead for StageAdc {
    type Channel = Axis;

    #[inline]
    fn read_code(&mut self, channel: Axis) -> Result<AdcCode, Infallible> {
        self.0.read_code(channel)
    }
}

/// The command link's transport: USART1.
pub type Link = UsartLink;

/// The interrupt the link task is bound to; the tick pends it when bytes wait.
pub const LINK_INTERRUPT: pac::Interrupt = pac::Interrupt::USART1;

/// How the boot log names the link.
pub const LINK_DESCRIPTION: &str = "USART1 (QEMU's first -serial)";

/// Why bring-up failed.
#[derive(Debug)]
pub enum BoardError {
    /// The built-in stage file gives no simulated stage (sensor scale refused).
    Stage,
}

/// TIM2 as the loop timer under QEMU's model (see the module docs).
pub struct LoopTimer {
    tim: pac::TIM2,
    /// CNT extended to 64 bits: its high word and the last CNT read.
    high: u32,
    last: u32,
    /// The extended CNT when ARR was written (updates come ARR counts apart from it).
    origin: u64,
}

impl LoopTimer {
    /// CNT extended past its 32-bit wrap (read at least every 4.3 s: each tick reads it).
    fn extended(&mut self) -> u64 {
        let raw = self.tim.cnt().read().cnt().bits();
        if raw < self.last {
            self.high = self.high.wrapping_add(1);
        }
        self.last = raw;
        (u64::from(self.high) << 32) | u64::from(raw)
    }

    /// True if TIM2's update flag is set (an update the tick has not served yet).
    #[inline]
    pub fn update_pending(&self) -> bool {
        self.tim.sr().read().uif().bit_is_set()
    }

    /// Clears the update flag (the tick serves the update); counts it for [`measured_rate`].
    #[inline]
    pub fn clear_update(&mut self) {
        self.tim.sr().write(|w| w.uif().clear());
        RATE.served(SYST::get_current());
    }

    /// Core cycles since the latest update: `(CNT − CNT₀) mod ARR`, in counts of 1 ns, times
    /// [`SYSCLK_HZ`]/[`TIMER_HZ`].
    #[inline]
    pub fn count(&mut self) -> u32 {
        let since = (self.extended().wrapping_sub(self.origin)) % u64::from(TIMER_TICKS_PER_PERIOD);
        (since * u64::from(SYSCLK_HZ) / u64::from(TIMER_HZ)) as u32
    }
}

/// SysTick counting down from 2²⁴ − 1 at [`SYSCLK_HZ`], extended to a wrapping 32-bit cycle count
/// (the DWT cycle counter's place; QEMU does not model the DWT). Exact as long as two reads are
/// less than 2²⁴ cycles (99.9 ms) apart: the tick reads it every period.
pub struct CycleCounter {
    _syst: SYST,
    last: u32,
    total: u32,
}

impl CycleCounter {
    /// Core cycles, wrapping every 2³².
    #[inline]
    pub fn now(&mut self) -> u32 {
        let up = SYST_RELOAD - SYST::get_current();
        let delta = up.wrapping_sub(self.last) & SYST_RELOAD;
        self.last = up;
        self.total = self.total.wrapping_add(delta);
        self.total
    }
}

/// Bits of [`stamp`]'s count: SysTick's 24.
pub const STAMP_MASK: u32 = SYST_RELOAD;

/// SysTick's count as a free-running 24-bit cycle count (up: `reload − current`), for
/// differences shorter than one wrap (2²⁴ cycles, 99.9 ms) from any task ([`super::timed_lock`]).
#[inline]
pub fn stamp() -> u32 {
    SYST_RELOAD - SYST::get_current()
}

/// TIM2's rate as served, measured with SysTick: the updates the tick served and the core
/// cycles between the first and the latest (written by the tick only).
struct Rate {
    served: AtomicU32,
    span_cycles_high: AtomicU32,
    span_cycles_low: AtomicU32,
    last_systick: AtomicU32,
}

static RATE: Rate = Rate {
    served: AtomicU32::new(0),
    span_cycles_high: AtomicU32::new(0),
    span_cycles_low: AtomicU32::new(0),
    last_systick: AtomicU32::new(0),
};

impl Rate {
    /// One more update served, SysTick reading `current` (counting down).
    fn served(&self, current: u32) {
        let up = SYST_RELOAD - current;
        let n = self.served.load(Ordering::Relaxed);
        if n > 0 {
            let delta = up.wrapping_sub(self.last_systick.load(Ordering::Relaxed)) & SYST_RELOAD;
            let low = self.span_cycles_low.load(Ordering::Relaxed);
            let (sum, carry) = low.overflowing_add(delta);
            self.span_cycles_low.store(sum, Ordering::Relaxed);
            if carry {
                let high = self.span_cycles_high.load(Ordering::Relaxed);
                self.span_cycles_high.store(high + 1, Ordering::Relaxed);
            }
        }
        self.last_systick.store(up, Ordering::Relaxed);
        self.served.store(n.wrapping_add(1), Ordering::Relaxed);
    }
}

/// TIM2's measured rate: (updates served, core cycles from the first to the latest), so the
/// rate is `(updates − 1)·SYSCLK_HZ / cycles` \[Hz\]. Read between two ticks (the link task runs
/// below the tick's priority, and the three words are written by the tick).
pub fn measured_rate() -> (u32, u64) {
    let served = RATE.served.load(Ordering::Relaxed);
    let high = RATE.span_cycles_high.load(Ordering::Relaxed);
    let low = RATE.span_cycles_low.load(Ordering::Relaxed);
    (served, (u64::from(high) << 32) | u64::from(low))
}

/// Memory the bring-up hands out for the rest of the run (an RTIC `init` local).
pub struct Statics {
    stage: MaybeUninit<Cell<XyPlant>>,
}

impl Statics {
    /// Not yet used.
    pub const fn new() -> Self {
        Self {
            stage: MaybeUninit::uninit(),
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

/// SysTick as the cycle counter; TIM2 and USART1 clocks enabled (RCC writes QEMU ignores; no
/// clock is waited for); the simulated stage of the built-in stage file, at rest at the lower
/// end of each window, as the loop's converters (read through `scale`); USART1 as the link,
/// announced by a semihosting line (`board-emu: parameters …, command link on USART1`) once it
/// receives.
pub fn bring_up(
    core: cortex_m::Peripherals,
    dp: pac::Peripherals,
    statics: &'static mut Statics,
    scale: SensorScale,
) -> Result<Parts, BoardError> {
    let mut syst = core.SYST;
    syst.set_clock_source(SystClkSource::Core);
    syst.set_reload(SYST_RELOAD);
    syst.clear_current();
    syst.enable_counter();

    dp.RCC.apb1enr().modify(|_, w| w.tim2en().enabled());
    dp.RCC.apb2enr().modify(|_, w| w.usart1en().enabled());

    let stage = XyPlant::from_params(crate::params::SAMPLE_PERIOD_S).ok_or(BoardError::Stage)?;
    let stage: &'static Cell<XyPlant> = statics.stage.write(Cell::new(stage));
    let XyIo {
        dac,
        dac_channels,
        sensor,
    } = plant_io(stage, scale);
    let io = XyIo {
        dac: StageDac(dac),
        dac_channels,
        sensor: AdcSensor {
            adc: StageAdc(sensor.adc),
            channels: sensor.channels,
            scale: sensor.scale,
        },
    };
    let link = UsartLink::new(dp.USART1);
    // From here on the link receives: bytes that came before USART1 was enabled were dropped by
    // QEMU (as a disabled USART would), so a host waits for this line before it talks.
    cortex_m_semihosting::hprintln!(
        "board-emu: parameters {} ({}), fnv1a32 {:#010x}, loop {} Hz (TIM2 ARR {} at {} Hz), command link on USART1",
        crate::params::VERSION,
        crate::params::SOURCE,
        crate::params::FNV1A32,
        LOOP_RATE_HZ,
        TIMER_TICKS_PER_PERIOD,
        TIMER_HZ
    );
    let mut cycles = CycleCounter {
        _syst: syst,
        last: 0,
        total: 0,
    };
    cycles.now();
    Ok(Parts {
        io,
        loop_timer: LoopTimer {
            tim: dp.TIM2,
            high: 0,
            last: 0,
            origin: 0,
        },
        link,
        cycles,
    })
}

/// Starts TIM2 at the loop rate with its update interrupt on (DIER.UIE, CR1.CEN, then ARR: the
/// write that schedules QEMU's first update, one period later). PSC, CNT and EGR stay
/// unwritten (see the module docs). Cannot fail (ARR ≥ 1 by the loop-rate check at build time);
/// a `Result` as the board's.
pub fn start_loop_timer(timer: &mut LoopTimer) -> Result<(), BoardError> {
    let tim = &timer.tim;
    tim.dier().write(|w| w.uie().enabled());
    tim.cr1().write(|w| w.cen().enabled());
    timer.origin = timer.extended();
    timer
        .tim
        .arr()
        .write(|w| w.arr().set(TIMER_TICKS_PER_PERIOD));
    timer.tim.sr().write(|w| w.uif().clear());
    Ok(())
}

/// After each tick: the simulated stage moves one loop period on with the DAC codes the tick
/// wrote (they act from the next tick's reading on: the converters' zero-order hold).
#[inline]
pub fn end_of_tick(io: &mut Io) {
    let stage = io.dac.0 .0;
    let mut s = stage.get();
    s.advance();
    stage.set(s);
}

/// Prints the run's deadline figures, TIM2's measured rate and the link's worst lock holds per
/// kind of request over semihosting and exits QEMU
/// with success (the variant's answer to a `shutdown` request; the board keeps running).
pub fn exit(
    stats: &super::deadline::TickStats,
    overruns: u32,
    holds: &crate::session::LockHolds,
) -> ! {
    let (served, span) = measured_rate();
    let rate_mhz = if span > 0 && served > 1 {
        u64::from(served - 1) * u64::from(SYSCLK_HZ) * 1000 / span
    } else {
        0
    };
    cortex_m_semihosting::hprintln!(
        "board-emu: TIM2 updates served {} over {} cycles: {}.{:03} Hz (loop_rate_hz {}); ticks {}, late {}, skipped {}, overruns {}; cycles per period {}: worst cost {}, worst latency {}, worst completion {}",
        served,
        span,
        rate_mhz / 1000,
        rate_mhz % 1000,
        LOOP_RATE_HZ,
        stats.ticks,
        stats.late_ticks,
        stats.skipped_updates,
        overruns,
        PERIOD_CYCLES,
        stats.worst_cycles,
        stats.worst_latency_cycles,
        stats.worst_completion_cycles
    );
    let h = |kind| holds.worst(kind);
    use crate::session::RequestKind as K;
    cortex_m_semihosting::hprintln!(
        "board-emu: link lock held worst {} cycles: status {}, upload {}, table {}, control {}, track {}, other {}, transmit {}",
        holds.worst_of_all(),
        h(K::Status),
        h(K::Upload),
        h(K::Table),
        h(K::Control),
        h(K::Track),
        h(K::Other),
        h(K::Transmit)
    );
    cortex_m_semihosting::debug::exit(cortex_m_semihosting::debug::EXIT_SUCCESS);
    #[allow(clippy::empty_loop)]
    loop {}
}
