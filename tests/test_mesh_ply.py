"""The PLY files the package writes, and the ones Mitsuba would read wrongly (mesh.EXACT_SIGNED_INDICES)."""

import numpy as np
import pytest
import trimesh

from elo_mitsuba.errors import EloInputError
from elo_mitsuba.mesh import (EXACT_SIGNED_INDICES, check_ply_indices, heightmap_to_mesh, ply_header, ply_index_range,
                              write_mesh)


def _mitsuba_faces(path):
    import mitsuba as mi

    import elo_mitsuba as em

    em.ensure_variant()
    shape = mi.load_dict({"type": "ply", "filename": str(path)})
    params = mi.traverse(shape)
    return (np.array(params["vertex_positions"]).reshape(-1, 3), np.array(params["faces"]).reshape(-1, 3))


def _header_only(path, vertices, index_type):
    path.write_bytes(("ply\nformat binary_little_endian 1.0\n"
                      f"element vertex {vertices}\nproperty float x\nproperty float y\nproperty float z\n"
                      f"element face 1\nproperty list uchar {index_type} vertex_indices\nend_header\n").encode())
    return path


def test_write_mesh_round_trips_through_numpy_trimesh_and_mitsuba(tmp_path):
    rng = np.random.default_rng(1)
    mesh = heightmap_to_mesh(rng.normal(0, 0.1, (7, 9)), 0.5)
    p = write_mesh(mesh, tmp_path / "m.ply")
    h = ply_header(p)
    assert (h["format"], h["vertices"], h["faces"], h["index_type"]) == (
        "binary_little_endian", len(mesh.vertices), len(mesh.faces), "uint")
    raw = p.read_bytes()
    body = raw[raw.index(b"end_header\n") + len(b"end_header\n"):]
    nv = len(mesh.vertices)
    v = np.frombuffer(body[:12 * nv], "<f4").reshape(-1, 3)
    rows = np.frombuffer(body[12 * nv:], dtype=[("n", "u1"), ("i", "<u4", (3,))])
    assert np.all(rows["n"] == 3) and len(body) == 12 * nv + 13 * len(mesh.faces)
    np.testing.assert_array_equal(v, mesh.vertices.astype(np.float32))
    np.testing.assert_array_equal(rows["i"], mesh.faces)
    back = trimesh.load(p, process=False)
    np.testing.assert_array_equal(back.faces, mesh.faces)
    mv, mf = _mitsuba_faces(p)
    np.testing.assert_array_equal(mv, v)
    np.testing.assert_array_equal(mf, mesh.faces)


def test_write_mesh_refuses_indices_outside_the_vertices(tmp_path):
    bad = trimesh.Trimesh(vertices=np.zeros((3, 3)), faces=[[0, 1, 3]], process=False)
    with pytest.raises(EloInputError, match="face indices outside 0..2"):
        write_mesh(bad, tmp_path / "bad.ply")
    assert not (tmp_path / "bad.ply").exists()


@pytest.mark.parametrize("vertices,index_type,refused", [
    (EXACT_SIGNED_INDICES + 1, "int", True), (EXACT_SIGNED_INDICES + 1, "int32", True),
    (EXACT_SIGNED_INDICES + 1, "uint", False), (EXACT_SIGNED_INDICES + 1, "uint32", False),
    (EXACT_SIGNED_INDICES, "int", False)])
def test_check_ply_indices_refuses_signed_indices_beyond_float32(tmp_path, vertices, index_type, refused):
    p = _header_only(tmp_path / "h.ply", vertices, index_type)
    if refused:
        with pytest.raises(EloInputError, match=rf"h\.ply: {vertices} vertices with face indices of type "
                                                rf"'{index_type}'.*'uint'"):
            check_ply_indices(p)
    else:
        check_ply_indices(p)


def test_a_scene_with_such_a_mesh_is_refused_before_mitsuba_loads_it(tmp_path):
    import elo_mitsuba as em
    from elo_mitsuba.scene_files import write_scene

    _header_only(tmp_path / "big.ply", EXACT_SIGNED_INDICES + 5, "int")
    xml = write_scene(tmp_path / "big.xml", tmp_path / "big.ply")
    with pytest.raises(EloInputError, match=r"big\.xml: mesh file .*big\.ply: 16777221 vertices .*\(2\^24\)"):
        em.load_scene(xml, res=4)


