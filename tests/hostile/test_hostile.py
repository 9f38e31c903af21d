"""Compact versions of the hostile reproductions of issue 34: each stays fixed.

Runs are small (case B, a few trials of 12 s: ``quick_scenario``); crashes are injected by
monkeypatching the rename at the named moment. Every bad input: one line, exit 2, nothing
half-written, no traceback.
"""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path

import pytest

from cli_helpers import one_error_line, run_ok, spmc


@pytest.fixture(scope="module")
def run6(quick_scenario, tmp_path_factory):
    out = tmp_path_factory.mktemp("r") / "run"
    run_ok("run", quick_scenario, "--out", out, "--chunk-size", 3)
    return out


def _tree(d: Path) -> list[str]:
    return sorted(str(p.relative_to(d)) for p in d.rglob("*"))


# 1. --overwrite replaces only this tool's directories
@pytest.mark.parametrize("command", ["run", "simulate"])
def test_overwrite_refuses_a_foreign_directory(command, quick_scenario, tmp_path):
    d = tmp_path / "d"
    (d / "sub").mkdir(parents=True)
    (d / "thesis.tex").write_text("x")
    (d / "sub" / "fig.png").write_text("y")
    extra = ("--trials", 2, "--quiet", "--no-report") if command == "run" else ()
    r = spmc(command, quick_scenario, "--out", d, "--overwrite", *extra)
    one_error_line(r, str(d), "not a run, sweep or simulation directory", "--overwrite")
    assert _tree(d) == ["sub", "sub/fig.png", "thesis.tex"]
    assert [p.name for p in tmp_path.iterdir()] == ["d"]  # no staging sibling left behind


def test_overwrite_refuses_a_manifest_of_another_tool(quick_scenario, tmp_path):
    d = tmp_path / "d"
    d.mkdir()
    (d / "manifest.json").write_text(json.dumps({"kind": "run", "package": "other"}))
    one_error_line(spmc("run", quick_scenario, "--out", d, "--overwrite", "--trials", 2, "--quiet"),
                   "not a run, sweep or simulation directory")  # fmt: skip
    assert _tree(d) == ["manifest.json"]


def test_overwrite_replaces_a_run_directory(run6, quick_scenario, tmp_path):
    import shutil

    d = tmp_path / "run"
    shutil.copytree(run6, d)
    run_ok("run", quick_scenario, "--out", d, "--overwrite", "--trials", 2)
    assert json.loads((d / "manifest.json").read_text())["trials"] == 2


# 2. never write over a non-regular file
def test_rerun_out_refuses_a_fifo(run6, tmp_path):
    n = tmp_path / "n"
    os.mkfifo(n)
    one_error_line(spmc("rerun", run6, "--trial", 0, "--out", n), str(n), "not a regular file")
    assert stat.S_ISFIFO(os.lstat(n).st_mode)
    assert [p.name for p in tmp_path.iterdir()] == ["n"]


def test_atomic_write_refuses_a_non_regular_file(tmp_path):
    from stereopose_mc.rundir import store

    n = tmp_path / "n"
    os.mkfifo(n)
    with pytest.raises(OSError, match="not a regular file"):
        store.atomic_write_text(n, "x")
    with pytest.raises(OSError, match="not a regular file"):
        store.write_parquet(n, {"a": __import__("numpy").arange(3)})
    assert stat.S_ISFIFO(os.lstat(n).st_mode) and [p.name for p in tmp_path.iterdir()] == ["n"]


# 3. atomic publication: a crash while publishing leaves a run that report/compare/rerun refuse and --resume repairs
def _crash_after(monkeypatch, name: str):
    """Make the publication die right after ``name`` is renamed into the run directory."""
    real = os.replace

    def replace(src, dst, *a, **k):
        real(src, dst, *a, **k)
        if Path(dst).name == name and Path(src).parent.name.startswith(".publish-"):
            raise KeyboardInterrupt(f"killed after {name}")

    monkeypatch.setattr(os, "replace", replace)


def _published_bytes(d: Path) -> dict[str, bytes]:
    names = ("trials.parquet", "timeseries.parquet", "percentiles.csv", "percentiles.parquet")  # timing: wall times
    return {n: (d / n).read_bytes() for n in names}


