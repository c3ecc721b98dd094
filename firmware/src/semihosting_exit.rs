//! The emulated images' failure exit (QEMU): the reason on the host's stderr through
//! semihosting, then QEMU exits with failure. The panic and HardFault handlers of the mps2 images
//! `qemu` and `replay` and of `board-emu` are written once, by [`crate::semihosting_fault_handlers`].

use core::fmt::Write as _;

use cortex_m_semihosting::{debug, hio};

/// Prints `what` on the host's stderr (best effort: an error while printing must not stop the
/// exit) and exits QEMU with failure.
pub fn fail(what: core::fmt::Arguments<'_>) -> ! {
    if let Ok(mut err) = hio::hstderr() {
        let _ = err.write_fmt(what);
        let _ = err.write_str("\n");
    }
    debug::exit(debug::EXIT_FAILURE);
    #[allow(clippy::empty_loop)]
    loop {}
}

/// Defines an emulated image's `#[panic_handler]` and its `HardFault` exception, both ending in
/// [`fail`] with the reason after `$prefix` (e.g. `""` or `"board-emu: "`): `panic: …` and
/// `HardFault at pc 0x…`. Used once per image, in a module of the binary (a handler must be
/// defined in the image that links it).
#[macro_export]
macro_rules! semihosting_fault_handlers {
    ($prefix:literal) => {
        #[panic_handler]
        fn panic(info: &core::panic::PanicInfo<'_>) -> ! {
            $crate::semihosting_exit::fail(format_args!(concat!($prefix, "panic: {}"), info))
        }

        #[allow(unsafe_code)] // cortex-m-rt requires HardFault to be an `unsafe fn`.
        #[cortex_m_rt::exception]
        unsafe fn HardFault(frame: &cortex_m_rt::ExceptionFrame) -> ! {
            $crate::semihosting_exit::fail(format_args!(
                concat!($prefix, "HardFault at pc {:#010x}"),
                frame.pc()
            ))
        }
    };
}
