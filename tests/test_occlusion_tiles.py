"""The walls' occlusion analysis (plugins/_occlusion_tiles.py) against Mitsuba's own ray tracer.

A cell the analysis calls free for a detector must never see a shadow ray to that detector
blocked; the render with the free cells' shadow rays skipped must equal the render that casts them
(but for rays Mitsuba finds blocked by the target detector itself at grazing incidence, where
float32 puts the hit before the sampled point); the cells are rebuilt when a detector moves.
"""

import numpy as np
import pytest

import elo_mitsuba as em

mi = em.ensure_variant()
import drjit as dr  # noqa: E402

from elo_mitsuba.plugins import _occlusion_tiles as ot  # noqa: E402
from elo_mitsuba.plugins._occlusion import _all_separated  # noqa: E402
from elo_mitsuba.plugins._shapes import shape_key  # noqa: E402


def _points_in_cells(tiles, cells, rng, per_cell=8):
    """Uniform random points (M, 3) in the given cells (K, 3: triangle, i, j), clipped to their
    triangles, and the cells they were drawn for."""
    n = 1 << tiles.levels
    cells = np.repeat(cells, per_cell, axis=0)
    u = (cells[:, 1] + rng.random(len(cells))) / n
    v = (cells[:, 2] + rng.random(len(cells))) / n
    inside = u + v <= 1.0
    cells, u, v = cells[inside], u[inside], v[inside]
    tri = tiles.tris[cells[:, 0]]
    p = tri[:, 0] + u[:, None] * (tri[:, 1] - tri[:, 0]) + v[:, None] * (tri[:, 2] - tri[:, 0])
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return p, normal / np.linalg.norm(normal, axis=1)[:, None], cells


def _shadow_rays(scene, points, normals, detector, rng):
    """Mitsuba's shadow rays from ``points`` to uniform points of ``detector``: (blocked, the shape
    key each blocked ray hits, |cos| of the ray at the detector)."""
    m = len(points)
    si = dr.zeros(mi.SurfaceInteraction3f, m)
    si.p = mi.Point3f(*(mi.Float(points[:, k].astype(np.float32)) for k in range(3)))
    si.n = mi.Normal3f(*(mi.Float(normals[:, k].astype(np.float32)) for k in range(3)))
    u = mi.Point2f(mi.Float(rng.random(m).astype(np.float32)), mi.Float(rng.random(m).astype(np.float32)))
    ps = detector.sample_position(0.0, u)
    ray = si.spawn_ray_to(ps.p)
    blocked = scene.ray_test(ray).numpy()
    hit = scene.ray_intersect(ray)
    key = dr.reinterpret_array(mi.UInt32, hit.shape).numpy()
    cos = np.abs(dr.dot(ps.n, ray.d).numpy())
    return blocked, key, cos


@pytest.mark.parametrize("name", ["shield_chamber", "corrugated_chamber"])
def test_free_cells_never_see_a_blocked_ray(name):
    """Random points of every free cell towards random points of the detector: Mitsuba's tracer
    finds no blocker but, at grazing incidence, the target detector itself (float32 puts the plane
    hit before the sampled point; such a ray adds |cos| ~ 0). From the cells that are not free it
    finds blocked rays (the radiation sheet, the heat shield, other detectors): the test can fail."""
    scene = em.load_scene(name, res=8)
    detectors = scene.integrator.detectors
    tiles = ot.WallTiles(scene.scene, detectors)
    rng = np.random.default_rng(7)
    for d, (det_name, det) in enumerate(detectors):
        cells = tiles.cells[d]
        assert cells is not None and 0.3 < cells.sum() / np.count_nonzero(
            np.add.outer(np.arange(cells.shape[1]), np.arange(cells.shape[1])) < cells.shape[1]) / len(cells)
        free = np.argwhere(cells)
        p, n, _ = _points_in_cells(tiles, free, rng, per_cell=256)
        blocked, key, cos = _shadow_rays(scene.scene, p, n, det, rng)
        own = key == shape_key(det)
        assert np.all(own[blocked]), f"{det_name}: {np.count_nonzero(blocked & ~own)} rays from free cells blocked"
        assert np.all(cos[blocked] < 0.05), det_name
        assert len(blocked) > 50_000 and np.count_nonzero(blocked) < 1e-3 * len(blocked)
        # where the analysis refuses, the tracer does find blockers other than the detector
        n_cells = cells.shape[1]
        i, j = np.meshgrid(np.arange(n_cells), np.arange(n_cells), indexing="ij")
        refused = np.argwhere(~cells & (i + j < n_cells)[None])
        p, n, _ = _points_in_cells(tiles, refused, rng, per_cell=32)
        blocked, key, _ = _shadow_rays(scene.scene, p, n, det, rng)
        assert np.count_nonzero(blocked & (key != shape_key(det))) > 0.05 * len(blocked), det_name


