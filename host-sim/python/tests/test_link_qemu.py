"""A link session from Python against the QEMU image's simulated XY stage:
status -> excite -> identify -> upload -> track (compensator, then the linear baseline) ->
a refusal with the firmware's reason -> shutdown. Skipped without qemu-system-arm or the
thumbv7em-none-eabihf target. QEMU is stopped at the end whatever happens."""

import os
import shutil
import socket
import subprocess
from pathlib import Path

import numpy as np
import pytest

import piezo
from conftest import REPO, target_dir

TARGET = "thumbv7em-none-eabihf"


def missing_tools():
    if shutil.which("qemu-system-arm") is None:
        return "qemu-system-arm not found (apt-get install qemu-system-arm)"
    sysroot = subprocess.run(["rustc", "--print", "sysroot"], capture_output=True, text=True)
    if not (Path(sysroot.stdout.strip()) / "lib" / "rustlib" / TARGET / "lib").is_dir():
        return f"the {TARGET} target is not installed (rustup target add {TARGET})"
    return None


def link_image() -> Path:
    """The `qemu` image with its built-in stage file, built where the Rust link tests build it
    (`<target dir>/link-session`)."""
    build_dir = target_dir() / "link-session"
    env = {k: v for k, v in os.environ.items() if k != "PIEZO_PARAMS"}
    env["CARGO_TARGET_DIR"] = str(build_dir)
    subprocess.run(
        ["cargo", "build", "--release", "--features", "qemu", "--bin", "qemu"],
        cwd=REPO / "firmware", env=env, check=True,
    )
    return build_dir / TARGET / "release" / "qemu"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def qemu_link():
    why = missing_tools()
    if why:
        pytest.skip(why)
    elf = link_image()
    port = free_port()
    qemu = subprocess.Popen(
        [str(REPO / "firmware" / "run-qemu.sh"), "--link", str(port), str(elf)],
        stdout=subprocess.DEVNULL, env={**os.environ, "QEMU_TIMEOUT": "300"},
    )
    try:
        yield f"tcp:127.0.0.1:{port}", qemu
    finally:
        if qemu.poll() is None:
            qemu.terminate()
        qemu.wait(timeout=20)


def test_a_link_session_from_python(qemu_link, scratch):
    address, qemu = qemu_link
    built_in = piezo.Stage.load(REPO / "firmware" / "params" / "xy-stage.toml")
    with piezo.Link(address, timeout=20, wait=30) as link:
        status = link.status()
        assert status["mode"] == "Running", status

        # Excite 0.5-119.5 V at 5 Hz on both axes, every tick recorded.
        record = link.excite("sine:amp=59.5,offset=60,freq=5,phase_deg=-90", 1.2)
        assert set(record) == {"t_s", "ux_V", "uy_V", "x_m", "y_m"}
        assert len(record["t_s"]) == round(1.2 * status["loop_rate_hz"]) - 1
        assert np.ptp(record["ux_V"]) > 100 and np.ptp(record["x_m"]) > 10e-6

        # Identify both axes on it, [stage] and [io] carried from the running stage file.
        u = np.column_stack([record["ux_V"], record["uy_V"]])
        y = np.column_stack([record["x_m"], record["y_m"]])
        stage, report = piezo.identify(
            record["t_s"], u, y, "symmetric", invertible=True, start=0.2, stage=built_in
        )
        assert report["verdict"] == "accepted", report
        assert all(a["fit"]["rms"] < 200e-9 for a in report["axes"]), report["axes"]

        # Upload: the firmware runs the identified set.
        checksum = link.upload(stage)
        assert link.status()["params_fnv1a32"] == checksum

        # Track a 10 Hz sine with the compensator, then with the linear baseline.
        reference = "sine:amp=12e-6,offset=19e-6,freq=10,phase_deg=-90"
        figure = scratch / "track.png"
        tracked = link.track(reference, 1.0, decimation=10, plot=str(figure))
        assert set(tracked) == {"t_s", "ux_V", "uy_V", "x_m", "y_m", "rx_m", "ry_m"}
        assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        compensated = link.status()["tracking"]
        link.control("open-loop")
        link.track(reference, 1.0, decimation=10)
        linear = link.status()["tracking"]
        link.control("feedforward")
        for c, l in zip(compensated, linear):
            assert c["rms_m"] < 0.5 * l["rms_m"], (c, l)
            assert c["rms_m"] < 600e-9, c

        # A refusal carries the firmware's reason: feedback needs a servo the set lacks.
        with pytest.raises(piezo.PiezoError, match="servo"):
            link.control("feedforward+feedback")
        link.rearm()
        link.shutdown()
    qemu.wait(timeout=10)
    assert qemu.returncode == 0
    with pytest.raises(piezo.PiezoError, match="closed"):
        link.status()
