"""Borrowed arrays in the kernels (core/kernels/_refs.py): the same memory without an owner, and the rules that keep
their owners alive."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
from numba import njit, types
from numba.extending import intrinsic

from stereopose_mc.core.kernels import _refs
from stereopose_mc.core.kernels._refs import borrow, keep

KERNELS = Path(_refs.__file__).parent


@intrinsic
def _meminfo(typingctx, a):
    """The address of ``a``'s meminfo (0: no owner, no reference counting)."""
    sig = types.intp(a)

    def codegen(context, builder, signature, args):
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        return builder.ptrtoint(ary.meminfo, context.get_value_type(types.intp))

    return sig, codegen


@njit(cache=False)
def _borrow_and_write(a, c):
    """Borrows ``a`` (and a view of a view of it), writes through both; their meminfos and data addresses."""
    b = borrow(a)
    v = b[1:, ::2]
    v[0, 0] = 7.0
    b[0, 0] = -1.0
    return _meminfo(a), _meminfo(b), _meminfo(v), b.shape, b.strides, v.ctypes.data, a[1:, ::2].ctypes.data


def test_borrow_is_the_same_memory_without_an_owner():
    a = np.arange(12.0).reshape(3, 4)
    own, bm, vm, shape, strides, vdata, adata = _borrow_and_write(a, 0)
    assert own != 0  # an array from Python has an owner ...
    assert bm == 0 and vm == 0  # ... its borrowed view and the views of that have none
    assert shape == a.shape and strides == a.strides and vdata == adata
    assert a[0, 0] == -1.0 and a[1, 0] == 7.0  # the writes went to a's memory


@njit(cache=False)
def _borrow_tuple(x, P, k):
    """A tuple of arrays of several types borrowed at once: their meminfos, and writes through them."""
    xb, Pb, kb = borrow((x, P, k))
    xb[0] = 1.5
    Pb[1, 1] = 2.5
    kb[2] = 9
    return _meminfo(xb), _meminfo(Pb), _meminfo(kb)


def test_borrow_of_a_tuple_borrows_each_array():
    x, P, k = np.zeros(3), np.zeros((2, 2)), np.zeros(4, np.int64)
    assert _borrow_tuple(x, P, k) == (0, 0, 0)
    assert x[0] == 1.5 and P[1, 1] == 2.5 and k[2] == 9


@njit(cache=False)
def _borrow_named(model):
    """A named tuple of an array and scalars (``model.StepModel``) borrowed: its array's meminfo, its scalars."""
    mb = borrow(model)
    mb.vis[0] = 5
    return _meminfo(mb.vis), mb.baseline, mb.disparity, mb.focal, mb.pseudo, mb.nd, mb.ndd


def test_borrow_of_a_named_tuple_borrows_its_arrays_and_keeps_its_scalars():
    from stereopose_mc.core.kernels.model import StepModel

    vis = np.arange(3, dtype=np.int64)
    got = _borrow_named(StepModel(vis, 0.5, True, 800.0, False, 1e-3, -2e-7))
    assert got == (0, 0.5, True, 800.0, False, 1e-3, -2e-7)
    assert vis[0] == 5  # written through the borrowed array


@njit(cache=False)
def _kept(m):
    """An owner allocated here, borrowed, then ``m`` arrays of its size allocated and filled with zeros before its
    borrowed view is read: ``keep`` holds the owner to the end, so the view still reads the owner's 7s."""
    a = np.full(100, 7.0)
    own = (a,)
    b = borrow(a)
    s = 0.0
    for _ in range(m):
        z = np.zeros(100)  # (were the owner freed, malloc would hand its block out again here)
        s += z[0]
    for i in range(100):
        s += b[i]
    keep(own)
    return s


def test_keep_holds_the_owner_of_a_borrowed_array():
    # Without the keep, Numba frees ``a`` after its last use (the borrow) and the zeros reuse its block: the sum
    # reads 0 (observed with numba 0.68 while writing this test)
    assert _kept(50) == 700.0


def _kernel_functions():
    for path in sorted(KERNELS.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef):
                yield path.name, node


def _called(node, name):
    """The calls of ``name`` in ``node``."""
    return [c for c in ast.walk(node) if isinstance(c, ast.Call) and isinstance(c.func, ast.Name) and c.func.id == name]


def _names(node):
    return {n.id for n in ast.walk(node) if isinstance(n, ast.Name)}


def test_every_kernel_keeps_the_owners_of_what_it_borrows():
    """The rules of ``_refs`` on every kernel that borrows: an array it allocates and borrows is kept (``keep``, directly
    or in a tuple passed to it) or returned (the caller then owns it), and no borrowed array is returned."""
    checked = 0
    for fname, fn in _kernel_functions():
        borrows = _called(fn, "borrow")
        if not borrows:
            continue
        checked += 1
        allocated, tuples, borrowed_names = set(), {}, set()
        for node in ast.walk(fn):
            if not isinstance(node, ast.Assign):
                continue
            targets = set().union(*(_names(t) for t in node.targets))
            if isinstance(node.value, ast.Call):
                f = node.value.func
                if isinstance(f, ast.Attribute) and getattr(f.value, "id", "") == "np" and f.attr in _ALLOCATE:
                    allocated |= targets
                if isinstance(f, ast.Name) and f.id == "_nees_scratch":  # views of one allocation
                    allocated |= targets
                if isinstance(f, ast.Name) and f.id == "borrow":
                    borrowed_names |= targets
            if isinstance(node.value, ast.Tuple) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name):
                tuples[node.targets[0].id] = _names(node.value)

        def expand(names):
            return set().union(names, *(tuples.get(n, set()) for n in names))

        borrowed = expand(set().union(*(_names(c) for c in borrows)))
        kept = expand(set().union(set(), *(_names(c) for c in _called(fn, "keep"))))
        returns = [n.value for n in ast.walk(fn) if isinstance(n, ast.Return) and n.value is not None]
        returned = expand(set().union(set(), *(_names(r) for r in returns)))
        for name in sorted(borrowed & allocated - returned):
            assert name in kept, f"{fname}: {fn.name} borrows {name}, which it allocated, and does not keep it"
        for r in returns:
            assert not (_names(r) & borrowed_names), f"{fname}: {fn.name} returns a borrowed array"
    assert checked >= 10  # the kernels that borrow (update, predict, measurement, charts, NEES)


_ALLOCATE = ("empty", "zeros", "full", "ones")
