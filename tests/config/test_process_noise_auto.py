"""``process_noise: auto`` (config/resolve.py ``process_noise_of``): the Q it resolves to, and its errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from stereopose_mc.config import ScenarioError, load_scenario_text
from stereopose_mc.config.resolve import DEG, filter_setup_of, setup_of
from stereopose_mc.config.warnings import process_noise_notes
from stereopose_mc.core import state as st
from stereopose_mc.core.unmodelled import gravity_gradient_alpha, j2_differential

ROOT = Path(__file__).resolve().parents[2]
REALISTIC = yaml.safe_load((ROOT / "configs" / "mission-realistic.yaml").read_text())
CASE_B = yaml.safe_load((ROOT / "configs" / "caseB.yaml").read_text())
DEFAULTS = {"rho": 1e-8, "rho_dot": 1e-12, "omega": 1e-10 * DEG**2, "q": 3e-11, "feature_points": 3e-10, "k": 1e-10}


def with_filters(base: dict, *filters) -> str:
    return yaml.safe_dump({**base, "filters": list(filters)}, sort_keys=False)


def blocks(text: str) -> list[dict[str, np.ndarray]]:
    scn = load_scenario_text(text, "s.yaml")
    s = setup_of(scn)
    b = st.block_index(s.n_points)
    return [{k: filter_setup_of(f, s).Q_diag[sl] for k, sl in b.items()} for f in scn.filters]


def test_auto_on_mission_realistic_is_the_derived_diagonal():
    """J2 differential and gravity gradient from the scenario's numbers, by hand: perigee 7170 km x 0.95, the
    separation |rho_0| + |rho_dot_0| T, inclination 15 deg, the box's inertia; Q = defaults + white acceleration."""
    auto, plain = blocks(with_filters(REALISTIC, {"type": "iekf", "process_noise": "auto"}, {"type": "iekf", "name": "b"}))
    rho0, v0 = np.linalg.norm([10.0, 60.0, 10.0]), np.linalg.norm([0.01, -0.0225, -0.01])
    sep = rho0 + 100.0 * v0
    r_p = 7170e3 * 0.95 - sep
    a = j2_differential(r_p, np.sin(np.radians(15.0)), sep)
    alpha = gravity_gradient_alpha(r_p, [11.25, 13.0, 6.25])
    assert 3e-7 < a < 6e-7 and 1e-6 < alpha < 2e-6  # the magnitudes docs/filters.md quotes
    np.testing.assert_allclose(auto["rho_dot"], DEFAULTS["rho_dot"] + a**2, rtol=1e-9)
    np.testing.assert_allclose(auto["rho"], DEFAULTS["rho"] + a**2 / 3.0, rtol=1e-9)
    np.testing.assert_allclose(auto["omega"], DEFAULTS["omega"] + alpha**2, rtol=1e-9)
    for k in ("q", "feature_points", "k"):
        np.testing.assert_array_equal(auto[k], DEFAULTS[k])
    for k, v in DEFAULTS.items():  # the mapping form (here: the defaults) is unchanged
        np.testing.assert_array_equal(plain[k], v)


def test_auto_widens_the_pseudo_rows_by_the_torque_they_see_as_a_bias():
    """The pseudo rows compare the measured angular acceleration (with the truth's gravity-gradient torque) with the
    torque-free model: ``auto`` adds the variance of a bias of norm ``alpha`` (the bound above) averaged over the
    run's 100 rows, ``100 alpha^2 / 3``, in quadrature to the scenario's 1e-6 rad/s^2; nothing without ``auto`` or
    without a truth model."""
    scn = load_scenario_text(with_filters(REALISTIC, {"type": "iekf", "process_noise": "auto"},
                                          {"type": "iekf", "name": "b"}), "s.yaml")  # fmt: skip
    s = setup_of(scn)
    auto, plain = (filter_setup_of(f, s).sigma_alpha for f in scn.filters)
    sep = np.linalg.norm([10.0, 60.0, 10.0]) + 100.0 * np.linalg.norm([0.01, -0.0225, -0.01])
    alpha = gravity_gradient_alpha(7170e3 * 0.95 - sep, [11.25, 13.0, 6.25])
    assert plain == 1e-6
    np.testing.assert_allclose(auto, np.sqrt(1e-12 + 100.0 * alpha**2 / 3.0), rtol=1e-12)
    assert 8e-6 < auto < 9e-6
    assert "pseudo rows' sigma + 8." in process_noise_notes(scn)[0][1]
    b = load_scenario_text(with_filters(CASE_B, {"type": "iekf", "process_noise": "auto"}), "s.yaml")
    assert filter_setup_of(b.filters[0], setup_of(b)).sigma_alpha == setup_of(b).sigma_alpha


