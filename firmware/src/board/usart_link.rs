//! The command link's transport in the emulated board image: USART1 of the STM32F405 (SR, DR,
//! BRR, CR1; RM0090 section 30.6), which QEMU's `netduinoplus2` connects to its first `-serial`
//! (feature `board-emu`, target only).
//!
//! [`UsartLink::service`] runs in the USART1 interrupt (RXNE: a byte came) and whenever the
//! control tick pends it because the session has bytes to send, as the USB link does: received
//! bytes are decoded here, each request prepared outside the session ([`session::prepare`]),
//! applied under its lock with its reply copied out, the reply encoded outside and queued under
//! the lock again ([`super::serve`]); bytes out are taken from
//! [`Session::transmit`] in batches of at most [`BATCH_BYTES`] under the lock and written to DR
//! while TXE is set, never waiting for it: what DR cannot take yet stays staged, and TXEIE is on
//! only while bytes are staged (QEMU's USART writes each byte at once, TXE is always set there,
//! so nothing is ever staged under QEMU).

use stm32f4xx_hal::pac;

use piezo_link::{Decoder, Packet, Request};

use super::{serve, timed_lock, LinkCounters};
use crate::session::{self, RequestKind, Session};

/// Bytes taken from the session under one lock.
pub const BATCH_BYTES: usize = 64;

/// BRR for 115 200 Bd from the 16 MHz reset clock (HSI), oversampling 16: USARTDIV = 8.6875
/// (mantissa 8, fraction 11/16). QEMU ignores the baud rate.
const BRR_MANTISSA: u16 = 8;
const BRR_FRACTION: u8 = 11;

/// USART1 as the command link.
pub struct UsartLink {
    usart: pac::USART1,
    decoder: Decoder,
    staged: [u8; BATCH_BYTES],
    start: usize,
    end: usize,
    counters: LinkCounters,
}

impl UsartLink {
    /// USART1 enabled both ways, 8N1, with its receive interrupt (RXNEIE) on.
    pub fn new(usart: pac::USART1) -> Self {
        usart.brr().write(|w| {
            w.div_mantissa()
                .set(BRR_MANTISSA)
                .div_fraction()
                .set(BRR_FRACTION)
        });
        usart.cr1().write(|w| {
            w.ue()
                .enabled()
                .te()
                .enabled()
                .re()
                .enabled()
                .rxneie()
                .enabled()
        });
        Self {
            usart,
            decoder: Decoder::new(),
            staged: [0; BATCH_BYTES],
            start: 0,
            end: 0,
            counters: LinkCounters::default(),
        }
    }

    /// What the link has counted.
    pub fn counters(&self) -> LinkCounters {
        self.counters
    }

    /// Always true: a serial line has no configuration state.
    pub fn configured(&self) -> bool {
        true
    }

    /// Bytes staged and not yet written to DR.
    pub fn staged(&self) -> usize {
        self.end - self.start
    }

    /// Decodes the received bytes (each request prepared, then served: [`super::serve`]), then
    /// writes what the session has while DR takes it. Every hold of `session`'s lock is
    /// measured ([`LinkCounters::lock_holds`]).
    pub fn service<M>(&mut self, session: &mut M)
    where
        M: rtic::Mutex<T = &'static mut Session>,
    {
        let holds = &mut self.counters.lock_holds;
        while self.usart.sr().read().rxne().bit_is_set() {
            let byte = self.usart.dr().read().dr().bits() as u8;
            self.counters.bytes_in = self.counters.bytes_in.wrapping_add(1);
            match self.decoder.push::<Request>(byte) {
                None => {}
                Some(Ok(Packet { sequence, body })) => {
                    serve(session, holds, sequence, session::prepare(body));
                }
                Some(Err(_)) => timed_lock(session, holds, RequestKind::Other, |s| {
                    s.note_rejected_packet()
                }),
            }
        }
        loop {
            if self.start == self.end {
                let (staged, end, holds) = (
                    &mut self.staged,
                    &mut self.end,
                    &mut self.counters.lock_holds,
                );
                self.start = 0;
                *end = timed_lock(session, holds, RequestKind::Transmit, |s| {
                    let mut n = 0;
                    s.transmit(|b| {
                        if n == BATCH_BYTES {
                            return false;
                        }
                        staged[n] = b;
                        n += 1;
                        true
                    });
                    n
                });
                if *end == 0 {
                    self.usart.cr1().modify(|_, w| w.txeie().disabled());
                    return;
                }
            }
            while self.start < self.end {
                if self.usart.sr().read().txe().bit_is_clear() {
                    // DR is full: TXE's interrupt brings the link back.
                    self.usart.cr1().modify(|_, w| w.txeie().enabled());
                    return;
                }
                let byte = self.staged[self.start];
                self.usart.dr().write(|w| w.dr().set(u16::from(byte)));
                self.start += 1;
                self.counters.bytes_out = self.counters.bytes_out.wrapping_add(1);
            }
        }
    }
}
