"""Test surfaces meshed with their own normals (objects.surface_mesh, mesh.heightmap_to_mesh): the
PLY carries them, Mitsuba loads them, walls keep flat triangles, and the renderer's beam then sees
the surface's normal (an independent quadrature of Eq. 5 on a saddle), which flat triangles sampled
at the pixel centres do not."""

from __future__ import annotations

import numpy as np
import pytest

from elo_mitsuba.errors import EloInputError
from elo_mitsuba.mesh import heightmap_to_mesh, ply_header, write_mesh
from elo_mitsuba.objects.surface_mesh import surface_mesh, surface_normals


def test_normals_written_and_loaded(mi, tmp_path):
    """The vertex normals reach Mitsuba as written; without them the PLY has none."""
    mesh = surface_mesh(lambda x, y: 0.1 * np.sin(x) * np.cos(0.5 * y), 0.25, 4.0)
    write_mesh(mesh, tmp_path / "s.ply")
    write_mesh(surface_mesh(lambda x, y: 0.1 * np.sin(x), 0.25, 4.0, smooth=False), tmp_path / "f.ply")
    smooth = mi.load_dict({"type": "ply", "filename": str(tmp_path / "s.ply"), "face_normals": False})
    flat = mi.load_dict({"type": "ply", "filename": str(tmp_path / "f.ply"), "face_normals": True})
    assert smooth.has_vertex_normals() and not flat.has_vertex_normals()
    got = np.array(smooth.vertex_normals_buffer(), float).reshape(-1, 3)
    np.testing.assert_allclose(got, mesh.metadata["vertex_normals"], atol=1e-6)
    assert ply_header(tmp_path / "s.ply")["vertices"] == len(mesh.vertices)


def test_walls_keep_flat_triangles():
    """A cliff's cells get vertices of their own with their triangle's normal; the relief either side
    keeps the surface's normals (here: the plane's, up)."""
    def height(x, y):
        return np.where(x > 0.1, 0.5, 0.0)

    mesh = surface_mesh(height, 0.5, 4.0, part=lambda x, y: x > 0.1)
    vn = mesh.metadata["vertex_normals"]
    walls = vn[:, 2] < 0.999
    assert walls.sum() == 42  # 7 wall cells (one column), 2 triangles, 3 vertices each
    tri = mesh.vertices[mesh.faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    fn /= np.linalg.norm(fn, axis=1, keepdims=True)
    np.testing.assert_allclose(vn[mesh.faces], np.repeat(fn[:, None], 3, axis=1), atol=1e-12)  # every face: its own
    np.testing.assert_allclose(surface_normals(height, np.array([1.0]), np.array([0.0]))[0], [0, 0, 1])


@pytest.mark.parametrize("kw, match", [
    (dict(normals=np.zeros((3, 4, 3))), "unit vectors"),
    (dict(normals=np.ones((3, 3, 3))), "height map needs"),
    (dict(normals="up"), "height map needs"),
    (dict(flat_cells=np.zeros((2, 3), bool)), "only with vertex normals"),
    (dict(normals=np.dstack([np.zeros((3, 4))] * 2 + [np.ones((3, 4))]), step=2), "only with step 1"),
    (dict(normals=np.dstack([np.zeros((3, 4))] * 2 + [np.ones((3, 4))]), flat_cells=np.zeros((3, 3))), "cells"),
])
def test_bad_normals_refused(kw, match):
    with pytest.raises(EloInputError, match=match):
        heightmap_to_mesh(np.zeros((3, 4)), 1.0, **kw)


def test_renderer_sees_the_surface_normal(mi, tmp_path):
    """A saddle Z = c x y, whose cross curvature c is what flat triangles sampled at the cells'
    diagonals get wrong (by about half the pitch times c in the slope): the renderer's 1st event
    (single-ray beam) at every pixel against Eq. 5 by quadrature at the surface's own point and
    normal (analysis.first_event, no Mitsuba). Measured: with the surface's normals 2.7e-4 RMS, at
    most 4.5e-4 (the 24-triangle discs against the round ones: the flat plate shows the same
    2.6e-4); flat triangles 5.1e-3 RMS, 1.1e-2 at most."""
    import elo_mitsuba as em
    from elo_mitsuba.analysis.first_event import disc_integral
    from elo_mitsuba.analysis.scan_geometry import ScanGeometry
    from elo_mitsuba.constants import DETECTOR_NAMES
    from elo_mitsuba.grid import pixel_coordinates
    from elo_mitsuba.scene_files import write_object_scene

    c, res, field = 0.05, 24, 20.0

    def height(x, y):
        return c * x * y

    rms = {}
    for smooth in (True, False):
        mesh = surface_mesh(height, field / res / 3, field + 2.0, smooth=smooth)
        scene = write_object_scene(tmp_path, f"saddle_{smooth}", mesh)
        r = em.load_scene(str(scene), res=res, field=field, layout="zeta25", fwhm=0,
                          projection="orthographic").render(quality="default", events=1, progress=False)
        geo = ScanGeometry.from_metadata(r.metadata, (res, res))
        xx, yy = pixel_coordinates((res, res), field)
        rel = []
        for n in DETECTOR_NAMES:
            d = geo.detectors[n]
            ref = np.array([disc_integral([x, y, height(x, y)], [0, 0, -1], [-c * y, -c * x, 1], d.center, d.normal,
                                          d.radius, geo.material, n_r=8, n_phi=32)
                            for x, y in zip(xx.ravel(), yy.ravel())]).reshape(res, res)
            rel.append(r.channels[n] / ref - 1)
        rel = np.array(rel)
        rms[smooth] = float(np.sqrt(np.mean(rel ** 2)))
        if smooth:
            assert np.abs(rel).max() < 1e-3, np.abs(rel).max()
    assert rms[False] > 3e-3, rms  # what the test is about: flat triangles see another normal


def test_normals_that_no_longer_fit_the_vertices_are_refused(tmp_path):
    """A mesh whose vertices changed after it was given normals: refused in one line, nothing written."""
    mesh = surface_mesh(lambda x, y: 0.0 * x, 0.5, 2.0)
    mesh.metadata["vertex_normals"] = mesh.metadata["vertex_normals"][:-1]
    with pytest.raises(EloInputError, match="vertex normals are"):
        write_mesh(mesh, tmp_path / "m.ply")
    assert not (tmp_path / "m.ply").exists()
