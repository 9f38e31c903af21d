"""Run-directory integrity: chunk sidecars (identity, trial range, rows, checksums), their
verification before a resume or a merge, and the checks of the published tables.

A finished chunk ``first..last`` is three Parquet files (``trials-``, ``timing-`` and,
with a time series, ``timeseries-<first>-<last>.parquet``) and, written last and
atomically as the chunk's commit marker, the sidecar ``chunk-<first>-<last>.json``::

    {"run_id": "...", "first": 0, "last": 49, "steps": 1001,
     "files": {"trials-0000000-0000049.parquet": {"sha256": "...", "rows": 100}, ...},
     "diverged": {"iekf": 1, "ekf": 3}}

``run_id`` hashes the resolved scenario (with its seed) and the code version; the same
identity and trial range are also in every chunk file's Parquet metadata. A chunk is
accepted only if its sidecar parses, belongs to this run, is named after its range,
does not overlap another accepted chunk, lists every file it should, and every listed
file exists with the recorded checksum and the expected number of rows. Anything else
in ``chunks/`` (foreign, renamed, truncated, corrupt or incomplete chunks, stray files)
is reported by name: a resume moves it to ``chunks/rejected/`` and recomputes its
trials; a merge refuses to publish.
"""

from __future__ import annotations

import hashlib
import json
import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from .. import __version__
from . import store
from .tables import columns_of

SIDE_RE = re.compile(r"^chunk-(\d{7})-(\d{7})\.json$")
SUMMARY_TRIALS = 100  # trials kept in the time series with --timeseries summary


class IntegrityError(Exception):
    """Chunks or tables that cannot be merged or published; ``problems`` names each one."""

    def __init__(self, problems: list[str]):
        super().__init__("; ".join(problems))
        self.problems = problems


def code_version() -> str:
    """The package version and the git revision of its checkout (when it is one)."""
    return f"{__version__}+{store.git_revision() or 'unknown'}"


def run_id(scenario_hash: str, seed: int, code: str) -> str:
    """The identity of a run's chunks: scenario (hash without the trial count), seed, code."""
    return hashlib.sha256(f"{scenario_hash}\n{seed}\n{code}".encode()).hexdigest()


def file_sha256(path: Path) -> str:
    with open(path, "rb") as fh:
        return hashlib.file_digest(fh, "sha256").hexdigest()


def written_sha256(path: Path, record: Mapping[str, Any] | None) -> tuple[int, str]:
    """``(size, sha256)`` of a file: from the writer's record of it (``store.write_parquet``, ``ParquetStream``:
    taken as the bytes were written) where the file has the recorded size, else read and hashed."""
    size = path.stat().st_size
    if record is not None and record.get("bytes") == size:
        return size, record["sha256"]
    return size, file_sha256(path)


def chunk_file(kind: str, first: int, last: int) -> str:
    return f"{kind}-{first:07d}-{last:07d}.parquet"


def sidecar_name(first: int, last: int) -> str:
    return f"chunk-{first:07d}-{last:07d}.json"


def expected_kinds(first: int, last: int, timeseries: str) -> list[str]:
    """The files a chunk must have for the run's ``--timeseries`` mode."""
    ts = timeseries == "full" or (timeseries == "summary" and first < SUMMARY_TRIALS)
    return ["trials", "timing"] + (["timeseries"] if ts else [])


OPTIONAL_KINDS = ("tracks",)  # measurements.source images | tracks: the chunk's track table (rows: as many as tracked)


def ts_trials(first: int, last: int, timeseries: str) -> int:
    """How many of the chunk's trials are in the time series."""
    if timeseries == "full":
        return last - first + 1
    if timeseries == "summary":
        return max(0, min(last, SUMMARY_TRIALS - 1) - first + 1)
    return 0


