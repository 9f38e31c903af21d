"""Compiled (Numba) kernels, the fast twins of the numpy model and filter functions.

Importing this package compiles nothing: the kernels are compiled on first call (or
loaded from Numba's on-disk cache, ``cache=True``). ``core/kernels/model.py`` holds
``f``, RK4, ``F``, the transition matrix and the block-structured covariance predict,
``h`` and ``H`` per feature and the inertia pseudo-measurement rows;
``core/kernels/aligned.py`` the aligned error state (chart, ``S``, ``T``, the error-state
covariance predict, the row-sparse ``H_e``); ``core/kernels/attitude.py`` the same for the
attitude error state; ``core/kernels/charts.py`` the batch entry points of both charts (the
chart's code as an argument); ``core/kernels/update.py`` the EKF and IEKF updates in any of the
three charts; ``core/kernels/consistency.py`` the per-step NEES.
"""

from . import _cache

_cache.install()  # before any kernel module is imported: their @njit(cache=True) pick a locator when decorated
