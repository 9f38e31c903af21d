"""``spmc observability`` and ``spmc inertia`` end to end (JSON parsed and checked)."""

from __future__ import annotations

import json
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from stereopose_mc.cli.main import app
from stereopose_mc.config import load_scenario
from stereopose_mc.core import mesh as M
from stereopose_mc.config.meshfiles import write_obj, write_ply, write_stl

from scenarios import CONFIGS

runner = CliRunner()
MESHES = CONFIGS / "meshes"


def spmc(*args):
    return runner.invoke(app, [str(a) for a in args])


def spmc_json(*args) -> dict:
    r = spmc(*args, "--json")
    assert r.exit_code == 0, r.output
    return json.loads(r.stdout)  # exactly one JSON object on stdout


# --------------------------------------------------------------------------- observability


def test_observability_default_is_case_b_rank_five():
    d = spmc_json("observability")
    assert d["rank"] == 5
    I = np.array([0.83, 1.0, 1.083])
    assert len(d["null_space"]) == 1
    np.testing.assert_allclose(d["null_space"][0], np.r_[0, 0, 0, I / np.linalg.norm(I)], atol=1e-10)
    assert len(d["singular_values"]) == 6
    # O = [I_3, 0; ...]: three singular values ~ 1, the last one numerically zero
    assert d["singular_values"][-1] < 1e-15
    assert d["omega_radps"] == pytest.approx(np.deg2rad([-0.1, -0.1, 0.034]).tolist(), rel=1e-15)


def test_observability_options():
    d = spmc_json("observability", "--omega-degps", "-3", "5", "10", "--inertia", "1", "2", "2.5", "--order", "2")
    assert d["rank"] == 5 and d["rows"] == 9 and len(d["singular_values"]) == 6
    np.testing.assert_allclose(d["null_space"][0][3:], np.array([1, 2, 2.5]) / np.linalg.norm([1, 2, 2.5]), atol=1e-10)
    d = spmc_json("observability", "--omega-degps", "0", "0", "4")
    assert d["rank"] == 3 and len(d["null_space"]) == 3
    r = spmc("observability")
    assert r.exit_code == 0
    assert "rank 5 of 6" in r.stdout and "only the inertia ratios are observable" in r.stdout


@pytest.mark.parametrize(
    "args", [["--inertia", "1", "-1", "2"], ["--order", "3"], ["--rtol", "2"], ["--omega-degps", "1", "2"]]
)
def test_observability_bad_input_exit_2(args):
    r = spmc("observability", *args)
    assert r.exit_code == 2


def test_observability_filter_state_case_e_json_names_k_among_the_weak_directions():
    d = spmc_json("observability", "--filter-state", CONFIGS / "caseE.yaml", "--duration-s", "30")
    assert d["scenario"] == "caseE" and d["duration_s"] == 30.0
    names = d["state_names"]
    assert len(names) == 30 and names[-2:] == ["k1", "k2"] and names[9:13] == ["q0", "q1", "q2", "q3"]
    assert set(d["scaling"]) == set(names) == set(d["crlb_sigma"])
    lam = d["eigenvalues"]
    assert lam == sorted(lam) and len(lam) == 26  # q norm and 3 gauge directions projected out
    assert len(d["weak_directions"]) == 5
    assert [w["eigenvalue"] for w in d["weak_directions"]] == lam[:5]
    weak_names = set().union(*(w["components"] for w in d["weak_directions"]))
    assert {"k1", "k2"} <= weak_names
    for w in d["weak_directions"]:
        v = np.array(list(w["components"].values()))
        assert np.all(np.abs(v) <= 1.0) and np.sum(v**2) <= 1.0 + 1e-12  # parts of a unit vector
    # the CRLB never exceeds the prior sqrt(P0): q 1e-5, k 0.5 in case E
    assert d["crlb_sigma"]["q0"] <= np.sqrt(1e-5) * (1 + 1e-9)
    assert d["crlb_sigma"]["k1"] <= np.sqrt(0.5)


