#!/usr/bin/env bash
# The core's static model on the host against the numba peer, in one run, repeated: samples per second
# of `cargo bench -p host-sim --bench throughput -- core/static` (criterion, middle estimate) and of
# host-sim/evidence/peer_static.py (the same records and sets), and their ratio. Then one SSE
# evaluation of the identification (N = 10 000, `--bench identify -- sse_stage3_N10000`).
# Usage (from the repository root): bash host-sim/evidence/host_speed.sh [RUNS]
set -euo pipefail
RUNS=${1:-3}
T=${CARGO_TARGET_DIR:-target}
cargo bench -p host-sim --bench throughput --no-run -q
for r in $(seq 1 "$RUNS"); do
  cargo bench -p host-sim --bench throughput -q -- --quick core/static 2>/dev/null \
    | awk '/^core\/static/ {name=$1} /thrpt:/ && name {print name, $(NF-3), $(NF-2); name=""}' > "$T/host_speed_project.txt"
  python3 host-sim/evidence/peer_static.py > "$T/host_speed_peer.json"
  python3 - "$T/host_speed_project.txt" "$T/host_speed_peer.json" "$r" <<'PY'
import json, sys
unit = {"elem/s": 1.0, "Kelem/s": 1e3, "Melem/s": 1e6, "Gelem/s": 1e9}
peer = json.load(open(sys.argv[2]))
for line in open(sys.argv[1]):
    name, value, u = line.split()
    key = name.split("/")[1]
    ours = float(value) * unit[u]
    print(f"run {sys.argv[3]}: {key}: project {ours / 1e6:.2f} M samples/s, peer {peer[key] / 1e6:.2f} M/s, ratio {ours / peer[key]:.2f}")
PY
done
