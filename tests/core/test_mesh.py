"""Mass properties of triangle meshes (thesis ch. 7.4) against analytic solids.

References: closed-form boxes and regular-polygon prisms (exact), a cylinder and a
sphere approached at the O(1/n^2) rate of their polygonal approximations, hollow tanks
(outer surface minus reversed inner surface), an independent volume integration
(Delaunay tetrahedra with a degree-2 exact quadrature rule) for random convex solids,
the transformation law of the inertia tensor, and the mesh checks and repairs.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import ConvexHull, Delaunay
from scipy.spatial.transform import Rotation

from stereopose_mc.core import mesh as M

# --------------------------------------------------------------------------- references


def box_inertia(m, a, b, c):
    """Central principal moments of a solid box a x b x c (x, y, z)."""
    return np.array([b * b + c * c, a * a + c * c, a * a + b * b]) * m / 12.0


def ngon_prism_reference(R, h, n, rho=1.0):
    """Exact volume and central moments (I_xx = I_yy, I_zz) of a right prism on a regular n-gon.

    Area A = n R^2 sin(2 pi/n) / 2; polar second moment of area J = n R^4 sin(2 pi/n) (2 + cos(2 pi/n)) / 12
    (-> pi R^4 / 2 as n -> inf); in-plane moments J/2 each (n >= 3). Then
    I_zz = rho h J and I_xx = rho (h J / 2 + A h^3 / 12).
    """
    t = 2 * np.pi / n
    A = 0.5 * n * R * R * np.sin(t)
    J = n * R**4 * np.sin(t) * (2 + np.cos(t)) / 12.0
    return A * h, rho * (h * J / 2 + A * h**3 / 12), rho * h * J


def keast_moments(points):
    """Volume, int x dV, int x x^T dV of the convex hull of ``points`` by Delaunay tetrahedra and
    the 4-point quadrature rule exact for degree 2 (barycentric 0.5854..., 0.1381..., weights V/4)."""
    tets = points[Delaunay(points).simplices]  # (k, 4, 3)
    e1, e2, e3 = (tets[:, i] - tets[:, 0] for i in (1, 2, 3))
    vol = np.abs(np.einsum("ki,ki->k", e1, np.cross(e2, e3))) / 6
    a, b = 0.5854101966249685, 0.1381966011250105
    W = np.full((4, 4), b) + np.eye(4) * (a - b)  # quadrature points in barycentric coordinates
    q = np.einsum("pv,kvi->kpi", W, tets)
    V = vol.sum()
    first = np.einsum("k,kpi->i", vol / 4, q)
    second = np.einsum("k,kpi,kpj->ij", vol / 4, q, q)
    return V, first, second


def hull_mesh(points, orient=True):
    """Closed triangle mesh of a convex hull; outward if ``orient`` (using the hull's facet normals)."""
    hull = ConvexHull(points)
    faces = hull.simplices.copy()
    if orient:
        tri = points[faces]
        nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        inward = np.einsum("ij,ij->i", nrm, hull.equations[:, :3]) < 0
        faces[inward] = faces[inward][:, [0, 2, 1]]
    return points, faces


RNG_POINTS = np.random.default_rng(11).normal(size=(40, 3)) * [1.0, 0.6, 0.3] + [0.2, -0.1, 0.05]


# --------------------------------------------------------------------------- analytic solids


@settings(max_examples=40, deadline=None)
@given(
    st.floats(0.01, 100.0),
    st.floats(0.01, 100.0),
    st.floats(0.01, 100.0),
    st.floats(1.0, 20000.0),
    st.tuples(*[st.floats(-1e3, 1e3)] * 3),
)
def test_box_of_any_size(a, b, c, rho, center):
    V, F = M.box_mesh(a, b, c, center)
    assert M.check_mesh(V, F).problems == []
    p = M.mass_properties(V, F, rho)
    m = rho * a * b * c
    # the vertex coordinates themselves carry a relative error ~ eps (|center| + size) / min(a, b, c)
    scale = max(a, b, c, *map(abs, center))
    rel = 1e-12 + 1e-14 * scale / min(a, b, c)
    assert p.volume == pytest.approx(a * b * c, rel=rel)
    assert p.mass == pytest.approx(m, rel=rel)
    np.testing.assert_allclose(p.centroid, center, atol=1e-12 * scale)
    Iref = box_inertia(m, a, b, c)
    np.testing.assert_allclose(p.inertia, np.diag(Iref), rtol=1e3 * rel, atol=1e-12 * Iref.max())
    np.testing.assert_allclose(p.principal_moments, np.sort(Iref), rtol=1e3 * rel, atol=1e-12 * Iref.max())


def test_unit_cube_by_hand():
    # unit cube, rho = 1: V = 1, I = (1 + 1)/12 = 1/6 about every central axis, k1 = k2 = 0
    V, F = M.box_mesh(1.0, 1.0, 1.0, center=(0.5, 0.5, 0.5))
    p = M.mass_properties(V, F, 1.0)
    assert p.volume == pytest.approx(1.0, rel=1e-15)
    np.testing.assert_allclose(p.centroid, [0.5, 0.5, 0.5], atol=1e-15)
    np.testing.assert_allclose(p.inertia, np.eye(3) / 6, atol=1e-15)
    assert p.k1 == pytest.approx(0.0, abs=1e-14) and p.k2 == pytest.approx(0.0, abs=1e-14)
    assert M.equal_moment_pairs(p.principal_moments) == [(0, 1), (1, 2)]


def test_box_k_ratios_by_hand():
    # 1 x 2 x 3, rho = 1, m = 6: I = 6/12 [4 + 9, 1 + 9, 1 + 4] = [6.5, 5, 2.5] -> ascending [2.5, 5, 6.5];
    # k1 = ln(2.5/5) = ln(1/2), k2 = ln(5/6.5) = ln(10/13)
    V, F = M.box_mesh(1.0, 2.0, 3.0)
    p = M.mass_properties(V, F, 1.0)
    np.testing.assert_allclose(p.principal_moments, [2.5, 5.0, 6.5], rtol=1e-14)
    assert p.k1 == pytest.approx(np.log(0.5), rel=1e-13)
    assert p.k2 == pytest.approx(np.log(10 / 13), rel=1e-13)
    # principal axes: z, y, then x (up to sign), right-handed
    np.testing.assert_allclose(np.abs(p.principal_axes), [[0, 0, 1], [0, 1, 0], [1, 0, 0]], atol=1e-14)
    assert np.linalg.det(p.principal_axes) == pytest.approx(1.0, rel=1e-14)


@pytest.mark.parametrize("n", [3, 4, 7, 32])
def test_regular_prism_is_exact(n):
    R, h, rho = 0.7, 1.9, 2700.0
    V, F = M.prism_mesh(R, h, n)
    assert M.check_mesh(V, F).problems == []
    p = M.mass_properties(V, F, rho)
    vol, Ixx, Izz = ngon_prism_reference(R, h, n, rho)
    assert p.volume == pytest.approx(vol, rel=1e-13)
    np.testing.assert_allclose(np.diag(p.inertia), [Ixx, Ixx, Izz], rtol=1e-12)
    np.testing.assert_allclose(p.inertia - np.diag(np.diag(p.inertia)), 0.0, atol=1e-13 * Ixx)


def test_cylinder_converges_at_second_order():
    """n-gon prisms -> m (3 r^2 + h^2)/12 and m r^2/2 with error ~ 1/n^2 (ratio 4 per doubling)."""
    r, h, rho = 0.5, 2.0, 1000.0
    m = rho * np.pi * r * r * h
    ref = np.array([m * r * r / 2, m * (3 * r * r + h * h) / 12])
    errs = []
    for n in (16, 32, 64, 128):
        V, F = M.prism_mesh(r, h, n)
        pm = M.mass_properties(V, F, rho).principal_moments
        errs.append(np.abs(np.array([pm[0], pm[2]]) - ref) / ref)
    errs = np.array(errs)
    ratios = errs[:-1] / errs[1:]
    assert np.all(ratios > 3.8) and np.all(ratios < 4.2), ratios
    assert np.all(errs[-1] < 1e-3)


def test_icosphere_converges_to_two_fifths_m_r2():
    r, rho = 1.3, 500.0
    errs = []
    for s in (1, 2, 3, 4):
        V, F = M.icosphere_mesh(r, s)
        p = M.mass_properties(V, F, rho)
        I_ref = 0.4 * (rho * 4 / 3 * np.pi * r**3) * r * r
        errs.append(np.max(np.abs(p.principal_moments - I_ref)) / I_ref)
        # a (nearly) uniform sphere: isotropic tensor, centroid at the centre
        assert np.ptp(p.principal_moments) < 1e-2 * I_ref
        np.testing.assert_allclose(p.centroid, 0.0, atol=1e-12)
    ratios = np.array(errs[:-1]) / np.array(errs[1:])
    assert np.all(ratios > 3.5) and np.all(ratios < 4.5), ratios
    assert errs[-1] < 4e-3


def test_hollow_cylindrical_tank_is_exact():
    """Tank = outer closed prism minus an inner reversed prism (walls 5 mm, caps 8 mm)."""
    Ro, Ho, t_wall, t_cap, n, rho = 0.25, 0.9, 0.005, 0.008, 48, 2800.0
    Ri, Hi = Ro - t_wall, Ho - 2 * t_cap
    # the inner polygon is the outer one scaled (same angles), so the walls have constant thickness
    outer = M.prism_mesh(Ro, Ho, n)
    inner_v, inner_f = M.prism_mesh(Ri, Hi, n)
    V, F = M.combine(outer, (inner_v, M.flip_faces(inner_f)))
    chk = M.check_mesh(V, F)
    assert chk.problems == []
    assert sorted(s.depth for s in chk.shells) == [0, 1]
    p = M.mass_properties(V, F, rho)
    vo, Ixo, Izo = ngon_prism_reference(Ro, Ho, n, rho)
    vi, Ixi, Izi = ngon_prism_reference(Ri, Hi, n, rho)
    assert p.volume == pytest.approx(vo - vi, rel=1e-11)
    np.testing.assert_allclose(np.diag(p.inertia), [Ixo - Ixi, Ixo - Ixi, Izo - Izi], rtol=1e-10)


def test_thick_spherical_shell_converges():
    """I = 2/5 M (R^5 - r^5)/(R^3 - r^3) for a shell R = 1, r = 0.8."""
    R, r, rho = 1.0, 0.8, 1000.0
    M_ref = rho * 4 / 3 * np.pi * (R**3 - r**3)
    I_ref = 0.4 * M_ref * (R**5 - r**5) / (R**3 - r**3)
    errs = []
    for s in (2, 3, 4):
        V, F = M.combine(M.icosphere_mesh(R, s), (lambda v, f: (v, M.flip_faces(f)))(*M.icosphere_mesh(r, s)))
        assert M.check_mesh(V, F).problems == []
        p = M.mass_properties(V, F, rho)
        errs.append(np.max(np.abs(p.principal_moments - I_ref)) / I_ref)
    assert errs[0] / errs[1] > 3.5 and errs[1] / errs[2] > 3.5
    assert errs[-1] < 5e-3


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 10_000))
def test_random_convex_solid_matches_independent_volume_quadrature(seed):
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(int(rng.integers(6, 40)), 3)) * rng.uniform(0.2, 3.0, size=3) + rng.normal(size=3) * 5
    V, F = hull_mesh(pts)
    vol, first, second = keast_moments(pts)
    c_ref = first / vol
    C = second - vol * np.outer(c_ref, c_ref)
    J_ref = 3.0 * (np.trace(C) * np.eye(3) - C)
    p = M.mass_properties(V, F, 3.0)
    assert p.volume == pytest.approx(vol, rel=1e-10)
    assert p.volume == pytest.approx(ConvexHull(pts).volume, rel=1e-10)
    np.testing.assert_allclose(p.centroid, c_ref, atol=1e-10 * np.abs(pts).max())
    np.testing.assert_allclose(p.inertia, J_ref, atol=1e-9 * np.abs(J_ref).max())
    # principal axes diagonalize J, are orthonormal and right-handed
    A = p.principal_axes
    np.testing.assert_allclose(A.T @ p.inertia @ A, np.diag(p.principal_moments), atol=1e-10 * p.principal_moments[-1])
    np.testing.assert_allclose(A.T @ A, np.eye(3), atol=1e-12)
    assert np.linalg.det(A) == pytest.approx(1.0, abs=1e-12)


