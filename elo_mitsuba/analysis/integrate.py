"""Normal integration: height map Z(x, y) (mm, up to a constant) from the gradient dZ/dx, dZ/dy.

Four solvers, chosen after the survey of Quéau, Durou and Aujol, "Normal integration: a survey"
(J. Math. Imaging Vis. 60, 2018) and its companion on variational methods; the code is our own:

* ``"fft"`` — Frankot-Chellappa: project the gradient onto integrable fields in the Fourier
  basis. The FFT assumes a periodic surface; we mirror the gradient field (even extension of Z,
  i.e. odd extension of the derivative across each edge) to 2H x 2W so that the periodic
  continuation has no jump. Fast, but the spectral derivative does not match the finite
  differences of sampled data near kinks, and it cannot exclude pixels.
* ``"dct"`` — least squares with natural (Neumann) boundary: minimise the sum over all pairs of
  neighbouring pixels of (Z_b - Z_a - (g_a + g_b)/2)^2, with g the gradient along that pair in
  pixel units. The normal equations are the 5-point Poisson equation with Neumann boundary,
  diagonalised by the type-II DCT (Simchony et al. 1990): the exact minimiser, in O(N log N).
* ``"masked"`` — the same functional restricted to pairs of *trusted* pixels, solved on the valid
  domain only: a sparse direct solve (scipy.sparse.linalg.spsolve) for up to 250 000 trusted pixels,
  above that conjugate gradients preconditioned by the DCT solver. Each 4-connected component
  of the valid domain is integrated independently and gets zero mean: relative heights between
  components are unknown (no gradient connects them). Components smaller than
  ``min_component_size`` pixels are added to the mask. Without any mask it reproduces ``"dct"``.
* ``"robust"`` — discontinuity-preserving: the Cauchy estimator of the same pair misfits
  (Quéau, Durou and Aujol, "Variational methods for normal integration", J. Math. Imaging Vis.
  60, 2018), minimised by iteratively reweighted least squares, each iteration a weighted
  ``"masked"`` solve. A pair whose gradient disagrees with the rest (one wall of a cliff saying
  less than the others) is given up instead of being spread over the relief around it; it cannot
  add a jump that no wall's gradient holds. Not chosen by ``"auto"``: on the hills and the melt
  plate it equals least squares within 4 %, on rendered cliffs it lowers the error spread over the
  relief beside them from 3.0 to 2.3 µm RMS (``python -m validation.study_steps``), at 2.5-4
  times the time of ``"masked"`` (15-25 s at 1500² on 2 cores; up to 85 s where it runs to its
  :data:`ROBUST_ITERATIONS` solves).

Orientation as everywhere (:mod:`elo_mitsuba.grid`); dZ/dy is the derivative along +y,
i.e. *against* the row index. All returned heights are finite; masked pixels hold 0.
"""

from __future__ import annotations

import math
import time

import numpy as np

# scipy is imported inside the solvers: 'elo-mitsuba reconstruct --help' reads this module's
# constants, and a help text or a rejected argument must not pay for importing scipy (~0.3 s)
from ..arguments import flag, real_array, shown, whole_number
from ..errors import EloInputError
from .layout import pixel_size
from .quadric import bowl_exceeds, fit_quadric
from .sampling_check import MAX_HALF_SAMPLING, resolution_warning

METHODS = ("dct", "fft", "masked", "robust")

#: ``"robust"``: the Cauchy estimator's lambda in units of the least-squares misfits' robust
#: spread. 2.385 is the constant that gives the Cauchy M-estimator 95 % efficiency at Gaussian
#: residuals (Holland & Welsch 1977): on a noisy but smooth gradient it is nearly least squares.
ROBUST_SCALE = 2.385
#: ``"robust"``: at most this many reweighted solves, stopping when one lowers the Cauchy energy by
#: less than ``ROBUST_TOL`` of it (on a noise-free 1500² render of the melt plate the energy still
#: fell 0.4 % at the 30th, from 4.7 % at the 2nd: there the cap ends it, after 68 s on 2 cores).
ROBUST_ITERATIONS = 30
ROBUST_TOL = 1e-3
#: ``"robust"``: relative residual of each conjugate-gradient solve (started from the previous
#: iterate; the next reweighting corrects what is left). On the stepped layer at 400² the result
#: is within 1 µm RMS of the converged one.
ROBUST_CG_TOL = 1e-4

#: :func:`reconstruction_quality` warns above these (documented in ``reconstruct --help``).
#: Integrability residual: the relative RMS misfit between the gradient of the height map and the
#: input gradient (0 for an integrable field; about 0.7 for pure noise, whose curl-free part
#: carries half the energy). Above 0.3 a third of the input is not the gradient of any surface.
MAX_INTEGRABILITY_RESIDUAL = 0.3
#: Untrusted share of the pixels above which the height map covers too little of the field.
MAX_MASKED_FRACTION = 0.5
#: Share of the measured pixels outside the largest connected region above which the map is said
#: to fall apart: each region's heights are relative to its own mean (no slope connects them). On
#: the hills at 256^2 under 15-degree detectors with 1 % noise (34 % masked by shadows) 1.6 % of
#: the measured pixels lay in 8 hilltops apart from the largest region, 1.7-2.3 mm off, which made
#: the map's error 246 um RMS where the rest is 40 um; no warning was given.
MAX_DETACHED_FRACTION = 0.005


def _gradient_pair(dzdx, dzdy):
    """dzdx, dzdy as float arrays of real numbers, 2-D and of one shape."""
    dzdx, dzdy = real_array("dzdx", dzdx, ndim=None), real_array("dzdy", dzdy, ndim=None)
    if dzdx.shape != dzdy.shape or dzdx.ndim != 2:
        raise EloInputError(f"dzdx {dzdx.shape} and dzdy {dzdy.shape}: expected two 2-D arrays of one shape")
    return dzdx, dzdy