def _refused_everywhere(d: Path, ref: Path, what: str):
    one_error_line(spmc("report", d), str(d), what, "--resume")
    r = spmc("compare", d, ref)
    assert r.exit_code == 2 and what in r.output and "Traceback" not in r.output, r.output
    one_error_line(spmc("rerun", d, "--trial", 0), what)


@pytest.mark.parametrize("extend", [False, True])
def test_crash_while_publishing(extend, run6, quick_scenario, tmp_path, monkeypatch):
    import shutil

    from stereopose_mc import api

    d = tmp_path / "run"
    if extend:  # extend a finished 3-trial run to 6, killed right after trials.parquet is renamed into place
        run_ok("run", quick_scenario, "--out", d, "--trials", 3, "--chunk-size", 3)
    _crash_after(monkeypatch, "trials.parquet")
    with pytest.raises(KeyboardInterrupt):
        if extend:
            api.resume(d, trials=6)
        else:
            api.run(quick_scenario, out=d)
    monkeypatch.undo()
    m = json.loads((d / "manifest.json").read_text())
    assert m["end"] is None and m["published"] is None
    _refused_everywhere(d, run6, "incomplete run")
    run_ok("run", "--resume", d)  # repairs: publishes again, the same bytes as an uninterrupted run
    assert _published_bytes(d) == _published_bytes(run6)
    assert not list(d.glob(".publish-*"))
    assert spmc("report", d).exit_code == 0
    shutil.rmtree(d / "figures")


def test_mixed_tables_are_refused(run6, tmp_path):
    import shutil

    d = tmp_path / "run"
    shutil.copytree(run6, d)
    other = tmp_path / "other"
    shutil.copytree(run6, other)
    (d / "timing.parquet").write_bytes((d / "timing.parquet").read_bytes() + b"x")
    _refused_everywhere(d, other, "timing.parquet is not the file the run published")
    (d / "timeseries.parquet").unlink()
    one_error_line(spmc("rerun", d, "--trial", 0), "timeseries.parquet is missing")
    run_ok("run", "--resume", d)
    assert _published_bytes(d) == _published_bytes(run6)


# 4. the manifest records kernels and backend before the first chunk; resume keeps them, a change is refused
def test_kernels_recorded_before_the_first_chunk(quick_scenario, tmp_path, monkeypatch):
    from stereopose_mc import api
    from stereopose_mc.mc import engine

    d = tmp_path / "run"
    seen = []

    def killed(scenario_json, trials, timeseries, kernels="numpy", tick=None):
        seen.append(kernels)
        raise KeyboardInterrupt("killed before the first chunk finished")

    monkeypatch.setattr(engine, "compute_chunk", killed)
    with pytest.raises(KeyboardInterrupt):
        api.run(quick_scenario, out=d, trials=2, kernels="compiled")
    assert json.loads((d / "manifest.json").read_text())["backend"]["kernels"] == "compiled"
    with pytest.raises(KeyboardInterrupt):
        api.resume(d)  # no --kernels: the run's own
    assert seen == ["compiled", "compiled"]
    monkeypatch.undo()
    before = (d / "manifest.json").read_bytes()
    one_error_line(spmc("run", "--resume", d, "--kernels", "numpy", "--quiet"), "--kernels compiled",
                   "--kernels numpy", "start a new run")  # fmt: skip
    assert (d / "manifest.json").read_bytes() == before


def test_resume_of_a_compiled_run_refuses_numpy(run6, tmp_path):
    import shutil

    d = tmp_path / "run"
    shutil.copytree(run6, d)  # run6 ran on the default kernels: compiled
    before = (d / "manifest.json").read_bytes()
    one_error_line(spmc("run", "--resume", d, "--kernels", "numpy", "--quiet"), "--kernels compiled")
    assert (d / "manifest.json").read_bytes() == before


# 7. a report over data that are all non-finite (every trial of a filter diverged at step 1) draws, never crashes
def test_report_on_all_non_finite_data(run6, tmp_path):
    import numpy as np
    import pandas as pd

    from outputs.output_helpers import copy_run  # a hand-edited run: no publication record

    d = copy_run(run6, tmp_path / "run")
    for name in ("timeseries.parquet", "trials.parquet"):
        t = pd.read_parquet(d / name)
        num = [c for c in t.columns if t[c].dtype.kind == "f" and c != "t"]
        t.loc[t["filter"] == "ekf", num] = np.nan
        t.to_parquet(d / name)
    r = spmc("report", d)
    assert r.exit_code == 0, r.output
    assert (d / "figures" / "time-ekf.png").is_file() and (d / "figures" / "nees-ekf.png").is_file()


