"""A filter's numpy step, looked up in its registry entry (``filters/registry.py``).

Filters whose chart is ``full`` carry the covariance of the full state (``filters/relnav.py``);
every other that of an error state, ``n - 1`` (``filters/mekf.py``, ``filters/ukf.py``).
"""

from __future__ import annotations

from . import mekf, registry
from .relnav import flow_linearization_variance, pseudo_linearization_variance  # noqa: F401 (the step's R terms)


def error_state(fs) -> bool:
    """True when the filter's covariance is that of an error state (``n - 1``)."""
    return registry.chart(fs) != "full"


def initial_covariance(x, P, fs):
    """The filter's starting covariance from a full-state one (mapped to its error state when it has one)."""
    return mekf.to_error_covariance(x, P, fs) if error_state(fs) else P


def predict(x, P, t, fs, setup):
    """``(x-, P-)`` at ``t + dt`` by the numpy step of ``fs``'s type."""
    return registry.of(fs).numpy.predict(x, P, t, fs, setup)


def update(x, P, step, rows, fs, setup, model=None):
    """The update of ``fs``'s type; ``model(setup, step)``: the step's measurement model (``relnav.update``; default
    ``relnav.measurement_model``); the UKF's own update measures its sigma points with numpy's."""
    return registry.of(fs).numpy.update(x, P, step, rows, fs, setup, model)