def test_observability_filter_state_text_and_options():
    r = spmc("observability", "--filter-state", CONFIGS / "caseB.yaml", "--duration-s", "10", "--weak", "3")
    assert r.exit_code == 0, r.output
    assert "weakest 3 directions" in r.stdout and "CRLB" in r.stdout and "quaternion norm direction" in r.stdout
    d = spmc_json("observability", "--filter-state", CONFIGS / "caseB.yaml", "--duration-s", "10", "--keep-gauge")
    assert d["projected_out"] == ["q_norm"] and len(d["eigenvalues"]) == 29


@pytest.mark.parametrize(
    "args",
    [
        ["--filter-state", "configs/caseE.yaml", "--order", "2"],
        ["--filter-state", "configs/caseE.yaml", "--duration-s", "-1"],
        ["--filter-state", "configs/caseE.yaml", "--duration-s", "0.2"],
        ["--filter-state", "configs/caseE.yaml", "--weak", "0"],
        ["--filter-state", "does/not/exist.yaml"],
        ["--weak", "3"],
        ["--keep-gauge"],
    ],
)
def test_observability_filter_state_bad_input_exit_2(args):
    args = [str(CONFIGS.parent / a) if a.startswith("configs/") else a for a in args]
    r = spmc("observability", *args)
    assert r.exit_code == 2, r.output
    assert r.stdout == ""


def test_observability_filter_state_noise_free_scenario_exit_2(tmp_path):
    from scenarios import write_scenario

    d = yaml.safe_load((CONFIGS / "caseE.yaml").read_text())
    path = write_scenario(
        tmp_path / "quiet.yaml",
        "caseE",
        measurements={**d["measurements"], "flow_sigma": 0.0},
        filters=[{"type": "ekf", "measurement_noise": {"flow_sigma": 1e-5}}],
    )
    r = spmc("observability", "--filter-state", path, "--duration-s", "5")
    assert r.exit_code == 2 and r.stdout == ""
    assert "nonzero truth noise" in r.stderr


# --------------------------------------------------------------------------- inertia


def test_inertia_box_json():
    d = spmc_json("inertia", MESHES / "box.obj", "--density", "2700")
    m = 2700 * 6.0
    assert d["volume"] == pytest.approx(6.0, rel=1e-14)
    assert d["mass"] == pytest.approx(m, rel=1e-14)
    np.testing.assert_allclose(d["centroid"], 0.0, atol=1e-14)
    np.testing.assert_allclose(d["inertia"], np.diag([13, 10, 5]) * m / 12, rtol=1e-13)
    np.testing.assert_allclose(d["principal_moments"], np.array([5, 10, 13]) * m / 12, rtol=1e-13)
    A = np.array(d["principal_axes"])
    np.testing.assert_allclose(np.abs(A[:, 0]), [0, 0, 1], atol=1e-14)  # smallest moment about the long z edge
    assert d["k1"] == pytest.approx(np.log(0.5), rel=1e-13)
    assert d["k2"] == pytest.approx(np.log(10 / 13), rel=1e-13)
    assert d["repairs"] == []


@pytest.mark.parametrize("units, s", [("m", 1.0), ("cm", 0.01), ("mm", 0.001)])
def test_inertia_units_scale_the_input_only(tmp_path, units, s):
    V, F = M.box_mesh(10.0, 20.0, 30.0, center=(5, 5, 5))
    path = tmp_path / "box.ply"
    write_ply(path, V, F)
    d = spmc_json("inertia", path, "--units", units, "--density", "1000")
    a, b, c = 10 * s, 20 * s, 30 * s
    m = 1000 * a * b * c
    assert d["volume"] == pytest.approx(a * b * c, rel=1e-12)
    np.testing.assert_allclose(d["centroid"], [5 * s] * 3, rtol=1e-12)
    ref = np.array([b * b + c * c, a * a + c * c, a * a + b * b]) * m / 12
    np.testing.assert_allclose(np.diag(d["inertia"]), ref, rtol=1e-12)


