"""Which prediction and update a filter entry uses (``FilterSetup.kind``).

``ekf`` and ``iekf`` carry the covariance of the full state (``filters/relnav.py``);
``mekf`` and ``ukf`` that of the error state, ``n - 1`` (``filters/mekf.py``,
``filters/ukf.py``).
"""

from __future__ import annotations

from . import mekf, relnav

ERROR_STATE_KINDS = ("mekf", "ukf")


def error_state(kind: str) -> bool:
    """True when the filter's covariance is that of the error state."""
    return kind in ERROR_STATE_KINDS


def predict(x, P, t, fs, setup):
    if fs.kind == "mekf":
        return mekf.predict(x, P, t, fs, setup)
    if fs.kind == "ukf":
        from . import ukf

        return ukf.predict(x, P, t, fs, setup)
    return relnav.predict(x, P, t, fs, setup)


def update(x, P, step, rows, fs, setup):
    if fs.kind == "mekf":
        return mekf.update(x, P, step, rows, fs, setup)
    if fs.kind == "ukf":
        from . import ukf

        return ukf.update(x, P, step, rows, fs, setup)
    return relnav.update(x, P, step, rows, fs, setup)
