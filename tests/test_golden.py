"""The CLI's outputs on the shipped scenes at a fixed seed are bit-identical to the goldens.

The goldens (``tests/golden_cases.json``, made by ``python3 tests/golden_cases.py --update``)
are digests of every channel and file the cases of :mod:`golden_cases` write. Floating-point
results depend on the CPU's instruction set and on the LLVM, Mitsuba and Dr.Jit versions, so
bit-identity is demanded where the fingerprint matches the one recorded; elsewhere the test is
skipped with the command that regenerates the goldens on that machine.
"""

import pytest

from golden_cases import digest, fingerprint, load_golden, run_cases


def test_cli_outputs_bit_identical(tmp_path):
    golden, recorded = load_golden()
    here = fingerprint()
    if here != recorded:
        pytest.skip(f"goldens were made on {recorded}, this is {here}; regenerate with "
                    "python3 tests/golden_cases.py --update (at a commit whose outputs you trust)")
    results = run_cases(tmp_path)
    assert sorted(results) == sorted(golden), "the cases wrote other files or channels than the goldens"
    changed = [f"{key} (mean {golden[key]['mean']} -> {digest(arr)['mean']})"
               for key, arr in results.items() if digest(arr) != golden[key]]
    assert not changed, f"{len(changed)} output(s) changed: " + "; ".join(changed[:8])
