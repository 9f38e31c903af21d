"""Arrays without reference counts inside the kernels: ``borrow`` and ``keep``.

Numba counts the references to every array it did not prove short-lived: an array argument
of a compiled function that has a branch, and every view made of such an array (``P[b]``,
``x[9:13]``), gets an atomic increment on entry and an atomic decrement on exit of the owner's
count (``NRT_incref`` / ``NRT_decref``: a locked instruction each, which drains the store buffer).
Its pruning pass removes the pairs it can match, but not across the branches of the kernels'
per-trial loops, where hundreds of them per trial and step are a measurable part of a small update
(docs/kernels.md).

``borrow(a)`` is ``a`` (the same data, shape and strides) with no owner: its views and the calls
that take it pay no atomic operation (``NRT_incref`` of a null meminfo returns at once). It is a
borrowed reference, so the array it came from must stay referenced for as long as it is used:

- an argument of the kernel is referenced by its caller for the whole call;
- an array the kernel allocates is held to the end with ``keep``: the kernel puts the owners
  in a tuple before borrowing them and passes that tuple to ``keep`` after its last use of the
  borrowed arrays (Numba frees a variable after its last use: without the ``keep``, an owner
  whose name is rebound to its borrowed view is freed at once, and the next allocation may
  reuse its memory).

A borrowed array never leaves the kernel: not returned, not stored in a returned container
(boxing it would make a NumPy array of memory that nothing owns). ``tests/core/test_kernels_refs.py``
checks the two rules on every kernel source that borrows.
"""

from __future__ import annotations

from numba import types
from numba.extending import intrinsic


def _borrowed(context, builder, ty, value):
    """The array ``value`` of type ``ty`` with a null meminfo and parent (``populate_array``'s defaults)."""
    from numba.np.arrayobj import populate_array

    ary = context.make_array(ty)(context, builder, value)
    out = context.make_array(ty)(context, builder)
    populate_array(out, data=ary.data, shape=ary.shape, strides=ary.strides, itemsize=ary.itemsize, meminfo=None)
    return out._getvalue()


@intrinsic
def borrow(typingctx, a):
    """``a`` (an array, or a tuple or named tuple of arrays and scalars, e.g. ``model.StepModel``) without reference
    counting: the same data, shape and strides, no owner; a tuple's scalars as they are. Valid while the owner is
    referenced (module docstring)."""
    if isinstance(a, types.Array):
        arrays = False
    elif (isinstance(a, types.BaseTuple) and any(isinstance(t, types.Array) for t in a)
          and all(isinstance(t, (types.Array, types.Number, types.Boolean)) for t in a)):  # fmt: skip
        arrays = True
    else:
        return None
    sig = a(a)

    def codegen(context, builder, signature, args):
        ty, value = signature.args[0], args[0]
        if not arrays:
            return _borrowed(context, builder, ty, value)
        parts = [builder.extract_value(value, i) for i in range(len(ty))]
        parts = [_borrowed(context, builder, t, v) if isinstance(t, types.Array) else v for t, v in zip(ty, parts)]
        return context.make_tuple(builder, ty, parts)

    return sig, codegen


@intrinsic
def keep(typingctx, a):
    """No operation: a use of ``a``, so that Numba keeps the owners in ``a`` referenced up to this point."""
    sig = types.none(a)

    def codegen(context, builder, signature, args):
        return context.get_dummy_value()

    return sig, codegen
