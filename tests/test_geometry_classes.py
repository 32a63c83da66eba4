"""Events >= 2 shared by pixels of matching geometry (bounce_share, plugins/_geometry_classes.py)."""

import numpy as np
import pytest

import elo_mitsuba as em
from elo_mitsuba.errors import EloInputError
from elo_mitsuba.options import QUALITY_PRESETS, SHARE_BLOCK_MM, EloOptions
from elo_mitsuba.plugins._geometry_classes import classes, probe_directions
from elo_mitsuba.plugins._strata import PICK_MAX_PATHS

DETS = ("right", "left", "back", "front")
#: The block of `default`'s classes where the near relief makes the later events.
NEAR_MM = QUALITY_PRESETS["default"]["near_share_mm"]


def test_classes_join_equal_features_within_a_block_only():
    valid = np.ones((4, 6), bool)
    valid[0, 0] = False
    features = np.zeros((2, 4, 6), np.int64)
    features[0, :, 1] = 5  # column 1 apart from the rest
    index, counts = classes(valid, features, block_px=3)
    assert counts.sum() == valid.size
    # one block (rows 0-2, columns 0-2): column 1 is a class, columns 0 and 2 another (less the invalid pixel)
    assert index[0, 1] == index[1, 1] == index[2, 1] != index[1, 0]
    assert index[1, 0] == index[2, 0] == index[0, 2] == index[2, 2]
    # the next block along x and the next along y are other classes
    assert index[0, 4] != index[0, 2] and index[3, 0] != index[2, 0]
    # an invalid pixel is alone
    assert counts[index[0, 0]] == 1
    # features equal in every component but one
    features[1, 2, 2] = 1
    index2, _ = classes(valid, features, block_px=3)
    assert index2[2, 2] != index2[1, 2]


