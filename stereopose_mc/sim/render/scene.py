"""The rendered target: its triangle mesh in the target frame ``T``, surfaces, materials.

The body is the scenario's ``target.shape`` (config/sensor.py ``shape_of``, the same body the
occlusion and illumination tests use): a box as 12 triangles, an ellipsoid as an icosphere
(``ELLIPSOID_SUBDIVISIONS``, 20 480 triangles, shaded with its analytic normals), a mesh as
read. Optional solar panels (:class:`Panels`) are two thin plates beside the body along one of
its axes; they are seen, shadow and occlude, but are not part of ``target.shape`` (the point
model's occlusion test does not know them).

Every triangle belongs to a *surface*: triangles joined across edges whose normals differ by
less than ``SMOOTH_DEG`` (a box face, a panel side, the whole ellipsoid). A surface has one
material (``texture.MLI | EQUIPMENT | CELLS``, body surfaces drawn from the seed, panels are
cells) and a random offset into its material's tile, so no two surfaces look alike.
With a texture from an image file (``texture.file_atlas``) every surface shows that one tile,
at offset zero (the tile's corner at the body frame's origin, repeated every ``w x h`` m).
Texture coordinates are planar along the dominant axis ``k`` of the triangle's normal:
``a = p[(k + 1) % 3]``, ``b = p[(k + 2) % 3]`` (a face normal to ``x``: ``a = y``, ``b = z``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ...core import mesh as cmesh
from ...core import shapes
from . import texture

Array = NDArray[np.float64]

ELLIPSOID_SUBDIVISIONS = 5
SMOOTH_DEG = 20.0


@dataclass(frozen=True)
class Panels:
    """Two solar-panel wings along ``+-axis`` of ``T``, cells facing ``+-normal_axis``."""

    span_m: float = 3.0  # length of each wing
    width_m: float = 1.0
    thickness_m: float = 0.03
    gap_m: float = 0.15  # between the body's bounding box and a wing
    axis: int = 0
    normal_axis: int = 2

    def meshes(self, half: Array) -> list[tuple[Array, NDArray[np.int64]]]:
        """The two wings as closed boxes beside a body of bounding half-sizes ``half``."""
        out = []
        third = 3 - self.axis - self.normal_axis
        for sign in (1.0, -1.0):
            size = np.empty(3)
            size[self.axis], size[self.normal_axis], size[third] = self.span_m, self.thickness_m, self.width_m
            centre = np.zeros(3)
            centre[self.axis] = sign * (half[self.axis] + self.gap_m + 0.5 * self.span_m)
            out.append(cmesh.box_mesh(*size, center=centre))
        return out


@dataclass(frozen=True)
class Scene:
    shape: shapes.Shape
    mesh: trimesh.Trimesh  # body triangles first, then the panels'
    n_body: int  # triangles of the body
    normals: Array  # (M, 3) outward triangle normals
    surface: NDArray[np.int64]  # (M,) surface of each triangle
    material: NDArray[np.int64]  # (S,) material of each surface
    offset: Array  # (S, 2) texture offset of each surface (m)
    atlas: texture.Atlas

    @property
    def smooth(self) -> bool:
        """The body is shaded with the shape's analytic normals (an ellipsoid)."""
        return self.shape.kind == "ellipsoid"


def body_mesh(shape: shapes.Shape) -> tuple[Array, NDArray[np.int64]]:
    """Vertices and outward triangles of a body in ``T``."""
    if shape.kind == "box":
        return cmesh.box_mesh(*(2.0 * shape.size))
    if shape.kind == "ellipsoid":
        v, f = cmesh.icosphere_mesh(1.0, ELLIPSOID_SUBDIVISIONS)
        return v * shape.size, f
    tri = shape.triangles
    return tri.reshape(-1, 3), np.arange(tri.shape[0] * 3).reshape(-1, 3)


def surfaces(mesh: trimesh.Trimesh, smooth_deg: float = SMOOTH_DEG) -> NDArray[np.int64]:
    """Surface label of each triangle: components joined across edges bent less than ``smooth_deg``."""
    adj = mesh.face_adjacency[mesh.face_adjacency_angles < np.radians(smooth_deg)]
    m = len(mesh.faces)
    g = coo_matrix((np.ones(len(adj)), (adj[:, 0], adj[:, 1])), shape=(m, m))
    return connected_components(g, directed=False)[1].astype(np.int64)


def scene(shape: shapes.Shape, seed: int, panels: Panels | None = None, tile: texture.Atlas | None = None) -> Scene:
    """The textured target: the body, optional panels, surfaces, materials and textures from ``seed``; with
    ``tile`` (a one-material atlas, ``texture.file_atlas``) every surface shows it, at offset zero."""
    rng = np.random.default_rng(seed)
    parts = [body_mesh(shape)]
    if panels is not None:
        parts += panels.meshes(shape.size)
    verts, faces, base = [], [], 0
    for v, f in parts:
        verts.append(v)
        faces.append(f + base)
        base += len(v)
    mesh = trimesh.Trimesh(np.concatenate(verts), np.concatenate(faces), process=False)
    n_body = len(parts[0][1])
    label = surfaces(mesh)
    n_surf = int(label.max()) + 1
    on_panel = np.zeros(n_surf, bool)
    on_panel[label[n_body:]] = True
    body_material = rng.choice([texture.MLI, texture.EQUIPMENT], size=n_surf, p=[0.6, 0.4])
    material = np.where(on_panel, texture.CELLS, body_material)
    offset = rng.uniform(0.0, texture.TILE * texture.TEXEL_M, size=(n_surf, 2))
    if tile is not None:
        return Scene(shape, mesh, n_body, np.asarray(mesh.face_normals, dtype=float), label,
                     np.zeros(n_surf, np.int64), np.zeros((n_surf, 2)), tile)  # fmt: skip
    return Scene(shape, mesh, n_body, np.asarray(mesh.face_normals, dtype=float), label, material, offset,
                 texture.atlas(rng))  # fmt: skip