# --------------------------------------------------------------------------- invariance


@st.composite
def rigid_motions(draw):
    q = np.array([draw(st.floats(-1, 1)) for _ in range(4)])
    if np.linalg.norm(q) < 0.1:
        q = np.array([1.0, 0.0, 0.0, 0.0])
    t = np.array([draw(st.floats(-1e4, 1e4)) for _ in range(3)])
    return Rotation.from_quat(q / np.linalg.norm(q)).as_matrix(), t


@settings(max_examples=40, deadline=None)
@given(rigid_motions())
def test_rotation_and_translation(motion):
    R, t = motion
    V, F = hull_mesh(RNG_POINTS)
    p0 = M.mass_properties(V, F, 7.0)
    p1 = M.mass_properties(V @ R.T + t, F, 7.0)
    scale = p0.principal_moments[-1]
    assert p1.volume == pytest.approx(p0.volume, rel=1e-10)
    np.testing.assert_allclose(p1.centroid, R @ p0.centroid + t, atol=1e-10 * (1 + np.abs(t).max()))
    np.testing.assert_allclose(p1.inertia, R @ p0.inertia @ R.T, atol=1e-9 * scale)
    np.testing.assert_allclose(p1.principal_moments, p0.principal_moments, rtol=1e-9)
    assert p1.k1 == pytest.approx(p0.k1, abs=1e-9) and p1.k2 == pytest.approx(p0.k2, abs=1e-9)
    # distinct moments: each principal axis rotates with the body (up to sign)
    dots = np.abs(np.einsum("ij,ij->j", p1.principal_axes, R @ p0.principal_axes))
    np.testing.assert_allclose(dots, 1.0, atol=1e-8)


