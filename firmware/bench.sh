#!/usr/bin/env bash
# Instructions per loop tick of the QEMU image, counted exactly under QEMU (mps2-an386) with the
# shared qemu-insn-count tool: window 0 = BENCH_TICKS ticks of control::tick on the simulated
# stage (linear feed-forward, guard, DacCode conversion, plant step), window 1 = empty window.
# Not cycles: see the tool's README. Needs qemu-system-arm, gcc, nm.
# usage: firmware/bench.sh   (COUNT_SH=path/to/count.sh to override the tool's location)
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
cd "$here"
count_sh=${COUNT_SH:-$here/../../shared/tools/qemu-insn-count/count.sh}
[[ -f $count_sh ]] || { echo "bench.sh: count.sh not found at $count_sh (set COUNT_SH)" >&2; exit 2; }
bench_ticks=$(sed -n 's/^ *pub const BENCH_TICKS: u32 = \([0-9_]*\);/\1/p' src/bin/qemu.rs | tr -d _)
cargo build --release --features qemu --bin qemu
elf=${CARGO_TARGET_DIR:-$here/../target}/thumbv7em-none-eabihf/release/qemu
lines=$(bash "$count_sh" "$elf")
echo "$lines"
loop=$(awk '/window 0 /{sub("insns=","",$4); print $4}' <<<"$lines")
empty=$(awk '/window 1 /{sub("insns=","",$4); print $4}' <<<"$lines")
awk -v l="$loop" -v e="$empty" -v n="$bench_ticks" \
  'BEGIN { printf "instructions per tick: %.1f (%d ticks)\n", (l - e) / n, n }'
