"""Load once, render many times: a render depends on the scene's state and its arguments only.

Issue 23: repeated ``render()`` calls without ``spp`` halved the samples each time (Mitsuba's
``render(spp=n)`` leaves the sensor's sampler at n), and a sweep point with ``quality="scene"``
kept the integrator options of the preset its worker had rendered before. Each test renders on a
scene that has already rendered other things and compares, bit for bit, with a fresh scene (same
process, same Dr.Jit thread count).
"""

from __future__ import annotations

import numpy as np
import pytest

import elo_mitsuba as em


def _same(a, b):
    assert sorted(a.channels) == sorted(b.channels)
    for name in a.channels:
        assert np.array_equal(a.channels[name], b.channels[name]), name
    assert a.metadata["spp"] == b.metadata["spp"] and a.metadata["quality"] == b.metadata["quality"]
    assert a.metadata["integrator_options"] == b.metadata["integrator_options"]


def test_repeated_renders_keep_the_scene_spp():
    scene = em.load_scene("flat_plate", res=8)
    results = [scene.render(seed=3) for _ in range(4)]
    assert [r.metadata["spp"] for r in results] == [16] * 4
    for r in results[1:]:
        _same(results[0], r)
    assert scene.sensor.sampler().sample_count() == 16  # also for mi.render(scene) without spp


@pytest.mark.parametrize("quality", ["draft", "default", "reference", "unbiased", "scene"])
def test_a_quality_after_other_renders_equals_a_fresh_scene(quality):
    """athene_flat with events 2: the presets' bounce filter, the top-up pass (default) and the
    error estimate's halves (1 spp: half the continuation paths each) all run."""
    args = dict(res=12)
    fresh = em.load_scene("athene_flat", **args).render(events=2, quality=quality, seed=5, progress=False)
    used = em.load_scene("athene_flat", **args)
    for other in ("reference", "unbiased", "default", "scene", "draft"):
        used.render(events=2, quality=other, spp=2, seed=1, progress=False)
    used.render(events=1, progress=False)
    _same(fresh, used.render(events=2, quality=quality, seed=5, progress=False))


def test_quality_is_kept_until_changed():
    scene = em.load_scene("flat_plate", res=8)
    draft = scene.render(quality="draft", progress=False)
    again = scene.render(progress=False)  # the scene's quality is now draft: applied again
    _same(draft, again)
    assert again.metadata["quality"] == "draft"
    back = scene.render(quality="scene", progress=False)
    _same(em.load_scene("flat_plate", res=8).render(progress=False), back)


def test_configuring_a_preset_field_is_applied_not_undone():
    scene = em.load_scene("flat_plate", res=8)
    scene.render(quality="default", progress=False)
    scene.configure(quadrature_triangles=24)
    result = scene.render(progress=False)
    assert result.metadata["quality"] == "custom"
    assert result.metadata["integrator_options"]["quadrature_triangles"] == 24
    assert result.metadata["spp"] == 16  # the scene file's: no preset chose one


def test_sweep_points_with_the_scene_quality_equal_direct_renders(tmp_path):
    """A sweep with ``quality = "scene"`` and no spp (issue 23: points 2-4 were 3-5 % off a direct
    render, each rendered with half the previous point's samples): every point, rendered after
    the others in one process, equals a fresh scene with the same detector move."""
    import xarray as xr

    from elo_mitsuba import sweep

    radii = [20.0, 22.0, 24.0, 26.0]
    spec = {"scene": "flat_plate", "vary": {"right": {"radius": radii}},
            "render": {"resolution": 8, "quality": "scene"}, "keep": {"channels": ["right"]}}
    sweep(spec, tmp_path / "s.zarr", workers=0, progress=False)
    ds = xr.open_zarr(tmp_path / "s.zarr")
    for r in radii:
        scene = em.load_scene("flat_plate", res=8)
        scene.set_detector("right", radius=r)
        direct = scene.render(quality="scene", progress=False).channels["right"]
        assert np.array_equal(ds["image_right"].sel(right_radius=r).values, direct), r


def test_scene_quality_keeps_what_configure_set_before_a_preset():
    """The sweep worker's order: configure the scene's own options, render other points with a
    preset, then one with ``quality="scene"``: the configured options come back, not the scene
    file's nor the preset's."""
    def configured():
        scene = em.load_scene("flat_plate", res=8)
        scene.configure(detector_sampling="quadrature", quadrature_triangles=24)
        return scene

    fresh = configured().render(quality="scene", progress=False)
    used = configured()
    used.render(quality="draft", progress=False)
    _same(fresh, used.render(quality="scene", progress=False))
    assert fresh.metadata["integrator_options"]["quadrature_triangles"] == 24


