"""Detectors collect on both faces (or on the front only, shielded); plates that backscatter.

Independent references: Eq. 5 by quadrature over the disc (analysis.first_event), and Mitsuba's
own ``path`` integrator, in which a two-sided detector is two one-sided emitter discs back to
back and a backscattering plate is an ``elo_bse`` surface.
"""

import numpy as np
import pytest
from forward_scenes import detector, flat_scene

import elo_mitsuba as em
from elo_mitsuba.analysis.first_event import disc_integral

mi = em.ensure_variant()

R = 25.0
ESTIMATORS = [{"detector_sampling": "independent", "detector_samples": 4},
              {"detector_sampling": "stratified", "detector_samples": 16},
              {"detector_sampling": "quadrature", "quadrature_triangles": 64}]


def _look(origin, target, radius=R):
    return (mi.ScalarTransform4f().look_at(origin=list(origin), target=list(target), up=[0, 0, 1])
            @ mi.ScalarTransform4f().scale(radius))


def _render(scene_dict, spp, seed=0):
    scene = mi.load_dict(scene_dict)
    img = np.array(mi.render(scene, spp=spp, seed=seed), dtype=np.float64)
    return {n: img[..., i + 1] for i, n in enumerate(scene.integrator().channel_names())}, img[..., 0]


def _plate_scene(res, field, integrator, detectors):
    scene = {"type": "scene", "integrator": integrator,
             "sensor": {"type": "elo_beam", "wd": 400.0, "field": field,
                        "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"},
                                 "pixel_format": "luminance"},
                        "sampler": {"type": "independent", "sample_count": 1}},
             "plate": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale(150.0),
                       "bsdf": {"type": "elo_bse", "material": "Ti-6Al-4V"}}}
    scene.update(detectors)
    return scene


@pytest.mark.parametrize("options", ESTIMATORS, ids=lambda o: o["detector_sampling"])
def test_back_face_collects_the_eq5_integral(options):
    """A disc whose front faces away from the plate collects, on its back, exactly what Eq. 5
    gives for that face; shielded (front_only) it collects nothing."""
    c = np.array([60.0, -20.0, 150.0])
    away = {"right": {"type": "disk", "to_world": _look(c, 2 * c), "emitter": {"type": "area"}}}
    res, field = 3, 60.0
    both, _ = _render(_plate_scene(res, field, {"type": "elo", **options}, away), spp=256, seed=1)
    shielded, _ = _render(_plate_scene(res, field, {"type": "elo", "front_only": "right", **options}, away), spp=16)
    assert np.all(shielded["right"] == 0.0)
    xs = -field / 2 + (np.arange(res) + 0.5) * field / res
    for j, y in enumerate(xs[::-1]):
        for i, x in enumerate(xs):
            p = np.array([x, y, 0.0])
            ref = disc_integral(p, p - np.array([0, 0, 400.0]), [0, 0, 1], c, -c, R, "Ti-6Al-4V")
            tol = 2e-3 if options["detector_sampling"] == "quadrature" else 0.03
            assert both["right"][j, i] == pytest.approx(ref, rel=tol), (x, y)


def _ceiling():
    """316L above the detectors facing down: its electrons reach the detectors' backs."""
    return {"type": "rectangle", "bsdf": {"type": "elo_bse", "material": "316L"},
            "to_world": mi.ScalarTransform4f().translate([0, 0, 420.0]) @ mi.ScalarTransform4f().rotate([1, 0, 0], 180)
            @ mi.ScalarTransform4f().scale(400.0)}


def test_two_sided_detectors_equal_path_with_back_to_back_emitters():
    res, field, events = 3, 120.0, 2
    ours_dict = flat_scene(mi, res=res, field=field, events=events)
    ours_dict["ceiling"] = _ceiling()
    ours, total = _render(ours_dict, spp=1024, seed=2)
    front_dict = dict(ours_dict, integrator={"type": "elo", "events": events, "front_only": "*"})
    front, front_total = _render(front_dict, spp=1024, seed=2)
    back_share = (total - front_total) / total
    assert np.all(back_share > 0.05)  # the ceiling makes the back faces matter (measured ~0.1)
    path_dict = dict(ours_dict, integrator={"type": "path", "max_depth": events + 1, "rr_depth": 100})
    for name in ("right", "left", "back", "front"):
        c = np.array(path_dict[name]["to_world"].translation(), float)
        twin = c + 1e-3 * c / np.linalg.norm(c)  # just behind, front face pointing away
        path_dict[f"{name}_back"] = detector(mi, twin, R) | {"to_world": _look(twin, 2 * twin)}
    scene = mi.load_dict(path_dict)
    runs = np.stack([np.array(mi.render(scene, spp=8192, seed=s))[..., 0] for s in range(4)])
    ref, sem = runs.mean(axis=0), runs.std(axis=0, ddof=1) / 2.0
    z = (total - ref) / np.sqrt(sem**2 + (0.003 * ref) ** 2)
    assert np.all(np.abs(z) < 5), (total, ref, sem)
    assert np.all(np.abs(front_total - ref) > 5 * sem)  # one-sided collection would fail this


