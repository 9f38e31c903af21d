"""measurements.source / images / tracks and target.feature_slots: defaults, one-line errors naming the key."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from stereopose_mc.config import ScenarioError, load_scenario, load_scenario_text
from stereopose_mc.config.resolve import setup_of
from stereopose_mc.config.sensor import feature_count
from stereopose_mc.sim import images

ROOT = Path(__file__).resolve().parents[2]
IMAGES = ROOT / "configs" / "caseB-images.yaml"


def data() -> dict:
    return yaml.safe_load(IMAGES.read_text())


def one_problem(d: dict, file: str = "bad.yaml") -> str:
    with pytest.raises(ScenarioError) as exc:
        load_scenario_text(yaml.safe_dump(d, sort_keys=False), file)
    ps = exc.value.problems
    assert len(ps) == 1 and "\n" not in str(ps[0]), [str(p) for p in ps]
    return f"{ps[0].path}: {ps[0].message}"


def test_bundled_images_scenario_resolves_to_the_tracker_settings():
    s = load_scenario(IMAGES)
    assert s.measurements.source == "images" and feature_count(s) == 24
    setup = setup_of(s)
    assert setup.n_points == 24 and not setup.x0[13:-2].any()  # the slots have no fixed points
    cfg = images.image_config(s)
    assert cfg.panels is not None and (cfg.panels.axis, cfg.panels.normal_axis, cfg.panels.span_m) == (0, 1, 3.0)
    assert (cfg.tracker.detector, cfg.tracker.window_px, cfg.tracker.min_tracks) == ("gftt", 15, 60)
    assert cfg.sensor.read_noise_e == 10.0 and cfg.cache
    # the point model keeps its default source and the (unused) default images block dumps and reloads
    b = load_scenario(ROOT / "configs" / "caseB.yaml")
    assert b.measurements.source == "model"
    assert load_scenario_text(yaml.safe_dump(b.model_dump(mode="json"))) == b


def test_panels_true_is_the_default_wings():
    d = data()
    d["measurements"]["images"]["panels"] = True
    assert images.image_config(load_scenario_text(yaml.safe_dump(d))).panels == images.Panels()
    d["measurements"]["images"]["panels"] = False
    assert images.image_config(load_scenario_text(yaml.safe_dump(d))).panels is None


@pytest.mark.parametrize("edit, message", [
    (lambda d: d["target"].pop("feature_slots"),
     "target: give exactly one of feature_points_m, feature_points or feature_slots"),
    (lambda d: d["target"].update(feature_points={"sample_on_surface": 5}),
     "target: give exactly one of feature_points_m, feature_points or feature_slots (got feature_points, "
     "feature_slots)"),
    (lambda d: d["target"].update(feature_slots=0), "target.feature_slots: Input should be greater than or equal to 1"),
    (lambda d: d["target"].pop("shape"), "measurements.source: images needs target.shape (the body to render)"),
    (lambda d: [d["camera"].pop(k) for k in ("resolution_px", "fov_deg")]
     + [d["measurements"].pop(k) for k in ("image_sigma_px", "flow_sigma_pxps")],
     "measurements.source: images needs camera.resolution_px (a pixel camera)"),
    (lambda d: d["measurements"]["images"].update(detector="surf"), "measurements.images.detector: Input should be"),
    (lambda d: d["measurements"]["images"]["tracker"].update(window_px=14),
     "measurements.images.tracker: window_px (14) must be odd"),
    (lambda d: d["measurements"]["images"]["tracker"].update(min_tracks=200),
     "measurements.images.tracker: min_tracks (200) must not exceed max_tracks (150)"),
    (lambda d: d["measurements"]["images"]["panels"].update(normal_axis=0),
     "measurements.images.panels: normal_axis (0) must differ from axis (0)"),
    (lambda d: d["measurements"].update(dropout_probability=0.1),
     "measurements: dropout_probability is a point-model effect"),
    (lambda d: d["measurements"].update(tracks={"file": "t.csv"}), "measurements: tracks needs source: tracks"),
    (lambda d: d["measurements"].update(source="tracks"), "measurements: source tracks needs tracks: {file: ...}"),
    (lambda d: d["measurements"].update(source="model"), "measurements: images needs source: images (source is model)"),
    (lambda d: d["measurements"].update(source="pictures"), "measurements.source: Input should be"),
])  # fmt: skip
def test_errors_name_the_key(edit, message):
    d = data()
    edit(d)
    assert one_problem(d).startswith(message)


def test_slots_need_a_non_model_source():
    d = yaml.safe_load((ROOT / "configs" / "caseB.yaml").read_text())
    d["target"] = {"inertia_kgm2": d["target"]["inertia_kgm2"], "feature_slots": 4}
    assert one_problem(d) == "target.feature_slots: needs measurements.source images or tracks"


def test_tracks_files_are_taken_from_the_scenario_folder(tmp_path):
    d = data()
    d["measurements"].pop("images")
    d["measurements"]["source"] = "tracks"
    d["measurements"]["tracks"] = {"file": "mine/tracks.parquet", "truth_file": "truth.csv"}
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "tracks.parquet").write_bytes(b"")
    (tmp_path / "truth.csv").write_text("")
    path = tmp_path / "s.yaml"
    path.write_text(yaml.safe_dump(d))
    s = load_scenario(path)
    assert s.measurements.tracks.file == str(tmp_path / "mine" / "tracks.parquet")
    assert s.measurements.tracks.truth_file == str(tmp_path / "truth.csv")
    d["measurements"]["tracks"] = {"file": "missing.csv", "truth_file": "mine"}
    path.write_text(yaml.safe_dump(d))
    with pytest.raises(ScenarioError) as exc:
        load_scenario(path)
    got = sorted(f"{p.path}: {p.message}" for p in exc.value.problems)
    assert got == [f"measurements.tracks.file: {tmp_path / 'missing.csv'}: file not found",
                   f"measurements.tracks.truth_file: {tmp_path / 'mine'}: is a directory, not a file"]  # fmt: skip
    d["measurements"]["tracks"] = {"file": "mine"}
    (tmp_path / "t.txt").write_text("")
    d["measurements"]["tracks"] = {"file": "t.txt"}
    path.write_text(yaml.safe_dump(d))
    with pytest.raises(ScenarioError, match=r"t\.txt: expected a \.parquet or \.csv file"):
        load_scenario(path)


def test_texture_file_is_resolved_from_the_scenario_folder_and_checked(tmp_path):
    import cv2
    import numpy as np

    d = data()
    (tmp_path / "tex").mkdir()
    cv2.imwrite(str(tmp_path / "tex" / "mli.png"), np.full((8, 16), 128, np.uint8))
    d["measurements"]["images"]["texture"] = {"file": "tex/mli.png", "size_m": [0.5, 0.25]}
    d["measurements"]["images"]["background"] = "earth"
    path = tmp_path / "s.yaml"
    path.write_text(yaml.safe_dump(d))
    s = load_scenario(path)
    assert s.measurements.images.texture.file == str(tmp_path / "tex" / "mli.png")
    assert s.measurements.images.background == "earth"
    for texture, fragment in [({"file": "nope.png", "size_m": [1, 1]}, f"{tmp_path / 'nope.png'}: file not found"),
                              ({"file": "tex", "size_m": [1, 1]}, "is a directory, not a file"),
                              ({"file": "s.yaml", "size_m": [1, 1]}, "not an image OpenCV can read")]:  # fmt: skip
        d["measurements"]["images"]["texture"] = texture
        path.write_text(yaml.safe_dump(d))
        with pytest.raises(ScenarioError) as exc:
            load_scenario(path)
        ps = exc.value.problems
        assert len(ps) == 1 and ps[0].path == "measurements.images.texture.file" and fragment in ps[0].message
        assert ps[0].line is not None and "\n" not in str(ps[0])
    d["measurements"]["images"]["texture"] = {"file": "tex/mli.png", "size_m": [1.0, -1.0]}
    assert one_problem(d).startswith("measurements.images.texture.size_m.1:")
    d["measurements"]["images"]["texture"] = {"file": "tex/mli.png", "size_m": [1.0, 1.0], "tile": 2}
    assert one_problem(d).startswith("measurements.images.texture.tile:")
    d["measurements"]["images"]["texture"] = None
    d["measurements"]["images"]["background"] = "stars"
    msg = one_problem(d)
    assert msg.startswith("measurements.images.background:") and "earth" in msg
