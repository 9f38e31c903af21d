"""Scenarios in Python: load a YAML file, build one from a dict, edit one by dotted key paths.

Key paths are those of ``spmc sweep --set``: mapping keys joined by dots, ``[i]`` for a
list item (``camera.baseline_m``, ``truth_initial_state.rho_m[1]``, ``filters[0].type``).
Every scenario these functions return has passed the same validation as ``spmc validate``.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml

from ..config.loader import ScenarioError, load_scenario, load_scenario_text
from ..config.schema import Scenario
from .errors import SpmcError


def _sweep():
    """``studies.sweep`` (its key-path parser and setter), imported when used: it imports pandas."""
    from ..studies import sweep

    return sweep


def load(path: str | Path) -> Scenario:
    """The scenario of a YAML file; :class:`SpmcError` lists every problem as ``FILE:LINE: key.path: message``."""
    try:
        return load_scenario(path)
    except ScenarioError as exc:
        raise SpmcError([str(p) for p in exc.problems]) from None


def _plain(v: Any) -> Any:
    """numpy scalars and arrays, tuples -> plain YAML data."""
    if hasattr(v, "tolist"):
        return v.tolist()
    if isinstance(v, Mapping):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    return v


def from_dict(data: Mapping[str, Any], where: str = "<dict>") -> Scenario:
    """A scenario from a mapping shaped like a scenario file (``where`` names it in error messages).

    Problems are ``WHERE: key.path: message`` (no line numbers: there is no file).
    """
    if not isinstance(data, Mapping):
        raise SpmcError(f"{where}: a scenario is a mapping of keys to values, not a {type(data).__name__}")
    try:
        text = yaml.safe_dump(_plain(dict(data)), sort_keys=False)
    except yaml.YAMLError as exc:
        raise SpmcError(f"{where}: not plain data (numbers, text, lists, mappings): {exc}") from None
    try:
        return load_scenario_text(text, where)
    except ScenarioError as exc:
        raise SpmcError([str(dataclasses.replace(p, line=None)) for p in exc.problems]) from None


def _changes(changes: Mapping[str, Any] | Sequence[str]) -> list[tuple[str, Any]]:
    """``{PATH: value}`` or ``["PATH=VALUE", ...]`` (values read as YAML, as ``--set`` reads them)."""
    sw = _sweep()
    if isinstance(changes, Mapping):
        items = [(str(k), _plain(v)) for k, v in changes.items()]
    else:
        items = []
        for text in changes:
            try:
                axis = sw.parse_set(text)
            except sw.SweepError as exc:
                raise SpmcError(str(exc)) from None
            if len(axis.values) != 1:
                raise SpmcError(f"{text!r}: one value per key path (a list is written [a, b])")
            items.append((axis.path, axis.values[0]))
    for path, _ in items:
        if not sw.is_key_path(path):
            raise SpmcError(f"{path!r} is not a key path (a.b.c, a.b[1])")
    return items


def edit(scenario: Scenario, changes: Mapping[str, Any] | Sequence[str]) -> Scenario:
    """A copy of ``scenario`` with values set at key paths, validated again.

    ``changes``: ``{"camera.baseline_m": 0.5, "truth_initial_state.rho_m[1]": 60}`` or the
    ``--set`` form ``["camera.baseline_m=0.5"]`` (one value each). Mappings along a path that
    are absent are created; list items must exist.
    """
    sw = _sweep()
    items = _changes(changes)
    d = scenario.model_dump(mode="json")
    for path, value in items:
        try:
            sw.set_path(d, path, value)
        except sw.SweepError as exc:
            raise SpmcError(f"{scenario.name}: " + str(exc).replace("--set ", "", 1)) from None
    where = f"{scenario.name} with " + ", ".join(f"{p}={json.dumps(v)}" for p, v in items)
    return from_dict(d, where)


def as_scenario(scenario: Scenario | str | Path | Mapping[str, Any]) -> Scenario:
    """A :class:`Scenario`, a YAML file's path or a scenario mapping -> a validated scenario."""
    if isinstance(scenario, Scenario):
        return scenario
    if isinstance(scenario, Mapping):
        return from_dict(scenario)
    return load(scenario)


def to_yaml(scenario: Scenario) -> str:
    """The scenario as YAML text (every key, defaults included), loadable by :func:`load`."""
    return yaml.safe_dump(scenario.model_dump(mode="json"), sort_keys=False)