def test_far_from_origin_loses_no_accuracy():
    V, F = M.box_mesh(1.0, 2.0, 3.0)
    p = M.mass_properties(V + [3e6, -2e6, 1e6], F, 1.0)
    np.testing.assert_allclose(p.inertia, np.diag([6.5, 5.0, 2.5]), rtol=1e-9, atol=1e-9)


def test_batched_triangle_moments_equal_loop():
    tri = np.stack([M.triangles(*M.box_mesh(1, 2, 3)), M.triangles(*M.box_mesh(2, 2, 1, (1, 0, 0)))])
    vol, first, second = M.triangle_moments(tri)
    assert vol.shape == (2,) and first.shape == (2, 3) and second.shape == (2, 3, 3)
    for i in range(2):
        v, f, s = M.triangle_moments(tri[i])
        assert vol[i] == v
        np.testing.assert_array_equal(first[i], f)
        np.testing.assert_array_equal(second[i], s)
    np.testing.assert_allclose(vol, [6.0, 4.0], rtol=1e-14)
    np.testing.assert_allclose(first[1], [4.0, 0.0, 0.0], atol=1e-14)  # V * centroid


# --------------------------------------------------------------------------- checks and repairs


def test_inward_facing_is_detected_by_the_volume_sign_and_repaired():
    V, F = M.icosphere_mesh(1.0, 2)
    Fi = M.flip_faces(F)
    assert M.signed_volume(V, Fi) == pytest.approx(-M.signed_volume(V, F), rel=1e-14) and M.signed_volume(V, Fi) < 0
    chk = M.check_mesh(V, Fi)
    assert len(chk.problems) == 1 and "inward-facing" in chk.problems[0]
    with pytest.raises(ValueError):
        M.mass_properties(V, Fi)
    V2, F2, changes = M.repair_mesh(V, Fi)
    assert len(changes) == 1 and "flipped all 320 triangles" in changes[0]
    np.testing.assert_array_equal(F2, F)


