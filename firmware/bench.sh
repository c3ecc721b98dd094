#!/usr/bin/env bash
# Instructions per axis-step of the compensator + safety guard, and per two-axis loop tick,
# counted exactly under QEMU (mps2-an386, Cortex-M4F) with the shared qemu-insn-count tool on the
# `check` image (src/bin/check.rs):
#   window 0: BENCH_STEPS two-axis steps of Compensator::compensate + SafetyLimits::apply, n = 1
#             (the parameter file's set); the references are computed before the window, the
#             two axes are written out (no axis-index loop), so only compensator + guard are counted
#   window 1: the same with n = GENERAL_N (general-n RK4 path of the core)
#   window 2: BENCH_TICKS full ticks of TwoAxisLoop::tick (sensor, compensator, guard, DAC code,
#             frame) plus the simulated stage's DAC/ADC and its Euler step
#   window 3: BENCH_STEPS two-axis steps of compensator + Servo::step (feedforward + feedback) +
#             guard, n = 1: the servo's cost per axis-step is window 3 − window 0
#   window 4: BENCH_TICKS whole control ticks without the simulated stage (the ADC replays
#             recorded readings, the DAC keeps codes), feedforward
#   window 5: the same, feedforward + feedback
#   window 6: empty (marker overhead, subtracted)
#   windows 7 .. 6 + WORST_TICKS: one feedforward + feedback tick each, from rest: the
#             largest is the tick's worst case, stated against the stage file's loop period at
#             168 MHz (instructions, not cycles: the board's DWT counter gives cycles, see
#             firmware/README.md), and as a share of a 20 kHz and a 50 kHz period; with it the
#             converters' SPI frames inside a tick (two 32-bit ADS8681 reads and two 24-bit
#             DAC8563 writes at the board's 21 MHz SPI clock, src/board/discovery.rs: 5.33 µs
#             in all, from the datasheets' frame formats, not measured on a board) and the time
#             a period leaves after both
#   then STAGE_WINDOWS windows: the stages of a feedforward + feedback tick one by one, each over
#             BENCH_TICKS ticks with the inputs of the same run (check.rs `stage_windows`); what
#             the whole tick (window 5) costs beyond their sum is its bookkeeping
# Then the converter time that still lies inside the board's tick (src/converter_timing.rs, from
# the ADS8681/DAC8563 datasheets and the SPI clocks: QEMU's converters are simulated), and the
# worst tick with it as a share of a 20 kHz and a 50 kHz period.
# Not cycles: see the tool's README. Needs qemu-system-arm, gcc, nm.
# usage: firmware/bench.sh   (COUNT_SH=path/to/count.sh to override the tool's location)
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
cd "$here"
count_sh=${COUNT_SH:-$here/../../shared/tools/qemu-insn-count/count.sh}
[[ -f $count_sh ]] || { echo "bench.sh: count.sh not found at $count_sh (set COUNT_SH)" >&2; exit 2; }
const() { sed -n "s/^ *pub const $1: [a-z0-9]* = \([0-9_.]*\);/\1/p" src/bin/check.rs | tr -d _; }
steps=$(const BENCH_STEPS) ticks=$(const BENCH_TICKS) general_n=$(const GENERAL_N)
worst_ticks=$(const WORST_TICKS) stage_windows=$(const STAGE_WINDOWS)
timing() { sed -n "s/^pub const $1: u32 = \([0-9_]*\);/\1/p" src/converter_timing.rs | tr -d _; }
conv=$(timing CONVERTER_CYCLES_IN_TICK) conv_blocking=$(timing CONVERTER_CYCLES_IN_TICK_BLOCKING)
[[ -n $conv && -n $conv_blocking ]] || { echo "bench.sh: converter cycles not found in src/converter_timing.rs" >&2; exit 1; }
rate=$(sed -n 's/^loop_rate_hz = \([0-9.e]*\).*/\1/p' "${PIEZO_PARAMS:-params/xy-stage.toml}" | head -1)
cargo build --release --features qemu --bin check
elf=${CARGO_TARGET_DIR:-$here/../target}/thumbv7em-none-eabihf/release/check
lines=$(bash "$count_sh" "$elf")
echo "$lines" | head -8
win() { awk -v w="$1" '$2 == "window" && $3 == w {sub("insns=", "", $4); print $4}' <<<"$lines"; }
n1=$(win 0) nx=$(win 1) loop=$(win 2) servo=$(win 3) ff=$(win 4) both=$(win 5) empty=$(win 6)
[[ -n $n1 && -n $nx && -n $loop && -n $servo && -n $ff && -n $both && -n $empty ]] \
  || { echo "bench.sh: expected at least 7 windows" >&2; exit 1; }