def _mask_array(mask, shape):
    """``mask`` (True = untrusted) as bools of ``shape``: 0/1 or bool values only (2 or NaN would
    read as True)."""
    raw = np.asarray(mask)
    if raw.dtype != bool:
        values = real_array("mask", raw, ndim=None)
        if not np.all((values == 0) | (values == 1)):
            raise EloInputError("mask: holds values other than 0 and 1 (True = untrusted); give bools")
        raw = values.astype(bool)
    if raw.shape != tuple(shape):
        raise EloInputError(f"mask shape {raw.shape} differs from the gradient's {tuple(shape)}")
    return raw


def _pixel_gradients(dzdx, dzdy, field_mm):
    """Gradients in mm per pixel along columns (+x) and rows (-y); non-finite -> 0."""
    dzdx, dzdy = _gradient_pair(dzdx, dzdy)
    dx, dy = pixel_size(dzdx.shape, field_mm)
    gc = np.nan_to_num(dzdx, nan=0.0, posinf=0.0, neginf=0.0) * dx
    gr = -np.nan_to_num(dzdy, nan=0.0, posinf=0.0, neginf=0.0) * dy  # rows run towards -y
    return gc, gr


def integrate_fft(dzdx, dzdy, field_mm, *, mirror: bool = True) -> np.ndarray:
    """Frankot-Chellappa integration (least squares in the Fourier basis).

    Parameters
    ----------
    dzdx, dzdy : ndarray (H, W)
        Gradient (mm/mm), package orientation. Non-finite values count as 0.
    field_mm : float or (float, float)
        Scan field in mm.
    mirror : bool
        Mirror-extend to (2H, 2W) first (recommended); False assumes a periodic surface.

    Returns
    -------
    ndarray (H, W)
        Height in mm with zero mean.

    Examples
    --------
    >>> import numpy as np
    >>> height = np.outer(np.ones(8), np.sin(np.linspace(0, np.pi, 8)))
    >>> dzdx, dzdy = height_gradient(height, 8.0)
    >>> z = integrate_fft(dzdx, dzdy, 8.0)
    >>> z.shape, bool(abs(z.mean()) < 1e-12)
    ((8, 8), True)
    """
    mirror = flag("mirror", mirror)
    from scipy import fft as sfft

    gc, gr = _pixel_gradients(dzdx, dzdy, field_mm)
    h, w = gc.shape
    if mirror:
        # Even extension of Z <=> the derivative along the mirrored axis changes sign.
        gc = np.block([[gc, -gc[:, ::-1]], [gc[::-1, :], -gc[::-1, ::-1]]])
        gr = np.block([[gr, gr[:, ::-1]], [-gr[::-1, :], -gr[::-1, ::-1]]])
    hh, ww = gc.shape
    wr = 2 * np.pi * sfft.fftfreq(hh)[:, None]
    wc = 2 * np.pi * sfft.fftfreq(ww)[None, :]
    denom = wc * wc + wr * wr
    denom[0, 0] = 1.0
    zhat = (-1j * wc * sfft.fft2(gc, workers=-1) - 1j * wr * sfft.fft2(gr, workers=-1)) / denom
    zhat[0, 0] = 0.0
    z = np.real(sfft.ifft2(zhat, workers=-1))[:h, :w]
    return z - z.mean()


def _divergence_rhs(gc, gr):
    """Right-hand side D^T b of the least-squares normal equations (trapezoidal pair targets)."""
    bc = 0.5 * (gc[:, 1:] + gc[:, :-1])   # target of Z[:, j+1] - Z[:, j]
    br = 0.5 * (gr[1:, :] + gr[:-1, :])   # target of Z[i+1, :] - Z[i, :]
    # D^T of a forward difference: (D^T b)_j = b_{j-1} - b_j with b_{-1} = b_{N-1} = 0.
    rhs = -np.diff(np.pad(bc, ((0, 0), (1, 1))), axis=1)
    rhs -= np.diff(np.pad(br, ((1, 1), (0, 0))), axis=0)
    return rhs


def integrate_dct(dzdx, dzdy, field_mm) -> np.ndarray:
    """Least-squares integration with Neumann boundary via the DCT (Poisson solver).

    Minimises sum over neighbouring pixel pairs (a, b) of (Z_b - Z_a - (g_a + g_b)/2)^2; its normal
    equations L Z = D^T g (L the 5-point Neumann Laplacian) are solved exactly in the DCT-II basis,
    whose eigenvalues are (2 - 2 cos(pi k / W)) + (2 - 2 cos(pi l / H)).

    Parameters
    ----------
    dzdx, dzdy : ndarray (H, W)
        Gradient (mm/mm), package orientation. Non-finite values count as 0.
    field_mm : float or (float, float)
        Scan field in mm.

    Returns
    -------
    ndarray (H, W)
        Height in mm with zero mean.

    Examples
    --------
    >>> import numpy as np
    >>> dzdx, dzdy = np.full((3, 4), 0.5), np.zeros((3, 4))    # 1 mm pixels
    >>> integrate_dct(dzdx, dzdy, (4.0, 3.0)).round(4).tolist()[0]
    [-0.75, -0.25, 0.25, 0.75]
    """
    from scipy import fft as sfft

    gc, gr = _pixel_gradients(dzdx, dzdy, field_mm)
    h, w = gc.shape
    rhs = _divergence_rhs(gc, gr)
    lam = (2 - 2 * np.cos(np.pi * np.arange(h) / h))[:, None] + (2 - 2 * np.cos(np.pi * np.arange(w) / w))[None, :]
    lam[0, 0] = 1.0
    zhat = sfft.dctn(rhs, type=2, norm="ortho", workers=-1) / lam
    zhat[0, 0] = 0.0  # the free constant: zero mean
    return sfft.idctn(zhat, type=2, norm="ortho", workers=-1)