@dataclass(frozen=True)
class RunSpec:
    """What every chunk of a run must agree with."""

    run_id: str
    trials: int
    filters: list[str]
    steps: int  # time-series rows per trial x filter (steps after t = 0, plus one)
    timeseries: str

    def rows(self, kind: str, first: int, last: int) -> int:
        n = ts_trials(first, last, self.timeseries) if kind == "timeseries" else last - first + 1
        return n * len(self.filters) * (self.steps if kind == "timeseries" else 1)


def write_sidecar(chunk_dir: Path, spec: RunSpec, first: int, last: int, diverged: dict[str, int],
                  written: Mapping[str, Mapping[str, Any]] | None = None) -> None:  # fmt: skip
    """Record the chunk's (already written) files; written last, atomically: the commit marker. ``written``: the
    writer's records of the files (``written_sha256``), by name; the others are read and hashed."""
    files = {}
    written = written or {}
    for kind in expected_kinds(first, last, spec.timeseries):
        name = chunk_file(kind, first, last)
        if (chunk_dir / name).is_file():
            sha = written_sha256(chunk_dir / name, written.get(name))[1]
            files[name] = {"sha256": sha, "rows": spec.rows(kind, first, last)}
    for kind in OPTIONAL_KINDS:
        name = chunk_file(kind, first, last)
        if (chunk_dir / name).is_file():
            sha = written_sha256(chunk_dir / name, written.get(name))[1]
            files[name] = {"sha256": sha, "rows": store.parquet_rows(chunk_dir / name)}
    rec = {"run_id": spec.run_id, "first": first, "last": last, "steps": spec.steps, "files": files,
           "diverged": {k: int(v) for k, v in diverged.items()}}  # fmt: skip
    store.write_json(chunk_dir / sidecar_name(first, last), rec)