def test_kernel_finds_the_cell_of_a_point():
    """The kernel's cell (float32 barycentric coordinates from the hit point) is the cell the
    point was drawn in, but within 1e-5 of a cell's border (where TILE_MARGIN covers it)."""
    scene = em.load_scene("corrugated_chamber", res=8)
    tiles = ot.WallTiles(scene.scene, scene.integrator.detectors)
    n = 1 << tiles.levels
    rng = np.random.default_rng(3)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    cells = np.array([(t, a, b) for t in range(len(tiles.tris)) for a, b in zip(i[i + j < n], j[i + j < n])])
    p, normals, drawn = _points_in_cells(tiles, cells, rng, per_cell=4)
    # hit the points with rays along their normals from 1 mm in front: a real intersection record
    origin = p + normals
    ray = mi.Ray3f(mi.Point3f(*(mi.Float(origin[:, k].astype(np.float32)) for k in range(3))),
                   mi.Vector3f(*(mi.Float(-normals[:, k].astype(np.float32)) for k in range(3))))
    si = scene.scene.ray_intersect(ray)
    on, index = tiles.cell_index(si)
    on, index = on.numpy(), index.numpy()
    want = (drawn[:, 0] * n + drawn[:, 1]) * n + drawn[:, 2]
    hit_right = np.linalg.norm(si.p.numpy().T - p, axis=1) < 1e-3
    assert np.mean(hit_right) > 0.95  # a few points are hidden by what stands in front of them
    tri = tiles.tris[drawn[:, 0]]
    u = ((p - tri[:, 0]) @ np.eye(3))  # distance to the cell's border, in barycentric units
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    gram = np.stack([np.einsum("ik,ik->i", e1, e1), np.einsum("ik,ik->i", e1, e2), np.einsum("ik,ik->i", e2, e2)], 1)
    rhs = np.stack([np.einsum("ik,ik->i", u, e1), np.einsum("ik,ik->i", u, e2)], 1)
    det = gram[:, 0] * gram[:, 2] - gram[:, 1] ** 2
    b1 = (gram[:, 2] * rhs[:, 0] - gram[:, 1] * rhs[:, 1]) / det
    b2 = (gram[:, 0] * rhs[:, 1] - gram[:, 1] * rhs[:, 0]) / det
    border = np.minimum(np.abs(b1 * n - np.round(b1 * n)), np.abs(b2 * n - np.round(b2 * n))) / n
    check = hit_right & (border > ot.TILE_MARGIN)
    assert np.all(on[hit_right])
    np.testing.assert_array_equal(index[check], want[check])


def test_batched_separation_equals_the_scan_regions_test():
    """separated_batch decides as _occlusion._all_separated (one hull at a time) on random hulls
    of a triangle and a tilted square and random blockers, an own triangle left out."""
    rng = np.random.default_rng(5)
    hulls, blockers = [], rng.normal(0.0, 1.0, (16, 3, 3)) * 0.5 + rng.normal(0.0, 2.0, (16, 1, 3))
    for _ in range(300):
        tri = rng.normal(0.0, 1.0, (3, 3))
        square = rng.normal(0.0, 0.3, (1, 3)) + np.array([[1, 1, 0], [1, -1, 0], [-1, -1, 0], [-1, 1, 0]]) * 0.3
        square = square @ np.linalg.qr(rng.normal(size=(3, 3)))[0] + rng.normal(0.0, 2.0, 3)
        hulls.append(np.vstack([tri, tri[:2], square]))  # repeated corners, as clipped blocks have
    hulls = np.array(hulls)
    own = rng.integers(-1, len(blockers), len(hulls))
    got = ot.separated_batch(hulls, blockers, own)
    want = [_all_separated(h, np.delete(blockers, o, axis=0) if o >= 0 else blockers,
                           1e-6 * max(1.0, float(np.ptp(h, axis=0).max()))) for h, o in zip(hulls, own)]
    np.testing.assert_array_equal(got, want)
    assert 0.1 < np.mean(want) < 0.9  # both answers occur


def _render(scene, tiles_on, seed=3):
    integ = scene.integrator
    if not tiles_on:
        integ._use_wall_tiles = lambda *a: setattr(integ, "_wall_tiles", None)
    result = scene.render(quality="default", events=2, seed=seed, progress=False)
    return result.channels, integ


