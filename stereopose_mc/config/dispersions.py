"""Dispersions of a scenario (``dispersions:``): which keys may be dispersed, their units,
the check of a ``dispersions`` block, and applying one trial's values to a scenario.

A key of ``dispersions`` is the dotted path of a scenario value (docs/scenarios.md,
"Dispersions"). The sampling itself (distributions, plans, the per-trial stream) is in
``stereopose_mc.sim.dispersions``; this module only knows the scenario side.
"""

from __future__ import annotations

import copy
import difflib
from typing import Any

import numpy as np
from pydantic import ValidationError

from .schema import DispersionSpec, Scenario

#: dispersible key paths -> unit (in the scenario's units, as in the key names)
DISPERSIBLE: dict[str, str] = {
    "truth_initial_state.rho_m": "m",
    "truth_initial_state.rho_dot_mps": "m/s",
    "truth_initial_state.omega_degps": "deg/s",
    "truth_initial_state.q": "-",
    "target.inertia_kgm2": "kg m^2",
    "target.feature_points_m": "m",
    "leader.orbit.a_km": "km",
    "leader.orbit.e": "-",
    "leader.orbit.i_deg": "deg",
    "leader.orbit.raan_deg": "deg",
    "leader.orbit.argp_deg": "deg",
    "leader.orbit.true_anomaly_deg": "deg",
    "camera.baseline_m": "m",
    "camera.focal_length": "-",
    "measurements.image_sigma": "-",
    "measurements.flow_sigma": "1/s",
    "measurements.disparity_sigma": "-",
    "measurements.inertia_pseudo_measurement.angular_acceleration_sigma_radps2": "rad/s^2",
}
#: keys of the filter's model: ``applies_to: both`` gives the filter the dispersed value
MODEL_PREFIXES = ("leader.", "camera.", "measurements.")
DEFAULT_MODE = {"normal": "add", "truncnormal": "add", "uniform": "add", "lognormal": "scale", "choice": "replace",
                "uniform_rotation": "replace", "uniform_direction": "replace"}  # fmt: skip


def mode_of(spec: DispersionSpec) -> str:
    return spec.mode or DEFAULT_MODE[spec.dist]


def get_path(d: dict, path: str) -> Any:
    for k in path.split("."):
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return d


def set_path(d: dict, path: str, value: Any) -> None:
    keys = path.split(".")
    for k in keys[:-1]:
        d = d[k]
    d[keys[-1]] = value


def component_names(path: str, shape: tuple[int, ...]) -> list[str]:
    """Column names of the scalars of a value: ``path``, ``path[i]`` or ``path[i][j]``."""
    if not shape:
        return [path]
    return [path + "".join(f"[{i}]" for i in idx) for idx in np.ndindex(*shape)]


def _broadcasts(param: Any, shape: tuple[int, ...]) -> bool:
    try:
        np.broadcast_to(np.asarray(param, dtype=float), shape)
        return True
    except ValueError:
        return False


def spec_problems(path: str, spec: DispersionSpec, nominal: Any) -> list[str]:
    """What is wrong with dispersing ``path`` (nominal value ``nominal``) as ``spec``."""
    if path not in DISPERSIBLE:
        close = difflib.get_close_matches(path, list(DISPERSIBLE), n=1, cutoff=0.6)
        return ["unknown or non-dispersible key path" + (f" (did you mean {close[0]!r}?)" if close else "")
                + "; dispersible: " + ", ".join(DISPERSIBLE)]  # fmt: skip
    if nominal is None:
        return [f"{path} has no nominal value in the scenario; set it to disperse it"]
    shape = np.shape(nominal)
    if path == "truth_initial_state.q" and spec.dist != "uniform_rotation":
        return ["the attitude is dispersed with dist uniform_rotation only"]
    if spec.dist == "uniform_rotation" and path != "truth_initial_state.q":
        return ["dist uniform_rotation applies to truth_initial_state.q only"]
    if spec.dist == "uniform_direction" and shape != (3,):
        return ["dist uniform_direction applies to a 3-vector"]
    out = []
    for name in ("mean", "std", "low", "high", "sigma", "median"):
        v = getattr(spec, name)
        if v is not None and not _broadcasts(v, shape):
            out.append(f"{name} {v!r} does not fit the value's shape {list(shape)} (give a scalar or one per component)")
    for v in spec.values or []:
        if not _broadcasts(v, shape):
            out.append(f"choice value {v!r} does not fit the value's shape {list(shape)}")
    if spec.low is not None and spec.high is not None and _broadcasts(spec.low, shape) and _broadcasts(spec.high, shape):
        if np.any(np.asarray(spec.low, float) > np.asarray(spec.high, float)):
            out.append("low must not be above high in any component (low = high keeps a component fixed)")
        elif spec.dist == "truncnormal" and np.any(np.asarray(spec.low, float) >= np.asarray(spec.high, float)):
            out.append("truncnormal needs low below high in every component")
    if spec.std is not None and np.any(np.asarray(spec.std, float) < 0):
        out.append("std must be >= 0")
    if spec.sigma is not None and np.any(np.asarray(spec.sigma, float) < 0):
        out.append("sigma must be >= 0")
    if spec.dist == "lognormal" and np.any(np.asarray(spec.median, float) <= 0):
        out.append("median must be > 0")
    return out