def test_inertia_cylinder_stl_matches_the_polygon_prism():
    d = spmc_json("inertia", MESHES / "cylinder.stl", "--density", "1000")
    n, R, h = 64, 0.5, 2.0
    t = 2 * np.pi / n
    A = 0.5 * n * R * R * np.sin(t)
    J = n * R**4 * np.sin(t) * (2 + np.cos(t)) / 12
    Izz, Ixx = 1000 * h * J, 1000 * (h * J / 2 + A * h**3 / 12)
    np.testing.assert_allclose(d["principal_moments"], [Izz, Ixx, Ixx], rtol=1e-6)  # STL is float32
    assert d["k2"] == pytest.approx(0.0, abs=1e-6)


def test_thesis_tank_reproduces_the_cad_inertia():
    """Thesis eq. 7.39: I_SW = diag(85.3, 85.34, 26.67) kg cm^2 at 1 g/cm^3 (tank.obj fitted to it)."""
    d = spmc_json("inertia", MESHES / "tank.obj", "--units", "cm", "--density", "1000")
    kgcm2 = np.array(d["principal_moments"]) * 1e4
    np.testing.assert_allclose(kgcm2, [26.67, 85.32, 85.32], rtol=2e-3)
    assert d["k1"] == pytest.approx(np.log(26.67 / 85.32), abs=3e-3)


def test_inertia_bad_meshes_exit_2(tmp_path):
    for name, needle in [("open_box.obj", "not closed"), ("inward_box.ply", "inward-facing")]:
        r = spmc("inertia", MESHES / name)
        assert r.exit_code == 2
        assert needle in r.stderr and r.stdout == ""
    r = spmc("inertia", tmp_path / "missing.stl")
    assert r.exit_code == 2 and "file not found" in r.stderr
    (tmp_path / "x.off").write_text("OFF\n")
    assert spmc("inertia", tmp_path / "x.off").exit_code == 2
    assert spmc("inertia", MESHES / "box.obj", "--units", "inch").exit_code == 2
    assert spmc("inertia", MESHES / "box.obj", "--density", "0").exit_code == 2
    # --repair cannot close a hole
    r = spmc("inertia", MESHES / "open_box.obj", "--repair")
    assert r.exit_code == 2 and "not closed" in r.stderr


def test_inertia_repair_says_what_it_changed(tmp_path):
    d = spmc_json("inertia", MESHES / "inward_box.ply", "--repair")
    assert d["repairs"] == ["flipped all 12 triangles: the mesh was inward-facing (signed volume -6 -> 6)"]
    assert d["volume"] == pytest.approx(6.0, rel=1e-14)
    # inconsistent orientation: two faces flipped
    V, F = M.box_mesh(1.0, 2.0, 3.0)
    F[[2, 7]] = F[[2, 7]][:, [0, 2, 1]]
    write_obj(tmp_path / "b.obj", V, F)
    r = spmc("inertia", tmp_path / "b.obj")
    assert r.exit_code == 2 and "not consistently oriented" in r.stderr
    r = spmc("inertia", tmp_path / "b.obj", "--repair")
    assert r.exit_code == 0
    assert "repair: flipped 2 triangle(s) to orient each shell consistently" in r.stdout
    # an STL soup of a hollow box with the cavity facing outward
    V, F = M.combine(M.box_mesh(2.0, 2.0, 2.0), M.box_mesh(1.0, 1.0, 1.0))
    write_stl(tmp_path / "h.stl", V, F, binary=False)
    assert spmc("inertia", tmp_path / "h.stl").exit_code == 2
    d = spmc_json("inertia", tmp_path / "h.stl", "--repair")
    assert d["volume"] == pytest.approx(7.0, rel=1e-12) and d["shells"] == 2
    assert "cavity" in d["repairs"][0]


def test_target_config_writes_a_new_valid_scenario(tmp_path):
    src = CONFIGS / "caseB.yaml"
    out = tmp_path / "sub" / "caseB-tank.yaml"
    d = spmc_json("inertia", MESHES / "tank.obj", "--units", "cm", "--target-config", src, "--write-config", out)
    assert d["written_config"] == str(out)
    scn = load_scenario(out)
    assert scn.target.inertia_kgm2 == d["principal_moments"]  # full precision, ascending
    # everything else is the original text, comments included
    old, new = src.read_text().splitlines(), out.read_text().splitlines()
    changed = [line for line in new if line not in old]
    assert len(changed) == 2 and changed[0].strip().startswith("# inertia_kgm2 written by 'spmc inertia tank.obj'")
    assert changed[1].strip().startswith("inertia_kgm2: [")
    assert [line for line in old if line not in new] == ["  inertia_kgm2: [0.83, 1.0, 1.083]"]
    assert yaml.safe_load(out.read_text())["name"] == "caseB"


