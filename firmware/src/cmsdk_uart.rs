//! UART0 of QEMU's `mps2-an386` (an Arm CMSDK APB UART at 0x4000_4000; Arm DDI 0479C, "Cortex-M
//! System Design Kit", section 4.3): the QEMU image's command link. Target and `qemu` feature
//! only.
//!
//! | offset | register  | bits used                                             |
//! |--------|-----------|-------------------------------------------------------|
//! | 0x000  | DATA      | one byte in or out                                    |
//! | 0x004  | STATE     | 0 TX buffer full, 1 RX buffer full                    |
//! | 0x008  | CTRL      | 0 TX enable, 1 RX enable, 2 TX interrupt, 3 RX interrupt |
//! | 0x00C  | INTSTATUS | 0 TX, 1 RX (write 1 to clear)                         |
//! | 0x010  | BAUDDIV   | ≥ 16 (QEMU does not model the baud rate)              |
//!
//! The UART holds one byte each way: QEMU delivers the next received byte only after DATA was
//! read (no byte is lost, the sender waits), and a byte written while the TX buffer is full is
//! dropped, so [`Uart0::write`] checks first. Its interrupts are NVIC lines 0 (RX) and 1 (TX);
//! [`Uart0::clear_interrupts`] acknowledges both (the image's handler only wakes the main loop).

const BASE: usize = 0x4000_4000;
const DATA: usize = BASE;
const STATE: usize = BASE + 0x004;
const CTRL: usize = BASE + 0x008;
const INTSTATUS: usize = BASE + 0x00C;
const BAUDDIV: usize = BASE + 0x010;

const STATE_TX_FULL: u32 = 1 << 0;
const STATE_RX_FULL: u32 = 1 << 1;
const CTRL_TX_RX_AND_INTERRUPTS: u32 = 0b1111;

/// NVIC line of UART0's receive interrupt.
pub const RX_IRQ: u16 = 0;
/// NVIC line of UART0's transmit interrupt.
pub const TX_IRQ: u16 = 1;

#[allow(unsafe_code)]
fn read(register: usize) -> u32 {
    // SAFETY: `register` is one of the UART0 registers above, a 32-bit aligned MMIO address that
    // mps2-an386 always maps; reading it has no side effect besides the UART's own.
    unsafe { core::ptr::read_volatile(register as *const u32) }
}

#[allow(unsafe_code)]
fn write(register: usize, value: u32) {
    // SAFETY: as in `read`; only this module touches UART0, and the image is single-threaded
    // (the interrupt handler only writes INTSTATUS, whose bits are write-1-to-clear).
    unsafe { core::ptr::write_volatile(register as *mut u32, value) }
}

/// UART0, enabled both ways with its interrupts.
#[derive(Debug)]
pub struct Uart0(());

impl Uart0 {
    /// Enables transmit, receive and both interrupts (the NVIC lines are the caller's).
    pub fn init() -> Self {
        write(BAUDDIV, 16);
        write(CTRL, CTRL_TX_RX_AND_INTERRUPTS);
        Self(())
    }

    /// The received byte, if one is waiting.
    pub fn read(&mut self) -> Option<u8> {
        (read(STATE) & STATE_RX_FULL != 0).then(|| read(DATA) as u8)
    }

    /// Sends `byte` if the TX buffer has room; false if it has not (try again later).
    pub fn write(&mut self, byte: u8) -> bool {
        if read(STATE) & STATE_TX_FULL != 0 {
            return false;
        }
        write(DATA, u32::from(byte));
        true
    }

    /// Acknowledges the TX and RX interrupts (from the interrupt handler).
    pub fn clear_interrupts() {
        write(INTSTATUS, 0b11);
    }
}
