"""``spmc validate`` and ``spmc simulate`` through the command line (typer's CliRunner)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from stereopose_mc.cli.main import app
from stereopose_mc.config import load_scenario
from stereopose_mc.core import camera, state as st

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
CASE_B = (CONFIGS / "caseB.yaml").read_text()
runner = CliRunner()

TRUTH_FIRST = ["t", "nu", "rho_x", "rho_y", "rho_z", "rho_dot_x", "rho_dot_y", "rho_dot_z",
               "omega_x", "omega_y", "omega_z", "q0", "q1", "q2", "q3"]  # fmt: skip
MEAS = ["t", "feature", "u_r", "v_r", "u_l", "v_l", "du_r", "dv_r", "du_l", "dv_l"]


def spmc(*args: str):
    return runner.invoke(app, [str(a) for a in args])


def write(tmp_path: Path, name: str, text: str) -> Path:
    f = tmp_path / name
    f.write_text(text)
    return f


def mutate(old: str, new: str, text: str = CASE_B) -> str:
    assert text.count(old) == 1
    return text.replace(old, new)


def line_of(text: str, needle: str) -> int:
    hits = [i + 1 for i, line in enumerate(text.splitlines()) if needle in line]
    assert len(hits) == 1, (needle, hits)
    return hits[0]


# ------------------------------------------------------------------ spmc validate


def test_validate_all_configs():
    files = sorted(CONFIGS.glob("*.yaml"))
    assert {f"case{c}" for c in "ABCDEF"} <= {f.stem for f in files}
    r = spmc("validate", *files)
    assert r.exit_code == 0, r.output
    assert r.stdout.splitlines() == [f"ok: {f}" for f in files]
    # the Sobol debris campaign disperses the along-track range beyond P0 on the truth alone (a factor of its
    # sensitivity study, on purpose); validate says so, and nothing else (mission-debris's P0 covers its range);
    # mission-realistic's `process_noise: auto` gets its note (what it resolved to)
    lines = r.stderr.splitlines()
    warned = sorted(ln.split(":")[0] for ln in lines if ": warning: " in ln)
    assert warned == [str(CONFIGS / "mission-debris-sobol.yaml")], r.stderr
    assert all("dispersions.truth_initial_state.rho_m: warning: " in ln for ln in lines if ": warning: " in ln)
    notes = [ln for ln in lines if ": warning: " not in ln]
    assert len(notes) == 1 and notes[0].startswith(str(CONFIGS / "mission-realistic.yaml")), r.stderr
    assert "filters.0.process_noise: note: process_noise auto: " in notes[0]


# (id, old, new, needle of the line (None: line 1), key path, message fragment)
BAD = [
    ("syntax", "trials: 100", "trials: 100: 3", "trials: 100: 3", "", "YAML syntax error"),
    ("unknown-key", "seed: 2014", "seed: 2014\nsede: 3", "sede: 3", "sede", "unknown key"),
    ("wrong-type", "dt_s: 1.0", "dt_s: fast", "dt_s: fast", "time.dt_s", "valid number"),
    ("missing-key", "a_km: 7170.0, ", "", "orbit: {", "leader.orbit.a_km", "required key is missing"),
    ("missing-top", "seed: 2014\n", "", None, "seed", "required key is missing"),
    ("negative-variance", "omega_deg2ps2: 1.0, q: 1.0e-5", "omega_deg2ps2: -1.0, q: 1.0e-5", "initial_covariance",
     "initial_covariance.omega_deg2ps2", "greater than or equal to 0"),
    ("inertia", "inertia_kgm2: [0.83, 1.0, 1.083]", "inertia_kgm2: [0.83, 1.0, 0.0]", "inertia_kgm2",
     "target.inertia_kgm2.2", "greater than 0"),
    ("zero-quaternion", "q: [1.0, 0.0, 0.0, 0.0]", "q: [0, 0, 0, 0]", "q: [0, 0, 0, 0]", "truth_initial_state.q",
     "non-zero"),
    ("behind", "rho_m: [10.0, 60.0, 10.0]", "rho_m: [10.0, 1.0, 10.0]", "[-1.06, -1.06, 0.0]",
     "target.feature_points_m.3", "behind the cameras at t=0"),
    ("filter-type", "{type: ekf}", "{type: kalman}", "{type: kalman}", "filters.1.type",
     "unknown filter type 'kalman'; expected one of 'iekf', 'ekf'"),
    ("filter-key", "tolerance: 0.01", "tolrance: 0.01", "tolrance", "filters.0.tolrance", "unknown key"),
    ("duplicate", "trials: 100", "trials: 100\ntrials: 50", "trials: 50", "trials", "duplicate key (first at line"),
    ("nan", "flow_sigma: 1.0e-5", "flow_sigma: .nan", ".nan", "measurements.flow_sigma", "finite number"),
    ("inf", "baseline_m: 1.0", "baseline_m: .inf", ".inf", "camera.baseline_m", "finite number"),
    ("zero-noise", "image_sigma: 1.0e-5", "image_sigma: 0.0", "{type: ekf}", "filters.1.measurement_noise.image_sigma",
     "the filter's R must be positive"),
]  # fmt: skip


@pytest.mark.parametrize("old,new,needle,path,fragment", [b[1:] for b in BAD], ids=[b[0] for b in BAD])
def test_validate_bad_file(tmp_path, old, new, needle, path, fragment):
    text = mutate(old, new)
    f = write(tmp_path, "bad.yaml", text)
    r = spmc("validate", f)
    assert r.exit_code == 2
    assert r.stdout == ""
    line = 1 if needle is None else line_of(text, needle)
    prefix = f"error: {f}:{line}: " + (f"{path}: " if path else "")
    hits = [ln for ln in r.stderr.splitlines() if ln.startswith(prefix)]
    assert len(hits) == 1, r.stderr
    assert fragment in hits[0]
    # every stderr line has the FILE:LINE: form
    assert all(re.match(rf"error: {re.escape(str(f))}:\d+: ", ln) for ln in r.stderr.splitlines())


def test_validate_whole_file_problems(tmp_path):
    empty = write(tmp_path, "empty.yaml", "")
    lst = write(tmp_path, "list.yaml", "- 1\n- 2\n")
    missing = tmp_path / "missing.yaml"
    good = CONFIGS / "caseA.yaml"
    r = spmc("validate", empty, good, lst, missing)
    assert r.exit_code == 2
    assert r.stdout.splitlines() == [f"ok: {good}"]
    assert r.stderr.splitlines() == [
        f"error: {empty}:1: the file is empty; a scenario is a YAML mapping of keys to values",
        f"error: {lst}:1: a scenario must be a YAML mapping of keys to values, not a list",
        f"error: {missing}: file not found",
    ]


def test_validate_reports_every_problem_of_a_file(tmp_path):
    text = mutate("dt_s: 1.0", "dt_s: -1.0", mutate("{type: ekf}", "{type: ekf, bogus: 1}"))
    f = write(tmp_path, "two.yaml", text)
    r = spmc("validate", f)
    assert r.exit_code == 2
    assert r.stderr.splitlines() == [
        f"error: {f}:{line_of(text, 'dt_s: -1.0')}: time.dt_s: Input should be greater than 0 (got -1.0)",
        f"error: {f}:{line_of(text, 'bogus')}: filters.1.bogus: unknown key",
    ]


# ------------------------------------------------------------------ spmc simulate


def test_simulate_bad_file_writes_nothing(tmp_path):
    f = write(tmp_path, "bad.yaml", mutate("seed: 2014", "seed: 2014\nsede: 3"))
    out = tmp_path / "out"
    r = spmc("simulate", f, "--out", out)
    assert r.exit_code == 2 and "sede: unknown key" in r.stderr
    assert not out.exists()


@pytest.fixture(scope="module")
def sim_dirs(tmp_path_factory):
    """caseB simulated: noisy (scenario seed), noisy (seed 7, twice), and noise-free."""
    base = tmp_path_factory.mktemp("sim")
    runs = {"noisy": [], "seed7": ["--seed", "7"], "seed7b": ["--seed", "7"], "exact": ["--no-noise"]}
    for name, extra in runs.items():
        r = spmc("simulate", CONFIGS / "caseB.yaml", "--out", base / name, *extra)
        assert r.exit_code == 0, r.output
        assert str(base / name) in r.stdout
    return base


def test_simulate_writes_the_four_files(sim_dirs):
    d = sim_dirs / "noisy"
    assert sorted(p.name for p in d.iterdir()) == ["config.yaml", "manifest.json", "measurements.parquet",
                                                    "truth.parquet"]  # fmt: skip
    truth = pd.read_parquet(d / "truth.parquet")
    meas = pd.read_parquet(d / "measurements.parquet")
    assert list(truth.columns[: len(TRUTH_FIRST)]) == TRUTH_FIRST
    assert list(meas.columns) == MEAS
    assert np.array_equal(truth["t"], np.arange(101.0))
    assert len(meas) == 101 * 5  # every feature visible at every step in case B
    assert load_scenario(d / "config.yaml") == load_scenario(CONFIGS / "caseB.yaml")
    man = json.loads((d / "manifest.json").read_text())
    assert man["kind"] == "simulate" and man["scenario"] == "caseB" and man["seed"] == 2014 and man["noise"] is True


def _state(truth: pd.DataFrame, scenario) -> np.ndarray:
    """The full state (K+1, n) from truth.parquet and the scenario's fixed points and inertia ratios."""
    pts = np.asarray(scenario.target.feature_points_m, dtype=float)
    k = st.k_from_inertia(np.asarray(scenario.target.inertia_kgm2, dtype=float))
    x = np.empty((len(truth), st.size(len(pts))))
    x[:, :13] = truth[TRUTH_FIRST[2:]].to_numpy()
    x[:, st.points_slice(len(pts))] = pts.reshape(-1)
    x[:, st.k_slice(len(pts))] = k
    return x


