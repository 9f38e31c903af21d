"""The run directory's files: atomic writes, manifests, Parquet with metadata and units."""

from __future__ import annotations

import errno
import functools
import hashlib
import json
import os
import platform
import shutil
import stat
import subprocess
import sys
import tempfile
import threading
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

if TYPE_CHECKING:  # pandas and pyarrow are imported where used, so that `spmc --help` starts fast
    import pandas as pd
    import pyarrow as pa

from .. import __version__
from ..config.schema import SCHEMA_VERSION
from .tables import arrow_table


class RunDirError(Exception):
    """A run directory that cannot be written or read as asked."""


def now_iso() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def git_revision() -> str | None:
    """The git revision of the package's checkout, if it is one."""
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            cwd=Path(__file__).resolve().parent,
            capture_output=True,
            text=True,
            timeout=5,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None if out.returncode == 0 else None


def base_manifest(command: list[str] | None = None) -> dict[str, Any]:
    return {
        "package": "stereopose_mc",
        "version": __version__,
        "schema_version": SCHEMA_VERSION,
        "git_revision": git_revision(),
        "host": platform.node(),
        "python": sys.version.split()[0],
        "command": command if command is not None else sys.argv,
    }


_UMASK_LOCK = threading.Lock()  # chunk files are written from several threads (mc/engine.py)


@functools.lru_cache(maxsize=1)
def _read_umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def umask() -> int:
    """The process's file-creation mask (read once, under a lock: reading it means setting it back
    and forth, which two threads doing at once would get wrong)."""
    with _UMASK_LOCK:
        return _read_umask()


def refuse_non_regular(path: Path) -> None:
    """``OSError`` when ``path`` exists and is neither a regular file nor a symbolic link (a device, a
    FIFO, a socket, a directory): a write replaces only files (a link is replaced, its target never)."""
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return
    if not (stat.S_ISREG(mode) or stat.S_ISLNK(mode)):
        raise OSError(errno.EEXIST, "exists and is not a regular file; not replacing it", str(path))


def _publish(tmp: str | Path, path: Path) -> None:
    """Give a temporary file (``mkstemp``: mode 0600) the mode the umask asks for, then rename it
    (never over anything but a regular file: :func:`refuse_non_regular`)."""
    os.chmod(tmp, 0o666 & ~umask())
    refuse_non_regular(path)
    os.replace(tmp, path)


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and a rename."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        _publish(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write_bytes(path, text.encode("utf-8"))


def write_json(path: Path, obj: Any) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=False, default=str) + "\n")


def with_units(table: pa.Table, units: dict[str, str] | None) -> pa.Table:
    """``table`` with each field's unit (``units[name]``) in the field's metadata, key ``unit``."""
    import pyarrow as pa

    if not units:
        return table
    fields = [f.with_metadata({b"unit": units[f.name].encode()}) if f.name in units else f for f in table.schema]
    # the same columns under the annotated schema (not table.cast: it imports pyarrow.compute, ~0.05 s)
    return pa.Table.from_arrays(table.columns, schema=pa.schema(fields, metadata=table.schema.metadata))


def field_units(path: Path) -> dict[str, str | None]:
    """The ``unit`` of each field of a Parquet file (None where it has none)."""
    import pyarrow.parquet as pq

    return {f.name: (f.metadata or {}).get(b"unit", b"").decode() or None for f in pq.read_schema(path)}


def parquet_options(schema: pa.Schema) -> dict[str, Any]:
    """The writer settings of every Parquet file of a run: no statistics; the columns that are not floating point
    (``filter``, ``trial``, ``step``, counts, flags) dictionary-encoded and zstd-compressed; the floating-point
    columns plain and uncompressed.

    Dictionary encoding suits the few distinct values of ``filter``, ``trial`` or ``step``; on the float columns
    (errors, sigmas, NEES: nearly all values distinct) the writer would fill a dictionary page, give up and fall
    back to plain pages, for 2.6x the time of the whole file and a larger file. Their mantissas are nearly random,
    so zstd takes only 5-9 % off their pages, at more than half of the writing time: 80,800 rows of case B's time
    series (51 columns) took 57 ms and 24.2 MB with zstd on every column, 24 ms and 26.3 MB with the floats
    uncompressed (zstd's fast levels: 30-36 ms, 25.7 MB). A run writes each chunk's time series twice (its chunk
    file, then the merged file), the last chunks' after its last trial.
    """
    import pyarrow.types as pat

    keep = [f.name for f in schema if not pat.is_floating(f.type)]
    codecs = {f.name: "none" if pat.is_floating(f.type) else "zstd" for f in schema}
    return {"compression": codecs, "write_statistics": False, "use_dictionary": keep}


