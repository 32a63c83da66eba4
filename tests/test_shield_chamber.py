"""The shipped heat-shield scene (scenes_xml/shield_chamber.xml, issue 26): the shield sits where
its file says, it is a closed slab (rims included: no electron from the field meets the back of a
face), it leaves the 1st event of the default layout alone (every line of sight passes its
opening) and takes part of the chamber's 2nd event away; a lower layout looks through the ring.
"""

from __future__ import annotations

import numpy as np
import pytest

import elo_mitsuba as em
from elo_mitsuba.scene_files import shipped_scenes

#: (id suffix, x range, y range) of the ring's four parts as parts/heat_shield.xml documents them.
PARTS = {"right": ((100, 300), (-300, 300)), "left": ((-300, -100), (-300, 300)),
         "back": ((-100, 100), (100, 300)), "front": ((-100, 100), (-300, -100))}


@pytest.fixture(scope="module")
def scenes(mi):
    return em.load_scene("shield_chamber", res=8), em.load_scene("athene_flat", res=8)


def test_shipped_and_the_shield_is_where_documented(scenes):
    """Vertical rays (Mitsuba merges shapes that share a BSDF, so the ring is probed, not looked up):
    inside the ring a ray from z = 50 upwards meets the lower face at z = 100, facing down, and a ray
    from z = 200 downwards the upper face at z = 102, facing up; through the opening and outside the
    ring they pass on (to the ceiling/its opening, or to the floor/plate at z = 0)."""
    mi = em.ensure_variant()
    assert "shield_chamber" in shipped_scenes()
    scene = scenes[0].scene
    ring = [(150, 0), (-150, 0), (0, 150), (0, -150), (299, 299), (-299, -299), (101, 0), (0, -101)]
    free = [(0, 0), (99, 99), (-99, 0), (40, -40), (310, 0), (0, 320)]
    for (x, y), inside in [(p, True) for p in ring] + [(p, False) for p in free]:
        up = scene.ray_intersect(mi.Ray3f(mi.Point3f(x, y, 50.0), mi.Vector3f(0, 0, 1)))
        down = scene.ray_intersect(mi.Ray3f(mi.Point3f(x, y, 200.0), mi.Vector3f(0, 0, -1)))
        z_up = float(np.ravel(up.p)[2]) if bool(up.is_valid()[0]) else np.inf
        z_down = float(np.ravel(down.p)[2])
        if inside:
            assert z_up == pytest.approx(100.0, abs=1e-3) and np.ravel(up.n)[2] == pytest.approx(-1.0), (x, y)
            assert z_down == pytest.approx(102.0, abs=1e-3) and np.ravel(down.n)[2] == pytest.approx(1.0), (x, y)
        else:
            assert z_up > 300 and z_down == pytest.approx(0.0, abs=1e-3), (x, y, z_up, z_down)


def test_the_slab_is_closed_rims_face_out_and_nothing_is_met_from_behind(scenes):
    """Rays from the axis to the inner rims at mid-height meet them facing the axis; and no plane of
    a shipped chamber scene is met from behind by electrons leaving the field (without the inner
    rims, 1.1 % of them entered the slab and ended on the back of its upper face)."""
    mi = em.ensure_variant()
    scene = scenes[0].scene
    for target, normal in (((100, 0, 101), (-1, 0, 0)), ((-100, 30, 100.5), (1, 0, 0)), ((20, 100, 101.8), (0, -1, 0)),
                           ((0, -100, 101), (0, 1, 0))):
        o = mi.Point3f(0.0, 0.0, 0.01)
        hit = scene.ray_intersect(mi.Ray3f(o, mi.Vector3f(np.subtract(target, (0, 0, 0.01)) /
                                                          np.linalg.norm(np.subtract(target, (0, 0, 0.01))))))
        assert np.allclose(np.ravel(hit.p), target, atol=1e-3) and np.allclose(np.ravel(hit.n), normal), target
    from elo_mitsuba.plugins._relief import beam_probe, surfaces_met_from_behind

    for name in ("shield_chamber", "athene_flat", "melt_chamber", "corrugated_chamber"):
        loaded = em.load_scene(name, res=4).scene  # the render's note is this probe's (test_bad_input_more.py)
        beam = loaded.sensors()[0]
        walls = [s for s in loaded.shapes() if not s.is_emitter()]
        assert not surfaces_met_from_behind(loaded, walls, beam, lambda: beam_probe(loaded, beam)), name


def test_default_layout_first_event_unshadowed_second_event_reduced(scenes):
    """e1 equals athene_flat's bit for bit (the quadrature with one ray per triangle is
    deterministic: no line of sight is blocked); e2 drops well beyond the noise."""
    shield, plain = scenes
    out = []
    for scene in (shield, plain):
        scene.configure(detector_sampling="quadrature", quadrature_visibility="triangle", events=2,
                        bounce_detector_samples=1)
        out.append(scene.render(spp=64, seed=5, progress=False, quality="custom"))
    for d in ("right", "left", "back", "front"):
        assert np.array_equal(out[0].channels[f"{d}.e1"], out[1].channels[f"{d}.e1"])
        a, b = out[0].channels[f"{d}.e2"].mean(), out[1].channels[f"{d}.e2"].mean()
        err = np.hypot(out[0].errors[f"{d}.e2"].mean(), out[1].errors[f"{d}.e2"].mean()) / np.sqrt(64)
        assert a < b - 5 * err, (d, a, b, err)


def test_lower_layout_sees_the_field_through_the_ring(mi):
    """zeta50 (d_h 192.7, d_w 229.6): the ring shadows part of the 1st event (as documented)."""
    out = []
    for name in ("shield_chamber", "athene_flat"):
        scene = em.load_scene(name, res=4, layout="zeta50")
        scene.configure(detector_sampling="quadrature", quadrature_visibility="triangle", events=1)
        out.append(scene.render(spp=1, seed=1, progress=False, quality="custom").channels["right"])
    assert np.all(out[0] <= out[1]) and out[0].mean() < 0.9 * out[1].mean()