last_worst=$((7 + worst_ticks - 1))
worst=$(awk -v last="$last_worst" '$2 == "window" && $3 >= 7 && $3 <= last {sub("insns=", "", $4); if ($4 > m) m = $4} END {print m}' <<<"$lines")
[[ $(win $((last_worst + stage_windows))) ]] \
  || { echo "bench.sh: expected $((last_worst + stage_windows + 1)) windows" >&2; exit 1; }
stages=$(for k in $(seq 1 "$stage_windows"); do win $((last_worst + k)); done | tr '\n' ' ')
awk -v stages="$stages" -v wt="$worst_ticks" -v a="$n1" -v b="$nx" -v c="$loop" -v sv="$servo" -v f="$ff" -v fb="$both" -v w="$worst" \
    -v e="$empty" -v cv="$conv" -v cvb="$conv_blocking" -v s="$steps" -v t="$ticks" -v n="$general_n" -v rate="$rate" 'BEGIN {
  printf "instructions per axis-step (n = 1, compensator + safety guard): %.1f\n", (a - e) / (2 * s)
  printf "instructions per axis-step (n = %s, compensator + safety guard): %.1f\n", n, (b - e) / (2 * s)
  printf "instructions per axis-step (n = 1, compensator + servo + safety guard): %.1f (servo: %.1f)\n", (sv - e) / (2 * s), (sv - a) / (2 * s)
  printf "instructions per two-axis loop tick (n = 1, incl. simulated stage): %.1f\n", (c - e) / t
  printf "instructions per whole control tick without the stage, feedforward: %.1f\n", (f - e) / t
  printf "instructions per whole control tick without the stage, feedforward + feedback: %.1f\n", (fb - e) / t
  budget = 168e6 / rate
  printf "worst feedforward + feedback tick of %d from rest: %d instructions = %.1f %% of the %d cycles one period of %s Hz has at 168 MHz\n", wt, w - e, 100 * (w - e) / budget, budget, rate
  printf "  the same as a share of one period at 168 MHz: %.1f %% at 20 kHz (8400 cycles), %.1f %% at 50 kHz (3360 cycles)\n", 100 * (w - e) / 8400, 100 * (w - e) / 3360
  printf "converter time still inside the tick on the board (src/converter_timing.rs): %d cycles = %.2f us (both ADC frames at once, DAC frames by DMA; %d cycles = %.2f us with blocking transfers)\n", cv, cv / 168, cvb, cvb / 168
  printf "  worst tick + converter time: %d = %.1f %% of the period at %s Hz, %.1f %% at 20 kHz, %.1f %% at 50 kHz\n", w - e + cv, 100 * (w - e + cv) / budget, rate, 100 * (w - e + cv) / 8400, 100 * (w - e + cv) / 3360
  split(stages, g, " ")
  name[1] = "reference generator"; name[2] = "inverse effect chain: targets"; name[3] = "sensor reads"
  name[4] = "compensators"; name[5] = "servos"; name[6] = "models advanced by the applied voltage"
  name[7] = "guards"; name[8] = "DAC codes"; name[9] = "inverse effect chain: commit"; name[10] = "frame"
  printf "feedforward + feedback tick by stage (instructions per tick, both axes, %d ticks each):\n", t
  total = 0
  for (k = 1; k <= 10; k++) {
    v = (g[k] - e) / t
    if (k == 2) v = (g[2] - g[1]) / t
    total += v
    printf "  %-40s %8.1f\n", name[k], v
  }
  printf "  %-40s %8.1f\n", "sum of the stages", total
  printf "  %-40s %8.1f\n", "rest of the tick (checks, counters, copies)", (fb - e) / t - total
}'
