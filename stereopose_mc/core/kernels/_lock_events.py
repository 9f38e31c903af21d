"""Numba's LLVM-lock events off: loading the cached kernels without a Python event per LLVM call.

llvmlite serializes its calls into LLVM with a lock, and Numba registers two callbacks on it
(``numba.core.base._initialize_llvm_lock_event``) that broadcast a ``"numba:llvm_lock"`` start and end event
(``numba.core.event``) around every call. Their only reader is the timer Numba installs while it compiles, which
reports the time spent holding the lock in a dispatcher's compile metadata (``timers["llvm_lock"]``, absent once
they are removed); nothing in this package reads it. Loading a kernel from the cache makes thousands of short LLVM
calls (``codegen.JitEngine._load_defined_symbols`` makes two for every global of each library), and the two events
cost more than the calls themselves: removed, a 2-trial run of case B (imports, kernel loading, one chunk) took
0.05-0.09 s less over five alternated pairs. The lock itself stays.

:func:`remove` unregisters exactly Numba's two callbacks through llvmlite's public
``unregister_lock_callback`` (llvmlite reached through ``numba.core.base``, which imports it: ``core`` imports
numpy, scipy and numba only), and does nothing if they are not where this Numba puts them.
"""

from __future__ import annotations

# the qualified names of Numba's callbacks (``numba.core.base``)
_NUMBA_CALLBACKS = ("_initialize_llvm_lock_event.<locals>.enter_fn", "_initialize_llvm_lock_event.<locals>.exit_fn")


def remove() -> bool:
    """Unregister Numba's LLVM-lock event callbacks; True if they were found and removed (or are already gone)."""
    from numba.core import base  # (registers them on import)

    ffi = getattr(getattr(base, "ll", None), "ffi", None)  # llvmlite.binding.ffi, as Numba imports it
    registered = getattr(getattr(getattr(ffi, "lib", None), "_lock", None), "_cblist", None)
    if not isinstance(registered, list):
        return False
    for pair in list(registered):
        names = tuple(getattr(f, "__qualname__", "") for f in pair) if isinstance(pair, tuple) else ()
        if names == _NUMBA_CALLBACKS:
            ffi.unregister_lock_callback(*pair)
    return True
