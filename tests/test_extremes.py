"""Numerical stability at the extremes: no NaN/Inf anywhere, impossible input
gets a clear error. Tiny resolutions; the whole file runs in well under a minute."""

import numpy as np
import pytest

from forward_scenes import flat_scene

import elo_mitsuba as em

mi = em.ensure_variant()

DETECTORS = ("right", "left", "back", "front")
STRATEGIES = ({}, {"detector_sampling": "stratified", "detector_samples": 4},
              {"detector_sampling": "quadrature", "quadrature_triangles": 8})


def render(scene_dict, spp=4, seed=0, **options):
    scene = mi.load_dict(scene_dict)
    integ = scene.integrator()
    integ.configure(integ.options.replace(**options))
    img = np.array(mi.render(scene, spp=spp, seed=seed), dtype=np.float64)
    assert np.all(np.isfinite(img)), "NaN/Inf in the image"
    assert np.all(img >= 0), "negative electron counts"
    return {n: img[..., i + 1] for i, n in enumerate(integ.channel_names())}


def disk(center, normal, radius=25.0):
    c = np.asarray(center, float)
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    up = [0, 0, 1] if abs(n[2]) < 0.9 else [1, 0, 0]
    return {"type": "disk", "emitter": {"type": "area"}, "bsdf": {"type": "diffuse", "reflectance": 0.0},
            "to_world": mi.ScalarTransform4f().look_at(origin=c.tolist(), target=(c + n).tolist(), up=up)
            @ mi.ScalarTransform4f().scale(radius)}


@pytest.mark.parametrize("options", STRATEGIES)
def test_grazing_beam(options):
    """wd = 5 mm over a 400 mm field: the beam meets the plate at up to 89.6 deg (k ~ 6.9)."""
    ch = render(flat_scene(mi, res=5, field=400.0, wd=5.0, wall=True, events=2), spp=4, **options)
    assert ch["right"].max() > 0


@pytest.mark.parametrize("options", STRATEGIES)
def test_detector_nearly_edge_on(options):
    """A detector whose face is 0.06 deg from edge-on as seen from the field centre."""
    scene = flat_scene(mi, res=3, field=40.0)
    c = np.array([127.0, 0.0, 272.0])
    towards = -c / np.linalg.norm(c)
    side = np.array([0.0, 1.0, 0.0])
    scene["right"] = disk(c, side + 1e-3 * towards)
    ch = render(scene, front_only="right", **options)
    # rows at y > 0 see the face at a few degrees, y < 0 its shielded back (nothing)
    assert np.all(ch["right"][-1] == 0) and ch["right"][0].min() > 0
    assert ch["right"].max() < 0.1 * ch["left"].min()
    both = render(scene, **options)  # collecting on both faces, the y < 0 rows see the back
    assert both["right"][-1].min() > 0 and both["right"].max() < 0.1 * both["left"].min()


@pytest.mark.parametrize("options", STRATEGIES)
def test_detector_fully_masked_by_a_steep_flank(options):
    """A 320 mm high wall between the field and the right detector: exactly nothing arrives."""
    scene = flat_scene(mi, res=4, field=40.0)
    scene["flank"] = {"type": "rectangle", "bsdf": {"type": "elo_bse"},
                      "to_world": mi.ScalarTransform4f().translate([100.0, 0.0, 160.0])
                      @ mi.ScalarTransform4f().rotate([0, 1, 0], -90.0)
                      @ mi.ScalarTransform4f().scale([160.0, 200.0, 1.0])}
    ch = render(scene, **options)
    assert np.all(ch["right"] == 0) and np.all(ch["left"] > 0)


@pytest.mark.parametrize("options", STRATEGIES)
def test_detector_that_sees_nothing(options):
    """A detector under the plate, facing up into it, and one above everything facing up with
    its back shielded: zeros, not NaN."""
    scene = flat_scene(mi, res=3, field=40.0, events=2, wall=True)
    scene["right"] = disk([0.0, 0.0, -50.0], [0, 0, 1])
    scene["left"] = disk([-127.0, 0.0, 450.0], [0.0, 0.0, 1.0])  # above everything, facing up
    ch = render(scene, front_only="left", **options)
    assert np.all(ch["right"] == 0) and np.all(ch["left"] == 0) and ch["back"].min() > 0
    both = render(scene, **options)  # the plate sees the left detector's back
    assert np.all(both["right"] == 0) and both["left"].min() > 0


@pytest.mark.parametrize("lobe_width", [1e6, 1e-3])
def test_extreme_lobe_exponents(lobe_width):
    """k -> 0 (lobe width 1e6 deg) and k up to 9e4 (1e-3 deg) at oblique incidence."""
    scene = flat_scene(mi, res=4, field=240.0, wd=150.0, wall=True, events=2)
    scene["plate"]["bsdf"]["lobe_width"] = lobe_width
    for options in STRATEGIES:
        ch = render(scene, **options)
        # the electrons collected never exceed the backscattered ones (eta < 0.5 here)
        assert sum(ch[n] for n in DETECTORS).max() < 0.5


