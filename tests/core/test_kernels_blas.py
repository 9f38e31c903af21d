"""``core/kernels/_blas.py``: SciPy's BLAS/LAPACK tables for Numba without importing ``scipy.linalg``."""

from __future__ import annotations

import subprocess
import sys

SCRIPT = r"""
import sys
from stereopose_mc.core.kernels import _blas
assert _blas.preload() and "scipy.linalg" not in sys.modules
mods = [sys.modules[m] for m in _blas.MODULES]
print("CAPI", *(len(m.__pyx_capi__) for m in mods))
import numpy as np
from numba import njit

@njit(cache=False)
def products(a, b):  # BLAS gemm and LAPACK potrf through the preloaded tables
    return np.dot(a, b), np.linalg.cholesky(np.dot(a, a.T) + 3.0 * np.eye(a.shape[0]))

a = np.arange(12.0).reshape(3, 4) / 7.0
b = np.arange(8.0).reshape(4, 2) - 2.5
ab, L = products(a, b)
assert np.allclose(ab, a @ b, rtol=0, atol=1e-13)
assert np.allclose(L @ L.T, a @ a.T + 3.0 * np.eye(3), rtol=0, atol=1e-12)
print("LINALG", "scipy.linalg" in sys.modules)
import scipy.linalg
from scipy.linalg import cython_blas
assert cython_blas is mods[0]  # a later import finds the same module
assert np.allclose(scipy.linalg.solve(np.eye(2) * 2.0, np.ones(2)), 0.5)
print("OK")
"""

NORMAL = r"""
import scipy.linalg.cython_blas as b, scipy.linalg.cython_lapack as l
print("CAPI", len(b.__pyx_capi__), len(l.__pyx_capi__))
"""


def _run(code: str) -> str:
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    return r.stdout


def test_preloaded_tables_serve_numba_without_scipy_linalg():
    out = _run(SCRIPT)
    assert "LINALG False" in out and out.rstrip().endswith("OK")  # Numba's BLAS check and calls did not import it
    capi = [line for line in out.splitlines() if line.startswith("CAPI")]
    assert capi == [line for line in _run(NORMAL).splitlines() if line.startswith("CAPI")]  # the same tables


def test_preload_leaves_an_imported_scipy_linalg_alone():
    out = _run("import sys, scipy.linalg\nfrom stereopose_mc.core.kernels import _blas\n"
               "print(_blas.preload(), sys.modules['scipy.linalg.cython_blas'].__name__)")  # fmt: skip
    assert out.split() == ["True", "scipy.linalg.cython_blas"]
