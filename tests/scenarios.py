"""Helpers for tests: small scenarios built from the bundled case files."""

from __future__ import annotations

from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"


def scenario_dict(case: str = "caseB", **overrides) -> dict:
    """A bundled case as a dict, with top-level keys replaced by ``overrides``."""
    d = yaml.safe_load((CONFIGS / f"{case}.yaml").read_text())
    for k, v in overrides.items():
        if isinstance(v, dict) and isinstance(d.get(k), dict):
            d[k] = {**d[k], **v}
        else:
            d[k] = v
    return d


def write_scenario(path: Path, case: str = "caseB", **overrides) -> Path:
    path.write_text(yaml.safe_dump(scenario_dict(case, **overrides), sort_keys=False))
    return path