@pytest.mark.parametrize("radius", [1e-3, 100.0])
def test_tiny_and_huge_detectors(radius):
    scene = flat_scene(mi, res=3, field=40.0)
    c = np.array([127.0, 0.0, 272.0])
    scene["right"] = disk(c, -c, radius)
    q = render(scene, spp=1, detector_sampling="quadrature", quadrature_triangles=24)
    s = render(scene, spp=256, seed=1, detector_sampling="stratified", detector_samples=4)
    i = render(scene, spp=4)
    assert q["right"].min() > 0 and i["right"].min() > 0
    np.testing.assert_allclose(q["right"], s["right"], rtol=0.01 if radius < 1 else 0.03)


@pytest.mark.parametrize("width, height", [(1, 1), (1, 7), (7, 1)])
def test_degenerate_images(width, height):
    scene = flat_scene(mi, res=width, height=height, field=80.0, wall=True, events=2)
    for options in STRATEGIES + ({"detector_sampling": "quadrature", "bounce_filter": 5.0,
                                  "bounce_fraction": 0.5, "bounce_min": 2.0},):
        ch = render(scene, **options)
        assert ch["right"].shape == (height, width)


@pytest.mark.parametrize("field", [1.0, 500.0])
def test_tiny_and_huge_fields(field):
    """1 mm (19 um pixels at 53 px) and 500 mm (beyond the 300 mm plate: the beam also misses)."""
    scene = flat_scene(mi, res=5, field=field, wall=True, events=2)
    for options in STRATEGIES:
        render(scene, **options)
    quality = em.load_scene("athene_flat", res=5, field=field)
    result = quality.render(quality="default")
    assert all(np.all(np.isfinite(v)) for v in result.channels.values())


def test_normalised_differences_float32_cancellation():
    """M_x = (R - L)/(R + L) for float32 images with R and L one ulp apart, equal, zero, huge."""
    from elo_mitsuba.analysis.stsa import normalised_differences

    one = np.float32(1.0)
    r = np.array([[one, one, 0.0, 3e38, 1e-40]], np.float32)
    l = np.array([[np.nextafter(one, np.float32(2)), one, 0.0, 3e38, 1e-40]], np.float32)
    imgs = {"right": r, "left": l, "back": np.ones_like(r), "front": np.ones_like(r)}
    mx, my, mask = normalised_differences(imgs)
    assert np.all(np.isfinite(mx)) and np.all(np.isfinite(my))
    assert mx[0, 0] == pytest.approx(-2.0**-24, rel=1e-6)  # not 0, not garbage
    assert mx[0, 1] == 0 and mx[0, 3] == 0
    assert mask[0, 2] and mask[0, 4] and not mask[0, 3]  # R + L = 0 (or subnormal) is masked


def test_impossible_input_gives_clear_errors(tmp_path):
    bad = [({"events": 0}, "events"), ({"detector_sampling": "magic"}, "detector_sampling"),
           ({"quadrature_triangles": 2}, "quadrature_triangles"), ({"bounce_fraction": 0.0}, "bounce_fraction"),
           ({"bounce_fraction": 1.5}, "bounce_fraction"), ({"bounce_filter": -1.0}, "bounce_filter"),
           ({"bounce_samples": 0}, "bounce_samples"), ({"bounce_min": -1.0}, "bounce_min"),
           ({"detector_samples": 0}, "detector_samples")]
    for props, word in bad:
        with pytest.raises(Exception, match=word):
            mi.load_dict({"type": "elo", **props})
    # a detector of zero size
    scene = flat_scene(mi, res=2)
    scene["right"] = disk([127.0, 0.0, 272.0], [-127.0, 0.0, -272.0], radius=1e-30)
    loaded = mi.load_dict(scene)
    integ = loaded.integrator()
    integ.configure(integ.options.replace(detector_sampling="quadrature"))
    with pytest.raises(em.EloInputError, match="zero area|non-finite"):
        integ.prepare_scene(loaded)
    # an edge-on detector and one facing away from the field: refused by name
    xml = tmp_path / "edge.xml"
    xml.write_text(
        '<scene version="3.0.0"><integrator type="elo"/><sensor type="elo_beam"><film type="hdrfilm">'
        '<integer name="width" value="2"/><integer name="height" value="2"/><rfilter type="box"/></film></sensor>'
        '<shape type="rectangle"><transform name="to_world"><scale value="100"/></transform><bsdf type="elo_bse"/></shape>'
        '<shape type="disk" id="right"><transform name="to_world"><scale value="25"/>'
        '<lookat origin="127, 0, 272" target="127, 1, 272" up="0, 0, 1"/></transform><emitter type="area"/></shape>'
        '</scene>')
    with pytest.raises(em.EloInputError, match="faces away"):
        em.load_scene(xml)
    with pytest.raises(em.EloInputError, match="quality"):
        em.load_scene("flat_plate", res=2).render(quality="best")