def test_restore_detectors_puts_them_back_as_loaded():
    scene = em.load_scene("flat_plate", res=8)
    loaded = scene.detector_geometry()
    fresh = scene.render(spp=2).channels
    scene.set_detector("right", center=(150, 0, 250), radius=30)
    scene.set_detector("left", center=(-150, 0, 250))
    scene.restore_detectors(["right"])
    assert scene.detector_geometry()["right"] == loaded["right"]
    assert scene.detector_geometry()["left"] != loaded["left"]
    scene.restore_detectors()
    assert scene.detector_geometry() == loaded
    again = scene.render(spp=2).channels
    for name, img in fresh.items():  # the transform from its float32 copy: last bits of the inverse
        np.testing.assert_allclose(again[name], img, rtol=1e-6, atol=1e-6 * float(np.abs(img).max()))
    with pytest.raises(em.EloInputError, match=r"no placed detector 'nowhere' \(detectors: right, left"):
        scene.restore_detectors(["nowhere"])


def test_a_move_does_not_depend_on_the_moves_before_it():
    """set_detector's promise: the result depends on its arguments alone. The default centre and
    radius (where the detector is) were read back from the float32 transform, so a detector moved
    away and back rendered 4.7e-10 (3e-7 of the signal) off a fresh scene's single move."""
    def moved(*centres):
        scene = em.load_scene("flat_plate", res=8)
        for c in centres:
            scene.set_detector("right", center=c)
            result = scene.render(spp=4, progress=False)
        return result.channels["right"]

    assert np.array_equal(moved((150, 0, 250)), moved((100, 50, 300), (150, 0, 250)))


def test_a_detector_moved_to_where_the_scene_put_it_renders_as_the_scene_does():
    """A disc is symmetric about its normal, but its samples are drawn in its own frame: with
    set_detector orienting it otherwise than parts/detectors.xml (look-at up +z against the
    azimuthal direction), a detector "moved" to its own place rendered another Monte Carlo
    realisation, 2 % of the signal apart at 4 spp. In the scene's frame only float32 rounding of
    the transform remains: at most 1.0e-6 of the mean (1.2e-5 for the 2nd event's longer paths)
    over seeds 0-7; the bounds leave 10x for other CPUs' rounding."""
    scene = em.load_scene("athene_flat", res=8)
    before = scene.render(spp=4, events=2, progress=False).channels
    for name, geometry in scene.detector_geometry().items():
        scene.set_detector(name, center=geometry["center"])
    after = scene.render(spp=4, events=2, progress=False).channels
    for key, image in before.items():
        bound = 1e-4 if key.endswith(".e2") else 1e-5
        assert np.abs(after[key] - image).max() <= bound * image.mean(), key


def test_detectors_swapped_one_by_one_render_as_placed_there():
    """Detectors move one at a time, so a swap passes through a state where two coincide: only
    the system a render uses is checked for discs that intersect (set_detector refused the first
    move). The swapped scene renders each image where the other detector's was."""
    scene = em.load_scene("flat_plate", res=8)
    before = scene.render(quality="draft", progress=False).channels
    scene.set_detector("right", center=(0, 127, 272))  # onto 'back', for a moment
    scene.set_detector("back", center=(127, 0, 272))
    after = scene.render(quality="draft", progress=False).channels
    for a, b in (("right", "back"), ("back", "right")):
        assert np.abs(after[a] - before[b]).max() <= 1e-5 * before[b].mean(), a  # 4.7e-7 here: float32


