"""The run directory's files: atomic writes, manifests, Parquet with metadata and units."""

from __future__ import annotations

import functools
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any

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


@functools.lru_cache(maxsize=1)
def umask() -> int:
    """The process's file-creation mask (read once: setting it back and forth is not thread-safe)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _publish(tmp: str | Path, path: Path) -> None:
    """Give a temporary file (``mkstemp``: mode 0600) the mode the umask asks for, then rename it."""
    os.chmod(tmp, 0o666 & ~umask())
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
    """The writer settings of every Parquet file of a run: zstd, no statistics, dictionary pages for the
    columns that are not floating point only.

    Dictionary encoding suits the few distinct values of ``filter``, ``trial`` or ``step``; on the
    float columns (errors, sigmas, NEES: nearly all values distinct) the writer fills a dictionary
    page, gives up and falls back to plain pages, which took 2.6x the time of the whole file for a
    larger file (case B's 1,000-trial time series: 0.11 s and 17.1 MB with dictionaries everywhere,
    0.04 s and 13.6 MB with this).
    """
    import pyarrow.types as pat

    keep = [f.name for f in schema if not pat.is_floating(f.type)]
    return {"compression": "zstd", "write_statistics": False, "use_dictionary": keep}


def write_parquet(path: Path, df: pd.DataFrame | pa.Table | dict, metadata: dict[str, str] | None = None,
                  units: dict[str, str] | None = None) -> None:  # fmt: skip
    """Write a table as Parquet atomically, with ``metadata`` in the file's key-value metadata
    and ``units`` in its fields' metadata.

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
    os.close(fd)
    try:
        pq.write_table(table, tmp, **parquet_options(table.schema))
        _publish(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_parquet_stream(path: Path, sources: list[Path], metadata: dict[str, str] | None = None,
                         row_group_rows: int = 262_144, units: dict[str, str] | None = None) -> int:  # fmt: skip
    """Concatenate Parquet files into one, streaming, with fixed-size row groups.

    Only one source file and one row group are in memory at a time, so memory stays
    bounded whatever the total size. Row groups hold exactly ``row_group_rows`` rows
    (the last one fewer) whatever the sources' sizes, so the output's bytes do not
    depend on how the rows were split into sources. Returns the number of rows.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    writer = None
    buffered: list[pa.Table] = []
    n_buf = n_all = 0
    try:
        for src in sources:
            t = pq.ParquetFile(src).read()  # not pq.read_table: it imports pandas (rundir/arrow.py)
            # the output's metadata only: the sources' own (e.g. a chunk's trial range) would
            # make the bytes depend on the chunking
            t = t.replace_schema_metadata({k.encode(): str(v).encode() for k, v in (metadata or {}).items()})
            t = with_units(t, units)
            if writer is None:
                writer = pq.ParquetWriter(tmp, t.schema, **parquet_options(t.schema))
            buffered.append(t)
            n_buf += t.num_rows
            n_all += t.num_rows
            while n_buf >= row_group_rows:
                merged = pa.concat_tables(buffered)
                writer.write_table(merged.slice(0, row_group_rows), row_group_size=row_group_rows)
                rest = merged.slice(row_group_rows)
                buffered, n_buf = [rest], rest.num_rows
        if writer is None:
            raise ValueError("no source files to concatenate")
        if n_buf:
            writer.write_table(pa.concat_tables(buffered), row_group_size=row_group_rows)
        writer.close()
        _publish(tmp, path)
    except BaseException:
        if writer is not None:
            writer.close()
        Path(tmp).unlink(missing_ok=True)
        raise
    return n_all


def read_parquet_metadata(path: Path) -> dict[str, str]:
    import pyarrow.parquet as pq

    md = pq.read_schema(path).metadata or {}
    return {k.decode(): v.decode() for k, v in md.items()}


def prepare_dir(path: Path, overwrite: bool) -> None:
    """Create an empty output directory; refuse to reuse a non-empty one unless ``overwrite``."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise RunDirError(f"{path} exists and is not a directory; choose another --out")
    try:
        if path.exists() and any(path.iterdir()):
            if not overwrite:
                raise RunDirError(f"{path} already exists and is not empty; pass --overwrite to replace it")
            shutil.rmtree(path)
        path.mkdir(parents=True, exist_ok=True)
        probe = tempfile.NamedTemporaryFile(dir=path, prefix=".probe-")
        probe.close()
    except OSError as exc:
        raise RunDirError(f"{path}: cannot create or write it ({exc.strerror})") from None
