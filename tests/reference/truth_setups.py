"""Scenarios for the truth-model tests, loaded through the public YAML path (``load_scenario_text``)."""

from __future__ import annotations

import yaml
from scenarios import scenario_dict

from stereopose_mc.config.loader import load_scenario_text
from stereopose_mc.config.resolve import Setup, setup_of

from reference.inertial import Elements

# An eccentric (e = 0.15), inclined leader orbit and a target spinning at about 2.6 deg/s
# about a non-principal axis, with three distinct principal moments.
ECCENTRIC = dict(
    time={"dt_s": 10.0, "duration_s": 1000.0, "error_window_start_s": 10.0, "truth_rtol": 1e-12},
    leader={"orbit": {"a_km": 8000.0, "e": 0.15, "i_deg": 40.0, "raan_deg": 30.0, "argp_deg": 60.0,
                      "true_anomaly_deg": 45.0}},
    target={"inertia_kgm2": [1.0, 1.6, 2.2],
            "feature_points_m": [[1.5, 0.0, 0.0], [0.0, 1.5, 0.0], [0.0, 0.0, 1.5], [-1.06, -1.06, 0.0]]},
    truth_initial_state={"rho_m": [20.0, 80.0, -10.0], "rho_dot_mps": [0.05, -0.04, 0.02],
                         "omega_degps": [1.2, -1.8, 1.5], "q": [0.8, 0.3, -0.4, 0.2]},
)  # fmt: skip


def setup_from(**overrides) -> Setup:
    """``Setup`` of case B with top-level keys replaced (via YAML text and the loader)."""
    text = yaml.safe_dump(scenario_dict("caseB", **overrides), sort_keys=False)
    return setup_of(load_scenario_text(text, "<test>"))


def elements_of(setup: Setup) -> Elements:
    o = setup.orbit
    return Elements(a=o.a, e=o.e, i=o.i, raan=o.raan, argp=o.argp, nu0=o.nu0, mu=o.mu)
