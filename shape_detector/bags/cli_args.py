"""argparse ``type=`` validators: a bad value fails at parse time with a message that
names the option and the reason (exit status 2), before any bag or model is opened."""

from __future__ import annotations

import argparse
import math
import re
from collections.abc import Callable

import numpy as np


def finite_float(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
                 what: str = "") -> Callable[[str], float]:
    """A float parser: finite, and within ``[lo, hi]`` (``(lo, hi]`` when ``lo_open``)."""

    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        if not math.isfinite(v):
            raise argparse.ArgumentTypeError(f"{text!r} must be a finite number")
        if lo is not None and (v <= lo if lo_open else v < lo):
            raise argparse.ArgumentTypeError(f"{text!r} must be {'>' if lo_open else '>='} {lo:g}{what}")
        if hi is not None and v > hi:
            raise argparse.ArgumentTypeError(f"{text!r} must be <= {hi:g}{what}")
        return v

    return parse


def int_at_least(lo: int) -> Callable[[str], int]:
    """An integer parser: ``>= lo``."""

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if v < lo:
            raise argparse.ArgumentTypeError(f"{text!r} must be >= {lo}")
        return v

    return parse


#: metres per raw depth unit: positive (16UC1 millimetres = 0.001)
depth_scale = finite_float(0.0, lo_open=True, what=" (metres per raw depth unit)")
#: a score in [0, 1]
probability = finite_float(0.0, 1.0)
#: seconds, >= 0
seconds = finite_float(0.0)
#: a playback rate factor; <= 0 means as fast as possible, so only finiteness is checked
rate = finite_float()


def up_vector(text: str) -> np.ndarray:
    """``'x,y,z'``: three finite numbers, not all zero -> unit vector (camera optical frame)."""
    try:
        v = np.asarray([float(x) for x in text.split(",")], dtype=np.float64)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not three comma-separated numbers") from None
    if v.shape != (3,) or not np.all(np.isfinite(v)) or np.linalg.norm(v) < 1e-9:
        raise argparse.ArgumentTypeError(f"{text!r} must be three finite numbers, not all zero (e.g. 0,-1,0)")
    return v / np.linalg.norm(v)


_DEVICE = re.compile(r"^(auto|cpu|cuda(:\d+)?|mps|xpu(:\d+)?)$")


def device(text: str) -> str:
    """A device: ``auto``, ``cpu``, ``cuda``, ``cuda:N``, ``mps``, ``xpu[:N]``."""
    if not _DEVICE.match(text):
        raise argparse.ArgumentTypeError(f"{text!r} is not a device (auto, cpu, cuda, cuda:N, mps)")
    return text


def topic(text: str) -> str:
    """A topic name: non-empty, no whitespace."""
    if not text or any(c.isspace() for c in text):
        raise argparse.ArgumentTypeError(f"{text!r} is not a topic name")
    return text


def remap(text: str) -> tuple[str, str]:
    """``FROM:=TO`` -> ``(FROM, TO)``."""
    a, sep, b = text.partition(":=")
    if not sep or not a or not b:
        raise argparse.ArgumentTypeError(f"{text!r} is not FROM:=TO")
    return a, b


def path_text(text: str) -> str:
    """A non-empty path."""
    if not text.strip():
        raise argparse.ArgumentTypeError("an empty path")
    return text
