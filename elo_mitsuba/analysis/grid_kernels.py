"""The height model's linear maps on the scan grid as Dr.Jit kernels: the beam blur and the
corner stencil, with their transposes.

The Gauss-Newton solves of :mod:`.inversion` apply the model's Jacobian and its transpose hundreds
of times per solve (12 conjugate-gradient products per step, as many per noise probe of
``height_error``); at 1500^2 with four detectors that was a third of ``invert``'s time in numpy and
scipy, one thread each. Here they are gathers in Dr.Jit (llvm: every core, SIMD; cuda: the GPU).
Their definitions are :func:`~.height_model.blur` and :func:`~.height_model.corner` (numpy), which
the tests hold these to.

* **Blur**: the separable Gaussian of scipy's ``gaussian_filter(mode='reflect', truncate=4.0)``:
  taps ``exp(-x^2 / 2 sigma^2)`` normalised, radius ``int(4 sigma + 0.5)``, the edges mirrored
  about the border (d c b a | a b c d | d c b a). Symmetric, so the blur is its own transpose.
* **Corners**: pixel (i, j) of an (H, W) grid has the corners (i + di, j + dj) of the (H + 1, W + 1)
  corner grid; the transpose sums each corner's (up to four) pixels, as gathers (no atomics).

Float32, as the partials are: the products agree with numpy's float64 to ~1e-7 of their size.
"""

from __future__ import annotations

import numpy as np

#: Corner offsets (row, column) of each pixel's stencil corners, in :data:`.height_model.STENCIL` order.
OFFSETS = ((0, 0), (0, 1), (1, 0), (1, 1))


def gaussian_taps(sigma: float) -> np.ndarray:
    """The weights of scipy's ``gaussian_filter1d(truncate=4.0)``: 2 r + 1 of them, r = int(4 sigma + 0.5).

    Examples
    --------
    >>> w = gaussian_taps(1.0)
    >>> len(w), round(float(w.sum()), 12), bool(w[4] == w.max())
    (9, 1.0, True)
    """
    r = int(4.0 * float(sigma) + 0.5)
    x = np.arange(-r, r + 1, dtype=float)
    w = np.exp(-0.5 * x * x / (float(sigma) ** 2))
    return w / w.sum()


