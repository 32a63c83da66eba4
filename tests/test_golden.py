"""The CLI's outputs on the shipped scenes at a fixed seed are bit-identical to the goldens.

The goldens (``tests/golden_cases.json``, made by ``python3 tests/golden_cases.py --update``)
are digests of every channel and file the cases of :mod:`golden_cases` write. Floating-point
results depend on the CPU's instruction set and on the LLVM, Mitsuba and Dr.Jit versions, so
bit-identity is demanded where the fingerprint matches the one recorded; elsewhere the test is
skipped with the command that regenerates the goldens on that machine.

The cases run in a fresh interpreter (``golden_cases.py --digests``), started by conftest.py when
the collection ended, beside the other tests; this test compares what that run wrote.
"""

import json

import pytest

from golden_cases import fingerprint, load_golden


def test_cli_outputs_bit_identical(background_run):
    golden, recorded = load_golden()
    here = fingerprint()
    if here != recorded:
        pytest.skip(f"goldens were made on {recorded}, this is {here}; regenerate with "
                    "python3 tests/golden_cases.py --update (at a commit whose outputs you trust)")
    rc, output, out = background_run("golden")
    assert rc == 0, output[-4000:]
    run = json.loads((out / "digests.json").read_text())
    assert run["fingerprint"] == recorded, run["fingerprint"]
    results = run["outputs"]
    assert sorted(results) == sorted(golden), "the cases wrote other files or channels than the goldens"
    changed = [f"{key} (mean {golden[key]['mean']} -> {results[key]['mean']})"
               for key in results if results[key] != golden[key]]
    assert not changed, f"{len(changed)} output(s) changed: " + "; ".join(changed[:8])
