"""Mass properties of a closed triangle mesh by the divergence theorem (thesis ch. 7.4).

Every oriented triangle ``(a, b, c)`` of a closed, outward-facing surface spans, with
the origin ``0``, a signed tetrahedron; the solid is the signed sum of these
tetrahedra, so volume integrals become sums of the canonical tetrahedron integrals
(``d = a . (b x c)`` is six times the signed volume, ``s = a + b + c``):

    V         = sum d / 6
    int x dV  = sum d / 24  * s
    int x x^T = sum d / 120 * (s s^T + a a^T + b b^T + c c^T)

(the last is the degree-2 moment ``V/20 (sum_v v v^T + s s^T)`` of a tetrahedron with
vertices ``0, a, b, c``). These equal the thesis's 3D moments ``m_pqr`` (eqs. 7.3-7.22)
and are exact for any closed, consistently oriented polyhedron. With the centroid
``c = int x dV / V`` and the central second moment ``C = int x x^T dV - V c c^T``, the
inertia tensor about the centroid at density ``rho`` is ``J = rho (tr(C) I_3 - C)``
(eqs. 7.32-7.37); its eigenvalues (ascending) are the principal moments.

The sums are taken about the mean vertex (a translation) to avoid cancellation far from
the origin. The module also checks that a mesh is closed, manifold, consistently and
outward oriented and free of degenerate faces (:func:`check_mesh`), repairs what can be
repaired without inventing geometry (:func:`repair_mesh`), and builds primitive solids
(:func:`box_mesh`, :func:`prism_mesh`, :func:`icosphere_mesh`) for tests and examples.

Meshes are ``vertices (n, 3)`` float and ``faces (m, 3)`` integer vertex indices; the
batched kernel :func:`triangle_moments` takes triangles ``(..., m, 3, 3)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, connected_components
from scipy.spatial import cKDTree

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

AREA_RTOL = 1e-12
"""A triangle is degenerate when its area is at most ``AREA_RTOL * L^2`` (``L``: bounding-box diagonal)."""
MERGE_RTOL = 1e-9
"""``repair_mesh`` merges vertices closer than ``MERGE_RTOL * L``."""
EQUAL_RTOL = 1e-9
"""Principal moments closer than this (relative) are reported as equal (axes not unique)."""


# --------------------------------------------------------------------------- integrals


def triangles(vertices: Array, faces: IntArray) -> Array:
    """Triangle corner coordinates ``(m, 3, 3)``: ``tri[f, v] = vertices[faces[f, v]]``."""
    return np.asarray(vertices, dtype=float)[np.asarray(faces)]


def triangle_moments(tri: Array) -> tuple[Array, Array, Array]:
    """Volume ``(...)``, first moment ``int x dV (..., 3)`` and second moment
    ``int x x^T dV (..., 3, 3)`` of the solid bounded by triangles ``(..., m, 3, 3)``.

    Sums of the signed tetrahedra ``(0, a, b, c)``: ``d = a . (b x c)``,
    ``V = sum d/6``, ``int x = sum d/24 (a+b+c)``,
    ``int x x^T = sum d/120 (s s^T + a a^T + b b^T + c c^T)`` with ``s = a+b+c``.
    """
    tri = np.asarray(tri, dtype=float)
    a, b, c = tri[..., 0, :], tri[..., 1, :], tri[..., 2, :]
    d = np.einsum("...i,...i->...", a, np.cross(b, c))
    s = a + b + c
    volume = d.sum(axis=-1) / 6.0
    first = np.einsum("...m,...mi->...i", d, s) / 24.0
    outer = (
        np.einsum("...mi,...mj->...mij", s, s)
        + np.einsum("...mi,...mj->...mij", a, a)
        + np.einsum("...mi,...mj->...mij", b, b)
        + np.einsum("...mi,...mj->...mij", c, c)
    )
    second = np.einsum("...m,...mij->...ij", d, outer) / 120.0
    return volume, first, second


def signed_volume(vertices: Array, faces: IntArray) -> float:
    """Signed volume ``sum a . (b x c) / 6`` (positive for an outward-facing closed mesh)."""
    v, _, _ = triangle_moments(triangles(vertices, faces) - _origin(vertices, faces))
    return float(v)


def _origin(vertices: Array, faces: IntArray) -> Array:
    """Mean of the referenced vertices (the reference point of the sums)."""
    faces = np.asarray(faces)
    if faces.size == 0:
        return np.zeros(3)
    return np.asarray(vertices, dtype=float)[np.unique(faces)].mean(axis=0)


@dataclass(frozen=True)
class MassProperties:
    """Mass properties at constant density (SI if the mesh is in metres).

    ``inertia`` is about the centroid in the mesh's axes; ``principal_moments`` ascending;
    ``principal_axes`` has the matching unit eigenvectors as columns (right-handed);
    ``k1 = ln(I_1/I_2)``, ``k2 = ln(I_2/I_3)`` of the ascending principal moments.
    """

    volume: float
    mass: float
    density: float
    centroid: Array
    inertia: Array
    principal_moments: Array
    principal_axes: Array
    k1: float
    k2: float


def inertia_from_moments(volume: float, first: Array, second: Array, density: float) -> tuple[Array, Array]:
    """Centroid ``c = first / V`` and inertia about it ``J = rho (tr(C) I - C)``, ``C = second - V c c^T``."""
    centroid = np.asarray(first, dtype=float) / volume
    C = np.asarray(second, dtype=float) - volume * np.outer(centroid, centroid)
    C = 0.5 * (C + C.T)
    return centroid, density * (np.trace(C) * np.eye(3) - C)


def principal_axes(inertia: Array) -> tuple[Array, Array]:
    """Ascending principal moments and axes (columns) of a symmetric 3x3 tensor.

    Sign convention: axes 1 and 2 have their largest-magnitude component positive and
    axis 3 = axis 1 x axis 2 (right-handed, det = +1).
    """
    moments, axes = np.linalg.eigh(0.5 * (inertia + inertia.T))
    for j in (0, 1):
        if axes[np.argmax(np.abs(axes[:, j])), j] < 0:
            axes[:, j] = -axes[:, j]
    axes[:, 2] = np.cross(axes[:, 0], axes[:, 1])
    return moments, axes


def mass_properties(vertices: Array, faces: IntArray, density: float = 1.0) -> MassProperties:
    """Volume, mass, centroid, central inertia, principal moments/axes and ``k1, k2``.

    The mesh must be closed and outward oriented (see :func:`check_mesh`); the volume
    must be positive.
    """
    if not (np.isfinite(density) and density > 0):
        raise ValueError(f"density must be positive, got {density}")
    origin = _origin(vertices, faces)
    volume, first, second = triangle_moments(triangles(vertices, faces) - origin)
    volume = float(volume)
    if not volume > 0:
        raise ValueError(f"mesh volume {volume:.6g} is not positive (inward-facing, open or flat mesh)")
    centroid, inertia = inertia_from_moments(volume, first, second, density)
    moments, axes = principal_axes(inertia)
    with np.errstate(divide="ignore", invalid="ignore"):
        k1 = float(np.log(moments[0] / moments[1]))
        k2 = float(np.log(moments[1] / moments[2]))
    return MassProperties(
        volume=volume,
        mass=density * volume,
        density=float(density),
        centroid=centroid + origin,
        inertia=inertia,
        principal_moments=moments,
        principal_axes=axes,
        k1=k1,
        k2=k2,
    )


def equal_moment_pairs(moments: Array, rtol: float = EQUAL_RTOL) -> list[tuple[int, int]]:
    """Pairs ``(i, i+1)`` of ascending principal moments equal to ``rtol`` (their axes are not unique)."""
    scale = float(np.max(np.abs(moments))) or 1.0
    return [(i, i + 1) for i in range(2) if abs(moments[i + 1] - moments[i]) <= rtol * scale]


# --------------------------------------------------------------------------- topology


def _validate(vertices: Array, faces: IntArray) -> tuple[Array, IntArray]:
    vertices = np.asarray(vertices, dtype=float)
    faces = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"vertices must be (n, 3), got shape {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must be (m, 3) triangles, got shape {faces.shape}")
    if not np.issubdtype(faces.dtype, np.integer):
        raise ValueError("faces must hold integer vertex indices")
    faces = faces.astype(np.int64)
    if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise ValueError(f"face vertex index out of range [0, {len(vertices) - 1}]")
    if not np.all(np.isfinite(vertices)):
        raise ValueError("vertices have non-finite coordinates")
    return vertices, faces


def bbox_diagonal(vertices: Array, faces: IntArray) -> float:
    """Diagonal of the bounding box of the referenced vertices (the mesh's length scale)."""
    faces = np.asarray(faces)
    if faces.size == 0:
        return 0.0
    v = np.asarray(vertices, dtype=float)[np.unique(faces)]
    return float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))


