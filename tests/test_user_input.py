"""What a user sets takes effect or is refused in one line, before anything changes."""

import subprocess
import sys

import numpy as np
import pytest
from forward_scenes import flat_scene

import elo_mitsuba as em
from elo_mitsuba.exr import write_exr

mi = em.ensure_variant()


def _cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "elo_mitsuba", *args], capture_output=True, text=True,
                          cwd=cwd, timeout=300)


def test_a_refused_detector_move_is_not_kept():
    scene = em.load_scene("flat_plate", res=4)
    before = scene.detector_geometry()["right"]
    with pytest.raises(em.EloInputError, match="at or below the build plane"):
        scene.set_detector("right", center=(127.0, 0.0, -10.0))
    assert scene.detector_geometry()["right"] == before  # the next render uses the old detector
    with pytest.raises(em.EloInputError, match="is the origin"):
        scene.set_detector("right", center=(0.0, 0.0, 0.0))
    assert scene.detector_geometry()["right"] == before
    assert np.all(np.isfinite(scene.render(quality="default").channels["right"]))


@pytest.mark.parametrize("kwargs,message", [
    ({"seed": 1 << 32}, r"seed=4294967296; must be a whole number in \[0, 4294967295\]"),
    ({"seed": -1}, "seed=-1"), ({"spp": float("nan")}, r"spp=nan; must be a whole number in \[1, 4294967295\]"),
    ({"spp": 0}, "spp=0"), ({"spp": 2.5}, "spp=2.5"),
])
def test_render_refuses_bad_counts_before_any_work(kwargs, message):
    scene = em.load_scene("flat_plate", res=2)
    options = scene.options
    with pytest.raises(em.EloInputError, match=message):
        scene.render(quality="draft", **kwargs)
    assert scene.options == options  # nothing was changed on the way


def test_large_seeds_render():
    scene = em.load_scene("flat_plate", res=2)
    assert scene.render(seed=(1 << 32) - 1, spp=2, quality="scene").metadata["seed"] == (1 << 32) - 1


def test_a_surface_without_elo_bse_is_refused_or_absorbs():
    d = flat_scene(mi, res=2)
    d["plate"]["bsdf"] = {"type": "diffuse"}  # reflectance 0.5: a light-scattering law, not the electrons'
    scene = mi.load_dict(d)
    with pytest.raises(em.EloInputError, match="'plate' has a SmoothDiffuse BSDF, which does not describe electron"):
        scene.integrator().prepare_scene(scene)
    d["plate"]["bsdf"] = {"type": "diffuse", "reflectance": 0.0}  # an absorber: nothing comes back
    scene = mi.load_dict(d)
    img = np.array(mi.render(scene, spp=4))
    assert np.all(img == 0)


def test_header_never_stores_nan(tmp_path):
    with pytest.raises(em.EloInputError, match="metadata holds NaN or Inf"):
        write_exr(tmp_path / "x.exr", {"right": np.zeros((2, 2))}, {"detectors": {"right": {"center": [np.nan, 0, 1]}}})
    assert not (tmp_path / "x.exr").exists()


@pytest.mark.parametrize("args,message", [
    (["-D", "spp=64"], "-D spp=64 sets the scene file's sampler, which --quality default replaces; give --spp"),
    # 2, not a large count: the refusal does not depend on it, and with --quality scene each
    # detector sample is traced in the kernel, so 100 of them cost ~40 s of compilation (cold cache)
    (["--detector-samples", "2"], "--detector-samples 2 would change nothing"),
    (["--seed", "4294967296"], "4294967296 is above 4294967295"),
])
def test_cli_refuses_settings_that_would_not_take_effect(tmp_path, args, message):
    r = _cli("render", "flat_plate", "-o", str(tmp_path / "o.exr"), "--resolution", "4", *args)
    assert r.returncode == 2 and message in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) <= 2 and not (tmp_path / "o.exr").exists()
    ok = _cli("render", "flat_plate", "-o", str(tmp_path / "s.exr"), "--resolution", "4", "--quality", "scene",
              *args[:2]) if args[0] != "--seed" else None
    if ok is not None:
        assert ok.returncode == 0, ok.stderr  # with the scene's own sampling they do take effect


def test_the_header_records_the_parameters_as_applied():
    """A scene parameter the render replaced (the sampler's spp under a preset, the events of
    render(events=)) is recorded as applied, not as given: the header never says 64 spp for 1."""
    scene = em.load_scene("flat_plate", res=4, spp=64)
    own = scene.render(progress=False)  # the scene file's sampler: its spp applies
    assert own.metadata["spp"] == 64 and own.metadata["parameters"]["spp"] == "64"
    preset = scene.render(quality="default", events=2, progress=False)
    assert preset.metadata["spp"] == 1 and preset.metadata["events"] == 2
    assert preset.metadata["parameters"]["spp"] == "1" and preset.metadata["parameters"]["events"] == "2"


def test_a_material_set_after_loading_is_not_recorded_as_the_scene_parameter():
    """set_material changes what a shape holds: the header's per-shape 'materials' says it, and the
    scene file's 'material' parameter, no longer applied, is not recorded."""
    scene = em.load_scene("flat_plate", res=4)
    assert scene.render(progress=False).metadata["parameters"]["material"] == "Ti-6Al-4V"
    scene.set_material("plate", "Cu")
    meta = scene.render(progress=False).metadata
    assert meta["materials"]["plate"].startswith("Cu") and "material" not in meta["parameters"]
