"""The Examples sections of the public API's docstrings run as written (numpydoc; issue 24).

Each module's examples run with :func:`doctest.testmod` in a fresh working folder; the scenes they
render are tiny (``flat_plate`` at 4 x 4 pixels), so the whole list takes seconds.
"""

import doctest
import importlib

import pytest

#: Every module whose docstrings hold Examples; tests/test_house.py checks that each public name's
#: module is here (an Examples section that no test runs would rot).
MODULES = [
    "elo_mitsuba.schema", "elo_mitsuba.analysis.chain", "elo_mitsuba.analysis.noise",
    "elo_mitsuba.render", "elo_mitsuba.options", "elo_mitsuba.result", "elo_mitsuba.arguments", "elo_mitsuba.errors", "elo_mitsuba.runtime", "elo_mitsuba.grid",
    "elo_mitsuba.heightmap", "elo_mitsuba.mesh", "elo_mitsuba.exr", "elo_mitsuba.budget",
    "elo_mitsuba.physics.backscatter", "elo_mitsuba.physics.scattering", "elo_mitsuba.physics.solid_angle",
    "elo_mitsuba.physics.materials",
    "elo_mitsuba.analysis.layout", "elo_mitsuba.analysis.reflectance", "elo_mitsuba.analysis.point_detector",
    "elo_mitsuba.analysis.stsa", "elo_mitsuba.analysis.gradient", "elo_mitsuba.analysis.integrate",
    "elo_mitsuba.analysis.model_gradient", "elo_mitsuba.analysis.detector_model", "elo_mitsuba.analysis.precision", "elo_mitsuba.design.geometry", "elo_mitsuba.design.spec", "elo_mitsuba.design.evaluate",
    "elo_mitsuba.design.store", "elo_mitsuba.design.optimize", "elo_mitsuba.design.results", "elo_mitsuba.sweeps.run", "elo_mitsuba.objects.stepped_layer",
    "elo_mitsuba.objects.rough_layer", "elo_mitsuba.analysis.local_inversion", "elo_mitsuba.scene_files",
    "elo_mitsuba.analysis.step_offsets", "elo_mitsuba.analysis.inversion", "elo_mitsuba.analysis.height_solver",
    "elo_mitsuba.analysis.scan_geometry", "elo_mitsuba.analysis.calibration", "elo_mitsuba.analysis.quadric",
    "elo_mitsuba.analysis.jit_arrays", "elo_mitsuba.cli.invert", "validation.study_defects", "elo_mitsuba.analysis.fine_band",
]
#: Modules that document conventions without a runnable example (yet).
NO_EXAMPLES = {"elo_mitsuba.analysis.noise"}


@pytest.mark.parametrize("module", MODULES)
def test_examples_run(module, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    mod = importlib.import_module(module)
    result = doctest.testmod(mod, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE, verbose=False)
    assert result.failed == 0, f"{module}: {result.failed} of {result.attempted} examples failed"
    if module not in NO_EXAMPLES:
        assert result.attempted > 0, f"{module}: no examples ran"