class _DigestingFile:
    """A binary file for pyarrow's writer that also takes the SHA-256 and the size of what is written to it (the
    Parquet writer only appends: those of the file once it is closed)."""

    def __init__(self, fh):
        self._fh = fh
        self._sha = hashlib.sha256()
        self.size = 0

    def write(self, data) -> int:
        self._sha.update(data)
        self.size += memoryview(data).nbytes
        return self._fh.write(data)

    def tell(self) -> int:
        return self._fh.tell()

    def flush(self) -> None:
        self._fh.flush()

    def close(self) -> None:
        self._fh.close()

    @property
    def closed(self) -> bool:
        return self._fh.closed

    def writable(self) -> bool:
        return True

    def __enter__(self) -> _DigestingFile:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def record(self) -> dict[str, Any]:
        """``{"bytes", "sha256"}`` of what was written (``rundir/publish.py``'s record of a file)."""
        return {"bytes": self.size, "sha256": self._sha.hexdigest()}


def write_parquet(path: Path, df: pd.DataFrame | pa.Table | dict, metadata: dict[str, str] | None = None,
                  units: dict[str, str] | None = None) -> dict[str, Any]:  # fmt: skip
    """Write a table as Parquet atomically, with ``metadata`` in the file's key-value metadata
    and ``units`` in its fields' metadata; return the file's ``{"bytes", "sha256"}``, taken as it was written.

    ``df``: a pandas DataFrame, a pyarrow Table or ``rundir.tables.Columns`` (the run path,
    which does not import pandas). Written without pandas' index and with a fixed writer so
    that the same table gives the same bytes. ``units``: column -> unit, stored as the field
    metadata ``unit``.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    if isinstance(df, dict):
        table = arrow_table(df)
    elif isinstance(df, pa.Table):
        table = df
    else:
        table = pa.Table.from_pandas(df, preserve_index=False)
    meta = dict(table.schema.metadata or {})
    meta.pop(b"pandas", None)
    for k, v in (metadata or {}).items():
        meta[k.encode()] = str(v).encode()
    table = with_units(table.replace_schema_metadata(meta), units)
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with _DigestingFile(os.fdopen(fd, "wb")) as sink:
            pq.write_table(table, sink, **parquet_options(table.schema))
        _publish(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return sink.record()


# Rows per row group of a streamed file (the last one fewer). Small enough that a run's time-series merge writes its
# groups while later chunks still compute, leaving only the last chunks' rows to encode once they finish (case B,
# 1,000 trials, 202,000 rows: 0.05 s after the last chunk, against 0.13 s with 262,144 rows, which held the whole
# file until the end); a group of case B's 51 columns is ~26 MB in memory.
ROW_GROUP_ROWS = 65_536


class ParquetStream:
    """One Parquet file written from tables appended in row order, with fixed-size row groups.

    The rows go to a temporary file next to ``path``; :meth:`close` renames it to ``path``,
    :meth:`abort` (or leaving a ``with`` block by an exception) deletes it: nothing is ever
    half-written at ``path``. At most one row group and the last appended table are held,
    so memory stays bounded whatever the total size. Row groups hold exactly
    ``row_group_rows`` rows (the last one fewer) whatever the sizes of the appended tables,
    and the file carries only ``metadata`` (the tables' own schema metadata, e.g. a chunk's
    trial range, is dropped), so its bytes do not depend on how the rows were split.
    ``units``: column -> unit, stored as the field metadata ``unit``.

    The file's size and SHA-256 are taken as it is written (``record``, once closed): a run publishes its
    time series without reading it back (``rundir/publish.py``).
    """

    def __init__(self, path: Path, metadata: dict[str, str] | None = None, units: dict[str, str] | None = None,
                 row_group_rows: int = ROW_GROUP_ROWS):  # fmt: skip
        self.path = Path(path)
        self.rows = 0
        self.record: dict[str, Any] | None = None  # {"bytes", "sha256"} of the file, once closed
        self._meta = {k.encode(): str(v).encode() for k, v in (metadata or {}).items()}
        self._units, self._group = units, row_group_rows
        self._tmp: str | None = None
        self._sink: _DigestingFile | None = None
        self._writer = None
        self._buffered: list[pa.Table] = []
        self._n_buf = 0

    def append(self, table: pa.Table) -> None:
        """Append ``table``'s rows (the same columns and types as the tables before it)."""
        import pyarrow as pa
        import pyarrow.parquet as pq

        t = with_units(table.replace_schema_metadata(self._meta), self._units)
        if self._writer is None:
            fd, self._tmp = tempfile.mkstemp(dir=self.path.parent, prefix=f".{self.path.name}.", suffix=".tmp")
            self._sink = _DigestingFile(os.fdopen(fd, "wb"))
            self._writer = pq.ParquetWriter(self._sink, t.schema, **parquet_options(t.schema))
        self._buffered.append(t)
        self._n_buf += t.num_rows
        self.rows += t.num_rows
        while self._n_buf >= self._group:
            merged = pa.concat_tables(self._buffered)
            self._writer.write_table(merged.slice(0, self._group), row_group_size=self._group)
            rest = merged.slice(self._group)
            self._buffered, self._n_buf = [rest], rest.num_rows

    def close(self) -> int:
        """Write the last row group and rename the file into place; the number of rows.
        ``ValueError`` when nothing was appended (no file is written)."""
        import pyarrow as pa

        if self._writer is None:
            raise ValueError(f"{self.path}: no tables to write")
        try:
            if self._n_buf:
                self._writer.write_table(pa.concat_tables(self._buffered), row_group_size=self._group)
            self._buffered, self._n_buf = [], 0
            self._writer.close()
            self._sink.close()
            _publish(self._tmp, self.path)
        except BaseException:
            self.abort()
            raise
        self.record = self._sink.record()
        self._writer = self._tmp = self._sink = None
        return self.rows

    def abort(self) -> None:
        """Drop what was written (the temporary file); ``path`` is left as it was."""
        if self._writer is not None:
            self._writer.close()
        if self._sink is not None:
            self._sink.close()
        if self._tmp is not None:
            Path(self._tmp).unlink(missing_ok=True)
        self._writer = self._tmp = self._sink = None
        self._buffered, self._n_buf = [], 0

    def __enter__(self) -> ParquetStream:
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if exc_type is not None:
            self.abort()


