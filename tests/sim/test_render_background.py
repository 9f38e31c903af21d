"""The renderer's image-file texture (the file's albedo, read by OpenCV) and the Earth background (the
limb at asin(R / r) from nadir, Lambert shading against the law of sines, the target in front of it)."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from stereopose_mc.config.sensor import PixelCamera
from stereopose_mc.core import shapes
from stereopose_mc.sim.render import earth as ea, renderer as rr, scene as sc, texture as tx

CAM = PixelCamera(256, 192, 100.0, 128.0, 96.5)  # wide (104 deg across); row 96's centre is on the x-y plane
RIG = rr.Rig(CAM, 0.8)
DARK, BRIGHT = 64, 191  # the two tones of the test texture (8-bit)


@pytest.fixture(scope="module")
def two_tone(tmp_path_factory):
    """A 64 x 64 PNG: rows 0-31 DARK, rows 32-63 BRIGHT (a 1 m tile: tones alternate every 0.5 m along b)."""
    img = np.full((64, 64), DARK, np.uint8)
    img[32:] = BRIGHT
    path = tmp_path_factory.mktemp("tex") / "two_tone.png"
    cv2.imwrite(str(path), img)
    return path


def test_image_file_texture_renders_the_files_albedo(two_tone):
    atlas = tx.file_atlas(two_tone, (1.0, 1.0))
    assert [p.shape for p in atlas.pyramids[0]] == [(64 >> L,) * 2 for L in range(7)]
    scn = sc.scene(shapes.box([2.0, 2.0, 2.0]), 4, tile=atlas)
    cam = PixelCamera(128, 128, 300.0, 64.0, 64.0)
    # the face y = -1 faces the camera and the Sun (behind the camera): radiance = albedo exactly
    v = rr.render_view(scn, rr.Rig(cam, 0.8), np.array([0.0, 10.0, 0.0]), np.eye(3), np.array([0.0, -1.0, 0.0]),
                       "right")  # fmt: skip
    on_face = v.truth.hit & (np.abs(v.truth.point[..., 1] + 1.0) < 1e-9)
    frac = np.mod(v.truth.point[..., 0], 1.0)  # b = x on a face normal to y (texture rows)
    dark = on_face & (frac > 0.1) & (frac < 0.4)
    bright = on_face & (frac > 0.6) & (frac < 0.9)
    assert dark.sum() > 500 and bright.sum() > 500
    assert np.allclose(v.radiance[dark], DARK / 255, atol=1e-6)
    assert np.allclose(v.radiance[bright], BRIGHT / 255, atol=1e-6)
    ratio = v.radiance[bright].mean() / v.radiance[dark].mean()
    assert abs(ratio / (BRIGHT / DARK) - 1.0) < 0.01


def test_image_file_texture_is_mip_mapped_like_the_procedural_one(two_tone):
    """Far away (a pixel covers many tiles) the file's tile averages to its mean albedo."""
    atlas = tx.file_atlas(two_tone, (0.01, 0.01))
    a = np.linspace(0.0, 1.0, 50)
    got = atlas.sample(0, a, 0.37 * a, np.full(50, 5.0))
    assert np.allclose(got, (DARK + BRIGHT) / 2 / 255, atol=1e-6)


def _flat_earth(albedo: float = 0.3) -> ea.Earth:
    size = (2 * np.pi * ea.R_EARTH_M, np.pi * ea.R_EARTH_M)
    return ea.Earth(tx.Atlas((tx.pyramid(np.full((64, 128), albedo, np.float32)),), (size,)))


@pytest.mark.parametrize("altitude_km", [500.0, 900.0])
def test_earth_limb_and_lambert_shading_against_the_analytic_sphere(altitude_km):
    r = ea.R_EARTH_M + 1e3 * altitude_km
    ev = ea.view(_flat_earth(), r, 0.3)
    assert np.allclose(ev.centre_L, [-r, 0.0, 0.0])
    box = sc.scene(shapes.box([0.2, 0.2, 0.2]), 1)
    v = rr.render_view(box, RIG, np.array([0.0, -50.0, 0.0]), np.eye(3), np.array([1.0, 0.0, 0.0]), "right",
                       earth=ev)  # fmt: skip  (the target behind the camera: the Earth alone)
    row = v.radiance[96]
    col = np.arange(CAM.width) + 0.5
    theta = np.pi / 2 - np.arctan((CAM.cx - col) / CAM.f_px)  # angle of each pixel's ray from nadir (-x)
    limb = np.arcsin(ea.R_EARTH_M / r)
    inside, outside = theta < limb - 1e-3, theta > limb
    assert inside.sum() > 5 and outside.sum() > 5
    assert np.all(row[outside] == 0.0)
    # law of sines: r sin(theta) = R sin(e) (e: emission angle); the normal is gamma = e - theta from +x
    e = np.pi - np.arcsin(r * np.sin(theta[inside]) / ea.R_EARTH_M)
    gamma = np.pi - e - theta[inside]
    assert np.allclose(row[inside], float(np.float32(0.3)) * np.cos(gamma), rtol=1e-9, atol=1e-12)
    # the limb column: the first black pixel of the row sits where the ray leaves the disc
    first_black = np.flatnonzero(row == 0.0)[0]
    assert abs((CAM.cx - CAM.f_px / np.tan(limb)) - first_black) <= 1.0


def test_target_hides_the_earth_and_black_background_is_unchanged():
    box = sc.scene(shapes.box([2.0, 1.5, 3.0]), 3)
    rho, D, sun = np.array([-3.0, 9.0, 0.0]), np.eye(3), np.array([1.0, -0.5, 0.2]) / np.linalg.norm([1, -0.5, 0.2])
    ev = ea.view(_flat_earth(), ea.R_EARTH_M + 6e5, 0.0)
    black = rr.render_view(box, RIG, rho, D, sun, "left")
    earth = rr.render_view(box, RIG, rho, D, sun, "left", earth=ev)
    alone = rr.render_view(box, RIG, np.array([0.0, -50.0, 0.0]), D, sun, "left", earth=ev)
    hit = black.truth.hit
    assert hit.sum() > 1000 and (alone.radiance[hit] > 0).sum() > 100  # the target stands in front of the Earth
    assert np.array_equal(earth.radiance[hit], black.radiance[hit])
    assert np.array_equal(earth.radiance[~hit], alone.radiance[~hit])
    # an Earth out of view (behind the cameras) changes no bit
    away = dataclasses.replace(ev, centre_L=np.array([0.0, -1e8, 0.0]))
    assert np.array_equal(rr.render_view(box, RIG, rho, D, sun, "left", earth=away).radiance, black.radiance)


def test_earth_map_has_ocean_land_and_clouds():
    m = ea.earth(np.random.default_rng(5)).atlas.pyramids[0][0]
    assert m.shape == (ea.MAP_ROWS, ea.MAP_COLS) and m.min() >= ea.OCEAN - 1e-6 and m.max() <= ea.CLOUD + 1e-6
    for albedo, lo, hi in ((ea.OCEAN, 0.2, 0.7), (ea.LAND, 0.05, 0.4)):  # clear ocean and clear land
        assert lo < np.mean(np.abs(m - albedo) < 1e-4) < hi
    assert 0.05 < np.mean(m > 0.4) < 0.5  # cloud