def _solve_direct(lap, rhs, comp):
    """Sparse LU with the first pixel of each component pinned (removes the constant null space)."""
    from scipy import sparse
    from scipy.sparse.linalg import spsolve

    _, first = np.unique(comp, return_index=True)
    pin = np.zeros(rhs.size, dtype=bool)
    pin[first] = True
    lap = sparse.diags((~pin).astype(float)) @ lap + sparse.diags(pin.astype(float))
    return spsolve(lap.tocsc(), np.where(pin, 0.0, rhs))


def _solve_pcg(lap, rhs, valid, tol, x0=None, maxiter=2000):
    """Conjugate gradients preconditioned with the full-grid DCT Poisson solver.

    The restricted Laplacian differs from the full-grid Neumann Laplacian only next to masked
    pixels, so the DCT inverse is a good preconditioner; the system is singular (one constant
    per component) but consistent (rhs sums to 0 over each component), which CG tolerates.
    ``x0`` starts it (the previous iterate of a reweighted solve).
    """
    from scipy import fft as sfft
    from scipy.sparse.linalg import LinearOperator, cg

    h, w = valid.shape
    lam = (2 - 2 * np.cos(np.pi * np.arange(h) / h))[:, None] + (2 - 2 * np.cos(np.pi * np.arange(w) / w))[None, :]
    lam[0, 0] = np.inf  # drop the constant mode

    def precondition(r):
        full = np.zeros(valid.shape)
        full[valid] = r
        # every core (the transforms along one axis are independent rows: the same bits as one core):
        # 2.2x on 2 cores at 1500², where the preconditioner is half of a robust integration
        return sfft.idctn(sfft.dctn(full, type=2, norm="ortho", workers=-1) / lam, type=2, norm="ortho",
                          workers=-1)[valid]

    m = LinearOperator(lap.shape, matvec=precondition, dtype=float)
    z, info = cg(lap, rhs, x0=x0, M=m, rtol=tol, atol=0.0, maxiter=maxiter)
    if info != 0:
        raise EloInputError(
            f"masked integration did not converge in {maxiter} iterations (tolerance {tol:g}); "
            "try method 'dct' or a smaller image"
        )
    return z


def _pair_system(gc, gr, valid):
    """The difference operator D (one row per 4-neighbour pair of valid pixels, columns the valid
    pixels in C order) and each pair's target (g_a + g_b)/2; (None, None) when there is no pair."""
    from scipy import sparse

    n = int(valid.sum())
    if n == 0:
        return None, None
    index = -np.ones(valid.shape, dtype=np.int64)
    index[valid] = np.arange(n)
    rows, cols, data, rhs_parts = [], [], [], []
    eq = 0
    for ia, ib, g in ((index[:, :-1], index[:, 1:], 0.5 * (gc[:, :-1] + gc[:, 1:])),
                      (index[:-1, :], index[1:, :], 0.5 * (gr[:-1, :] + gr[1:, :]))):
        keep = (ia >= 0) & (ib >= 0)
        a, b, t = ia[keep], ib[keep], g[keep]
        k = np.arange(eq, eq + a.size)
        rows += [k, k]
        cols += [a, b]
        data += [-np.ones(a.size), np.ones(a.size)]
        rhs_parts.append(t)
        eq += a.size
    if eq == 0:
        return None, None
    d = sparse.csr_matrix((np.concatenate(data), (np.concatenate(rows), np.concatenate(cols))), shape=(eq, n))
    return d, np.concatenate(rhs_parts)


def integrate_masked(dzdx, dzdy, field_mm, mask=None, *, min_component_size: int = 1,
                     direct_limit: int = 250_000, tol: float = 1e-9):
    """Least-squares integration over the trusted pixels only (sparse solve on the valid domain).

    The functional of :func:`integrate_dct`, restricted to neighbouring pairs whose two pixels are
    both trusted. Each 4-connected component of the trusted domain is solved with one pixel pinned
    and then shifted to zero mean.

    Parameters
    ----------
    dzdx, dzdy : ndarray (H, W)
        Gradient (mm/mm); values at masked pixels are ignored. Non-finite values are masked.
    field_mm : float or (float, float)
        Scan field in mm.
    mask : ndarray of bool (H, W), optional
        True = untrusted (the convention of :mod:`.gradient`).
    min_component_size : int
        Trusted components with fewer pixels are masked too (their height would be arbitrary).
    direct_limit : int
        Up to this many trusted pixels a sparse LU solve (exact, memory ~ N^1.5); above it
        conjugate gradients preconditioned by the DCT Poisson solver (relative residual ``tol``).

    Returns
    -------
    height : ndarray (H, W)
        Height in mm, zero mean per component, 0 at masked pixels.
    mask_out : ndarray of bool (H, W)
        The pixels that have no height (input mask, non-finite gradients, small components).

    Examples
    --------
    >>> import numpy as np
    >>> dzdx, dzdy = np.full((2, 3), 0.5), np.zeros((2, 3))    # 1 mm pixels
    >>> mask = np.array([[False, False, False], [True, False, False]])
    >>> height, mask_out = integrate_masked(dzdx, dzdy, (3.0, 2.0), mask)
    >>> height.round(4).tolist(), mask_out.tolist()
    ([[-0.6, -0.1, 0.4], [0.0, -0.1, 0.4]], [[False, False, False], [True, False, False]])
    """
    dzdx, dzdy = _gradient_pair(dzdx, dzdy)
    whole_number("direct_limit", direct_limit, 0, None)
    if not (isinstance(tol, (int, float)) and math.isfinite(tol) and tol > 0):
        raise EloInputError(f"tol={shown(tol)}: must be a finite number > 0")
    valid, labels = _trusted_domain(dzdx, dzdy, mask, min_component_size)
    gc, gr = _pixel_gradients(dzdx, dzdy, field_mm)
    height = np.zeros(dzdx.shape)
    d, target = _pair_system(gc, gr, valid)
    if d is None:  # no pixel, or isolated single pixels only
        return height, ~valid
    lap = (d.T @ d).tocsr()
    rhs = d.T @ target
    comp = labels[valid]
    if comp.size <= direct_limit:
        z = _solve_direct(lap, rhs, comp)
    else:
        z = _solve_pcg(lap, rhs, valid, tol)
    # Zero mean per component: its constant is arbitrary (pinned value or CG start).
    counts = np.bincount(comp)
    means = np.bincount(comp, weights=z) / np.maximum(counts, 1)
    z -= means[comp]
    height[valid] = z
    return height, ~valid


