"""The CLI's outputs on the shipped scenes at a fixed seed equal the goldens: bit for bit where
the machine compiles the same code, within float32 rounding (and a few Monte Carlo paths that end
otherwise, :data:`golden_cases.FLIP_PIXELS`) on any other x86-64 CPU.

The goldens (``tests/golden_cases.json``: digests, shapes, means and the fingerprint of the
machine that made them; ``tests/golden_cases.npz``: the arrays) come from
``python3 tests/golden_cases.py --update``. Bit-identity is demanded where the fingerprint agrees
(Dr.Jit's instruction set, vector width and thread count, LLVM, Mitsuba, Dr.Jit, numpy; the CPU's
name does not decide it: two "AMD EPYC" can differ in AVX-512). Elsewhere every output must lie
within :func:`golden_cases.reference_scale`'s tolerance, grounded in float32 rounding and
checked on this machine by compiling the same cases for a narrower instruction set
(``--other-isa``), which must differ in some bits and stay within it.

The cases run in fresh interpreters (``golden_cases.py --digests``), started by conftest.py when
the collection ended, beside the other tests; these tests compare what those runs wrote.
"""

import json

import numpy as np
import pytest

from golden_cases import (FLIP_PIXELS, TOLERANCE_ULPS, ULP32, bit_identical_expected, compare, load_golden,
                          load_golden_arrays)


def _run(background_run, name):
    rc, output, out = background_run(name)
    assert rc == 0, output[-4000:]
    digests = json.loads((out / "digests.json").read_text())
    if "skipped" in digests:
        pytest.skip(digests["skipped"])
    with np.load(out / "digests.npz", allow_pickle=False) as z:
        arrays = {key: z[key] for key in z.files}
    return digests, arrays


def test_cli_outputs_equal_the_goldens(background_run):
    golden, recorded = load_golden()
    run, arrays = _run(background_run, "golden")
    assert sorted(run["outputs"]) == sorted(golden), "the cases wrote other files or channels than the goldens"
    if bit_identical_expected(recorded, run["fingerprint"]):
        changed = [f"{key} (mean {golden[key]['mean']} -> {run['outputs'][key]['mean']})"
                   for key in golden if run["outputs"][key] != golden[key]]
        assert not changed, f"{len(changed)} output(s) changed bit-wise on the goldens' machine: " + "; ".join(changed[:8])
    problems, _ = compare(load_golden_arrays(), arrays)
    assert not problems, f"{len(problems)} output(s) beyond float32 rounding: " + "; ".join(problems[:8])


def test_the_tolerance_covers_another_instruction_set(background_run):
    """The same cases compiled for AVX2 (or AVX) instead of the host's widest vectors: some bits
    differ (else this check would test nothing), all within the tolerance."""
    base, native = _run(background_run, "golden")
    run, other = _run(background_run, "golden-other-isa")
    assert run["fingerprint"]["llvm_target"] != base["fingerprint"]["llvm_target"]
    differing = [key for key in native if not np.array_equal(native[key], other[key])]
    assert differing, "the other instruction set changed no bit: the tolerance check is vacuous here"
    problems, _ = compare(native, other)
    assert not problems, "; ".join(problems[:8])


def test_the_tolerance_catches_real_changes():
    """What a real change does to an output fails the comparison: a 0.1 % change of a render
    channel (a backscatter coefficient), one pixel moved by more than a path's share, more pixels
    moved beyond rounding than a few paths ending otherwise would move, a slope moved by 1e-3;
    what a path ending otherwise on another instruction set does passes (a 3 x 3 block of e2 moved
    by 1.7e-4 of the channel's largest value, measured between AVX-512 and AVX2 code)."""
    golden = load_golden_arrays()
    render = "athene_default/athene.exr:right"
    slope = "gradient/grad.exr:dzdx"
    g = {render: golden[render], slope: golden[slope]}
    assert not compare(g, {k: v.copy() for k, v in g.items()})[0]
    rounding = {render: (golden[render] * np.float32(1 + 32 * ULP32)).astype(np.float32), slope: golden[slope]}
    assert not compare(g, rounding)[0]  # 32 roundoffs: within float32 rounding of a sum
    scaled = {render: (golden[render] * np.float32(1.001)).astype(np.float32), slope: golden[slope]}
    assert [p for p in compare(g, scaled)[0] if p.startswith(render)]
    top = float(np.abs(golden[render]).max())
    flip = golden[render].copy()
    flip[100:103, 10:13] += np.float32(1.7e-4 * top)
    assert not compare(g, {render: flip, slope: golden[slope]})[0]
    pixel = golden[render].copy()
    pixel[5, 7] += np.float32(2e-3 * top)  # 12 times the share of the path measured to end otherwise
    assert compare(g, {render: pixel, slope: golden[slope]})[0]
    spread = golden[render].copy()
    spread[:FLIP_PIXELS + 1, 0] += np.float32(4 * TOLERANCE_ULPS * ULP32 * top)
    assert compare(g, {render: spread, slope: golden[slope]})[0]
    moved = golden[slope] + np.float32(1e-3)
    assert compare(g, {render: golden[render], slope: moved})[0]
