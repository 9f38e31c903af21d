"""Ray-cast stereo images of the target (trimesh + Embree), with per-pixel ground truth.

Cameras (core/camera.py, config/sensor.py): the right camera at the origin of ``L``, the left
one at ``[b, 0, 0]``, both looking along ``+y``; a point ``[x, y, z]`` in a camera's frame
has normalized coordinates ``u = x / y``, ``v = z / y`` and lands at the continuous image
position ``col = c_x + f_px u``, ``row = c_y + f_px v``. Pixel ``[i, j]`` (row ``i``, column
``j``) covers ``j <= col < j + 1``, ``i <= row < i + 1``; its centre is ``(j + 0.5, i + 0.5)``.
(OpenCV puts pixel centres at integers: ``col = x_cv + 0.5``; the tracker converts.)

The pose is the truth's: ``rho`` (target centre in ``L``) and ``D`` (``v^L = D v^T``). Rays
are cast in ``T``: a camera at ``c`` in ``L`` sits at ``D^T (c - rho)``, a direction ``d``
becomes ``D^T d``. Embree intersects in single precision; each hit is then recomputed in
double precision on the hit triangle's plane, so a hit point projects back to its ray's pixel
position to ~1e-9 px.

Radiance (relative; a white Lambertian surface facing the Sun is 1):
``L = albedo (max(0, n . s) lit + ambient)``, with ``s`` the unit vector toward the Sun
(``measurements.illumination.sun_direction_lvlh``: toward the Sun, in ``L``, the sign the
illumination test uses) and ``lit`` false when a second ray from the hit point toward the Sun
meets the body (self-shadow). Background (no hit) is black, or the sunlit Earth (earth.py) when
an ``EarthView`` is given (then every pixel's rays are tested against it). With ``supersample = s`` each
pixel averages ``s x s`` rays on a regular sub-grid (anti-aliased edges); the ground truth is
the ray through the pixel centre.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ...config.sensor import PixelCamera
from ...core import quaternion as qt
from ...core import shapes
from ...core import state as st
from . import earth as ea, texture
from .scene import Scene

Array = NDArray[np.float64]

DEFAULT_SUN_L = np.array([-0.4, -1.0, -0.6]) / np.linalg.norm([-0.4, -1.0, -0.6])
"""Toward the Sun when a scenario has no illumination key: behind the cameras, beside and above."""
SHADOW_OFFSET = 1e-6  # shadow-ray origin above the surface, in units of the body's size


@dataclass(frozen=True)
class Rig:
    """The stereo rig: one pixel camera model for both cameras, the left one at ``[baseline, 0, 0]``."""

    camera: PixelCamera
    baseline: float

    def centre(self, cam: str) -> Array:
        return np.array([self.baseline if cam == "left" else 0.0, 0.0, 0.0])


@dataclass(frozen=True)
class RenderSettings:
    supersample: int = 1  # rays per pixel along each axis
    ambient: float = 0.0  # diffuse light from everywhere (Earth, the chaser), a fraction of the Sun's
    shadows: bool = True


@dataclass(frozen=True)
class Hits:
    """Ray-cast ground truth, shaped like the query: body point in ``T`` (nan: background), triangle
    (-1: background), surface (-1), depth (the point's ``y`` in ``L``, the distance along the optical
    axis; nan), the outward shading normal in ``T`` (nan) and whether the ray hit the target."""

    point: Array
    triangle: NDArray[np.int64]
    surface: NDArray[np.int64]
    depth: Array
    normal: Array
    hit: NDArray[np.bool_]


@dataclass(frozen=True)
class View:
    """One camera's rendering: radiance ``(H, W)`` and the pixel-centre ground truth."""

    radiance: Array
    truth: Hits


def pose_of(x: Array) -> tuple[Array, Array]:
    """``(rho, D)`` of a state ``x (n,)``: the target's centre in ``L`` and ``v^L = D v^T``."""
    return np.asarray(x[st.RHO], dtype=float), qt.dcm(qt.normalize(x[st.QUAT]))


def pixel_grid(camera: PixelCamera, supersample: int = 1) -> tuple[Array, Array]:
    """Continuous image positions ``(col, row)`` of the sample rays, ``(H, W, s*s)`` each."""
    s = supersample
    sub = (np.arange(s) + 0.5) / s
    col = np.arange(camera.width)[None, :, None, None] + sub[None, None, None, :]
    row = np.arange(camera.height)[:, None, None, None] + sub[None, None, :, None]
    col, row = np.broadcast_arrays(col, row)
    shp = (camera.height, camera.width, s * s)
    return col.reshape(shp).astype(float), row.reshape(shp).astype(float)