def _trusted_domain(dzdx, dzdy, mask, min_component_size):
    """Trusted pixels (finite gradient, not masked, in a 4-connected component of at least
    ``min_component_size`` pixels) and their component labels."""
    from scipy import ndimage

    min_component_size = whole_number("min_component_size", min_component_size, 1, None)
    bad = ~(np.isfinite(dzdx) & np.isfinite(dzdy))
    if mask is not None:
        bad |= _mask_array(mask, dzdx.shape)
    valid = ~bad
    labels, n_comp = ndimage.label(valid)  # 4-connectivity: the pairs of the functional
    if n_comp:
        sizes = np.bincount(labels.ravel(), minlength=n_comp + 1)
        small = sizes < int(min_component_size)
        small[0] = False
        valid &= ~small[labels]
        labels = np.where(valid, labels, 0)
    return valid, labels


def check_trusted_regions(dzdx, dzdy, mask=None, min_component_size: int | None = None, *,
                          source: str = "gradient") -> None:
    """Refuse a gradient no pixel of which can get a height, before any solve: every pixel masked
    (or not finite), or, with ``min_component_size``, every trusted region (4-connected) smaller
    than it (the masked and robust solvers drop those). Either wrote an all-NaN height map with
    exit status 0 and a warning.

    Examples
    --------
    >>> g = np.zeros((4, 4))
    >>> check_trusted_regions(g, g, np.ones((4, 4), bool))
    Traceback (most recent call last):
    ...
    elo_mitsuba.errors.EloInputError: gradient: all 16 pixels are masked (untrusted) or not finite; ...
    >>> check_trusted_regions(g, g, None, 17)
    Traceback (most recent call last):
    ...
    elo_mitsuba.errors.EloInputError: --min-component 17: the largest trusted region of gradient has 16 pixels; ...
    """
    dzdx, dzdy = _gradient_pair(dzdx, dzdy)
    valid, labels = _trusted_domain(dzdx, dzdy, mask, 1)
    if not valid.any():
        raise EloInputError(f"{source}: all {valid.size} pixels are masked (untrusted) or not finite; no height can be "
                            "integrated (the mask channel: 1 = untrusted, 0 = trusted)")
    if min_component_size is not None:
        largest = int(np.bincount(labels[valid]).max())
        if largest < whole_number("min_component_size", min_component_size, 1, None):
            raise EloInputError(f"--min-component {min_component_size}: the largest trusted region of {source} has "
                                f"{largest} pixels; every region would be dropped: give at most {largest}")


