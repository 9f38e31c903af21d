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


def random_states(rng, B: int = 4, N: int = 3):
    """``(B, 13 + 3N + 2)`` random states near case B's geometry: unit quaternions, points ~1 m, target ~40 m out."""
    import numpy as np

    from stereopose_mc.core import quaternion as qt, state as st

    q = qt.normalize(rng.standard_normal((B, 4)))
    pts = rng.standard_normal((B, N, 3))
    return st.assemble(rng.standard_normal((B, 3)) + [0, 40, 0], 1e-2 * rng.standard_normal((B, 3)),
                       1e-2 * rng.standard_normal((B, 3)), q, pts, 0.2 * rng.standard_normal((B, 2)))  # fmt: skip