def degenerate_faces(vertices: Array, faces: IntArray, area_rtol: float = AREA_RTOL) -> IntArray:
    """Indices of faces with a repeated vertex index or area ``<= area_rtol L^2``."""
    tri = triangles(vertices, faces)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=-1)
    L = bbox_diagonal(vertices, faces)
    repeated = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2])
    return np.flatnonzero(repeated | (area <= area_rtol * L * L))


def duplicate_faces(faces: IntArray) -> IntArray:
    """Indices of faces whose vertex set repeats an earlier face's (either orientation)."""
    if len(faces) == 0:
        return np.zeros(0, dtype=np.int64)
    key = np.sort(faces, axis=1)
    _, first = np.unique(key, axis=0, return_index=True)
    mask = np.ones(len(faces), dtype=bool)
    mask[first] = False
    return np.flatnonzero(mask)


def duplicate_vertex_count(vertices: Array, faces: IntArray) -> int:
    """Number of referenced vertices whose coordinates exactly repeat another referenced vertex's."""
    used = np.unique(faces)
    if used.size == 0:
        return 0
    return int(used.size - np.unique(np.asarray(vertices)[used], axis=0).shape[0])


@dataclass(frozen=True)
class EdgeTopology:
    """Undirected edges ``(e, 2)`` (sorted vertex pairs), how many faces use each, and for
    edges used exactly twice the two faces and whether both traverse it in the same
    direction (an orientation conflict)."""

    edges: IntArray
    counts: IntArray
    pair_faces: IntArray  # (p, 2) faces of each twice-used edge
    pair_same_direction: NDArray[np.bool_]  # (p,)
    pair_edges: IntArray  # (p,) index into ``edges``


