"""A render's progress on stderr: a bar on a terminal, plain lines (no carriage returns) in a log."""

import io

import elo_mitsuba as em
from elo_mitsuba import progress


class _Terminal(io.StringIO):
    def isatty(self):
        return True


def test_progress_lines_off_a_terminal(monkeypatch):
    err = io.StringIO()
    monkeypatch.setattr(progress.sys, "stderr", err)
    p = progress.RenderProgress(100, 10, None)
    for k in range(1, 11):
        p(10 * k, 1.0 * k)  # 10 passes, 1 s each: quiet for the first PROGRESS_AFTER_S
    p.end()
    lines = err.getvalue().splitlines()
    assert lines[0].startswith("  render: 30/100 spp (30 %), 3.0 s") and "s left" in lines[0]
    assert len(lines) == 8 and lines[-1].startswith("  render: 100/100 spp (100 %)")
    assert "\r" not in err.getvalue()
    err.truncate(0)
    progress.RenderProgress(100, 1, None)(100, 50.0)  # a single pass: nothing to report
    assert err.getvalue() == ""


def test_progress_asked_for_off_a_terminal_is_lines_from_the_start(monkeypatch):
    err = io.StringIO()
    monkeypatch.setattr(progress.sys, "stderr", err)
    p = progress.RenderProgress(40, 40, True)
    for k in range(1, 41):
        p(k, 0.01 * k)
    p.end()
    lines = err.getvalue().splitlines()
    assert "\r" not in err.getvalue() and len(lines) == 11  # the first, then one per 10 %, none redrawn
    assert lines[0].startswith("  render: 1/40 spp") and lines[-1].startswith("  render: 40/40 spp (100 %)")


def test_progress_on_a_terminal_is_one_bar(monkeypatch):
    err = _Terminal()
    monkeypatch.setattr(progress.sys, "stderr", err)
    p = progress.RenderProgress(100, 10, None)
    for k in range(1, 11):
        p(10 * k, 0.1 * k)
    p.end()
    text = err.getvalue()
    assert "\r" in text and "100/100" in text and "spp" in text  # redrawn in place
    assert text.endswith("\n") and text.rstrip("\n").count("\n") == 0  # one line, left when done


def test_a_render_logged_to_a_file_has_no_carriage_returns(capfd):
    scene = em.load_scene("flat_plate", res=8)
    scene.render(spp=4, progress=True)  # two halves, a pass each
    err = capfd.readouterr().err
    assert "render: 4/4 spp (100 %)" in err and "\r" not in err
