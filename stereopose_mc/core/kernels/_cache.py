"""Numba's on-disk cache for the kernels, keyed by the source of the whole package and the core modules it imports.

Numba stamps a cached function with the hash of its own source file only. A kernel in one
module compiles in the functions it calls from another (``consistency.nees_batch`` calls
``cholesky._cholesky``) and the constants it reads from ``core/layout.py`` (module-level ints,
frozen into the machine code), so a per-file stamp would keep stale code after an edit of a
callee's module or of the layout. The locators below give every function of this package the
hash of all its modules' sources and of the ``core`` modules they import (``from .. import
layout``, ``from ..layout import ...``: ``core_dependencies``) as the stamp, so any edit to any
of them recompiles them all (a release's cache is rebuilt on upgrade as before). Functions elsewhere keep
Numba's own locators. Installed by ``core/kernels/__init__.py`` before the first
``@njit(cache=True)`` of the package runs (Numba picks a function's locator when it is
decorated).
"""

from __future__ import annotations

import ast
import functools
import hashlib
import os
import re
import textwrap
from pathlib import Path

from numba.core import caching

PACKAGE_DIR = Path(__file__).resolve().parent


def source_files(directory: Path = PACKAGE_DIR) -> list[Path]:
    """The package's Python modules, sorted (the stamp does not depend on listing order). One ``scandir``: every
    kernel asks for its stamp when it is decorated (135 of them at import), so a ``glob`` with a ``stat`` per entry
    cost a fifth of the kernel modules' import."""
    with os.scandir(directory) as it:
        return sorted(Path(e.path) for e in it if e.name.endswith(".py") and e.is_file())


def core_dependencies(directory: Path = PACKAGE_DIR) -> list[Path]:
    """The modules of the parent package (``core``) that the package's modules import, sorted: ``from ..x import``
    and ``from .. import x`` where ``x.py`` exists one level up."""
    return list(_dependencies_of(_listing(source_files(directory))))


def _listing(paths: list[Path]) -> tuple[tuple[str, float, int], ...]:
    """``(path, mtime, size)`` of each file: the key of the memos below (the content itself is read)."""
    out = []
    for p in paths:
        st = p.stat()
        out.append((str(p), st.st_mtime, st.st_size))
    return tuple(out)


# a statement ``from ..x import ...`` or ``from .. import (...)`` at the start of a line (indented too): the
# candidates that ``_dependencies_of`` parses, instead of parsing whole modules (a fifth of a second per process)
_FROM_PARENT = re.compile(rb"^[ \t]*from[ \t]+\.\.(?!\.)[^\n(]*(?:\([^)]*\)[^\n]*)?", re.MULTILINE)


def _imports_from_parent(source: bytes) -> list[ast.ImportFrom]:
    """The ``from ..`` imports of a module's source (any depth). Each candidate line is parsed alone; a module
    where one does not parse (e.g. such a line inside a string) is parsed whole."""
    try:
        nodes = [ast.parse(textwrap.dedent(m.group(0).decode())).body[0] for m in _FROM_PARENT.finditer(source)]
    except (SyntaxError, IndexError, UnicodeDecodeError):
        nodes = list(ast.walk(ast.parse(source)))
    return [n for n in nodes if isinstance(n, ast.ImportFrom) and n.level == 2]


@functools.lru_cache(maxsize=8)
def _dependencies_of(files: tuple[tuple[str, float, int], ...]) -> tuple[Path, ...]:
    names = set()
    for path, _mtime, _size in files:
        for node in _imports_from_parent(Path(path).read_bytes()):
            names.update([node.module.split(".")[0]] if node.module else [a.name for a in node.names])
    parent = Path(files[0][0]).parent.parent if files else Path()
    return tuple(sorted(f for f in (parent / f"{name}.py" for name in names) if f.is_file()))


@functools.lru_cache(maxsize=8)
def _stamp_of(files: tuple[tuple[str, float, int], ...], deps: tuple[tuple[str, float, int], ...]) -> bytes:
    h = hashlib.sha256()
    for label, listing in ((b"", files), (b"../", deps)):  # (mtime, size) only key the memo: the content is hashed
        for path, _mtime, _size in listing:
            h.update(label + Path(path).name.encode() + b"\0")
            h.update(Path(path).read_bytes())
            h.update(b"\0")
    return h.digest()


def package_stamp(directory: Path = PACKAGE_DIR) -> bytes:
    """SHA-256 of the names and contents of the package's modules and of the ``core`` modules they import."""
    files = _listing(source_files(directory))
    return _stamp_of(files, _listing(list(_dependencies_of(files))))


def _package_locator(base: type) -> type:
    """``base`` (one of Numba's locators) for this package's functions, stamped with ``package_stamp``."""

    class PackageLocator(base):
        def get_source_stamp(self):
            return package_stamp()

        @classmethod
        def from_function(cls, py_func, py_file):
            if Path(os.path.abspath(py_file)).parent != PACKAGE_DIR:
                return None  # not a kernel: Numba's own locators
            return super().from_function(py_func, py_file)

    PackageLocator.__name__ = PackageLocator.__qualname__ = f"Package{base.__name__}"
    return PackageLocator


_NAMES = ("UserProvidedCacheLocator", "InTreeCacheLocator", "UserWideCacheLocator")
_IMPL = getattr(caching, "CacheImpl", None) or getattr(caching, "_CacheImpl", None)
BASES = tuple(getattr(caching, n) for n in _NAMES if hasattr(caching, n))
LOCATORS = tuple(_package_locator(b) for b in BASES)


def install() -> bool:
    """Put the package locators first in Numba's list (once), in Numba's own order of preference.

    False (nothing changed: Numba's per-file stamps) if this Numba lacks the classes used here.
    """
    classes = getattr(_IMPL, "_locator_classes", None)
    if not isinstance(classes, list) or len(BASES) != len(_NAMES):
        return False
    if not any(c in classes for c in LOCATORS):
        classes[:0] = list(LOCATORS)
    return True
