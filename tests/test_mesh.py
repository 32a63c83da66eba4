"""Height map -> mesh (elo_mitsuba.mesh, `elo-mitsuba mesh`) and the generated objects.

Conventions under test: row 0 of a height map is the +y edge, columns run towards +x, pixel
centres are centred on the z-axis, face normals are [-dZ/dx, -dZ/dy, 1] normalised (Eq. 16).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

from elo_mitsuba.cli import main
from elo_mitsuba.errors import EloInputError
from elo_mitsuba.heightmap import load_heightmap, pixel_centres
from elo_mitsuba.mesh import heightmap_to_mesh, write_mesh
from elo_mitsuba.objects import melt_plate
from elo_mitsuba.objects.corrugated_sheet import corrugated_profile, corrugated_sheet_mesh

REPO_ROOT = Path(__file__).resolve().parents[1]
MESHES = REPO_ROOT / "scenes_xml" / "meshes"


def _grid_lookup(mesh):
    """Map (x, y) rounded to 1e-6 mm -> z of the mesh vertices."""
    return {(round(x, 6), round(y, 6)): z for x, y, z in mesh.vertices}


def _mesh_height_at(mesh, xq, yq):
    """Height of a tensor-grid mesh made by heightmap_to_mesh at points (xq, yq).

    Re-derives the triangulation (diagonal from the -x,-y corner to the +x,+y corner of every
    cell) independently of the implementation, to test what a ray would see.
    """
    xs = np.unique(mesh.vertices[:, 0])
    ys = np.unique(mesh.vertices[:, 1])
    z = {(round(a, 9), round(b, 9)): c for a, b, c in mesh.vertices}
    out = np.empty(len(xq))
    for n, (x, y) in enumerate(zip(xq, yq)):
        j = min(max(np.searchsorted(xs, x, side="right") - 1, 0), len(xs) - 2)
        i = min(max(np.searchsorted(ys, y, side="right") - 1, 0), len(ys) - 2)
        x0, x1, y0, y1 = xs[j], xs[j + 1], ys[i], ys[i + 1]
        u, v = (x - x0) / (x1 - x0), (y - y0) / (y1 - y0)
        z00 = z[(round(x0, 9), round(y0, 9))]
        z10 = z[(round(x1, 9), round(y0, 9))]
        z01 = z[(round(x0, 9), round(y1, 9))]
        z11 = z[(round(x1, 9), round(y1, 9))]
        if u >= v:  # triangle (x0,y0) (x1,y0) (x1,y1)
            out[n] = z00 + u * (z10 - z00) + v * (z11 - z10)
        else:  # triangle (x0,y0) (x1,y1) (x0,y1)
            out[n] = z00 + v * (z01 - z00) + u * (z11 - z01)
    return out


# --- geometry and orientation -------------------------------------------------------------------------
def test_vertices_are_pixel_centres_with_their_heights():
    rng = np.random.default_rng(1)
    h = rng.normal(size=(7, 9))
    mesh = heightmap_to_mesh(h, 0.5)
    assert len(mesh.vertices) == 7 * 9 and len(mesh.faces) == 2 * 6 * 8
    x, y = pixel_centres(h.shape, 0.5)
    assert x[0] == pytest.approx(-2.0) and x[-1] == pytest.approx(2.0)  # centred, +x with column
    assert y[0] == pytest.approx(1.5) and y[-1] == pytest.approx(-1.5)  # row 0 is the +y edge
    lookup = _grid_lookup(mesh)
    for i in range(7):
        for j in range(9):
            assert lookup[(round(x[j], 6), round(y[i], 6))] == pytest.approx(h[i, j], abs=1e-12)


def test_row_zero_is_plus_y_and_column_zero_is_minus_x():
    h = np.zeros((5, 6))
    h[0, :] = 1.0  # only the first row raised
    h[:, 0] += 2.0  # and the first column
    mesh = heightmap_to_mesh(h, 1.0)
    v = mesh.vertices
    assert np.all(v[v[:, 1] == v[:, 1].max(), 2] >= 1.0)
    assert np.all(v[v[:, 0] == v[:, 0].min(), 2] >= 2.0)
    assert np.all(v[(v[:, 1] < v[:, 1].max()) & (v[:, 0] > v[:, 0].min()), 2] == 0.0)


def test_ramp_normals_follow_eq16():
    """Z = a x + b y, rising towards +x and +y: every normal is [-a, -b, 1]/norm."""
    a, b, p = 0.3, 0.7, 0.25
    x, y = pixel_centres((6, 8), p)
    h = a * x[None, :] + b * y[:, None]
    assert h[0, -1] > h[-1, -1] and h[0, -1] > h[0, 0]  # higher at row 0 (+y) and last col (+x)
    mesh = heightmap_to_mesh(h, p)
    expected = np.array([-a, -b, 1.0]) / math.sqrt(a * a + b * b + 1)
    np.testing.assert_allclose(mesh.face_normals, np.broadcast_to(expected, mesh.face_normals.shape), atol=1e-12)
    assert np.all(mesh.face_normals[:, 0] < 0) and np.all(mesh.face_normals[:, 1] < 0)


def test_bumpy_normals_point_up_and_match_finite_differences():
    x, y = pixel_centres((41, 41), 0.1)
    xx, yy = np.meshgrid(x, y)
    h = 0.2 * np.sin(xx) * np.cos(0.5 * yy)
    mesh = heightmap_to_mesh(h, 0.1)
    n = mesh.face_normals
    assert np.all(n[:, 2] > 0)
    c = mesh.triangles_center
    gx = 0.2 * np.cos(c[:, 0]) * np.cos(0.5 * c[:, 1])
    gy = -0.1 * np.sin(c[:, 0]) * np.sin(0.5 * c[:, 1])
    np.testing.assert_allclose(-n[:, 0] / n[:, 2], gx, atol=0.01)
    np.testing.assert_allclose(-n[:, 1] / n[:, 2], gy, atol=0.01)


def test_step_downsamples_and_keeps_extent():
    h = np.arange(11 * 13, dtype=float).reshape(11, 13)
    mesh = heightmap_to_mesh(h, 1.0, step=4)
    xs, ys = np.unique(mesh.vertices[:, 0]), np.unique(mesh.vertices[:, 1])
    np.testing.assert_allclose(xs, [-6, -2, 2, 6])  # columns 0, 4, 8, 12
    np.testing.assert_allclose(ys, [-5, -3, 1, 5])  # rows 10, 8, 4, 0 (y = 5 - row)
    assert set(_grid_lookup(mesh).values()) <= set(h.ravel())


def test_tolerance_drops_flat_lines_and_stays_within_tolerance():
    x, y = pixel_centres((101, 121), 0.1)
    xx, yy = np.meshgrid(x, y)
    h = np.where((np.abs(xx - 1) < 1.5) & (np.abs(yy) < 1.0), 0.05 * np.cos(xx) * np.cos(yy), 0.0)
    full = heightmap_to_mesh(h, 0.1)
    tol = 1e-4
    small = heightmap_to_mesh(h, 0.1, tolerance_mm=tol)
    assert len(small.vertices) < 0.3 * len(full.vertices)
    rebuilt = _mesh_height_at(small, xx.ravel(), yy.ravel())
    assert np.max(np.abs(rebuilt - h.ravel())) <= 2 * tol + 1e-12
    assert small.bounds == pytest.approx(full.bounds)


def test_base_makes_a_watertight_solid_with_outward_normals():
    rng = np.random.default_rng(3)
    h = rng.uniform(0, 0.1, size=(6, 8))
    mesh = heightmap_to_mesh(h, 0.5, base_mm=-1.0)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0  # outward normals
    assert mesh.volume == pytest.approx((3.5 * 2.5) * (1.0 + h.mean()), rel=0.05)
    top = heightmap_to_mesh(h, 0.5)
    np.testing.assert_array_equal(mesh.vertices[: len(top.vertices)], top.vertices)


def test_write_mesh_roundtrip_and_refuses_to_overwrite(tmp_path):
    h = np.random.default_rng(4).normal(size=(5, 5))
    mesh = heightmap_to_mesh(h, 0.2)
    out = write_mesh(mesh, tmp_path / "m.ply")
    back = trimesh.load(out, process=False)
    np.testing.assert_allclose(back.vertices, mesh.vertices, atol=1e-6)
    np.testing.assert_array_equal(back.faces, mesh.faces)
    assert b"binary_little_endian" in out.read_bytes()[:200]
    assert b"nx" not in out.read_bytes()[:400]  # no vertex normals: flat shading is the scene's job
    with pytest.raises(EloInputError, match="exists; pass --overwrite"):
        write_mesh(mesh, out)
    write_mesh(mesh, out, overwrite=True)


# --- bad inputs --------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "height, pixel, match",
    [
        (np.zeros((3, 4, 5)), 1.0, r"shape \(3, 4, 5\).*2-D"),
        (np.zeros(7), 1.0, r"shape \(7,\).*2-D"),
        (np.array([[0.0, np.nan], [0.0, 0.0]]), 1.0, r"non-finite.*row 0, column 1"),
        (np.array([[0.0, np.inf], [0.0, 0.0]]), 1.0, "non-finite"),
        (np.zeros((1, 5)), 1.0, "at least 2 rows"),
        (np.array([["a", "b"], ["c", "d"]]), 1.0, "dtype"),
        (np.zeros((3, 3)), 0.0, "pixel size"),
        (np.zeros((3, 3)), -0.1, "pixel size"),
        (np.zeros((3, 3)), float("nan"), "pixel size"),
    ],
)
def test_bad_heightmaps_raise_one_line_errors(height, pixel, match):
    with pytest.raises(EloInputError, match=match) as err:
        heightmap_to_mesh(height, pixel)
    assert "\n" not in str(err.value)


def test_bad_step_tolerance_base():
    h = np.zeros((4, 4))
    with pytest.raises(EloInputError, match="step"):
        heightmap_to_mesh(h, 1.0, step=0)
    with pytest.raises(EloInputError, match="tolerance"):
        heightmap_to_mesh(h, 1.0, tolerance_mm=-1)
    with pytest.raises(EloInputError, match="below the lowest height"):
        heightmap_to_mesh(h, 1.0, base_mm=0.0)


def test_load_heightmap_formats_and_units(tmp_path):
    import tifffile

    h = np.random.default_rng(5).uniform(-0.05, 0.05, size=(6, 7))
    np.save(tmp_path / "h.npy", h)
    tifffile.imwrite(tmp_path / "h.tif", h.astype(np.float32))
    np.savetxt(tmp_path / "h.csv", h * 1000, delimiter=",")
    np.testing.assert_allclose(load_heightmap(tmp_path / "h.npy"), h)
    np.testing.assert_allclose(load_heightmap(tmp_path / "h.tif"), h, atol=1e-7)
    np.testing.assert_allclose(load_heightmap(tmp_path / "h.csv", units="um"), h, atol=1e-12)
    with pytest.raises(EloInputError, match="does not exist"):
        load_heightmap(tmp_path / "missing.npy")
    (tmp_path / "h.png").write_bytes(b"x")
    with pytest.raises(EloInputError, match=r"extension '\.png'.*\.npy, \.tif"):
        load_heightmap(tmp_path / "h.png")
    (tmp_path / "bad.npy").write_bytes(b"not numpy")
    with pytest.raises(EloInputError, match="could not be read"):
        load_heightmap(tmp_path / "bad.npy")
    with pytest.raises(EloInputError, match="units"):
        load_heightmap(tmp_path / "h.npy", units="inch")


# --- the command line -----------------------------------------------------------------------------------
def test_cli_mesh_writes_ply_and_scene(tmp_path, capsys):
    x, y = pixel_centres((20, 30), 0.1)
    h_um = 10.0 * x[None, :] + 0.0 * y[:, None]  # rises towards +x, in micrometres
    np.save(tmp_path / "h.npy", h_um)
    rc = main(["mesh", str(tmp_path / "h.npy"), "-o", str(tmp_path / "m.ply"), "--pixel-size", "0.1",
               "--units", "um", "--scene", str(tmp_path / "s.xml"), "--material", "316L"])
    assert rc == 0
    out = capsys.readouterr().out
    assert "600 vertices" in out and "1102 triangles" in out
    mesh = trimesh.load(tmp_path / "m.ply", process=False)
    assert mesh.bounds[0][0] == pytest.approx(-1.45) and mesh.bounds[1][1] == pytest.approx(0.95)
    np.testing.assert_allclose(mesh.face_normals[:, 0], -0.01 / math.sqrt(1 + 1e-4), atol=1e-6)
    text = (tmp_path / "s.xml").read_text()
    assert 'value="m.ply"' in text and 'value="316L"' in text and "$layout.xml" in text


@pytest.mark.parametrize(
    "setup, argv, message",
    [
        (None, ["missing.npy", "-o", "m.ply", "--pixel-size", "1"], "does not exist"),
        ("h.txt", ["h.txt", "-o", "m.ply", "--pixel-size", "1"], "extension '.txt'"),
        ("nan.npy", ["nan.npy", "-o", "m.ply", "--pixel-size", "1"], "non-finite"),
        ("3d.npy", ["3d.npy", "-o", "m.ply", "--pixel-size", "1"], "2-D array"),
        ("h.npy", ["h.npy", "-o", "m.ply", "--pixel-size", "0"], "--pixel-size"),
        ("h.npy", ["h.npy", "-o", "m.ply", "--pixel-size", "-2"], "--pixel-size"),
        ("h.npy", ["h.npy", "-o", "exists.ply", "--pixel-size", "1"], "exists; pass --overwrite"),
        ("h.npy", ["h.npy", "-o", "m.stl", "--pixel-size", "1"], "must end in .ply"),
        ("h.npy", ["h.npy", "-o", "m.ply", "--pixel-size", "1", "--material", "Cu"], "give --scene"),
        ("h.npy", ["h.npy", "-o", "m.ply", "--pixel-size", "1", "--scene", "s.xml", "--material", "Xx"],
         "unknown material"),
    ],
)
def test_cli_mesh_errors_are_one_line(tmp_path, capsys, monkeypatch, setup, argv, message):
    monkeypatch.chdir(tmp_path)
    np.save("h.npy", np.zeros((3, 3)))
    np.save("nan.npy", np.array([[0.0, np.nan], [1.0, 2.0]]))
    np.save("3d.npy", np.zeros((2, 3, 4)))
    Path("h.txt").write_text("0,0\n0,0\n")
    Path("exists.ply").write_text("x")
    rc = main(["mesh", *argv])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.startswith("elo-mitsuba: error: ") and message in err
    assert err.count("\n") == 1  # one line, no traceback
    assert not Path("m.ply").exists()


# --- the corrugated sheet (Sec. 4.2) ---------------------------------------------------------------------
def test_corrugated_profile_has_1mm_45deg_flanks_and_zero_mean():
    x, z = corrugated_profile()
    dx, dz = np.diff(x), np.diff(z)
    np.testing.assert_allclose(np.hypot(dx, dz), 1.0, atol=1e-5)  # 1 mm flanks
    np.testing.assert_array_equal(np.abs(dz), dx)  # 45 degrees, exactly
    np.testing.assert_array_equal(x.astype(np.float32), x)  # exact in a float32 PLY
    np.testing.assert_array_equal(z.astype(np.float32), z)
    assert np.all(dz[0::2] > 0) and np.all(dz[1::2] < 0)  # alternating rise / fall
    assert x[0] < -45 and x[-1] > 45  # whole 80 mm field plus a margin
    k = np.searchsorted(x, 0.0)  # x = 0 in the middle of a rising flank
    assert dz[k - 1] > 0 and (x[k - 1] + x[k]) / 2 == pytest.approx(0.0, abs=1e-12)
    mean = np.sum(0.5 * (z[1:] + z[:-1]) * np.diff(x)) / (x[-1] - x[0])  # trapezoid rule, exact here
    assert mean == pytest.approx(0.0, abs=1e-12)


def test_corrugated_mesh_normals_are_exact():
    mesh = corrugated_sheet_mesh()
    n = mesh.face_normals
    s = 1 / math.sqrt(2)
    rising = np.isclose(n[:, 0], -s, atol=1e-12)
    falling = np.isclose(n[:, 0], s, atol=1e-12)
    assert np.all(rising | falling) and rising.sum() == falling.sum() + 2  # 65 rising, 64 falling
    np.testing.assert_allclose(n[:, 1], 0.0, atol=1e-12)
    np.testing.assert_allclose(n[:, 2], s, atol=1e-12)
    assert len(mesh.faces) == 2 * 129


def test_shipped_corrugated_ply_matches_the_generator():
    shipped = trimesh.load(MESHES / "corrugated_sheet.ply", process=False)
    mesh = corrugated_sheet_mesh()
    np.testing.assert_array_equal(shipped.faces, mesh.faces)
    np.testing.assert_allclose(shipped.vertices, mesh.vertices, atol=1e-5)  # float32 in the PLY
    s = 1 / math.sqrt(2)
    # exact: dx = dz also in the float32 PLY (flank extents are multiples of 2^-17 mm)
    np.testing.assert_allclose(np.abs(shipped.face_normals), np.broadcast_to([s, 0, s], (258, 3)), atol=1e-12)
    edges = shipped.vertices[1:130] - shipped.vertices[0:129]  # the y = -45 profile
    np.testing.assert_allclose(np.linalg.norm(edges, axis=1), 1.0, atol=1e-5)


# --- the synthetic melt plate ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def melt_map():
    return melt_plate.melt_plate_heightmap()


def test_melt_plate_relief_is_tens_of_micrometres(melt_map):
    h, p = melt_map
    assert h.shape == (500, 500) and h.dtype == np.float32 and p == pytest.approx(0.2)
    stats = melt_plate.relief_statistics(h)
    assert 0.02 < stats["peak_to_valley"] < 0.3  # mm: tens to a few hundred micrometres
    assert 0.01 < stats["rms_in_squares"] < 0.1
    assert 0.05 < stats["max_slope"] < 0.5  # bulging edges, no cliffs
    # 3 x 3 squares: 5 of 15 mm, 4 of 10 mm
    area = 5 * 15**2 + 4 * 10**2
    assert stats["fraction_in_squares"] == pytest.approx(area / 100**2, rel=0.05)
    # blank plate exactly flat (beyond the 2 mm tails of the edge fade), relief in every square
    x, y = pixel_centres(h.shape, p)
    assert np.all(h[~melt_plate.in_squares(x[None, :], y[:, None], inset_mm=-2.0)] == 0)
    assert np.mean(np.abs(h[melt_plate.in_squares(x[None, :], y[:, None], inset_mm=0.3)]) > 1e-3) > 0.9
    assert np.all(h[(np.abs(x)[None, :] > 35) | (np.abs(y)[:, None] > 35)] == 0)  # inside the field


def test_melt_plate_orientation_and_layout(melt_map):
    h, p = melt_map
    x, y = pixel_centres(h.shape, p)
    sq = melt_plate.squares()
    assert sorted({s["half"] * 2 for s in sq}) == [10.0, 15.0] and len(sq) == 9
    for s in sq:
        i = int(np.argmin(np.abs(y - s["cy"])))
        j = int(np.argmin(np.abs(x - s["cx"])))
        z = melt_plate.melt_plate_height(x[j], y[i])
        assert h[i, j] == pytest.approx(z, abs=1e-6)  # row/column orientation of the map
        inner = np.abs(melt_plate.melt_plate_height(s["cx"] + 0.7 * s["half"], s["cy"]))
        assert inner > 0


def test_melt_plate_gradient_is_exact():
    rng = np.random.default_rng(7)
    xq, yq = rng.uniform(-33, 33, 400), rng.uniform(-33, 33, 400)
    gx, gy = melt_plate.melt_plate_gradient(xq, yq)
    e = 1e-3
    fx = (melt_plate.melt_plate_height(xq + e, yq) - melt_plate.melt_plate_height(xq - e, yq)) / (2 * e)
    fy = (melt_plate.melt_plate_height(xq, yq + e) - melt_plate.melt_plate_height(xq, yq - e)) / (2 * e)
    np.testing.assert_allclose(gx, fx, atol=2e-4)
    np.testing.assert_allclose(gy, fy, atol=2e-4)
    assert np.abs(gx).max() > 0.01 and np.abs(gy).max() > 0.01


def test_shipped_melt_plate_height_map_is_the_generator_output(melt_map):
    h, _ = melt_map
    shipped = np.load(MESHES / "melt_plate_height.npy")
    assert shipped.dtype == np.float32 and shipped.shape == h.shape
    np.testing.assert_allclose(shipped, h, atol=1e-6)


def test_shipped_melt_plate_mesh_matches_height_map():
    path = MESHES / "melt_plate.ply"
    assert path.stat().st_size < 4e6
    mesh = trimesh.load(path, process=False)
    h = np.load(MESHES / "melt_plate_height.npy")
    assert len(mesh.faces) < 200_000
    assert np.all(mesh.face_normals[:, 2] > 0.9)  # up, no slope above ~25 deg
    x, y = pixel_centres(h.shape, melt_plate.PIXEL_SIZE_MM)
    j = np.rint((mesh.vertices[:, 0] - x[0]) / melt_plate.PIXEL_SIZE_MM).astype(int)
    i = np.rint((y[0] - mesh.vertices[:, 1]) / melt_plate.PIXEL_SIZE_MM).astype(int)
    np.testing.assert_allclose(mesh.vertices[:, 0], x[j], atol=1e-5)  # vertices at pixel centres
    np.testing.assert_allclose(mesh.vertices[:, 1], y[i], atol=1e-5)
    np.testing.assert_allclose(mesh.vertices[:, 2], h[i, j], atol=1e-7)
    # between the vertices the mesh reproduces every pixel within the tolerance (plus float32)
    rng = np.random.default_rng(8)
    ii, jj = rng.integers(0, 500, 3000), rng.integers(0, 500, 3000)
    rebuilt = _mesh_height_at(mesh, x[jj], y[ii])
    assert np.max(np.abs(rebuilt - h[ii, jj])) < 2 * melt_plate.MESH_TOLERANCE_MM + 1e-6


def test_melt_plate_squares_lie_inside_the_field():
    from elo_mitsuba.constants import FIELD_MM

    for s in melt_plate.squares():
        assert max(abs(s["cx"]), abs(s["cy"])) + s["half"] < FIELD_MM / 2


def test_melt_plate_is_deterministic():
    a = melt_plate._squares(melt_plate.SEED)
    b = melt_plate._squares(melt_plate.SEED)
    for s, t in zip(a, b):
        assert s["level"] == t["level"]
        np.testing.assert_array_equal(s["wave_k"], t["wave_k"])