# 13. an interrupted report leaves the previous figures/ whole
def test_interrupted_report_keeps_the_previous_figures(run6, tmp_path, monkeypatch):
    import shutil

    from stereopose_mc.outputs import report

    d = tmp_path / "run"
    shutil.copytree(run6, d)
    report.build_run_report(d)
    before = {p.name: p.read_bytes() for p in (d / "figures").iterdir()}
    assert "time-iekf.png" in before

    def interrupted(*args, **kwargs):  # Ctrl-C after every run figure was drawn into the staging directory
        raise KeyboardInterrupt

    monkeypatch.setattr(report.sensitivity_report, "section", interrupted)
    with pytest.raises(KeyboardInterrupt):
        report.build_run_report(d)
    assert {p.name: p.read_bytes() for p in (d / "figures").iterdir()} == before
    assert not [p for p in d.iterdir() if p.name.startswith(".figures-")]  # no staging left behind
    monkeypatch.undo()
    out = report.build_run_report(d)  # and the next report swaps a new set in whole
    assert sorted(p.name for p in (d / "figures").iterdir()) == sorted(before)
    assert 'src="data:image/png;base64,' in out.read_text() and "figures/time-iekf.png" in out.read_text()


# 9. corrupt run-directory files: one line naming the file
def _damaged(run6, tmp_path, name: str, edit) -> Path:
    import shutil

    d = tmp_path / "run"
    shutil.copytree(run6, d)
    p = d / name
    edit(p)
    return d


CORRUPT = {
    "yaml-syntax": ("config.yaml", lambda p: p.write_text(p.read_text() + "name: [\n"), "config.yaml"),
    "unknown-key": ("config.yaml", lambda p: p.write_text(p.read_text() + "colour: blue\n"), "colour"),
    "not-utf8": ("config.yaml", lambda p: p.write_bytes(p.read_bytes() + b"\xff\xfe\n"), "config.yaml"),
    "manifest-null": ("manifest.json", lambda p: p.write_text("null"), "manifest.json"),
    "trials-eight": ("manifest.json",
                     lambda p: p.write_text(json.dumps({**json.loads(p.read_text()), "trials": "eight"})), "trials"),
    "manifest-binary": ("manifest.json", lambda p: p.write_bytes(b"\xff{"), "manifest.json"),
}


@pytest.mark.parametrize("case", sorted(CORRUPT))
@pytest.mark.parametrize("command", ["rerun", "resume"])
def test_corrupt_run_directory_files(case, command, run6, tmp_path):
    name, edit, needle = CORRUPT[case]
    d = _damaged(run6, tmp_path, name, edit)
    before = {p: p.read_bytes() for p in d.rglob("*") if p.is_file() and p.name != ".lock"}
    args = ("rerun", d, "--trial", 0) if command == "rerun" else ("run", "--resume", d, "--quiet", "--no-report")
    line = one_error_line(spmc(*args), needle)
    assert str(d) in line or name in line
    after = {p: p.read_bytes() for p in d.rglob("*") if p.is_file() and p.name != ".lock"}
    assert after == before



def test_a_folder_report_names_a_run_whose_manifest_is_not_utf8_and_reports_the_others(run6, tmp_path):
    """(Before: a traceback from the folder search, UnicodeDecodeError, and no report at all.)"""
    import shutil

    folder = tmp_path / "runs"
    good, bad = folder / "a-good", folder / "b-bad"
    shutil.copytree(run6, good)
    shutil.copytree(run6, bad)
    (bad / "manifest.json").write_bytes(b"\xff{")
    before = {p: p.read_bytes() for p in bad.rglob("*") if p.is_file() and p.name != ".lock"}
    r = spmc("report", folder)
    assert r.exit_code == 2, r.output
    errors = [ln for ln in r.output.splitlines() if ln.startswith("error: ")]
    assert len(errors) == 1 and str(bad) in errors[0] and "manifest.json is unreadable" in errors[0], r.output
    assert "Traceback" not in r.output
    assert (good / "report.html").is_file() and (folder / "index.html").is_file()
    assert {p: p.read_bytes() for p in bad.rglob("*") if p.is_file() and p.name != ".lock"} == before


