"""EloOptions: validated once, changed only through configure(), recorded whole, applied."""

import dataclasses

import numpy as np
import pytest
from forward_scenes import flat_scene

import elo_mitsuba as em
from elo_mitsuba.constants import BEAM_CURRENT_A, TRANSIMPEDANCE_V_PER_A
from elo_mitsuba.options import (MAX_BOUNCE_SAMPLES, MAX_BOUNCE_SPP, QUALITY_PRESETS, EloOptions, filter_window_levels,
                                 quality_options)

BAD = [
    ("events", 0, r"events=0; must be in \[1, 10\]"), ("events", 2.5, "whole number"), ("events", True, "number"),
    ("detector_sampling", "grid", "allowed: independent, stratified, quadrature"),
    ("detector_samples", 0, ">= 1"), ("bounce_detector_samples", -1, ">= 1"),
    ("quadrature_triangles", 3, r"\[4, 256\]"), ("quadrature_triangles", 257, r"\[4, 256\]"),
    ("quadrature_visibility", "all", "sampled, triangle"), ("bounce_samples", 0, ">= 1"),
    ("bounce_fraction", 0.0, r"\(0, 1\]"), ("bounce_fraction", 1.5, r"\(0, 1\]"),
    ("bounce_filter", -1.0, "mm; must be >= 0"), ("bounce_filter", float("nan"), ">= 0"),
    ("bounce_share", float("inf"), "must be a finite number >= 0"),
    ("bounce_filter_angle", 90.0, r"\(0, 90\)"), ("bounce_min", 5000.0, r"\[0, 4096\]"),
    ("units", "volts", "allowed: fraction, voltage"), ("beam_current", 0.0, "> 0"),
    ("transimpedance", float("inf"), "> 0"), ("count_rays", 1, "true or false"), ("events", "two", "number"),
]


@pytest.mark.parametrize("name,value,message", BAD)
def test_every_option_refuses_a_bad_value_in_one_line(name, value, message):
    with pytest.raises(em.EloInputError, match=message) as err:
        EloOptions().replace(**{name: value})
    assert str(err.value).startswith(f"elo: {name}=") and "\n" not in str(err.value)


def test_unknown_option_and_defaults():
    with pytest.raises(em.EloInputError, match="no option 'spp'; options are events"):
        EloOptions().replace(spp=4)
    o = EloOptions(detector_samples=3)
    assert o.bounce_detector_samples == 3  # follows detector_samples unless given
    assert o.replace(events=2).bounce_detector_samples == 3 and o.replace(events=2).events == 2
    assert o.as_dict()["beam_current"] == BEAM_CURRENT_A and len(o.as_dict()) == len(dataclasses.fields(o))


def test_xml_options_are_read_once_and_bad_ones_refused_at_load(mi):
    integ = mi.load_dict({"type": "elo", "events": 3, "units": "voltage", "bounce_fraction": 0.5})
    assert integ.options == EloOptions(events=3, units="voltage", bounce_fraction=0.5)
    assert integ.events == 3 and integ.units == "voltage"
    with pytest.raises(Exception, match="units='volts'; allowed: fraction, voltage"):
        mi.load_dict({"type": "elo", "units": "volts"})


def test_options_are_read_only_attributes(mi):
    integ = mi.load_dict({"type": "elo"})
    with pytest.raises(em.EloInputError, match=r"read-only; use integrator.configure"):
        integ.units = "voltage"
    with pytest.raises(em.EloInputError, match="takes EloOptions"):
        integ.configure({"units": "voltage"})
    assert integ.units == "fraction"


def test_configured_units_are_applied_and_recorded(mi):
    plain = em.load_scene("flat_plate", res=6).render(quality="default")
    volts_scene = em.load_scene("flat_plate", res=6)
    volts_scene.configure(units="voltage")
    volts = volts_scene.render(quality="default")
    scale = BEAM_CURRENT_A * TRANSIMPEDANCE_V_PER_A
    for name in plain.detectors:  # U_d = N_d/N_0 I_b T (Eq. 9), exactly what was configured
        np.testing.assert_allclose(volts.channels[name], plain.channels[name] * scale, rtol=2e-6)
    recorded = volts.metadata["integrator_options"]
    assert recorded == volts_scene.options.as_dict() and recorded["units"] == "voltage"
    assert volts.metadata["units"] == "V" and recorded["detector_sampling"] == "quadrature"


def test_quality_options_spread_the_bounce_budget():
    base = EloOptions(events=2, units="voltage")
    for name, preset in QUALITY_PRESETS.items():
        for pixel_mm in (0.0533, 0.3125, 1.6):
            o, spp = quality_options(name, base, pixel_mm=pixel_mm, fwhm_mm=0.0, traced_events=2)
            assert o.units == "voltage" and o.events == 2 and o.detector_sampling == "quadrature"
            level = filter_window_levels(preset["bounce_filter"], pixel_mm)
            window = 1 if level is None else 3 * 2**level  # the filter's window (3 x 3 tiles of 2^k px)
            paths = o.bounce_fraction * o.bounce_samples * spp * window**2
            # capped where a pixel would need more than MAX_BOUNCE_SPP samples (one-pixel windows)
            budget = min(preset["bounce_budget"], MAX_BOUNCE_SPP * MAX_BOUNCE_SAMPLES * window**2)
            if spp == 1:
                assert paths == pytest.approx(budget, rel=1e-9)  # the budget, exactly spent
            else:  # every sample traces: rounded up to whole paths per sample
                assert o.bounce_fraction == 1.0 and budget <= paths < budget * (1 + 1 / (o.bounce_samples - 1 or 1))
            assert 1 <= o.bounce_samples <= 8
        _, spp_blur = quality_options(name, base, pixel_mm=0.05, fwhm_mm=0.27, traced_events=1)
        assert spp_blur == preset["spp_blur"]
    with pytest.raises(em.EloInputError, match="choose one of draft, default, reference, unbiased, scene"):
        quality_options("ultra", base, pixel_mm=0.05, fwhm_mm=0.0, traced_events=1)


def test_flat_scene_options_via_dict(mi):
    scene = mi.load_dict(flat_scene(mi, res=2, integrator={"type": "elo", "detector_sampling": "stratified",
                                                            "detector_samples": 4}))
    assert scene.integrator().options.bounce_detector_samples == 4


def test_filter_windows_at_the_benchmarked_resolutions():
    """1 mm half-width: 12 px windows at 512^2, 6 px at 250^2 over 80 mm, 48 px at 1500^2 (the budget
    used to assume (2r+1)^2 = 13^2, 5^2 and 39^2 pixels)."""
    assert filter_window_levels(1.0, 80.0 / 512) == 2 and filter_window_levels(1.0, 80.0 / 1500) == 4
    assert filter_window_levels(1.0, 80.0 / 250) == 1 and filter_window_levels(1.0, 1.5) is None
