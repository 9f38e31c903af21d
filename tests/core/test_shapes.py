"""Target bodies (core/shapes.py): ray tests on hand-built cases, sampling, normals."""

from __future__ import annotations

import numpy as np
import pytest

from stereopose_mc.core import shapes
from stereopose_mc.config.meshfiles import read_mesh
from scenarios import CONFIGS

BOX = shapes.box([2.0, 4.0, 6.0])  # half-sizes 1, 2, 3


def test_ray_box_by_hand():
    # along x through the centre: inside for x in [-1, 1], from p = [-5, 0, 0] with d = [10, 0, 0]: t in [0.4, 0.6]
    tn, tf = shapes.ray_box(np.array([-5.0, 0, 0]), np.array([10.0, 0, 0]), BOX.size)
    assert (tn, tf) == pytest.approx((0.4, 0.6))
    # a line parallel to x at y = 2.5 (outside the |y| <= 2 slab): a miss
    tn, tf = shapes.ray_box(np.array([-5.0, 2.5, 0]), np.array([10.0, 0, 0]), BOX.size)
    assert tn > tf
    # diagonal through the corner region: from [-2, -3, 0] along [1, 1, 0]: x >= -1 at t = 1, y <= 2 until t = 5,
    # x <= 1 until t = 3, y >= -2 from t = 1 -> [1, 3]
    tn, tf = shapes.ray_box(np.array([-2.0, -3.0, 0]), np.array([1.0, 1.0, 0]), BOX.size)
    assert (tn, tf) == pytest.approx((1.0, 3.0))


def test_ray_ellipsoid_by_hand():
    axes = np.array([1.0, 2.0, 3.0])
    # along z through the centre: |z| <= 3; from [0, 0, -6] with d = [0, 0, 12]: t in [0.25, 0.75]
    tn, tf = shapes.ray_ellipsoid(np.array([0, 0, -6.0]), np.array([0, 0, 12.0]), axes)
    assert (tn, tf) == pytest.approx((0.25, 0.75))
    # along y at x = 0.6: (y/2)^2 <= 1 - 0.36 -> |y| <= 1.6; from y = -4 with d = [0, 8, 0]: t in [0.3, 0.7]
    tn, tf = shapes.ray_ellipsoid(np.array([0.6, -4.0, 0]), np.array([0, 8.0, 0]), axes)
    assert (tn, tf) == pytest.approx((0.3, 0.7))
    tn, tf = shapes.ray_ellipsoid(np.array([1.01, -4.0, 0]), np.array([0, 8.0, 0]), axes)
    assert not tn < tf


def box_mesh():
    m = read_mesh(CONFIGS / "meshes" / "box.obj")
    return shapes.mesh(m.vertices, m.faces)


@pytest.mark.parametrize("shape", ["box", "ellipsoid", "mesh"])
def test_occlusion_by_hand(shape):
    s = {"box": shapes.box([2.0, 2.0, 2.0]), "ellipsoid": shapes.ellipsoid([1.0, 1.0, 1.0]), "mesh": None}[shape]
    if s is None:  # the bundled 1 x 2 x 3 m box mesh, scaled to the cube [-1, 1]^3
        m = read_mesh(CONFIGS / "meshes" / "box.obj")
        s = shapes.mesh(m.vertices / [0.5, 1.0, 1.5], m.faces)
    cam = np.array([0.0, 10.0, 0.0])
    # the near pole/face centre is seen, the far one is hidden behind the body
    near, far = np.array([0.0, 1.0, 0.0]), np.array([0.0, -1.0, 0.0])
    n = shapes.normals(s, np.stack([near, far]))
    np.testing.assert_allclose(n, [[0, 1, 0], [0, -1, 0]], atol=1e-12)
    assert shapes.sees(s, near, n[0], cam) and not shapes.sees(s, far, n[1], cam)
    assert shapes.segment_blocked(s, far, cam) and not shapes.segment_blocked(s, near, cam)
    # a point outside the body, beside it, is not blocked; one right behind it is
    assert not shapes.segment_blocked(s, np.array([3.0, -5.0, 0.0]), cam)
    assert shapes.segment_blocked(s, np.array([0.0, -5.0, 0.0]), cam)
    # batched: the same answers in one call
    pts = np.array([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0], [3.0, -5.0, 0.0], [0.0, -5.0, 0.0]])
    np.testing.assert_array_equal(shapes.segment_blocked(s, pts, cam), [False, True, False, True])


def test_box_side_face_seen_at_grazing_angles():
    s = shapes.box([2.0, 2.0, 2.0])
    p, n = np.array([1.0, 0.2, 0.3]), np.array([1.0, 0.0, 0.0])  # on the +x face
    assert shapes.sees(s, p, n, np.array([5.0, 10.0, 0.0]))  # camera on the +x side
    assert not shapes.sees(s, p, n, np.array([-5.0, 10.0, 0.0]))  # camera on the -x side: back face


