"""Run-directory integrity (issue 13, items 1-2): chunk identity and checksums verified on
resume and merge, one writer per run directory, run directories complete or absent."""

from __future__ import annotations

import json
import os
import shutil
import stat
from pathlib import Path

import pandas as pd
import pytest
from stereopose_mc.rundir import integrity, runlock
from stereopose_mc.rundir.store import RunDirError

from cli_helpers import one_error_line, run_ok, spmc

PUBLISHED = ("trials.parquet", "timeseries.parquet", "timing.parquet", "percentiles.csv")


@pytest.fixture(scope="module")
def ref(quick_scenario, tmp_path_factory):
    """The uninterrupted run, chunks of 3 trials (0-2, 3-5)."""
    out = tmp_path_factory.mktemp("ref") / "run"
    run_ok("run", quick_scenario, "--out", out, "--chunk-size", 3)
    return out


@pytest.fixture(scope="module")
def other_seed(quick_scenario, tmp_path_factory):
    out = tmp_path_factory.mktemp("s7") / "run"
    run_ok("run", quick_scenario, "--out", out, "--chunk-size", 3, "--seed", 7)
    return out


def same_bytes(a: Path, b: Path):
    for n in ("trials.parquet", "timeseries.parquet", "percentiles.csv"):
        assert (a / n).read_bytes() == (b / n).read_bytes(), n


def unpublished_copy(ref: Path, dest: Path) -> Path:
    """A copy of the run with its chunks but nothing merged yet (as after a kill)."""
    shutil.copytree(ref, dest)
    for n in PUBLISHED + ("percentiles.md", "percentiles.parquet"):
        (dest / n).unlink(missing_ok=True)
    return dest


def resume(out: Path):
    r = spmc("run", "--resume", out, "--quiet", "--no-report")
    assert r.exit_code == 0, r.output
    return r


def test_foreign_chunk_is_rejected_by_name_and_recomputed(ref, other_seed, tmp_path):
    out = unpublished_copy(ref, tmp_path / "k")
    for p in (other_seed / "chunks").glob("*-0000000-0000002.parquet"):
        shutil.copy(p, out / "chunks" / p.name)
    r = resume(out)
    assert "trials-0000000-0000002.parquet: from another run" in r.output or \
        "timeseries-0000000-0000002.parquet: from another run" in r.output, r.output
    same_bytes(ref, out)
    assert set(pd.read_parquet(out / "trials.parquet")["seed"]) == {2014}
    assert (out / "chunks" / "rejected" / "trials-0000000-0000002.parquet").is_file()


def test_chunk_renamed_to_another_range_is_rejected(ref, tmp_path):
    out = unpublished_copy(ref, tmp_path / "k")
    c = out / "chunks"
    for p in list(c.glob("*-0000003-0000005.*")):
        p.unlink()
    for p in list(c.glob("*-0000000-0000002.*")):
        shutil.copy(p, c / p.name.replace("0000000-0000002", "0000003-0000005"))
    r = resume(out)
    assert "chunk-0000003-0000005.json: misnamed (it holds trials 0-2)" in r.output, r.output
    same_bytes(ref, out)


def test_deleted_timeseries_chunk_is_recomputed(ref, tmp_path):
    out = unpublished_copy(ref, tmp_path / "k")
    (out / "chunks" / "timeseries-0000003-0000005.parquet").unlink()
    r = resume(out)
    assert "timeseries-0000003-0000005.parquet is missing" in r.output, r.output
    same_bytes(ref, out)
    assert len(pd.read_parquet(out / "timeseries.parquet")) == 6 * 2 * 13  # trials x filters x steps


def test_truncated_chunk_is_recomputed_without_traceback(ref, tmp_path):
    out = unpublished_copy(ref, tmp_path / "k")
    p = out / "chunks" / "trials-0000000-0000002.parquet"
    p.write_bytes(p.read_bytes()[:100])
    r = resume(out)
    assert "trials-0000000-0000002.parquet: truncated or corrupt" in r.output, r.output
    assert "Traceback" not in r.output
    same_bytes(ref, out)


def test_chunks_without_sidecar_are_recomputed(ref, tmp_path):
    out = unpublished_copy(ref, tmp_path / "k")
    (out / "chunks" / "chunk-0000003-0000005.json").unlink()  # killed before the commit marker
    r = resume(out)
    assert "trials-0000003-0000005.parquet: not part of a recorded chunk" in r.output, r.output
    same_bytes(ref, out)


