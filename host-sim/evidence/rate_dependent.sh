#!/usr/bin/env bash
# Evidence for rate-dependent hysteresis across records: host-sim's xy-stage (x axis) with the
# stacks' dielectric lag (dielectric-lag:tau, the Bouc-Wen operator driven by a first-order lag of
# the voltage; the fits are not told of it), driven by rising-amplitude raised sines 0-120 V at
# 20, 40 and 100 Hz (0.5 s at 10 kHz, 2 nm noise unless NOISE_RMS_M says otherwise, sensor offsets
# 0, +2.5 and -1.5 um). For each rate left out, `identify` (symmetric) and `close-loop` are fitted
# on the two other records together (--free-offset) and the stage file predicts the third from
# rest, its offset re-estimated (`predict --free-offset`, zeroed RMS). Prints fit RMS, prediction
# RMS, their ratio, and the effects close-loop added with their forms.
# EFFECT replaces the dielectric lag by another undeclared rate dependence, e.g.
# EFFECT=rate-bouc-wen:rate=1e5 (the operator's gain growing with the input's speed); several
# specs separated by spaces act together, e.g. EFFECT="dielectric-lag:tau=1e-3 rate-bouc-wen:rate=1e5".
# PLANT=stage runs the same on the asymmetric stage of seed 001 (raised sines 0-20 V, its u_V
# and y_m columns) instead of the XY stage's x axis, without --invertible: that stage's own map
# folds (dy/du changes sign over its reachable states), so no compensator inverts it and its
# sets are judged by their fits alone (close-loop then says the stage file would be refused).
# Usage (from the repository root):
#   [EFFECT=SPEC] [PLANT=xy-stage|stage] bash host-sim/evidence/rate_dependent.sh [OUT_DIR] [TAU_S] [NOISE_RMS_M]
set -euo pipefail
OUT=${1:-out/rate-dependent}
TAU=${2:-1e-3}
NOISE=${3:-2e-9}
EFFECT=${EFFECT:-dielectric-lag:tau=$TAU}
PLANT=${PLANT:-xy-stage}
case $PLANT in
  xy-stage) AMP=60; U=ux_V; Y=x_m; INV=--invertible;;
  stage) AMP=10; U=u_V; Y=y_m; INV=;;
  *) echo "PLANT must be xy-stage or stage, not $PLANT" >&2; exit 2;;
esac
# Without --invertible a set the firmware would refuse ends a fit with exit status 1, its report
# and stage file written with the verdict: that is the expected end there, and only there.
refused_ok() { [ -z "$INV" ]; }
effects=()
for e in $EFFECT; do effects+=(--effect "$e"); done
mkdir -p "$OUT"
cargo build --release -p host-sim -q
B=${CARGO_TARGET_DIR:-target}/release/host-sim
offset() { case $1 in 20) echo 0;; 40) echo 2.5e-6;; 100) echo -1.5e-6;; esac; }
for f in 20 40 100; do
  $B simulate --plant "$PLANT" \
    --signal "rising-sine:amp=$AMP,offset=0,freq=$f,phase_deg=-90,raised=1,duration=0.5,rate=10000" \
    "${effects[@]}" --effect "noise:rms_m=$NOISE,seed=$f" --out "$OUT/raw$f.csv" >/dev/null
  # The sensor's zero moved between sessions: a constant offset per record.
  python3 "$(dirname "$0")/sensor_offset.py" "$OUT/raw$f.csv" "$OUT/r$f.csv" "$(offset $f)"
done
for held in 20 40 100; do
  fit=""
  for f in 20 40 100; do
    if [ "$f" != "$held" ]; then fit="$fit${fit:+,}$OUT/r$f.csv"; fi
  done
  $B identify --data "$fit" --free-offset --u $U --y $Y --model symmetric $INV \
    --out "$OUT/identify-$held.toml" --report "$OUT/identify-$held.json" >/dev/null 2>&1 || refused_ok
  $B close-loop --data "$fit" --free-offset --u $U --y $Y $INV \
    --report "$OUT/close-loop-$held.json" --out "$OUT/close-loop-$held.toml" >/dev/null 2>&1 || refused_ok
  for m in identify close-loop; do
    $B predict --params "$OUT/$m-$held.toml" --data "$OUT/r$held.csv" --u $U --y $Y \
      --free-offset --report "$OUT/predict-$m-$held.json" >/dev/null 2>&1
  done
done
python3 - "$OUT" <<'PY'
import json, sys
out = sys.argv[1]
print("| left out | model | effects added | fit RMS [um] | prediction RMS, offset re-estimated [um] | ratio |")
print("|---|---|---|---|---|---|")
for held in (20, 40, 100):
    ident = json.load(open(f"{out}/identify-{held}.json"))
    cl = json.load(open(f"{out}/close-loop-{held}.json"))
    added = [f"{s['effect']} ({s['form']})" if s.get("form") else s["effect"]
             for s in cl["steps"] if s.get("outcome") == "added"]
    rows = [("identify symmetric", "-", ident["fit"]["rms"]),
            ("close-loop", ", ".join(added) or "none", cl["after"]["rms"])]
    for (name, added, fit), m in zip(rows, ("identify", "close-loop")):
        pred = json.load(open(f"{out}/predict-{m}-{held}.json"))["rms_zeroed_m"][0]
        print(f"| {held} Hz | {name} | {added} | {fit*1e6:.3f} | {pred*1e6:.3f} | {pred/fit:.2f} |")
PY