def integrate_robust(dzdx, dzdy, field_mm, mask=None, *, scale_mm: float | None = None,
                     iterations: int = ROBUST_ITERATIONS, tol: float = ROBUST_TOL, min_component_size: int = 1,
                     direct_limit: int = 40_000, return_weights: bool = False, progress=None):
    """Discontinuity-preserving integration: the Cauchy estimator of the pair misfits, minimised by
    iteratively reweighted least squares (Quéau, Durou & Aujol, "Variational methods for normal
    integration", J. Math. Imaging Vis. 60, 2018, the non-convex estimators of their Sec. 5).

    Minimises sum over neighbouring trusted pairs (a, b) of log(1 + (r_ab / lambda)^2), with
    r_ab = Z_b - Z_a - (g_a + g_b)/2 the misfit of :func:`integrate_masked`'s functional. A misfit
    well above lambda costs only its logarithm, so a pair whose gradient disagrees with the rest
    (a wall whose slope is truncated on one side and not the other, a blurred rim) is given up
    instead of being spread, as least squares spreads it, over the relief around it. Each
    iteration is a weighted Poisson solve with the weights w = 1 / (1 + (r / lambda)^2) of the
    previous solution's misfits, starting from least squares (the non-convex functional needs a
    good start). lambda defaults to :data:`ROBUST_SCALE` times the robust spread (1.4826 x the
    median absolute misfit) of the least-squares solution, so that on a gradient that is a surface's
    plus noise nearly every weight stays near 1 and the result is least squares'.

    Pairs with a masked pixel do not enter (as in ``"masked"``), and each trusted component gets
    its own zero mean. What it cannot do: recover a jump that the gradient does not hold. The
    height across a cliff is what the wall's pairs say; a wall whose gradient is truncated on every
    side (blur, saturated slopes, or a mask all round the foot) stays truncated, and a patch cut off
    by masked pixels all round is a component of its own whose height relative to the rest is
    unknown (zero mean, like ``"masked"``).

    Parameters
    ----------
    dzdx, dzdy : ndarray (H, W)
        Gradient (mm/mm); values at masked pixels are ignored. Non-finite values are masked.
    field_mm : float or (float, float)
        Scan field in mm.
    mask : ndarray of bool (H, W), optional
        True = untrusted.
    scale_mm : float, optional
        lambda (mm per pixel pair): misfits well above it are treated as outliers. Default from the
        data (above).
    iterations : int
        At most this many reweighted solves after the least-squares start.
    tol : float
        Stop when a reweighted solve lowers the Cauchy energy by less than ``tol`` of it.
    min_component_size : int
        Trusted components with fewer pixels are masked too.
    direct_limit : int
        Up to this many trusted pixels each solve is a sparse LU; above it conjugate gradients
        preconditioned by the DCT Poisson solver, started from the previous iterate.
    return_weights : bool
        Also return the final pair weights as two arrays (H, W-1) (pairs along +x) and (H-1, W)
        (pairs along rows), 0 where a pair does not enter.
    progress : callable, optional
        Called after each reweighted solve with a dict: ``iteration``, ``iterations`` (the most
        there will be), ``energy`` (the Cauchy energy) and ``seconds`` (since the start); at 1500²
        a solve takes about 2 s.

    Returns
    -------
    height : ndarray (H, W)
        Height in mm, zero mean per component, 0 at masked pixels.
    mask_out : ndarray of bool (H, W)
        The pixels that have no height.
    weights : (ndarray, ndarray)
        Only with ``return_weights``.

    Examples
    --------
    A flat field with a 1 mm step between columns 3 and 4, whose wall gradient is wrong in one
    row (the gradient says 0 there): least squares gives that row 0.81 mm and spreads the rest of
    its disagreement over the flats; the robust estimator gives up the row's wall pairs.

    >>> import numpy as np
    >>> dzdx, dzdy = np.zeros((6, 8)), np.zeros((6, 8))            # 1 mm pixels
    >>> dzdx[:, 3] = dzdx[:, 4] = 0.5                              # the wall: 0.5 + 0.5 = 1 mm
    >>> dzdx[2, 3:5] = 0.0
    >>> z_ls, _ = integrate_masked(dzdx, dzdy, (8.0, 6.0))
    >>> z, _ = integrate_robust(dzdx, dzdy, (8.0, 6.0))
    >>> round(float(z_ls[2, -1] - z_ls[2, 0]), 2), round(float(z[2, -1] - z[2, 0]), 2)
    (0.81, 0.99)
    """
    dzdx, dzdy = _gradient_pair(dzdx, dzdy)
    whole_number("iterations", iterations, 1, None)
    whole_number("direct_limit", direct_limit, 0, None)
    return_weights = flag("return_weights", return_weights)
    if not (isinstance(tol, (int, float)) and math.isfinite(tol) and tol >= 0):
        raise EloInputError(f"tol={shown(tol)}: must be a finite number >= 0")
    if scale_mm is not None and not (math.isfinite(scale_mm) and scale_mm > 0):
        raise EloInputError(f"scale_mm {scale_mm!r}: must be a finite number > 0")
    valid, labels = _trusted_domain(dzdx, dzdy, mask, min_component_size)
    gc, gr = _pixel_gradients(np.where(valid, dzdx, 0.0), np.where(valid, dzdy, 0.0), field_mm)
    height = np.zeros(dzdx.shape)
    d, target = _pair_system(gc, gr, valid)
    weights = None
    if d is None:
        z = None
    else:
        from scipy import sparse

        comp = labels[valid]
        dt = d.T.tocsr()

        def solve(w, z0):
            lap = (dt @ sparse.diags(w) @ d).tocsr()
            rhs = dt @ (w * target)
            if comp.size <= direct_limit:
                return _solve_direct(lap, rhs, comp)
            return _solve_pcg(lap, rhs, valid, ROBUST_CG_TOL, x0=z0)

        t0 = time.perf_counter()
        w = np.ones(target.size)
        z = solve(w, None)  # least squares: the start
        r = d @ z - target
        lam = scale_mm
        if lam is None:
            # the misfits' robust spread; a floor for an exactly integrable field (misfits ~ 0)
            floor = 1e-9 * max(float(np.sqrt(np.mean(target ** 2))), 1e-12)
            lam = max(ROBUST_SCALE * 1.4826 * float(np.median(np.abs(r))), floor)
        energy = float(np.sum(np.log1p((r / lam) ** 2)))
        for k in range(int(iterations)):
            w = 1.0 / (1.0 + (r / lam) ** 2)
            z = solve(w, z)
            r = d @ z - target
            # IRLS decreases the Cauchy energy at every step (a majorise-minimise iteration)
            previous, energy = energy, float(np.sum(np.log1p((r / lam) ** 2)))
            if progress is not None:
                progress({"iteration": k + 1, "iterations": int(iterations), "energy": energy,
                          "seconds": time.perf_counter() - t0})
            if previous - energy <= tol * previous:
                break
        counts = np.bincount(comp)
        z -= (np.bincount(comp, weights=z) / np.maximum(counts, 1))[comp]
        height[valid] = z
        weights = w
    if not return_weights:
        return height, ~valid
    wc, wr = np.zeros((dzdx.shape[0], dzdx.shape[1] - 1)), np.zeros((dzdx.shape[0] - 1, dzdx.shape[1]))
    if weights is not None:
        pc = valid[:, :-1] & valid[:, 1:]
        wc[pc] = weights[:int(pc.sum())]
        wr[valid[:-1, :] & valid[1:, :]] = weights[int(pc.sum()):]
    return height, ~valid, (wc, wr)


