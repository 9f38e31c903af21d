"""docs/scenarios.md documents every key of the schema with its current default."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest
import yaml
from pydantic import BaseModel

from stereopose_mc.config import load_scenario_text
from stereopose_mc.config.schema import Scenario

ROOT = Path(__file__).resolve().parents[2]
DOC = (ROOT / "docs" / "scenarios.md").read_text(encoding="utf-8")
HINT = "docs/scenarios.md is stale: run .venv/bin/python docs/make_scenario_table.py"


def _generator():
    spec = importlib.util.spec_from_file_location("make_scenario_table", ROOT / "docs" / "make_scenario_table.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


gen = _generator()


def _doc_rows() -> dict[str, list[str]]:
    """Table rows of the committed doc by key: ``| `key` | ... |`` -> cells."""
    rows = {}
    for line in DOC.splitlines():
        if line.startswith("| `"):
            cells = [c.strip() for c in line.strip("|").split(" | ")]
            rows[cells[0].strip("`")] = cells
    return rows


def _schema_leaves(model, prefix=""):
    out = []
    for name, f in model.model_fields.items():
        t = f.annotation
        if isinstance(t, type) and issubclass(t, BaseModel) and name != "filters":
            out += _schema_leaves(t, prefix + name + ".")
        else:
            out.append(prefix + name)
    return out


def test_generator_covers_the_schema():
    # an independent walk of the schema (pydantic's own field lists) against the generator's key list
    keys = set(gen.key_paths())
    assert set(_schema_leaves(Scenario)) <= keys
    assert {"filters[].type", "filters[].tolerance", "filters[].measurement_noise.image_sigma",
            "filters[].process_noise.k", "filters[].step_control"} <= keys  # fmt: skip


@pytest.mark.parametrize("row", gen.scenario_rows() + gen.filter_rows(), ids=lambda r: r[0])
def test_every_key_is_documented_with_its_default(row):
    key = row[0] if len(row) == 5 else f"filters[].{row[0]}"
    doc = _doc_rows()
    assert key in doc, f"{key} missing; {HINT}"
    assert row[-2] in doc[key], f"default of {key} changed; {HINT}"
    assert row[-1], f"{key} has no meaning in docs/make_scenario_table.py"


def test_minimal_scenario_from_the_required_keys_loads():
    # the doc's **required** keys are exactly what a minimal file needs
    required = [r[0] for r in gen.scenario_rows() if r[3] == "**required**"]
    assert set(required) == {
        "name", "seed", "leader.orbit.a_km", "leader.orbit.e", "target.inertia_kgm2",
        "truth_initial_state.rho_m", "truth_initial_state.rho_dot_mps", "truth_initial_state.omega_degps",
        "truth_initial_state.q", "initial_covariance.rho_m2", "initial_covariance.rho_dot_m2ps2",
        "initial_covariance.omega_deg2ps2", "initial_covariance.q", "initial_covariance.feature_points_m2",
        "initial_covariance.k",
    }  # fmt: skip
    values = {"name": "mini", "seed": 1, "leader.orbit.a_km": 7000.0, "leader.orbit.e": 0.0,
              "target.inertia_kgm2": [1.0, 2.0, 2.5], "target.feature_points_m": [[0.0, 1.0, 0.0]],
              "truth_initial_state.rho_m": [0.0, 20.0, 0.0], "truth_initial_state.rho_dot_mps": [0.0, 0.0, 0.0],
              "truth_initial_state.omega_degps": [0.0, 0.0, 0.1], "truth_initial_state.q": [2.0, 0.0, 0.0, 0.0]}  # fmt: skip
    data: dict = {}
    for key in required:
        *parents, leaf = key.split(".")
        d = data
        for p in parents:
            d = d.setdefault(p, {})
        d[leaf] = values.get(key, 1.0)
    # plus the feature points: target.feature_points_m, or feature_points with a shape (exactly one of them)
    data["target"]["feature_points_m"] = values["target.feature_points_m"]
    s = load_scenario_text(yaml.safe_dump(data), "mini.yaml")
    assert s.truth_initial_state.q == [1.0, 0.0, 0.0, 0.0]
    assert [f.type for f in s.filters] == ["iekf"] and s.trials == 100