def test_a_mesh_given_new_vertices_is_analysed_again():
    """What the set-up learns of a mesh (whether it is one plane, so whether the relief can scatter
    onto itself) is kept per placement: the corrugated sheet's vertices moved, through Mitsuba's
    parameters (a new vertex buffer), onto a tilted plane within the same bounds are one plane at
    the next render, and bent back they are relief again; all moved into one point, the mesh is
    checked again and refused (no area)."""
    import mitsuba as mi

    from elo_mitsuba.plugins._far_field import near_share

    scene = em.load_scene("corrugated_sheet", res=8)
    scene.render(quality="draft", progress=False, events=2)
    assert scene.integrator.relief == ["corrugated_sheet"]
    params = mi.traverse(scene.scene)
    bent = np.array(params["corrugated_sheet.vertex_positions"]).reshape(-1, 3)
    tilted = bent.copy()
    x, z = bent[:, 0].astype(float), bent[:, 2].astype(float)
    tilted[:, 2] = z.min() + (z.max() - z.min()) * (x - x.min()) / (x.max() - x.min())  # the same bounds
    box = scene.scene.shapes()[[s.id() for s in scene.scene.shapes()].index("corrugated_sheet")].bbox
    for vertices, relief in ((tilted, []), (bent, ["corrugated_sheet"])):
        before = (tuple(box().min), tuple(box().max))
        params["corrugated_sheet.vertex_positions"] = mi.Float(vertices.ravel())
        params.update()
        assert (tuple(box().min), tuple(box().max)) == before
        scene.render(quality="draft", progress=False, events=2)
        assert scene.integrator.relief == relief
    # every other ridge lowered to the mean, within the same bounds: the share of later electrons
    # meeting the sheet again is the new relief's, not the corrugation's (read at every render)
    lowered = bent.copy()
    ridges = np.unique(bent[bent[:, 2] == bent[:, 2].max(), 0])
    lowered[np.isin(bent[:, 0], ridges[1::2]) & (bent[:, 2] == bent[:, 2].max()), 2] = 0.0
    shares = []
    for vertices in (bent, lowered):
        params["corrugated_sheet.vertex_positions"] = mi.Float(vertices.ravel())
        params.update()
        scene.render(quality="draft", progress=False, events=2)
        shares.append(scene.integrator.near_share(scene.scene, scene.sensor))
        assert shares[-1] == near_share(scene.scene, scene.sensor)
    assert shares[0] != shares[1]
    params["corrugated_sheet.vertex_positions"] = mi.Float(np.zeros(bent.size))  # every vertex in one point
    params.update()
    with pytest.raises(em.EloInputError, match="surface 'corrugated_sheet' has an area of 0"):
        scene.render(quality="draft", progress=False, events=2)


def test_a_new_vertex_buffer_is_a_new_placement(mi, monkeypatch):
    """GeometryKey tells every new vertex buffer of a mesh from the ones before, also where Dr.Jit
    gives the new buffer a freed buffer's variable index: a sheet bent and flattened in turn,
    through Mitsuba's parameters, is one plane exactly when flat (the set-up's cached answer), and
    the key differs from the last one at every update; and the triangles kept for the disc checks
    are read anew at every new buffer. Both failed before the buffers were held (index reuse)."""
    import elo_mitsuba.plugins._detectors as det
    from elo_mitsuba.plugins._shapes import GeometryKey, cover_triangles, is_planar

    scene = em.load_scene("corrugated_sheet", res=8)
    params = mi.traverse(scene.scene)
    sheet = next(s for s in scene.scene.shapes() if s.id() == "corrugated_sheet")
    bent = np.array(params["corrugated_sheet.vertex_positions"]).reshape(-1, 3)
    flat = bent.copy()
    x, z = bent[:, 0].astype(float), bent[:, 2].astype(float)
    flat[:, 2] = z.min() + (z.max() - z.min()) * (x - x.min()) / (x.max() - x.min())  # the same bounds
    key, keys, cache = GeometryKey(), [], {}
    detectors = [(s.id(), s) for s in scene.scene.shapes() if s.is_emitter()]
    sequence = (flat, bent, bent, flat, flat, bent, flat, bent)
    for vertices in sequence:
        params["corrugated_sheet.vertex_positions"] = mi.Float(vertices.ravel())
        params.update()
        keys.append(key(scene.scene))
        assert key.planar(sheet) == is_planar(sheet) == (vertices is flat)
    assert all(a != b for a, b in zip(keys, keys[1:]))
    read = []
    monkeypatch.setattr(det, "cover_triangles", lambda sh: read.append(sh.id()) or cover_triangles(sh))
    for vertices in sequence:  # alone: no key holds the buffers here, and Dr.Jit reuses their indices
        params["corrugated_sheet.vertex_positions"] = mi.Float(vertices.ravel())
        params.update()
        read.clear()
        det.surfaces_through_detectors(scene.scene, detectors, cache=cache)
        assert "corrugated_sheet" in read  # a new buffer: its triangles read anew
