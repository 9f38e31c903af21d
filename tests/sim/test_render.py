"""The ray-cast renderer against independent geometry: the point model's projection, the
analytic silhouette of an ellipsoid, slab tests for shadows, and the sensor noise's theory."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from stereopose_mc.config.sensor import PixelCamera
from stereopose_mc.core import camera, quaternion as qt, shapes
from stereopose_mc.sim.render import renderer as rr, scene as sc, sensor as ss, texture as tx

CAM = PixelCamera(256, 192, 300.0, 131.3, 90.7)  # principal point off-centre on purpose
RIG = rr.Rig(CAM, 0.8)


def _pose(axis, deg, rho):
    q = qt.from_axis_angle(np.asarray(axis, float) / np.linalg.norm(axis), np.radians(deg))
    return np.asarray(rho, float), qt.dcm(q)


def _flat(scene: sc.Scene, albedo: float = 0.6) -> sc.Scene:
    """The scene with an untextured (constant albedo) atlas."""
    pyr = tuple(tuple(np.full((tx.TILE >> L,) * 2, albedo, np.float32) for L in range(tx.LEVELS)) for _ in range(3))
    return dataclasses.replace(scene, atlas=tx.Atlas(pyr))


@pytest.fixture(scope="module")
def box():
    return sc.scene(shapes.box([2.0, 1.5, 3.0]), 3)


@pytest.mark.parametrize("cam", ["right", "left"])
def test_hit_points_project_back_to_their_pixel_centres(box, cam):
    rho, D = _pose([1, 2, 0.5], 35, [0.4, 9.0, -0.3])
    col, row = rr.pixel_grid(CAM)
    h = rr.cast(box, RIG, rho, D, cam, col[..., 0], row[..., 0])
    assert 1000 < h.hit.sum() < h.hit.size
    p_L = h.point[h.hit] @ D.T + rho
    z = camera.project(p_L, np.zeros_like(p_L), RIG.baseline)  # the point model's projection (normalized)
    u, v = (z[:, 0], z[:, 1]) if cam == "right" else (z[:, 2], z[:, 3])
    assert np.max(np.abs(CAM.cx + CAM.f_px * u - col[..., 0][h.hit])) < 1e-6
    assert np.max(np.abs(CAM.cy + CAM.f_px * v - row[..., 0][h.hit])) < 1e-6
    assert np.allclose(h.depth[h.hit], p_L[:, 1])
    assert np.all(np.abs(np.abs(h.point[h.hit]) - [1.0, 0.75, 1.5]).min(axis=1) < 1e-9)  # on the box's surface


def test_box_corner_renders_at_its_projected_pixel(box):
    """The sharpest corner of the box's silhouette (lit by ambient light only, on black), found by
    OpenCV's sub-pixel corner refinement in the rendered image, against core/camera.py's projection."""
    rho, D = _pose([1.0, -0.3, 0.6], 40, [0.3, 10.0, 0.2])
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-0.75, 0.75) for z in (-1.5, 1.5)])
    c_L = corners @ D.T + rho
    z = camera.project(c_L, np.zeros_like(c_L), RIG.baseline)
    flat = _flat(box)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    for cam, (iu, iv) in (("right", (0, 1)), ("left", (2, 3))):
        px = np.stack([CAM.cx + CAM.f_px * z[:, iu], CAM.cy + CAM.f_px * z[:, iv]], axis=1)
        hull = cv2.convexHull(px.astype(np.float32), returnPoints=False).ravel()
        a, b, c = px[np.roll(hull, 1)], px[hull], px[np.roll(hull, -1)]
        cos = np.einsum("ij,ij->i", a - b, c - b) / np.linalg.norm(a - b, axis=1) / np.linalg.norm(c - b, axis=1)
        want = b[np.argmax(cos)]  # the silhouette vertex with the smallest angle
        rad = rr.render_view(flat, RIG, rho, D, np.array([0.0, 1.0, 0.0]), cam,
                             rr.RenderSettings(supersample=5, ambient=0.5)).radiance
        start = (want - 0.5 + [1.2, -1.1]).astype(np.float32).reshape(1, 1, 2)  # OpenCV: pixel centres at integers
        got = cv2.cornerSubPix(rad.astype(np.float32), start, (5, 5), (-1, -1), crit).reshape(2) + 0.5
        assert np.linalg.norm(got - want) < 0.5 / 2, (cam, got, want)


def test_ellipsoid_silhouette_matches_the_analytic_projection():
    a = np.array([1.0, 0.6, 0.8])
    ell = sc.scene(shapes.ellipsoid(a), 1)
    rho, D = _pose([0.3, 1.0, -0.4], 50, [0.2, 5.0, -0.1])
    col, row = rr.pixel_grid(CAM)
    col, row = col[..., 0], row[..., 0]
    v = rr.render_view(ell, RIG, rho, D, rr.DEFAULT_SUN_L, "right")
    # a pixel-centre ray o + t d meets x^T A x = 1 (in T) iff (d'Ad')(o'Ao' - 1) <= (d'Ao')^2
    A = np.diag(1.0 / a**2)
    o = D.T @ -rho
    d = rr.directions_L(CAM, col, row) @ D
    inside = np.einsum("...i,ij,...j", d, A, d) * (o @ A @ o - 1.0) <= np.einsum("...i,ij,j", d, A, o) ** 2
    assert inside.sum() > 5000
    iou = (inside & v.truth.hit).sum() / (inside | v.truth.hit).sum()
    assert iou >= 0.98, iou
    assert np.allclose(v.radiance > 0, v.truth.hit & (v.radiance > 0))  # nothing off the body is bright


def test_faces_turned_away_from_the_sun_are_dark_and_panels_cast_shadows():
    body = shapes.box([2.0, 1.5, 3.0])
    panels = sc.Panels(span_m=2.0, width_m=1.2, gap_m=0.1, axis=0, normal_axis=1)
    scn = _flat(sc.scene(body, 5, panels))
    rho, D = _pose([0.0, 0.0, 1.0], -35, [0.0, 12.0, 0.0])
    sun_T = np.array([1.0, 0.3, 0.1])  # from +x: the +x wing shadows the +x face, the -y face is turned away
    sun = D @ sun_T / np.linalg.norm(sun_T)
    v = rr.render_view(scn, RIG, rho, D, sun, "right")
    t = v.truth
    cos_i = np.einsum("hwi,i->hw", np.nan_to_num(t.normal), D.T @ sun)
    away = t.hit & (cos_i < -1e-3)
    assert away.sum() > 500 and np.all(v.radiance[away] == 0.0)
    # lit-facing body pixels: dark exactly when the segment toward the Sun crosses a wing (slab test)
    facing = t.hit & (cos_i > 1e-3) & (t.triangle < scn.n_body)
    p = t.point[facing]
    shadowed = np.zeros(len(p), bool)
    for sign in (1.0, -1.0):
        centre = np.array([sign * (1.0 + 0.1 + 1.0), 0.0, 0.0])
        half = np.array([1.0, 0.015, 0.6])
        tn, tf = shapes.ray_box(p - centre, np.broadcast_to(D.T @ sun, p.shape), half)
        shadowed |= (tn < tf) & (tf > 1e-9)
    assert 100 < shadowed.sum() < len(p) - 100
    assert np.array_equal(v.radiance[facing] == 0.0, shadowed)
    lit = v.radiance[facing][~shadowed]
    assert np.allclose(lit, 0.6 * cos_i[facing][~shadowed])  # Lambert, albedo 0.6


def test_noise_statistics_match_poisson_plus_read_noise():
    sensor = ss.SensorModel(exposure=0.8, full_well_e=20000.0, read_noise_e=12.0, bits=12)
    flat = np.full((256, 256), 0.4)
    e = ss.electrons(flat, sensor, np.random.default_rng(11))
    n = e.size
    mu, var = 0.8 * 20000.0 * 0.4, 0.8 * 20000.0 * 0.4 + 12.0**2
    assert abs(e.mean() - mu) < 4 * np.sqrt(var / n)
    assert abs(e.var() - var) < 4 * var * np.sqrt(2.0 / n)
    dn = ss.digitize(e, sensor).astype(float)  # quantization adds 1/12 DN^2
    g = sensor.gain
    assert abs(dn.mean() - g * mu) < 4 * g * np.sqrt(var / n)
    assert abs(dn.var() - (g**2 * var + 1 / 12)) < 4 * (g**2 * var + 1 / 12) * np.sqrt(2.0 / n)
    dark = ss.electrons(np.zeros((256, 256)), sensor, np.random.default_rng(12))
    assert abs(dark.std() - 12.0) < 4 * 12.0 / np.sqrt(2 * n)


def test_defocus_blur_spreads_a_point_by_its_sigma():
    r = np.zeros((65, 65))
    r[32, 32] = 1.0
    m = ss.mean_electrons(r, ss.SensorModel(exposure=1.0, full_well_e=1.0, defocus_sigma_px=2.0))
    y, x = np.mgrid[0:65, 0:65] - 32
    assert m.sum() == pytest.approx(1.0, abs=1e-6)
    assert (m * x**2).sum() == pytest.approx(4.0, rel=0.02)
    assert (m * y**2).sum() == pytest.approx(4.0, rel=0.02)


def test_same_seed_same_image(box):
    rho, D = _pose([1, 1, 0], 20, [0.0, 8.0, 0.0])
    v = rr.render_view(box, RIG, rho, D, rr.DEFAULT_SUN_L, "right")
    s = ss.SensorModel()
    a = ss.expose(v.radiance, s, np.random.default_rng(5))
    b = ss.expose(v.radiance, s, np.random.default_rng(5))
    c = ss.expose(v.radiance, s, np.random.default_rng(6))
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    again = sc.scene(shapes.box([2.0, 1.5, 3.0]), 3)
    assert np.array_equal(rr.render_view(again, RIG, rho, D, rr.DEFAULT_SUN_L, "right").radiance, v.radiance)
    assert v.radiance[v.truth.hit].std() > 0.05  # textured, not flat