def edge_topology(faces: IntArray) -> EdgeTopology:
    """Edge use counts and face adjacency from the half-edges ``(f0,f1), (f1,f2), (f2,f0)``."""
    faces = np.asarray(faces, dtype=np.int64)
    m = len(faces)
    start = faces.reshape(-1)
    end = faces[:, [1, 2, 0]].reshape(-1)
    face_of = np.repeat(np.arange(m), 3)
    und = np.stack([np.minimum(start, end), np.maximum(start, end)], axis=1)
    if m == 0:
        empty = np.zeros((0, 2), dtype=np.int64)
        return EdgeTopology(empty, np.zeros(0, np.int64), empty, np.zeros(0, bool), np.zeros(0, np.int64))
    edges, inverse, counts = np.unique(und, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    order = np.argsort(inverse, kind="stable")
    twice = np.flatnonzero(counts == 2)
    # half-edges sorted by edge index; the first of each edge's group sits at offsets[e]
    offsets = np.concatenate([[0], np.cumsum(counts)[:-1]])
    h0 = order[offsets[twice]]
    h1 = order[offsets[twice] + 1]
    same = start[h0] == start[h1]
    return EdgeTopology(
        edges=edges,
        counts=counts,
        pair_faces=np.stack([face_of[h0], face_of[h1]], axis=1),
        pair_same_direction=same,
        pair_edges=twice,
    )


def face_components(n_faces: int, topo: EdgeTopology) -> tuple[int, IntArray]:
    """Connected components of faces joined by twice-used edges: ``(count, label per face)``."""
    if n_faces == 0:
        return 0, np.zeros(0, dtype=np.int64)
    p = topo.pair_faces
    g = coo_matrix((np.ones(len(p)), (p[:, 0], p[:, 1])), shape=(n_faces, n_faces)).tocsr()
    n, labels = connected_components(g, directed=False)
    return int(n), labels.astype(np.int64)


def orientation_flips(n_faces: int, topo: EdgeTopology) -> tuple[NDArray[np.bool_], int]:
    """Which faces to flip so every twice-used edge is traversed in opposite directions.

    Breadth-first over each component from its lowest-index face (kept as is):
    ``flip[g] = flip[f] xor same_direction(f, g)``. Returns the flips and the number of
    edges still in conflict afterwards (non-zero: a non-orientable component).
    """
    flip = np.zeros(n_faces, dtype=bool)
    if n_faces == 0:
        return flip, 0
    p = topo.pair_faces
    same = {}
    for (f, g), s in zip(p.tolist(), topo.pair_same_direction.tolist()):
        same[(f, g)] = s
        same[(g, f)] = s
    g_mat = coo_matrix((np.ones(len(p)), (p[:, 0], p[:, 1])), shape=(n_faces, n_faces)).tocsr()
    g_mat = g_mat + g_mat.T
    visited = np.zeros(n_faces, dtype=bool)
    for root in range(n_faces):
        if visited[root]:
            continue
        order, pred = breadth_first_order(g_mat, root, directed=False, return_predecessors=True)
        visited[order] = True
        for node in order[1:].tolist():
            parent = int(pred[node])
            flip[node] = flip[parent] ^ same[(parent, node)]
    conflicts = int(np.sum(topo.pair_same_direction ^ flip[p[:, 0]] ^ flip[p[:, 1]]))
    return flip, conflicts


def _rowdot(u: Array, v: Array) -> Array:
    return np.einsum("ij,ij->i", u, v)


def winding_number(point: Array, tri: Array) -> float:
    """Winding number of a closed triangle surface about ``point``: ``sum Omega / (4 pi)``.

    Solid angle of each triangle (Van Oosterom & Strackee 1983), with ``a, b, c`` the corners
    relative to ``point``: ``tan(Omega/2) = a.(b x c) / (|a||b||c| + (a.b)|c| + (a.c)|b| + (b.c)|a|)``.
    """
    a, b, c = (tri[:, i] - point for i in range(3))
    la, lb, lc = (np.linalg.norm(v, axis=1) for v in (a, b, c))
    num = _rowdot(a, np.cross(b, c))
    den = la * lb * lc + _rowdot(a, b) * lc + _rowdot(a, c) * lb + _rowdot(b, c) * la
    return float(np.sum(2.0 * np.arctan2(num, den)) / (4.0 * np.pi))


@dataclass(frozen=True)
class Shell:
    """One connected closed surface: its faces, signed volume and nesting depth (the
    number of other shells it lies inside; a shell at odd depth bounds a cavity and must
    face inward, i.e. have negative signed volume)."""

    faces: IntArray
    volume: float
    depth: int

    @property
    def facing_ok(self) -> bool:
        return (self.volume > 0) == (self.depth % 2 == 0)


def shells(vertices: Array, faces: IntArray, topo: EdgeTopology | None = None) -> list[Shell]:
    """Split a closed mesh into connected shells with their signed volumes and nesting depths.

    Depth: the number of other shells whose winding number about a point of this shell (its
    first face's centroid) has magnitude above 1/2; shells are assumed not to intersect.
    """
    topo = edge_topology(faces) if topo is None else topo
    n, labels = face_components(len(faces), topo)
    origin = _origin(vertices, faces)
    tri_all = triangles(vertices, faces) - origin
    groups = [np.flatnonzero(labels == k) for k in range(n)]
    vols = [float(triangle_moments(tri_all[g])[0]) for g in groups]
    probes = [tri_all[g[0]].mean(axis=0) for g in groups]
    depth = [0] * n
    for s in range(n):
        for t in range(n):
            if s != t and abs(winding_number(probes[s], tri_all[groups[t]])) > 0.5:
                depth[s] += 1
    return [Shell(faces=groups[k], volume=vols[k], depth=depth[k]) for k in range(n)]


@dataclass(frozen=True)
class MeshCheck:
    """What :func:`check_mesh` found; ``problems`` is empty for a usable mesh."""

    n_vertices: int
    n_faces: int
    boundary_edges: int
    nonmanifold_edges: int
    conflicting_edges: int
    degenerate_faces: int
    duplicate_faces: int
    duplicate_vertices: int
    shells: list[Shell] = field(default_factory=list)
    volume: float = float("nan")
    problems: list[str] = field(default_factory=list)


def check_mesh(vertices: Array, faces: IntArray, area_rtol: float = AREA_RTOL) -> MeshCheck:
    """Check that a triangle mesh bounds a solid the divergence theorem can integrate.

    Problems (each one sentence, with the fix ``repair_mesh`` would apply if any): no faces;
    degenerate or duplicate faces; edges used by one face (open) or more than two (not
    manifold); edges traversed in the same direction by both faces (inconsistent
    orientation); shells facing the wrong way for their nesting (an inward-facing solid
    or an outward-facing cavity, found from the sign of each shell's volume); zero volume.
    """
    vertices, faces = _validate(vertices, faces)
    problems: list[str] = []
    nv, nf = len(vertices), len(faces)
    if nf == 0:
        return MeshCheck(nv, 0, 0, 0, 0, 0, 0, 0, problems=["mesh has no triangles"])
    degen = degenerate_faces(vertices, faces, area_rtol)
    dups = duplicate_faces(faces)
    ndv = duplicate_vertex_count(vertices, faces)
    topo = edge_topology(faces)
    boundary = int(np.sum(topo.counts == 1))
    nonmanifold = int(np.sum(topo.counts > 2))
    conflicts = int(np.sum(topo.pair_same_direction))
    if len(degen):
        problems.append(
            f"{len(degen)} degenerate triangle(s) (zero area or a repeated vertex), e.g. face {degen[0]}"
            " (--repair drops them)"
        )
    if len(dups):
        problems.append(
            f"{len(dups)} duplicate triangle(s) repeating another face's vertices, e.g. face {dups[0]}"
            " (--repair drops them)"
        )
    if boundary:
        e = topo.edges[np.flatnonzero(topo.counts == 1)[0]]
        hint = (
            f"; {ndv} vertices repeat another vertex's coordinates (--repair merges them, which may close it)"
            if ndv
            else "; --repair does not fill holes: close them in a mesh editor"
        )
        problems.append(
            f"mesh is not closed: {boundary} boundary edge(s) used by only one triangle, "
            f"e.g. between vertices {e[0]} and {e[1]}{hint}"
        )
    if nonmanifold:
        e = topo.edges[np.flatnonzero(topo.counts > 2)[0]]
        problems.append(
            f"mesh is not manifold: {nonmanifold} edge(s) shared by more than two triangles, "
            f"e.g. between vertices {e[0]} and {e[1]}"
        )
    if conflicts:
        f = topo.pair_faces[np.flatnonzero(topo.pair_same_direction)[0]]
        problems.append(
            f"mesh is not consistently oriented: {conflicts} edge(s) traversed in the same direction by both "
            f"their triangles, e.g. faces {f[0]} and {f[1]} (--repair flips faces to agree)"
        )
    sh: list[Shell] = []
    volume = signed_volume(vertices, faces)
    if not (boundary or nonmanifold or conflicts or len(degen) or len(dups)):
        sh = shells(vertices, faces, topo)
        L = bbox_diagonal(vertices, faces)
        if abs(volume) <= area_rtol * L**3:
            problems.append(f"mesh encloses no volume (signed volume {volume:.6g}): it is flat or degenerate")
        elif len(sh) == 1 and sh[0].volume < 0:
            problems.append(
                f"mesh is inward-facing: signed volume {volume:.6g} < 0 (its normals point inward; "
                "--repair flips all triangles)"
            )
        elif len(sh) > 1:
            for k, s in enumerate(sh):
                if not s.facing_ok:
                    what = "a cavity, must face inward" if s.depth % 2 else "a solid, must face outward"
                    problems.append(
                        f"shell {k + 1} of {len(sh)} ({len(s.faces)} triangles, e.g. face {s.faces[0]}) lies inside "
                        f"{s.depth} other shell(s) ({what}) but has signed volume {s.volume:.6g} (--repair flips it)"
                    )
        if not problems and not volume > area_rtol * L**3:
            problems.append(f"mesh encloses no net volume (signed volume {volume:.6g})")
    return MeshCheck(nv, nf, boundary, nonmanifold, conflicts, len(degen), len(dups), ndv, sh, volume, problems)


# --------------------------------------------------------------------------- repair


def merge_vertices(vertices: Array, faces: IntArray, tol: float) -> tuple[Array, IntArray, int]:
    """Merge vertices closer than ``tol`` (transitively) into the lowest-index one.

    Returns the vertices (unchanged array), the re-indexed faces and the number of
    vertices merged away.
    """
    vertices = np.asarray(vertices, dtype=float)
    n = len(vertices)
    if n == 0:
        return vertices, faces, 0
    pairs = cKDTree(vertices).query_pairs(r=tol, output_type="ndarray") if tol > 0 else np.zeros((0, 2), int)
    exact = np.unique(vertices, axis=0, return_inverse=True)[1].reshape(-1)
    # exact duplicates always merge (query_pairs with r=0 finds nothing)
    rows = np.concatenate([pairs[:, 0], np.arange(n)])
    cols = np.concatenate([pairs[:, 1], n + exact])
    g = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(2 * n, 2 * n))
    _, labels = connected_components(g, directed=False)
    labels = labels[:n]
    # representative: lowest original index in each group
    rep = np.full(labels.max() + 1, n, dtype=np.int64)
    np.minimum.at(rep, labels, np.arange(n))
    mapping = rep[labels]
    merged = int(n - np.unique(mapping).size)
    return vertices, mapping[np.asarray(faces, dtype=np.int64)], merged


