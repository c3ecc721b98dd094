#!/usr/bin/env bash
# Runs the emulated board image (feature `board-emu`, src/bin/board_emu.rs) on QEMU's
# netduinoplus2 (STM32F405), its command link (USART1, the first -serial) served on
# 127.0.0.1:PORT (one host at a time, reconnects allowed), until a `shutdown` request (exit 0,
# after a semihosting line with the deadline figures and TIM2's measured rate) or QEMU_TIMEOUT
# seconds (default none; exit 124).
#
# -icount "shift=${QEMU_ICOUNT_SHIFT:-3},sleep=off": QEMU's virtual clock advances 2^3 = 8 ns per guest instruction
# (125 M instructions per virtual second, about 1.3 core cycles each at the 168 MHz the image
# assumes) and jumps ahead while the core sleeps. TIM2, SysTick and so the deadline monitor run
# on that clock, so a tick's cost and its deadline are the image's own instruction counts, not
# the host's load; the emulation itself runs as fast as the host allows (slower or faster than
# real time). QEMU_ICOUNT_SHIFT sets another shift (2: 4 ns per instruction).
#
# usage: run-board-emu.sh --link PORT FIRMWARE.elf
set -euo pipefail
if [[ ${1:-} != --link ]]; then
  echo "usage: run-board-emu.sh --link PORT FIRMWARE.elf" >&2
  exit 2
fi
port=${2:?usage: run-board-emu.sh --link PORT FIRMWARE.elf}
elf=${3:?usage: run-board-emu.sh --link PORT FIRMWARE.elf}
exec timeout "${QEMU_TIMEOUT:-0}" qemu-system-arm -machine netduinoplus2 -nographic \
  -monitor none -serial "tcp:127.0.0.1:$port,server=on,wait=off,nodelay=on" \
  -icount "shift=${QEMU_ICOUNT_SHIFT:-3},sleep=off" -semihosting-config enable=on,target=native -kernel "$elf"
