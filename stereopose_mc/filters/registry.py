"""The filter types: one entry each, all that the engine, the config and the outputs know of a filter.

An entry (``FilterType``) names a scenario's ``type:`` and gives

- ``config``: its pydantic model (config/filters.py: the keys of its ``filters:`` entry, with
  descriptions, a member of the scenario's discriminated union), whose ``setup`` resolves it
  to a frozen dataclass of SI parameters (``config.resolve.filter_setup_of``);
- ``numpy``: its step, ``predict(x, P, t, fs, setup) -> (x-, P-)`` and
  ``update(x, P, step, rows, fs, setup, model=None) -> GatedUpdate`` on a batch of trials
  (``filters.estimators`` runs it);
- ``compiled``: a loader of its step on the compiled kernels (the same signatures, the update
  with ``x_true=None`` for the NEES it evaluates), or None: no compiled path, its trials then
  run the numpy step under ``--kernels compiled`` (``steps`` says so once, as a warning);
- ``chart``: the coordinates of its covariance at a setup, ``"full"`` (the whole state),
  ``"aligned"`` or ``"attitude"`` (an ``n - 1`` error state, docs/filters.md): the initial
  covariance, the compiled kernels' chart and the NEES follow it;
- ``thesis``: the thesis's filter it stands for in the reports (``"ekf"``, ``"iekf"``: the thesis's
  tables next to its percentiles, the EKF/IEKF comparison figures), or None.

Adding a filter: a config model, a module with its step and one entry here (or ``register``
from outside the package). docs/filters.md, "Adding a filter".
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Callable, NamedTuple

from ..config import filters as config_filters
from ..config.filters import EKFConfig, FilterSetup, IEKFConfig, MEKFConfig, UKFConfig
from . import mekf, relnav, ukf

CHARTS = ("full", "aligned", "attitude")


class Step(NamedTuple):
    """A filter's ``predict`` and ``update`` (module docstring)."""

    predict: Callable
    update: Callable


@dataclass(frozen=True)
class FilterType:
    """One filter type (module docstring)."""

    name: str
    config: type
    numpy: Step
    compiled: Callable[[], Step] | None
    chart: Callable[[FilterSetup], str]
    thesis: str | None = None


def error_state_chart(fs: FilterSetup) -> str:
    """The chart of the entry's ``error_state`` key."""
    return fs.error_state


def multiplicative_chart(fs: FilterSetup) -> str:
    """The MEKF's and UKF's chart: always an error state, the attitude one for anything but ``aligned``."""
    return "aligned" if fs.error_state == "aligned" else "attitude"


def _by_chart_predict(x, P, t, fs, setup):
    """The EKF's and IEKF's prediction: on the full state (``relnav``) or in an error state's chart (``mekf``)."""
    return (relnav if fs.error_state == "full" else mekf).predict(x, P, t, fs, setup)


def _by_chart_update(x, P, step, rows, fs, setup, model=None):
    """The EKF's and IEKF's update, as ``_by_chart_predict``."""
    return (relnav if fs.error_state == "full" else mekf).update(x, P, step, rows, fs, setup, model)


def _ukf_update(x, P, step, rows, fs, setup, model=None):
    """``ukf.update`` (its sigma points measured by numpy's model: ``model`` is not used)."""
    return ukf.update(x, P, step, rows, fs, setup)


def _kernels() -> Step:
    """The EKF, IEKF and MEKF on the compiled kernels (``filters.compiled``, loaded when first asked for)."""
    from . import compiled

    return Step(compiled.kernel_predict, compiled.kernel_update)


def _ukf_kernels() -> Step:
    """The UKF's sigma points through the compiled model and charts (``filters.compiled``)."""
    from . import compiled

    return Step(compiled.ukf_predict, compiled.ukf_update)


_EKF_STEP = Step(_by_chart_predict, _by_chart_update)
FILTERS: dict[str, FilterType] = {
    "iekf": FilterType("iekf", IEKFConfig, _EKF_STEP, _kernels, error_state_chart, thesis="iekf"),
    "ekf": FilterType("ekf", EKFConfig, _EKF_STEP, _kernels, error_state_chart, thesis="ekf"),
    "mekf": FilterType("mekf", MEKFConfig, Step(mekf.predict, mekf.update), _kernels, multiplicative_chart),
    "ukf": FilterType("ukf", UKFConfig, Step(ukf.predict, _ukf_update), _ukf_kernels, multiplicative_chart),
}


def of(fs: FilterSetup) -> FilterType:
    """The entry of a filter's setup."""
    return FILTERS[fs.kind]


def chart(fs: FilterSetup) -> str:
    """The chart of a filter's covariance: ``full``, ``aligned`` or ``attitude``."""
    return of(fs).chart(fs)


def thesis_role(name: str | None) -> str | None:
    """The thesis's filter that a type (by name, as a run's manifest records it) stands for; None: none, or a type
    this version does not know."""
    entry = FILTERS.get(name) if name is not None else None
    return None if entry is None else entry.thesis


_WARNED: set[str] = set()


def steps(fs: FilterSetup, kernels: str) -> Step:
    """The step of a filter on ``kernels`` (``numpy`` or ``compiled``). A type without a compiled step runs its
    numpy step under ``compiled`` (its update called without ``x_true``), with a warning the first time."""
    entry = of(fs)
    if kernels == "numpy":
        return entry.numpy
    if entry.compiled is not None:
        return entry.compiled()
    if entry.name not in _WARNED:
        _WARNED.add(entry.name)
        warnings.warn(f"filter type {entry.name!r} has no compiled step: its trials run the numpy step", stacklevel=2)
    return Step(entry.numpy.predict, _without_truth(entry.numpy.update))


def _without_truth(update):
    def f(x, P, step, rows, fs, setup, x_true=None):
        return update(x, P, step, rows, fs, setup)

    return f


def register(entry: FilterType) -> None:
    """Add a filter type from outside the package: its entry here and its config model in the scenario schema."""
    if entry.name != config_filters.tag(entry.config):
        raise ValueError(f"filter type {entry.name!r}: its config model's type tag is {config_filters.tag(entry.config)!r}")
    if entry.name in FILTERS:
        raise ValueError(f"filter type {entry.name!r} is already registered")
    config_filters.register(entry.config)
    FILTERS[entry.name] = entry


def unregister(name: str) -> None:
    """Remove a filter type added by ``register``."""
    FILTERS.pop(name, None)
    _WARNED.discard(name)
    config_filters.unregister(name)