def test_open_mesh_is_an_error_that_repair_cannot_fix():
    V, F = M.box_mesh(1.0, 2.0, 3.0)
    Fo = F[1:]
    chk = M.check_mesh(V, Fo)
    assert chk.boundary_edges == 3
    assert any("not closed" in p for p in chk.problems)
    V2, F2, changes = M.repair_mesh(V, Fo)
    assert changes == []
    assert M.check_mesh(V2, F2).boundary_edges == 3


def test_inconsistent_orientation_error_and_repair():
    V, F = M.icosphere_mesh(1.0, 2)
    rng = np.random.default_rng(5)
    which = np.zeros(len(F), dtype=bool)
    which[rng.choice(len(F), 40, replace=False)] = True
    Fb = M.flip_faces(F, which)
    chk = M.check_mesh(V, Fb)
    assert chk.conflicting_edges > 0
    assert any("not consistently oriented" in p for p in chk.problems)
    V2, F2, changes = M.repair_mesh(V, Fb)
    assert changes == ["flipped 40 triangle(s) to orient each shell consistently"]
    np.testing.assert_array_equal(F2, F)
    # majority inward: flipped to agree, then the whole shell is turned outward
    V3, F3, changes = M.repair_mesh(V, M.flip_faces(Fb))
    assert len(changes) == 2 and "inward-facing" in changes[1]
    assert M.check_mesh(V3, F3).problems == []
    assert M.signed_volume(V3, F3) == pytest.approx(M.signed_volume(V, F), rel=1e-14)


