"""Small readers and writers for triangle-mesh files: OBJ, STL (ASCII and binary), PLY
(ASCII and binary, either byte order).

Readers return a :class:`MeshData` with ``vertices (n, 3)`` in the file's own units,
``faces (m, 3)`` zero-based vertex indices and notes about anything they did:

- polygons with more than three corners are split into a fan of triangles (correct for
  convex polygons, which is what exporters write);
- STL stores each triangle's corners separately (no shared vertices), so corners with
  identical coordinates are joined into one vertex; this loses nothing (the format has no
  other connectivity) and is needed to see whether the surface is closed.

Errors (:class:`MeshFileError`) name the file and, for text formats, the line.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

FORMATS = ("obj", "stl", "ply")


class MeshFileError(Exception):
    """A mesh file that cannot be read."""


@dataclass
class MeshData:
    """A triangle mesh as read from a file (coordinates in the file's units)."""

    vertices: NDArray[np.float64]
    faces: NDArray[np.int64]
    format: str
    notes: list[str] = field(default_factory=list)


def mesh_format(path: str | Path) -> str:
    """The format from the file extension (``.obj``, ``.stl``, ``.ply``, any case)."""
    ext = Path(path).suffix.lower().lstrip(".")
    if ext not in FORMATS:
        raise MeshFileError(f"{path}: unknown mesh format '.{ext}' (supported: .obj, .stl, .ply)")
    return ext


def read_mesh(path: str | Path) -> MeshData:
    """Read an OBJ, STL or PLY file (chosen by extension) into vertices and triangles."""
    path = Path(path)
    fmt = mesh_format(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise MeshFileError(f"{path}: file not found") from None
    except (IsADirectoryError, PermissionError, OSError) as exc:
        raise MeshFileError(f"{path}: cannot read: {exc}") from None
    reader = {"obj": parse_obj, "stl": parse_stl, "ply": parse_ply}[fmt]
    mesh = reader(data, str(path))
    _check_indices(mesh, str(path))
    return mesh


def _check_indices(mesh: MeshData, name: str) -> None:
    if not np.all(np.isfinite(mesh.vertices)):
        raise MeshFileError(f"{name}: vertex coordinates include NaN or infinity")
    if mesh.faces.size and (mesh.faces.min() < 0 or mesh.faces.max() >= len(mesh.vertices)):
        raise MeshFileError(f"{name}: a face refers to a vertex that does not exist ({len(mesh.vertices)} vertices)")
    if mesh.faces.size == 0:
        raise MeshFileError(f"{name}: no triangles found")


def _fan(polys: list[list[int]]) -> tuple[NDArray[np.int64], int]:
    """Triangles ``(p0, p_i, p_{i+1})`` of each polygon; also the number of polygons split."""
    tris: list[tuple[int, int, int]] = []
    split = 0
    for p in polys:
        if len(p) > 3:
            split += 1
        tris.extend((p[0], p[i], p[i + 1]) for i in range(1, len(p) - 1))
    return np.array(tris, dtype=np.int64).reshape(-1, 3), split


def _fan_note(split: int) -> list[str]:
    return [f"split {split} polygon(s) with more than 3 corners into triangles (fan)"] if split else []


def _text(data: bytes, name: str) -> str:
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        try:
            return data.decode("latin-1")
        except UnicodeDecodeError:  # pragma: no cover - latin-1 decodes anything
            raise MeshFileError(f"{name}: not a text file") from None


# --------------------------------------------------------------------------- OBJ


def parse_obj(data: bytes, name: str = "<obj>") -> MeshData:
    """Wavefront OBJ: ``v x y z [w]`` and ``f i j k ...`` with ``i``, ``i/t``, ``i//n``,
    ``i/t/n`` (1-based; negative = relative to the vertices so far). Other statements
    (``vt``, ``vn``, ``g``, ``o``, ``s``, ``usemtl``, ``l``, ...) are ignored."""
    verts: list[tuple[float, float, float]] = []
    polys: list[list[int]] = []
    text = _text(data, name).replace("\\\n", " ")
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split()
        key = parts[0]
        if key == "v":
            if len(parts) < 4:
                raise MeshFileError(f"{name}:{lineno}: vertex needs 3 coordinates: '{raw.strip()}'")
            try:
                verts.append((float(parts[1]), float(parts[2]), float(parts[3])))
            except ValueError:
                raise MeshFileError(f"{name}:{lineno}: bad vertex coordinates: '{raw.strip()}'") from None
        elif key == "f":
            if len(parts) < 4:
                raise MeshFileError(f"{name}:{lineno}: a face needs at least 3 vertices: '{raw.strip()}'")
            poly = []
            for tok in parts[1:]:
                try:
                    i = int(tok.split("/", 1)[0])
                except ValueError:
                    raise MeshFileError(f"{name}:{lineno}: bad face vertex '{tok}'") from None
                if i == 0:
                    raise MeshFileError(f"{name}:{lineno}: OBJ vertex indices start at 1, got 0")
                idx = i - 1 if i > 0 else len(verts) + i
                if not 0 <= idx < len(verts):
                    raise MeshFileError(
                        f"{name}:{lineno}: face vertex {i} does not exist ({len(verts)} vertices defined so far)"
                    )
                poly.append(idx)
            polys.append(poly)
    faces, split = _fan(polys)
    return MeshData(np.array(verts, dtype=float).reshape(-1, 3), faces, "obj", _fan_note(split))


def write_obj(path: str | Path, vertices, faces, comment: str = "") -> None:
    """Write vertices and triangles as OBJ (1-based indices, 17 significant digits)."""
    lines = [f"# {c}" for c in comment.splitlines()] if comment else []
    lines += [f"v {x!r} {y!r} {z!r}" for x, y, z in np.asarray(vertices, dtype=float).tolist()]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in np.asarray(faces).tolist()]
    Path(path).write_text("\n".join(lines) + "\n")


# --------------------------------------------------------------------------- STL


_STL_RECORD = np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")])
"""One binary STL triangle: normal, three corners (float32), attribute byte count."""


def _weld(soup: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Vertices and faces from a triangle soup ``(m, 3, 3)``, joining identical corners."""
    pts = soup.reshape(-1, 3)
    uniq, inv = np.unique(pts, axis=0, return_inverse=True)
    return uniq, inv.reshape(-1, 3).astype(np.int64)


def parse_stl(data: bytes, name: str = "<stl>") -> MeshData:
    """STL, binary (80-byte header, uint32 count, 50 bytes per triangle) or ASCII
    (``solid ... facet normal ... outer loop vertex x y z (x3) endloop endfacet ... endsolid``).

    Binary is recognized by its exact size ``84 + 50 n`` (some binary headers start with
    ``solid`` too). Stored normals are ignored: orientation comes from the corner order.
    """
    if len(data) >= 84:
        (n,) = struct.unpack_from("<I", data, 80)
        if len(data) == 84 + 50 * n:
            rec = np.frombuffer(data, dtype=_STL_RECORD, count=n, offset=84)
            v, f = _weld(rec["v"].astype(float))
            note = f"binary STL: {n} triangles, identical corners joined into {len(v)} vertices"
            return MeshData(v, f, "stl", [note])
    head = data[:512].lstrip()
    if not head[:5].lower() == b"solid":
        raise MeshFileError(
            f"{name}: neither binary STL (size {len(data)} bytes is not 84 + 50 n) nor ASCII STL (no 'solid' header)"
        )
    text = _text(data, name)
    num = r"([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|[-+]?(?:nan|inf))"
    good = rf"^\s*vertex\s+{num}\s+{num}\s+{num}\s*$"
    any_vertex = r"^\s*vertex\b"
    verts = re.findall(good, text, flags=re.MULTILINE | re.IGNORECASE)
    n_vertex_lines = len(re.findall(any_vertex, text, flags=re.MULTILINE | re.IGNORECASE))
    if n_vertex_lines != len(verts):
        bad = next(
            i + 1
            for i, line in enumerate(text.splitlines())
            if re.match(any_vertex, line, re.IGNORECASE) and not re.match(good, line, re.IGNORECASE)
        )
        raise MeshFileError(f"{name}:{bad}: bad 'vertex x y z' line")
    n_facets = len(re.findall(r"^\s*facet\b", text, flags=re.MULTILINE | re.IGNORECASE))
    if len(verts) != 3 * n_facets:
        raise MeshFileError(f"{name}: ASCII STL has {n_facets} facets but {len(verts)} vertex lines (need 3 per facet)")
    soup = np.array(verts, dtype=float).reshape(-1, 3, 3)
    v, f = _weld(soup)
    return MeshData(v, f, "stl", [f"ASCII STL: {len(f)} triangles, identical corners joined into {len(v)} vertices"])


def write_stl(path: str | Path, vertices, faces, binary: bool = True, name: str = "mesh") -> None:
    """Write triangles as binary (float32) or ASCII STL, with facet normals from the corner order."""
    tri = np.asarray(vertices, dtype=float)[np.asarray(faces)]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    ln = np.linalg.norm(nrm, axis=1, keepdims=True)
    nrm = np.divide(nrm, ln, out=np.zeros_like(nrm), where=ln > 0)
    if binary:
        rec = np.zeros(len(tri), dtype=_STL_RECORD)
        rec["n"], rec["v"] = nrm, tri
        header = f"binary STL {name}".encode()[:80].ljust(80, b" ")
        Path(path).write_bytes(header + struct.pack("<I", len(tri)) + rec.tobytes())
        return
    out = [f"solid {name}"]
    for n, t in zip(nrm.tolist(), tri.tolist()):
        out.append(f"  facet normal {n[0]!r} {n[1]!r} {n[2]!r}\n    outer loop")
        out += [f"      vertex {x!r} {y!r} {z!r}" for x, y, z in t]
        out.append("    endloop\n  endfacet")
    out.append(f"endsolid {name}")
    Path(path).write_text("\n".join(out) + "\n")


# --------------------------------------------------------------------------- PLY

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip


@dataclass
class _Prop:
    name: str
    dtype: str  # numpy type code without byte order
    count_dtype: str | None = None  # set for list properties


@dataclass
class _Element:
    name: str
    count: int
    props: list[_Prop]


def _ply_header(data: bytes, name: str) -> tuple[str, list[_Element], int]:
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise MeshFileError(f"{name}: not a PLY file (no 'ply' magic or no 'end_header')")
    nl = data.find(b"\n", end)
    body_start = len(data) if nl < 0 else nl + 1
    lines = data[:end].decode("ascii", errors="replace").splitlines()
    fmt = None
    elements: list[_Element] = []
    for lineno, line in enumerate(lines, start=1):
        parts = line.split()
        if not parts or parts[0] in ("ply", "comment", "obj_info"):
            continue
        if parts[0] == "format":
            if len(parts) < 2 or parts[1] not in ("ascii", "binary_little_endian", "binary_big_endian"):
                raise MeshFileError(f"{name}:{lineno}: unknown PLY format '{line.strip()}'")
            fmt = parts[1]
        elif parts[0] == "element":
            try:
                elements.append(_Element(parts[1], int(parts[2]), []))
            except (IndexError, ValueError):
                raise MeshFileError(f"{name}:{lineno}: bad element line '{line.strip()}'") from None
        elif parts[0] == "property":
            if not elements:
                raise MeshFileError(f"{name}:{lineno}: property before any element")
            try:
                if parts[1] == "list":
                    elements[-1].props.append(_Prop(parts[4], _PLY_TYPES[parts[3]], _PLY_TYPES[parts[2]]))
                else:
                    elements[-1].props.append(_Prop(parts[2], _PLY_TYPES[parts[1]]))
            except (IndexError, KeyError):
                raise MeshFileError(f"{name}:{lineno}: bad property line '{line.strip()}'") from None
        else:
            raise MeshFileError(f"{name}:{lineno}: unexpected PLY header line '{line.strip()}'")
    if fmt is None:
        raise MeshFileError(f"{name}: PLY header has no 'format' line")
    return fmt, elements, body_start


def _ply_parts(elements: list[_Element], name: str) -> tuple[_Element, _Element, list[int], int]:
    by_name = {e.name: e for e in elements}
    if "vertex" not in by_name or "face" not in by_name:
        raise MeshFileError(f"{name}: PLY needs 'vertex' and 'face' elements")
    vert, face = by_name["vertex"], by_name["face"]
    pn = [p.name for p in vert.props]
    if not all(k in pn for k in ("x", "y", "z")):
        raise MeshFileError(f"{name}: PLY vertex element lacks x, y or z")
    lists = [i for i, p in enumerate(face.props) if p.count_dtype and p.name in ("vertex_indices", "vertex_index")]
    if not lists:
        raise MeshFileError(f"{name}: PLY face element has no 'vertex_indices' list")
    return vert, face, [pn.index(k) for k in ("x", "y", "z")], lists[0]


def parse_ply(data: bytes, name: str = "<ply>") -> MeshData:
    """PLY (``ascii``, ``binary_little_endian``, ``binary_big_endian``): the ``vertex``
    element's ``x, y, z`` and the ``face`` element's ``vertex_indices`` (or ``vertex_index``)
    list; other properties and elements are skipped."""
    fmt, elements, start = _ply_header(data, name)
    vert, face, xyz, li = _ply_parts(elements, name)
    if fmt == "ascii":
        verts, polys = _ply_ascii(data[start:], elements, vert, face, xyz, li, name)
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        verts, polys = _ply_binary(data[start:], order, elements, vert, face, xyz, li, name)
    faces, split = _fan(polys)
    return MeshData(verts, faces, "ply", _fan_note(split))


def _ply_ascii(body: bytes, elements, vert, face, xyz, li, name):
    tokens = body.decode("ascii", errors="replace").split()
    pos = 0
    verts = None
    polys: list[list[int]] = []

    def take(k: int) -> list[str]:
        nonlocal pos
        if pos + k > len(tokens):
            raise MeshFileError(f"{name}: PLY data ends early (reading element '{el.name}')")
        out = tokens[pos : pos + k]
        pos += k
        return out

    for el in elements:
        rows: list[list[float]] = []
        for _ in range(el.count):
            rec: list = []
            for p in el.props:
                if p.count_dtype:
                    (cnt,) = take(1)
                    try:
                        rec.append([int(t) for t in take(int(cnt))])
                    except ValueError:
                        raise MeshFileError(f"{name}: bad list in PLY element '{el.name}'") from None
                else:
                    (t,) = take(1)
                    try:
                        rec.append(float(t))
                    except ValueError:
                        raise MeshFileError(f"{name}: bad number '{t}' in PLY element '{el.name}'") from None
            rows.append(rec)
        if el is vert:
            verts = np.array([[r[i] for i in xyz] for r in rows], dtype=float).reshape(-1, 3)
        elif el is face:
            polys = [r[li] for r in rows]
    return verts, _check_polys(polys, name)


def _check_polys(polys: list[list[int]], name: str) -> list[list[int]]:
    for k, p in enumerate(polys):
        if len(p) < 3:
            raise MeshFileError(f"{name}: PLY face {k} has {len(p)} vertices (need at least 3)")
    return polys


def _ply_binary(body: bytes, bo: str, elements, vert, face, xyz, li, name):
    pos = 0
    verts = None
    polys: list[list[int]] = []
    for el in elements:
        if not any(p.count_dtype for p in el.props):
            dt = np.dtype([(f"p{i}", bo + p.dtype) for i, p in enumerate(el.props)])
            if pos + dt.itemsize * el.count > len(body):
                raise MeshFileError(f"{name}: PLY data ends early (reading element '{el.name}')")
            arr = np.frombuffer(body, dtype=dt, count=el.count, offset=pos)
            pos += dt.itemsize * el.count
            if el is vert:
                verts = np.stack([arr[f"p{i}"].astype(float) for i in xyz], axis=1)
            continue
        rows, pos = _ply_binary_lists(body, pos, bo, el, name)
        if el is vert:
            verts = np.array([[r[i] for i in xyz] for r in rows], dtype=float).reshape(-1, 3)
        elif el is face:
            polys = [r[li] for r in rows]
    if verts is None:
        verts = np.zeros((0, 3))
    return verts, _check_polys(polys, name)


def _ply_binary_lists(body: bytes, pos: int, bo: str, el: _Element, name: str):
    """Records of an element with list properties.

    Fast path: guess that every list has the length found in the first record, read all
    records as one structured array and accept the result if every stored count matches
    the guess (then every record was read at its true offset). Otherwise one at a time.
    """
    fast = _ply_binary_lists_uniform(body, pos, bo, el)
    if fast is not None:
        return fast
    rows = []
    try:
        for _ in range(el.count):
            rec: list = []
            for p in el.props:
                if p.count_dtype:
                    cnt = int(np.frombuffer(body, dtype=bo + p.count_dtype, count=1, offset=pos)[0])
                    pos += np.dtype(p.count_dtype).itemsize
                    rec.append(np.frombuffer(body, dtype=bo + p.dtype, count=cnt, offset=pos).astype(np.int64).tolist())
                    pos += cnt * np.dtype(p.dtype).itemsize
                else:
                    rec.append(float(np.frombuffer(body, dtype=bo + p.dtype, count=1, offset=pos)[0]))
                    pos += np.dtype(p.dtype).itemsize
            rows.append(rec)
    except ValueError:
        raise MeshFileError(f"{name}: PLY data ends early (reading element '{el.name}')") from None
    return rows, pos


def _ply_binary_lists_uniform(body: bytes, pos: int, bo: str, el: _Element):
    if el.count == 0:
        return [], pos
    lengths: list[int] = []
    off = pos
    try:
        for p in el.props:  # lengths of the lists in the first record
            if p.count_dtype:
                cnt = int(np.frombuffer(body, dtype=bo + p.count_dtype, count=1, offset=off)[0])
                lengths.append(cnt)
                off += np.dtype(p.count_dtype).itemsize + cnt * np.dtype(p.dtype).itemsize
            else:
                off += np.dtype(p.dtype).itemsize
    except ValueError:
        return None
    fields, it = [], iter(lengths)
    for i, p in enumerate(el.props):
        if p.count_dtype:
            fields += [(f"n{i}", bo + p.count_dtype), (f"p{i}", bo + p.dtype, (next(it),))]
        else:
            fields.append((f"p{i}", bo + p.dtype))
    dt = np.dtype(fields)
    if pos + dt.itemsize * el.count > len(body):
        return None
    arr = np.frombuffer(body, dtype=dt, count=el.count, offset=pos)
    it = iter(lengths)
    for i, p in enumerate(el.props):
        if p.count_dtype and not np.all(arr[f"n{i}"] == next(it)):
            return None
    cols = [arr[f"p{i}"].astype(np.int64).tolist() if p.count_dtype else arr[f"p{i}"].astype(float).tolist()
            for i, p in enumerate(el.props)]  # fmt: skip
    return [list(r) for r in zip(*cols)], pos + dt.itemsize * el.count


def write_ply(path: str | Path, vertices, faces, binary: bool = True) -> None:
    """Write vertices (double) and triangles (uchar count, int indices) as PLY."""
    v = np.asarray(vertices, dtype=float)
    f = np.asarray(faces, dtype=np.int64)
    fmt = "binary_little_endian" if binary else "ascii"
    header = (
        f"ply\nformat {fmt} 1.0\ncomment written by stereopose_mc\nelement vertex {len(v)}\n"
        "property double x\nproperty double y\nproperty double z\n"
        f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    if binary:
        rec = np.zeros(len(f), dtype=np.dtype([("n", "u1"), ("i", "<i4", 3)]))
        rec["n"], rec["i"] = 3, f
        Path(path).write_bytes(header.encode() + v.astype("<f8").tobytes() + rec.tobytes())
    else:
        body = [f"{x!r} {y!r} {z!r}" for x, y, z in v.tolist()] + [f"3 {a} {b} {c}" for a, b, c in f.tolist()]
        Path(path).write_text(header + "\n".join(body) + "\n")
