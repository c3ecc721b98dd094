//! The command link's transport on the board: USB CDC-ACM (a virtual serial port,
//! `/dev/ttyACM*` on Linux) on the STM32F407's OTG_FS (PA11 D−, PA12 D+; the Discovery's
//! micro-USB socket CN5), with `usb-device` 0.3 and `usbd-serial` 0.2 on stm32f4xx-hal's
//! `otg_fs::UsbBus` (synopsys-usb-otg 0.4).
//!
//! [`UsbLink::service`] runs in the OTG_FS interrupt (and whenever the control tick pends it
//! because the session has bytes to send): it polls the USB device, decodes the received bytes
//! into requests itself, prepares each one outside the session ([`session::prepare`]: an
//! upload's validation by the core, several loop periods of work, happens here while the loop
//! keeps ticking) and serves it ([`super::serve`]: the request's effect and a copy of its reply
//! under the session's lock, between two ticks; the reply's encoding outside it; its bytes
//! queued under the lock again), and moves bytes from [`Session::transmit`] to the serial port.
//! The session is taken through an RTIC lock for one of those two steps or one batch of at most
//! [`PACKET_BYTES`] bytes out, never while encoding a packet or waiting for the bus, so a slow or
//! absent host never holds up the tick (each hold is measured: [`LinkCounters::lock_holds`]); what
//! the host does not read stays in the session's transmit buffer, which drops frames (counted)
//! when full.
//!
//! Bytes go out only while the device is configured (enumerated by a host): `usbd-serial`
//! accepts bytes into its buffer and then reports a bus error in other states, which would send
//! them twice.

use stm32f4xx_hal::otg_fs::{UsbBus, USB};
use usb_device::bus::UsbBusAllocator;
use usb_device::prelude::{
    BuilderError, StringDescriptors, UsbDevice, UsbDeviceBuilder, UsbDeviceState, UsbError,
    UsbVidPid,
};
use usbd_serial::SerialPort;

use piezo_link::{Decoder, Packet, Request};

use super::{serve, timed_lock, LinkCounters};
use crate::session::{self, RequestKind, Session};

/// The USB bus of the board.
pub type Bus = UsbBus<USB>;

/// Bytes of a full-speed bulk packet: the size of one batch in and out.
pub const PACKET_BYTES: usize = 64;

/// USB vendor and product id: pid.codes' shared id for CDC-ACM devices told apart by their
/// strings (0x16c0:0x27dd, as the stm32f4xx-hal CDC examples).
const VID_PID: UsbVidPid = UsbVidPid(0x16c0, 0x27dd);

/// The device's serial number string (short: a string descriptor must fit usb-device's 128-byte
/// control buffer; the parameter set's version is in `status`).
const SERIAL_NUMBER: &str = "piezo-f407";

/// Bytes taken from the session and not yet accepted by the serial port.
struct Staged {
    bytes: [u8; PACKET_BYTES],
    start: usize,
    end: usize,
}

impl Staged {
    fn pending(&self) -> &[u8] {
        &self.bytes[self.start..self.end]
    }

    fn push(&mut self, byte: u8) -> bool {
        if self.end == self.bytes.len() {
            return false;
        }
        self.bytes[self.end] = byte;
        self.end += 1;
        true
    }

    fn consume(&mut self, n: usize) {
        self.start = (self.start + n).min(self.end);
        if self.start == self.end {
            self.start = 0;
            self.end = 0;
        }
    }
}

/// The CDC-ACM device and what it has staged.
pub struct UsbLink {
    device: UsbDevice<'static, Bus>,
    serial: SerialPort<'static, Bus>,
    decoder: Decoder,
    staged: Staged,
    counters: LinkCounters,
}

impl UsbLink {
    /// The CDC-ACM device on `bus` (the serial port's endpoints are allocated first, then the
    /// device is built and the bus enabled; the host sees it once the OTG_FS interrupt runs).
    pub fn new(bus: &'static UsbBusAllocator<Bus>) -> Result<Self, BuilderError> {
        let serial = SerialPort::new(bus);
        let strings = StringDescriptors::default()
            .manufacturer("piezo-firmware")
            .product("piezo compensator command link")
            .serial_number(SERIAL_NUMBER);
        let device = UsbDeviceBuilder::new(bus, VID_PID)
            .device_class(usbd_serial::USB_CLASS_CDC)
            .strings(&[strings])?
            .build();
        Ok(Self {
            device,
            serial,
            decoder: Decoder::new(),
            staged: Staged {
                bytes: [0; PACKET_BYTES],
                start: 0,
                end: 0,
            },
            counters: LinkCounters::default(),
        })
    }

    /// What the link has counted.
    pub fn counters(&self) -> LinkCounters {
        self.counters
    }

    /// True while a host has the device configured.
    pub fn configured(&self) -> bool {
        self.device.state() == UsbDeviceState::Configured
    }

    /// Polls the device, decodes and prepares received requests and serves them
    /// ([`super::serve`]), and sends what the session has, until the serial port would block.
    /// `session` is locked twice per request (after its preparation, and after its reply's
    /// encoding) and once per batch of at most [`PACKET_BYTES`] bytes out.
    pub fn service<M>(&mut self, session: &mut M)
    where
        M: rtic::Mutex<T = &'static mut Session>,
    {
        self.device.poll(&mut [&mut self.serial]);
        let mut received = [0u8; PACKET_BYTES];
        while let Ok(n @ 1..) = self.serial.read(&mut received) {
            let holds = &mut self.counters.lock_holds;
            for &byte in &received[..n] {
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
            self.counters.bytes_in = self.counters.bytes_in.wrapping_add(n as u32);
        }
        if !self.configured() {
            return;
        }
        loop {
            if self.staged.pending().is_empty() {
                let (staged, holds) = (&mut self.staged, &mut self.counters.lock_holds);
                timed_lock(session, holds, RequestKind::Transmit, |s| {
                    s.transmit(|b| staged.push(b))
                });
                if staged.pending().is_empty() {
                    return;
                }
            }
            match self.serial.write(self.staged.pending()) {
                Ok(n) => {
                    self.staged.consume(n);
                    self.counters.bytes_out = self.counters.bytes_out.wrapping_add(n as u32);
                }
                Err(UsbError::WouldBlock) => return,
                Err(_) => {
                    self.staged.consume(PACKET_BYTES);
                    self.counters.errors = self.counters.errors.saturating_add(1);
                    return;
                }
            }
        }
    }
}
