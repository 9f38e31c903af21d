"""The in-order merge of chunk tables (rundir/merge.py) against the file-by-file merge
(store.write_parquet_stream): same bytes whatever the arrival order, the mix of tables and
files, or the memory budget; nothing half-written when a part is missing."""

from __future__ import annotations

import itertools

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from stereopose_mc.rundir import store
from stereopose_mc.rundir.merge import InOrderMerge
from stereopose_mc.rundir.tables import arrow_table

META = {"stereopose_mc.table": "timeseries", "stereopose_mc.seed": "7"}
UNITS = {"trial": "-", "e_rho": "m"}
GROUP = 50  # rows per row group: small, so that chunks straddle row-group boundaries


def chunk_table(first: int, n_trials: int, steps: int = 7) -> pa.Table:
    """A chunk's rows (trial, filter, step) as the engine builds them: sorted, one chunk of trials."""
    rng = np.random.default_rng(first)
    trial = np.repeat(np.arange(first, first + n_trials), 2 * steps)
    n = trial.size
    e = rng.normal(size=n)
    e[rng.random(n) < 0.05] = np.nan  # nulls, as a diverged trial's errors
    cols = {"trial": trial, "filter": np.tile(np.repeat(["iekf", "ekf"], steps), n_trials).astype(object),
            "step": np.tile(np.arange(steps, dtype=np.int32), 2 * n_trials), "e_rho": e}  # fmt: skip
    return arrow_table(cols).replace_schema_metadata({"stereopose_mc.first": str(first)})  # NaN -> null, as a run


SIZES = [3, 5, 1, 4, 6, 2]  # trials per chunk: 42-84 rows each, not a multiple of GROUP


@pytest.fixture()
def chunks(tmp_path):
    """The chunks as tables and as chunk files (written as the engine writes them), keyed by first trial."""
    firsts = np.concatenate([[0], np.cumsum(SIZES)[:-1]]).tolist()
    out = {}
    for first, n in zip(firsts, SIZES):
        t = chunk_table(first, n)
        path = tmp_path / f"timeseries-{first:07d}.parquet"
        store.write_parquet(path, t, {"stereopose_mc.first": str(first)}, units=UNITS)
        out[first] = (t, path)
    return out


@pytest.fixture()
def reference(chunks, tmp_path):
    """What the run wrote before the in-order merge: the chunk files, read back and streamed in trial order."""
    path = tmp_path / "ref.parquet"
    store.write_parquet_stream(path, [p for _, p in sorted(chunks.values(), key=lambda c: c[1].name)], META,
                               row_group_rows=GROUP, units=UNITS)  # fmt: skip
    return path


def merged(chunks, path, order, from_files=(), budget=1 << 30):
    m = InOrderMerge(chunks, store.ParquetStream(path, META, UNITS, GROUP), max_pending_bytes=budget)
    for k in from_files:  # chunks of an earlier session: their files
        m.add(k, path=chunks[k][1])
    held = []
    for k in order:
        m.add(k, *chunks[k])
        held.append(m.pending_bytes)
    return m.close(), held


@pytest.mark.parametrize("order", [[0, 3, 8, 9, 13, 19], [19, 13, 9, 8, 3, 0], [3, 0, 13, 19, 8, 9]])
def test_out_of_order_arrivals_give_the_bytes_of_the_file_merge(chunks, reference, tmp_path, order):
    n, _ = merged(chunks, tmp_path / "m.parquet", order)
    assert (tmp_path / "m.parquet").read_bytes() == reference.read_bytes()
    assert n == sum(t.num_rows for t, _ in chunks.values()) == 14 * sum(SIZES)


