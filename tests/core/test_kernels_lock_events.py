"""``core.kernels._lock_events``: Numba's LLVM-lock event callbacks are off once the kernels are imported, and
Numba still compiles and loads (the lock itself stays)."""

from __future__ import annotations

import numpy as np
from numba import njit
from numba.core import base

import stereopose_mc.core.kernels  # noqa: F401  (removes them)
from stereopose_mc.core.kernels import _lock_events


def _registered() -> list[tuple[str, ...]]:
    return [tuple(f.__qualname__ for f in pair) for pair in base.ll.ffi.lib._lock._cblist]


def test_numba_callbacks_are_not_registered():
    assert _lock_events._NUMBA_CALLBACKS not in _registered()
    assert _lock_events.remove()  # again: nothing left to remove, still True
    assert _lock_events._NUMBA_CALLBACKS not in _registered()


def test_only_numba_callbacks_are_removed():
    calls = []

    def acq():
        calls.append("acq")

    def rel():
        calls.append("rel")

    base.ll.ffi.register_lock_callback(acq, rel)
    try:
        _lock_events.remove()
        assert ("test_only_numba_callbacks_are_removed.<locals>.acq",
                "test_only_numba_callbacks_are_removed.<locals>.rel") in _registered()  # fmt: skip
        base.ll.ffi.lib.LLVMPY_GetVersionInfo()  # an LLVM call goes through the lock and its callbacks
        assert calls == ["acq", "rel"]
    finally:
        base.ll.ffi.unregister_lock_callback(acq, rel)


def test_numba_compiles_without_them():
    @njit
    def weighted(a, w):
        s = 0.0
        for i in range(a.shape[0]):
            s += a[i] * w[i]
        return s

    a, w = np.array([1.0, 2.0, 3.0]), np.array([0.5, 0.25, 2.0])
    assert weighted(a, w) == 1.0 * 0.5 + 2.0 * 0.25 + 3.0 * 2.0
    timers = next(iter(weighted.overloads.values())).metadata["timers"]
    assert "compiler_lock" in timers and "llvm_lock" not in timers  # the one reader of the events: its timer is gone