def test_export_of_a_run_whose_manifest_is_not_utf8(run6, tmp_path):
    d = _damaged(run6, tmp_path, "manifest.json", lambda p: p.write_bytes(b"\xff{"))
    one_error_line(spmc("export", d, "--format", "csv"), str(d), "not a run directory")
    assert not (d / "export").exists()


@pytest.mark.parametrize("content", [b"\xff{", b"[1, 2]", b"{"])
def test_a_sweep_directory_whose_sweep_file_is_damaged(content, quick_scenario, tmp_path):
    """``spmc sweep --out`` and ``spmc report`` on it: one line each, the file left as it was."""
    out = tmp_path / "sweep"
    out.mkdir()
    (out / "sweep.json").write_bytes(content)
    r = spmc("sweep", quick_scenario, "--set", "camera.baseline_m=1.0,1.5", "--trials", 2, "--out", out, "--quiet",
             "--no-report")  # fmt: skip
    one_error_line(r, "sweep.json", "another --out")
    line = one_error_line(spmc("report", out), "not a sweep")
    assert str(out) in line
    assert [p.name for p in out.iterdir()] == ["sweep.json"] and (out / "sweep.json").read_bytes() == content


def test_api_report_takes_one_path(run6, tmp_path):
    """``api.report("runs/x")``: the run (before: each character of the string taken for a path, "/" searched)."""
    import shutil

    from stereopose_mc import api

    d = tmp_path / "run"
    shutil.copytree(run6, d)
    res = api.report(str(d))
    assert res.problems == [] and res.written == [d / "report.html"]
    assert api.report(d).written == [d / "report.html"]

# 11. a size limit on scenario files
def test_validate_reads_a_bounded_amount(tmp_path):
    big = tmp_path / "big.yaml"
    big.write_text("# " + "x" * (5 << 20) + "\n")
    one_error_line(spmc("validate", big), str(big), "larger than 4 MiB")
    one_error_line(spmc("validate", "/dev/zero"), "/dev/zero", "larger than 4 MiB")


# 8. schema bounds: nothing that passes validate crashes or hangs a run
def _drag(**kw):
    return {"drag": {"ballistic_coefficient_leader_kgpm2": 100.0, "ballistic_coefficient_target_kgpm2": 100.0, **kw}}


OUT_OF_RANGE = {
    "a_km": ({"leader": {"orbit": {"a_km": 1.0e300, "e": 0.0}}}, "leader.orbit.a_km"),
    "rho_m": ({"truth_initial_state": {"rho_m": [10.0, 1.0e308, 10.0]}}, "truth_initial_state.rho_m"),
    "omega": ({"truth_initial_state": {"omega_degps": [0.0, 1.0e9, 0.0]}}, "truth_initial_state.omega_degps"),
    "seed": ({"seed": 10**38}, "seed"),
    "density": ({"truth_model": _drag(reference_density_kgpm3=1.0e30)}, "reference_density_kgpm3"),
    "scale_height": ({"truth_model": _drag(scale_height_km=1.0e-9)}, "scale_height_km"),
    "choice": ({"dispersions": {"camera.baseline_m": {"dist": "choice", "values": []}}}, "values"),
}


@pytest.mark.parametrize("case", sorted(OUT_OF_RANGE))
def test_validate_refuses_values_a_run_cannot_survive(case, tmp_path):
    from scenarios import scenario_dict

    over, key = OUT_OF_RANGE[case]
    def merged(a, b):
        return {**a, **{k: merged(a[k], v) if isinstance(v, dict) and isinstance(a.get(k), dict) else v
                        for k, v in b.items()}}  # fmt: skip

    d = merged(scenario_dict(trials=1), over)
    f = tmp_path / "s.yaml"
    import yaml

    f.write_text(yaml.safe_dump(d, sort_keys=False))
    r = spmc("validate", f)
    assert r.exit_code == 2 and key in r.output and "Traceback" not in r.output, r.output
    r = spmc("run", f, "--out", tmp_path / "run", "--quiet", "--no-report")
    assert r.exit_code == 2 and "Traceback" not in r.output, r.output
    assert not (tmp_path / "run").exists()


def test_run_seed_option_is_bounded(quick_scenario, tmp_path):
    r = spmc("run", quick_scenario, "--seed", 2**63, "--out", tmp_path / "run", "--quiet")
    assert r.exit_code == 2 and "--seed" in r.output and "Traceback" not in r.output
    assert not (tmp_path / "run").exists()