def test_the_file_merge_has_fixed_row_groups_in_trial_order(chunks, reference):
    f = pq.ParquetFile(reference)
    n = 14 * sum(SIZES)
    assert [f.metadata.row_group(i).num_rows for i in range(f.num_row_groups)] == [GROUP] * (n // GROUP) + [n % GROUP]
    got = f.read()
    want = pa.concat_tables([chunks[k][0] for k in sorted(chunks)])
    assert got.column("trial").to_pylist() == want.column("trial").to_pylist()
    assert got.column("e_rho").equals(want.column("e_rho"))
    assert {k.decode(): v.decode() for k, v in got.schema.metadata.items() if k.startswith(b"stereopose")} == META
    assert got.schema.field("e_rho").metadata == {b"unit": b"m"}


def test_every_arrival_order_of_four_chunks(chunks, reference, tmp_path):
    keys = [0, 3, 8, 9]
    ref = tmp_path / "ref4.parquet"
    store.write_parquet_stream(ref, [chunks[k][1] for k in keys], META, row_group_rows=GROUP, units=UNITS)
    four = {k: chunks[k] for k in keys}
    for order in itertools.permutations(keys):
        merged(four, tmp_path / "m.parquet", order)
        assert (tmp_path / "m.parquet").read_bytes() == ref.read_bytes(), order


@pytest.mark.parametrize("earlier", [[0, 3], [8, 19], [3, 9, 13]])
def test_resume_mixes_files_of_earlier_sessions_with_tables(chunks, reference, tmp_path, earlier):
    rest = [k for k in (19, 0, 13, 9, 8, 3) if k not in earlier]
    merged(chunks, tmp_path / "m.parquet", rest, from_files=earlier)
    assert (tmp_path / "m.parquet").read_bytes() == reference.read_bytes()


def test_waiting_tables_stay_within_the_memory_budget(chunks, reference, tmp_path):
    order = [19, 13, 9, 8, 3, 0]  # everything waits for chunk 0
    _, held = merged(chunks, tmp_path / "big.parquet", order)
    sizes = [chunks[k][0].nbytes for k in order]
    assert held == list(np.cumsum(sizes[:-1])) + [0]  # all held in memory, released once chunk 0 is in
    budget = sizes[0] + sizes[1]
    _, held = merged(chunks, tmp_path / "m.parquet", order, budget=budget)
    assert max(held) <= budget and held[-1] == 0
    assert held[:3] == [sizes[0], budget, budget]  # past the budget, a waiting chunk keeps only its file
    assert (tmp_path / "m.parquet").read_bytes() == reference.read_bytes()


def test_parts_without_rows_are_skipped(chunks, tmp_path):
    m = InOrderMerge([0, 3, 8], store.ParquetStream(tmp_path / "m.parquet", META, UNITS, GROUP))
    m.add(8, *chunks[8])
    m.add(3)  # e.g. --timeseries summary: a chunk past the summary trials has no rows
    m.add(0, *chunks[0])
    assert m.close() == chunks[0][0].num_rows + chunks[8][0].num_rows


def test_a_missing_part_leaves_nothing_written(chunks, tmp_path):
    m = InOrderMerge([0, 3, 8, 9], store.ParquetStream(tmp_path / "m.parquet", META, UNITS, GROUP))
    for k in (0, 3, 9):
        m.add(k, *chunks[k])
    assert m.pending == [9]
    with pytest.raises(ValueError, match="part 8 never arrived"):
        m.close()
    assert not list(tmp_path.glob("m.parquet")) and not list(tmp_path.glob(".m.parquet*"))


def test_unknown_or_repeated_parts_are_refused(chunks, tmp_path):
    m = InOrderMerge([0, 3], store.ParquetStream(tmp_path / "m.parquet", META, UNITS, GROUP))
    m.add(0, *chunks[0])
    with pytest.raises(ValueError, match="part 0: not expected"):
        m.add(0, *chunks[0])
    with pytest.raises(ValueError, match="part 5: not expected"):
        m.add(5, *chunks[0])
    with pytest.raises(ValueError, match="duplicate keys"):
        InOrderMerge([0, 0], store.ParquetStream(tmp_path / "x.parquet"))
    m.abort()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(p.name for _, p in chunks.values())


def test_an_aborted_stream_leaves_the_old_file(chunks, tmp_path):
    path = tmp_path / "m.parquet"
    path.write_bytes(b"old")
    with pytest.raises(KeyboardInterrupt):
        with store.ParquetStream(path, META, UNITS, GROUP) as s:
            s.append(chunks[0][0])
            raise KeyboardInterrupt
    assert path.read_bytes() == b"old" and not list(tmp_path.glob(".m.parquet*"))
    with pytest.raises(ValueError, match="no tables"):
        store.ParquetStream(tmp_path / "n.parquet").close()


def test_the_stream_records_the_size_and_sha256_of_the_file_it_wrote(chunks, tmp_path):
    import hashlib

    path = tmp_path / "m.parquet"
    merged(chunks, path, sorted(chunks))
    s = store.ParquetStream(tmp_path / "again.parquet", META, UNITS, GROUP)
    for k in sorted(chunks):
        s.append(chunks[k][0])
    assert s.record is None  # not before it is closed
    s.close()
    data = (tmp_path / "again.parquet").read_bytes()
    assert data == path.read_bytes()
    assert s.record == {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}
    aborted = store.ParquetStream(tmp_path / "gone.parquet", META, UNITS, GROUP)
    aborted.append(chunks[0][0])
    aborted.abort()
    assert aborted.record is None and not list(tmp_path.glob(".gone.parquet.*"))


def test_publish_takes_a_writers_record_only_for_a_file_of_the_recorded_size(tmp_path):
    import hashlib

    from stereopose_mc.rundir import publish

    out = tmp_path / "run"
    out.mkdir()
    stage = publish.new_stage(out)
    (stage / "a.parquet").write_bytes(b"abc")
    (stage / "b.parquet").write_bytes(b"defg")
    known = {"a.parquet": {"bytes": 3, "sha256": "recorded"},  # taken: the size matches
             "b.parquet": {"bytes": 3, "sha256": "stale"}}  # another size: hashed again  # fmt: skip
    rec = publish.publish(stage, out, known)
    assert rec == {"a.parquet": {"bytes": 3, "sha256": "recorded"},
                   "b.parquet": {"bytes": 4, "sha256": hashlib.sha256(b"defg").hexdigest()}}  # fmt: skip
    assert (out / "a.parquet").read_bytes() == b"abc" and not stage.exists()


def test_write_parquet_returns_the_size_and_sha256_of_the_file_it_wrote(chunks, tmp_path):
    import hashlib

    rec = store.write_parquet(tmp_path / "one.parquet", chunks[0][0], META, units=UNITS)
    data = (tmp_path / "one.parquet").read_bytes()
    assert rec == {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}
    assert not list(tmp_path.glob(".one.parquet.*"))  # no temporary left