def test_auto_adds_to_given_blocks_and_mapping_form():
    """Beside ``auto`` the given blocks are the base the derived Q adds to; a plain mapping is taken as it is."""
    given, short, mapping = blocks(with_filters(
        REALISTIC, {"type": "iekf", "process_noise": {"auto": True, "omega_deg2ps2": 2e-9, "q": 1e-9}},
        {"type": "iekf", "name": "b", "process_noise": "auto"},
        {"type": "ekf", "process_noise": {"rho_m2": 2e-8, "omega_deg2ps2": 3e-9}}))  # fmt: skip
    np.testing.assert_allclose(given["omega"], 2e-9 * DEG**2 + short["omega"] - DEFAULTS["omega"], rtol=1e-12)
    np.testing.assert_array_equal(given["q"], 1e-9)
    np.testing.assert_array_equal(given["rho_dot"], short["rho_dot"])
    assert given["rho_dot"][0] > DEFAULTS["rho_dot"]
    np.testing.assert_array_equal(mapping["rho"], 2e-8)
    np.testing.assert_array_equal(mapping["omega"], 3e-9 * DEG**2)
    np.testing.assert_array_equal(mapping["rho_dot"], DEFAULTS["rho_dot"])


def test_auto_survives_the_run_directory_round_trip():
    """A run stores its scenario as JSON (every block written out): it resolves to the same Q."""
    from stereopose_mc.config.schema import Scenario

    scn = load_scenario_text(with_filters(REALISTIC, {"type": "iekf", "process_noise": "auto"}), "s.yaml")
    again = Scenario.model_validate_json(scn.model_dump_json())
    q1, q2 = (filter_setup_of(x.filters[0], setup_of(x)).Q_diag for x in (scn, again))
    np.testing.assert_array_equal(q1, q2)


def test_auto_without_truth_model_is_the_defaults():
    (auto,) = blocks(with_filters(CASE_B, {"type": "iekf", "process_noise": "auto"}))
    for k, v in DEFAULTS.items():
        np.testing.assert_array_equal(auto[k], v)
    scn = load_scenario_text(with_filters(CASE_B, {"type": "iekf", "process_noise": "auto"}), "s.yaml")
    assert "the defaults" in process_noise_notes(scn)[0][1]


def test_note_names_the_values():
    scn = load_scenario_text(with_filters(REALISTIC, {"type": "iekf"}, {"type": "iekf", "name": "a",
                                                                        "process_noise": "auto"}), "s.yaml")  # fmt: skip
    ((loc, line),) = process_noise_notes(scn)
    assert loc == ("filters", 1, "process_noise")
    assert line.startswith("process_noise auto: rho ") and "J2 differential 4." in line and "gravity gradient 1." in line


@pytest.mark.parametrize("value, path, fragment", [
    ("autoo", "filters.0.process_noise", "must be 'auto' or a mapping of per-block variances (got 'autoo')"),
    (3, "filters.0.process_noise", "must be a mapping"),
    ({"auto": "maybe"}, "filters.0.process_noise.auto", "valid boolean"),
    ({"auto": True, "rho_m2": -1.0}, "filters.0.process_noise.rho_m2", "greater than or equal to 0"),
    ({"atuo": True}, "filters.0.process_noise.atuo", "unknown key (did you mean 'auto'?)"),
])  # fmt: skip
def test_bad_values_give_one_line(value, path, fragment):
    with pytest.raises(ScenarioError) as exc:
        load_scenario_text(with_filters(REALISTIC, {"type": "iekf", "process_noise": value}), "bad.yaml")
    (p,) = exc.value.problems
    assert p.path == path and fragment in p.message and "\n" not in str(p)


def test_tune_starts_from_auto_and_writes_it_out():
    """``spmc tune`` on an ``auto`` entry starts from the values it resolves to; its tuned Q are those values in full,
    so the tuned entry has no ``auto`` (the derived part would be added twice), and keeps the pseudo rows' sigma that
    ``auto`` widened as its own ``measurement_noise``."""
    from stereopose_mc.studies.tuning import scenario_of, start_params

    scn = load_scenario_text(with_filters(REALISTIC, {"type": "iekf", "process_noise": "auto"}), "s.yaml")
    (auto,) = blocks(with_filters(REALISTIC, {"type": "iekf", "process_noise": "auto"}))
    p = start_params(scn, 0, ("q",))
    assert p["Q.omega"] * DEG**2 == pytest.approx(auto["omega"][0], rel=1e-12)
    assert p["Q.rho_dot"] == pytest.approx(auto["rho_dot"][0], rel=1e-12)
    tuned = scenario_of(scn, 0, {**p, "Q.omega": 2.0 * p["Q.omega"]})
    pn = tuned.filters[0].process_noise
    assert not pn.auto and "auto" not in pn.model_dump()
    assert pn.omega_deg2ps2 == pytest.approx(2.0 * p["Q.omega"], rel=2e-3)  # 3 significant digits
    # auto also widened the pseudo rows: without auto the tuned entry keeps that sigma as its own
    s = setup_of(scn)
    widened = filter_setup_of(scn.filters[0], s).sigma_alpha
    assert widened > 8 * s.sigma_alpha
    assert tuned.filters[0].measurement_noise.angular_acceleration_sigma_radps2 == pytest.approx(widened, rel=2e-3)
    assert filter_setup_of(tuned.filters[0], setup_of(tuned)).sigma_alpha == pytest.approx(widened, rel=2e-3)
    untouched = scenario_of(scn, 0, {"R": 2.0})
    assert untouched.filters[0].process_noise.auto