def integrate_gradient(dzdx, dzdy, field_mm, *, method: str = "auto", mask=None,
                       min_component_size: int = 1, progress=None):
    """Height map from a gradient field with the chosen solver (module docstring).

    Parameters
    ----------
    dzdx, dzdy : ndarray (H, W)
        Gradient (mm/mm), package orientation.
    field_mm : float or (float, float)
        Scan field in mm.
    method : {"auto", "dct", "fft", "masked", "robust"}
        ``"auto"`` uses ``"masked"`` when any pixel is masked (or a gradient is non-finite) and
        ``"dct"`` otherwise. ``"dct"``/``"fft"`` use every pixel and take masked gradients as 0
        (a flat patch), which biases the surrounding heights. ``"robust"``
        (:func:`integrate_robust`) gives up pairs whose gradient disagrees with the rest instead
        of spreading them: for surfaces with cliffs.
    mask : ndarray of bool, optional
        True = untrusted.
    min_component_size : int
        For ``"masked"`` and ``"robust"``: smaller trusted components are masked too.
    progress : callable, optional
        ``"robust"``: called after each reweighted solve (:func:`integrate_robust`); the other
        solvers are one solve each.

    Returns
    -------
    height : ndarray (H, W)
        Height in mm (zero mean over the trusted pixels, per component for ``"masked"``).
    mask_out : ndarray of bool (H, W)
        Pixels whose height is not measured (the input mask, grown by the masked solver).

    Examples
    --------
    >>> import numpy as np
    >>> dzdx, dzdy = np.full((3, 4), 0.5), np.zeros((3, 4))    # 1 mm pixels
    >>> height, mask_out = integrate_gradient(dzdx, dzdy, (4.0, 3.0))
    >>> height.round(4).tolist()[0], bool(mask_out.any())
    ([-0.75, -0.25, 0.25, 0.75], False)
    >>> mask = np.zeros((3, 4), bool); mask[:, 0] = True       # a column not measured
    >>> height, mask_out = integrate_gradient(dzdx, dzdy, (4.0, 3.0), mask=mask)
    >>> (height.round(4) + 0.0).tolist()[0], mask_out[:, 0].tolist()
    ([0.0, -0.5, 0.0, 0.5], [True, True, True])
    """
    dzdx, dzdy, bad = _checked_inputs(dzdx, dzdy, mask)
    whole_number("min_component_size", min_component_size, 1, None)  # also where no mask uses it
    method = resolve_method(method, dzdx, dzdy, bad)
    if method == "masked":
        return integrate_masked(dzdx, dzdy, field_mm, bad, min_component_size=min_component_size)
    if method == "robust":
        return integrate_robust(dzdx, dzdy, field_mm, bad, min_component_size=min_component_size, progress=progress)
    if method == "dct":
        z = integrate_dct(np.where(bad, 0.0, dzdx), np.where(bad, 0.0, dzdy), field_mm)
    elif method == "fft":
        z = integrate_fft(np.where(bad, 0.0, dzdx), np.where(bad, 0.0, dzdy), field_mm)
    if bad.any() and not bad.all():
        z = z - z[~bad].mean()
    z = np.where(bad, 0.0, z)
    return z, bad


def _checked_inputs(dzdx, dzdy, mask):
    """The gradient as float arrays of one 2-D shape, and the untrusted pixels (mask or non-finite)."""
    dzdx, dzdy = _gradient_pair(dzdx, dzdy)
    bad = ~(np.isfinite(dzdx) & np.isfinite(dzdy))
    if mask is not None:
        bad = bad | _mask_array(mask, dzdx.shape)
    return dzdx, dzdy, bad


def resolve_method(method: str, dzdx, dzdy, mask=None) -> str:
    """The solver :func:`integrate_gradient` runs for ``method``: ``"auto"`` is ``"masked"`` when a
    pixel is masked or a gradient non-finite, else ``"dct"``. One rule, so that what a caller
    reports is what ran."""
    if method != "auto" and method not in METHODS:
        raise EloInputError(f"integration method {method!r}: choose one of auto, {', '.join(METHODS)}")
    if method != "auto":
        return method
    bad = ~(np.isfinite(dzdx) & np.isfinite(dzdy))
    if mask is not None:
        bad = bad | np.asarray(mask, dtype=bool)
    return "masked" if bad.any() else "dct"


def reconstruction_quality(dzdx, dzdy, field_mm, height, mask_out, half_sampling_mm: float | None = None) -> dict:
    """How far a height map can be trusted: figures computed from its input and itself.

    Parameters
    ----------
    dzdx, dzdy : ndarray (H, W)
        The gradient that was integrated (mm/mm).
    field_mm : float or (float, float)
        Scan field in mm.
    height, mask_out : ndarray (H, W)
        What :func:`integrate_gradient` returned.
    half_sampling_mm : float, optional
        :func:`.sampling_check.half_sampling` of this map: how far heights from every other
        pixel differ from it (None: not measured).

    Returns
    -------
    dict
        ``integrability_residual``: RMS over neighbouring trusted pixel pairs of
        (Z_b - Z_a - (g_a + g_b)/2), relative to the RMS of (g_a + g_b)/2: 0 when the gradient is
        that of a surface, about 0.7 for noise (least squares keeps only the curl-free part).
        ``masked_fraction``: share of pixels without height. ``bowl_mm``: peak-to-valley of the
        best-fitting quadric (tilt and bowl) over the largest trusted region, and ``relief_mm``:
        that of the height minus the quadric. A small bias of the gradient over the field
        (flat-field correction, Eq. 26 at steep flanks, noise) integrates to exactly such a
        quadric, so ``bowl_mm > relief_mm`` says the height *range* is not measured relief.
        ``relief_rms_mm``: the RMS of the height minus the quadric. ``half_sampling_mm`` as given.
        ``regions``: connected regions of measured pixels, ``detached_fraction``: the share of
        them outside the largest (warned above :data:`MAX_DETACHED_FRACTION`: their heights are
        relative to their own means).
        ``warnings``: one line per figure above :data:`MAX_INTEGRABILITY_RESIDUAL`,
        :data:`MAX_MASKED_FRACTION`, a bowl larger than the relief, or a half-sampling difference
        above :data:`.sampling_check.MAX_HALF_SAMPLING` of the relief's RMS (the scan does not
        resolve the relief). ``flags``: a few words for each warning (a preview's title).
    """
    from scipy import ndimage

    dzdx, dzdy, bad = _checked_inputs(dzdx, dzdy, mask_out)
    gc, gr = _pixel_gradients(np.where(bad, 0.0, dzdx), np.where(bad, 0.0, dzdy), field_mm)
    z = np.asarray(height, dtype=float)
    ok = ~bad
    num = den = 0.0
    for axis in (1, 0):  # pairs along columns (+x), then along rows
        g = gc if axis == 1 else gr
        a = (slice(None), slice(None, -1)) if axis == 1 else (slice(None, -1), slice(None))
        b = (slice(None), slice(1, None)) if axis == 1 else (slice(1, None), slice(None))
        pair = ok[a] & ok[b]
        target = 0.5 * (g[a] + g[b])[pair]
        num += float(np.sum(((z[b] - z[a])[pair] - target) ** 2))
        den += float(np.sum(target ** 2))
    residual = math.sqrt(num / den) if den > 0 else 0.0
    masked = float(bad.mean())
    bowl = relief = relief_rms = 0.0
    labels, n = ndimage.label(ok)
    detached = 0.0
    if n:
        sizes = ndimage.sum_labels(ok, labels, range(1, n + 1))
        detached = float(1.0 - sizes.max() / sizes.sum())
        _, bowl, relief, relief_rms = fit_quadric(z, labels == 1 + int(np.argmax(sizes)))
    warnings, flags = [], []
    if residual > MAX_INTEGRABILITY_RESIDUAL:
        flags.append(f"not the gradient of a surface (residual {residual:.2f})")
        warnings.append(f"integrability residual {residual:.2f} > {MAX_INTEGRABILITY_RESIDUAL:g}: the gradient is "
                        "not that of a surface (noise, or inconsistent detector images); the heights are not reliable")
    if masked > MAX_MASKED_FRACTION:
        flags.append(f"{100 * masked:.0f} % without height")
        warnings.append(f"{100 * masked:.1f} % of the pixels have no height (> {100 * MAX_MASKED_FRACTION:g} %)")
    pixel = max(pixel_size(z.shape, field_mm))
    if bowl_exceeds(bowl, relief, pixel):
        flags.append(f"bowl {bowl:.3g} mm > relief {relief:.3g} mm")
        warnings.append(f"a field-wide tilt/bowl of {bowl:.3g} mm exceeds the relief of {relief:.3g} mm: a small "
                        "bias of the gradient integrates to that shape, so the height range is not measured relief "
                        "(local relief is)")
    if detached > MAX_DETACHED_FRACTION:
        flags.append(f"{n} regions apart")
        warnings.append(f"the measured pixels fall into {n} regions that masked pixels cut apart, "
                        f"{100 * detached:.1f} % of them outside the largest: each region's heights are relative to its "
                        "own mean (no slope connects them), so compare heights within one region only")
    said = resolution_warning(half_sampling_mm, relief_rms, pixel)
    if said:
        warnings.append(f"{said[0]}; smaller pixels help, and 'invert' where cliffs are the cause")
        flags.append(said[1])
    return {"integrability_residual": round(residual, 4), "masked_fraction": round(masked, 6),
            "bowl_mm": round(bowl, 6), "relief_mm": round(relief, 6), "relief_rms_mm": round(relief_rms, 6),
            "regions": int(n), "detached_fraction": round(detached, 6),
            "half_sampling_mm": None if half_sampling_mm is None else round(half_sampling_mm, 6), "warnings": warnings,
            "flags": flags,
            "thresholds": {"integrability_residual": MAX_INTEGRABILITY_RESIDUAL,
                           "masked_fraction": MAX_MASKED_FRACTION, "detached_fraction": MAX_DETACHED_FRACTION,
                           "bowl": "bowl_mm > relief_mm",
                           "half_sampling": f"half_sampling_mm > {MAX_HALF_SAMPLING:g} x relief_rms_mm"}}


