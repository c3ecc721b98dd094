"""The sensor's zero moved between sessions: writes OUT, the CSV record IN with the constant
OFFSET_M (m) added to every displacement column (name ending in `_m`), repr-exact floats.
Shared by rate_dependent.sh and unseen_actuator.sh.
Usage: python3 sensor_offset.py IN OUT OFFSET_M
"""
import csv
import sys

src, dst, off = sys.argv[1], sys.argv[2], float(sys.argv[3])
with open(src, newline="") as f:
    rows = list(csv.reader(f))
moved = [i for i, name in enumerate(rows[0]) if name.endswith("_m")]
with open(dst, "w", newline="") as out:
    w = csv.writer(out)
    w.writerow(rows[0])
    for r in rows[1:]:
        w.writerow([repr(float(v) + off) if i in moved else v for i, v in enumerate(r)])