def test_target_config_refusals(tmp_path):
    src = tmp_path / "s.yaml"
    src.write_text((CONFIGS / "caseB.yaml").read_text())
    before = src.read_text()
    out = tmp_path / "o.yaml"
    # --target-config without --write-config (never edited in place)
    assert spmc("inertia", MESHES / "box.obj", "--target-config", src).exit_code == 2
    # same file, even with --overwrite
    r = spmc("inertia", MESHES / "box.obj", "--target-config", src, "--write-config", src, "--overwrite")
    assert r.exit_code == 2 and "write to a new file" in r.stderr
    assert src.read_text() == before
    # existing OUT needs --overwrite
    out.write_text("keep me\n")
    r = spmc("inertia", MESHES / "box.obj", "--target-config", src, "--write-config", out)
    assert r.exit_code == 2 and "--overwrite" in r.stderr and out.read_text() == "keep me\n"
    r = spmc("inertia", MESHES / "box.obj", "--target-config", src, "--write-config", out, "--overwrite")
    assert r.exit_code == 0
    assert load_scenario(out).target.inertia_kgm2 == pytest.approx([2500.0, 5000.0, 6500.0], rel=1e-14)
    # a bad mesh writes nothing
    out2 = tmp_path / "o2.yaml"
    assert spmc("inertia", MESHES / "open_box.obj", "--target-config", src, "--write-config", out2).exit_code == 2
    assert not out2.exists()
    # an invalid scenario is reported with its problems and nothing is written
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\n")
    assert spmc("inertia", MESHES / "box.obj", "--target-config", bad, "--write-config", out2).exit_code == 2
    assert not out2.exists()


def test_block_style_inertia_is_replaced(tmp_path):
    text = (CONFIGS / "caseB.yaml").read_text().replace(
        "  inertia_kgm2: [0.83, 1.0, 1.083]\n", "  inertia_kgm2:\n    - 0.83\n    - 1.0\n    - 1.083\n"
    )
    src = tmp_path / "s.yaml"
    src.write_text(text)
    out = tmp_path / "o.yaml"
    assert spmc("inertia", MESHES / "box.obj", "--target-config", src, "--write-config", out).exit_code == 0
    assert load_scenario(out).target.inertia_kgm2 == pytest.approx([2500.0, 5000.0, 6500.0], rel=1e-14)
    assert load_scenario(out).target.feature_points_m == load_scenario(src).target.feature_points_m


def test_text_output_states_si_units():
    r = spmc("inertia", MESHES / "tank.obj", "--units", "cm")
    assert r.exit_code == 0
    assert "all outputs in SI units" in r.stdout and "coordinates in cm" in r.stdout
    assert "equal principal moments 2 and 3" in r.stdout
    help_text = spmc("inertia", "--help").stdout
    assert "SI" in help_text


def test_meshes_folder_is_reproducible(tmp_path, monkeypatch):
    """configs/meshes/generate.py rewrites the checked-in meshes (same triangles, same numbers)."""
    import importlib.util

    from stereopose_mc.config.meshfiles import read_mesh

    spec = importlib.util.spec_from_file_location("gen", MESHES / "generate.py")
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)
    monkeypatch.setattr(gen, "HERE", tmp_path)
    gen.main()
    made = sorted(p.name for p in tmp_path.iterdir())
    assert made == sorted(p.name for p in MESHES.iterdir() if p.suffix in (".obj", ".stl", ".ply"))
    for name in made:
        a, b = read_mesh(tmp_path / name), read_mesh(MESHES / name)
        np.testing.assert_array_equal(a.faces, b.faces)
        np.testing.assert_allclose(a.vertices, b.vertices, rtol=1e-12, atol=1e-12)
