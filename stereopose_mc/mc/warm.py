"""Numba's cache of the compiled kernels: whether it is warm, and warming it (``python -m stereopose_mc.mc.warm``).

The kernels (``core/kernels``, ``cache=True``) compile on their first call in a process that
finds no cache entry for them, and store the machine code in ``core/kernels/__pycache__``
(an index file ``<module>.<function>-<line>.py311.nbi`` per kernel called from Python, holding
the cache stamp: ``core/kernels/_cache.py``). ``make venv`` runs :func:`main`, a few steps of
short campaigns that call every kernel signature a run uses, so the first ``spmc run`` loads
instead of compiling (about a minute on 2 cores).

:func:`kernels_cached` reads those index files: the cache is warm when one of them carries the
current stamp. An edit of any kernel module, or of a ``core`` module they import, changes the
stamp of every kernel at once, so after an edit (or on a fresh install) none does. Indexes of
kernels no run has called since an edit stay stale (some kernels are called only by other
scenarios or by the tests), so "every index fresh" would report a cold cache forever; and
kernels only ever called from other kernels are compiled into their callers and have no index.
"""

from __future__ import annotations

import argparse
import importlib
import pickle
import pkgutil
import sys
import tempfile
import time
from pathlib import Path

COMPILING = "compiling kernels, first run only (about a minute; `make venv` does it at install)"
ROOT = Path(__file__).resolve().parents[2]
# scenarios whose few steps call every signature: the full-state and aligned charts, both filters,
# small and large states (past 64 columns), masked rows, dispersions and a mesh target
WARM_SCENARIOS = ("caseB.yaml", "mission-realistic.yaml", "mission-mesh-dispersed.yaml")
WARM_STEPS = 6


def dispatchers() -> list:
    """Every ``@njit(cache=True)`` function of ``core.kernels`` (imports the modules; compiles nothing). A kernel
    module's ``@njit`` without ``cache=True`` (Numba's ``NullCache``: no index file) is not one of them."""
    from numba.core.registry import CPUDispatcher

    from ..core import kernels

    out = []
    for info in pkgutil.iter_modules(kernels.__path__):
        mod = importlib.import_module(f"{kernels.__name__}.{info.name}")
        out += [v for v in vars(mod).values() if isinstance(v, CPUDispatcher) and v.__module__ == mod.__name__
                and hasattr(getattr(v, "_cache", None), "_cache_file")]  # fmt: skip
    return out


def _index_state(d) -> bool | None:
    """True: an index with the current stamp; False: a stale or unreadable one; None: no index."""
    cf = d._cache._cache_file
    try:
        with open(cf._index_path, "rb") as f:
            version = pickle.load(f)
            data = f.read()
    except FileNotFoundError:
        return None
    except (OSError, pickle.UnpicklingError, EOFError):
        return False
    if version != cf._version:
        return False
    try:
        stamp, overloads = pickle.loads(data)
    except Exception:  # noqa: BLE001 - an index another Numba wrote: treat as stale, as Numba does
        return False
    return stamp == cf._source_stamp and bool(overloads)


def kernels_cached() -> bool:
    """True when Numba's cache holds the kernels for the current source (see the module's docstring)."""
    return any(_index_state(d) for d in dispatchers())


def warm(config_dir: Path = ROOT / "configs", steps: int = WARM_STEPS, echo=print) -> float:
    """Run ``steps`` steps of 2 trials of each warm-up scenario on the compiled kernels; return the seconds."""
    from ..config import load_scenario
    from . import engine

    t0 = time.perf_counter()
    opts = engine.RunOptions(trials=2, jobs=1, kernels="compiled", timeseries="none", overwrite=True,
                             command=["python", "-m", "stereopose_mc.mc.warm"])  # fmt: skip
    with tempfile.TemporaryDirectory(prefix="spmc-warm-") as tmp:
        for name in WARM_SCENARIOS:
            path = Path(config_dir) / name
            if not path.is_file():
                continue
            dt = load_scenario(path).time.dt_s
            scn = load_scenario(path, {"time": {"dt_s": dt, "duration_s": steps * dt, "error_window_start_s": 0.0}})
            t1 = time.perf_counter()
            engine.run(scn, Path(tmp) / name, opts)
            echo(f"warm: {name} {time.perf_counter() - t1:.1f} s")
    warm_numpy_fallback(Path(config_dir) / WARM_SCENARIOS[0])
    return time.perf_counter() - t0


def warm_numpy_fallback(path: Path) -> None:
    """The compiled measurement model of the trials the update kernels leave to numpy's update (a factorization
    that failed: ``filters.compiled.numpy_update``), which a few steps of healthy trials never call: ``h`` and the
    dense ``H`` of a step of ``path``'s scenario at its initial state."""
    import numpy as np

    from ..config import load_scenario
    from ..config.resolve import setup_of
    from ..filters import compiled, relnav

    if not path.is_file():
        return
    setup = setup_of(load_scenario(path))
    x = setup.x0[None, :].copy()
    step = relnav.StepMeasurement(y=np.zeros((1, 0)), alpha=np.zeros((1, 3)), visible=np.ones(setup.n_points, bool),
                                  t=setup.dt)  # fmt: skip
    compiled.measurement_model(setup, step)(x, np.arange(1), True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m stereopose_mc.mc.warm", description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="only say whether the cache is warm (exit 1 if not)")
    a = ap.parse_args(argv)
    if a.check:
        ok = kernels_cached()
        print("kernels cached" if ok else "kernels not cached")
        return 0 if ok else 1
    print(f"warm: {warm():.1f} s (Numba's cache of the kernels, stereopose_mc/core/kernels/__pycache__)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