def test_unoriented_convex_hull_is_repaired():
    V, F = hull_mesh(RNG_POINTS, orient=False)
    ref = M.mass_properties(*hull_mesh(RNG_POINTS))
    V2, F2, _ = M.repair_mesh(V, F)
    assert M.check_mesh(V2, F2).problems == []
    p = M.mass_properties(V2, F2)
    assert p.volume == pytest.approx(ref.volume, rel=1e-12)
    np.testing.assert_allclose(p.inertia, ref.inertia, rtol=1e-10, atol=1e-12)


def test_triangle_soup_needs_vertex_merging():
    V, F = M.box_mesh(1.0, 2.0, 3.0)
    soup = V[F].reshape(-1, 3) + np.random.default_rng(0).normal(scale=1e-13, size=(36, 3))
    Fs = np.arange(36).reshape(12, 3)
    chk = M.check_mesh(soup, Fs)
    assert chk.boundary_edges == 36
    V2, F2, changes = M.repair_mesh(soup, Fs)
    assert changes[0].startswith("merged 28 duplicate vertices")
    assert M.check_mesh(V2, F2).problems == []
    assert M.mass_properties(V2, F2).volume == pytest.approx(6.0, rel=1e-12)


def test_degenerate_and_duplicate_faces():
    V, F = M.box_mesh(1.0, 2.0, 3.0)
    Fd = np.vstack([F, [[0, 1, 1]], F[3:4], F[5:6, [0, 2, 1]]])  # repeated vertex, same copy, reversed copy
    chk = M.check_mesh(V, Fd)
    assert chk.degenerate_faces == 1 and chk.duplicate_faces == 2
    V2, F2, changes = M.repair_mesh(V, Fd)
    assert "dropped 1 degenerate" in changes[0]
    assert "dropped 3 duplicate" in changes[1] and "zero-thickness" in changes[1]
    # dropping both copies of face 5 leaves a hole: reported, not hidden
    chk2 = M.check_mesh(V2, F2)
    assert chk2.boundary_edges == 3
    # collinear corners (zero area) are degenerate too
    Vc = np.vstack([V, [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]]])
    assert M.degenerate_faces(Vc, np.array([[8, 9, 10]])).tolist() == [0]