def height_gradient(height, field_mm):
    """dZ/dx, dZ/dy (mm/mm) of a height map by central differences (one-sided at the edges).

    The inverse of the integrators, for histograms of normals (Fig. 14a) and tests. Rows run
    towards -y, hence the sign of dZ/dy.

    Parameters
    ----------
    height : ndarray (H, W)
        Heights in mm, package orientation.
    field_mm : float or (float, float)
        Scan field in mm.

    Returns
    -------
    dzdx, dzdy : ndarray (H, W)
        Gradient in mm/mm.

    Examples
    --------
    >>> import numpy as np
    >>> height = np.tile(0.5 * np.arange(4.0), (3, 1))     # rises by 0.5 mm per 1 mm pixel towards +x
    >>> dzdx, dzdy = height_gradient(height, (4.0, 3.0))
    >>> dzdx.round(4).tolist()[0], float(np.abs(dzdy).max())
    ([0.5, 0.5, 0.5, 0.5], 0.0)
    """
    height = real_array("height", height)
    if min(height.shape) < 2:
        raise EloInputError(f"height: {height.shape[1]}x{height.shape[0]} px; differences need 2 pixels a side")
    dx, dy = pixel_size(height.shape, field_mm)
    g_row, g_col = np.gradient(height)
    return g_col / dx, -g_row / dy


def scan_grid_gradient(dzdx, dzdy, field_mm, work_distance_mm, heights=None, *, mask=None):
    """Surface slopes at the beam's landing points -> the gradient of the height *over the scan
    grid* of a perspective scan (beam from the pivot (0, 0, wd)).

    A gradient image holds, per pixel, the slope g = grad Z where that pixel's beam lands,
    L = S (1 - h / wd) for the scan point S on z = 0. The height seen by pixel S is H(S) = Z(L(S)),
    and differentiating, grad H = (1 - h / wd) g / (1 + S . g / wd). Integrating g itself over the
    scan grid is wrong by the factor: on 45-degree flanks 40 mm off axis (wd = 400) one flank
    reads 0.91 and the other 1.11 per pixel, and a relief whose mean slope is 0 integrates to a
    bowl (2 mm on the README's corrugated sheet). ``heights`` (mm, optional) refines the
    (1 - h/wd) factor; it is within 1e-3 of 1 for millimetre relief.

    The denominator 1 + S . g / wd is the cosine between the surface normal and the beam (over
    their lengths): <= 0 means a facet that faces away from the beam, which no beam lands on.
    Such slopes at unmasked pixels are refused (:func:`check_scan_grid_slopes`), not clamped: a
    clamp turned slopes scaled by 1e6 or 1e30 into the same plausible height map.

    Parameters
    ----------
    dzdx, dzdy : ndarray (H, W)
        Slopes (mm/mm) where each pixel's beam lands; NaN where unknown.
    field_mm : float or (float, float)
        Scan field in mm.
    work_distance_mm : float
        Height of the beam's pivot above the plate (mm), finite and > 0.
    heights : ndarray (H, W), optional
        Heights (mm) for the (1 - h/wd) factor; 1 without them.
    mask : ndarray of bool (H, W), optional
        Untrusted pixels (True): not checked, NaN in the result where their slope faces away.

    Returns
    -------
    gx, gy : ndarray
        The gradient of H over the scan grid; integrate these to get H per pixel. NaN where the
        input is not finite.

    Raises
    ------
    EloInputError
        A work distance that is not finite and > 0, or an unmasked slope facing away from the beam.
    """
    dzdx = np.asarray(dzdx, float)
    dzdy = np.asarray(dzdy, float)
    den = check_scan_grid_slopes(dzdx, dzdy, field_mm, work_distance_mm, mask)
    wd = float(work_distance_mm)
    shrink = 1.0 if heights is None else 1.0 - np.asarray(heights, float) / wd
    ok = np.isfinite(den) & (den > 0)
    safe = np.where(ok, den, 1.0)
    return (np.where(ok, shrink * dzdx / safe, np.nan), np.where(ok, shrink * dzdy / safe, np.nan))


