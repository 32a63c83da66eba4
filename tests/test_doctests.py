"""The Examples sections of the pipeline's and the file conventions' docstrings run as written."""

import doctest
import importlib

import pytest


@pytest.mark.parametrize("module", ["elo_mitsuba.schema", "elo_mitsuba.analysis.chain", "elo_mitsuba.analysis.noise"])
def test_examples_run(module, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    mod = importlib.import_module(module)
    result = doctest.testmod(mod, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE, verbose=False)
    assert result.failed == 0, f"{module}: {result.failed} of {result.attempted} examples failed"
    if module != "elo_mitsuba.analysis.noise":
        assert result.attempted > 0