def test_ray_triangles_by_hand():
    """Moller-Trumbore on two triangles, by hand: the unit right triangle in z = 0 and the same lifted to z = 1."""
    tri = np.array([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
                    [[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0]]])  # fmt: skip
    p = np.array([[[0.2, 0.2, 2.0], [0.9, 0.9, 2.0]], [[0.2, 0.2, 0.5], [0.2, 0.2, 2.0]]])  # (2, 2, 3) rays
    d = np.array([[[0.0, 0.0, -2.0], [0.0, 0.0, -2.0]], [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]])
    t = shapes.ray_triangles(p, d, tri)
    assert t.shape == (2, 2, 2)
    np.testing.assert_allclose(t[0, 0], [1.0, 0.5], rtol=0, atol=1e-15)  # down through both planes
    assert np.isnan(t[0, 1]).all()  # x + y = 1.8 > 1: outside both
    np.testing.assert_allclose(t[1, 0], [-0.5, 0.5], rtol=0, atol=1e-15)  # up from z = 0.5: behind (t < 0) and ahead
    assert np.isnan(t[1, 1]).all()  # parallel to both planes


def _two_boxes():
    """A mesh that is not convex: the bundled box mesh twice, side by side along x (each hides part of the other)."""
    m = read_mesh(CONFIGS / "meshes" / "box.obj")
    v = np.concatenate([m.vertices - [1.5, 0.0, 0.0], m.vertices + [1.5, 0.0, 0.0]])
    return shapes.mesh(v, np.concatenate([m.faces, m.faces + len(m.vertices)]))


@pytest.mark.parametrize("kind", ["box", "ellipsoid", "mesh", "two boxes"])
def test_sees_tests_only_the_facing_points_in_where_and_gives_the_definition(kind):
    """``sees(where=w)`` is ``w & facing & ~segment_blocked`` entry by entry (the definition, evaluated here on every
    segment), on surface points seen from cameras all around the body, batched as ``(steps, N)``."""
    s = {"box": shapes.box([2.0, 1.0, 0.5]), "ellipsoid": shapes.ellipsoid([2.0, 1.0, 0.5]), "mesh": box_mesh(),
         "two boxes": _two_boxes()}[kind]  # fmt: skip
    rng = np.random.default_rng(7)
    p, n = shapes.sample_surface(s, 24, rng)
    cams = rng.normal(size=(40, 1, 3)) * 6.0  # (steps, 1, 3): one camera per step, broadcast over the points
    where = rng.random((40, 24)) < 0.7
    facing = np.sum(n * (cams - p), axis=-1) > 0.0
    blocked = shapes.segment_blocked(s, np.broadcast_to(p, (40, 24, 3)), np.broadcast_to(cams, (40, 24, 3)))
    assert (facing & ~blocked).any() and (~facing & blocked).any()  # seen points, and back faces the body hides
    if kind == "two boxes":  # a face turned to the camera with the other box in between
        assert (facing & blocked).any()
    np.testing.assert_array_equal(shapes.sees(s, p, n, cams, where=where), where & facing & ~blocked)
    np.testing.assert_array_equal(shapes.sees(s, p, n, cams), facing & ~blocked)
    one = shapes.sees(s, p[0], n[0], cams[0, 0])  # one point: a 0-d answer, the same
    assert one.shape == () and bool(one) == bool(facing[0, 0] & ~blocked[0, 0])


@pytest.mark.parametrize("kind", ["box", "ellipsoid", "mesh"])
def test_samples_lie_on_the_surface_with_outward_normals(kind):
    s = {"box": shapes.box([2.0, 1.0, 0.5]), "ellipsoid": shapes.ellipsoid([2.0, 1.0, 0.5])}.get(kind) or box_mesh()
    p, n = shapes.sample_surface(s, 400, np.random.default_rng(3))
    if kind == "box":
        assert np.allclose(np.max(np.abs(p) / s.size, axis=-1), 1.0)
    elif kind == "ellipsoid":
        np.testing.assert_allclose(np.sum((p / s.size) ** 2, -1), 1.0, rtol=1e-12)
    # outward: a step along the normal leaves the body, a step against it enters
    far = p + 1e-3 * n
    assert not shapes.segment_blocked(s, far, far + 50 * n).any()
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0)
    # deterministic from the generator
    p2, _ = shapes.sample_surface(s, 400, np.random.default_rng(3))
    np.testing.assert_array_equal(p, p2)


def test_box_samples_are_uniform_by_area():
    s = shapes.box([4.0, 2.0, 1.0])  # face areas 2 (x), 4 (y), 8 (z) in pairs: fractions 1/7, 2/7, 4/7
    p, n = shapes.sample_surface(s, 7000, np.random.default_rng(0))
    frac = np.abs(n).mean(axis=0)
    np.testing.assert_allclose(frac, [1 / 7, 2 / 7, 4 / 7], atol=4 * np.sqrt(0.25 / 7000))


def test_ellipsoid_samples_are_uniform_by_area():
    # a prolate spheroid a = 1, c = 3: the area fraction with |z| < 1.5 against a numerical quadrature
    s = shapes.ellipsoid([1.0, 1.0, 3.0])
    p, _ = shapes.sample_surface(s, 20000, np.random.default_rng(1))
    z = np.linspace(-3, 3, 20001)
    r = np.sqrt(np.clip(1 - (z / 3) ** 2, 0, None))
    dr = np.gradient(r, z)
    dA = 2 * np.pi * r * np.sqrt(1 + dr**2)
    inner = np.abs(z) < 1.5
    expected = np.trapezoid(dA * inner, z) / np.trapezoid(dA, z)
    assert abs(np.mean(np.abs(p[:, 2]) < 1.5) - expected) < 4 * np.sqrt(0.25 / 20000)