def flip_faces(faces: IntArray, which: NDArray[np.bool_] | None = None) -> IntArray:
    """Reverse the orientation of the selected faces (all by default): ``(a, b, c) -> (a, c, b)``."""
    faces = np.array(faces, dtype=np.int64, copy=True)
    sel = slice(None) if which is None else which
    faces[sel] = faces[sel][:, [0, 2, 1]]
    return faces


def _same_cyclic_order(f: IntArray, g: IntArray) -> bool:
    """Whether two faces on the same three vertices have the same orientation."""
    k = int(np.flatnonzero(g == f[0])[0])
    return bool(np.array_equal(np.roll(g, -k), f))


def repair_mesh(
    vertices: Array,
    faces: IntArray,
    merge_rtol: float = MERGE_RTOL,
    area_rtol: float = AREA_RTOL,
) -> tuple[Array, IntArray, list[str]]:
    """Fix what can be fixed without inventing geometry, and say what changed.

    In order: merge vertices closer than ``merge_rtol * L``; drop degenerate triangles;
    drop repeated triangles (one copy kept when all copies agree in orientation, all dropped
    when copies face opposite ways: a zero-thickness wall); drop unreferenced vertices;
    then, if the mesh is closed and manifold, flip faces so each connected shell is
    consistently oriented and flip whole shells to face outward (solids) or inward
    (cavities, i.e. shells nested at odd depth), judged by the sign of each shell's volume.
    Holes and non-manifold edges are left for :func:`check_mesh` to report.
    """
    vertices, faces = _validate(vertices, faces)
    changes: list[str] = []
    L = bbox_diagonal(vertices, faces)

    _, faces, merged = merge_vertices(vertices, faces, merge_rtol * L)
    if merged:
        changes.append(f"merged {merged} duplicate vertices (closer than {merge_rtol * L:.3g})")

    degen = degenerate_faces(vertices, faces, area_rtol)
    if len(degen):
        faces = np.delete(faces, degen, axis=0)
        changes.append(f"dropped {len(degen)} degenerate triangle(s) (zero area or a repeated vertex)")

    if len(faces):
        key = np.sort(faces, axis=1)
        _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
        inv = inv.reshape(-1)
        drop: list[int] = []
        walls = 0
        for grp in np.flatnonzero(cnt > 1):
            idx = np.flatnonzero(inv == grp)
            agree = [_same_cyclic_order(faces[idx[0]], faces[j]) for j in idx]
            if all(agree):
                drop.extend(idx[1:].tolist())
            else:
                drop.extend(idx.tolist())
                walls += 1
        if drop:
            faces = np.delete(faces, drop, axis=0)
            msg = f"dropped {len(drop)} duplicate triangle(s)"
            if walls:
                msg += f" ({walls} set(s) of copies facing opposite ways dropped entirely: zero-thickness walls)"
            changes.append(msg)

    used = np.unique(faces)
    if used.size < len(vertices):
        remap = np.full(len(vertices), -1, dtype=np.int64)
        remap[used] = np.arange(used.size)
        changes.append(f"removed {len(vertices) - used.size} unreferenced vertices")
        vertices, faces = vertices[used], remap[faces]

    topo = edge_topology(faces)
    if len(faces) == 0 or np.any(topo.counts != 2):
        return vertices, faces, changes

    flip, conflicts = orientation_flips(len(faces), topo)
    if np.any(flip) and conflicts == 0:
        # keep the majority orientation of each component, so a nearly right mesh changes least
        n, labels = face_components(len(faces), topo)
        for k in range(n):
            sel = labels == k
            if flip[sel].sum() * 2 > sel.sum():
                flip[sel] = ~flip[sel]
        faces = flip_faces(faces, flip)
        changes.append(f"flipped {int(flip.sum())} triangle(s) to orient each shell consistently")
        topo = edge_topology(faces)
    if conflicts:
        return vertices, faces, changes  # non-orientable: check_mesh reports the conflicts

    sh = shells(vertices, faces, topo)
    for k, s in enumerate(sh):
        if not s.facing_ok:
            faces = flip_faces(faces, np.isin(np.arange(len(faces)), s.faces))
            if len(sh) == 1:
                changes.append(
                    f"flipped all {len(s.faces)} triangles: the mesh was inward-facing "
                    f"(signed volume {s.volume:.6g} -> {-s.volume:.6g})"
                )
            else:
                role = "a cavity inside" if s.depth % 2 else "a solid inside" if s.depth else "an outer solid"
                where = f" {s.depth} other shell(s)" if s.depth else ""
                changes.append(
                    f"flipped shell {k + 1} of {len(sh)} ({len(s.faces)} triangles, {role}{where}): "
                    f"signed volume {s.volume:.6g} -> {-s.volume:.6g}"
                )
    return vertices, faces, changes