def test_nested_shell_facing_the_wrong_way():
    outer = M.box_mesh(2.0, 2.0, 2.0)
    inner = M.box_mesh(1.0, 1.0, 1.0)
    V, F = M.combine(outer, inner)  # cavity faces outward: it would add volume
    assert M.signed_volume(V, F) == pytest.approx(9.0)
    chk = M.check_mesh(V, F)
    assert len(chk.problems) == 1 and "inside 1 other shell" in chk.problems[0]
    V2, F2, changes = M.repair_mesh(V, F)
    assert len(changes) == 1 and "cavity" in changes[0]
    assert M.mass_properties(V2, F2).volume == pytest.approx(7.0, rel=1e-14)
    # two separate solids side by side: both outward, no problem
    V3, F3 = M.combine(outer, M.box_mesh(1.0, 1.0, 1.0, center=(5.0, 0.0, 0.0)))
    assert M.check_mesh(V3, F3).problems == []
    assert M.mass_properties(V3, F3).volume == pytest.approx(9.0, rel=1e-14)


def test_non_manifold_edge():
    V, F = M.box_mesh(1.0, 1.0, 1.0)
    V2, F2 = M.combine((V, F), M.box_mesh(1.0, 1.0, 1.0, center=(1.0, 1.0, 0.0)))
    # weld the shared edge x = y = 0.5 of the two cubes
    V2, F2, _ = M.merge_vertices(V2, F2, 1e-12)
    chk = M.check_mesh(V2, F2)
    assert chk.nonmanifold_edges == 1
    assert any("not manifold" in p for p in chk.problems)


def test_winding_number():
    V, F = M.icosphere_mesh(1.0, 2)
    tri = M.triangles(V, F)
    assert M.winding_number(np.array([0.1, -0.2, 0.3]), tri) == pytest.approx(1.0, abs=1e-12)
    assert M.winding_number(np.array([2.0, 0.0, 0.0]), tri) == pytest.approx(0.0, abs=1e-12)
    assert M.winding_number(np.zeros(3), M.triangles(V, M.flip_faces(F))) == pytest.approx(-1.0, abs=1e-12)


def test_flat_closed_surface_has_no_volume():
    # a flat "pillow": a square triangulated along one diagonal on top and the other below,
    # closed, manifold and consistently oriented, yet enclosing nothing
    V = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    F = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]])
    chk = M.check_mesh(V, F)
    assert chk.boundary_edges == chk.nonmanifold_edges == chk.conflicting_edges == chk.duplicate_faces == 0
    assert len(chk.problems) == 1 and "encloses no volume" in chk.problems[0]
    # two coincident triangles facing opposite ways are reported as duplicates (a zero-thickness wall)
    chk = M.check_mesh(V[:3], np.array([[0, 1, 2], [0, 2, 1]]))
    assert chk.duplicate_faces == 1


def test_bad_arrays_raise():
    with pytest.raises(ValueError):
        M.check_mesh(np.zeros((3, 2)), np.array([[0, 1, 2]]))
    with pytest.raises(ValueError):
        M.check_mesh(np.zeros((3, 3)), np.array([[0, 1, 3]]))
    with pytest.raises(ValueError):
        M.mass_properties(*M.box_mesh(1, 1, 1), density=-1.0)
