#!/usr/bin/env bash
# Evidence for `host-sim identify` (issue 5): reruns every fit whose figures the README quotes and
# prints the tables. Usage (from the repository root): bash host-sim/evidence/identify.sh [OUT_DIR]
# Needs python3 for the tables only. Measured data are read in place from ../shared/data.
set -euo pipefail
OUT=${1:-out/identify}
DATA=${DATA:-../shared/data}
mkdir -p "$OUT"
cargo build --release -p host-sim -q
B=${CARGO_TARGET_DIR:-target}/release/host-sim
SIG="sine:amp=10,offset=10,freq=2,phase_deg=-90,duration=1,rate=10000"   # seed 001: 10 - 10 cos(4 pi t), N = 10 000

# 1. Seed 001's stage (host-sim's f64 plant), Cases I-III, 10 nm white sensor noise.
for c in 1 2 3; do
  plant=stage-case$c; [ $c = 3 ] && plant=stage
  $B simulate --plant $plant --signal "$SIG" --effect noise:rms_m=1e-8,seed=1 --out "$OUT/stage$c.csv" >/dev/null
  case $c in 1) m="--model symmetric";; 2) m="--model asymmetric --no-shift";; 3) m="--model asymmetric";; esac
  for method in vp-de-lm ga; do
    $B identify --data "$OUT/stage$c.csv" $m --method $method --seed 1 \
      --out "$OUT/stage$c-$method.toml" --report "$OUT/stage$c-$method.json" | cut -c1-110
  done
done
# Recovery for several seeds of the noise and of the method.
for s in 2 3 4 5; do
  $B simulate --plant stage-case1 --signal "$SIG" --effect noise:rms_m=1e-8,seed=$s --out "$OUT/stage1-n$s.csv" >/dev/null
  $B identify --data "$OUT/stage1-n$s.csv" --model symmetric --seed $s \
    --out "$OUT/stage1-n$s.toml" --report "$OUT/stage1-n$s.json" | cut -c1-110
done

# 2. Measured data: fit on a window, validate on the rest (predict sees only u).
P885="$DATA/piezo_P885_yan9a/identification_1Hz_sine.csv"
SH="$DATA/piezo_smarthysteresis/piezo_150V_1Hz.csv"
$B identify --data "$P885" --model symmetric --start 2 --end 20 --out "$OUT/p885.toml" --report "$OUT/p885.json" | cut -c1-110
$B predict --params "$OUT/p885.toml" --data "$P885" --start 20 --report "$OUT/p885-predict.json"
$B identify --data "$P885" --model symmetric --invertible --start 2 --end 20 --out "$OUT/p885-inv.toml" --report "$OUT/p885-inv.json" | cut -c1-110
$B predict --params "$OUT/p885-inv.toml" --data "$P885" --start 20 --report "$OUT/p885-inv-predict.json"
$B identify --data "$SH" --model symmetric --start 4.5 --end 7.5 --out "$OUT/sh.toml" --report "$OUT/sh.json" | cut -c1-110
$B predict --params "$OUT/sh.toml" --data "$SH" --start 7.5 --report "$OUT/sh-predict.json"
$B identify --data "$SH" --model symmetric --invertible --start 4.5 --end 7.5 --out "$OUT/sh-inv.toml" --report "$OUT/sh-inv.json" | cut -c1-110
$B predict --params "$OUT/sh-inv.toml" --data "$SH" --start 7.5 --report "$OUT/sh-inv-predict.json"

# 3. The Bouc-Wen benchmark: identify on a training file only, then simulate the test multisine
#    (one steady-state period: three periods of its input first, unscored).
BW="$DATA/boucwen_benchmark"
$B identify --data "$BW/train_multisine_forgione.csv" --model oscillator --out "$OUT/bw-forgione.toml" --report "$OUT/bw-forgione.json" | cut -c1-110
$B predict --params "$OUT/bw-forgione.toml" --data "$BW/test_multisine.csv" --periodic-warmup 3 --report "$OUT/bw-forgione-test.json"
# The EHH file's first period (8192 samples, 10.92 s) holds a start-up transient: simulated, not scored.
$B identify --data "$BW/train_multisine_ehh.csv" --model oscillator --start 10.93 --out "$OUT/bw-ehh.toml" --report "$OUT/bw-ehh.json" | cut -c1-110
$B predict --params "$OUT/bw-ehh.toml" --data "$BW/test_multisine.csv" --periodic-warmup 3 --report "$OUT/bw-ehh-test.json"

