#!/usr/bin/env bash
# Firmware CI: builds the QEMU image, runs it under QEMU (mps2-an386) with a timeout, fails on a
# non-zero exit (the self-check, then the servo table of the four control modes); runs the check
# image (bench windows) likewise; checks that no panic path is
# reachable in the check image (panic handler -> undefined symbol; surviving sites listed by
# panic-sites.sh must be in panic-sites.allowed); runs clippy on the images for the target;
# builds the STM32F407 board image (RTIC 2: checks its TIM2 and OTG_FS handlers) and its
# emulated variant for QEMU netduinoplus2 (board-emu: TIM2 and USART1 handlers); prints image
# sizes. (The emulated board's link session runs in `cargo test`: tests/tests/board_emu.rs.) Installs nothing: it checks prerequisites and says what is missing.
#
# Prerequisites (what .ci/run installs):
#   rustup target add thumbv7em-none-eabihf
#   apt-get install -y --no-install-recommends qemu-system-arm binutils
#
# usage: firmware/ci.sh            (from anywhere; honours CARGO_TARGET_DIR, QEMU_TIMEOUT)
#   SKIP_BOARD=1 firmware/ci.sh    skips the board image and its emulated variant (stm32f4xx-hal:
#                                  ~25 s cold build)
#
# The host side of this crate (library tests, clippy --all-targets) runs in the workspace's
# `cargo test` / `cargo clippy` at the root; the images are feature-gated and target-only.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
cd "$here"
target=thumbv7em-none-eabihf

missing=0
if ! rustup target list --installed 2>/dev/null | grep -qx "$target"; then
  echo "ci.sh: Rust target $target is not installed: rustup target add $target" >&2
  missing=1
fi
if ! command -v qemu-system-arm >/dev/null; then
  echo "ci.sh: qemu-system-arm not found: apt-get install -y --no-install-recommends qemu-system-arm" >&2
  missing=1
fi
for tool in size nm; do
  if ! command -v $tool >/dev/null; then
    echo "ci.sh: '$tool' not found (binutils): apt-get install -y --no-install-recommends binutils" >&2
    missing=1
  fi
done
[[ $missing == 0 ]] || exit 2

target_dir=${CARGO_TARGET_DIR:-$(cd .. && pwd)/target}
out=$target_dir/$target/release

echo "== firmware: clippy (target $target, features qemu, board, board-emu)"
cargo clippy --release --features qemu --lib --bins -- -D warnings
cargo clippy --release --features panic-never --bin check -- -D warnings
cargo clippy --release --features board --lib --bins -- -D warnings
cargo clippy --release --features board-emu --lib --bin board-emu -- -D warnings

echo "== firmware: QEMU image (mps2-an386) and check image"
cargo build --release --features qemu --bin qemu --bin check
if ! readelf -S "$out/qemu" | grep -q '\.vector_table.* 00000000 '; then
  echo "ci.sh: the qemu image is not linked at 0x00000000 (wrong memory.x?)" >&2
  exit 1
fi
size "$out/qemu"
status=0
"$here/run-qemu.sh" "$out/qemu" || status=$?
if [[ $status != 0 ]]; then
  [[ $status == 124 ]] && echo "ci.sh: QEMU timed out after ${QEMU_TIMEOUT:-60} s" >&2
  echo "ci.sh: QEMU image FAILED (exit $status)" >&2
  exit 1
fi
echo "ci.sh: QEMU image passed"
status=0
"$here/run-qemu.sh" --servo-table "$out/qemu" || status=$?
[[ $status == 0 ]] || { echo "ci.sh: QEMU servo table FAILED (exit $status)" >&2; exit 1; }
echo "ci.sh: QEMU servo table passed"
size "$out/check"
status=0
"$here/run-qemu.sh" "$out/check" || status=$?
[[ $status == 0 ]] || { echo "ci.sh: check image FAILED under QEMU (exit $status)" >&2; exit 1; }

echo "== firmware: no panic reachable (check image, panic handler -> undefined symbol)"
# Attribute first (on the image without the trap), then try to link the trap.
sites=""
if command -v llvm-objdump >/dev/null; then
  sites=$("$here/panic-sites.sh" "$out/check")
fi
log=$(mktemp)
if cargo build --release --features panic-never --bin check 2>"$log"; then
  echo "ci.sh: no panic path reachable in the check image (boot, loop, compensator n = 1 and 1.5)"
else
  if ! grep -q loop_code_reached_a_panic_path "$log"; then
    cat "$log" >&2
    echo "ci.sh: check image (panic-never) failed to build" >&2
    exit 1
  fi
  if ! command -v llvm-objdump >/dev/null; then
    echo "ci.sh: WARNING: panic paths are reachable in the check image and llvm-objdump is missing," >&2
    echo "ci.sh: WARNING: so they cannot be attributed (apt-get install llvm); not failing on it" >&2
  else
    echo "panic sites surviving optimisation (file:line, std function, caller):"
    echo "$sites" | sed 's/^/  /'
    allowed=$(grep -v '^#' "$here/panic-sites.allowed" | sed '/^$/d')
    unexpected=$(echo "$sites" | awk -F'\t' -v allowed="$allowed" '
      BEGIN { n = split(allowed, a, "\n"); for (i = 1; i <= n; i++) ok[a[i]] = 1 }
      { f = $1; sub(/:[0-9?]+$/, "", f); if (!(f in ok)) print }')
    if [[ -n $unexpected ]]; then
      echo "ci.sh: panic sites outside firmware/panic-sites.allowed:" >&2
      echo "$unexpected" >&2
      exit 1
    fi
    echo "ci.sh: all reachable panic sites are the known ones in core/ (panic-sites.allowed)"
  fi
fi
rm -f "$log"

if [[ ${SKIP_BOARD:-0} == 1 ]]; then
  echo "== firmware: board image skipped (SKIP_BOARD=1)"
else
  echo "== firmware: board image (STM32F407)"
  cargo build --release --features board --bin board
  if ! readelf -S "$out/board" | grep -q '\.vector_table.* 08000000 '; then
    echo "ci.sh: the board image is not linked at 0x08000000 (wrong memory.x?)" >&2
    exit 1
  fi
  # The RTIC tasks are bound to their interrupts: the control tick to TIM2, the link to OTG_FS,
  # the end of a DAC frame sent by DMA to DMA1_STREAM3 (SPI2 RX).
  symbols=$(nm "$out/board")
  for handler in TIM2 OTG_FS DMA1_STREAM3; do
    if ! grep -q " T $handler\$" <<<"$symbols"; then
      echo "ci.sh: the board image has no $handler handler (RTIC task binding lost)" >&2
      exit 1
    fi
  done
  size "$out/board"

  echo "== firmware: board image under emulation (QEMU netduinoplus2, board-emu)"
  cargo build --release --features board-emu --bin board-emu
  if ! readelf -S "$out/board-emu" | grep -q '\.vector_table.* 08000000 '; then
    echo "ci.sh: the board-emu image is not linked at 0x08000000 (wrong memory.x?)" >&2
    exit 1
  fi
  # The same RTIC application: the control tick on TIM2, the link on USART1.
  symbols=$(nm "$out/board-emu")
  for handler in TIM2 USART1; do
    if ! grep -q " T $handler\$" <<<"$symbols"; then
      echo "ci.sh: the board-emu image has no $handler handler (RTIC task binding lost)" >&2
      exit 1
    fi
  done
  size "$out/board-emu"
fi
echo "ci.sh: firmware OK (QEMU self-check passed, images built)"
