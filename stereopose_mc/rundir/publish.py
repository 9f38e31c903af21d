"""Atomic publication of a run's tables: staged, renamed into place, recorded in the manifest last.

A session of ``spmc run`` (or ``--resume``) first writes ``"end": null, "published": null`` to
the manifest; the merged tables (``trials.parquet``, ``timeseries.parquet``, ``timing.parquet``,
the percentile tables) are written into a hidden staging directory ``DIR/.publish-…``, renamed
into ``DIR`` one by one, and only then does the manifest record each published file's size and
SHA-256 (``published``) together with ``end``: the run's completion mark. A crash anywhere in
between leaves a manifest without the mark, which :func:`problems` reports (``report``,
``compare`` and ``rerun`` refuse the directory) and ``--resume`` repairs by publishing again.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Mapping

from .integrity import file_sha256, written_sha256
from .store import refuse_non_regular

STAGE_PREFIX = ".publish-"


def remove_stages(out: Path) -> None:
    """Remove staging directories an interrupted publication left in ``out``."""
    for d in Path(out).glob(STAGE_PREFIX + "*"):
        shutil.rmtree(d, ignore_errors=True)


def new_stage(out: Path) -> Path:
    """A fresh, empty staging directory inside ``out`` (the same file system: renames are atomic)."""
    remove_stages(out)
    return Path(tempfile.mkdtemp(dir=out, prefix=STAGE_PREFIX))


def publish(stage: Path, out: Path, known: Mapping[str, dict] | None = None) -> dict[str, dict]:
    """Rename every file of ``stage`` into ``out``; return ``{name: {"bytes", "sha256"}}`` for the manifest.

    ``known``: records the writer took as it wrote a file (``store.ParquetStream.record``), used where the staged
    file has the recorded size instead of reading the file again; the others are read and hashed here.
    """
    records = {}
    for f in sorted(Path(stage).iterdir()):
        size, sha = written_sha256(f, (known or {}).get(f.name))
        records[f.name] = {"bytes": size, "sha256": sha}
    for name in records:
        refuse_non_regular(Path(out) / name)
        os.replace(Path(stage) / name, Path(out) / name)
    Path(stage).rmdir()
    return records


def problems(out: Path, manifest: dict) -> list[str]:
    """What makes run directory ``out`` incomplete or inconsistent (one line each, to be prefixed with
    ``out``; empty: it is complete).

    A manifest without a ``published`` key predates publication records (or was written by
    hand): only its own checks apply.
    """
    if "published" not in manifest:
        return []
    pub = manifest.get("published")
    hint = f"repair it with spmc run --resume {out}"
    if not isinstance(pub, dict) or manifest.get("end") is None:
        return [f"incomplete run: its tables were not published (interrupted or still running); {hint}"]
    out_problems = []
    for name, rec in pub.items():
        p = Path(out) / name
        if not p.is_file():
            out_problems.append(f"{name} is missing (the run published it); {hint}")
        elif not isinstance(rec, dict) or p.stat().st_size != rec.get("bytes") or file_sha256(p) != rec.get("sha256"):
            out_problems.append(f"{name} is not the file the run published (changed, or mixed with another "
                                f"session's); {hint}")
    return out_problems


def dir_problems(out: Path) -> list[str]:
    """:func:`problems` of ``out`` when it is a run directory (its ``manifest.json`` says ``kind: run``),
    one line for a manifest that cannot be read; nothing for any other directory."""
    p = Path(out) / "manifest.json"
    if not p.is_file():
        return []
    try:
        m = json.loads(p.read_bytes())
    except (OSError, ValueError) as exc:
        return [f"{p}: unreadable manifest ({exc})"]
    if not isinstance(m, dict):
        return [f"{p}: not a JSON object"]
    return [f"{out}: {line}" for line in problems(out, m)] if m.get("kind") == "run" else []
