#!/usr/bin/env bash
# Evidence for close-loop on an actuator whose rate dependence is none of the core's forms, one
# of three piezo-reference plants (PLANT): bipolar-stack (the default: the Bouc-Wen operator driven
# through three dielectric relaxations, 0.2 / 1 / 5 ms, weights 0.4 / 0.35 / 0.25, the linear
# strain following the voltage at once, so its loops narrow with rate) or relaxing-stack (the whole
# strain following the voltage through the drive's 80 us RC lag and relaxations of 0.5 / 2 ms,
# weights 0.06 each, so its loops widen with rate; a cubic strain saturation the core has no form
# for), or relaxing-stack-shaped (the relaxing stack with a second, fast-saturating switching
# population, a rate-independent loop-shape error no core form has: its static fit leaves about
# 1 % of the span, as a measured actuator's does), or relaxing-stack-stiff (the relaxing stack with
# its mode at 7.4 kHz); all with a force-driven mode (740 Hz unless said), zeta 0.03, and a 35 um span, driven by rising-amplitude sines
# +-90 V (bipolar) at 20, 40 and 100 Hz, 0.5 s at 10 kHz unless DURATION_S says otherwise, white
# sensor noise NOISE_RMS_M (1 nm), a sensor offset per record (sessions: 20 Hz 0, 40 Hz +2.5 um,
# 100 Hz session A -1.5 um; 100 Hz session B +3.2 um, rising to 80 V, another noise draw). `close-loop --data
# r20.csv,r40.csv --free-offset --validate r100a.csv` writes the stage file; `predict
# --free-offset` scores both 100 Hz records (offset re-estimated). Prints the fit RMS, each 100 Hz
# record's zeroed prediction RMS and its ratio to the fit RMS, the effects added, and the 100 Hz
# validation record's zeroed RMS before and after the first effect added. With STEPS=1 a third
# fitted record is passed with the sines: voltage steps 0/40/-30/60/-60/20/-80/80/0 V held 50 ms
# each (they ring the mode that the sines barely excite), offset 0. AMP (V, default 90) is the
# final amplitude of the 20 Hz, 40 Hz and session A 100 Hz records (session B stays at 80 V).
# Usage (from the repository root):
#   [STEPS=1] [AMP=V] bash host-sim/evidence/unseen_actuator.sh [OUT_DIR] [NOISE_RMS_M] [DURATION_S] [PLANT]
set -euo pipefail
OUT=${1:-out/unseen-actuator}
NOISE=${2:-1e-9}
DUR=${3:-0.5}
PLANT=${4:-bipolar-stack}
AMP=${AMP:-90}
mkdir -p "$OUT"
cargo build --release -p host-sim -q
B=${CARGO_TARGET_DIR:-target}/release/host-sim
rec() { # name freq offset seed amplitude
  $B simulate --plant "$PLANT" \
    --signal "rising-sine:amp=$5,offset=0,freq=$2,phase_deg=0,raised=0,duration=$DUR,rate=10000" \
    --effect "noise:rms_m=$NOISE,seed=$4" --out "$OUT/raw-$1.csv" >/dev/null
  # The sensor's zero moved between sessions: a constant offset per record.
  python3 "$(dirname "$0")/sensor_offset.py" "$OUT/raw-$1.csv" "$OUT/$1.csv" "$3"
  rm "$OUT/raw-$1.csv"
}
rec r20 20 0 20 "$AMP"
rec r40 40 2.5e-6 40 "$AMP"
rec r100a 100 -1.5e-6 100 "$AMP"
rec r100b 100 3.2e-6 101 80
DATA="$OUT/r20.csv,$OUT/r40.csv"
if [ "${STEPS:-0}" = 1 ]; then
  $B simulate --plant "$PLANT" \
    --signal "steps:levels=0/40/-30/60/-60/20/-80/80/0,hold=0.05,rate=10000" \
    --effect "noise:rms_m=$NOISE,seed=7" --out "$OUT/steps.csv" >/dev/null
  DATA="$DATA,$OUT/steps.csv"
fi
$B close-loop --data "$DATA" --free-offset --validate "$OUT/r100a.csv" \
  --report "$OUT/close-loop.json" --out "$OUT/close-loop.toml" >"$OUT/close-loop.txt" 2>&1 \
  || echo "close-loop exited non-zero (see $OUT/close-loop.txt)"
for r in r100a r100b; do
  $B predict --params "$OUT/close-loop.toml" --data "$OUT/$r.csv" --free-offset \
    --report "$OUT/predict-$r.json" >/dev/null 2>&1 || echo "predict $r failed"
done
python3 - "$OUT" <<'PY'
import json, sys
out = sys.argv[1]
cl = json.load(open(f"{out}/close-loop.json"))
added = [s for s in cl["steps"] if s.get("outcome") == "added"]
names = [f"{s['effect']} ({s['form']})" if s.get("form") else s["effect"] for s in added]
fit = cl["after"]["rms"]
print("| fit RMS [um] | 100 Hz record | prediction RMS, offset re-estimated [um] | ratio | effects added |")
print("|---|---|---|---|---|")
for r in ("r100a", "r100b"):
    p = json.load(open(f"{out}/predict-{r}.json"))["rms_zeroed_m"][0]
    print(f"| {fit*1e6:.4f} | {r} | {p*1e6:.4f} | {p/fit:.2f} | {', '.join(names) or 'none'} |")
if added:
    first = next(c for c in added[0]["candidates"] if c.get("decision") == "added")
    run = first["another_run"]
    before, after = run["rms_zeroed_without"], run["rms_zeroed_with"]
    print(f"first effect added: {names[0]}; r100a zeroed RMS {before*1e6:.4f} -> {after*1e6:.4f} um "
          f"({100*(after/before-1):+.1f} %)")
else:
    print("no effect added")
PY