class GridKernels:
    """Blur and corner stencil of one (H, W) grid, on Dr.Jit arrays of H * W (row-major) values.

    Parameters
    ----------
    shape : (int, int)
        The pixel grid (H, W); corner arrays have (H + 1) * (W + 1) values.
    sigma_px : (float, float)
        The beam profile's standard deviation in pixels along rows and columns ((0, 0): no blur;
        an axis below 1e-15 is not blurred, as in scipy).

    Examples
    --------
    >>> import numpy as np
    >>> k = GridKernels((3, 4), (0.0, 0.0))
    >>> g = k.mi.Float(np.arange(20, dtype=np.float32))  # corners 4 x 5
    >>> np.asarray(k.corners(g)[3]).reshape(3, 4)[0].tolist()  # each pixel's bottom-right corner
    [6.0, 7.0, 8.0, 9.0]
    """

    def __init__(self, shape, sigma_px):
        from ..runtime import ensure_variant

        self.mi = ensure_variant()
        import drjit as dr

        self.dr = dr
        self.shape = (int(shape[0]), int(shape[1]))
        # scipy filters the last axis first: columns (sigma_px[1]) then rows (sigma_px[0])
        self.taps = [(axis, gaussian_taps(s)) for axis, s in ((1, float(sigma_px[1])), (0, float(sigma_px[0])))
                     if s > 1e-15]

    # -- indices --
    def _rows_cols(self, rows: int, cols: int):
        dr, mi = self.dr, self.mi
        # opaque: one kernel for every grid size (literals would compile one per window)
        n_cols = dr.opaque(mi.Int32, cols)
        idx = dr.arange(mi.Int32, rows * cols)
        row = idx // n_cols
        return row, idx - row * n_cols, n_cols

    def _mirror(self, i, n: int, reach: int):
        """Index ``i`` (Int32) mirrored into [0, n) about the borders (scipy's 'reflect')."""
        dr, mi = self.dr, self.mi
        nn = dr.opaque(mi.Int32, n)
        if reach < n:  # one reflection at most
            i = dr.select(i < 0, -i - 1, i)
            return dr.select(i >= nn, 2 * nn - 1 - i, i)
        period = 2 * nn
        m = (i + period * ((reach // (2 * n)) + 1)) % period
        return dr.select(m >= nn, period - 1 - m, m)

    # -- the blur --
    def blur(self, images: list) -> list:
        """Each of ``images`` (Float of H * W) convolved with the beam profile (evaluated)."""
        if not self.taps:
            return list(images)
        dr, mi = self.dr, self.mi
        rows, cols = self.shape
        row, col, n_cols = self._rows_cols(rows, cols)
        out = list(images)
        for axis, w in self.taps:
            r = len(w) // 2
            n = cols if axis == 1 else rows
            dr.eval(out)
            new = [dr.zeros(mi.Float, rows * cols) for _ in out]
            for j in range(len(w)):
                wj = dr.opaque(mi.Float, float(w[j]))  # a parameter: one kernel for every beam width
                if axis == 1:
                    src = row * n_cols + self._mirror(col + (j - r), cols, r)
                else:
                    src = self._mirror(row + (j - r), rows, r) * n_cols + col
                src = mi.UInt32(src)
                new = [acc + wj * dr.gather(mi.Float, img, src) for acc, img in zip(new, out)]
            out = new
        dr.eval(out)
        return out

    # -- the corner stencil --
    def corners(self, g) -> list:
        """The four corners' values (Float of H * W each, :data:`OFFSETS` order) of each pixel,
        from the corner grid ``g`` (Float of (H + 1) * (W + 1))."""
        mi, dr = self.mi, self.dr
        rows, cols = self.shape
        row, col, _ = self._rows_cols(rows, cols)
        stride = dr.opaque(mi.Int32, cols + 1)
        base = row * stride + col
        return [dr.gather(mi.Float, g, mi.UInt32(base + (di * stride + dj))) for di, dj in OFFSETS]

    def corners_t(self, values: list):
        """The transpose of :meth:`corners`: Float of (H + 1) * (W + 1), each corner the sum of
        ``values[c]`` (Float of H * W, :data:`OFFSETS` order) over the pixels it is corner c of."""
        mi, dr = self.mi, self.dr
        rows, cols = self.shape
        row, col, n_cols = self._rows_cols(rows + 1, cols + 1)
        n_rows = dr.opaque(mi.Int32, rows)
        out = dr.zeros(mi.Float, (rows + 1) * (cols + 1))
        for (di, dj), v in zip(OFFSETS, values):
            i, j = row - di, col - dj
            ok = (i >= 0) & (i < n_rows) & (j >= 0) & (j < n_cols - 1)
            out += dr.gather(mi.Float, v, mi.UInt32(dr.select(ok, i * (n_cols - 1) + j, 0)), ok)
        return out

    # -- sub-pixels --
    def sub_pixel_mean(self, values: list, factor: int) -> list:
        """The mean of each ``factor`` x ``factor`` block of ``values`` (Floats on this grid): Floats
        on the grid ``factor`` times coarser (:func:`~.height_model.sub_pixel_mean`)."""
        mi, dr = self.mi, self.dr
        rows, cols = self.shape[0] // factor, self.shape[1] // factor
        row, col, _ = self._rows_cols(rows, cols)
        stride = dr.opaque(mi.Int32, self.shape[1])
        base = (row * factor) * stride + col * factor
        scale = 1.0 / (factor * factor)
        out = [dr.zeros(mi.Float, rows * cols) for _ in values]
        for a in range(factor):
            for b in range(factor):
                src = mi.UInt32(base + (a * stride + b))
                out = [o + dr.gather(mi.Float, v, src) for o, v in zip(out, values)]
        return [o * scale for o in out]

    def sub_pixel_spread(self, values: list, factor: int) -> list:
        """The transpose of :meth:`sub_pixel_mean`: Floats on this grid from ``values`` on the grid
        ``factor`` times coarser, each sub-pixel 1 / factor^2 of its pixel's value."""
        mi, dr = self.mi, self.dr
        row, col, _ = self._rows_cols(*self.shape)
        coarse_cols = dr.opaque(mi.Int32, self.shape[1] // factor)
        src = mi.UInt32((row // factor) * coarse_cols + col // factor)
        scale = 1.0 / (factor * factor)
        return [dr.gather(mi.Float, v, src) * scale for v in values]
