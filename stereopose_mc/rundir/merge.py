"""In-order merging of a run's chunk tables as the chunks finish (``timeseries.parquet``).

The chunks of a run finish in any order, but the merged file holds their rows in trial
order. :class:`InOrderMerge` knows every chunk of the run by its key (its first trial) and
feeds a :class:`store.ParquetStream` each chunk as soon as all the chunks before it are
in: a chunk computed in this session arrives as its in-memory Arrow table (no read-back
of the file just written), one from an earlier session (``--resume``) as the path of its
chunk file, read at its turn. A table that finished early waits in memory until its
predecessors are in; past ``max_pending_bytes`` of waiting tables, a new early arrival
keeps only its file's path (the chunk's files are written before it arrives), so memory
stays bounded whatever the run's size and completion order.

The merged bytes are those of :func:`store.write_parquet_stream` over the chunk files in
trial order: the same rows in the same order through the same writer.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Iterable

from . import store

if TYPE_CHECKING:
    import pyarrow as pa

MAX_PENDING_BYTES = 512 << 20  # tables waiting for a predecessor; beyond: their files are read at their turn


class InOrderMerge:
    """Feed ``stream`` the parts ``keys`` (in that order) from arrivals in any order.

    :meth:`add` gives a part: an Arrow table, the path of a Parquet file holding it, or
    neither (a part without rows). :meth:`close` checks that every part came and closes
    the stream; :meth:`abort` drops everything written.
    """

    def __init__(self, keys: Iterable[int], stream: store.ParquetStream, max_pending_bytes: int = MAX_PENDING_BYTES):
        self.keys = sorted(keys)
        self._index = {k: i for i, k in enumerate(self.keys)}
        if len(self._index) != len(self.keys):
            raise ValueError("duplicate keys")
        self.stream = stream
        self._max_pending = max_pending_bytes
        self._next = 0  # index in keys of the next part to write
        self._pending: dict[int, tuple[pa.Table | Path | None, int]] = {}  # key -> (part, bytes held)
        self._pending_bytes = 0

    @property
    def pending(self) -> list[int]:
        """The keys that arrived and wait for a predecessor."""
        return sorted(self._pending)

    @property
    def pending_bytes(self) -> int:
        """The memory held by tables that wait for a predecessor (at most ``max_pending_bytes``
        when every waiting table came with its file)."""
        return self._pending_bytes

    def add(self, key: int, table: pa.Table | None = None, path: Path | None = None) -> None:
        """Part ``key`` arrived: ``table`` (preferred), or ``path`` (read when its turn comes), or neither: no rows.

        With both, a part that must wait beyond the memory budget keeps only ``path``.
        """
        if self._index.get(key, -1) < self._next or key in self._pending:
            raise ValueError(f"part {key}: not expected (unknown, or already added)")
        part: pa.Table | Path | None = table if table is not None else path
        held = 0  # bytes of a table that waits for a predecessor
        if table is not None and key != self.keys[self._next]:
            if path is not None and self._pending_bytes + table.nbytes > self._max_pending:
                part = path
            else:
                held = table.nbytes
        self._pending[key] = (part, held)
        self._pending_bytes += held
        self._drain()

    def _drain(self) -> None:
        while self._next < len(self.keys) and self.keys[self._next] in self._pending:
            part, held = self._pending.pop(self.keys[self._next])
            self._pending_bytes -= held
            if isinstance(part, Path):
                part = store.read_parquet_file(part)
            if part is not None and part.num_rows:
                self.stream.append(part)
            self._next += 1

    def close(self) -> int:
        """Close the stream once every part is in (``ValueError`` naming the first missing one); its row count."""
        if self._next < len(self.keys):
            self.abort()
            raise ValueError(f"{self.stream.path}: part {self.keys[self._next]} never arrived")
        return self.stream.close()

    def abort(self) -> None:
        self._pending.clear()
        self._pending_bytes = 0
        self.stream.abort()
