#!/usr/bin/env bash
# Runs a firmware ELF on QEMU's mps2-an386 (Cortex-M4F) with semihosting, with a timeout.
# Exit status: the image's semihosting exit status (0 = PASS), 124 on timeout.
# Used as the cargo runner by `cargo qemu` (alias in .cargo/config.toml) and by ci.sh.
#
# usage: run-qemu.sh FIRMWARE.elf              self-check (QEMU_TIMEOUT seconds, default 60)
#        run-qemu.sh --link PORT FIRMWARE.elf  the qemu image's command link: UART0 served on
#                                              127.0.0.1:PORT (one host at a time, reconnects
#                                              allowed), running until a `shutdown` request
#                                              (QEMU_TIMEOUT seconds if set, default none)
#        run-qemu.sh --servo-table FIRMWARE.elf  the qemu image's servo table (four control
#                                              modes on its simulated stage; QEMU_TIMEOUT,
#                                              default 300 s)
set -euo pipefail
serial=(-serial none)
args=()
timeout_s=${QEMU_TIMEOUT:-60}
if [[ ${1:-} == --link ]]; then
  port=${2:?usage: run-qemu.sh --link PORT FIRMWARE.elf}
  shift 2
  serial=(-serial "tcp:127.0.0.1:$port,server=on,wait=off,nodelay=on")
  args=(,arg=firmware,arg=--link)
  timeout_s=${QEMU_TIMEOUT:-0}
fi
if [[ ${1:-} == --servo-table ]]; then
  shift
  args=(,arg=firmware,arg=--servo-table)
  timeout_s=${QEMU_TIMEOUT:-300}
fi
elf=${1:?usage: run-qemu.sh [--link PORT | --servo-table] FIRMWARE.elf}
exec timeout "$timeout_s" qemu-system-arm -machine mps2-an386 -cpu cortex-m4 -nographic \
  -monitor none "${serial[@]}" -semihosting-config "enable=on,target=native${args[*]:-}" \
  -kernel "$elf"
