"""Unbounded work is estimated before it starts: refused where it cannot fit in memory, noted
where it is long, and shown as progress (tests/test_progress.py)."""

import pytest

import elo_mitsuba as em

from elo_mitsuba import budget
from elo_mitsuba.cli import main


def test_memory_that_cannot_fit_is_refused_with_the_numbers():
    with pytest.raises(em.EloInputError, match=r"a 100000x100000 render with 4 channels needs about 1.2 TB of memory, "
                                               r"1 GB is available"):
        budget.check_render((100000, 100000), 5, 1, 1, 1, available=10 ** 9)
    assert budget.check_render((1500, 1500), 13, 1, 2, 1, available=10 ** 10) == []  # the README's render


def test_long_renders_and_big_kernels_get_a_note():
    notes = budget.check_render((64, 64), 5, 10 ** 9, 1, 10 ** 6, available=10 ** 10, force=True)  # asked for
    assert any("4.1e+12 samples" in n and "days" in n for n in notes)
    assert any("compiling the kernel" in n for n in budget.check_render((8, 8), 29, 1, 7, 1, available=10 ** 10))


def test_events_beyond_the_unrolled_limit_are_refused():
    scene = em.load_scene("flat_plate", res=2)
    with pytest.raises(em.EloInputError, match=r"events=100; must be in \[1, 10\].*compile time grows"):
        scene.render(events=100)


def test_cli_refuses_a_resolution_that_cannot_fit(tmp_path, capsys):
    assert main(["render", "flat_plate", "-o", str(tmp_path / "o.exr"), "--resolution", "100000"]) == 2
    err = capsys.readouterr().err
    # the error estimate renders two halves (two sets of channel planes): 1.6 TB, was 1.2 TB in one pass
    assert "needs about 1.6 TB of memory" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o.exr").exists()


def test_one_pass_for_both_halves_only_where_it_fits(monkeypatch):
    """A 1-spp render with events >= 2 takes both halves in one pass (its film holds both halves'
    channels) where that fits in memory; where only two passes' film fits, it renders two passes
    (the same images' statistics, no refusal)."""
    from elo_mitsuba.budget import detector_points, estimate

    scene = em.load_scene("corrugated_chamber", res=32)
    cls = type(scene.integrator)
    calls = []
    for name in ("render_planes", "render_halves"):
        original = getattr(cls, name)
        monkeypatch.setattr(cls, name, lambda self, *a, _o=original, _n=name, **k: calls.append(_n) or _o(self, *a, **k))
    scene.render(quality="default", events=2, progress=False)
    assert calls == ["render_halves"]
    names = scene.integrator.channel_names()
    one = len(names) + 1 + len(scene.integrator.mean_channels())
    work = [estimate((32, 32), c, 1, 2, 1, detector_points(scene.integrator))["memory_bytes"] for c in (one, one + len(names))]
    monkeypatch.setattr(budget, "memory_limit", lambda: (int(sum(work) / 2), "set by the test"))
    calls.clear()
    result = scene.render(quality="default", events=2, progress=False)
    assert calls == ["render_planes", "render_planes"] and result.errors
