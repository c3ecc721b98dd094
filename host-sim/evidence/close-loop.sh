#!/usr/bin/env bash
# Evidence for `host-sim close-loop` (issue 6): the measured-data before/after table of the README.
# Usage (from the repository root): bash host-sim/evidence/close-loop.sh [OUT_DIR]
# --invertible: the base set must be one the firmware's compensator accepts (the parameter file
# written is then usable by the firmware). Each record is fitted on one window and validated on the rest of the record (both models predict
# it from its first sample, seeing only u; scored from --validate-start). Needs python3 for the table.
set -euo pipefail
OUT=${1:-out/close-loop}
DATA=${DATA:-../shared/data}
mkdir -p "$OUT"
cargo build --release -p host-sim -q
B=${CARGO_TARGET_DIR:-target}/release/host-sim
P885="$DATA/piezo_P885_yan9a/identification_1Hz_sine.csv"
SH="$DATA/piezo_smarthysteresis/piezo_150V_1Hz.csv"
# P-885: the first 2 s are the start-up transient (warm-up, unscored); fit 2-20 s, validate 20-40 s.
$B close-loop --data "$P885" --u u_ctrl_V --y y_um --start 2 --end 20 --invertible \
  --validate "$P885" --validate-start 20 --report "$OUT/p885.json" --plots "$OUT/p885"
# SmartHysteresis: the sine starts at 0.5 s and its first cycles settle; fit 4.5-7.5 s, validate 7.5-10 s.
$B close-loop --data "$SH" --start 4.5 --end 7.5 --invertible \
  --validate "$SH" --validate-start 7.5 --report "$OUT/sh.json" --plots "$OUT/sh"
python3 - "$OUT" <<'PY'
import json, sys
out = sys.argv[1]
print("\n| data | fit window | effects added (in order) | fit RMS before [um] | after [um] | ratio | validation window | RMS before [um] | after [um] | ratio | noise estimate [um] |")
print("|---|---|---|---|---|---|---|---|---|---|---|")
for name, fw, vw in (("p885", "2-20 s", "20-40 s"), ("sh", "4.5-7.5 s", "7.5-10 s")):
    r = json.load(open(f"{out}/{name}.json"))
    b, a = r["before"]["rms"] * 1e6, r["after"]["rms"] * 1e6
    vb, va = r["validation"]["before"]["rms"] * 1e6, r["validation"]["after"]["rms"] * 1e6
    noise = [s["evidence"].get("residual", {}).get("noise_estimate") for s in r["steps"] if s.get("effect") is None]
    noise = noise[-1] * 1e6 if noise and noise[-1] else float("nan")
    steps = [s["effect"] + (" (removed)" if s.get("removed") else "") for s in r["steps"] if s.get("effect") and not s.get("rejected")]
    print(f"| {name} | {fw} | {', '.join(steps)} | {b:.4f} | {a:.4f} | {a/b:.2f} | {vw} | {vb:.4f} | {va:.4f} | {va/vb:.2f} | {noise:.4f} |")
PY
