"""``core.kernels._lazy_bitcode``: a kernel loaded from Numba's cache keeps its bitcode unparsed, runs, and is
parsed (and linked) when a function compiled later calls it.

Each scenario runs in a fresh interpreter (a cache is only loaded by a process that did not compile), on a small
module of two ``@njit(cache=True)`` functions written to a temporary directory with its own cache."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

MODULE = '''
import numpy as np
from numba import njit


@njit(cache=True)
def callee(a):
    s = 0.0
    for i in range(a.shape[0]):
        s += (i + 1.0) * a[i]
    return s


@njit(cache=True)
def caller(a):
    return 2.0 * callee(a) + 1.0
'''

# every run prints: the values, whether callee's library was loaded lazily, and how many bitcode parses happened
PROBE = '''
import sys
import numpy as np
import stereopose_mc.core.kernels  # installs the loader
from numba.core import codegen

parses = []
numba_parse = codegen.ll.parse_bitcode
codegen.ll.parse_bitcode = lambda data: parses.append(len(data)) or numba_parse(data)
import kern

a = np.array([1.0, 2.0, 3.0])
out = []
for name in sys.argv[1:]:
    out.append(repr(getattr(kern, name)(a)))
lib = next(iter(kern.callee.overloads.values())).library if kern.callee.overloads else None
pending = getattr(lib, "_spmc_bitcode", None) is not None
print(" ".join(out), "pending" if pending else "parsed", len(parses))
'''


def _probe(tmp: Path, *calls: str) -> list[str]:
    env = {"PYTHONPATH": f"{tmp}:{Path(__file__).resolve().parents[2]}", "NUMBA_CACHE_DIR": str(tmp / "cache"),
           "PATH": "/usr/bin:/bin"}  # fmt: skip
    res = subprocess.run([sys.executable, str(tmp / "probe.py"), *calls], env=env, capture_output=True, text=True,
                         timeout=300)  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    return res.stdout.split()


def _setup(tmp: Path) -> None:
    (tmp / "kern.py").write_text(textwrap.dedent(MODULE))
    (tmp / "probe.py").write_text(PROBE)


def test_cached_kernel_loads_without_parsing_and_links_when_called_by_a_new_compile(tmp_path):
    _setup(tmp_path)
    expected_callee = 1.0 * 1 + 2.0 * 2 + 3.0 * 3  # 14, by hand
    # 1: compiles callee alone and caches it (a compiled library is Numba's own: nothing pending)
    assert _probe(tmp_path, "callee") == [repr(expected_callee), "parsed", "0"]
    # 2: loads callee from the cache: runs, bitcode kept unparsed, no parse at all
    assert _probe(tmp_path, "callee") == [repr(expected_callee), "pending", "0"]
    # 3: loads callee, then compiles caller, which links callee's library: its bitcode is parsed then (once)
    v_callee, v_caller, state, parses = _probe(tmp_path, "callee", "caller")
    assert (float(v_callee), float(v_caller), state) == (expected_callee, 2 * expected_callee + 1, "parsed")
    assert int(parses) >= 1
    # 4: both from the cache now: nothing parsed
    assert _probe(tmp_path, "callee", "caller") == [repr(expected_callee), repr(2 * expected_callee + 1),
                                                     "pending", "0"]  # fmt: skip


def test_install_is_idempotent():
    from numba.core import codegen

    from stereopose_mc.core.kernels import _lazy_bitcode

    loader = codegen.CPUCodeLibrary._unserialize
    assert _lazy_bitcode.install() and _lazy_bitcode.install()
    assert codegen.CPUCodeLibrary._unserialize == loader  # not wrapped twice
