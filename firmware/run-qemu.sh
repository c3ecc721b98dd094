#!/usr/bin/env bash
# Runs a firmware ELF on QEMU's mps2-an386 (Cortex-M4F) with semihosting, with a timeout.
# Exit status: the image's semihosting exit status (0 = PASS), 124 on timeout.
# Used as the cargo runner by `cargo qemu` (alias in .cargo/config.toml) and by ci.sh.
# usage: run-qemu.sh FIRMWARE.elf      (QEMU_TIMEOUT seconds, default 60)
set -euo pipefail
elf=${1:?usage: run-qemu.sh FIRMWARE.elf}
exec timeout "${QEMU_TIMEOUT:-60}" qemu-system-arm -machine mps2-an386 -cpu cortex-m4 -nographic \
  -monitor none -serial none -semihosting-config enable=on,target=native -kernel "$elf"
