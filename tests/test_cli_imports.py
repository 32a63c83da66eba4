"""What the command line imports before it needs it (issue 13, "Speed of the command line").

Every ``--help`` and every argument refused before any work leaves scipy, Mitsuba and Dr.Jit
unimported: Mitsuba and Dr.Jit cost ~0.4 s of a new process, scipy ~0.3 s (a rejected argument
should cost < 0.5 s in all). Checked in a fresh interpreter that looks like the ``elo-mitsuba``
command (``sys.argv[0]``), one case after another, so that each case's own imports are seen.
"""

from __future__ import annotations

import json

#: Imported by no --help and no refused argument.
HEAVY = ("scipy", "mitsuba", "drjit")

#: Arguments refused before any work ({d} = an empty folder), with the reason's fragment.
REFUSED = [
    ("render nosuchscene -o {d}/x.exr", "neither an XML file nor a shipped scene"),
    ("render flat_plate -o {d}/x.png", "must end in .exr"),
    ("render flat_plate -o {d}/x.exr -D colour=red", "parameter 'colour' is not declared"),
    ("render flat_plate -o {d}/x.exr --layout zeta99", "unknown detector layout 'zeta99'"),
    ("render flat_plate -o {d}/x.exr --spp 0", "0 must be >= 1"),
    ("gradient --bogus", "the following arguments are required: -o/--output"),
    ("gradient {d}/missing.exr -o {d}/g.exr --bogus", "unrecognized arguments: --bogus"),
    ("reconstruct {d}/missing.exr -o {d}/h.npy", "no such file"),
    ("calibrate {d}/missing.exr --dh 272 --dw 127 -o {d}/c.json", "missing.exr"),
    ("mesh {d}/missing.npy -o {d}/m.ply --pixel-size 0.1", "missing.npy"),
    ("sweep {d}/missing.toml -o {d}/s.zarr", "missing.toml"),
    ("paint", "invalid choice: 'paint'"),
]

SNIPPET = r"""
import contextlib, io, json, sys
sys.argv = ["elo-mitsuba"]  # as the console script: the package does not hook Mitsuba
from elo_mitsuba.cli import COMMANDS, checkout, main
cases = [[c.replace("_", "-"), "--help"] for c in COMMANDS] + [[c, "--help"] for c in checkout.COMMANDS]
cases += [["--help"]] + [a.split() for a in json.loads(sys.stdin.read())]
result = []
for argv in cases:
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        try:
            rc = main(argv)
        except SystemExit as exc:
            rc = exc.code
    result.append([" ".join(argv), rc, out.getvalue(), sorted({m.split(".")[0] for m in sys.modules})])
print("RESULT " + json.dumps(result))
"""


def test_help_and_refused_arguments_import_no_scipy_mitsuba_or_drjit(tmp_path):
    import subprocess
    import sys

    from conftest import REPO_ROOT, _environment

    refused = [a.format(d=tmp_path) for a, _ in REFUSED]
    p = subprocess.run([sys.executable, "-c", SNIPPET], input=json.dumps(refused), cwd=REPO_ROOT, env=_environment(),
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    result = json.loads(p.stdout.splitlines()[-1][len("RESULT "):])
    helps = [r for r in result if r[0].endswith("--help")]
    assert len(helps) >= 12  # every sub-command, validate, benchmark and the command itself
    for argv, rc, text, modules in result:
        leaked = sorted(set(modules) & set(HEAVY))
        assert not leaked, f"'elo-mitsuba {argv}' imported {leaked}"
        if argv.endswith("--help"):
            assert rc == 0 and "usage:" in text, (argv, rc, text[-500:])
    for (argv, rc, text, _), (_, fragment) in zip(result[len(helps):], REFUSED):
        assert rc == 2 and fragment in text and text.count("\n") == 1, (argv, rc, text)
    assert not any(tmp_path.iterdir())  # nothing written