def test_merge_refuses_what_it_cannot_verify(ref, tmp_path):
    out = unpublished_copy(ref, tmp_path / "k")
    man = json.loads((out / "manifest.json").read_text())
    spec = integrity.RunSpec(integrity.run_id(man["scenario_hash"], man["seed"], man["code_version"]), 6,
                             man["filters"], 13, "full")  # fmt: skip
    v = integrity.verify_chunks(out / "chunks", spec)
    assert v.problems == [] and v.done_trials() == list(range(6))
    integrity.check_complete(v, spec)
    p = out / "chunks" / "timing-0000003-0000005.parquet"
    p.write_bytes(p.read_bytes() + b"x")
    with pytest.raises(integrity.IntegrityError, match="timing-0000003-0000005.parquet: truncated or corrupt"):
        integrity.check_complete(integrity.verify_chunks(out / "chunks", spec), spec)
    trials = pd.read_parquet(ref / "trials.parquet")
    integrity.check_trials_table(trials, spec)
    with pytest.raises(integrity.IntegrityError, match="1 duplicated trial x filter"):
        integrity.check_trials_table(pd.concat([trials, trials.iloc[:1]]), spec)
    with pytest.raises(integrity.IntegrityError, match="10 rows, expected 6 trials x 2 filters"):
        integrity.check_trials_table(trials.iloc[2:], spec)


def test_second_writer_is_refused_naming_the_holder(ref, quick_scenario, tmp_path):
    out = unpublished_copy(ref, tmp_path / "busy")
    fd = runlock.acquire(out, "test")
    try:
        for args in (("run", "--resume", out), ("run", quick_scenario, "--out", out, "--overwrite"), ("report", out)):
            r = spmc(*args, "--quiet", "--no-report") if args[0] == "run" else spmc(*args)
            assert r.exit_code == 2, r.output
            assert f"is in use by pid {os.getpid()}" in r.output and "started 20" in r.output, r.output
            assert "Traceback" not in r.output
        assert (out / "chunks" / "chunk-0000000-0000002.json").is_file()  # --overwrite did not touch it
    finally:
        runlock.release(fd)
    resume(out)  # released: the lock file left behind blocks no one
    same_bytes(ref, out)


def test_run_directory_is_created_complete_or_not_at_all(tmp_path):
    out = tmp_path / "new"

    def populate(d: Path) -> None:
        (d / "config.yaml").write_text("x")
        raise OSError(28, "No space left on device")

    with pytest.raises(RunDirError, match="No space left on device"):
        runlock.create_locked(out, False, populate, "test")
    assert list(tmp_path.iterdir()) == []


def test_overwrite_replaces_a_run_atomically(ref, quick_scenario, tmp_path):
    out = tmp_path / "run"
    shutil.copytree(ref, out)
    (out / "stale.txt").write_text("old")
    run_ok("run", quick_scenario, "--out", out, "--chunk-size", 6, "--overwrite")
    assert not (out / "stale.txt").exists()
    same_bytes(ref, out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]  # no staging or old copy left


@pytest.mark.parametrize("case", ["file", "under_file", "read_only"])
def test_bad_out_is_one_line_and_exit_2(quick_scenario, tmp_path, case):
    f = tmp_path / "afile"
    f.write_text("x")
    out = {"file": f, "under_file": f / "run", "read_only": tmp_path / "ro" / "run"}[case]
    if case == "read_only":
        (tmp_path / "ro").mkdir()
        os.chmod(tmp_path / "ro", stat.S_IRUSR | stat.S_IXUSR)
        if os.access(tmp_path / "ro", os.W_OK):  # root ignores permissions; /proc refuses even root
            out = Path("/proc/self/spmc-test/run")
    one_error_line(spmc("run", quick_scenario, "--out", out, "--quiet", "--no-report"), str(out))
    assert f.read_text() == "x"


def test_files_respect_the_umask(ref):
    mask = os.umask(0o022)
    os.umask(mask)
    for n in ("trials.parquet", "manifest.json", "config.yaml", "percentiles.csv", "chunks/chunk-0000000-0000002.json"):
        assert stat.S_IMODE((ref / n).stat().st_mode) == 0o666 & ~mask, n
    assert stat.S_IMODE(ref.stat().st_mode) == 0o777 & ~mask