def test_truth_integration_has_a_limit(tmp_path, monkeypatch):
    from scenarios import write_scenario

    from cli_helpers import SHORT
    from stereopose_mc.core import perturbed

    monkeypatch.setattr(perturbed, "MAX_EVALUATIONS", 50)
    monkeypatch.setenv("SPMC_NO_CACHE", "1")
    f = write_scenario(tmp_path / "s.yaml", trials=1, time=SHORT, truth_model=_drag())
    one_error_line(spmc("run", f, "--out", tmp_path / "run", "--quiet"), "cannot be integrated",
                   "more than 50 evaluations")  # fmt: skip
    assert not (tmp_path / "run").exists()


# 5. an lhs run cannot be extended to the bytes of a fresh run: refused
def test_lhs_extension_is_refused(tmp_path):
    from scenarios import write_scenario

    from cli_helpers import SHORT

    disp = {"sampling": "lhs", "camera.baseline_m": {"dist": "uniform", "low": -0.01, "high": 0.01}}
    f = write_scenario(tmp_path / "s.yaml", trials=2, time=SHORT, dispersions=disp)
    d = tmp_path / "run"
    run_ok("run", f, "--out", d)
    before = {p: p.read_bytes() for p in d.rglob("*") if p.is_file() and p.name != ".lock"}
    one_error_line(spmc("run", "--resume", d, "--trials", 4, "--quiet"), "Latin hypercube", "--trials 4")
    assert {p: p.read_bytes() for p in d.rglob("*") if p.is_file() and p.name != ".lock"} == before


# 6. sweep resume checks each point's scenario hash
def test_sweep_resume_refuses_a_changed_scenario(quick_scenario, tmp_path):
    import yaml

    f = tmp_path / "s.yaml"
    f.write_text(quick_scenario.read_text())
    out = tmp_path / "sweep"
    args = ("sweep", f, "--set", "camera.baseline_m=1.0,1.5", "--trials", 2, "--out", out, "--quiet", "--no-report")
    r = spmc(*args)
    assert r.exit_code == 0, r.output
    d = yaml.safe_load(f.read_text())
    d["measurements"]["image_sigma"] = 2.0e-5
    f.write_text(yaml.safe_dump(d, sort_keys=False))
    one_error_line(spmc(*args), "p000", "different scenario", "another --out")


# 10. --scheduler at a service that is not Dask: one line within the connect timeout
@pytest.fixture
def fake_service():
    import socket
    import threading

    servers = []

    def start(answer: bytes | None):
        srv = socket.socket()
        srv.bind(("127.0.0.1", 0))
        srv.listen()
        conns = []

        def serve():
            try:
                c, _ = srv.accept()
            except OSError:
                return
            conns.append(c)
            if answer is not None:
                c.sendall(answer)

        threading.Thread(target=serve, daemon=True).start()
        servers.append((srv, conns))
        return f"tcp://127.0.0.1:{srv.getsockname()[1]}"

    yield start
    for srv, conns in servers:
        for c in conns:
            c.close()
        srv.close()


@pytest.mark.parametrize("answer,needle", [(b"\xff" * 64, "not a Dask scheduler"),
                                           (b"HTTP/1.1 200 OK\r\n\r\n", "not a Dask scheduler"),
                                           (None, "no Dask handshake within")])  # fmt: skip
def test_scheduler_that_is_not_dask(answer, needle, fake_service, quick_scenario, tmp_path, monkeypatch):
    import time

    from stereopose_mc.mc import engine

    monkeypatch.setattr(engine, "DASK_CONNECT_TIMEOUT_S", 1)
    address = fake_service(answer)
    t0 = time.monotonic()
    r = spmc("run", quick_scenario, "--backend", "dask", "--scheduler", address, "--out", tmp_path / "run", "--quiet")
    assert time.monotonic() - t0 < 30
    one_error_line(r, address, needle)
    assert not (tmp_path / "run").exists()


# 12. the right words for a wrong shape type
def test_wrong_shape_type_is_named_as_a_shape(tmp_path):
    from scenarios import write_scenario

    f = write_scenario(tmp_path / "s.yaml", target={"shape": {"type": "torus"}})
    line = one_error_line(spmc("validate", f), "target.shape.type", "unknown shape type 'torus'", "'box'", "'mesh'")
    assert "filter" not in line


