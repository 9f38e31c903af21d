"""Whether Numba's cache holds the kernels for the current source (the 'compiling kernels' note)."""

from __future__ import annotations

import pickle
from types import SimpleNamespace

import pytest

from stereopose_mc.mc import warm


def _dispatcher(tmp_path, name: str, stamp=b"now", content=None, version=("0.68",)):
    """A stand-in with the attributes of a cached Numba dispatcher; ``content``: (stamp, overloads) in its index."""
    path = tmp_path / f"{name}.nbi"
    if content is not None:
        with open(path, "wb") as f:
            pickle.dump(version, f)
            f.write(pickle.dumps(content))
    cf = SimpleNamespace(_index_path=str(path), _version=("0.68",), _source_stamp=stamp)
    return SimpleNamespace(_cache=SimpleNamespace(_cache_file=cf))


def test_index_states(tmp_path):
    assert warm._index_state(_dispatcher(tmp_path, "fresh", content=(b"now", {"sig": "f-1.nbc"}))) is True
    assert warm._index_state(_dispatcher(tmp_path, "stale", content=(b"before", {"sig": "f-1.nbc"}))) is False
    assert warm._index_state(_dispatcher(tmp_path, "empty", content=(b"now", {}))) is False
    assert warm._index_state(_dispatcher(tmp_path, "other", content=(b"now", {"s": 1}), version=("0.1",))) is False
    assert warm._index_state(_dispatcher(tmp_path, "callee")) is None  # compiled into its callers only


@pytest.mark.parametrize("states,cached", [
    (["fresh", "callee"], True), (["fresh", "stale"], True), (["stale", "stale"], False), (["callee"], False),
    ([], False),
])  # fmt: skip
def test_kernels_cached_needs_one_index_of_the_current_stamp(tmp_path, monkeypatch, states, cached):
    content = {"fresh": (b"now", {"s": 1}), "stale": (b"old", {"s": 1}), "callee": None}
    ds = [_dispatcher(tmp_path, f"{s}{i}", content=content[s]) for i, s in enumerate(states)]
    monkeypatch.setattr(warm, "dispatchers", lambda: ds)
    assert warm.kernels_cached() is cached


def test_the_real_kernels_have_cache_files_of_their_own():
    ds = warm.dispatchers()
    assert len(ds) > 50
    assert all(d._cache._cache_file._index_path.endswith(".nbi") for d in ds)


def test_a_kernel_without_a_cache_is_not_a_cached_kernel(monkeypatch):
    """An ``@njit`` of a kernel module without ``cache=True`` (Numba's ``NullCache``, no index file) is left out, and
    does not break ``kernels_cached`` (which every compiled run calls)."""
    from numba import njit

    from stereopose_mc.core.kernels import gate

    def _helper(a):
        return a

    _helper.__module__ = gate.__name__
    uncached = njit(_helper)
    monkeypatch.setattr(gate, "_uncached_helper", uncached, raising=False)
    ds = warm.dispatchers()
    assert uncached not in ds and gate.innovation_blocks_batch in ds
    assert warm.kernels_cached() in (True, False)


@pytest.mark.parametrize("cold", [True, False])
def test_a_compiled_run_says_when_it_compiles(tmp_path, monkeypatch, cold):
    from scenarios import write_scenario

    from stereopose_mc.config import load_scenario
    from stereopose_mc.mc import engine

    short = {"dt_s": 1.0, "duration_s": 3.0, "error_window_start_s": 0.0}
    scn = write_scenario(tmp_path / "s.yaml", trials=2, time=short)
    monkeypatch.setattr(warm, "kernels_cached", lambda: not cold)
    notes: list[str] = []
    engine.run(load_scenario(scn), tmp_path / "run", engine.RunOptions(say=notes.append, command=["test"]))
    assert (warm.COMPILING in notes) is cold
    assert warm.COMPILING.startswith("compiling kernels, first run only")
