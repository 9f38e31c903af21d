"""Scenario loader: every kind of bad file gives one line per problem with the right line and key path.

Expected line numbers are found by searching the mutated text for the changed line (an
independent reference to the YAML parser's marks), never typed in by hand.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from stereopose_mc.config import ScenarioError, load_scenario, load_scenario_text
from stereopose_mc.config.loader import Problem, problems_of
from stereopose_mc.config.resolve import filter_setup_of, setup_of

ROOT = Path(__file__).resolve().parents[2]
CASE_B = (ROOT / "configs" / "caseB.yaml").read_text()
F = "bad.yaml"


def mutate(old: str, new: str, text: str = CASE_B) -> str:
    assert text.count(old) == 1, f"{old!r} must occur once"
    return text.replace(old, new)


def line_of(text: str, needle: str) -> int:
    """1-based number of the one line of ``text`` containing ``needle``."""
    hits = [i + 1 for i, line in enumerate(text.splitlines()) if needle in line]
    assert len(hits) == 1, (needle, hits)
    return hits[0]


def problems(text: str) -> list[Problem]:
    with pytest.raises(ScenarioError) as exc:
        load_scenario_text(text, F)
    ps = exc.value.problems
    assert ps, "a ScenarioError must carry at least one problem"
    for p in ps:  # one line each, FILE:LINE: path: message
        s = str(p)
        assert "\n" not in s
        assert s.startswith(f"{F}:{p.line}: ")
        if p.path:
            assert s == f"{F}:{p.line}: {p.path}: {p.message}"
    return ps


def only(ps: list[Problem], path: str) -> Problem:
    hits = [p for p in ps if p.path == path]
    assert len(hits) == 1, [str(p) for p in ps]
    return hits[0]


# (id, old, new, needle of the expected line or None for line 1, key path, message fragment)
CASES = [
    ("unknown-key", "seed: 2014", "seed: 2014\nsede: 3", "sede: 3", "sede", "unknown key (did you mean 'seed'?)"),
    ("wrong-type", "dt_s: 1.0", "dt_s: fast", "dt_s: fast", "time.dt_s", "valid number"),
    ("wrong-type-list", "rho_m: [10.0, 60.0, 10.0]", "rho_m: 60.0", "rho_m: 60.0", "truth_initial_state.rho_m",
     "valid list"),
    ("missing-nested", "a_km: 7170.0, ", "", "orbit: {", "leader.orbit.a_km", "required key is missing"),
    ("missing-top", "seed: 2014\n", "", None, "seed", "required key is missing"),
    ("non-positive-inertia", "inertia_kgm2: [0.83, 1.0, 1.083]", "inertia_kgm2: [0.83, -1.0, 1.083]", "inertia_kgm2", "target.inertia_kgm2.1",
     "greater than 0"),
    ("zero-inertia", "inertia_kgm2: [0.83, 1.0, 1.083]", "inertia_kgm2: [0.0, 1.0, 1.083]", "inertia_kgm2", "target.inertia_kgm2.0",
     "greater than 0"),
    ("zero-quaternion", "q: [1.0, 0.0, 0.0, 0.0]", "q: [0.0, 0.0, 0.0, 0.0]", "q: [0.0", "truth_initial_state.q",
     "quaternion must be non-zero"),
    ("filter-type", "{type: ekf}", "{type: pf}", "{type: pf}", "filters.1.type",
     "unknown filter type 'pf'; expected one of 'iekf', 'ekf', 'mekf', 'ukf'"),
    ("filter-no-type", "{type: ekf}", "{name: plain}", "{name: plain}", "filters.1.type", "needs a 'type'"),
    ("filter-unknown-key", "tolerance: 0.01", "tolrance: 0.01", "tolrance", "filters.0.tolrance", "unknown key"),
    ("filter-not-mapping", "  - {type: ekf}", "  - ekf", "  - ekf", "filters.1", "must be a mapping"),
    ("filter-R-unknown-key", "{type: ekf}", "{type: ekf, measurement_noise: {imag_sigma: 1.0e-4}}", "imag_sigma",
     "filters.1.measurement_noise.imag_sigma", "unknown key (did you mean 'image_sigma'?)"),
    ("nan", "image_sigma: 1.0e-5", "image_sigma: .nan", ".nan", "measurements.image_sigma",
     "must be a finite number (got nan)"),
    ("inf-in-list", "omega_degps: [-0.1, -0.1, 0.034]", "omega_degps: [-0.1, -.inf, 0.034]", "-.inf",
     "truth_initial_state.omega_degps.1", "must be a finite number (got -inf)"),
    ("inf-point", "- [0.0, 1.5, 0.0]", "- [0.0, .inf, 0.0]", ".inf", "target.feature_points_m.1.1", "finite"),
    ("boolean-number", "trials: 100", "trials: yes", "trials: yes", "trials", "not a boolean"),
    ("boolean-in-vector", "rho_m: [10.0, 60.0, 10.0]", "rho_m: [10.0, 60.0, on]", "60.0, on]", "truth_initial_state.rho_m.2",
     "not a boolean"),
    ("whole-steps", "dt_s: 1.0", "dt_s: 0.3", "dt_s: 0.3", "time", "whole number of dt_s"),
    ("duplicate-filter-label", "{type: ekf}", "{type: iekf}", "filters:", "filters", "labels must be unique"),
    ("bad-enum", "{type: ekf}", "{type: ekf, transition: magic}", "magic", "filters.1.transition", "'expm' or 'taylor'"),
    ("ukf-gate", "{type: ekf}", "{type: ukf, gating: {probability: 0.999}}", "gating", "filters.1.gating",
     "the UKF has no innovation gate"),
]  # fmt: skip


@pytest.mark.parametrize("old,new,needle,path,fragment", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_each_bad_kind_names_line_and_path(old, new, needle, path, fragment):
    text = mutate(old, new)
    p = only(problems(text), path)
    assert fragment in p.message
    assert p.line == (1 if needle is None else line_of(text, needle))


@pytest.mark.parametrize("key", ["rho_m2", "rho_dot_m2ps2", "omega_deg2ps2", "q", "feature_points_m2", "k"])
def test_negative_variance_each_block(key):
    text = re.sub(rf"([{{ ]{key}: )([0-9.e-]+)", r"\1-0.5", CASE_B.replace("initial_covariance:", "initial_covariance:"))
    # only the initial_covariance line is changed (the other 'q:' is a list, not a number)
    changed = [a for a, b in zip(CASE_B.splitlines(), text.splitlines()) if a != b]
    assert len(changed) == 1 and changed[0].startswith("initial_covariance:")
    ps = problems(text)
    assert len(ps) == 1
    p = ps[0]
    assert p.path == f"initial_covariance.{key}"
    assert p.line == line_of(text, "initial_covariance:")
    assert "greater than or equal to 0" in p.message and "-0.5" in p.message


def test_feature_point_behind_cameras_identity():
    # q0 = identity: y_i = rho_y + P_iy; with rho_y = 1 points 3 and 4 (P_y = -1.06) have y = -0.06.
    text = mutate("rho_m: [10.0, 60.0, 10.0]", "rho_m: [10.0, 1.0, 10.0]")
    ps = problems(text)
    assert [p.path for p in ps] == ["target.feature_points_m.3", "target.feature_points_m.4"]
    assert ps[0].line == line_of(text, "[-1.06, -1.06, 0.0]")
    assert ps[1].line == line_of(text, "[0.0, -1.06, -1.06]")
    assert all("behind the cameras at t=0" in p.message and "y = -0.06 m" in p.message for p in ps)


def test_feature_point_behind_cameras_uses_the_rotation():
    # q0 = 90 deg about z (scalar first): D = R_z(90), D [1.5, 0, 0] = [0, 1.5, 0], D [-1.5, 0, 0] = [0, -1.5, 0].
    c, s = math.cos(math.pi / 4), math.sin(math.pi / 4)
    pts = "    - [1.5, 0.0, 0.0]\n    - [-1.5, 0.0, 0.0]\n"
    text = re.sub(r"  feature_points_m:\n(    - .*\n)+", "  feature_points_m:\n" + pts, CASE_B)
    text = mutate("rho_m: [10.0, 60.0, 10.0]", "rho_m: [10.0, 1.0, 10.0]", text)
    ok = load_scenario_text(text, F)  # identity: both points at y = 1 > 0
    assert len(ok.target.feature_points_m) == 2
    text = mutate("q: [1.0, 0.0, 0.0, 0.0]", f"q: [{c!r}, 0.0, 0.0, {s!r}]", text)
    ps = problems(text)
    assert [p.path for p in ps] == ["target.feature_points_m.1"]
    assert "y = -0.5 m" in ps[0].message
    assert ps[0].line == line_of(text, "[-1.5, 0.0, 0.0]")


def test_duplicate_keys_name_both_lines():
    text = mutate("trials: 100", "trials: 100\nseed: 7")
    p = only(problems(text), "seed")
    first, again = line_of(text, "seed: 2014"), line_of(text, "seed: 7")
    assert p.line == again
    assert f"first at line {first}, again at line {again}" in p.message


def test_duplicate_key_in_flow_mapping_and_nested():
    text = mutate("camera: {baseline_m: 1.0, focal_length: 1.0}", "camera: {baseline_m: 1.0, baseline_m: 2.0}")
    text = mutate("  flow_sigma: 1.0e-5", "  flow_sigma: 1.0e-5\n  flow_sigma: 2.0e-5", text)
    ps = problems(text)
    cam = only(ps, "camera.baseline_m")
    assert cam.line == line_of(text, "camera:") and "twice on line" in cam.message
    fl = only(ps, "measurements.flow_sigma")
    assert fl.line == line_of(text, "flow_sigma: 2.0e-5")
    assert f"first at line {line_of(text, 'flow_sigma: 1.0e-5')}" in fl.message


def test_merge_keys_are_not_duplicates():
    text = mutate(
        "camera: {baseline_m: 1.0, focal_length: 1.0}",
        "camera:\n  <<: {baseline_m: 1.0, focal_length: 1.0}\n  baseline_m: 0.5",
    )
    assert load_scenario_text(text, F).camera.baseline_m == 0.5


def test_zero_truth_noise_needs_filter_R():
    text = mutate("image_sigma: 1.0e-5", "image_sigma: 0")
    ps = problems(text)
    assert [p.path for p in ps] == ["filters.0.measurement_noise.image_sigma", "filters.1.measurement_noise.image_sigma"]
    assert ps[0].line == line_of(text, "{type: iekf")
    assert ps[1].line == line_of(text, "{type: ekf}")
    assert all("the filter's R must be positive: set it when the truth noise is 0" in p.message for p in ps)
    # setting the filters' own R fixes it, and the filters then use it
    fixed = mutate("{type: ekf}", "{type: ekf, measurement_noise: {image_sigma: 3.0e-5}}", text)
    fixed = mutate("max_iterations: 10}", "max_iterations: 10, measurement_noise: {image_sigma: 2.0e-5}}", fixed)
    s = load_scenario_text(fixed, F)
    setup = setup_of(s)
    assert setup.sigma_image == 0.0
    assert [filter_setup_of(f, setup).sigma_image for f in s.filters] == [2.0e-5, 3.0e-5]


def test_zero_flow_noise_with_default_filters_points_at_top():
    text = re.sub(r"filters:\n(  - .*\n)+", "", mutate("flow_sigma: 1.0e-5", "flow_sigma: 0.0"))
    ps = problems(text)
    assert [(p.path, p.line) for p in ps] == [("filters.0.measurement_noise.flow_sigma", 1)]


def test_zero_disparity_noise_when_enabled():
    text = mutate("disparity: false", "disparity: true\n  disparity_sigma: 0.0")
    ps = problems(text)
    assert [p.path for p in ps] == [f"filters.{k}.measurement_noise.disparity_sigma" for k in (0, 1)]
    # disabled disparity channel: a zero disparity noise does not matter
    load_scenario_text(mutate("disparity: false", "disparity: false\n  disparity_sigma: 0.0"), F)


def test_all_problems_are_collected_in_line_order():
    text = CASE_B
    for old, new in [
        ("seed: 2014", "seed: 2014\nsede: 3"),
        ("dt_s: 1.0", "dt_s: fast"),
        ("inertia_kgm2: [0.83, 1.0, 1.083]", "inertia_kgm2: [0.83, -1.0, 1.083]"),
        ("q: [1.0, 0.0, 0.0, 0.0]", "q: [0.0, 0.0, 0.0, 0.0]"),
        ("{type: ekf}", "{type: pf}"),
        ("rho_m2: 1.0, rho_dot", "rho_m2: -1.0, rho_dot"),
        ("image_sigma: 1.0e-5", "image_sigma: .inf"),
    ]:
        text = mutate(old, new, text)
    ps = problems(text)
    assert [p.path for p in ps] == [
        "sede", "time.dt_s", "target.inertia_kgm2.1", "truth_initial_state.q", "measurements.image_sigma",
        "initial_covariance.rho_m2", "filters.1.type",
    ]  # fmt: skip
    assert [p.line for p in ps] == sorted(p.line for p in ps)


@pytest.mark.parametrize(
    "old,new,needle",
    [
        ("trials: 100", "trials: 100: 3", "trials: 100: 3"),  # mapping values not allowed here
        ("seed: 2014", "seed: 2014\n   oops: 1", "oops"),  # bad indentation
        ("seed: 2014", "seed: 2014\n\tx: 1", "\tx: 1"),  # a tab
    ],
)
def test_yaml_syntax_error_line(old, new, needle):
    text = mutate(old, new)
    ps = problems(text)
    assert len(ps) == 1 and ps[0].path == "" and ps[0].message.startswith("YAML syntax error: ")
    assert ps[0].line == line_of(text, needle)


@pytest.mark.parametrize(
    "text,fragment",
    [("", "the file is empty"), ("# nothing\n\n", "the file is empty"), ("- 1\n- 2\n", "not a list"),
     ("42\n", "not a int"), ("just words\n", "not a str"), ("a: 1\n---\nb: 2\n", "YAML syntax error")],
)  # fmt: skip
def test_whole_file_problems(text, fragment):
    ps = problems(text)
    assert len(ps) == 1 and ps[0].path == "" and fragment in ps[0].message
    assert ps[0].line is not None and ps[0].line >= 1


def test_missing_file_and_directory(tmp_path):
    for path, fragment in [(tmp_path / "nope.yaml", "file not found"), (tmp_path, "is a directory")]:
        with pytest.raises(ScenarioError) as exc:
            load_scenario(path)
        (p,) = exc.value.problems
        assert str(p) == f"{path}: {p.message}" and fragment in p.message


def test_not_utf8(tmp_path):
    f = tmp_path / "latin1.yaml"
    f.write_bytes("name: caf\xe9\n".encode("latin-1"))
    with pytest.raises(ScenarioError) as exc:
        load_scenario(f)
    assert "not UTF-8" in exc.value.problems[0].message


def _key_occurrences(text: str) -> list[tuple[int, int, str]]:
    """(line, column, key) of every mapping key of the YAML text (comments and strings skipped)."""
    out = []
    for i, line in enumerate(text.splitlines()):
        code = line.split("#", 1)[0]
        code = re.sub(r'"[^"]*"', lambda m: " " * len(m.group()), code)
        for m in re.finditer(r"(?<![\w.\-])([a-z_][a-z0-9_]*):(?=\s|$)", code):
            out.append((i + 1, m.start(1), m.group(1)))
    return out


KEYS = _key_occurrences(CASE_B)


def test_key_scan_finds_the_keys():
    assert len(KEYS) > 40
    assert {k for _, _, k in KEYS} >= {"a_km", "tolerance", "feature_points_m", "rho_m2", "type", "enabled"}


@pytest.mark.parametrize("line,col,key", KEYS, ids=[f"{ln}:{k}" for ln, _, k in KEYS])
def test_renaming_any_key_points_at_that_line(line, col, key):
    lines = CASE_B.splitlines(keepends=True)
    lines[line - 1] = lines[line - 1][:col] + key + "x" + lines[line - 1][col + len(key) :]
    ps = problems("".join(lines))
    if key == "type":  # a filter entry without a type: the discriminator is missing
        hit = [p for p in ps if p.path.endswith(".type") and p.line == line]
        assert hit and "needs a 'type'" in hit[0].message
        return
    hit = [p for p in ps if p.path.split(".")[-1] == key + "x"]
    assert len(hit) == 1, [str(p) for p in ps]
    assert hit[0].line == line and hit[0].message.startswith("unknown key")
    assert f"did you mean '{key}'" in hit[0].message
    # any other problem is the renamed key now missing, reported at the parent's line or line 1
    for p in ps:
        if p is not hit[0]:
            assert p.message == "required key is missing" and p.path.split(".")[-1] == key
            assert p.line <= line


@pytest.mark.parametrize("case", "ABCDEF")
def test_dump_and_reload_is_identity(case):
    s = load_scenario(ROOT / "configs" / f"case{case}.yaml")
    again = load_scenario_text(yaml.safe_dump(s.model_dump(mode="json"), sort_keys=False), F)
    assert again == s
    assert np.isclose(np.linalg.norm(again.truth_initial_state.q), 1.0)


def test_problems_of_returns_the_scenario_when_clean():
    ps, s = problems_of(CASE_B, F)
    assert ps == [] and s is not None and s.name == "caseB"
