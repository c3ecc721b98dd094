#!/usr/bin/env bash
# Evidence for `host-sim close-loop`: the measured-data table of the README's close-loop section.
# Usage (from the repository root): bash host-sim/evidence/close-loop.sh [OUT_DIR]
# Each record is fitted on one window and validated on the rest (both models predict it from the
# record's first sample, seeing only u, through piezo-stage's chain; scored from --validate-start):
# `rms` is the plain RMS, `rms_zeroed` the RMS with one constant offset re-estimated on the scored
# window. `held-out` is the blocked cross-validation RMS inside the fit window. --invertible: the
# base set must be one the firmware's compensator accepts. Needs python3 for the table.
set -euo pipefail
OUT=${1:-out/close-loop}
DATA=${DATA:-../shared/data}
mkdir -p "$OUT"
cargo build --release -p host-sim -q
B=${CARGO_TARGET_DIR:-target}/release/host-sim
P885="$DATA/piezo_P885_yan9a/identification_1Hz_sine.csv"
SH="$DATA/piezo_smarthysteresis/piezo_150V_1Hz.csv"
# P-885: the first second is the start-up transient (warm-up, unscored); fit 1-20 s, validate 20-40 s.
$B close-loop --data "$P885" --u u_ctrl_V --y y_um --start 1 --end 20 --invertible \
  --validate "$P885" --validate-start 20 --report "$OUT/p885.json" --plots "$OUT/p885"
# P-885, the whole record (1-40 s) fitted; held-out figures from the cross-validation only.
$B close-loop --data "$P885" --u u_ctrl_V --y y_um --start 1 --invertible \
  --report "$OUT/p885-all.json" --plots "$OUT/p885-all"
# SmartHysteresis: the sine starts at 0.5 s and its first cycles settle; fit 4.5-7.5 s, validate 7.5-10 s.
# Its ±150 V get a placeholder io chain that drives them (bipolar DAC span, 30 V/V): not one the
# firmware's DAC8563 drives, so the stage file needs the real [io] (--stage) before it builds.
$B close-loop --data "$SH" --start 4.5 --end 7.5 --invertible \
  --validate "$SH" --validate-start 7.5 --report "$OUT/sh.json" --plots "$OUT/sh"
python3 - "$OUT" <<'PY'
import json, sys
out = sys.argv[1]
print("\n| data | fit window | effects added (in order) | noise estimate [um] | fit RMS before [um] | after [um] | held-out before [um] | after [um] | validation window | rms before [um] | after [um] | rms_zeroed before [um] | after [um] |")
print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
for name, fw, vw in (("p885", "1-20 s", "20-40 s"), ("p885-all", "1-40 s", "-"), ("sh", "4.5-7.5 s", "7.5-10 s")):
    r = json.load(open(f"{out}/{name}.json"))
    a = r["axes"][0]
    um = lambda v: f"{v * 1e6:.4f}"
    added = ", ".join(e["effect"] + (f" ({e['form']})" if e["form"] else "") for e in a["effects_added"]) or "nothing"
    row = [name, fw, added, um(a["noise_estimate_m"]), um(r["before"]["rms"]), um(r["after"]["rms"]),
           um(a["held_out"]["rms_before"]), um(a["held_out"]["rms_after"]), vw]
    v = r.get("validation")
    if v:
        row += [um(v["before"]["rms"]), um(v["after"]["rms"]), um(v["before"]["rms_zeroed"]), um(v["after"]["rms_zeroed"])]
    else:
        row += ["-"] * 4
    print("| " + " | ".join(row) + " |")
PY
