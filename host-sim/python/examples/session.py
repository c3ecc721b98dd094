"""From a measurement to tracking, in Python, with the firmware over its command link: excite
the stage, identify both axes, compute the compensator's voltages on the host, upload the
identified stage file and track a reference with it and with the linear baseline.

usage: python session.py [tcp:127.0.0.1:4560 | serial:/dev/ttyACM0]
"""

import sys
from pathlib import Path

import numpy as np

import piezo

REPO = Path(__file__).resolve().parents[3]
address = sys.argv[1] if len(sys.argv) > 1 else "tcp:127.0.0.1:4560"
with piezo.Link(address, timeout=20, wait=30) as link:
    print("running:", link.status()["params_version"])
    # 1. excite both axes 0.5-119.5 V at 5 Hz for 1.2 s, every tick recorded (t_s, ux_V, ...)
    rec = link.excite("sine:amp=59.5,offset=60,freq=5,phase_deg=-90", 1.2)
    # 2. identify both axes; [stage] and [io] from the stage file the firmware was built with
    u = np.column_stack([rec["ux_V"], rec["uy_V"]])
    y = np.column_stack([rec["x_m"], rec["y_m"]])
    given = piezo.Stage.load(REPO / "firmware" / "params" / "xy-stage.toml")
    stage, report = piezo.identify(
        rec["t_s"], u, y, "symmetric", invertible=True, start=0.2, stage=given
    )
    fits = ", ".join(f'{a["axis"]} {a["fit"]["rms"] * 1e9:.1f} nm' for a in report["axes"])
    print(f"identified: rms {fits} ({report['verdict']})")
    # 3. the voltages the firmware commands for a 10 Hz sine, 7-31 um (host-sim compensate's),
    #    and the model's output for them: the reference again, to the inverse's accuracy
    t = np.arange(10_000) / stage.loop_rate_hz
    r = 19e-6 - 12e-6 * np.cos(2 * np.pi * 10 * t)
    volts = stage.compensate(np.column_stack([r, r]))
    back = stage.predict(volts)
    print(
        f"compensate: {volts.min():.2f}-{volts.max():.2f} V; model(u) - r: "
        f"rms {np.sqrt(np.mean((back[:, 0] - r) ** 2)) * 1e9:.2f} nm"
    )
    # 4. upload it and track the same sine: compensator, then the linear baseline
    link.upload(stage)
    reference = "sine:amp=12e-6,offset=19e-6,freq=10,phase_deg=-90"
    for mode in ["feedforward", "open-loop"]:
        link.control(mode)
        tracked = link.track(reference, 1.0, decimation=10)
        error_nm = (tracked["x_m"] - tracked["rx_m"]) * 1e9
        stats = link.status()["tracking"][0]
        print(
            f"track ({mode}): x rms {stats['rms_m'] * 1e9:.1f} nm, "
            f"max {stats['max_abs_m'] * 1e9:.1f} nm (firmware's statistics); "
            f"{len(error_nm)} frames recorded"
        )
    link.control("feedforward")
    link.shutdown()