def directions_L(camera: PixelCamera, col: Array, row: Array) -> Array:
    """Unit ray directions in ``L`` ``(..., 3)`` through image positions ``(col, row)``."""
    u, v = camera.normalized(col, row)
    d = np.stack([u, np.ones_like(u), v], axis=-1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def project_px(camera: PixelCamera, rig_baseline: float, p_L: Array, cam: str) -> Array:
    """Image positions ``(..., 2) = (col, row)`` of points ``p_L (..., 3)`` in one camera (the point model's
    projection)."""
    x = p_L[..., 0] - (rig_baseline if cam == "left" else 0.0)
    u, v = x / p_L[..., 1], p_L[..., 2] / p_L[..., 1]
    return np.stack(camera.pixels(u, v), axis=-1)


def cast(scene: Scene, rig: Rig, rho: Array, D: Array, cam: str, col: Array, row: Array) -> Hits:
    """First hits of the rays of camera ``cam`` ("right" | "left") through the image positions ``(col, row)``."""
    col, row = np.broadcast_arrays(np.asarray(col, dtype=float), np.asarray(row, dtype=float))
    shp = col.shape
    d_L = directions_L(rig.camera, col.ravel(), row.ravel())
    o_T = D.T @ (rig.centre(cam) - rho)
    d_T = d_L @ D  # rows: D^T d
    n = d_T.shape[0]
    tri, ray = scene.mesh.ray.intersects_id(np.broadcast_to(o_T, d_T.shape), d_T, multiple_hits=False)
    point = np.full((n, 3), np.nan)
    tri_of = np.full(n, -1, dtype=np.int64)
    tri_of[ray] = tri
    # the hit again in double precision on the triangle's plane: t = n . (v0 - o) / (n . d)
    nrm = scene.normals[tri]
    v0 = scene.mesh.vertices[scene.mesh.faces[tri, 0]]
    t = np.einsum("ij,ij->i", nrm, v0 - o_T) / np.einsum("ij,ij->i", nrm, d_T[ray])
    point[ray] = o_T + t[:, None] * d_T[ray]
    nrm_full = np.full((n, 3), np.nan)
    nrm_full[ray] = shading_normals(scene, point[ray], tri)
    depth = np.full(n, np.nan)
    depth[ray] = (point[ray] @ D.T + rho)[:, 1]
    surface = np.where(tri_of >= 0, scene.surface[np.maximum(tri_of, 0)], -1)
    return Hits(point.reshape(shp + (3,)), tri_of.reshape(shp), surface.reshape(shp), depth.reshape(shp),
                nrm_full.reshape(shp + (3,)), (tri_of >= 0).reshape(shp))  # fmt: skip


def shading_normals(scene: Scene, p: Array, tri: NDArray[np.int64]) -> Array:
    """Outward normals for shading: the analytic ellipsoid normal on a smooth body, else the triangle's."""
    n = scene.normals[tri].copy()
    if scene.smooth:
        body = tri < scene.n_body
        n[body] = shapes.normals(scene.shape, p[body])
    return n


def shade(scene: Scene, hits: Hits, d_T: Array, sun_T: Array, footprint_m: Array, settings: RenderSettings) -> Array:
    """Radiance of the hit rays ``(m,)`` (``hits`` flattened to its hits)."""
    p, tri, n = hits.point, hits.triangle, hits.normal
    cos_i = np.clip(n @ sun_T, 0.0, None)
    lit = cos_i > 0.0
    if settings.shadows and lit.any():
        idx = np.flatnonzero(lit)
        eps = SHADOW_OFFSET * scene.shape.extent
        origin = p[idx] + eps * scene.normals[tri[idx]]
        blocked = scene.mesh.ray.intersects_any(origin, np.broadcast_to(sun_T, origin.shape))
        lit[idx[blocked]] = False
    albedo = albedo_at(scene, p, tri, texture.slant_footprint(footprint_m, n, d_T))
    return albedo * (np.where(lit, cos_i, 0.0) + settings.ambient)


def albedo_at(scene: Scene, p: Array, tri: NDArray[np.int64], footprint_m: Array) -> Array:
    """Texture albedo at body points ``p (m, 3)`` on triangles ``tri`` (planar along the normal's dominant axis)."""
    k = np.argmax(np.abs(scene.normals[tri]), axis=-1)
    a = np.take_along_axis(p, ((k + 1) % 3)[:, None], -1)[:, 0]
    b = np.take_along_axis(p, ((k + 2) % 3)[:, None], -1)[:, 0]
    s = scene.surface[tri]
    a = a + scene.offset[s, 0]
    b = b + scene.offset[s, 1]
    out = np.empty(len(p))
    mat = scene.material[s]
    for m in np.unique(mat):
        sel = mat == m
        out[sel] = scene.atlas.sample(int(m), a[sel], b[sel], footprint_m[sel])
    return out


def footprint_window(scene: Scene, rig: Rig, rho: Array, D: Array, cam: str) -> tuple[slice, slice]:
    """Rows and columns of the pixels whose rays can meet the target: the bounding box of its projected
    vertices (a ray meets the mesh only inside the projection of its convex hull), one pixel wider; the
    whole image if a vertex is not in front of the camera."""
    cam_ = rig.camera
    p_L = scene.mesh.vertices @ D.T + rho
    if np.any(p_L[:, 1] <= 0.0):
        return slice(0, cam_.height), slice(0, cam_.width)
    px = project_px(cam_, rig.baseline, p_L, cam)
    c0, r0 = np.clip(np.floor(px.min(axis=0)).astype(int) - 1, 0, [cam_.width, cam_.height])
    c1, r1 = np.clip(np.ceil(px.max(axis=0)).astype(int) + 1, 0, [cam_.width, cam_.height])
    return slice(r0, r1), slice(c0, c1)


def earth_window(rig: Rig, earth: ea.EarthView, cam: str) -> tuple[slice, slice]:
    """Rows and columns of the pixels whose centre ray meets the Earth, one pixel wider (empty: no such pixel)."""
    col, row = pixel_grid(rig.camera, 1)
    t = ea.intersect(rig.centre(cam), directions_L(rig.camera, col[..., 0], row[..., 0]).reshape(-1, 3),
                     earth.centre_L, earth.earth.radius).reshape(col.shape[:2])  # fmt: skip
    r, c = np.nonzero(np.isfinite(t))
    if not len(r):
        return slice(0, 0), slice(0, 0)
    H, W = rig.camera.height, rig.camera.width
    return slice(max(r.min() - 1, 0), min(r.max() + 2, H)), slice(max(c.min() - 1, 0), min(c.max() + 2, W))


def render_view(scene: Scene, rig: Rig, rho: Array, D: Array, sun_L: Array, cam: str,
                settings: RenderSettings = RenderSettings(), earth: ea.EarthView | None = None) -> View:  # fmt: skip
    """Radiance and ground truth of one camera at the pose ``(rho, D)`` (rays cast only where the target can be;
    with ``earth``, the rays that miss the target and meet the Earth show it)."""
    s = settings.supersample
    H, W = rig.camera.height, rig.camera.width
    rows, cols = footprint_window(scene, rig, rho, D, cam)
    col, row = pixel_grid(rig.camera, s)
    col, row = col[rows, cols], row[rows, cols]
    h, w, S = col.shape
    hits = cast(scene, rig, rho, D, cam, col, row)
    flat = Hits(*(a.reshape((h * w * S,) + a.shape[3:]) for a in (hits.point, hits.triangle, hits.surface,
                                                                   hits.depth, hits.normal, hits.hit)))  # fmt: skip
    rad = np.zeros(h * w * S)
    m = flat.hit
    if m.any():
        d_T = directions_L(rig.camera, col.ravel()[m], row.ravel()[m]) @ D
        sub = Hits(flat.point[m], flat.triangle[m], flat.surface[m], flat.depth[m], flat.normal[m], flat.hit[m])
        rng_m = np.linalg.norm(sub.point - D.T @ (rig.centre(cam) - rho), axis=-1)
        footprint = rng_m / (rig.camera.f_px * s)
        rad[m] = shade(scene, sub, d_T, D.T @ np.asarray(sun_L, dtype=float), footprint, settings)
    radiance = np.zeros((H, W))
    if earth is None:
        radiance[rows, cols] = rad.reshape(h, w, S).mean(axis=-1)
    else:
        miss = np.ones((H, W, S), bool)
        miss[rows, cols] = ~hits.hit
        cf, rf = pixel_grid(rig.camera, s)
        full = np.zeros((H, W, S))
        full[miss] = ea.radiance(earth, rig.centre(cam), directions_L(rig.camera, cf[miss], rf[miss]),
                                 np.asarray(sun_L, float), 1.0 / (rig.camera.f_px * s))  # fmt: skip
        full[rows, cols] += rad.reshape(h, w, S)
        radiance = full.mean(axis=-1)
    if s % 2:  # the middle sub-sample is the pixel centre
        win = Hits(*(a[:, :, (S - 1) // 2] for a in (hits.point, hits.triangle, hits.surface, hits.depth,
                                                        hits.normal, hits.hit)))  # fmt: skip
    else:
        col0, row0 = pixel_grid(rig.camera, 1)
        win = cast(scene, rig, rho, D, cam, col0[rows, cols, 0], row0[rows, cols, 0])
    truth = Hits(np.full((H, W, 3), np.nan), np.full((H, W), -1, np.int64), np.full((H, W), -1, np.int64),
                 np.full((H, W), np.nan), np.full((H, W, 3), np.nan), np.zeros((H, W), bool))  # fmt: skip
    for full, part in zip(truth.__dict__.values(), win.__dict__.values()):
        full[rows, cols] = part
    return View(radiance, truth)


@dataclass(frozen=True)
class StereoFrame:
    right: View
    left: View


def render_stereo(scene: Scene, rig: Rig, rho: Array, D: Array, sun_L: Array,
                  settings: RenderSettings = RenderSettings(), earth: ea.EarthView | None = None) -> StereoFrame:  # fmt: skip
    """Both cameras at one pose (``earth``: the Earth behind the target at this step, else black)."""
    return StereoFrame(*(render_view(scene, rig, rho, D, sun_L, c, settings, earth) for c in ("right", "left")))