python3 - "$OUT" <<'PY'
import json, sys
out = sys.argv[1]
J = lambda f: json.load(open(f"{out}/{f}"))
print("\n## Stage plant, Cases I-III (10 nm noise; fitness = RMS)")
print("| case | method | fitness (AFV) [nm] | RAE [nm] | evaluations | seconds |")
print("|---|---|---|---|---|---|")
for c in (1, 2, 3):
    for m in ("vp-de-lm", "ga"):
        s = J(f"stage{c}-{m}.json"); f = s["fit"]
        print(f"| {'I'*c if c<3 else 'III'} | {m} | {f['rms']*1e9:.3f} | [{f['rae_min']*1e9:.1f}, {f['rae_max']*1e9:.1f}] | {s['evaluations']} | {s['seconds']:.2f} |")
print("\n## Recovery, stage Case I, symmetric, vp-de-lm (truth normalised to A = 1)")
a, b, g, n, k1, k2 = -7.02182e-2, 4.45753, 3.49259, 3.05869, -3.51711e-7, -1.94566e-6
sc = abs(a) ** (n - 1)
truth = {"beta": b * sc, "gamma": -g * sc, "n": n, "k1": k1, "k2": k2 * a}
print("| noise seed | RMS / noise floor | beta err % | gamma err % | n err % | k1 err % | k2 err % | seconds |")
print("|---|---|---|---|---|---|---|---|")
for name, seed in [("stage1-vp-de-lm.json", 1)] + [(f"stage1-n{s}.json", s) for s in (2, 3, 4, 5)]:
    s = J(name); p = s["params"]; bw = p["bouc_wen"]; mp = p["static_map"]
    got = {"beta": bw["beta"], "gamma": bw["gamma"], "n": bw["n"], "k1": mp["k1_m_per_v"], "k2": mp["k2_m_per_h"]}
    e = {k: 100 * (got[k] - truth[k]) / truth[k] for k in truth}
    print(f"| {seed} | {s['fit']['rms']/1e-8:.4f} | {e['beta']:+.2f} | {e['gamma']:+.2f} | {e['n']:+.3f} | {e['k1']:+.3f} | {e['k2']:+.2f} | {s['seconds']:.2f} |")
print("\n## Measured data (symmetric model; fit window, then predict on the rest)")
print("| data | constraint | fit window | fit RMS [um] | fit R2 | validation window | RMS [um] | R2 | MRD % |")
print("|---|---|---|---|---|---|---|---|---|")
for d, fw, vw in (("p885", "2-20 s", "20 s-end"), ("sh", "4.5-7.5 s", "7.5 s-end")):
    for c, suffix in (("none", ""), ("--invertible", "-inv")):
        s = J(f"{d}{suffix}.json"); p = J(f"{d}{suffix}-predict.json")
        print(f"| {d} | {c} | {fw} | {s['fit']['rms']*1e6:.4f} | {s['fit']['r2']:.6f} | {vw} | {p['fit']['rms']*1e6:.4f} | {p['fit']['r2']:.6f} | {p['fit']['mrd_percent']:.3f} |")
print("\n## Bouc-Wen benchmark (oscillator; test = simulation RMS on test_multisine.csv)")
print("| training file | training RMS [m] | test RMS [m] | test R2 | evaluations | seconds |")
print("|---|---|---|---|---|---|")
for name in ("forgione", "ehh"):
    s = J(f"bw-{name}.json"); p = J(f"bw-{name}-test.json")
    print(f"| {name} | {s['fit']['rms']:.4e} | {p['fit']['rms']:.4e} | {p['fit']['r2']:.9f} | {s['evaluations']} | {s['seconds']:.1f} |")
PY
