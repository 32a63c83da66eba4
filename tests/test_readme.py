"""README's shell commands run top to bottom in an empty folder (issue 13): every ```bash block,
in order, through the CLI in-process, renders at a small resolution (README states the cost of
its full-size renders, 2-10 s each).

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

from elo_mitsuba.cli import main

README = Path(__file__).resolve().parents[1] / "README.md"
EXCLUDED = ("install.sh", "elo-mitsuba validate", "elo-mitsuba benchmark", "python -m validation",
            "python -m benchmarks")
#: Renders run at this resolution (README's own are 256-1500).
SMALL = "24"


def readme_commands() -> list:
    """README's bash blocks, in order, excluded lines dropped: the argv lists after ``elo-mitsuba``,
    ``("file", name, text)`` for a here-document and ``("python", argv)`` for a Python line."""
    blocks = re.findall(r"```bash\n(.*?)```", README.read_text(), flags=re.S)
    commands = []
    for block in blocks:
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
    if argv[0] == "sweep" and "--workers" in argv:
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


def test_readme_runs_top_to_bottom_in_an_empty_folder(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    commands = readme_commands()
    assert len(commands) >= 10 and any(c[0] == "reconstruct" for c in commands)
    assert any(c[0] == "calibrate" for c in commands) and any(c[0] == "sweep-plot" for c in commands)
    for argv in commands:
        if argv[0] == "file":
            (tmp_path / argv[1]).write_text(re.sub(r"(?m)^resolution = \d+", f"resolution = {SMALL}", argv[2]))
            continue
        if argv[0] == "python":
            done = subprocess.run([sys.executable, *argv[1]], cwd=tmp_path, capture_output=True, text=True, timeout=300)
            assert done.returncode == 0, f"README: python3 {' '.join(argv[1])}: {done.stderr}"
            continue
        rc = main(small(argv))
        err = capsys.readouterr().err
        assert rc == 0, f"README: elo-mitsuba {' '.join(argv)}: {err}"
    assert (tmp_path / "height.npy").is_file() and (tmp_path / "my_scene.xml").is_file()


def test_new_scene_loads_from_any_folder(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["new-scene", "mine.xml", "--from", "corrugated_sheet"]) == 0
    (tmp_path / "elsewhere").mkdir()
    monkeypatch.chdir(tmp_path / "elsewhere")
    assert main(["render", "../mine.xml", "-o", "m.exr", "--resolution", "4", "-D", "dh=250", "--quiet"]) == 0
    assert main(["new-scene", "../mine.xml"]) == 2 and "exists; pass --overwrite" in capsys.readouterr().err
