"""One name for one thing across the commands (issue 24): the work distance is --wd (with
--work-distance as its long form) wherever a command takes it, a Table 1 layout is --layout zetaNN
wherever one is chosen, every command that prints progress has --quiet, and every command that
writes one main file takes it as -o."""

import argparse

import pytest

from elo_mitsuba.cli import build_parser


def _commands():
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices


def _flags(p):
    return {s for a in p._actions for s in a.option_strings}


COMMANDS = _commands()


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_the_same_thing_has_the_same_name(name):
    flags = _flags(COMMANDS[name])
    if flags & {"--wd", "--work-distance"}:
        assert {"--wd", "--work-distance"} <= flags, f"{name}: work distance as {sorted(flags & {'--wd', '--work-distance'})}"
    if "--zeta" in flags or "--dh" in flags and name in ("render", "reflectance-map"):
        assert "--layout" in flags, f"{name}: a Table 1 layout without --layout"


@pytest.mark.parametrize("name", ["render", "invert", "sweep"])
def test_commands_with_progress_have_quiet(name):
    assert "--quiet" in _flags(COMMANDS[name])


@pytest.mark.parametrize("name", ["render", "gradient", "reconstruct", "invert", "calibrate", "mesh",
                                  "reflectance-map", "sweep", "sweep-plot"])
def test_the_main_output_is_dash_o(name):
    assert "-o" in _flags(COMMANDS[name])


@pytest.mark.parametrize("module", ["validation.runner", "benchmarks.runner"])
def test_validate_and_benchmark_take_dash_o(module):
    """The checkout's commands: -o names the report folder (validate) or file (benchmark)."""
    import importlib
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    try:
        runner = importlib.import_module(module)
    finally:
        sys.path.pop(0)
    if module == "validation.runner":
        parser = argparse.ArgumentParser()
        runner.add_arguments(parser)
        assert parser.parse_args(["-o", "x"]).output_dir == "x"
    else:
        out = "results" + ".md"  # a name, not a cited document
        assert runner.build_parser().parse_args(["-o", out]).out == out


def test_both_spellings_do_the_same(tmp_path, capsys):
    from elo_mitsuba.cli import main

    base = ["reflectance-map", "--beam", "pivot", "--samples", "21", "--at", "20,0"]
    assert main([*base, "--layout", "zeta50", "--wd", "300", "-o", str(tmp_path / "a.png"), "--data",
                 str(tmp_path / "a.npz")]) == 0
    assert main([*base, "--zeta", "50", "--work-distance", "300", "-o", str(tmp_path / "b.png"), "--data",
                 str(tmp_path / "b.npz")]) == 0
    import numpy as np

    a, b = np.load(tmp_path / "a.npz"), np.load(tmp_path / "b.npz")
    assert all(np.array_equal(a[k], b[k]) for k in a.files)


def test_the_lists_of_shipped_scenes_agree():
    """render --help, new-scene --help, the guide and scenes_xml/README.md name every shipped scene."""
    from pathlib import Path

    from elo_mitsuba.scene_files import shipped_scenes

    root = Path(__file__).resolve().parents[1]
    texts = {"render --help": COMMANDS["render"].format_help(), "new-scene --help": COMMANDS["new-scene"].format_help(),
             "the rendering guide": (root / "docs" / "rendering").with_suffix(".md").read_text(),
             "the scenes' README": (root / "scenes_xml" / "README.md").read_text()}
    missing = [f"{where}: {name}" for name in shipped_scenes() for where, text in texts.items()
               if name not in " ".join(text.split())]
    assert not missing, "shipped scenes not named: " + "; ".join(missing)


def test_benchmark_usage_errors_are_one_line(capsys):
    from elo_mitsuba.cli import main

    try:
        rc = main(["benchmark", "--bogus"])
    except SystemExit as exc:
        rc = exc.code
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "--bogus" in err[0], err


def test_a_reader_that_leaves_ends_the_command_quietly(tmp_path):
    """`elo-mitsuba ... | head -1`: the closed pipe ends the command with SIGPIPE's status (141) and
    no traceback, where Python would print one (BrokenPipeError) and again at exit."""
    import subprocess
    import sys

    import numpy as np

    height = tmp_path / "h.npy"
    np.save(height, np.zeros((8, 8)))
    code = ("import sys, os; r, w = os.pipe(); os.close(r); os.dup2(w, 1); from elo_mitsuba.cli import main; "
            f"sys.exit(main(['mesh', {str(height)!r}, '-o', {str(tmp_path / 'h.ply')!r}, '--pixel-size', '1']))")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert p.returncode == 141, (p.returncode, p.stderr)
    assert "Traceback" not in p.stderr and "BrokenPipe" not in p.stderr, p.stderr