def invalid_reason(data: dict) -> str:
    """'' if the scenario mapping ``data`` is valid, else the first problem as ``key.path: message``."""
    from .loader import _points_behind, clean_loc, error_message, path_str

    try:
        Scenario.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        loc, msg = error_message(err, clean_loc(tuple(err["loc"])), data)
        return f"{path_str(loc)}: {msg}"
    behind = _points_behind(data)
    if behind:
        loc, msg = behind[0]
        return f"{path_str(loc)}: {msg}"
    return ""


def apply_values(base: dict, values: dict[str, Any]) -> dict:
    """A copy of the scenario mapping ``base`` with ``values`` (path -> value) set, without dispersions."""
    d = copy.deepcopy({k: v for k, v in base.items() if k != "dispersions"})
    for path, v in values.items():
        set_path(d, path, np.asarray(v, dtype=float).tolist())
    return d


def _extremes(spec: DispersionSpec, nominal: Any) -> list[tuple[str, Any]]:
    """The draws at the bounds of a bounded distribution (all components low, all high; every choice)."""
    shape = np.shape(nominal)
    if spec.dist == "choice":
        draws = [("value " + repr(v), np.broadcast_to(np.asarray(v, float), shape)) for v in spec.values or []]
    elif spec.dist in ("uniform", "truncnormal"):
        lo = np.broadcast_to(np.asarray(spec.low, float), shape)
        hi = np.broadcast_to(np.asarray(spec.high, float), shape)
        draws = [("low", lo), ("high", hi)]
        if shape == (3,):  # every corner of a 3-vector's box
            draws += [(f"corner {c}", np.where(np.array(c, bool), hi, lo)) for c in np.ndindex(2, 2, 2)]
    else:
        return []
    mode = mode_of(spec)
    nom = np.asarray(nominal, float)
    return [(what, nom + d if mode == "add" else nom * d if mode == "scale" else d) for what, d in draws]


def check(data: Any) -> list[tuple[tuple, str]]:
    """Problems of the ``dispersions`` block of the raw scenario mapping ``data`` (key path, message).

    Unknown paths and ill-fitting parameters, and bounded distributions (uniform,
    truncnormal, choice) that reach an invalid scenario at their bounds (rejected up
    front). Unbounded ones (normal, lognormal, ...) are checked per draw at run time:
    an invalid draw becomes an invalid trial with its reason.
    """
    if not isinstance(data, dict) or not isinstance(data.get("dispersions"), dict):
        return []
    base = {k: v for k, v in data.items() if k != "dispersions"}
    try:
        nominal = Scenario.model_validate(base).model_dump(mode="python")
    except ValidationError:
        return []  # the base scenario's own problems are reported by pydantic
    out: list[tuple[tuple, str]] = []
    for path, raw in data["dispersions"].items():
        if path == "sampling":
            continue
        try:
            spec = DispersionSpec.model_validate(raw)
        except ValidationError:
            continue  # reported by pydantic
        nom = get_path(nominal, path)
        msgs = spec_problems(path, spec, nom)
        out += [(("dispersions", path), m) for m in msgs]
        if msgs:
            continue
        for what, value in _extremes(spec, nom):
            reason = invalid_reason(apply_values(nominal, {path: value}))
            if reason:
                out.append((("dispersions", path), f"can produce an invalid scenario: at {what} -> {reason}"))
                break
    return out


def units(scn: Scenario) -> dict[str, str]:
    """The unit of every dispersion column of a scenario's ``trials.parquet``."""
    if scn.dispersions is None:
        return {}
    nominal = scn.model_dump(mode="python")
    out = {}
    for path, spec in scn.dispersions.specs.items():
        for name in component_names(path, np.shape(get_path(nominal, path))):
            out[name] = DISPERSIBLE[path]
        if spec.dist == "uniform_direction":
            out[f"|{path}|"] = DISPERSIBLE[path]
    return out