def check_scan_grid_slopes(dzdx, dzdy, field_mm, work_distance_mm, mask=None, *, source: str = "gradient"):
    """Refuse slopes that face away from the beam of a perspective scan, in one line naming them.

    The beam of scan point S = (x, y) comes from the pivot (0, 0, wd) and lands on a facet of
    slope g only if 1 + S . g / wd > 0 (the cosine between the facet's normal and the beam is
    positive): at r = |S| from the axis the surface may fall away from the axis by at most wd / r
    (mm/mm). Pixels where ``mask`` is True, and non-finite slopes (unknown), are not checked.

    Parameters
    ----------
    dzdx, dzdy : ndarray (H, W)
        Slopes (mm/mm) where each pixel's beam lands.
    field_mm : float or (float, float)
        Scan field in mm.
    work_distance_mm : float
        Height of the pivot above the plate (mm).
    mask : ndarray of bool (H, W), optional
        Untrusted pixels (True).
    source : str
        How the message names the gradient (its file).

    Returns
    -------
    ndarray (H, W)
        The denominator 1 + S . g / wd (NaN where a slope is not finite).

    Examples
    --------
    >>> import numpy as np
    >>> dzdx = np.zeros((4, 4)); dzdx[0, 3] = -30.0      # at (30, 30) mm: falls steeply towards +x
    >>> check_scan_grid_slopes(dzdx, np.zeros((4, 4)), 80.0, 400.0, source="g.exr")
    Traceback (most recent call last):
    ...
    elo_mitsuba.errors.EloInputError: g.exr: 1 of 16 unmasked pixels hold a slope that faces away from the beam ...
    """
    from ..grid import pixel_coordinates

    try:
        wd = float(work_distance_mm)
    except (TypeError, ValueError, OverflowError):
        wd = math.nan
    if not (math.isfinite(wd) and wd > 0):
        raise EloInputError(f"{source}: work distance {work_distance_mm!r} mm: a perspective scan needs a finite "
                            "pivot height > 0")
    dzdx = np.asarray(dzdx, float)
    dzdy = np.asarray(dzdy, float)
    if dzdx.shape != dzdy.shape or dzdx.ndim != 2:
        raise EloInputError(f"dzdx {dzdx.shape} and dzdy {dzdy.shape}: expected two 2-D arrays of one shape")
    x, y = pixel_coordinates(dzdx.shape, field_mm)
    finite = np.isfinite(dzdx) & np.isfinite(dzdy)
    with np.errstate(all="ignore"):
        den = np.where(finite, 1.0 + (x * np.where(finite, dzdx, 0.0) + y * np.where(finite, dzdy, 0.0)) / wd, np.nan)
    checked = finite if mask is None else finite & ~np.asarray(mask, bool)
    bad = checked & ~(np.isfinite(den) & (den > 0))
    if bad.any():
        worst = np.where(bad, np.nan_to_num(den, nan=-np.inf), np.inf)
        i, j = np.unravel_index(int(np.argmin(worst)), den.shape)
        r = math.hypot(x[i, j], y[i, j])
        fall = -(x[i, j] * dzdx[i, j] + y[i, j] * dzdy[i, j]) / r
        raise EloInputError(
            f"{source}: {int(bad.sum())} of {int(checked.sum())} unmasked pixels hold a slope that faces away from "
            f"the beam (1 + S.g/wd <= 0, perspective scan, work distance {wd:g} mm); the worst, row {i} column {j} "
            f"({r:.4g} mm off axis), falls away from the axis by {fall:.4g} mm/mm (dzdx {dzdx[i, j]:.4g}, "
            f"dzdy {dzdy[i, j]:.4g}) where the beam reaches at most wd/r = {wd / r:.4g}: a slope of the wrong "
            "scale or sign; mask such pixels (mask 1) if they are unknown")
    return den


#: ``reconstruct``: a perspective scan's conversion (:func:`scan_grid_gradient`) takes the factor
#: 1 - h/wd as 1; a height range above this share of the work distance makes that several % wrong.
MAX_RELIEF_OVER_WORK_DISTANCE = 0.05


def perspective_relief_warning(height, mask_out, work_distance_mm) -> str | None:
    """One warning line when a perspective scan's height range is not small against the work
    distance (:data:`MAX_RELIEF_OVER_WORK_DISTANCE`), else None."""
    height = np.asarray(height, float)
    valid = ~np.asarray(mask_out, bool)
    span = float(np.ptp(height[valid])) if valid.any() else 0.0
    wd = float(work_distance_mm)
    if span > MAX_RELIEF_OVER_WORK_DISTANCE * wd:
        return (f"the height range {span:.4g} mm is {span / wd:.2g} x the work distance {wd:g} mm (> "
                f"{MAX_RELIEF_OVER_WORK_DISTANCE:g}): the perspective conversion assumes relief small against the "
                "work distance and neighbouring beams landing close together; these heights are not reliable "
                "(check the gradient's scale)")
    return None
