"""Load scenario YAML files with errors that name the file, the line and the key path."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from pydantic import ValidationError

from ..core import quaternion as qt
from .schema import Scenario


@dataclass(frozen=True)
class Problem:
    """One thing wrong with a scenario file."""

    file: str
    line: int | None
    path: str
    message: str

    def __str__(self) -> str:
        where = f"{self.file}:{self.line}" if self.line is not None else self.file
        key = f" {self.path}:" if self.path else ""
        return f"{where}:{key} {self.message}"


class ScenarioError(Exception):
    """A scenario file that cannot be used; ``problems`` lists every issue found."""

    def __init__(self, problems: list[Problem]):
        self.problems = problems
        super().__init__("\n".join(str(p) for p in problems))


def _node_at(root: yaml.Node | None, loc: tuple[Any, ...]) -> yaml.Node | None:
    """The deepest YAML node along ``loc`` (pydantic's error location)."""
    node = root
    for key in loc:
        if isinstance(node, yaml.MappingNode):
            nxt = None
            for k, v in node.value:
                if isinstance(k, yaml.ScalarNode) and k.value == str(key):
                    nxt = v
                    if isinstance(key, str) and key not in {"0", "1"}:
                        pass
                    break
            if nxt is None:
                # unknown keys: point at the key itself
                return node
            node = nxt
        elif isinstance(node, yaml.SequenceNode) and isinstance(key, int):
            if 0 <= key < len(node.value):
                node = node.value[key]
            else:
                return node
        else:
            # a discriminated-union tag ('iekf', 'ekf') or a scalar: stay here
            continue
    return node


def _key_line(root: yaml.Node | None, loc: tuple[Any, ...]) -> int | None:
    """Line (1-based) of the key or item that ``loc`` points at."""
    if not loc:
        return 1
    parent = _node_at(root, loc[:-1])
    last = loc[-1]
    if isinstance(parent, yaml.MappingNode):
        for k, _ in parent.value:
            if isinstance(k, yaml.ScalarNode) and k.value == str(last):
                return k.start_mark.line + 1
    node = _node_at(root, loc)
    return node.start_mark.line + 1 if node is not None else None


def _clean_loc(loc: tuple[Any, ...]) -> tuple[Any, ...]:
    # drop the discriminator tags pydantic inserts into union locations
    return tuple(p for p in loc if p not in ("iekf", "ekf"))


def _path(loc: tuple[Any, ...]) -> str:
    return ".".join(str(p) for p in loc)


def load_scenario_text(text: str, file: str = "<string>", overrides: dict[str, Any] | None = None) -> Scenario:
    """Parse and validate scenario YAML text; raise ``ScenarioError`` listing all problems."""
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = mark.line + 1 if mark is not None else None
        msg = getattr(exc, "problem", None) or str(exc)
        raise ScenarioError([Problem(file, line, "", f"YAML syntax error: {msg}")]) from None
    if not isinstance(data, dict):
        raise ScenarioError([Problem(file, 1, "", "a scenario must be a YAML mapping of keys to values")])
    if overrides:
        data = {**data, **overrides}
    try:
        scenario = Scenario.model_validate(data)
    except ValidationError as exc:
        problems = []
        for err in exc.errors():
            loc = _clean_loc(tuple(err["loc"]))
            msg = err["msg"]
            if err["type"] == "extra_forbidden":
                msg = "unknown key"
            elif err["type"] == "missing":
                msg = "required key is missing"
            problems.append(Problem(file, _key_line(root, loc), _path(loc), msg))
        raise ScenarioError(problems) from None
    problems = [Problem(file, _key_line(root, loc), _path(loc), msg) for loc, msg in _semantic_checks(scenario)]
    if problems:
        raise ScenarioError(problems)
    return scenario


def _semantic_checks(s: Scenario) -> list[tuple[tuple[Any, ...], str]]:
    """Checks across keys that pydantic's field validators cannot see."""
    out: list[tuple[tuple[Any, ...], str]] = []
    D = qt.dcm(np.asarray(s.truth_initial_state.q))
    rho = np.asarray(s.truth_initial_state.rho_m)
    for i, p in enumerate(s.target.feature_points_m):
        y = (rho + D @ np.asarray(p))[1]
        if y <= 0.0:
            out.append(
                (("target", "feature_points_m", i), f"feature point {p} is behind the cameras at t=0 (y = {y:.3g} m <= 0)")
            )
    return out


def load_scenario(path: str | Path, overrides: dict[str, Any] | None = None) -> Scenario:
    """Load and validate a scenario YAML file."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ScenarioError([Problem(str(path), None, "", "file not found")]) from None
    except (IsADirectoryError, PermissionError, UnicodeDecodeError) as exc:
        raise ScenarioError([Problem(str(path), None, "", f"cannot read: {exc}")]) from None
    return load_scenario_text(text, str(path), overrides)
