"""Piezo stage models, compensation, identification and the firmware link, from Python.

The same Rust code as the ``host-sim`` command line, on NumPy arrays, in SI units (s, V, m).
One axis: 1-D arrays; two axes: N x 2 arrays (columns x, y). Every error of the tools raises
:class:`PiezoError` with the message ``host-sim`` prints (a stage file's errors name the file,
line, column and key); arguments of the wrong shape raise :class:`ValueError`.
"""

from __future__ import annotations

import os
from typing import Any, Callable, Dict, List, Optional, Tuple, Union

import numpy as np
import numpy.typing as npt

ArrayLike = npt.ArrayLike
PathLike = Union[str, "os.PathLike[str]"]
Progress = Callable[[float], Any]

class PiezoError(Exception):
    """An error of the piezo tools, with the message host-sim prints."""

class Stage:
    """A stage file: ``[stage]``, ``[io]`` and the axes ``x`` (and ``y``), validated by the core
    as ``host-sim predict`` validates it. :meth:`compensate`, :meth:`Link.upload` and the firmware
    also need the firmware's check (:meth:`firmware_refusal` says why it would refuse)."""

    @staticmethod
    def load(path: PathLike) -> Stage:
        """Reads and validates a stage file (TOML)."""
    @staticmethod
    def from_toml(text: str, name: str = "<string>") -> Stage:
        """Parses and validates a stage file's text; ``name`` is the file named in errors."""
    def save(self, path: PathLike) -> None:
        """Writes the stage file's text (as read, comments included)."""
    def to_toml(self) -> str:
        """The stage file's text."""
    @property
    def name(self) -> str:
        """The file named in errors."""
    @property
    def axes(self) -> List[str]:
        """``["x"]`` or ``["x", "y"]``."""
    @property
    def loop_rate_hz(self) -> float:
        """``[stage].loop_rate_hz`` [Hz]."""
    @property
    def params(self) -> Dict[str, Any]:
        """Every table of the file as a dict (``stage``, ``io``, ``x``, ``y``)."""
    def firmware_refusal(self) -> Optional[str]:
        """Why the firmware's check would refuse the file (located), or None."""
    def predict(self, u: ArrayLike, t: Optional[ArrayLike] = None) -> np.ndarray:
        """Stage output [m] for stack voltages ``u`` [V], as ``host-sim predict`` runs the
        firmware's chain from rest, at the sample period of ``t`` [s] (default: the loop
        period). Same shape as ``u``."""
    def compensate(self, r: ArrayLike, periodic: bool = False) -> np.ndarray:
        """Stack voltages [V] the firmware commands for the reference ``r`` [m] sampled at the
        loop rate, as ``host-sim compensate`` computes them; ``periodic``: ``r`` is one period
        of a looped reference. Same shape as ``r``."""

def identify(
    t: ArrayLike,
    u: ArrayLike,
    y: ArrayLike,
    model: str,
    *,
    method: str = "vp-de-lm",
    invertible: bool = False,
    stage: Optional[Stage] = None,
    start: float = 0.0,
    seed: int = 1,
    no_shift: bool = False,
    progress: Optional[Progress] = None,
    name: str = "arrays",
) -> Tuple[Stage, Dict[str, Any]]:
    """Fits ``model`` (symmetric, asymmetric, dynamic, oscillator) to the record ``t`` [s],
    ``u`` [V], ``y`` [m] as ``host-sim identify`` does; returns the stage file it writes and
    its report. ``stage``: carry its ``[stage]`` and ``[io]``; ``name``: the data named in the
    stage file's header. ``progress(elapsed_s)`` is called every 0.5 s; Ctrl-C raises
    KeyboardInterrupt at once (the abandoned fit ends on its own thread)."""

def close_loop(
    t: ArrayLike,
    u: ArrayLike,
    y: ArrayLike,
    *,
    start: float = 0.0,
    min_share: float = 0.05,
    seed: int = 1,
    invertible: bool = False,
    stage: Optional[Stage] = None,
    validate: Optional[Tuple[ArrayLike, ArrayLike, ArrayLike]] = None,
    validate_start: float = 0.0,
    progress: Optional[Progress] = None,
    name: str = "arrays",
) -> Tuple[Stage, Dict[str, Any]]:
    """Fits the base model, adds the effects its residual lacks and refits, as
    ``host-sim close-loop`` does; returns the stage file it writes and its report."""

class Link:
    """The firmware's command link (``tcp:HOST:PORT`` for the QEMU image, ``serial:PATH`` for
    the board), as ``host-sim link`` drives it; a context manager. Refusals raise
    :class:`PiezoError` with the core's reason."""

    def __init__(self, connect: str, timeout: float = 10.0, wait: float = 0.0) -> None: ...
    def __enter__(self) -> Link: ...
    def __exit__(self, *args: Any) -> bool: ...
    def close(self) -> None:
        """Closes the connection."""
    def status(self) -> Dict[str, Any]:
        """The firmware's state."""
    def excite(
        self,
        signal: str,
        duration: float,
        decimation: int = 1,
        allow_gaps: bool = False,
        plot: Optional[str] = None,
    ) -> Dict[str, np.ndarray]:
        """Open-loop excitation in volts; the record's columns ``t_s, ux_V, uy_V, x_m, y_m``.
        ``plot`` (``.png``/``.svg``) draws it as ``host-sim link excite --plot`` does."""
    def track(
        self,
        signal: str,
        duration: float,
        decimation: int = 1,
        allow_gaps: bool = False,
        plot: Optional[str] = None,
    ) -> Dict[str, np.ndarray]:
        """Tracks a reference in metres; the record's columns plus ``rx_m, ry_m``.
        ``plot`` (``.png``/``.svg``) draws it as ``host-sim link track --plot`` does."""
    def upload(self, stage: Stage) -> int:
        """Sends the stage's model; returns the checksum the firmware loaded."""
    def control(self, mode: str) -> Any:
        """open-loop | feedforward | feedback | feedforward+feedback | learned | learned+feedback."""
    def rearm(self) -> Any:
        """Leaves the safe state."""
    def shutdown(self) -> Any:
        """Ends the firmware's run (the QEMU image exits)."""