def test_skipping_the_free_cells_rays_changes_no_pixel(monkeypatch):
    """corrugated_chamber, `default`, with the path threshold lowered so that a small render uses
    the free cells: every channel equals the render that casts all shadow rays to 1e-4 (measured
    3.9e-7 of the channel's largest value: grazing rays that the target detector's own plane
    stops); a skipped ray that was blocked costs percent (a path of 16 of a pixel, and its class)."""
    monkeypatch.setattr(ot, "PATHS_PER_TILED_FACE_SQUARED", 0)
    on, integ = _render(em.load_scene("corrugated_chamber", res=24), True)
    assert integ._wall_tiles is not None
    off, integ_off = _render(em.load_scene("corrugated_chamber", res=24), False)
    assert integ_off._wall_tiles is None
    for name in on:
        np.testing.assert_allclose(on[name], off[name], rtol=1e-4, atol=1e-4 * float(np.abs(off[name]).max()),
                                   err_msg=name)


def test_wall_tiles_follow_the_detectors(monkeypatch):
    """A detector moved between renders: the cells are those of a fresh analysis of the new
    placement (never the old ones), and a render below the path threshold builds none."""
    monkeypatch.setattr(ot, "PATHS_PER_TILED_FACE_SQUARED", 0)
    scene = em.load_scene("corrugated_chamber", res=8)
    scene.render(quality="draft", events=2, progress=False)
    before = [c.copy() for c in scene.integrator._wall_tiles.cells]
    scene.set_detector("right", center=(60.0, 150.0, 200.0))  # beside the back detector, hiding part of it
    scene.render(quality="draft", events=2, progress=False)
    after = scene.integrator._wall_tiles.cells
    fresh = ot.WallTiles(scene.scene, scene.integrator.detectors).cells
    for a, f in zip(after, fresh):
        np.testing.assert_array_equal(a, f)
    assert any(not np.array_equal(a, b) for a, b in zip(after, before))
    monkeypatch.setattr(ot, "PATHS_PER_TILED_FACE_SQUARED", 1 << 40)
    scene.render(quality="draft", events=2, progress=False)
    assert scene.integrator._wall_tiles is None


def test_the_analysis_runs_where_it_pays():
    """The decisions the threshold was measured for (benchmarks/RESULTS.md, "The walls' shadow
    rays"): a 1500^2 `default` pass (1.2 M paths) uses the cells on melt_chamber (0.92x the time)
    and athene_flat (0.98x); a 256^2 `default` pass (2.6 M) does not on shield_chamber (its 62
    triangles' analysis, 0.35 s at every detector move, against 0.02 s saved); a draft pass at
    1500^2 (0.05 M) nowhere."""
    for name, paths, want in (("melt_chamber", 1.17e6, True), ("athene_flat", 1.17e6, True),
                              ("shield_chamber", 2.62e6, False), ("shield_chamber", 1.05e7, True),
                              ("athene_flat", 0.05e6, False), ("corrugated_chamber", 2.25e6 * 8, True)):
        scene = em.load_scene(name, res=4)
        assert ot.worth_tiling(scene.scene, scene.integrator.detectors, paths) == want, (name, paths)


def test_a_degenerate_triangle_gets_no_cell(tmp_path):
    """A few-faced mesh with a zero-area triangle (two corners the same point) beside a plate: that
    triangle is left out (no cell, no division by its zero area), the others are analysed, and the
    kernel's dual bases are finite."""
    ply = tmp_path / "ledge.ply"
    ply.write_text("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
                   "element face 2\nproperty list uchar int vertex_indices\nend_header\n"
                   "200 0 10\n250 0 10\n200 50 10\n200 0 10\n3 0 1 2\n3 0 3 1\n")
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "elo", "events": 2},
        "sensor": {"type": "elo_beam", "wd": 400.0, "field": 80.0,
                   "film": {"type": "hdrfilm", "width": 4, "height": 4, "rfilter": {"type": "box"}}},
        "ledge": {"type": "ply", "filename": str(ply), "bsdf": {"type": "elo_bse", "material": "316L"}},
        "plate": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale([40.0, 40.0, 1.0]),
                  "bsdf": {"type": "elo_bse", "material": "Ti-6Al-4V"}},
        "right": {"type": "disk", "emitter": {"type": "area"},
                  "to_world": mi.ScalarTransform4f().look_at([127, 0, 272], [0, 0, 0], [0, 1, 0]).scale(25.0)}})
    integ = scene.integrator()
    integ.prepare_scene(scene, scene.sensors()[0])
    tiles = ot.WallTiles(scene, integ.detectors)
    per_triangle = tiles.cells[0].sum(axis=(1, 2))
    area = np.linalg.norm(np.cross(tiles.tris[:, 1] - tiles.tris[:, 0], tiles.tris[:, 2] - tiles.tris[:, 0]), axis=1)
    assert np.any(area == 0) and np.all(per_triangle[area == 0] == 0) and np.all(per_triangle[area > 0] == 36)
    assert all(np.all(np.isfinite(np.array(a))) for a in (tiles._p0, tiles._g1, tiles._g2))