def test_backscattering_plate_keeps_one_minus_eta():
    """A copper plate keeps 1 - eta_Cu(theta) of what arrives (Eqs. 10-12): Eq. 5 weighted so."""
    c = np.array([127.0, 0.0, 272.0])
    det = {"right": {"type": "disk", "to_world": _look(c, [0, 0, 0]), "emitter": {"type": "area"},
                     "bsdf": {"type": "elo_bse", "material": "Cu"}}}
    res, field = 3, 80.0
    for options in (ESTIMATORS[2], ESTIMATORS[1]):
        ch, _ = _render(_plate_scene(res, field, {"type": "elo", **options}, det), spp=64)
        xs = -field / 2 + (np.arange(res) + 0.5) * field / res
        for j, y in enumerate(xs[::-1]):
            for i, x in enumerate(xs):
                p = np.array([x, y, 0.0])
                beam = p - np.array([0, 0, 400.0])
                ref = disc_integral(p, beam, [0, 0, 1], c, -c, R, "Ti-6Al-4V", collector="Cu")
                full = disc_integral(p, beam, [0, 0, 1], c, -c, R, "Ti-6Al-4V")
                assert ref < 0.75 * full  # copper backscatters ~30 %: the test can tell
                tol = 2e-3 if options["detector_sampling"] == "quadrature" else 0.01
                assert ch["right"][j, i] == pytest.approx(ref, rel=tol)


def test_crosstalk_from_a_backscattering_plate_equals_path():
    """Electrons backscattered by one detector's copper plate reach another (event 2). Mitsuba's
    path, with the plate as a plain elo_bse surface: its depth-3 paths (max_depth 3 minus 2, same
    seed) are exactly that crosstalk."""
    plate_c, det_c, aim = np.array([127.0, 0.0, 90.0]), np.array([127.0, 0.0, 272.0]), [0.0, 0.0, 200.0]
    cu = {"type": "elo_bse", "material": "Cu"}
    ours_det = {"right": {"type": "disk", "to_world": _look(det_c, [0, 0, 0]), "emitter": {"type": "area"}},
                "left": {"type": "disk", "to_world": _look(plate_c, aim, 60.0), "emitter": {"type": "area"},
                         "bsdf": cu}}
    res, field = 2, 60.0
    options = {"type": "elo", "events": 2, "detector_sampling": "stratified", "detector_samples": 4,
               "bounce_samples": 8}
    ours, _ = _render(_plate_scene(res, field, dict(options, front_only="*"), ours_det), spp=4096, seed=3)
    assert np.all(ours["right.e2"] > 3e-3 * ours["right.e1"])  # visible crosstalk
    path_det = {"right": detector(mi, det_c, R),
                "cu_plate": {"type": "disk", "to_world": _look(plate_c, aim, 60.0), "bsdf": cu}}
    depth = []
    for max_depth in (2, 3):
        scene = mi.load_dict(_plate_scene(res, field, {"type": "path", "max_depth": max_depth, "rr_depth": 100},
                                          path_det))
        depth.append(np.stack([np.array(mi.render(scene, spp=16384, seed=s))[..., 0] for s in range(4)]))
    cross = depth[1] - depth[0]
    ref, sem = cross.mean(axis=0), cross.std(axis=0, ddof=1) / 2.0
    np.testing.assert_allclose(ours["right.e2"], ref, rtol=0.05 + 4 * np.max(sem / ref))
    # a two-sided plate turned over (its back now faces the field) is the same plate
    flipped = dict(ours_det, left=dict(ours_det["left"], to_world=_look(plate_c, 2 * plate_c - np.array(aim), 60.0)))
    turned, _ = _render(_plate_scene(res, field, dict(options, front_only="right"), flipped), spp=4096, seed=3)
    for name in ("left", "right.e2"):
        np.testing.assert_allclose(turned[name], ours[name], rtol=0.03)


def test_front_only_names_real_detectors():
    scene = mi.load_dict(flat_scene(mi, res=2, integrator={"type": "elo", "front_only": "right,up"}))
    with pytest.raises(em.EloInputError, match="front_only='right,up' names no detector 'up'"):
        scene.integrator().prepare_scene(scene)
    loaded = em.load_scene("flat_plate", res=4)
    with pytest.raises(em.EloInputError, match="names no detector 'top'; detectors: right, left, back, front"):
        loaded.configure(front_only="top")
    assert loaded.options.front_only == ""  # the refused setting is not kept
    assert loaded.configure(front_only="right, left").front_only == "right, left"


def test_a_sphere_detector_equals_path():
    """A curved detector hides its own far side. The occlusion analysis, which skips shadow rays
    from plate regions nothing can block, took a sphere's far half as seen: the sphere read 3.03e-3
    where Mitsuba's path integrator (an emitting sphere, radiance 1) gives 1.65e-3. Curved
    detectors keep their shadow rays."""
    c = [127.0, 0.0, 272.0]
    sphere = {"type": "sphere", "center": c, "radius": R, "emitter": {"type": "area"},
              "bsdf": {"type": "diffuse", "reflectance": 0.0}}
    res, field = 3, 60.0
    elo = _plate_scene(res, field, {"type": "elo", "detector_sampling": "stratified", "detector_samples": 16},
                       {"right": sphere})
    ours = np.stack([_render(elo, spp=256, seed=s)[0]["right"] for s in range(4)])
    path = mi.load_dict(_plate_scene(res, field, {"type": "path", "max_depth": 2}, {"right": sphere}))
    runs = np.stack([np.array(mi.render(path, spp=4096, seed=s))[..., 0] for s in range(4)])
    ref = runs.mean(axis=0)
    sem = np.sqrt(ours.var(axis=0, ddof=1) / 4 + runs.var(axis=0, ddof=1) / 4)
    z = (ours.mean(axis=0) - ref) / sem
    assert np.all(np.abs(z) < 5), (ours.mean(axis=0), ref, sem)
