"""Target bodies (box, ellipsoid, triangle mesh): surface sampling, normals, ray tests.

Pure numerics in the target frame ``T`` (m), batched over leading axes ``...``. A box
is given by its half-sizes ``h``, an ellipsoid by its semi-axes ``a`` (both centred at
the origin, along the axes), a mesh by its triangles ``(M, 3, 3)`` (closed, consistently
oriented; the outward side is the one the signed volume makes positive).

Ray tests answer "does the segment ``p + t (c - p)``, ``eps < t < 1``, pass through
the body?":

- box (slab method; Kay & Kajiya 1986): the line is inside the box for
  ``t_near < t < t_far`` with ``t_near = max_k min(t_k-, t_k+)``,
  ``t_far = min_k max(t_k-, t_k+)``, ``t_k+- = (+-h_k - p_k) / d_k``;
- ellipsoid: scaled to the unit sphere, ``|p' + t d'|^2 = 1`` (a quadratic) gives the
  same interval;
- mesh (Moller & Trumbore 1997): any triangle hit at ``eps < t < 1``.

A convex body blocks the segment when the interval ``(t_near, t_far)`` overlaps
``(eps, 1)``; so a point on its surface whose outward side faces away from ``c`` is
blocked by the body itself (its segment enters the body at once). ``eps`` (a fraction
of the segment) keeps a point on the surface from blocking itself.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
EPS = 1e-9


@dataclass(frozen=True)
class Shape:
    kind: str  # "box" | "ellipsoid" | "mesh"
    size: Array  # (3,) half-sizes (box) or semi-axes (ellipsoid); the bounding half-sizes of a mesh
    triangles: Array | None = None  # (M, 3, 3) mesh triangles, outward by the right-hand rule

    @property
    def extent(self) -> float:
        """A length larger than the body (for rays toward infinity)."""
        return float(10.0 * np.linalg.norm(self.size))


def box(size: Array) -> Shape:
    """A box of full edge lengths ``size`` (m)."""
    return Shape("box", 0.5 * np.asarray(size, dtype=float))


def ellipsoid(semi_axes: Array) -> Shape:
    return Shape("ellipsoid", np.asarray(semi_axes, dtype=float))


def mesh(vertices: Array, faces: Array) -> Shape:
    """A closed triangle mesh; the triangles are reoriented outward if its signed volume is negative."""
    tri = np.asarray(vertices, dtype=float)[np.asarray(faces)]
    vol = np.sum(np.einsum("mi,mi->m", tri[:, 0], np.cross(tri[:, 1], tri[:, 2]))) / 6.0
    if vol < 0:
        tri = tri[:, ::-1]
    return Shape("mesh", np.max(np.abs(tri.reshape(-1, 3)), axis=0), tri)


def _triangle_normals(tri: Array) -> Array:
    n = np.cross(tri[..., 1, :] - tri[..., 0, :], tri[..., 2, :] - tri[..., 0, :])
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def normals(shape: Shape, p: Array) -> Array:
    """Outward unit normals ``(..., 3)`` at points ``p (..., 3)`` on (or near) the surface.

    Box: the face with the largest ``|p_k| / h_k``; ellipsoid: ``p / a^2`` normalized;
    mesh: the normal of the triangle with the nearest centroid.
    """
    p = np.asarray(p, dtype=float)
    if shape.kind == "box":
        r = np.abs(p) / shape.size
        k = np.argmax(r, axis=-1)
        n = np.zeros_like(p)
        np.put_along_axis(n, k[..., None], np.sign(np.take_along_axis(p, k[..., None], -1)), axis=-1)
        return n
    if shape.kind == "ellipsoid":
        g = p / shape.size**2
        return g / np.linalg.norm(g, axis=-1, keepdims=True)
    c = shape.triangles.mean(axis=1)
    j = np.argmin(np.linalg.norm(p[..., None, :] - c, axis=-1), axis=-1)
    return _triangle_normals(shape.triangles)[j]


def sample_surface(shape: Shape, n: int, rng: np.random.Generator) -> tuple[Array, Array]:
    """``n`` points uniformly distributed over the surface and their outward normals, ``(n, 3)`` each."""
    if shape.kind == "box":
        h = shape.size
        area = np.array([h[1] * h[2], h[1] * h[2], h[0] * h[2], h[0] * h[2], h[0] * h[1], h[0] * h[1]])
        face = rng.choice(6, size=n, p=area / area.sum())
        uv = rng.uniform(-1.0, 1.0, size=(n, 3))
        axis, sign = face // 2, np.where(face % 2 == 0, 1.0, -1.0)
        p = uv * h
        p[np.arange(n), axis] = sign * h[axis]
        nrm = np.zeros((n, 3))
        nrm[np.arange(n), axis] = sign
        return p, nrm
    if shape.kind == "ellipsoid":
        a, b, c = shape.size
        mu_max = max(b * c, a * c, a * b)
        out = np.empty((0, 3))
        while out.shape[0] < n:  # rejection by the area element of x = diag(a) u, u on the unit sphere
            u = rng.standard_normal((2 * n, 3))
            u /= np.linalg.norm(u, axis=-1, keepdims=True)
            mu = np.sqrt((b * c * u[:, 0]) ** 2 + (a * c * u[:, 1]) ** 2 + (a * b * u[:, 2]) ** 2)
            keep = rng.random(2 * n) < mu / mu_max
            out = np.concatenate([out, u[keep] * shape.size])
        p = out[:n]
        return p, normals(shape, p)
    tri = shape.triangles
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=-1)
    j = rng.choice(tri.shape[0], size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    w = np.stack([1.0 - s, s * (1.0 - r2), s * r2], axis=-1)
    p = np.einsum("nk,nki->ni", w, tri[j])
    return p, _triangle_normals(tri[j])


def _interval_blocks(t_near: Array, t_far: Array, eps: float) -> Array:
    return (t_near < t_far) & (t_far > eps) & (t_near < 1.0 - eps)


def ray_box(p: Array, d: Array, half: Array) -> tuple[Array, Array]:
    """``(t_near, t_far)`` of the line ``p + t d`` inside the box ``|x_k| <= half_k`` (``t_near > t_far``: a miss)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1 = (-half - p) * inv
        t2 = (half - p) * inv
    lo = np.fmin(t1, t2)
    hi = np.fmax(t1, t2)
    # a direction parallel to a slab: inside it for all t, or never
    par = d == 0.0
    inside = np.abs(p) <= half
    lo = np.where(par, np.where(inside, -np.inf, np.inf), lo)
    hi = np.where(par, np.where(inside, np.inf, -np.inf), hi)
    return lo.max(axis=-1), hi.min(axis=-1)


