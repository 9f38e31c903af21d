"""Dask (issue 13, item 7): a worker killed mid-run costs time, never results; the manifest
records backend, scheduler address and worker count (docs/distributed.md)."""

from __future__ import annotations

import json
import os
import signal

import pytest

from stereopose_mc.config import load_scenario
from stereopose_mc.mc import engine

from cli_helpers import run_ok

distributed = pytest.importorskip("dask.distributed")


@pytest.mark.slow  # 6 s alone, 12 s under load (a LocalCluster starts twice)
def test_killed_worker_still_gives_identical_results(quick_scenario, tmp_path):
    reference = tmp_path / "local"
    run_ok("run", quick_scenario, "--out", reference, "--chunk-size", 1)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        with distributed.Client(cluster) as client:
            pids = sorted(client.run(os.getpid).values())
        killed: list[int] = []

        def kill_one_worker(done: int, total: int, diverged: dict) -> None:
            if done > 0 and not killed:  # after the first chunk: the other chunks are in flight
                os.kill(pids[0], signal.SIGKILL)
                killed.append(pids[0])

        out = tmp_path / "dask"
        opts = engine.RunOptions(chunk_size=1, backend="dask", scheduler=cluster.scheduler_address, command=["test"])
        engine.run(load_scenario(quick_scenario), out, opts, kill_one_worker)
    assert killed, "no worker was killed"
    for n in ("trials.parquet", "timeseries.parquet", "percentiles.csv"):
        assert (out / n).read_bytes() == (reference / n).read_bytes(), n
    man = json.loads((out / "manifest.json").read_text())
    assert man["backend"] == {"backend": "dask", "jobs": 1, "address": cluster.scheduler_address, "workers": 2,
                              "kernels": "compiled", "blas": engine.blas_kernels(), "ran_as": "dask"}
