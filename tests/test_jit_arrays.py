"""The inversion's model compiles its kernels once: evaluating it again on fresh numpy arrays (new
heights, the same window) reuses every kernel (analysis/jit_arrays.py). Before, Dr.Jit wrote each
mapped array's alignment into the kernel, and nearly every evaluation compiled five kernels anew."""

from __future__ import annotations

import numpy as np

from elo_mitsuba.analysis.height_model import HeightModel, corners_from_pixels
from elo_mitsuba.analysis.jit_arrays import ALIGNMENT, aligned
from elo_mitsuba.analysis.scan_geometry import ScanGeometry
from elo_mitsuba.grid import pixel_coordinates
from elo_mitsuba.objects.hills import hills_height


def test_aligned_copies_start_on_the_boundary_and_keep_the_values():
    rng = np.random.default_rng(1)
    for offset in range(8):  # numpy's own buffers start anywhere on 16 bytes
        a = rng.normal(size=(7, 9))[:, offset % 3:]
        out = aligned(a, np.float32)
        assert out.ctypes.data % ALIGNMENT == 0
        np.testing.assert_array_equal(out, a.astype(np.float32).ravel())
    assert aligned(np.array([True, False, True]), bool).tolist() == [True, False, True]


def test_model_evaluations_reuse_their_kernels(mi):
    import drjit as dr

    shape = (24, 20)
    geo = ScanGeometry.nominal(shape, 80, 272, 127)
    x, y = pixel_coordinates(shape, geo.field_mm)
    model = HeightModel(geo, fwhm_mm=0.27, shadows=True)
    g = corners_from_pixels(0.25 * hills_height(x, y))
    rng = np.random.default_rng(2)

    def step():
        # fresh arrays each time, as a Gauss-Newton step makes them
        lin = model.evaluate(g + 1e-4 * rng.normal(size=g.shape), derivatives=True)
        model.apply_jacobian_t(lin, rng.normal(size=lin.images.shape))

    step()  # the first also builds what the model keeps (its blur's kernels)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        kernels = []
        for _ in range(4):
            dr.kernel_history()  # cleared
            step()
            kernels.append({k["hash"] for k in dr.kernel_history() if k.get("type") == dr.KernelType.JIT})
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    # the same kernels each time (Dr.Jit's cache on disk may hold earlier runs' kernels, so what
    # counts is the hash, not whether it was compiled here)
    assert len(kernels[0]) >= 6
    assert kernels[1] == kernels[2] == kernels[3] == kernels[0], [len(k - kernels[0]) for k in kernels[1:]]
