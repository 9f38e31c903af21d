"""Compiled (Numba) kernels, the fast twins of the numpy model and filter functions (docs/kernels.md).

Importing this package compiles nothing: the kernels are compiled on first call (or loaded from Numba's on-disk
cache, ``cache=True``). One idea per module:

- ``model``: ``f``, RK4, ``F``, the transition matrix and the block-structured covariance predict, ``h`` and ``H``
  per feature and the inertia pseudo-measurement rows; ``rows``: the small row/dot primitives the others share;
- ``aligned``, ``attitude``: the two error-state charts (chart, ``S``, ``T``, the error-state covariance predict,
  the row-sparse ``H_e``); ``charts``: their batch entry points (the chart's code as an argument);
- ``whiten``: ``Hw = R^-1/2 H L``, ``g`` and ``A = I + Hw^T Hw``; ``centred``: the aligned chart's centred point
  coordinates for large ``n``; ``cholesky``: the Cholesky factorizations and triangular solves; ``triangular``: the
  whitened ``A`` factorized in reverse order and ``P+ = L A^-1 L^T`` with its square root;
- ``update``: the EKF and IEKF update loop in any of the three charts (which, given the truth, evaluates each
  posterior's NEES as it forms it); ``consistency``: the per-step NEES and errors; ``gate``: the gate's per-feature
  innovation covariance blocks from the row-sparse ``H``, and their distances.

The state's offsets come from ``core.layout``. ``_cache`` keys Numba's cache by the whole package's source and
the core modules it imports; ``_blas`` loads SciPy's BLAS tables for Numba without ``scipy.linalg``;
``_lazy_bitcode`` loads a cached kernel without parsing the LLVM bitcode Numba keeps beside its machine code (parsed
only if a later compile links the kernel); ``_lock_events`` takes Numba's event callbacks off llvmlite's lock
(loading from the cache makes thousands of LLVM calls); ``_refs`` lets the kernels' per-trial loops work on
borrowed arrays, without the atomic reference counting of their views and calls (``borrow``, and ``keep`` for the
owners).
"""

import numpy as np

from . import _blas, _cache, _lazy_bitcode, _lock_events

_blas.preload()  # SciPy's BLAS/LAPACK tables for Numba, without scipy.linalg's slow import
_lazy_bitcode.install()  # a cached kernel's LLVM bitcode parsed only if a later compile links it
_lock_events.remove()  # no Python event around each of the cache loads' thousands of LLVM calls
_cache.install()  # before any kernel module is imported: their @njit(cache=True) pick a locator when decorated


def writable(a: np.ndarray) -> np.ndarray:
    """A C-contiguous, writable float64 array (a copy where needed): a read-only view, e.g. ``broadcast_to``'s
    with one trial, would be a second Numba signature of every kernel it enters (a second compile and load)."""
    a = np.asarray(a)
    if a.dtype == np.float64 and a.flags.c_contiguous and a.flags.writeable:
        return a
    return np.array(a, dtype=float, order="C")
