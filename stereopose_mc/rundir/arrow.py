"""numpy <-> Arrow for the column types of a run's tables, without pyarrow's pandas layer.

pyarrow's own converters (``pa.array`` on a numpy array or a list, ``Array.to_numpy`` when it
has to copy, ``pq.read_table``) first ask its pandas shim whether pandas is installed, which
imports pandas: ~0.25 s, a quarter of a two-trial run of case B (measured; ``spmc run`` never
needs pandas itself). The run path therefore moves its columns through Arrow's documented
buffer layout (``pa.Array.from_buffers`` and ``Array.buffers()``) for the few types its
tables hold, and reads files with ``pq.ParquetFile(...).read()``:

==================  ==================  =============================================
numpy               Arrow               nulls
==================  ==================  =============================================
float64, float32    double, float       NaN <-> null (as ``pa.array(..., from_pandas=True)``)
int64/32/16/8       int64/32/16/8       none written; read nulls are an error
bool                bool                none
object (str/None)   large_string        None <-> null (reads ``string`` too)
==================  ==================  =============================================

Both directions are tested against pyarrow's own converters (same arrays, same Parquet bytes).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import pyarrow as pa


def _bits(mask: np.ndarray) -> bytes:
    """A boolean array as an Arrow bitmap (least significant bit first)."""
    return np.packbits(mask, bitorder="little").tobytes()


def _unbits(buf, offset: int, n: int) -> np.ndarray:
    return np.unpackbits(np.frombuffer(buf, np.uint8), bitorder="little", count=offset + n)[offset:].astype(bool)


def to_arrow(v: np.ndarray) -> pa.Array:
    """A 1-D numpy column as an Arrow array (see the module's table of types)."""
    import pyarrow as pa

    v = np.asarray(v)
    if v.ndim != 1:
        raise ValueError(f"a column must be 1-D, not of shape {v.shape}")
    n = v.size
    if v.dtype == object:
        valid = ~(np.equal(v, None) | np.not_equal(v, v))  # None or NaN: null
        nulls = int(n - valid.sum())
        texts = (np.where(valid, v, "") if nulls else v).tolist()
        if not all(type(t) is str for t in texts):
            texts = [str(t) for t in texts]
        data = "".join(texts).encode()  # one call, not one per row (a time series has ~50k rows per chunk)
        lengths = np.fromiter(map(len, texts), np.int64, n)
        if len(data) != int(lengths.sum()):  # non-ASCII text: the lengths in bytes
            lengths = np.fromiter((len(t.encode()) for t in texts), np.int64, n)
        offsets = np.zeros(n + 1, np.int64)
        np.cumsum(lengths, out=offsets[1:])
        return pa.Array.from_buffers(pa.large_string(), n, [pa.py_buffer(_bits(valid)) if nulls else None,
                                                             pa.py_buffer(offsets), pa.py_buffer(data)],
                                     null_count=nulls)  # fmt: skip
    if v.dtype == np.bool_:
        return pa.Array.from_buffers(pa.bool_(), n, [None, pa.py_buffer(_bits(v))], null_count=0)
    if v.dtype.kind in "iuf":
        v = np.ascontiguousarray(v)
        typ = pa.from_numpy_dtype(v.dtype)
        if v.dtype.kind == "f":
            valid = ~np.isnan(v)
            nulls = int(n - valid.sum())
            if nulls:
                return pa.Array.from_buffers(typ, n, [pa.py_buffer(_bits(valid)), pa.py_buffer(v)], null_count=nulls)
        return pa.Array.from_buffers(typ, n, [None, pa.py_buffer(v)], null_count=0)
    raise TypeError(f"no Arrow conversion for a column of dtype {v.dtype}")


def _chunk_to_numpy(a: pa.Array) -> np.ndarray:
    import pyarrow.types as pat

    n, off = len(a), a.offset
    bufs = a.buffers()
    valid = None if a.null_count == 0 or bufs[0] is None else _unbits(bufs[0], off, n)
    t = a.type
    if pat.is_large_string(t) or pat.is_string(t):
        o = np.frombuffer(bufs[1], np.int64 if pat.is_large_string(t) else np.int32, count=off + n + 1)[off:]
        data = bufs[2].to_pybytes() if bufs[2] is not None else b""
        out = np.empty(n, object)
        out[:] = [data[o[i]:o[i + 1]].decode() for i in range(n)]
        if valid is not None:
            out[~valid] = None
        return out
    if pat.is_boolean(t):
        if valid is not None:
            raise ValueError("a boolean column with nulls")
        return _unbits(bufs[1], off, n)
    if pat.is_integer(t) or pat.is_floating(t):
        dt = np.dtype(t.to_pandas_dtype())
        x = np.frombuffer(bufs[1], dt, count=off + n)[off:].copy()
        if valid is not None:
            if dt.kind != "f":
                raise ValueError(f"an integer column ({t}) with nulls")
            x[~valid] = np.nan
        return x
    raise TypeError(f"no numpy conversion for an Arrow column of type {t}")


def _empty(t: pa.DataType) -> np.ndarray:
    import pyarrow.types as pat

    if pat.is_large_string(t) or pat.is_string(t):
        return np.empty(0, object)
    if pat.is_boolean(t):
        return np.empty(0, bool)
    return np.empty(0, np.dtype(t.to_pandas_dtype()))


def to_numpy(col: pa.Array | pa.ChunkedArray) -> np.ndarray:
    """An Arrow column (chunked or not) as a 1-D numpy array (see the module's table of types)."""
    chunks = getattr(col, "chunks", None)
    if chunks is None:
        return _chunk_to_numpy(col)
    if not chunks:
        return _empty(col.type)
    return np.concatenate([_chunk_to_numpy(c) for c in chunks]) if len(chunks) > 1 else _chunk_to_numpy(chunks[0])
