"""An on-disk cache of scenario truths (``simulate_truth``), so that a run's start-up skips the integration.

The true trajectory of a scenario depends only on what ``simulate_truth`` reads from the
resolved setup: the leader's orbit, the true initial state ``x0``, the time grid
(``dt``, ``steps``), ``truth_rtol`` and the ``truth_model`` perturbations. Those inputs,
the cache's format version, the package version, the numpy and scipy versions and a
digest of the source files the integration runs through are written as canonical JSON;
its SHA-256 names the cache file, ``<key>.npz`` (plain arrays, ``allow_pickle=False``).

- Where: ``$SPMC_CACHE_DIR/truth/`` if ``SPMC_CACHE_DIR`` is set, else
  ``$XDG_CACHE_HOME/stereopose_mc/truth/``, else ``~/.cache/stereopose_mc/truth/``.
- Off: ``SPMC_NO_CACHE=1`` (any value but empty or ``0``) neither reads nor writes it.
- A hit gives the same arrays, bit for bit and in the same memory order, as the
  integration (``tests/sim/test_truth_cache.py``); a file that cannot be read, has another
  key or wrong shapes is ignored, recomputed and replaced (written to a temporary file,
  then renamed, so readers never see half a file); a cache that cannot be written is
  skipped silently.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
import tempfile
from pathlib import Path

import numpy as np

from .. import __version__
from ..config.resolve import Setup
from ..core.orbit import Orbit
from .truth import Truth, simulate_truth

CACHE_FORMAT = 1
ARRAYS = ("t", "nu", "nu_dot", "nu_ddot", "x", "alpha")
ORBIT_FIELDS = tuple(f.name for f in dataclasses.fields(Orbit))
# the code the truth's numbers come from (relative to the package): a change there changes every key
SOURCES = ("sim/truth.py", "core/dynamics.py", "core/orbit.py", "core/perturbed.py", "core/quaternion.py",
           "core/state.py")  # fmt: skip


def disabled() -> bool:
    """``SPMC_NO_CACHE`` set to anything but empty or ``0``."""
    return os.environ.get("SPMC_NO_CACHE", "").strip() not in ("", "0")


def cache_dir() -> Path:
    """The truth cache's directory (see the module's doc); not created here."""
    root = os.environ.get("SPMC_CACHE_DIR")
    if root:
        return Path(root).expanduser() / "truth"
    xdg = os.environ.get("XDG_CACHE_HOME")
    base = Path(xdg).expanduser() if xdg else Path.home() / ".cache"
    return base / "stereopose_mc" / "truth"


@functools.lru_cache(maxsize=1)
def _code_digest() -> str:
    """SHA-256 over the truth's source files, numpy's version and scipy's (read without importing scipy)."""
    h = hashlib.sha256()
    pkg = Path(__file__).resolve().parents[1]
    for rel in SOURCES:
        h.update(rel.encode() + b"\0" + (pkg / rel).read_bytes() + b"\0")
    h.update(f"numpy {np.__version__}\0scipy {_scipy_version()}".encode())
    return h.hexdigest()


def _scipy_version() -> str:
    import importlib.util

    spec = importlib.util.find_spec("scipy")
    if spec is not None and spec.submodule_search_locations:
        p = Path(list(spec.submodule_search_locations)[0]) / "version.py"
        if p.is_file():  # version and git revision of the installed build
            return hashlib.sha256(p.read_bytes()).hexdigest()
    from importlib.metadata import version

    return version("scipy")


def _num(v) -> str:
    """A float, exactly (``float.hex``: -0.0, nan and inf included)."""
    return float(v).hex()


def truth_inputs(setup: Setup) -> dict:
    """Everything ``simulate_truth(setup)`` depends on, as JSON-ready values (floats exact)."""
    p = setup.perturbations
    return {
        "format": CACHE_FORMAT,
        "package": __version__,
        "code": _code_digest(),
        "orbit": {f: _num(getattr(setup.orbit, f)) for f in ORBIT_FIELDS},
        "x0": [_num(v) for v in np.asarray(setup.x0, dtype=float).ravel()],
        "dt": _num(setup.dt),
        "steps": int(setup.steps),
        "truth_rtol": _num(setup.truth_rtol),
        "perturbations": None if p is None else {f.name: _value(getattr(p, f.name)) for f in dataclasses.fields(p)},
    }


def _value(v):
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return _num(v)
    return str(v)


def truth_key(setup: Setup) -> str:
    """SHA-256 of the canonical JSON of ``truth_inputs(setup)``."""
    canon = json.dumps(truth_inputs(setup), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(canon.encode()).hexdigest()


def cached_truth(setup: Setup) -> Truth:
    """``simulate_truth(setup)``, from the cache when it has it (and written to it when not)."""
    if disabled():
        return simulate_truth(setup)
    try:
        key = truth_key(setup)
        path = cache_dir() / f"{key}.npz"
    except (OSError, RuntimeError):  # a source file unreadable, no home directory: no cache
        return simulate_truth(setup)
    truth = load(path, key, setup)
    if truth is None:
        truth = simulate_truth(setup)
        store(path, key, truth)
    return truth


def load(path: Path, key: str, setup: Setup) -> Truth | None:
    """The truth stored at ``path`` under ``key``, or None (missing, unreadable, another key, wrong shapes)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            if str(z["key"][()]) != key:
                return None
            a = {name: z[name] for name in ARRAYS}
            orbits = z["orbits"] if "orbits" in z.files else None
    except Exception:  # noqa: BLE001 - missing or corrupt (zip, header, truncated, no such member): recompute
        return None
    K1, n = setup.steps + 1, np.asarray(setup.x0).size
    shapes = {"t": (K1,), "nu": (K1,), "nu_dot": (K1,), "nu_ddot": (K1,), "x": (K1, n), "alpha": (K1, 3)}
    if any(a[k].dtype != np.float64 or a[k].shape != s for k, s in shapes.items()):
        return None
    if (setup.perturbations is None) != (orbits is None):
        return None
    filter_orbits = None
    if orbits is not None:
        if orbits.dtype != np.float64 or orbits.shape != (K1, len(ORBIT_FIELDS)):
            return None
        filter_orbits = tuple(Orbit(*(float(v) for v in row)) for row in orbits)
    return Truth(filter_orbits=filter_orbits, **a)


def store(path: Path, key: str, truth: Truth) -> None:
    """Write ``truth`` to ``path`` atomically (temporary file, then rename); any failure is ignored."""
    arrays = {name: getattr(truth, name) for name in ARRAYS}
    if truth.filter_orbits is not None:
        arrays["orbits"] = np.array([[getattr(o, f) for f in ORBIT_FIELDS] for o in truth.filter_orbits], dtype=float)
    store_npz(path, key=np.array(key), **arrays)


def store_npz(path: Path, **arrays) -> None:
    """``np.savez`` of ``arrays`` to ``path`` atomically (temporary file, then rename); any failure is ignored."""
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=".tmp")
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, **arrays)
        os.replace(tmp, path)
        tmp = None
    except (OSError, ValueError):
        pass
    finally:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