def ray_ellipsoid(p: Array, d: Array, axes: Array) -> tuple[Array, Array]:
    """``(t_near, t_far)`` of the line ``p + t d`` inside the ellipsoid ``sum (x_k / a_k)^2 <= 1``."""
    ps, ds = p / axes, d / axes
    A = np.sum(ds * ds, -1)
    B = np.sum(ps * ds, -1)
    C = np.sum(ps * ps, -1) - 1.0
    disc = B * B - A * C
    ok = (disc >= 0) & (A > 0)
    r = np.sqrt(np.where(ok, disc, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = np.where(ok, (-B - r) / A, np.inf)
        t2 = np.where(ok, (-B + r) / A, -np.inf)
    return t1, t2


def _cross(a: tuple, b: tuple) -> tuple:
    """``a x b`` of vectors given by their components (arrays that broadcast): ``np.cross``'s products and
    differences, without its stacking and copies of the operands."""
    return a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]


def _dot(a: tuple, b: tuple) -> Array:
    """``a . b`` by components, summed in ``np.sum(..., -1)``'s order over 3 entries."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def ray_triangles(p: Array, d: Array, tri: Array) -> Array:
    """Ray parameters ``t (..., M)`` where ``p + t d`` meets each triangle (``nan``: a miss): Moller-Trumbore, by
    components (rays on the leading axes, triangles on the last)."""
    v0 = tuple(tri[:, 0, k] for k in range(3))
    e1 = tuple(tri[:, 1, k] - tri[:, 0, k] for k in range(3))
    e2 = tuple(tri[:, 2, k] - tri[:, 0, k] for k in range(3))
    dc = tuple(d[..., None, k] for k in range(3))
    pv = _cross(dc, e2)
    det = _dot(e1, pv)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        s = tuple(p[..., None, k] - v0[k] for k in range(3))
        u = _dot(s, pv) * inv
        qv = _cross(s, e1)
        v = _dot(dc, qv) * inv
        t = _dot(e2, qv) * inv
        hit = (np.abs(det) > 1e-300) & (u >= 0) & (v >= 0) & (u + v <= 1)
    return np.where(hit, t, np.nan)


def segment_blocked(shape: Shape, p: Array, c: Array, eps: float = EPS) -> Array:
    """``(...)`` bool: the body lies on the segment from ``p`` to ``c`` (both ``(..., 3)``, broadcast)."""
    p, c = np.broadcast_arrays(np.asarray(p, dtype=float), np.asarray(c, dtype=float))
    d = c - p
    if shape.kind == "box":
        return _interval_blocks(*ray_box(p, d, shape.size), eps)
    if shape.kind == "ellipsoid":
        return _interval_blocks(*ray_ellipsoid(p, d, shape.size), eps)
    shp = p.shape[:-1]
    pf, df = p.reshape(-1, 3), d.reshape(-1, 3)
    out = np.zeros(pf.shape[0], bool)
    chunk = max(1, 200_000 // shape.triangles.shape[0])  # segments x triangles per pass (memory)
    for i in range(0, pf.shape[0], chunk):
        t = ray_triangles(pf[i : i + chunk], df[i : i + chunk], shape.triangles)
        out[i : i + chunk] = np.any((t > eps) & (t < 1.0 - eps), axis=-1)
    return out.reshape(shp)


def sees(shape: Shape, p: Array, n: Array, c: Array, eps: float = EPS, where: Array | None = None) -> Array:
    """``(...)`` bool: point ``p`` with outward normal ``n`` faces ``c`` and nothing of the body is in between.

    ``where`` (``(...)`` bool, or None: everywhere): False gives False without a ray test, i.e. ``where & sees(...)``.
    Only the segments of points that face ``c`` (and are in ``where``) are tested against the body: the others'
    answer is False whatever the test says (a back face, or a point already hidden from another camera).
    """
    p, c, n = np.broadcast_arrays(np.asarray(p, dtype=float), np.asarray(c, dtype=float), np.asarray(n, dtype=float))
    out = np.asarray(np.sum(n * (c - p), axis=-1) > 0.0)  # (an array also for one point: written below)
    if where is not None:
        out &= where
    flat = out.reshape(-1)  # (a view: ``out`` is a new array)
    todo = np.flatnonzero(flat)
    if todo.size:
        flat[todo] = ~segment_blocked(shape, p.reshape(-1, 3)[todo], c.reshape(-1, 3)[todo], eps)
    return out
