"""The on-disk truth cache (``sim/truth_cache.py``): the same bits as the integration, keys that follow
every truth input, corrupt files ignored, and whole runs byte-identical with and without it."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import SHORT, run_ok

from stereopose_mc.config import load_scenario_text
from stereopose_mc.config.resolve import setup_of
from stereopose_mc.core.perturbed import Perturbations
from stereopose_mc.mc import engine
from stereopose_mc.sim import truth_cache as tc
from stereopose_mc.sim.truth import simulate_truth

from scenarios import scenario_dict, write_scenario

import yaml


def setup_from(**overrides):
    return setup_of(load_scenario_text(yaml.safe_dump(scenario_dict(**overrides))))


@pytest.fixture
def cache(tmp_path, monkeypatch) -> Path:
    """An empty cache of this test (``SPMC_CACHE_DIR``), on."""
    monkeypatch.setenv("SPMC_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv("SPMC_NO_CACHE", raising=False)
    return tmp_path / "cache" / "truth"


def files(d: Path) -> list[Path]:
    return sorted(d.glob("*.npz")) if d.is_dir() else []


def assert_same_truth(a, b):
    for name in tc.ARRAYS:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape, name
        assert x.tobytes() == y.tobytes(), name  # bit for bit
        assert (x.flags.c_contiguous, x.flags.f_contiguous) == (y.flags.c_contiguous, y.flags.f_contiguous), name
    assert a.filter_orbits == b.filter_orbits


@pytest.mark.parametrize("perturbed", [False, True], ids=["keplerian", "perturbed"])
def test_a_hit_is_the_integration_bit_for_bit(cache, perturbed):
    kw = {"truth_model": {"j2": True, "gravity_gradient_torque": True}} if perturbed else {}
    setup = setup_from(time={"dt_s": 1.0, "duration_s": 30.0, "error_window_start_s": 5.0}, **kw)
    ref = simulate_truth(setup)
    assert (ref.filter_orbits is not None) == perturbed
    miss = tc.cached_truth(setup)  # empty cache: integrated, then written
    assert [p.name for p in files(cache)] == [f"{tc.truth_key(setup)}.npz"]
    hit = tc.cached_truth(setup)
    assert_same_truth(ref, miss)
    assert_same_truth(ref, hit)


def test_the_key_follows_every_truth_input_and_nothing_else():
    base = setup_from()
    key = tc.truth_key(base)
    assert key == tc.truth_key(setup_from())  # deterministic
    changed = {
        "x0": dataclasses.replace(base, x0=base.x0 + np.eye(base.x0.size)[0] * 1e-12),
        "orbit": dataclasses.replace(base, orbit=dataclasses.replace(base.orbit, e=base.orbit.e + 1e-15)),
        "orbit mu": dataclasses.replace(base, orbit=dataclasses.replace(base.orbit, mu=base.orbit.mu * (1 + 1e-15))),
        "dt": dataclasses.replace(base, dt=0.5),
        "steps": dataclasses.replace(base, steps=base.steps + 1),
        "truth_rtol": dataclasses.replace(base, truth_rtol=1e-11),
        "perturbations": dataclasses.replace(base, perturbations=Perturbations(j2=True)),
    }
    keys = {name: tc.truth_key(s) for name, s in changed.items()}
    assert key not in keys.values()
    assert len(set(keys.values())) == len(keys)
    j2 = changed["perturbations"]
    assert tc.truth_key(j2) != tc.truth_key(dataclasses.replace(j2, perturbations=Perturbations(j2=True, drag=True)))
    # what the truth does not read leaves the key alone
    same = setup_from(seed=7, trials=3, filters=[{"type": "ekf"}],
                      measurements={"image_sigma": 3e-5, "flow_sigma": 3e-5, "disparity": True})
    assert tc.truth_key(same) == key
    # and the scenario file's truth inputs reach it
    assert tc.truth_key(setup_from(truth_initial_state={"rho_m": [10.0, 61.0, 10.0], "rho_dot_mps": [0.01, -0.0225, -0.01],
                                                        "omega_degps": [-0.1, -0.1, 0.034], "q": [1.0, 0.0, 0.0, 0.0]})) != key


def test_the_key_follows_the_code(monkeypatch):
    setup = setup_from()
    key = tc.truth_key(setup)
    monkeypatch.setattr(tc, "_code_digest", lambda: "another version of core/dynamics.py")
    assert tc.truth_key(setup) != key


@pytest.mark.parametrize("damage", ["garbage", "truncated", "empty", "other key", "wrong shape"])
def test_a_bad_cache_file_is_recomputed_and_replaced(cache, damage):
    setup = setup_from(time=SHORT)
    ref = tc.cached_truth(setup)
    (path,) = files(cache)
    good = path.read_bytes()
    if damage == "garbage":
        path.write_bytes(b"not a zip file at all" * 10)
    elif damage == "truncated":
        path.write_bytes(good[: len(good) // 2])
    elif damage == "empty":
        path.write_bytes(b"")
    elif damage == "other key":  # another scenario's truth under this name
        other = setup_from(time={"dt_s": 1.0, "duration_s": 12.0, "error_window_start_s": 5.0}, seed=1,
                           truth_initial_state={"rho_m": [10.0, 70.0, 10.0], "rho_dot_mps": [0.0, 0.0, 0.0],
                                                "omega_degps": [-0.1, -0.1, 0.034], "q": [1.0, 0.0, 0.0, 0.0]})
        tc.store(path, tc.truth_key(other), simulate_truth(other))
    else:
        t = simulate_truth(setup)
        tc.store(path, tc.truth_key(setup), dataclasses.replace(t, x=t.x[:, :-1]))
    assert tc.load(path, tc.truth_key(setup), setup) is None
    assert_same_truth(ref, tc.cached_truth(setup))
    assert tc.load(path, tc.truth_key(setup), setup) is not None  # rewritten, whole
    assert not list(cache.glob(".*.tmp"))


def test_off_and_unwritable(tmp_path, monkeypatch):
    setup = setup_from(time=SHORT)
    ref = simulate_truth(setup)
    monkeypatch.setenv("SPMC_CACHE_DIR", str(tmp_path / "c"))
    monkeypatch.setenv("SPMC_NO_CACHE", "1")
    assert_same_truth(ref, tc.cached_truth(setup))
    assert not (tmp_path / "c").exists()
    monkeypatch.setenv("SPMC_NO_CACHE", "0")  # 0 or empty: on
    blocker = tmp_path / "file"
    blocker.write_text("a file where the cache directory should be")
    monkeypatch.setenv("SPMC_CACHE_DIR", str(blocker))
    assert_same_truth(ref, tc.cached_truth(setup))  # cannot write: computed, no error


def test_where_the_cache_lives(monkeypatch, tmp_path):
    monkeypatch.delenv("SPMC_CACHE_DIR", raising=False)
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert tc.cache_dir() == tmp_path / "home" / ".cache" / "stereopose_mc" / "truth"
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert tc.cache_dir() == tmp_path / "xdg" / "stereopose_mc" / "truth"
    monkeypatch.setenv("SPMC_CACHE_DIR", str(tmp_path / "spmc"))
    assert tc.cache_dir() == tmp_path / "spmc" / "truth"


def test_runs_are_byte_identical_with_and_without_the_cache(tmp_path, cache, monkeypatch):
    scn = write_scenario(tmp_path / "s.yaml", trials=3, time=SHORT)
    outs = []
    for i, off in enumerate(["1", "", ""]):  # no cache; empty cache (written); from the cache
        monkeypatch.setenv("SPMC_NO_CACHE", off)
        engine._prepared.cache_clear()  # this process's own memo of the prepared scenario
        out = tmp_path / f"run{i}"
        run_ok("run", scn, "--out", out)
        outs.append(out)
        assert len(files(cache)) == (0 if off else 1)
    for out in outs[1:]:
        for name in ("trials.parquet", "timeseries.parquet", "percentiles.csv"):
            assert (out / name).read_bytes() == (outs[0] / name).read_bytes(), name
