"""Compiled (Numba) kernels, the fast twins of the numpy model and filter functions.

Importing this package compiles nothing: the kernels are compiled on first call (or
loaded from Numba's on-disk cache, ``cache=True``). ``core/kernels/model.py`` holds
``f``, RK4, ``F``, the transition matrix and the block-structured covariance predict,
``h`` and ``H`` per feature and the inertia pseudo-measurement rows;
``core/kernels/aligned.py`` the aligned error state (chart, ``S``, ``T``, the error-state
covariance predict, the row-sparse ``H_e``); ``core/kernels/attitude.py`` the same for the
attitude error state; ``core/kernels/charts.py`` the batch entry points of both charts (the
chart's code as an argument); ``core/kernels/update.py`` the EKF and IEKF updates in any of the
three charts (which, given the truth, evaluate each posterior's NEES as they form it);
``core/kernels/consistency.py`` the per-step NEES; ``core/kernels/cholesky.py`` the small
Cholesky factorizations and solves both use. ``_cache`` keys Numba's cache by the
whole package's source; ``_blas`` loads SciPy's BLAS tables for Numba without ``scipy.linalg``;
``_refs`` lets the kernels' per-trial loops work on borrowed arrays, without the atomic reference
counting of their views and calls (``borrow``, and ``keep`` for the owners).
"""

import numpy as np

from . import _blas, _cache

_blas.preload()  # SciPy's BLAS/LAPACK tables for Numba, without scipy.linalg's 0.14-0.22 s import
_cache.install()  # before any kernel module is imported: their @njit(cache=True) pick a locator when decorated


def writable(a: np.ndarray) -> np.ndarray:
    """A C-contiguous, writable float64 array (a copy where needed): a read-only view, e.g. ``broadcast_to``'s
    with one trial, would be a second Numba signature of every kernel it enters (a second compile and load)."""
    a = np.asarray(a)
    if a.dtype == np.float64 and a.flags.c_contiguous and a.flags.writeable:
        return a
    return np.array(a, dtype=float, order="C")
