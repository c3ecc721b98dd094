#!/usr/bin/env bash
# The identified Bouc-Wen benchmark oscillator on the benchmark's test signals: the official test
# multisine, the official sine sweep (read in place from the EHH file in ../shared/data) without and
# with the sweep file's own decimation filter (`predict --output-filter`), and an independent sweep of
# the published system (host-sim/evidence/boucwen_sweep.py, which also shows which decimation the
# official sweep file carries). The model is identified on train_multisine_forgione.csv only.
# Prints one line per signal: test RMS and its ratio to the multisine's.
# Needs python3 with numpy, scipy and numba. Usage (from the repository root):
#   bash host-sim/evidence/boucwen_sweep.sh [OUT_DIR]
set -euo pipefail
OUT=${1:-out/sweep}
BW=../shared/data/boucwen_benchmark
mkdir -p "$OUT"
cargo build --release -p host-sim -q
B=${CARGO_TARGET_DIR:-target}/release/host-sim
$B identify --data "$BW/train_multisine_forgione.csv" --model oscillator --allow-refused \
  --out "$OUT/bw-forgione.toml" --report "$OUT/bw-forgione.json" >/dev/null 2>&1
python3 host-sim/evidence/boucwen_sweep.py "$OUT"
score() { # report name, predict arguments...
  local report=$1
  shift
  $B predict --params "$OUT/bw-forgione.toml" --report "$OUT/$report.json" "$@" >/dev/null 2>&1
  python3 -c "import json,sys; print(json.load(open(sys.argv[1]))['fit']['rms'])" "$OUT/$report.json" >"$OUT/$report.rms"
}
score test-multisine --data "$BW/test_multisine.csv" --periodic-warmup 3
score official-sweep --data "$OUT/sweep_official.csv"
score official-sweep-filtered --data "$OUT/sweep_official.csv" \
  --output-filter fir-decimate:factors=20,identified_with=2/2/5
score reference-sweep --data "$OUT/sweep_reference.csv"
python3 - "$OUT" <<'PY'
import sys
out = sys.argv[1]
rms = lambda name: float(open(f"{out}/{name}.rms").read())
base = rms("test-multisine")
print("\n| test signal | predict option | test RMS [m] | / multisine |")
print("|---|---|---|---|")
for label, name, option in (
        ("official test multisine (decimated 2, 2, 5 like the training data)", "test-multisine", "`--periodic-warmup 3`"),
        ("official sine sweep, read as it is", "official-sweep", "none"),
        ("official sine sweep, its one-stage decimation applied to the prediction", "official-sweep-filtered",
         "`--output-filter fir-decimate:factors=20,identified_with=2/2/5`"),
        ("independent sweep of the published system (not decimated)", "reference-sweep", "none")):
    print(f"| {label} | {option} | {rms(name):.3e} | {rms(name) / base:.2f} |")
PY