# 13. minor: one line for a NaN in a union-typed value, the key's own line, an impossible inertia
def test_nan_std_is_one_line(tmp_path):
    from scenarios import write_scenario

    f = write_scenario(tmp_path / "s.yaml", dispersions={"camera.baseline_m": {"dist": "normal", "std": float("nan")}})
    line = one_error_line(spmc("validate", f), "dispersions.camera.baseline_m.std:", "finite number")
    assert "list[" not in line


@pytest.mark.parametrize("key,value", [("occlusion", True), ("illumination", {"sun_direction_lvlh": [1.0, 0.0, 0.0]}),
                                       ("image_sigma_px", 0.3)])  # fmt: skip
def test_cross_key_errors_name_the_keys_line(key, value, tmp_path):
    import yaml

    from scenarios import scenario_dict

    d = scenario_dict()
    d["measurements"][key] = value
    f = tmp_path / "s.yaml"
    f.write_text(yaml.safe_dump(d, sort_keys=False))
    line_no = next(i for i, t in enumerate(f.read_text().splitlines(), 1) if t.strip().startswith(f"{key}:"))
    one_error_line(spmc("validate", f), f"s.yaml:{line_no}: measurements.{key}: needs")


def test_observability_refuses_an_impossible_inertia():
    one_error_line(spmc("observability", "--inertia", 1, 1, 3), "--inertia 1 1 3", "triangle inequality")


# 14. nonsense: a feature point inside an occluding box is never measured; refused
@pytest.mark.parametrize("shape,inside", [({"type": "box", "size_m": [4.0, 4.0, 4.0]}, True),
                                          ({"type": "ellipsoid", "semi_axes_m": [3.0, 3.0, 3.0]}, True),
                                          ({"type": "box", "size_m": [1.0, 1.0, 1.0]}, False)])  # fmt: skip
def test_feature_inside_an_occluding_body(shape, inside, tmp_path):
    import yaml

    from scenarios import scenario_dict

    d = scenario_dict()
    d["target"]["shape"] = shape
    d["measurements"]["occlusion"] = True
    f = tmp_path / "s.yaml"
    f.write_text(yaml.safe_dump(d, sort_keys=False))
    r = spmc("validate", f)
    if inside:  # case B's points are within 1.5 m of the centre
        assert r.exit_code == 2 and "lies inside the target's" in r.output and "never visible" in r.output, r.output
        assert all(line.startswith("error: ") for line in r.output.strip().splitlines())
    else:
        assert r.exit_code == 0, r.output


def test_feature_inside_an_occluding_mesh(tmp_path):
    import yaml

    from scenarios import scenario_dict

    d = scenario_dict()
    d["target"]["shape"] = {"type": "mesh", "file": str(Path(__file__).resolve().parents[2] / "configs/meshes/box.obj")}
    d["measurements"]["occlusion"] = True
    # the 1 x 2 x 3 m box: case B's points lie outside it but point 2, [0, 0, 1.5], on its top face; the new one inside
    assert d["target"]["feature_points_m"][2] == [0.0, 0.0, 1.5]
    d["target"]["feature_points_m"] = d["target"]["feature_points_m"] + [[0.1, -0.2, 0.3]]
    f = tmp_path / "s.yaml"
    f.write_text(yaml.safe_dump(d, sort_keys=False))
    one_error_line(spmc("validate", f), "target.feature_points_m.5", "feature point 5 [0.1, -0.2, 0.3]",
                   "inside the target's mesh")  # fmt: skip
    d["target"]["feature_points_m"] = d["target"]["feature_points_m"][:-1]
    f.write_text(yaml.safe_dump(d, sort_keys=False))
    assert spmc("validate", f).exit_code == 0


def test_exit_ignores_a_late_ctrl_c(monkeypatch):
    import signal

    from stereopose_mc.cli import main

    class Exited(Exception):
        pass

    seen = {}

    def fake_exit(code):
        seen["code"], seen["sigint"] = code, signal.getsignal(signal.SIGINT)
        raise Exited

    before = signal.getsignal(signal.SIGINT)
    monkeypatch.setattr(main.os, "_exit", fake_exit)
    monkeypatch.setattr(main.atexit, "_run_exitfuncs", lambda: None)
    try:
        with pytest.raises(Exited):
            main.exit_now(0)
    finally:
        signal.signal(signal.SIGINT, before)
    assert seen == {"code": 0, "sigint": signal.SIG_IGN}
