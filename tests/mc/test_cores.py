"""``--jobs``'s default: the affinity mask capped by a cgroup CPU quota (fake cgroup trees)."""

from __future__ import annotations

import os

import pytest

from stereopose_mc.mc import cores


def _tree(tmp_path, cgroup: str, files: dict[str, str]):
    tmp_path.mkdir(parents=True, exist_ok=True)
    proc = tmp_path / "proc-self-cgroup"
    proc.write_text(cgroup)
    root = tmp_path / "cgroup"
    for rel, text in files.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(text)
    return root, proc


def test_v2_quota_of_the_process_cgroup(tmp_path):
    root, proc = _tree(tmp_path, "0::/box/job\n", {"box/job/cpu.max": "150000 100000\n", "cpu.max": "max 100000\n"})
    assert cores.cgroup_cpus(root, proc) == pytest.approx(1.5)


def test_v2_tightest_ancestor_applies(tmp_path):
    root, proc = _tree(tmp_path, "0::/box/job\n", {"box/job/cpu.max": "max 100000", "box/cpu.max": "100000 100000"})
    assert cores.cgroup_cpus(root, proc) == pytest.approx(1.0)


def test_v2_unlimited(tmp_path):
    root, proc = _tree(tmp_path, "0::/\n", {"cpu.max": "max 100000"})
    assert cores.cgroup_cpus(root, proc) is None


def test_v1_quota(tmp_path):
    root, proc = _tree(tmp_path, "4:memory:/x\n1:cpu,cpuacct:/docker/abc\n0::/\n",
                       {"cpu/docker/abc/cpu.cfs_quota_us": "50000", "cpu/docker/abc/cpu.cfs_period_us": "100000"})
    assert cores.cgroup_cpus(root, proc) == pytest.approx(0.5)
    root, proc = _tree(tmp_path / "u", "1:cpu:/\n", {"cpu/cpu.cfs_quota_us": "-1", "cpu/cpu.cfs_period_us": "100000"})
    assert cores.cgroup_cpus(root, proc) is None


def test_available_cores_caps_the_affinity_by_the_quota_rounded_up(tmp_path, monkeypatch):
    monkeypatch.setattr(cores, "affinity_cpus", lambda: 8)
    root, proc = _tree(tmp_path, "0::/job\n", {"job/cpu.max": "250000 100000"})
    assert cores.available_cores(root, proc) == 3
    root, proc = _tree(tmp_path / "small", "0::/job\n", {"job/cpu.max": "20000 100000"})
    assert cores.available_cores(root, proc) == 1
    assert cores.available_cores(tmp_path / "none", tmp_path / "missing") == 8


def test_affinity_is_the_process_mask():
    assert cores.affinity_cpus() == len(os.sched_getaffinity(0))
