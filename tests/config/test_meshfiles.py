"""Mesh file readers: files written here by independent code (text by hand, binary with
``struct``), round trips through the package's writers, and errors."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from stereopose_mc.core import mesh as M
from stereopose_mc.config.meshfiles import MeshFileError, read_mesh, write_obj, write_ply, write_stl

# unit cube [0, 1]^3 as 8 vertices and 6 outward quads (counter-clockwise seen from outside)
CUBE_V = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)]
CUBE_Q = [(0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (2, 3, 7, 6), (1, 2, 6, 5), (0, 4, 7, 3)]
CUBE_T = [(q[0], q[1], q[2]) for q in CUBE_Q] + [(q[0], q[2], q[3]) for q in CUBE_Q]


def assert_unit_cube(mesh, scale=1.0):
    assert M.check_mesh(mesh.vertices, mesh.faces).problems == []
    p = M.mass_properties(mesh.vertices * scale, mesh.faces, 1.0)
    assert p.volume == pytest.approx(scale**3, rel=1e-6)
    np.testing.assert_allclose(p.centroid, [scale / 2] * 3, rtol=1e-6)
    np.testing.assert_allclose(p.inertia, np.eye(3) * scale**5 / 6, atol=1e-6 * scale**5)


def test_obj_with_quads_comments_slashes_and_negative_indices(tmp_path):
    text = "# a cube\nmtllib x.mtl\no cube\n"
    text += "".join(f"v {x} {y} {z}\n" for x, y, z in CUBE_V)
    text += "vt 0 0\nvn 0 0 1\ns off\n"
    for k, q in enumerate(CUBE_Q):
        if k == 0:
            text += "f " + " ".join(f"{i + 1}/1/1" for i in q) + "\n"
        elif k == 1:
            text += "f " + " ".join(f"{i + 1}//1" for i in q) + "  # trailing comment\n"
        elif k == 2:
            text += "f " + " ".join(str(i - 8) for i in q) + "\n"  # relative: -8 is the first vertex
        else:
            text += "f " + " ".join(str(i + 1) for i in q) + "\n"
    path = tmp_path / "cube.OBJ"
    path.write_text(text)
    mesh = read_mesh(path)
    assert mesh.format == "obj"
    assert mesh.vertices.shape == (8, 3) and mesh.faces.shape == (12, 3)
    assert mesh.notes == ["split 6 polygon(s) with more than 3 corners into triangles (fan)"]
    assert_unit_cube(mesh)


def _binary_stl(tris, header=b"solid but actually binary"):
    out = header.ljust(80, b"\0") + struct.pack("<I", len(tris))
    for t in tris:
        out += struct.pack("<3f", 0, 0, 0) + b"".join(struct.pack("<3f", *CUBE_V[i]) for i in t) + struct.pack("<H", 0)
    return out


def test_binary_stl_even_with_a_solid_header(tmp_path):
    path = tmp_path / "cube.stl"
    path.write_bytes(_binary_stl(CUBE_T))
    mesh = read_mesh(path)
    assert mesh.vertices.shape == (8, 3) and mesh.faces.shape == (12, 3)
    assert_unit_cube(mesh)


def test_ascii_stl(tmp_path):
    lines = ["solid cube"]
    for t in CUBE_T:
        lines += ["facet normal 0 0 0", " outer loop"]
        lines += [f"  vertex {CUBE_V[i][0]:.6e} {CUBE_V[i][1]:.6e} {CUBE_V[i][2]:.6e}" for i in t]
        lines += [" endloop", "endfacet"]
    lines.append("endsolid cube")
    path = tmp_path / "cube.stl"
    path.write_text("\n".join(lines) + "\n")
    mesh = read_mesh(path)
    assert mesh.faces.shape == (12, 3)
    assert_unit_cube(mesh)


def test_ascii_ply_with_extra_properties_quads_and_elements(tmp_path):
    header = (
        "ply\nformat ascii 1.0\ncomment made by hand\nelement vertex 8\nproperty float x\nproperty float y\n"
        "property float z\nproperty uchar red\nelement face 6\nproperty uchar flags\n"
        "property list uchar int vertex_indices\nelement edge 1\nproperty int vertex1\nproperty int vertex2\n"
        "end_header\n"
    )
    body = "".join(f"{x} {y} {z} 255\n" for x, y, z in CUBE_V)
    body += "".join(f"7 4 {q[0]} {q[1]} {q[2]} {q[3]}\n" for q in CUBE_Q)
    body += "0 1\n"
    path = tmp_path / "cube.ply"
    path.write_text(header + body)
    mesh = read_mesh(path)
    assert mesh.faces.shape == (12, 3)
    assert_unit_cube(mesh)


@pytest.mark.parametrize("order", ["<", ">"])
@pytest.mark.parametrize("quads", [False, True])
def test_binary_ply_both_byte_orders(tmp_path, order, quads):
    fmt = "binary_little_endian" if order == "<" else "binary_big_endian"
    polys = CUBE_Q if quads else CUBE_T
    header = (
        f"ply\nformat {fmt} 1.0\nelement vertex 8\nproperty double x\nproperty double y\nproperty double z\n"
        "property float confidence\nelement face {n}\nproperty list uchar int vertex_indices\nproperty short tag\n"
        "end_header\n"
    ).replace("{n}", str(len(polys)))
    body = b"".join(struct.pack(order + "dddf", *v, 0.5) for v in CUBE_V)
    body += b"".join(struct.pack(order + "B" + "i" * len(p) + "h", len(p), *p, -1) for p in polys)
    path = tmp_path / "cube.ply"
    path.write_bytes(header.encode() + body)
    mesh = read_mesh(path)
    assert mesh.faces.shape == (12, 3)
    assert_unit_cube(mesh)


def test_binary_ply_mixed_polygon_sizes(tmp_path):
    # first face a triangle, later quads: the uniform fast path must not be taken
    polys = [CUBE_T[0], CUBE_T[6]] + CUBE_Q[1:]
    header = (
        "ply\nformat binary_little_endian 1.0\nelement vertex 8\nproperty float x\nproperty float y\n"
        f"property float z\nelement face {len(polys)}\nproperty list uchar uint vertex_index\nend_header\n"
    )
    body = b"".join(struct.pack("<fff", *v) for v in CUBE_V)
    body += b"".join(struct.pack("<B" + "I" * len(p), len(p), *p) for p in polys)
    path = tmp_path / "cube.ply"
    path.write_bytes(header.encode() + body)
    mesh = read_mesh(path)
    assert mesh.faces.shape == (12, 3)
    assert_unit_cube(mesh)


@pytest.mark.parametrize(
    "name, write",
    [
        ("m.obj", lambda p, v, f: write_obj(p, v, f, "comment\nsecond line")),
        ("m.stl", lambda p, v, f: write_stl(p, v, f, binary=True)),
        ("m.stl", lambda p, v, f: write_stl(p, v, f, binary=False)),
        ("m.ply", lambda p, v, f: write_ply(p, v, f, binary=True)),
        ("m.ply", lambda p, v, f: write_ply(p, v, f, binary=False)),
    ],
)
def test_round_trip_through_writers(tmp_path, name, write):
    V, F = M.icosphere_mesh(0.37, 2)
    V = V + [1.0, -2.0, 0.5]
    write(tmp_path / name, V, F)
    mesh = read_mesh(tmp_path / name)
    ref = M.mass_properties(V, F)
    p = M.mass_properties(mesh.vertices, mesh.faces)
    rel = 1e-6 if name.endswith(".stl") else 1e-13  # STL stores float32
    assert p.volume == pytest.approx(ref.volume, rel=rel)
    np.testing.assert_allclose(p.inertia, ref.inertia, rtol=10 * rel, atol=10 * rel * ref.inertia.max())
    if not name.endswith(".stl"):
        np.testing.assert_array_equal(mesh.vertices, V)
        np.testing.assert_array_equal(mesh.faces, F)


def test_errors(tmp_path):
    with pytest.raises(MeshFileError, match="file not found"):
        read_mesh(tmp_path / "missing.obj")
    (tmp_path / "m.off").write_text("OFF\n")
    with pytest.raises(MeshFileError, match="unknown mesh format"):
        read_mesh(tmp_path / "m.off")
    (tmp_path / "bad.obj").write_text("v 0 0 0\nv 1 0 0\nf 1 2 3\n")
    with pytest.raises(MeshFileError, match=r"bad\.obj:3: face vertex 3 does not exist"):
        read_mesh(tmp_path / "bad.obj")
    (tmp_path / "bad2.obj").write_text("v 0 0 zero\n")
    with pytest.raises(MeshFileError, match=r"bad2\.obj:1: bad vertex"):
        read_mesh(tmp_path / "bad2.obj")
    (tmp_path / "empty.obj").write_text("# nothing\n")
    with pytest.raises(MeshFileError, match="no triangles"):
        read_mesh(tmp_path / "empty.obj")
    (tmp_path / "bad.stl").write_bytes(b"\x00" * 100)
    with pytest.raises(MeshFileError, match="neither binary STL"):
        read_mesh(tmp_path / "bad.stl")
    (tmp_path / "trunc.stl").write_bytes(_binary_stl(CUBE_T)[:-10])
    with pytest.raises(MeshFileError):
        read_mesh(tmp_path / "trunc.stl")
    (tmp_path / "noface.ply").write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n0\n")
    with pytest.raises(MeshFileError, match="'vertex' and 'face'"):
        read_mesh(tmp_path / "noface.ply")
    (tmp_path / "short.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n"
    )
    with pytest.raises(MeshFileError, match="ends early"):
        read_mesh(tmp_path / "short.ply")
