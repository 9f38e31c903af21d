"""Which prediction and update a filter entry uses (``FilterSetup.kind`` and ``error_state``).

``ekf`` and ``iekf`` with ``error_state: full`` carry the covariance of the full state
(``filters/relnav.py``); every other entry that of an error state, ``n - 1``: the MEKF,
and the EKF/IEKF with ``error_state: aligned|attitude``, through ``filters/mekf.py``; the
UKF through ``filters/ukf.py``.
"""

from __future__ import annotations

from . import mekf, relnav


def error_state(fs) -> bool:
    """True when the filter's covariance is that of an error state (``n - 1``)."""
    return fs.kind in ("mekf", "ukf") or fs.error_state != "full"


def initial_covariance(x, P, fs):
    """The filter's starting covariance from a full-state one (mapped to its error state when it has one)."""
    return mekf.to_error_covariance(x, P, fs) if error_state(fs) else P


def predict(x, P, t, fs, setup):
    if fs.kind == "ukf":
        from . import ukf

        return ukf.predict(x, P, t, fs, setup)
    if error_state(fs):
        return mekf.predict(x, P, t, fs, setup)
    return relnav.predict(x, P, t, fs, setup)


def update(x, P, step, rows, fs, setup, model=None):
    """The filter's update; ``model(setup, step)``: the step's measurement model (``relnav.update``; default
    ``relnav.measurement_model``); the UKF's own update measures its sigma points with numpy's."""
    if fs.kind == "ukf":
        from . import ukf

        return ukf.update(x, P, step, rows, fs, setup)
    if error_state(fs):
        return mekf.update(x, P, step, rows, fs, setup, model)
    return relnav.update(x, P, step, rows, fs, setup, model)
