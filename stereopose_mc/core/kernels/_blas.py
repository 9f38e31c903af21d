"""Load SciPy's Cython BLAS/LAPACK tables for Numba without importing ``scipy.linalg``.

Numba's compiled ``np.dot`` and ``np.linalg`` call BLAS and LAPACK through the function
pointers that ``scipy.linalg.cython_blas`` and ``scipy.linalg.cython_lapack`` export. Numba
imports those two modules by name (``numba.np.linalg.ensure_blas`` when its registries load,
then its C helpers on the first call), and a submodule's import runs its package's
``__init__`` first: ``scipy.linalg`` with its array-API layer, 0.14-0.22 s of a short run
(measured in a 2-trial run of case B: a third of Numba's whole load), which nothing else of
a run uses. The two modules are self-contained compiled extensions, so :func:`preload` loads
them from their files into ``sys.modules`` under their own names: Numba then finds them
there and the package ``__init__`` is not run. Both are the very modules the normal import
loads (the same file, once per process), with the same function tables (tested).

If anything is not as expected (another layout, a SciPy without the files), nothing is
loaded and Numba imports ``scipy.linalg`` as usual. A later ``import scipy.linalg`` works as
always; ``from scipy.linalg import cython_blas`` finds the loaded module (only the package
attribute ``scipy.linalg.cython_blas`` is not set, and nothing here reads it).
"""

from __future__ import annotations

import importlib.machinery
import importlib.util
import sys
from pathlib import Path

MODULES = ("scipy.linalg.cython_blas", "scipy.linalg.cython_lapack")


def preload() -> bool:
    """Load :data:`MODULES` into ``sys.modules`` unless they are there; True if both are there afterwards."""
    if all(m in sys.modules for m in MODULES) or "scipy.linalg" in sys.modules:
        return all(m in sys.modules for m in MODULES)
    try:
        import scipy
    except ImportError:
        return False
    loaded = {}
    for name in MODULES:
        leaf = name.rpartition(".")[2]
        paths = [p for d in scipy.__path__ for s in importlib.machinery.EXTENSION_SUFFIXES
                 if (p := Path(d) / "linalg" / f"{leaf}{s}").is_file()]  # fmt: skip
        if not paths:
            return False
        spec = importlib.util.spec_from_file_location(name, paths[0])
        if spec is None or spec.loader is None:
            return False
        try:
            module = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(module)
        except ImportError:
            return False
        if not isinstance(getattr(module, "__pyx_capi__", None), dict):
            return False
        loaded[name] = module
    sys.modules.update(loaded)
    return True