@dataclass
class Verified:
    """Accepted chunks (sidecar records, sorted by first trial) and what was rejected, by name."""

    chunks: list[dict] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    rejected: list[str] = field(default_factory=list)  # file names in chunks/ to set aside

    def done_trials(self) -> list[int]:
        return [t for c in self.chunks for t in range(c["first"], c["last"] + 1)]

    def diverged(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for c in self.chunks:
            for k, v in c.get("diverged", {}).items():
                out[k] = out.get(k, 0) + int(v)
        return out


def _foreign_reason(path: Path, spec: RunSpec) -> str:
    """Why a file whose checksum does not match was rejected, as precisely as its metadata tells."""
    try:
        md = store.read_parquet_metadata(path)
    except Exception:  # noqa: BLE001 - any unreadable file is "truncated or corrupt"
        return "truncated or corrupt (not a readable Parquet file)"
    if md.get("stereopose_mc.run_id", spec.run_id) != spec.run_id:
        return "from another run (different scenario, seed or code version)"
    return "content differs from its recorded checksum (modified, truncated or replaced)"


def _check_chunk(chunk_dir: Path, side: Path, spec: RunSpec, m: re.Match) -> str | None:
    """The reason a chunk is not acceptable, or None."""
    try:
        rec = json.loads(side.read_text(encoding="utf-8"))
        first, last, files = int(rec["first"]), int(rec["last"]), dict(rec["files"])
    except (OSError, ValueError, KeyError, TypeError):
        return "unreadable sidecar"
    if rec.get("run_id") != spec.run_id:
        return "from another run (different scenario, seed or code version)"
    if (first, last) != (int(m.group(1)), int(m.group(2))):
        return f"misnamed (it holds trials {first}-{last})"
    if not (0 <= first <= last < spec.trials):
        return f"trials {first}-{last} are outside this run's 0-{spec.trials - 1}"
    if rec.get("steps") != spec.steps:
        return "recorded with a different number of time steps"
    for kind in expected_kinds(first, last, spec.timeseries):
        name = chunk_file(kind, first, last)
        if name not in files:
            return f"{name} is not recorded"
        path = chunk_dir / name
        if not path.is_file():
            return f"{name} is missing"
        if file_sha256(path) != files[name].get("sha256"):
            return f"{name}: {_foreign_reason(path, spec)}"
        if files[name].get("rows") != spec.rows(kind, first, last):
            return f"{name}: {files[name].get('rows')} rows recorded, {spec.rows(kind, first, last)} expected"
    for kind in OPTIONAL_KINDS:  # recorded when the chunk has one: present, and with its recorded checksum
        name = chunk_file(kind, first, last)
        if name in files:
            if not (chunk_dir / name).is_file():
                return f"{name} is missing"
            if file_sha256(chunk_dir / name) != files[name].get("sha256"):
                return f"{name}: {_foreign_reason(chunk_dir / name, spec)}"
    return None


def verify_chunks(chunk_dir: Path, spec: RunSpec) -> Verified:
    """Check every chunk in ``chunk_dir`` against ``spec`` (see the module docstring)."""
    v = Verified()
    taken: set[int] = set()
    owned: set[str] = set()
    for side in sorted(chunk_dir.glob("chunk-*.json")):
        m = SIDE_RE.match(side.name)
        reason = "unexpected file name" if m is None else _check_chunk(chunk_dir, side, spec, m)
        if reason is None:
            rec = json.loads(side.read_text(encoding="utf-8"))
            rng = set(range(rec["first"], rec["last"] + 1))
            if rng & taken:
                reason = "overlaps trials of another chunk (duplicate trials)"
            else:
                taken |= rng
                owned |= {side.name, *rec["files"]}
                v.chunks.append(rec)
                continue
        v.problems.append(f"{chunk_dir / side.name}: {reason}")
        v.rejected.append(side.name)
    reported = {n[len("chunk") : -len(".json")] for n in v.rejected}  # "-0000000-0000049"
    for p in sorted(chunk_dir.iterdir()):
        if p.is_file() and p.name not in owned and p.name not in v.rejected and not p.name.startswith("."):
            v.rejected.append(p.name)
            if not any(p.name.endswith(f"{r}.parquet") for r in reported):
                v.problems.append(f"{p}: not part of a recorded chunk of this run")
    v.chunks.sort(key=lambda c: c["first"])
    return v


def remove_stale_temporaries(chunk_dir: Path) -> int:
    """Delete the ``.NAME.XXXX.tmp`` files of writes a killed run left; call only under the run's lock."""
    stale = list(chunk_dir.glob(".*.tmp"))
    for p in stale:
        p.unlink(missing_ok=True)
    return len(stale)


def set_aside(chunk_dir: Path, names: list[str]) -> Path:
    """Move rejected files to ``chunks/rejected/`` (kept for inspection, out of the merge)."""
    dest = chunk_dir / "rejected"
    dest.mkdir(exist_ok=True)
    for n in names:
        if (chunk_dir / n).exists():
            shutil.move(str(chunk_dir / n), str(dest / n))
    return dest


def check_complete(v: Verified, spec: RunSpec) -> None:
    """Refuse a merge unless the accepted chunks cover trials 0..N-1 exactly once, with no problem left."""
    problems = list(v.problems)
    missing = sorted(set(range(spec.trials)) - set(v.done_trials()))
    if missing:
        problems.append(f"{len(missing)} trial(s) have no valid chunk (first missing: {missing[0]})")
    if problems:
        raise IntegrityError(problems)


def check_trials_table(df: Any, spec: RunSpec) -> None:
    """Exactly one row per trial x filter, trials 0..N-1, the run's filters (a DataFrame or ``tables.Columns``)."""
    c = columns_of(df)
    pairs = list(zip(c["trial"].tolist(), c["filter"].tolist()))
    n = len(pairs)
    want = spec.trials * len(spec.filters)
    dup = n - len(set(pairs))
    problems = []
    if dup:
        problems.append(f"trials table: {dup} duplicated trial x filter row(s)")
    if n != want or set(c["filter"].tolist()) != set(spec.filters) or set(c["trial"].tolist()) != set(range(spec.trials)):
        problems.append(f"trials table: {n} rows, expected {spec.trials} trials x {len(spec.filters)} filters")
    if problems:
        raise IntegrityError(problems)