def read_parquet_file(path: Path) -> pa.Table:
    """A whole Parquet file as a table (not ``pq.read_table``: it imports pandas, ``rundir/arrow.py``)."""
    import pyarrow.parquet as pq

    return pq.ParquetFile(path).read()


def write_parquet_stream(path: Path, sources: list[Path], metadata: dict[str, str] | None = None,
                         row_group_rows: int = ROW_GROUP_ROWS, units: dict[str, str] | None = None) -> int:  # fmt: skip
    """Concatenate Parquet files into one, streaming (:class:`ParquetStream`: one source file in
    memory at a time, fixed-size row groups, atomic). Returns the number of rows."""
    with ParquetStream(path, metadata, units, row_group_rows) as stream:
        for src in sources:
            stream.append(read_parquet_file(src))
        return stream.close()


def read_parquet_metadata(path: Path) -> dict[str, str]:
    import pyarrow.parquet as pq

    md = pq.read_schema(path).metadata or {}
    return {k.decode(): v.decode() for k, v in md.items()}


def parquet_rows(path: Path) -> int:
    """The number of rows of a Parquet file (from its footer)."""
    import pyarrow.parquet as pq

    return int(pq.ParquetFile(path).metadata.num_rows)


TOOL_KINDS = ("run", "simulate", "dynamics", "sweep")  # the ``kind`` of the directories this tool writes


def tool_dir_kind(path: Path) -> str | None:
    """The kind of directory this tool wrote at ``path`` (its ``manifest.json``, or a sweep's
    ``sweep.json``, says ``"package": "stereopose_mc"`` and a known ``kind``), else None."""
    for name in ("manifest.json", "sweep.json"):
        f = Path(path) / name
        try:
            if not f.is_file() or f.stat().st_size > 1 << 24:
                continue
            m = json.loads(f.read_bytes())
        except (OSError, ValueError):
            continue
        if isinstance(m, dict) and m.get("package") == "stereopose_mc" and m.get("kind") in TOOL_KINDS:
            return str(m["kind"])
    return None


def check_replaceable(path: Path, overwrite: bool) -> bool:
    """Whether ``path`` holds something to replace (a non-empty directory): refuse unless ``overwrite``
    and the directory is one this tool wrote (recognised by its manifest). :class:`RunDirError` otherwise."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise RunDirError(f"{path} exists and is not a directory; choose another --out")
    try:
        full = path.is_dir() and any(path.iterdir())
    except OSError as exc:
        raise RunDirError(f"{path}: cannot read it ({exc.strerror})") from None
    if not full:
        return False
    if not overwrite:
        raise RunDirError(f"{path} already exists and is not empty; pass --overwrite to replace it")
    if tool_dir_kind(path) is None:
        raise RunDirError(f"{path} is not a run, sweep or simulation directory of spmc (no spmc manifest.json); "
                          "--overwrite replaces only those: choose another --out")  # fmt: skip
    return True


def build_dir(path: Path, overwrite: bool, populate: Callable[[Path], Any]) -> Any:
    """Write directory ``path`` complete or not at all: ``populate(stage)`` fills a hidden sibling,
    which then replaces ``path`` by renames (an old directory only if :func:`check_replaceable`)."""
    path = Path(path)
    replace = check_replaceable(path, overwrite)
    stage = trash = None
    try:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            stage = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.new-"))
            os.chmod(stage, 0o777 & ~umask())
        except OSError as exc:
            raise RunDirError(f"{path}: cannot create it in {path.parent} ({exc.strerror})") from None
        try:
            result = populate(stage)
            if replace:
                trash = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.old-"))
                os.rename(path, trash / "old")
            elif path.is_dir():
                path.rmdir()  # empty
            os.rename(stage, path)
        except OSError as exc:
            if trash is not None and (trash / "old").exists() and not path.exists():
                os.rename(trash / "old", path)
            raise RunDirError(f"{path}: cannot write it ({exc.strerror})") from None
        stage = None
        return result
    finally:
        if stage is not None:
            shutil.rmtree(stage, ignore_errors=True)
        if trash is not None:
            shutil.rmtree(trash, ignore_errors=True)