# --------------------------------------------------------------------------- primitives


def box_mesh(a: float, b: float, c: float, center: Array = (0.0, 0.0, 0.0)) -> tuple[Array, IntArray]:
    """Closed, outward box with edges ``a, b, c`` along x, y, z: 8 vertices, 12 triangles."""
    v = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)]) * [a, b, c]
    # vertex index = 4 ix + 2 iy + iz; quads listed counter-clockwise seen from outside
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    f = [(q[0], q[1], q[2]) for q in quads] + [(q[0], q[2], q[3]) for q in quads]
    return v + np.asarray(center, dtype=float), np.array(f, dtype=np.int64)


def prism_mesh(radius: float, height: float, n: int) -> tuple[Array, IntArray]:
    """Closed, outward right prism on a regular ``n``-gon (circumradius ``radius``) along z,
    centred at the origin: the polygonal approximation of a cylinder (2n + 2 vertices, 4n triangles)."""
    if n < 3:
        raise ValueError("a prism needs n >= 3 sides")
    t = 2.0 * np.pi * np.arange(n) / n
    ring = np.stack([radius * np.cos(t), radius * np.sin(t)], axis=1)
    bottom = np.column_stack([ring, np.full(n, -height / 2)])
    top = np.column_stack([ring, np.full(n, height / 2)])
    v = np.vstack([bottom, top, [[0, 0, -height / 2], [0, 0, height / 2]]])
    i = np.arange(n)
    j = (i + 1) % n
    cb, ct = 2 * n, 2 * n + 1
    side1 = np.stack([i, j, n + j], axis=1)
    side2 = np.stack([i, n + j, n + i], axis=1)
    cap_b = np.stack([np.full(n, cb), j, i], axis=1)
    cap_t = np.stack([np.full(n, ct), n + i, n + j], axis=1)
    return v, np.vstack([side1, side2, cap_b, cap_t]).astype(np.int64)


