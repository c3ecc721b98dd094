//! The board image's hardware edge, in two variants with one interface (target only):
//!
//! - feature `board`: the STM32F4-Discovery (STM32F407VG): clocks, SPI converters (DAC8563,
//!   two ADS8681), TIM2, the command link over USB CDC-ACM ([`usb_link`]);
//! - feature `board-emu`: the same image under QEMU's `netduinoplus2` (STM32F405): no clock
//!   set-up, the firmware's simulated stage ([`crate::plant`]) behind the converter traits, the
//!   command link on USART1 (`usart_link`), TIM2 driven through its registers (`emu`).
//!
//! The RTIC 2 application both images run (`src/bin/board/app.rs`) uses only what both variants
//! export under the same names: [`LOOP_RATE_HZ`], `SYSCLK_HZ`, `PERIOD_CYCLES`,
//! `CYCLES_PER_TIMER_TICK`, `stamp` and `STAMP_MASK` (a free-running cycle count any task reads,
//! for [`timed_lock`]), `Io` (the loop's converters), `LoopTimer` (`update_pending`,
//! `clear_update`, `count`), `CycleCounter` (`now`), `Link` (`service`, `counters`,
//! `configured`), `LINK_INTERRUPT`, `Statics`, `bring_up`, `start_loop_timer` and
//! `end_of_tick`. [`deadline`] is shared.

pub mod deadline;

use crate::session::{LockHolds, Prepared, RequestKind, Session};

#[cfg(feature = "board")]
mod discovery;
#[cfg(feature = "board")]
pub use discovery::*;
#[cfg(feature = "board")]
pub mod usb_link;

#[cfg(feature = "board-emu")]
mod emu;
#[cfg(feature = "board-emu")]
pub use emu::*;
#[cfg(feature = "board-emu")]
pub mod usart_link;

/// Loop rate, hertz (TIM2 update rate): the stage file's `stage.loop_rate_hz`, a whole number of
/// hertz checked by `build.rs`.
pub const LOOP_RATE_HZ: u32 = crate::params::LOOP_RATE_HZ as u32;

/// Core cycles from `start` to `end`, two readings of [`stamp`] less than one wrap of the
/// counter apart (2³² cycles for the DWT, 2²⁴ for SysTick): `(end − start) mod (STAMP_MASK + 1)`.
#[inline]
pub fn elapsed_cycles(start: u32, end: u32) -> u32 {
    end.wrapping_sub(start) & STAMP_MASK
}

/// Serves one request the link decoded and prepared ([`crate::session::prepare`]): its effect
/// and its reply's copy under one lock ([`Session::answer`]), the encoding with no lock held
/// ([`crate::session::Reply::encode`]), the encoded bytes queued under a second lock
/// ([`Session::queue_reply`]). Both holds are noted in `holds` under the request's kind.
pub fn serve<M>(session: &mut M, holds: &mut LockHolds, sequence: u32, prepared: Prepared)
where
    M: rtic::Mutex<T = &'static mut Session>,
{
    let kind = RequestKind::of_prepared(&prepared);
    let reply = timed_lock(session, holds, kind, |s| s.answer(sequence, &prepared));
    let mut out = [0u8; piezo_link::MAX_FRAME];
    let n = reply.encode(&mut out);
    let bytes = n.map(|n| &out[..n]);
    timed_lock(session, holds, kind, |s| s.queue_reply(&reply, bytes));
}

/// Runs `f` on the session under its lock and notes in `holds`, as `kind`, how long the lock was
/// held (from inside it: [`stamp`] after taking it and before releasing it).
#[inline]
pub fn timed_lock<M, R>(
    session: &mut M,
    holds: &mut LockHolds,
    kind: RequestKind,
    f: impl FnOnce(&mut Session) -> R,
) -> R
where
    M: rtic::Mutex<T = &'static mut Session>,
{
    let (r, cycles) = session.lock(|s| {
        let start = stamp();
        let r = f(s);
        (r, elapsed_cycles(start, stamp()))
    });
    holds.note(kind, cycles);
    r
}

/// What the command link's transport has counted (logged by the board image).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LinkCounters {
    /// The largest hold of the session's lock per kind of request \[core cycles\].
    pub lock_holds: LockHolds,
    /// Bytes received and handed to the session.
    pub bytes_in: u32,
    /// Bytes the transport accepted for sending.
    pub bytes_out: u32,
    /// Transport errors (USB: errors other than "would block" on a write; the staged bytes are
    /// dropped and the host resynchronises on the next delimiter).
    pub errors: u32,
}