@pytest.mark.slow
def test_mitsuba_reads_signed_indices_above_2_24_wrongly_and_unsigned_ones_exactly(tmp_path):
    """Why EXACT_SIGNED_INDICES exists: the same triangles, stored with 'int' and with 'uint' indices
    above 2^24. If the 'int' half fails, Mitsuba now reads signed indices exactly and the refusal
    (check_ply_indices) can go."""
    from trimesh.exchange.ply import export_ply

    n = EXACT_SIGNED_INDICES + 8
    vertices = np.zeros((n, 3), np.float32)
    vertices[:, 0] = np.arange(n) % 4096 * 1e-3
    vertices[:, 1] = np.arange(n) // 4096 * 1e-3
    high = EXACT_SIGNED_INDICES + np.array([[1, 3, 5], [0, 2, 7]])
    faces = np.concatenate([[[0, 1, 4096]], high])
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    _, f_uint = _mitsuba_faces(write_mesh(mesh, tmp_path / "uint.ply"))
    np.testing.assert_array_equal(f_uint, faces)
    (tmp_path / "int.ply").write_bytes(export_ply(mesh, encoding="binary", vertex_normal=False,
                                                  include_attributes=False))
    assert ply_header(tmp_path / "int.ply")["index_type"] == "int"
    _, f_int = _mitsuba_faces(tmp_path / "int.ply")
    assert np.any(f_int[1:] != faces[1:]) and np.all(f_int[:1] == faces[:1])


def test_ply_index_range_reads_the_indices_trimesh_reads(tmp_path):
    """The face indices are read from the file, before Mitsuba loads it (check_ply_indices), in the
    layouts users' tools write: ASCII and binary from trimesh (with vertex normals), big-endian
    with a face property after the list; layouts it cannot read (quads, a truncated file) give None,
    not a wrong range."""
    m = trimesh.creation.icosphere(2)
    m.faces = m.faces[:, ::-1][::3]                               # not sorted: the range is read, not assumed
    want = (int(m.faces.min()), int(m.faces.max()))
    for enc in ("ascii", "binary"):
        p = tmp_path / f"{enc}.ply"
        p.write_bytes(trimesh.exchange.ply.export_ply(m, encoding=enc, vertex_normal=True))
        assert ply_index_range(p) == want, enc
    v = np.asarray(m.vertices, ">f4")
    rows = np.empty(len(m.faces), dtype=[("n", "u1"), ("i", ">i4", (3,)), ("flag", "u1")])
    rows["n"], rows["i"], rows["flag"] = 3, m.faces, 1
    head = (f"ply\nformat binary_big_endian 1.0\nelement vertex {len(v)}\nproperty float x\nproperty float y\n"
            f"property float z\nelement face {len(rows)}\nproperty list uchar int vertex_indices\n"
            "property uchar flag\nend_header\n").encode()
    (tmp_path / "be.ply").write_bytes(head + v.tobytes() + rows.tobytes())
    assert ply_index_range(tmp_path / "be.ply") == want
    (tmp_path / "cut.ply").write_bytes((head + v.tobytes() + rows.tobytes())[:-20])
    assert ply_index_range(tmp_path / "cut.ply") is None
    (tmp_path / "quad.ply").write_text("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
                                       "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
                                       "end_header\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 9\n")
    assert ply_index_range(tmp_path / "quad.ply") is None


def test_a_face_naming_a_missing_vertex_is_refused_before_loading(tmp_path):
    """Mitsuba reads past the vertex buffer for such a face while building the scene: the surface
    area came out 0.44, 53.3, 0.5 or inf from run to run for index 7 of 3 vertices, and an index
    of 1e8 ended the process with a segmentation fault."""
    p = tmp_path / "far.ply"
    p.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                 "element face 2\nproperty list uchar int vertex_indices\nend_header\n0 0 1\n1 0 1\n0 1 1\n"
                 "3 0 1 2\n3 0 1 100000000\n")
    with pytest.raises(EloInputError, match="names vertex 100000000, but the file has 3"):
        check_ply_indices(p)