def _by_hand(truth: pd.DataFrame, pts: np.ndarray, b: float) -> np.ndarray:
    """u, v and their rates from rho_i = rho + R P_i, rho_i' = rho' + w x R P_i (R from scipy, scalar last)."""
    q = truth[["q1", "q2", "q3", "q0"]].to_numpy()
    R = Rotation.from_quat(q).as_matrix()  # (K+1, 3, 3)
    r = np.einsum("kij,nj->kni", R, pts)
    p = truth[["rho_x", "rho_y", "rho_z"]].to_numpy()[:, None] + r
    w = truth[["omega_x", "omega_y", "omega_z"]].to_numpy()[:, None]
    v = truth[["rho_dot_x", "rho_dot_y", "rho_dot_z"]].to_numpy()[:, None] + np.cross(w, r)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    vx, vy, vz = v[..., 0], v[..., 1], v[..., 2]
    cols = [x / y, z / y, (x - b) / y, z / y, (vx * y - x * vy) / y**2, (vz * y - z * vy) / y**2,
            (vx * y - (x - b) * vy) / y**2, (vz * y - z * vy) / y**2, -b / y]  # fmt: skip
    return np.stack(cols, axis=-1)


def test_no_noise_measurements_are_h_of_the_truth(sim_dirs):
    s = load_scenario(CONFIGS / "caseB.yaml")
    truth = pd.read_parquet(sim_dirs / "exact" / "truth.parquet")
    meas = pd.read_parquet(sim_dirs / "exact" / "measurements.parquet").sort_values(["t", "feature"])
    y = meas[MEAS[2:]].to_numpy().reshape(len(truth), 5, 8)
    h = camera.h_features(_state(truth, s), s.camera.baseline_m)
    np.testing.assert_array_equal(y, h)
    hand = _by_hand(truth, np.asarray(s.target.feature_points_m), s.camera.baseline_m)[..., :8]
    np.testing.assert_allclose(y, hand, rtol=1e-12, atol=1e-15)
    # the noise-free angular acceleration is the truth's
    np.testing.assert_array_equal(truth[["alpha_meas_x", "alpha_meas_y", "alpha_meas_z"]].to_numpy(),
                                  truth[["alpha_x", "alpha_y", "alpha_z"]].to_numpy())  # fmt: skip