def icosphere_mesh(radius: float, subdivisions: int) -> tuple[Array, IntArray]:
    """Closed, outward icosphere: an icosahedron with each triangle split in four
    ``subdivisions`` times, vertices projected onto the sphere (20 * 4^s triangles)."""
    p = (1.0 + 5.0**0.5) / 2.0
    v = [[-1, p, 0], [1, p, 0], [-1, -p, 0], [1, -p, 0], [0, -1, p], [0, 1, p],
         [0, -1, -p], [0, 1, -p], [p, 0, -1], [p, 0, 1], [-p, 0, -1], [-p, 0, 1]]  # fmt: skip
    f = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
         [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5],
         [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]]  # fmt: skip
    verts = [np.array(x, dtype=float) / np.linalg.norm(x) for x in v]
    faces = [tuple(x) for x in f]
    for _ in range(subdivisions):
        cache: dict[tuple[int, int], int] = {}

        def mid(i: int, j: int) -> int:
            key = (min(i, j), max(i, j))
            if key not in cache:
                m = verts[i] + verts[j]
                verts.append(m / np.linalg.norm(m))
                cache[key] = len(verts) - 1
            return cache[key]

        new = []
        for a, b, c in faces:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            new += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = new
    return radius * np.array(verts), np.array(faces, dtype=np.int64)


def combine(*meshes: tuple[Array, IntArray]) -> tuple[Array, IntArray]:
    """Concatenate meshes into one (faces re-indexed), e.g. an outer surface and a reversed inner one."""
    vs, fs, off = [], [], 0
    for v, f in meshes:
        vs.append(np.asarray(v, dtype=float))
        fs.append(np.asarray(f, dtype=np.int64) + off)
        off += len(v)
    return np.vstack(vs), np.vstack(fs)
