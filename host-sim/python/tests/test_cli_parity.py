"""The package gives the numbers of the `host-sim` command line on the same files: predict,
compensate, identify and close-loop, one axis and two; and its errors carry the CLI's message."""

import json
import re
import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

import piezo
from conftest import REPO, read_csv, run

XY_STAGE = REPO / "firmware" / "params" / "xy-stage.toml"


def simulate(host_sim, path, plant, spec, *effects):
    args = ["simulate", "--plant", plant, "--signal", spec, "--out", path]
    for e in effects:
        args += ["--effect", e]
    run(host_sim, *args)
    return read_csv(path)


@pytest.fixture
def stage_record(host_sim, scratch):
    """A one-axis record of the simulated stage: 0.5 s of a 5 Hz sine, 5-105 V, 2 kHz."""
    path = scratch / "stage.csv"
    return path, simulate(
        host_sim, path, "stage", "sine:amp=50,offset=55,freq=5,duration=1,rate=2000"
    )


def test_identify_gives_the_cli_stage_file_and_report(host_sim, scratch, stage_record):
    path, rec = stage_record
    out, report = scratch / "s.toml", scratch / "s.json"
    run(host_sim, "identify", "--data", path, "--model", "symmetric", "--invertible",
        "--out", out, "--report", report)
    stage, py_report = piezo.identify(
        rec["t_s"], rec["u_V"], rec["y_m"], "symmetric", invertible=True, name=str(path)
    )
    assert stage.to_toml() == out.read_text()
    cli_report = json.loads(report.read_text())
    assert py_report["fit"] == cli_report["fit"]
    assert py_report["params"] == cli_report["params"]
    assert py_report["verdict"] == cli_report["verdict"] == "accepted"
    assert stage.axes == ["x"]
    assert stage.params["x"]["model"] == "symmetric"


def test_identify_two_axes_with_a_given_stage(host_sim, scratch):
    path = scratch / "xy.csv"
    rec = simulate(host_sim, path, "xy-stage",
                   "sine:amp=50,offset=60,freq=5,duration=0.6,rate=10000")
    out, report = scratch / "xy.toml", scratch / "xy.json"
    run(host_sim, "identify", "--data", path, "--model", "symmetric", "--invertible",
        "--u", "ux_V,uy_V", "--y", "x_m,y_m", "--stage", XY_STAGE,
        "--out", out, "--report", report)
    u = np.column_stack([rec["ux_V"], rec["uy_V"]])
    y = np.column_stack([rec["x_m"], rec["y_m"]])
    stage, py_report = piezo.identify(
        rec["t_s"], u, y, "symmetric", invertible=True, stage=piezo.Stage.load(XY_STAGE),
        name=str(path),
    )
    assert stage.to_toml() == out.read_text()
    cli = json.loads(report.read_text())
    for a, b in zip(py_report["axes"], cli["axes"]):
        assert a["fit"] == b["fit"] and a["params"] == b["params"]


def test_predict_gives_the_cli_series(host_sim, scratch, stage_record):
    path, rec = stage_record
    out = scratch / "s.toml"
    run(host_sim, "identify", "--data", path, "--model", "symmetric", "--out", out,
        "--report", scratch / "s.json", "--allow-refused")
    series = scratch / "p.csv"
    run(host_sim, "predict", "--params", out, "--data", path, "--out", series,
        "--report", scratch / "p.json")
    cli = read_csv(series)
    predicted = piezo.Stage.load(out).predict(rec["u_V"], t=rec["t_s"])
    assert predicted.shape == rec["u_V"].shape
    np.testing.assert_array_equal(predicted, cli["predicted_m"])


def test_predict_two_axes_gives_the_cli_series(host_sim, scratch):
    path = scratch / "xy.csv"
    rec = simulate(host_sim, path, "xy-stage",
                   "sine:amp=50,offset=60,freq=20,duration=0.2,rate=10000")
    series = scratch / "p.csv"
    run(host_sim, "predict", "--params", XY_STAGE, "--data", path, "--u", "ux_V,uy_V",
        "--y", "x_m,y_m", "--out", series, "--report", scratch / "p.json")
    cli = read_csv(series)
    u = np.column_stack([rec["ux_V"], rec["uy_V"]])
    predicted = piezo.Stage.load(XY_STAGE).predict(u, t=rec["t_s"])
    assert predicted.shape == u.shape
    np.testing.assert_array_equal(predicted[:, 0], cli["x_predicted_m"])
    np.testing.assert_array_equal(predicted[:, 1], cli["y_predicted_m"])


@pytest.mark.parametrize("params", ["xy-stage.toml", "xy-stage-effects.toml"])
def test_compensate_gives_the_cli_voltages(host_sim, scratch, params):
    params = REPO / "firmware" / "params" / params
    reference, out = scratch / "r.csv", scratch / "u.csv"
    run(host_sim, "compensate", "--params", params, "--signal",
        "triangle:low=5,high=35,freq=10,duration=0.3", "--reference", reference,
        "--out", out)
    r = read_csv(reference)
    cli = read_csv(out)
    rm = np.column_stack([r["rx_um"], r["ry_um"]]) * 1e-6
    u = piezo.Stage.load(params).compensate(rm)
    assert u.shape == rm.shape
    np.testing.assert_array_equal(u[:, 0], cli["ux_V"])
    np.testing.assert_array_equal(u[:, 1], cli["uy_V"])


