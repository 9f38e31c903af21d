"""Warnings of ``spmc validate``: a valid scenario that probably does not do what its author meant.

One :class:`~stereopose_mc.config.loader.Problem` per warning (``file:line: key: message``, exit code 0):

- a dispersion on a quantity the filter estimates (``truth_initial_state.rho_m``, ``.rho_dot_mps``,
  ``.omega_degps``, ``target.feature_points_m``) with ``applies_to: truth`` (the default) whose spread exceeds the
  filter's initial standard deviation of that block (``initial_covariance``): the trials start with an error the
  filter's ``P0`` says is unlikely, so they are judged against a covariance that was never true.

Notes (``file:line: key: note: ...``, exit code 0): what ``process_noise: auto`` resolved to, per filter
(config/resolve.py ``process_noise_note``).

The other warning, a scenario whose cameras never see a feature point, needs the truth and the camera model: the
CLI adds it (``sim.measurements.noise_free``).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .loader import Locator, Problem, _compose
from .schema import DispersionSpec, Scenario

# dispersed key -> (its initial_covariance key, the unit of its standard deviation)
P0_OF = {
    "truth_initial_state.rho_m": ("rho_m2", "m"),
    "truth_initial_state.rho_dot_mps": ("rho_dot_m2ps2", "m/s"),
    "truth_initial_state.omega_degps": ("omega_deg2ps2", "deg/s"),
    "target.feature_points_m": ("feature_points_m2", "m"),
}


def spread(spec: DispersionSpec) -> float | None:
    """The largest standard deviation of an additive draw (normal, truncated normal, uniform); None otherwise."""
    if (spec.mode or "add") != "add":
        return None
    if spec.dist in ("normal", "truncnormal"):
        return float(np.max(np.abs(np.asarray(spec.std, float))))
    if spec.dist == "uniform":
        return float(np.max(np.abs(np.asarray(spec.high, float) - np.asarray(spec.low, float)))) / math.sqrt(12.0)
    return None


def dispersion_warnings(scn: Scenario) -> list[tuple[tuple, str]]:
    """``(key path, message)`` per estimated quantity dispersed on the truth alone beyond its ``P0`` sigma."""
    if scn.dispersions is None:
        return []
    out = []
    for key, spec in scn.dispersions.specs.items():
        if key not in P0_OF or spec.applies_to != "truth":
            continue
        s = spread(spec)
        p0_key, unit = P0_OF[key]
        sigma0 = math.sqrt(getattr(scn.initial_covariance, p0_key))
        if s is not None and s > sigma0:
            out.append((("dispersions", key), f"dispersion sigma {s:.3g} {unit} on the truth alone (applies_to: truth) "
                        f"exceeds the filter's initial sigma {sigma0:.3g} {unit} (initial_covariance.{p0_key}): the "
                        "trials start with errors their P0 calls unlikely; set applies_to: both (the estimate starts "
                        "at the dispersed value) or widen initial_covariance"))  # fmt: skip
    return out


def process_noise_notes(scn: Scenario) -> list[tuple[tuple, str]]:
    """``(key path, line)`` per filter with ``process_noise: auto``: the values it resolved to."""
    from .resolve import process_noise_note, setup_of

    auto = [i for i, f in enumerate(scn.filters) if f.process_noise.auto]
    if not auto:
        return []
    s = setup_of(scn)
    return [(("filters", i, "process_noise"), process_noise_note(scn.filters[i].process_noise, s)) for i in auto]


def scenario_warnings(path: Path, scn: Scenario, extra: list[tuple[tuple, str]] = ()) -> list[Problem]:
    """The warnings of a valid scenario file, with their lines (``extra``: more ``(key path, message)``), then
    its notes."""
    text = Path(path).read_text(encoding="utf-8")
    root, _, _ = _compose(text, str(path))
    where = Locator(root)
    items = [(loc, f"warning: {msg}") for loc, msg in dispersion_warnings(scn) + list(extra)]
    items += [(loc, f"note: {msg}") for loc, msg in process_noise_notes(scn)]
    return [Problem(str(path), where.line(loc), ".".join(map(str, loc)), msg) for loc, msg in items]