def test_probe_directions_cover_the_hemisphere_cosine_weighted():
    d = probe_directions(16)
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0) and np.all(d[:, 2] > 0)
    # cosine-weighted: E[cos theta] = 2/3; and every quadrant of azimuth holds a quarter of them
    assert abs(d[:, 2].mean() - 2.0 / 3.0) < 0.02
    quadrant = (np.arctan2(d[:, 1], d[:, 0]) // (np.pi / 2)).astype(int)
    assert np.bincount(quadrant + 2, minlength=4).tolist() == [4, 4, 4, 4]


def test_the_option_is_checked():
    with pytest.raises(EloInputError, match=r"bounce_share=-1.*mm.*>= 0"):
        EloOptions(bounce_share=-1.0)
    with pytest.raises(EloInputError, match="bounce_share=4 mm and bounce_filter=1 mm"):
        EloOptions(events=2, bounce_share=4.0, bounce_filter=1.0)


def test_sharing_needs_the_beam_sensor(mi):
    """bounce_share classifies the beam's scan points: another sensor is refused in one line
    before any work."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from forward_scenes import flat_scene

    scene = flat_scene(mi, res=4, wall=True, events=2, integrator={"type": "elo", "events": 2, "bounce_share": 4.0})
    scene["sensor"] = {"type": "perspective", "fov": 30,
                       "film": {"type": "hdrfilm", "width": 4, "height": 4, "rfilter": {"type": "box"}}}
    loaded = mi.load_dict(scene)
    with pytest.raises(EloInputError, match=r"bounce_share=4 mm .* sensor is .*; set bounce_share=0"):
        loaded.integrator().render_planes(loaded, 0, 0, 1)


def test_the_corrugated_sheets_flank_lines_are_classes(mi):
    """The corrugated sheet (ridges along y) at 0.156 mm pixels: in a block, the pixels of one
    column on one flank share a class, and no class holds both flanks' normals."""
    scene = em.load_scene("corrugated_chamber", res=64, field=10)
    scene.set_quality("default")
    integ = scene.integrator
    assert integ.options.bounce_share == NEAR_MM
    integ.prepare_scene(scene.scene, scene.sensor)
    c = integ.geometry_classes()
    assert c.block_px == round(NEAR_MM / (10 / 64))
    index = c.index
    block = index[:26, :26]
    # along y (rows) a column's pixels are one class, but where a probe distance lies on a step
    # of the quantisation (the beam's incidence changes a little along y): most pixels' classes
    # span most of the block's rows
    sizes = np.array([np.sum(block[:, j] == block[i, j]) for i in range(26) for j in range(26)])
    assert np.median(sizes) == 26 and np.mean(sizes >= 13) > 0.8, (np.median(sizes), np.mean(sizes >= 13))
    # across x the classes change with the flank and the place on it
    assert len(np.unique(block[0])) >= 13
    # no class holds pixels of two different normals (face normals: two exactly)
    import drjit as dr
    import mitsuba as mi_

    idx = dr.arange(mi_.UInt32, 64 * 64)
    film = mi_.Point2f((mi_.Float(idx % 64) + 0.5) / 64, (mi_.Float(idx // 64) + 0.5) / 64)
    ray, _ = scene.sensor.sample_ray(0.0, 0.5, film, mi_.Point2f(0.5, 0.5))
    nx = np.sign(np.array(scene.scene.ray_intersect(ray).sh_frame.n.x)).reshape(64, 64)
    for k in np.unique(index):
        assert len(np.unique(nx[index == k])) == 1


def test_classes_are_built_once_per_geometry(mi):
    """Re-renders and detector moves out of the probes' reach reuse the classes (a detector
    sweep), and another preset's block sorts the same features anew; a detector moved within reach
    of the field, or another film, scans them again."""
    scene = em.load_scene("corrugated_chamber", res=24, field=10)
    for seed in (1, 2):
        scene.render(quality="default", seed=seed, progress=False)
    integ = scene.integrator
    assert integ.class_builds == 1
    block = integ.geometry_classes().block_px
    scene.render(quality="reference", seed=1, progress=False)  # its own block, the same features
    assert integ.class_builds == 1 and integ.geometry_classes().block_px != block
    scene.render(quality="default", seed=1, progress=False)
    assert integ.class_builds == 1 and integ.geometry_classes().block_px == block
    centre = scene.detector_geometry()["right"]["center"]
    scene.set_detector("right", center=[centre[0] + 5.0, centre[1], centre[2]])
    scene.render(quality="default", seed=3, progress=False)
    assert integ.class_builds == 1
    scene.set_detector("right", center=[20.0, 0.0, 30.0])  # 30 mm above the field: within reach
    scene.render(quality="default", seed=3, progress=False)
    assert integ.class_builds == 2
    scene.restore_detectors()
    scene.render(quality="default", seed=3, progress=False)
    assert integ.class_builds == 3
    # the sheet given new vertices within its bounds (every other ridge lowered): built again
    params = mi.traverse(scene.scene)
    v = np.array(params["corrugated_sheet.vertex_positions"]).reshape(-1, 3)
    top = v[:, 2] == v[:, 2].max()
    v[top & np.isin(v[:, 0], np.unique(v[top, 0])[1::2]), 2] = 0.0
    params["corrugated_sheet.vertex_positions"] = mi.Float(v.ravel())
    params.update()
    scene.render(quality="default", seed=3, progress=False)
    assert integ.class_builds == 4


def test_the_presets_share_on_relief_only(mi):
    """Per-pixel paths shared by geometry on relief only: in blocks of the preset's
    ``near_share_mm`` with ``near_relief_paths`` where the near relief makes the later events
    (corrugated_chamber), of SHARE_BLOCK_MM with ``relief_paths`` where the far field does
    (melt_chamber at events 3)."""

    chosen = {}
    for name, fwhm, quality, events in (("corrugated_chamber", 0.0, "default", 2), ("corrugated_chamber", 0.0, "draft", 2),
                                        ("corrugated_chamber", 0.0, "reference", 2),
                                        ("corrugated_chamber", 0.0, "unbiased", 2),
                                        ("corrugated_chamber", 0.27, "default", 2),
                                        ("melt_chamber", 0.0, "default", 2), ("melt_chamber", 0.0, "default", 3),
                                        ("athene_flat", 0.0, "default", 2)):
        scene = em.load_scene(name, res=32, fwhm=fwhm, events=events)
        spp = scene.set_quality(quality)
        o = scene.integrator.options
        chosen[(name, fwhm, quality, events)] = (o.bounce_share, o.bounce_samples * o.bounce_fraction * spp)
    far = SHARE_BLOCK_MM
    near = {q: p["near_share_mm"] for q, p in QUALITY_PRESETS.items()}
    paths = {q: (p["near_relief_paths"], p["relief_paths"]) for q, p in QUALITY_PRESETS.items()}
    assert chosen == {("corrugated_chamber", 0.0, "default", 2): (near["default"], paths["default"][0]),
                      ("corrugated_chamber", 0.0, "draft", 2): (near["draft"], paths["draft"][0]),
                      ("corrugated_chamber", 0.0, "reference", 2): (near["reference"], paths["reference"][0]),
                      ("corrugated_chamber", 0.0, "unbiased", 2): (0.0, paths["unbiased"][0]),  # the ground truth
                      # classes of footprints; each of the profile's samples traces a path at least
                      ("corrugated_chamber", 0.27, "default", 2): (near["default"], max(paths["default"][0],
                                                                              QUALITY_PRESETS["default"]["spp_blur"])),
                      ("melt_chamber", 0.0, "default", 2): (0.0, chosen[("melt_chamber", 0.0, "default", 2)][1]),  # the residual filter
                      ("melt_chamber", 0.0, "default", 3): (far, paths["default"][1]),
                      ("athene_flat", 0.0, "default", 2): (0.0, chosen[("athene_flat", 0.0, "default", 2)][1])}, chosen
    assert near["default"] > far and paths["default"][0] < paths["default"][1]


def test_under_a_beam_profile_the_classes_see_the_footprint(mi):
    """With fwhm > 0 the classes also probe 1.5 sigma from the grid point along +-x, +-y: they
    refine the single-ray classes (no class joins pixels the centre rays tell apart) and split
    where the footprints' surroundings differ (the corrugated sheet at 0.31 mm pixels: columns at
    nearby places on a flank whose centres' probes agree)."""
    from elo_mitsuba.plugins._geometry_classes import FOOTPRINT_SIGMAS, footprint_offsets, scan_features

    found = {}
    for fwhm in (0.0, 0.27):
        scene = em.load_scene("corrugated_chamber", res=256, fwhm=fwhm)
        offsets = footprint_offsets(scene.sensor)
        valid, key, _, _ = scan_features(scene.scene, scene.sensor)
        found[fwhm] = classes(valid, key, 13)[0]
    sigma = 0.27 / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    assert offsets[1] == pytest.approx((FOOTPRINT_SIGMAS * sigma, 0.0)) and len(offsets) == 5
    single, footprint = found[0.0], found[0.27]
    pairs = np.unique(np.stack([footprint.ravel(), single.ravel()], axis=1), axis=0)
    assert len(np.unique(pairs[:, 0])) == len(pairs)  # each footprint class inside one single-ray class
    assert len(pairs) > len(np.unique(single))  # and some single-ray classes split


def _near_view_factor(scene, directions):
    """Per pixel (flat) the cosine-weighted share of the hemisphere over the scan point that meets
    a surface within the far field's near distance, by quadrature over ``directions`` fixed
    (u, v) points (Mitsuba's own hit, frame and ray offset: nothing of the classes' code), and
    whether the beam meets the relief there."""
    import drjit as dr
    import mitsuba as mi_

    from elo_mitsuba.plugins._far_field import NEAR_MM

    size = scene.sensor.film().crop_size()
    n_px = int(size[0]) * int(size[1])
    idx = dr.arange(mi_.UInt32, n_px)
    film = mi_.Point2f((mi_.Float(idx % int(size[0])) + 0.5) / int(size[0]), (mi_.Float(idx // int(size[0])) + 0.5) / int(size[1]))
    ray, _ = scene.sensor.sample_ray(0.0, 0.5, film, mi_.Point2f(0.5, 0.5))
    si = scene.scene.ray_intersect(ray)
    valid = si.is_valid() & ~si.shape.is_emitter()
    m = len(directions)
    lane = dr.arange(mi_.UInt32, n_px * m)
    pixel, k = lane // m, lane % m
    si_lane = dr.gather(type(si), si, pixel)
    u = dr.gather(mi_.Float, mi_.Float(directions[:, 0].astype(np.float32)), k)
    v = dr.gather(mi_.Float, mi_.Float(directions[:, 1].astype(np.float32)), k)
    local = mi_.warp.square_to_cosine_hemisphere(mi_.Point2f(u, v))
    probe = si_lane.spawn_ray(si_lane.sh_frame.to_world(local))
    probe.maxt = NEAR_MM
    hit = scene.scene.ray_test(probe, dr.gather(mi_.Bool, valid, pixel))
    share = dr.block_sum(mi_.Float(hit), m) / m
    return np.array(share, dtype=np.float64), np.array(valid, dtype=bool)


def test_a_class_holds_points_of_equal_surroundings_on_the_sawtooth(mi, tmp_path):
    """The sawtooth plate's valleys end at cliffs: a point on a flank sees more or less of the
    facing flank by its distance to the valley's end, between the probe directions. Within each
    class the near field's view factor (the cosine-weighted share of the hemisphere that meets
    relief within the near distance: the first order of the 2nd event) must agree: RMS over the
    relief's pixels of (own - class mean) <= 4 % of its mean (1024 fixed directions, an
    independent quadrature). Measured at 128²: 8.7 % with 16 probes, 5.1 % with 32, 2.9 % with
    64 (the e2 of 144 unshared renders at 256² gives 9.0 / 5.2 / 2.8 %: benchmarks.geometry_share
    --classes)."""
    from elo_mitsuba.objects import sawtooth_plate
    from elo_mitsuba.plugins._geometry_classes import GeometryClasses
    from elo_mitsuba.scene_files import write_object_scene

    scene = em.load_scene(str(write_object_scene(tmp_path, "saw", sawtooth_plate.sawtooth_mesh())), res=128)
    m = 1024
    k = np.arange(m)
    directions = np.stack([(k + 0.5) / m, (k * 0.6180339887498949 + 0.3) % 1.0], axis=1)  # not the probes' set
    share, valid = _near_view_factor(scene, directions)
    c = GeometryClasses(scene.scene, scene.sensor, SHARE_BLOCK_MM, None)
    class_mean = (np.bincount(c.flat, weights=share, minlength=c.counts.size) / c.counts)[c.flat]
    relief = valid & (share > 0)
    spread = np.sqrt(np.mean((share - class_mean)[valid] ** 2)) / share[relief].mean()
    assert relief.mean() > 0.1  # the patches' flanks see each other
    assert spread <= 0.04, spread


def test_view_factors_carry_a_detectors_solid_angle_across_a_block(mi):
    """The view factors are cos / r^2 of each detector's centre from the beam's hit (on the flat
    plate the pixel's grid point of docs/rendering.md's orientation: an independent computation),
    and they carry what a detector sees across a block: the 1st event (the Appendix A quadrature,
    deterministic), shared in `default`'s near-relief blocks with them, stays within 0.1 % RMS of
    itself (measured 0.03 %), where the plain class mean is off by 0.96 %."""
    from elo_mitsuba.plugins._geometry_classes import GeometryClasses

    scene = em.load_scene("flat_plate", res=64)
    result = scene.render(quality="default", progress=False)
    c = GeometryClasses(scene.scene, scene.sensor, NEAR_MM, None)
    geometry = scene.detector_geometry()
    views = c.view_factors([geometry[d]["center"] for d in DETS])
    field, w = float(scene.sensor.field), 64
    nudge = scene.sensor.aim_offset_mm  # the beam's aim, a hair off the grid point (sensor_elo_beam)
    x = -field / 2 + (np.arange(w) + 0.5) * field / w + nudge[0]
    y = field / 2 - (np.arange(w) + 0.5) * field / w + nudge[1]
    p = np.stack(np.broadcast_arrays(x[None, :], y[:, None], 0.0 * x[None, :]), axis=-1)
    for k, d in enumerate(DETS):
        v = np.asarray(geometry[d]["center"]) - p
        r = np.linalg.norm(v, axis=-1)
        assert np.allclose(views[k], v[..., 2] / r**3, rtol=1e-5, atol=0.0), d
        e1 = np.array(result.channels[d], np.float32)
        plain, viewed = e1.copy(), e1.copy()
        c.share(plain)
        c.share(viewed, views[k])
        rms = [np.sqrt(np.mean((a.astype(np.float64) - e1) ** 2)) / e1.mean() for a in (plain, viewed)]
        assert rms[1] < 1e-3 and rms[0] > 5e-3, (d, rms)
    # a detector moved (a sweep): its factors follow, never the cached ones of before
    moved = np.asarray(geometry["right"]["center"]) + (10.0, -20.0, 5.0)
    v = moved - p
    r = np.linalg.norm(v, axis=-1)
    assert np.allclose(c.view_factors([moved])[0], v[..., 2] / r**3, rtol=1e-5, atol=0.0)


def _flat_plate_classes(res):
    """The flat plate's classes in `default`'s near-relief blocks, a detector's view factors and
    each pixel's place in its class (x, y, mm, about the class's centre weighted by the view
    factors; from the grid of docs/rendering.md and the beam's aim nudge: an independent
    computation of the beam's hits on the plate)."""
    from elo_mitsuba.plugins._geometry_classes import GeometryClasses

    scene = em.load_scene("flat_plate", res=res)
    c = GeometryClasses(scene.scene, scene.sensor, NEAR_MM, None)
    view = c.view_factors([scene.detector_geometry()["right"]["center"]])[0]
    field, nudge = float(scene.sensor.field), scene.sensor.aim_offset_mm
    x = -field / 2 + (np.arange(res) + 0.5) * field / res + nudge[0]
    y = field / 2 - (np.arange(res) + 0.5) * field / res + nudge[1]
    xy = np.stack(np.broadcast_arrays(x[None, :], y[:, None]), axis=-1).reshape(-1, 2)
    v = view.ravel()
    centre = np.stack([np.bincount(c.flat, weights=v * xy[:, a]) for a in (0, 1)], axis=1) / np.bincount(c.flat, weights=v)[:, None]
    return c, view, (xy - centre[c.flat]).reshape(res, res, 2)


def test_a_tilt_across_the_blocks_is_fitted(mi, monkeypatch):
    """A plane that is each pixel's view factor times its class's value times 1 + theta . (x, y)
    ((x, y) its place in the class, mm) comes back from share() unchanged (float32 rounding),
    whatever the class values: the tilt theta that the classes of one normal share is fitted
    (least squares over all of them). Without the fit (too few pixels for it) the class's ratio
    alone leaves it > 0.5 % off (RMS; measured 2.1 %), and with 3 % noise per pixel the fitted tilt is within 4
    standard errors of theta. A tilt that would take a pixel's factor beyond MAX_TILT is scaled
    down."""
    import elo_mitsuba.plugins._geometry_classes as gc

    c, view, offset = _flat_plate_classes(96)
    rng = np.random.default_rng(3)
    theta = np.array([0.004, -0.0025])  # per mm: +-3 % across a 16 mm block along x
    value = rng.uniform(0.5, 2.0, c.counts.size)[c.index]  # a value per class
    truth = (view * value * (1.0 + offset @ theta)).astype(np.float32)
    plane = truth.copy()
    c.share(plane, view)
    assert np.allclose(plane, truth, rtol=2e-5, atol=0.0)
    noisy = (truth * (1.0 + 0.03 * rng.standard_normal(truth.shape))).astype(np.float32)
    x = noisy.ravel().astype(np.float64)
    sums = np.bincount(c.flat, weights=x)
    fitted = c.tilts(x, view.ravel(), sums, c._view_moments(view))
    standard_error = 0.03 / np.sqrt(np.sum(offset**2) / 2)  # of a slope fitted to 3 % noise
    assert np.all(np.abs(fitted[0] - theta) < 4 * standard_error), (fitted, standard_error)
    huge = (view * value * (1.0 + offset @ (200 * theta))).astype(np.float32)
    plane = huge.copy()
    c.share(plane, view)
    assert np.all(np.isfinite(plane)) and np.all(plane > 0)
    x = huge.ravel().astype(np.float64)
    big = c.tilts(x, view.ravel(), np.bincount(c.flat, weights=x), c._view_moments(view))
    assert np.abs(offset.reshape(-1, 2) @ big[0]).max() <= gc.MAX_TILT * (1 + 1e-9)
    monkeypatch.setattr(gc, "MIN_TILT_PIXELS", 10**9)
    plain, _, _ = _flat_plate_classes(96)
    plane = truth.copy()
    plain.share(plane, view)
    rms = np.sqrt(np.mean((plane.astype(np.float64) / truth - 1.0) ** 2))
    assert rms > 5e-3, rms


def test_shares_on_threads_are_each_planes_own_share(mi, monkeypatch):
    """share_all (the classes' sums of a render's planes on several threads, then each plane's
    pixels) gives every plane bit for bit what share() gives it alone, each with its own view:
    detectors of different view factors, planes of different tilts, with and without a view; and
    it runs the sums on more than one thread."""
    import sys
    import threading

    import elo_mitsuba.plugins._geometry_classes as gc

    c, view, offset = _flat_plate_classes(96)
    rng = np.random.default_rng(5)
    views = [view, view**1.5 / np.mean(view**0.5), None, view[::-1].copy()]
    planes = [(view * rng.uniform(0.5, 2.0, c.counts.size)[c.index] * (1.0 + offset @ rng.normal(0, 3e-3, 2))
               * (1.0 + 0.02 * rng.standard_normal(view.shape))).astype(np.float32) for _ in views]
    alone = [p.copy() for p in planes]
    for p, v in zip(alone, views):
        c.share(p, v)
    threads = set()
    tables = gc.GeometryClasses._tables

    def spy(self, plane, view):
        threads.add(threading.get_ident())
        return tables(self, plane, view)

    monkeypatch.setattr(sys.modules["elo_mitsuba.plugins._threads"], "PLANE_THREADS", 2)
    monkeypatch.setattr(gc.GeometryClasses, "_tables", spy)
    together = [p.copy() for p in planes]
    c.share_all(zip(together, views))
    for a, b in zip(alone, together):
        assert np.array_equal(a, b)
    assert len(threads) >= 1 and threading.get_ident() not in threads


def test_a_classs_pixels_take_its_point_set_in_a_scrambled_order(mi):
    """Ranks in a class are a permutation of 0 .. n - 1, in an order unrelated to where the pixels
    lie (rank against row and column: |correlation| < 0.05; row-major ranks give 0.97): neighbouring
    points of the set, which draw neighbouring directions, must not run across the block, or the
    tilt share() fits within one render would follow the directions drawn."""
    c, _, _ = _flat_plate_classes(96)
    cls, rank, size = (np.array(a) for a in c.ranks())
    assert np.array_equal(np.sort(rank[cls == 0]), np.arange(c.counts[0]))
    rows, cols = np.divmod(np.arange(cls.size), 96)
    r = rank / size
    for pos in (rows, cols):
        within = pos - (np.bincount(cls, weights=pos) / c.counts)[cls]
        assert abs(np.corrcoef(r, within)[0, 1]) < 0.05


def test_shared_events_are_the_class_means(mi):
    """Each pixel's shared e2 is its view factor times its class's ratio of e2 to view factor: one
    ratio per class, and that ratio agrees with the one of an independent unshared render
    (z-scores by the class's spread of those values: a sum instead of a mean, or a pixel's own
    value, fails); the 1st event is never shared."""
    from elo_mitsuba.plugins._shapes import bbox_centre

    scene = em.load_scene("corrugated_chamber", res=48, field=10)
    spp = scene.set_quality("default")
    integ = scene.integrator
    shared, _ = integ.render_planes(scene.scene, 0, 9, spp)
    shared = shared.copy()
    c = integ.geometry_classes()
    views = c.view_factors([bbox_centre(shape) for _, shape in integ.detectors])
    scene.configure(bounce_share=0.0)
    own, _ = integ.render_planes(scene.scene, 0, 10, spp)
    names = integ.channel_names()
    big = c.counts >= 8
    z = []
    for k, d in enumerate(DETS):
        i = names.index(f"{d}.e2")
        view = views[k].ravel()
        view_sum = np.bincount(c.flat, weights=view)
        ratio = shared[i].ravel().astype(np.float64) / view
        ratios = np.bincount(c.flat, weights=ratio) / c.counts
        assert np.allclose(ratio, ratios[c.flat], rtol=1e-5, atol=0.0)  # one ratio per class
        values = own[i].ravel().astype(np.float64)
        m = np.bincount(c.flat, weights=values) / c.counts
        var = (np.bincount(c.flat, weights=values**2) / c.counts - m**2) * c.counts / np.maximum(c.counts - 1, 1)
        own_ratio = np.bincount(c.flat, weights=values) / view_sum
        z.append(((ratios - own_ratio) / (np.sqrt(var * c.counts) / view_sum))[big])
        j = names.index(f"{d}.e1")
        assert np.array_equal(shared[j], own[j])  # the 1st event is never shared
    z = np.concatenate(z)
    # the shared value's own noise is below the unshared mean's (more paths, spread), and Student's
    # t of 7+ degrees of freedom has a variance of at most 1.4: E[z^2] < 2.8 (measured 1.65); the
    # four detectors' z of a class are correlated, so the mean's error counts the classes once
    # (measured mean 0.17; with shared values 10 % high: 2.6)
    assert z.size > 100 and np.mean(z**2) < 2.8 and abs(np.mean(z)) < 4.0 * np.sqrt(2.8 / (z.size / len(DETS)))


@pytest.mark.parametrize("k", [2, 16])
def test_a_class_spreads_its_paths_over_one_point_set(mi, k):
    """Over 8 seeds, the variance of a class's shared e2 against what averaging its pixels'
    independent per-pixel estimates would give (their variance over n), 8 mm blocks: the class's
    pixels taking one point set lower it to about half (16 paths a pixel: measured 0.47-0.64 per
    detector, 0.46-0.55 in 4 mm blocks; each pixel's own points gave 0.98-1.21), and with 2 paths,
    where the set also picks the paths' components, to 0.34-0.43 (mean 0.39; each pixel counting
    its own lobe paths: 0.48-0.56, mean 0.53) (2026-12-06, the spread being that of 8 seeds'
    variances)."""
    scene = em.load_scene("corrugated_chamber", res=48, field=10)
    spp = scene.set_quality("default")
    scene.configure(bounce_samples=k, bounce_share=8.0)  # as measured (the preset's paths and block aside)
    integ = scene.integrator

    def stack(seed0):
        return np.array([integ.render_planes(scene.scene, 0, seed0 + k, spp)[0].copy() for k in range(8)],
                        dtype=np.float64)

    shared = stack(0)
    c = integ.geometry_classes()
    names = integ.channel_names()
    scene.configure(bounce_share=0.0)
    own = stack(100)
    big = c.counts >= 8
    ratios = []
    for d in DETS:
        i = names.index(f"{d}.e2")
        v_shared = np.bincount(c.flat, weights=shared[:, i].reshape(8, -1).var(axis=0, ddof=1)) / c.counts
        v_mean = np.bincount(c.flat, weights=own[:, i].reshape(8, -1).var(axis=0, ddof=1)) / c.counts**2
        ratios.append(v_shared[big].sum() / v_mean[big].sum())
    assert big.sum() > 50 and max(ratios) < 0.8, ratios
    if k <= PICK_MAX_PATHS:  # the point set picks the components too
        assert np.mean(ratios) < 0.46, ratios
