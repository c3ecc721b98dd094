"""Fixtures of the `piezo` tests: the repository, the `host-sim` command line they compare
against (built with the extension's profile), and a scratch directory removed afterwards."""

import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[3]


def target_dir() -> Path:
    return Path(os.environ.get("CARGO_TARGET_DIR", REPO / "target"))


@pytest.fixture(scope="session")
def host_sim() -> Path:
    """The `host-sim` binary: $PIEZO_HOST_SIM, else built with `cargo build --profile python`
    (the profile the extension is built with, so the two share their compiled code)."""
    given = os.environ.get("PIEZO_HOST_SIM")
    if given:
        return Path(given)
    subprocess.run(
        ["cargo", "build", "--profile", "python", "-p", "host-sim", "--bin", "host-sim"],
        cwd=REPO,
        check=True,
    )
    return target_dir() / "python" / "host-sim"


@pytest.fixture
def scratch():
    """A directory of the test's own, removed when it ends."""
    path = Path(tempfile.mkdtemp(prefix="piezo_pytest_"))
    try:
        yield path
    finally:
        shutil.rmtree(path, ignore_errors=True)


def run(host_sim: Path, *args) -> subprocess.CompletedProcess:
    """Runs `host-sim ARGS`; fails the test with its stderr if it fails."""
    done = subprocess.run(
        [str(host_sim), *map(str, args)], capture_output=True, text=True, cwd=REPO
    )
    assert done.returncode == 0, f"host-sim {' '.join(map(str, args))}:\n{done.stderr}"
    return done


def read_csv(path: Path) -> dict:
    """A CSV written by host-sim as a dict of float arrays, by column name."""
    table = np.genfromtxt(path, delimiter=",", names=True, dtype=float, comments="#")
    return {name: np.asarray(table[name], dtype=float) for name in table.dtype.names}
