#!/usr/bin/env bash
# Identification speed against the Python peer, measured side by side in one run and repeated:
# seed 001's stage (host-sim's f64 plant, Case III), N = 10 000, 10 nm white sensor noise, the
# asymmetric model (8 parameters). The project: the whole `host-sim identify` process (start, CSV read,
# fit, stage file and report written). The peer (host-sim/evidence/peer_identify.py: scipy's
# differential_evolution, numba-jitted objective, the same search box and variable projection): its
# time to reach the project's fitness (RMS within 1 %), in process, after numba's compilation.
# Prints every run and the medians and ratio. Then one SSE evaluation on the same record at the search
# box's midpoint, side by side: the project's from criterion (`cargo bench -p host-sim --bench identify
# -- --quick sse_stage3_N10000`), the peer's objective (median of 200 calls, after compilation).
# Needs python3 with scipy and numba (pip install scipy numba).
# Usage (from the repository root): bash host-sim/evidence/identify_speed.sh [RUNS] [OUT_DIR]
set -euo pipefail
RUNS=${1:-5}
OUT=${2:-out/identify-speed}
mkdir -p "$OUT"
cargo build --release -p host-sim -q
B=${CARGO_TARGET_DIR:-target}/release/host-sim
SIG="sine:amp=10,offset=10,freq=2,phase_deg=-90,duration=1,rate=10000"
$B simulate --plant stage --signal "$SIG" --effect noise:rms_m=1e-8,seed=1 --out "$OUT/stage3.csv" >/dev/null
python3 - "$B" "$OUT" "$RUNS" <<'PY'
import json, statistics, subprocess, sys, time
b, out, runs = sys.argv[1], sys.argv[2], int(sys.argv[3])
data = f"{out}/stage3.csv"
project, peer = [], []
for r in range(runs):
    t0 = time.perf_counter()
    subprocess.run([b, "identify", "--data", data, "--model", "asymmetric", "--seed", "1", "--allow-refused",
                    "--out", f"{out}/stage3.toml", "--report", f"{out}/stage3.json"],
                   check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    seconds = time.perf_counter() - t0
    rms = json.load(open(f"{out}/stage3.json"))["fit"]["rms"]
    p = json.loads(subprocess.run([sys.executable, "host-sim/evidence/peer_identify.py", data,
                                   "--target-rms", repr(1.01 * rms)], check=True,
                                  capture_output=True, text=True).stdout)
    project.append(seconds)
    peer.append(p["seconds_to_target"] if p["seconds_to_target"] is not None else float("inf"))
    print(f"run {r + 1}: project {seconds:.3f} s (rms {rms * 1e9:.4f} nm), peer {peer[-1]:.3f} s to rms <= "
          f"{1.01 * rms * 1e9:.4f} nm ({p['evaluations']} evaluations), ratio {peer[-1] / seconds:.1f}")
mp, mq = statistics.median(project), statistics.median(peer)
ratios = [q / p for p, q in zip(project, peer)]
print(f"median: project {mp:.3f} s, peer {mq:.3f} s, ratio of medians {mq / mp:.1f}, median ratio {statistics.median(ratios):.1f}")

import re
bench = subprocess.run(["cargo", "bench", "-q", "-p", "host-sim", "--bench", "identify", "--", "--quick",
                        "sse_stage3_N10000"], check=True, capture_output=True, text=True).stdout
m = re.search(r"sse_stage3_N10000\s+time:\s+\[\S+ \S+ (\S+) (\S+)", bench)
if m is None:
    sys.exit("no sse_stage3_N10000 estimate in the criterion output:\n" + bench)
unit = {"ns": 1e-9, "µs": 1e-6, "us": 1e-6, "ms": 1e-3, "s": 1.0}[m.group(2)]
ours = float(m.group(1)) * unit
p = json.loads(subprocess.run([sys.executable, "host-sim/evidence/peer_identify.py", data, "--sse-timing"],
                              check=True, capture_output=True, text=True).stdout)
print(f"one SSE evaluation, N = {p['samples']}, theta = box midpoint {p['theta']}: project {ours * 1e3:.3f} ms "
      f"(criterion), peer {p['sse_seconds_median'] * 1e3:.3f} ms (median of {p['repeats']}), "
      f"ratio {p['sse_seconds_median'] / ours:.2f}")
PY
