"""Numbers for JSON objects and text reports of the studies: plain floats, no negative zero."""

from __future__ import annotations

import numpy as np


def num(x: float) -> float:
    """A float for JSON/printing, with negative zero made positive."""
    return float(x) + 0.0


def vec(v) -> list[float]:
    return [num(x) for x in np.asarray(v, dtype=float).reshape(-1)]


def mat(m) -> list[list[float]]:
    return [vec(row) for row in np.asarray(m, dtype=float)]


def fmt(x: float, spec: str) -> str:
    """``x`` formatted, without the sign of a value that prints as zero (``-0.000000``)."""
    s = f"{x:{spec}}"
    return f"{0.0:{spec}}" if s.strip().startswith("-") and float(s) == 0.0 else s


def fmt_vec(v, spec: str = "10.6g") -> str:
    return "[" + ", ".join(fmt(x, spec) for x in v) + "]"