def test_compensate_one_axis_gives_the_cli_voltages(host_sim, scratch, stage_record):
    path, _ = stage_record
    out = scratch / "s.toml"
    run(host_sim, "identify", "--data", path, "--model", "symmetric", "--invertible",
        "--out", out, "--report", scratch / "s.json")
    reference, volts = scratch / "r.csv", scratch / "u.csv"
    run(host_sim, "compensate", "--params", out, "--signal",
        "sine:amp=2,offset=3,freq=5,duration=0.5", "--reference", reference, "--out", volts)
    r = read_csv(reference)
    u = piezo.Stage.load(out).compensate(r["r_um"] * 1e-6)
    assert u.ndim == 1
    np.testing.assert_array_equal(u, read_csv(volts)["u_V"])


def test_close_loop_gives_the_cli_stage_file_and_report(host_sim, scratch):
    path = scratch / "creep.csv"
    rec = simulate(host_sim, path, "stage",
                   "sine:amp=50,offset=55,freq=2,duration=2,rate=1000", "creep")
    report = scratch / "cl.json"
    run(host_sim, "close-loop", "--data", path, "--invertible", "--report", report)
    calls = []
    stage, py_report = piezo.close_loop(
        rec["t_s"], rec["u_V"], rec["y_m"], invertible=True, name=str(path),
        progress=calls.append,
    )
    assert stage.to_toml() == (scratch / "cl.toml").read_text()
    cli = json.loads(report.read_text())
    for key in ("before", "after", "axes", "verdict"):
        assert py_report[key] == cli[key], key


def test_stage_errors_carry_the_cli_message(host_sim, scratch):
    text = XY_STAGE.read_text().replace("loop_rate_hz = 20000.0", "loop_rate_hz = -1.0")
    assert text != XY_STAGE.read_text()
    bad = scratch / "bad.toml"
    bad.write_text(text)
    with pytest.raises(piezo.PiezoError) as raised:
        piezo.Stage.load(bad)
    message = str(raised.value)
    # file:line:column: key: reason
    assert re.match(re.escape(str(bad)) + r":\d+:\d+: `stage.loop_rate_hz`", message), message
    done = subprocess.run(
        [str(host_sim), "predict", "--params", bad, "--data", bad, "--report",
         scratch / "r.json"], capture_output=True, text=True)
    assert done.returncode != 0
    assert message in done.stderr
    with pytest.raises(piezo.PiezoError, match="loop_rate_hz"):
        piezo.Stage.from_toml(text, name="inline.toml")


def test_stage_round_trip_and_shape_errors(scratch):
    stage = piezo.Stage.load(XY_STAGE)
    assert stage.axes == ["x", "y"] and stage.loop_rate_hz == 20000.0
    saved = scratch / "copy.toml"
    stage.save(saved)
    assert saved.read_text() == XY_STAGE.read_text()
    assert piezo.Stage.from_toml(saved.read_text()).params == stage.params
    with pytest.raises(ValueError, match="N x 2"):
        stage.predict(np.zeros((10, 3)))
    with pytest.raises(piezo.PiezoError, match="axis"):
        stage.compensate(np.zeros(10))


def interrupted_after(scratch, progress: bool):
    """Runs a long fit (a dynamic model on 40 s at 10 kHz) in a child Python, sends it SIGINT
    1.5 s after the fit started; returns the child's output after the fit line, its exit code
    and the seconds from SIGINT to its exit."""
    script = scratch / "interrupt.py"
    script.write_text(textwrap.dedent(f"""
        import sys
        import numpy as np
        import piezo
        t = np.arange(400_000) / 10_000.0
        u = 60 + 50 * np.sin(2 * np.pi * 5 * t)
        y = 3e-7 * u + 1e-8 * np.sin(2 * np.pi * 5 * t - 0.3)
        def progress(elapsed):
            print("progress", elapsed, flush=True)
        print("fitting", flush=True)
        try:
            piezo.identify(t, u, y, "dynamic", progress=progress if {progress} else None)
        except KeyboardInterrupt:
            print("interrupted", flush=True)
            sys.exit(3)
        print("finished", flush=True)
    """))
    child = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "fitting"
        time.sleep(1.5)
        sent = time.monotonic()
        child.send_signal(signal.SIGINT)
        rest = child.stdout.read()
        child.wait(timeout=10)
        return rest, child.returncode, time.monotonic() - sent
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()


def test_ctrl_c_stops_a_fit_without_a_progress_callback(scratch):
    """SIGINT raises KeyboardInterrupt within a second instead of waiting for the fit."""
    rest, code, seconds = interrupted_after(scratch, progress=False)
    assert "interrupted" in rest and code == 3, (rest, code)
    assert seconds < 1.0, seconds


def test_progress_is_reported_while_a_fit_runs(scratch):
    rest, code, seconds = interrupted_after(scratch, progress=True)
    lines = rest.splitlines()
    elapsed = [float(line.split()[1]) for line in lines if line.startswith("progress")]
    assert len(elapsed) >= 2 and elapsed == sorted(elapsed), lines
    assert lines[-1] == "interrupted" and code == 3 and seconds < 1.0, (lines, code, seconds)