def test_seed_changes_the_noise_and_only_the_noise(sim_dirs):
    read = {n: pd.read_parquet(sim_dirs / n / "measurements.parquet") for n in ("noisy", "seed7", "seed7b", "exact")}
    truths = [pd.read_parquet(sim_dirs / n / "truth.parquet")[TRUTH_FIRST] for n in ("noisy", "seed7", "exact")]
    assert all(t.equals(truths[0]) for t in truths)
    pd.testing.assert_frame_equal(read["seed7"], read["seed7b"])  # same seed, same numbers
    e = read["exact"][MEAS[2:]].to_numpy()
    d1 = read["noisy"][MEAS[2:]].to_numpy() - e
    d7 = read["seed7"][MEAS[2:]].to_numpy() - e
    assert not np.any(d1 == d7)
    # the noise is N(0, 1e-5^2) per channel: 4040 samples, so the sample std is within 5 % (>4 sigma)
    for d in (d1, d7):
        assert abs(d.std() / 1e-5 - 1) < 0.05 and abs(d.mean()) < 5 * 1e-5 / np.sqrt(d.size)
    assert abs(np.corrcoef(d1.ravel(), d7.ravel())[0, 1]) < 0.07


def test_simulate_refuses_non_empty_out(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    r = spmc("simulate", CONFIGS / "caseB.yaml", "--out", out, "--no-noise")
    assert r.exit_code == 2 and "--overwrite" in r.stderr
    assert [p.name for p in out.iterdir()] == ["keep.txt"]
    r = spmc("simulate", CONFIGS / "caseB.yaml", "--out", out, "--no-noise", "--overwrite")
    assert r.exit_code == 2 and "not a run, sweep or simulation directory" in r.stderr  # issue 34 item 1
    assert [p.name for p in out.iterdir()] == ["keep.txt"]
    (out / "keep.txt").unlink()
    for _ in range(2):  # into the empty directory, then over the simulation directory
        r = spmc("simulate", CONFIGS / "caseB.yaml", "--out", out, "--no-noise", "--overwrite")
        assert r.exit_code == 0, r.output
        assert sorted(p.name for p in out.iterdir()) == ["config.yaml", "manifest.json", "measurements.parquet",
                                                          "truth.parquet"]  # fmt: skip


def test_simulate_with_disparity(tmp_path):
    text = mutate("name: caseB", "name: caseB-d", mutate("disparity: false", "disparity: true"))
    text = mutate("duration_s: 100.0", "duration_s: 20.0", text)
    f = write(tmp_path, "d.yaml", text)
    r = spmc("simulate", f, "--out", tmp_path / "out", "--no-noise")
    assert r.exit_code == 0, r.output
    meas = pd.read_parquet(tmp_path / "out" / "measurements.parquet")
    assert list(meas.columns) == MEAS + ["d"]
    truth = pd.read_parquet(tmp_path / "out" / "truth.parquet")
    hand = _by_hand(truth, np.asarray(load_scenario(f).target.feature_points_m), 1.0)
    y = meas.sort_values(["t", "feature"])[MEAS[2:] + ["d"]].to_numpy().reshape(len(truth), 5, 9)
    np.testing.assert_allclose(y, hand, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(meas["d"], meas["u_l"] - meas["u_r"], rtol=1e-12)
