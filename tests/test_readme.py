"""The README's and the user guide's commands run top to bottom, each page in an empty folder
(issues 13, 24): every ```bash block, in order, through the CLI in-process, renders at a small
resolution (the pages state the cost of their full-size renders); every ```python block as a
script in a real interpreter (``res=`` made small as well).

Left out, by rule: ``bash install.sh`` lines (installing is not a test) and the long runs
``validate`` and ``benchmark`` (minutes; tests/test_validation_quick.py covers them). A
``cat > FILE <<'EOF'`` here-document is written as the shell would (a sweep spec: its
``resolution`` is made small too); ``python3 -c`` lines run in a real interpreter; ``sweep``
runs in process (``--workers 0``: tests/test_sweep.py covers the clusters).
"""

import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from elo_mitsuba.cli import main

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
#: The pages whose commands run, each in its own empty folder: the README and the user guide
#: (docs/index.md's order).
PAGES = [README] + [ROOT / "docs" / f"{name}.md" for name in ("rendering", "analysis", "inversion", "sweeps",
                                                                  "validation")]
EXCLUDED = ("install.sh", "elo-mitsuba validate", "elo-mitsuba benchmark", "python -m validation",
            "python -m benchmarks")
#: Renders run at this resolution (README's own are 256-1500).
SMALL = "24"


def readme_commands(page: Path = README) -> list:
    """A page's bash and python blocks, in order, excluded lines dropped: the argv lists after
    ``elo-mitsuba``, ``("file", name, text)`` for a here-document, ``("python", argv)`` for a
    Python line and ``("script", text)`` for a python block."""
    commands = []
    for lang, block in re.findall(r"```(bash|python)\n(.*?)```", page.read_text(), flags=re.S):
        if lang == "python":
            commands.append(("script", re.sub(r"\bres=\d+", f"res={SMALL}", block)))
            continue
        lines = iter(block.splitlines())
        for raw in lines:
            here = re.match(r"cat > (\S+) <<'EOF'$", raw.strip())
            if here:
                body = []
                for nxt in lines:
                    if nxt.strip() == "EOF":
                        break
                    body.append(nxt)
                commands.append(("file", here.group(1), "\n".join(body) + "\n"))
                continue
            line = raw.split("  #")[0].strip()
            if not line or any(x in line for x in EXCLUDED):
                continue
            argv = shlex.split(line)
            if argv[0] == "python3":
                commands.append(("python", argv[1:]))
                continue
            assert argv[0] == "elo-mitsuba", f"README command not run by this test: {line}"
            commands.append(argv[1:])
    return commands


def small(argv: list[str]) -> list[str]:
    if argv[0] in ("sweep", "optimize") and "--workers" in argv:
        argv = list(argv)
        argv[argv.index("--workers") + 1] = "0"
        return argv
    if argv[0] != "render":
        return argv
    argv = list(argv)
    if "--resolution" in argv:
        argv[argv.index("--resolution") + 1] = SMALL
    else:
        argv += ["--resolution", SMALL]
    return argv


@pytest.mark.parametrize("page", PAGES, ids=[p.name for p in PAGES])
def test_pages_run_top_to_bottom_in_an_empty_folder(page, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    commands = readme_commands(page)
    for argv in commands:
        if argv[0] == "file":
            (tmp_path / argv[1]).write_text(re.sub(r"(?m)^resolution = \d+", f"resolution = {SMALL}", argv[2]))
            continue
        if argv[0] in ("python", "script"):
            cmd = [sys.executable, *argv[1]] if argv[0] == "python" else [sys.executable, "-c", argv[1]]
            done = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=300)
            assert done.returncode == 0, f"{page.name}: {argv[0]} {argv[1][:200]}: {done.stderr[-2000:]}"
            continue
        try:
            rc = main(small(argv))
        except SystemExit as exc:  # --help ends through argparse
            rc = exc.code
        err = capsys.readouterr().err
        assert rc == 0, f"{page.name}: elo-mitsuba {' '.join(argv)}: {err}"


def test_the_pages_cover_every_command():
    """What the pages run together: every command a user meets, the Python API, files left."""
    commands = [c for page in PAGES for c in readme_commands(page)]
    run = {c[0] for c in commands}
    assert {"render", "gradient", "reconstruct", "calibrate", "invert", "new-scene", "sweep", "sweep-plot",
            "reflectance-map", "script"} <= run, run
    assert len([c for c in readme_commands(README) if c[0] != "file"]) >= 5  # the first five minutes
    assert any(c[0] == "script" for c in readme_commands(README))


def test_new_scene_loads_from_any_folder(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["new-scene", "mine.xml", "--from", "corrugated_sheet"]) == 0
    (tmp_path / "elsewhere").mkdir()
    monkeypatch.chdir(tmp_path / "elsewhere")
    assert main(["render", "../mine.xml", "-o", "m.exr", "--resolution", "4", "-D", "dh=250", "--quiet"]) == 0
    assert main(["new-scene", "../mine.xml"]) == 2 and "exists; pass --overwrite" in capsys.readouterr().err
