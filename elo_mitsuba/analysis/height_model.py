"""The detector images of a height map, and their derivatives with respect to every height.

The forward model that :mod:`.inversion` inverts, written once in Dr.Jit and differentiated by
Dr.Jit's automatic differentiation (forward mode), never by a second hand-written physics:

* **Surface.** The unknowns are the heights at the pixels' *corners*, ``g`` of shape (H + 1, W + 1);
  each pixel is the bilinear patch over its four corners, and the beam of pixel (i, j) lands at
  the patch's centre, at the mean height of the corners, ``corner_mean(g)``. The height map the
  package reports (the scan-grid convention of :func:`~.integrate.scan_grid_gradient`) is the
  cubic interpolation of the corners at the pixel centres (:func:`pixels_from_corners`), which a
  curved surface's own height follows to fourth order.
  The landing point is P = (t x, t y, h) with t = 1 - h / wd for the perspective beam (x, y the
  aim point on z = 0), (x, y, h) for the orthographic one; each corner's point likewise, and the
  facet normal is the patch's normal at its centre, (P_tr + P_br - P_tl - P_bl) x (P_tl + P_tr -
  P_bl - P_br) normalised. On a plane this is the plane's normal exactly, perspective included.
  Corners rather than central differences of the pixel heights: central differences do not see a
  height pattern that alternates from pixel to pixel along a row or a column (a whole line of
  frequencies), and an inversion would fill those with noise; the patch misses only the one
  corner checkerboard, which the solver's regulariser fixes.
* **1st event.** N_1,d/N_0 of that facet (Eq. 5 over each disc, g_BSE of Eq. 13) by
  :class:`~.detector_model.FacetModel`, the renderer's own g_BSE code.
* **Shadowing.** A node of a disc's integration rule that the surface hides from the landing point
  (the ray to it passes under the height field) contributes 0, so a disc that a ridge cuts in part
  is counted in part (to the rule's resolution: (1, 4) nodes count quarters). Visibility is a step
  function of the heights: it is evaluated in the value and held fixed in the derivative (its
  discontinuity has no derivative).
* **Beam profile.** The renderer's beam of FWHM w lands at Gaussian offsets around the aim point;
  the image is then the sharp-beam image convolved with that Gaussian on the scan grid (exact to
  the grid's sampling: the sub-beams see the surface at other scan points). With w below a pixel
  the convolution is left out.
* **Later events** (2nd and more, e.g. a chamber's walls): a fixed image per detector, added to the
  blurred 1st event, typically the ``<id>.e2`` channels of a full render of the current surface.
* **Gains**: a factor per detector (the STSA correction of Eq. 15 cancels them).

What the model leaves out: the variation of the later events with the heights within one solve, the
shadow of a neighbour on part of a disc, and the slope variation inside one pixel (the surface is
as smooth as its samples).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from ..errors import EloInputError
from ..grid import pixel_size
from ..schema import FWHM_RANGE, fwhm_to_sigma, is_fwhm
from .detector_model import DEFAULT_NODES, FacetModel
from .grid_kernels import GridKernels
from .jit_arrays import bools, floats

#: The stencil of one pixel's facet: its four corners (top = the +y side, row i of the corner grid).
STENCIL = ("tl", "tr", "bl", "br")
_CORNER = {"tl": (0, 0), "tr": (0, 1), "bl": (1, 0), "br": (1, 1)}  # (row, column) offsets
#: Shadow march: step along the ray's ground track, in pixels (a ridge narrower than this can be
#: stepped over); most steps per ray.
SHADOW_STEP_PX = 0.5
MAX_SHADOW_STEPS = 4096
#: Blocks (pixels) of the shadow march's height bound: a ray above the highest height of the 3 x 3
#: blocks around it skips a block's width at once (0: the global slope bound alone). Rays rise
#: towards the detectors, so they cannot meet the surface within that neighbourhood. A cliff makes
#: the slope bound useless (a 1 mm wall in one 0.053 mm pixel: 19): lifting 0.7 mm of a 1500^2 field
#: took the march from 0.5 to 2.5 s, and 0.45 s with blocks of 8 pixels.
SKIP_BLOCK_PX = 8
#: A beam FWHM below this many pixels is not convolved (the Gaussian would be a delta on the grid).
MIN_BLUR_PX = 0.25


# ---- the stencil, as linear maps of the height array (and their transposes) ----------------------
def corner(g, which: str) -> np.ndarray:
    """The (H, W) heights of each pixel's corner ``which`` from the corner grid ``g`` (H + 1, W + 1)."""
    di, dj = _CORNER[which]
    return g[di:di + g.shape[0] - 1, dj:dj + g.shape[1] - 1]


def corner_t(v, which: str) -> np.ndarray:
    """The transpose of :func:`corner`: (H + 1, W + 1) from per-pixel values ``v`` (H, W)."""
    di, dj = _CORNER[which]
    out = np.zeros((v.shape[0] + 1, v.shape[1] + 1))
    out[di:di + v.shape[0], dj:dj + v.shape[1]] = v
    return out


def corner_mean(g) -> np.ndarray:
    """Pixel heights (H, W): the mean of each pixel's four corners (its patch's centre)."""
    return 0.25 * sum(corner(g, c) for c in STENCIL)


def _midpoints(a, axis):
    """Values midway between neighbours along ``axis`` (n + 1 of them, the two ends outside), by the
    cubic through four neighbours, (-a_-1 + 9 a_0 + 9 a_1 - a_2) / 16: exact for cubics, so a
    smooth surface's curvature does not bias it (the mean of two neighbours is off by h'' d^2 / 8);
    linear extrapolation beyond the border (odd reflection), exact on planes."""
    a = np.moveaxis(np.asarray(a, float), axis, 0)
    if a.shape[0] < 3:
        pad = np.concatenate([2 * a[:1] - a[1:2], a, 2 * a[-1:] - a[-2:-1]])
        return np.moveaxis(0.5 * (pad[:-1] + pad[1:]), 0, axis)
    pad = np.concatenate([2 * a[:1] - a[2:3], 2 * a[:1] - a[1:2], a, 2 * a[-1:] - a[-2:-1], 2 * a[-1:] - a[-3:-2]])
    mid = (-pad[:-3] + 9 * pad[1:-2] + 9 * pad[2:-1] - pad[3:]) / 16.0
    return np.moveaxis(mid, 0, axis)


def corners_from_pixels(h) -> np.ndarray:
    """Corner heights (H + 1, W + 1) interpolated from pixel heights (H, W) (cubic, :func:`_midpoints`)."""
    return _midpoints(_midpoints(h, 0), 1)


def pixels_from_corners(g) -> np.ndarray:
    """Pixel-centre heights (H, W) interpolated from corner heights (H + 1, W + 1), the same cubic rule:
    the height map the inversion reports (its bilinear patches' own centres, :func:`corner_mean`, lie
    h'' d^2 / 8 below a curved surface)."""
    g = np.asarray(g, float)

    def inner(a, axis):
        a = np.moveaxis(a, axis, 0)
        n = a.shape[0] - 1  # pixels along this axis
        if n < 3:
            mid = 0.5 * (a[:-1] + a[1:])
        else:
            pad = np.concatenate([2 * a[:1] - a[1:2], a, 2 * a[-1:] - a[-2:-1]])
            mid = (-pad[:-3] + 9 * pad[1:-2] + 9 * pad[2:-1] - pad[3:]) / 16.0
        return np.moveaxis(mid, 0, axis)

    return inner(inner(g, 0), 1)


def blur_sigma_px(fwhm_mm: float, shape, field_mm) -> tuple[float, float]:
    """Standard deviation of the beam profile in pixels (rows, columns); (0, 0) below :data:`MIN_BLUR_PX`."""
    dx, dy = pixel_size(shape, field_mm)
    if not is_fwhm(fwhm_mm):
        raise EloInputError(f"beam fwhm {fwhm_mm!r} mm: must be {FWHM_RANGE}")
    sigma = fwhm_to_sigma(fwhm_mm)
    if fwhm_mm / max(dx, dy) < MIN_BLUR_PX:
        return 0.0, 0.0
    return sigma / dy, sigma / dx


def blur(image, sigma_px) -> np.ndarray:
    """The beam-profile convolution on the scan grid (separable Gaussian, edges extended); symmetric,
    so it is its own transpose up to the border treatment (``mode='reflect'``, which is symmetric)."""
    if not any(sigma_px):
        return image
    from scipy.ndimage import gaussian_filter

    return gaussian_filter(image, sigma_px, mode="reflect", truncate=4.0)


# ---- visibility ---------------------------------------------------------------------------------
def visibility(geometry, heights, points, targets) -> np.ndarray:
    """True where the ray from each landing point to each target clears the height field.

    Parameters
    ----------
    geometry : ScanGeometry
        The scan (grid, field, beam): the height field is bilinear in the scan grid, and a world
        point (x, y, z) lies over the scan point (x, y) / (1 - z / wd) of the perspective beam.
    heights : ndarray (H, W)
        Pixel heights (mm).
    points : ndarray (H, W, 3)
        Landing points.
    targets : ndarray (K, J, 3)
        E.g. the detectors' disc-rule nodes.

    Returns
    -------
    ndarray (K, J, H, W) bool
        (a byte per node and pixel: at 1500^2 with 4 discs of 16 nodes, 144 MB)

    The ray is marched along its ground track in one symbolic Dr.Jit loop per target, in steps of
    at least :data:`SHADOW_STEP_PX` pixels and, where it is high above the surface, as long as the
    surface's steepest slope allows without meeting it (exact to the minimum step); each ray stops
    when blocked, outside the grid or above the highest height.
    """
    from ..runtime import ensure_variant

    mi = ensure_variant()
    import drjit as dr

    h = np.asarray(heights, float)
    shape = h.shape
    targets = np.asarray(targets, float)
    out = np.ones(targets.shape[:2] + shape, bool)
    top = float(h.max())
    if top - float(h.min()) <= 0.0:
        return out  # a plane shadows nothing
    dx, dy = pixel_size(shape, geometry.field_mm)
    x0, y0 = geometry.aim_points()  # the grid's own aim points (a window of a scan is offset)
    col0, row0 = float(x0[0, 0]), float(y0[0, 0])
    inv_wd = 1.0 / geometry.work_distance_mm if geometry.projection == "perspective" else 0.0
    n_rows, n_cols = shape
    tex = floats(mi, h)
    px, py, pz = (floats(mi, points[..., c]) for c in range(3))
    step = SHADOW_STEP_PX * min(dx, dy)
    Float, UInt32 = mi.Float, mi.UInt32

    def height_at(row, col):
        r0 = dr.clip(dr.floor(row), 0, n_rows - 2)
        c0 = dr.clip(dr.floor(col), 0, n_cols - 2)
        fr, fc = row - r0, col - c0
        i = UInt32(r0) * n_cols + UInt32(c0)
        z00 = dr.gather(Float, tex, i)
        z01 = dr.gather(Float, tex, i + 1)
        z10 = dr.gather(Float, tex, i + n_cols)
        z11 = dr.gather(Float, tex, i + n_cols + 1)
        return dr.lerp(dr.lerp(z00, z01, fc), dr.lerp(z10, z11, fc), fr)

    # a bound on the surface's slope (bilinear cells): a ray `gap` above the surface that rises
    # at `slope` cannot meet it within gap / (bound - slope) along the ground, so it may skip that
    # far (and, rising faster than the bound, never meets it)
    gx = np.abs(np.diff(h, axis=1)).max(initial=0.0) / dx
    gy = np.abs(np.diff(h, axis=0)).max(initial=0.0) / dy
    bound = 1.01 * float(np.hypot(gx, gy)) + 1e-6
    # the highest height of each block and its 8 neighbours (bilinear cells reach no higher than
    # their corners): a rising ray above it cannot meet the surface within a block's width
    block = int(SKIP_BLOCK_PX)
    if block > 0:
        from scipy.ndimage import maximum_filter

        nbr, nbc = -(-n_rows // block), -(-n_cols // block)
        padded = np.full((nbr * block, nbc * block), -np.inf)
        padded[:n_rows, :n_cols] = h
        local = maximum_filter(padded.reshape(nbr, block, nbc, block).max(axis=(1, 3)), size=3, mode="nearest")
        tex_max = floats(mi, local)
        # (block - 1) pixels of the finer axis, less the perspective's magnification, keep the ray
        # within the 3 x 3 blocks; a whole number of steps keeps its samples where the march
        # without the skip puts them (else a wall one pixel thin is met or missed by chance)
        block_mm = step * np.floor((block - 1) * min(dx, dy) * (1.0 - max(top, 0.0) * inv_wd) / step)
    # opaque: what depends on the heights or on where a window lies changes at every step of a
    # solve (as literals it compiled the march anew each time)
    top_o, bound_o = dr.opaque(Float, top), dr.opaque(Float, bound)
    col0_o, row0_o = dr.opaque(Float, col0), dr.opaque(Float, row0)
    block_mm_o = dr.opaque(Float, float(block_mm)) if block > 0 else None
    for k in range(targets.shape[0]):
        for j in range(targets.shape[1]):
            # opaque: one kernel for every target (literals would compile one each)
            qx, qy, qz = (dr.opaque(Float, float(v)) for v in targets[k, j])
            vx, vy, vz = qx - px, qy - py, qz - pz
            ground = dr.maximum(dr.sqrt(vx * vx + vy * vy), 1e-9)
            ux, uy, slope = vx / ground, vy / ground, vz / ground
            blocked = dr.zeros(mi.Bool, dr.width(px))
            catchable = slope < bound_o

            def cond(d, blocked):
                return ~blocked & (d < MAX_SHADOW_STEPS * step) & (pz + slope * d < top_o) & catchable

            def body(d, blocked):
                wx, wy, wz = px + ux * d, py + uy * d, pz + slope * d
                t = 1.0 - wz * inv_wd
                col = (wx / t - col0_o) * (1.0 / dx)
                row = (row0_o - wy / t) * (1.0 / dy)
                inside = (col >= 0) & (col <= n_cols - 1) & (row >= 0) & (row <= n_rows - 1)
                gap = wz - height_at(row, col)
                hit = inside & (gap < 0)
                skip = dr.maximum(step, gap / (bound_o - slope))
                if block > 0:
                    b = (UInt32(dr.clip(dr.floor(row * (1.0 / block)), 0, nbr - 1)) * nbc
                         + UInt32(dr.clip(dr.floor(col * (1.0 / block)), 0, nbc - 1)))
                    skip = dr.select(wz > dr.gather(Float, tex_max, b), dr.maximum(skip, block_mm_o), skip)
                # leaving the grid ends the march: what lies beyond is not known (counted clear)
                return dr.select(inside, d + skip, MAX_SHADOW_STEPS * step), blocked | hit

            _, blocked = dr.while_loop((dr.full(Float, step, dr.width(px)), blocked), cond, body,
                                       label="elo_shadow_march")
            out[k, j] = ~np.asarray(blocked, bool).reshape(shape)
    return out


# ---- the model ----------------------------------------------------------------------------------
@dataclass
class Linearisation:
    """The model at one height map: values and the derivatives that Gauss-Newton needs.

    Attributes
    ----------
    sharp : ndarray (K, H, W)
        1st event with shadowing, single-ray beam (before the beam profile), gains applied.
    images : ndarray (K, H, W)
        The model images: ``blur(sharp) + later``.
    partials : ndarray (4, K, H, W) or None
        d sharp / d g of each pixel's corners (:data:`STENCIL` order).
    visible : ndarray of bool (K, J, H, W) or None
        The shadowing held fixed: True where the surface lets the landing point see node j of
        detector k's disc rule (None: no shadowing modelled).
    partials_dr : list or None
        ``partials`` as Dr.Jit arrays (4 lists of K Floats of H * W), what the Jacobian's products use.
    """

    sharp: np.ndarray
    images: np.ndarray
    partials: np.ndarray | None
    visible: np.ndarray | None
    partials_dr: list | None = None


class HeightModel:
    """Detector images of height maps on one scan's grid, and their derivatives.

    Parameters
    ----------
    geometry : ScanGeometry
        Field, grid, beam, detectors and material (:mod:`.scan_geometry`).
    fwhm_mm : float
        Beam profile FWHM (0: a single ray).
    later : mapping of str to ndarray (H, W), optional
        Fixed images of the events >= 2 per detector (same units as the 1st event).
    gains : mapping of str to float, optional
        Detector gains (default 1).
    shadows : bool
        Evaluate the surface's shadowing of the detectors (a plane has none; off saves the march).
    nodes : (int, int)
        Disc rule of :class:`~.detector_model.FacetModel`.
    """

    def __init__(self, geometry, *, fwhm_mm: float = 0.0, later: Mapping | None = None,
                 gains: Mapping | None = None, shadows: bool = True, nodes=DEFAULT_NODES):
        self.geometry = geometry
        self.names = tuple(geometry.detectors)
        self.shape = tuple(geometry.shape)
        self.sigma_px = blur_sigma_px(fwhm_mm, self.shape, geometry.field_mm)
        self.fwhm_mm = float(fwhm_mm)
        self.shadows = bool(shadows)
        self.facets = FacetModel(geometry.detectors, geometry.material, nodes=nodes)
        self.gains = np.array([float((gains or {}).get(n, 1.0)) for n in self.names])
        if later is None:
            self.later = np.zeros((len(self.names),) + self.shape, np.float32)
        else:
            missing = [n for n in self.names if n not in later]
            if missing:
                raise EloInputError(f"later-event images lack the detector(s) {', '.join(missing)}")
            self.later = np.stack([np.asarray(later[n], np.float32) for n in self.names])
            if self.later.shape[1:] != self.shape:
                raise EloInputError(f"later-event images are {self.later.shape[2]}x{self.later.shape[1]} px, "
                                    f"the scan {self.shape[1]}x{self.shape[0]}")
        ax, ay = geometry.aim_points()
        self._aim = (ax, ay)
        _, dirs = geometry.beam(None)  # the beam's direction does not depend on where it lands
        mi = self.facets.mi
        self.kernels = GridKernels(self.shape, self.sigma_px)
        self._dirs = mi.Vector3f(*[floats(mi, dirs[..., c]) for c in range(3)])

    # -- pieces --
    def landing_points(self, heights) -> np.ndarray:
        """(H, W, 3) landing points of the beams on ``heights``."""
        points, _ = self.geometry.beam(heights)
        return points

    def _landing_dr(self, h, x, y):
        """Landing point (Dr.Jit) of aim point (x, y) at height h."""
        mi = self.facets.mi
        if self.geometry.projection == "perspective":
            t = 1.0 - h * (1.0 / self.geometry.work_distance_mm)
            return mi.Point3f(t * x, t * y, h)
        return mi.Point3f(x, y, h)

    def _sharp(self, g, visible, derivatives: bool):
        """1st event (K Floats of H * W) of the corner heights ``g`` and, with ``derivatives``, its
        partials with respect to each pixel's corners (4 lists, :data:`STENCIL` order, of K Floats):
        one forward-mode AD pass per corner."""
        facets = self.facets
        mi, dr = facets.mi, facets.dr
        dx, dy = pixel_size(self.shape, self.geometry.field_mm)
        ax, ay = self._aim

        hs = {c: floats(mi, corner(g, c)) for c in STENCIL}
        offsets = {"tl": (-0.5 * dx, 0.5 * dy), "tr": (0.5 * dx, 0.5 * dy),
                   "bl": (-0.5 * dx, -0.5 * dy), "br": (0.5 * dx, -0.5 * dy)}
        aims = {c: (floats(mi, ax + ox), floats(mi, ay + oy)) for c, (ox, oy) in offsets.items()}
        centre = (floats(mi, ax), floats(mi, ay))
        # (J, H, W) per detector, node-major
        vis = None if visible is None else [bools(mi, v) for v in visible]
        gains = [float(v) for v in self.gains]

        def evaluate(hv):
            p = {c: self._landing_dr(hv[c], *aims[c]) for c in STENCIL}
            along_x = (p["tr"] + p["br"]) - (p["tl"] + p["bl"])
            along_y = (p["tl"] + p["tr"]) - (p["bl"] + p["br"])
            n = dr.normalize(dr.cross(along_x, along_y))
            h_c = (hv["tl"] + hv["tr"] + hv["bl"] + hv["br"]) * 0.25
            sig = facets.signals(self._landing_dr(h_c, *centre), self._dirs, [n], visible=vis)[0]
            return [v_s * gain for v_s, gain in zip(sig, gains)]

        values = evaluate(hs)
        dr.eval(values)
        if not derivatives:
            return values, None
        partials = []
        for c in STENCIL:
            hv = {key: mi.Float(v) for key, v in hs.items()}
            dr.enable_grad(hv[c])
            out = evaluate(hv)
            dr.forward(hv[c])
            grads = [dr.detach(dr.grad(o)) for o in out]
            dr.eval(grads)
            partials.append(grads)
        return values, partials

    # -- public --
    def evaluate(self, corners, *, derivatives: bool = False, visible=None) -> Linearisation:
        """The model images for the corner heights ``corners`` ((H + 1, W + 1) mm, see
        :func:`corners_from_pixels`) and, with ``derivatives``, the partials.

        ``visible`` (K, J, H, W) reuses a shadowing computed before (else it is evaluated when
        ``shadows`` is on)."""
        g = np.asarray(corners, float)
        if g.shape != (self.shape[0] + 1, self.shape[1] + 1):
            raise EloInputError(f"corner heights are {g.shape}; the scan of {self.shape[1]}x{self.shape[0]} px "
                                f"needs {(self.shape[0] + 1, self.shape[1] + 1)}")
        if visible is None:
            if self.shadows:
                h = corner_mean(g)
                visible = visibility(self.geometry, h, self.landing_points(h), self.facets.node_positions())
            else:
                visible = None
        values, partials_dr = self._sharp(g, visible, derivatives)
        shape = self.shape
        sharp = np.stack([np.asarray(v, np.float32).reshape(shape) for v in values])
        images = np.stack([np.asarray(v, np.float32).reshape(shape) for v in self.kernels.blur(values)]) + self.later
        partials = None if partials_dr is None else np.stack(
            [np.stack([np.asarray(v, np.float32).reshape(shape) for v in per]) for per in partials_dr])
        return Linearisation(sharp=sharp, images=images, partials=partials, visible=visible, partials_dr=partials_dr)

    def images(self, heights) -> dict[str, np.ndarray]:
        """The model images by detector name, each (H, W) float64, for pixel heights ``heights``
        (H, W; their corners by :func:`corners_from_pixels`) or corner heights (H + 1, W + 1)."""
        g = np.asarray(heights, float)
        if g.shape == self.shape:
            g = corners_from_pixels(g)
        lin = self.evaluate(g)
        return {n: lin.images[k].astype(np.float64) for k, n in enumerate(self.names)}

    def _partials_dr(self, lin: Linearisation) -> list:
        if lin.partials_dr is None:  # a linearisation built elsewhere: its numpy partials
            mi = self.facets.mi
            lin.partials_dr = [[floats(mi, a) for a in per]
                               for per in lin.partials]
        return lin.partials_dr

    def jacobian_dr(self, lin: Linearisation, dg) -> list:
        """d images . dg in Dr.Jit: K Floats of H * W for a change ``dg`` of the corner heights
        (Float of (H + 1) * (W + 1)), shadowing held fixed."""
        partials = self._partials_dr(lin)
        at = self.kernels.corners(dg)
        dsharp = [sum(partials[m][kk] * at[m] for m in range(len(STENCIL))) for kk in range(len(self.names))]
        return self.kernels.blur(dsharp)

    def jacobian_t_dr(self, lin: Linearisation, v: list):
        """The transpose of :meth:`jacobian_dr`: a Float of (H + 1) * (W + 1) for image-space weights
        ``v`` (K Floats of H * W)."""
        partials = self._partials_dr(lin)
        bv = self.kernels.blur(v)
        per_corner = [sum(partials[m][kk] * bv[kk] for kk in range(len(self.names))) for m in range(len(STENCIL))]
        self.facets.dr.eval(per_corner)
        return self.kernels.corners_t(per_corner)

    def apply_jacobian(self, lin: Linearisation, dg) -> np.ndarray:
        """d images . dg: (K, H, W) for a change ``dg`` of the corner heights, shadowing held fixed."""
        mi = self.facets.mi
        out = self.jacobian_dr(lin, floats(mi, dg))
        return np.stack([np.asarray(o, np.float32).reshape(self.shape) for o in out]).astype(float)

    def apply_jacobian_t(self, lin: Linearisation, v) -> np.ndarray:
        """The transpose of :meth:`apply_jacobian`: (H + 1, W + 1) for image-space weights ``v`` (K, H, W)."""
        mi = self.facets.mi
        out = self.jacobian_t_dr(lin, [floats(mi, x) for x in v])
        return np.asarray(out, np.float32).reshape(self.shape[0] + 1, self.shape[1] + 1).astype(float)


def sub_pixel_fwhm(fwhm_mm: float, pixel_mm: float, factor: int) -> float:
    """The beam FWHM (mm) that a model on a grid ``factor`` times finer convolves with, so that its
    images averaged over each scan pixel's ``factor`` x ``factor`` sub-pixels have the beam's own
    profile: the block mean adds the variance of ``factor`` equally spaced offsets per axis,
    pixel^2 (factor^2 - 1) / (12 factor^2), which is taken off the beam's (to 0 at least).

    Examples
    --------
    >>> round(sub_pixel_fwhm(0.27, 0.2, 2), 4), sub_pixel_fwhm(0.27, 0.2, 1)
    (0.243, 0.27)
    """
    sigma2 = fwhm_to_sigma(fwhm_mm) ** 2 - pixel_mm ** 2 * (factor * factor - 1) / (12.0 * factor * factor)
    return float(np.sqrt(max(sigma2, 0.0)) / fwhm_to_sigma(1.0))


def sub_pixel_mean(a, factor: int) -> np.ndarray:
    """The mean of each block of ``factor`` x ``factor`` values of the last two axes.

    Examples
    --------
    >>> sub_pixel_mean(np.arange(16.0).reshape(4, 4), 2).tolist()
    [[2.5, 4.5], [10.5, 12.5]]
    """
    a = np.asarray(a)
    *lead, h, w = a.shape
    return a.reshape(*lead, h // factor, factor, w // factor, factor).mean(axis=(-3, -1))


class SuperResolvedModel:
    """The images of a height map ``factor`` times finer than the scan grid, on the scan grid.

    A pore or a bump of two or three pixels has a relief inside each pixel that one facet per pixel
    cannot hold: on a rough layer with 0.5 mm pores at 0.2 mm pixels the model of the true heights
    misses the render by 2 noise levels at the pores (0.025 against 0.0013 elsewhere, corrected
    units). Here the facets are the sub-pixels of a grid ``factor`` times finer (:class:`HeightModel`
    on it), each scan pixel's image the mean of its sub-pixels' (the sub-beams land at their
    centres, the beam's profile reduced by the block's own spread, :func:`sub_pixel_fwhm`): at
    factor 2 the same case misses by 0.0125, at 4 by 0.0116. The unknowns are the fine grid's
    corners; the scan pixel's centre is one of them (even factors).

    Parameters
    ----------
    geometry : ScanGeometry
        The scan (its grid is the data's).
    factor : int
        Sub-pixels per pixel along each axis (2 or more).
    fwhm_mm, later, gains, shadows, nodes
        As for :class:`HeightModel` (``later`` on the scan grid).

    Examples
    --------
    >>> from elo_mitsuba.analysis.scan_geometry import ScanGeometry
    >>> geo = ScanGeometry.nominal((8, 8), 4.0, 100.0, 150.0)
    >>> model = SuperResolvedModel(geo, 2, fwhm_mm=0.0, shadows=False)
    >>> lin = model.evaluate(np.zeros((17, 17)))
    >>> lin.images.shape, lin.partials is None
    ((4, 8, 8), True)
    """

    def __init__(self, geometry, factor: int, *, fwhm_mm: float = 0.0, later: Mapping | None = None,
                 gains: Mapping | None = None, shadows: bool = True, nodes=DEFAULT_NODES):
        if int(factor) != factor or factor < 2:
            raise EloInputError(f"super-resolution factor {factor!r}: must be an integer >= 2")
        self.factor = int(factor)
        self.coarse_shape = tuple(geometry.shape)
        fine_shape = (self.coarse_shape[0] * self.factor, self.coarse_shape[1] * self.factor)
        dx, dy = pixel_size(self.coarse_shape, geometry.field_mm)
        self.fine = HeightModel(geometry.resized(fine_shape), fwhm_mm=sub_pixel_fwhm(fwhm_mm, max(dx, dy), self.factor),
                                gains=gains, shadows=shadows, nodes=nodes)
        self.geometry, self.names, self.shape = geometry, self.fine.names, fine_shape
        self.sigma_px = self.fine.sigma_px
        self.fwhm_mm, self.shadows = float(fwhm_mm), bool(shadows)
        coarse = HeightModel(geometry, later=later, shadows=False, nodes=nodes)  # checks ``later``
        self.later = coarse.later

    def evaluate(self, corners, *, derivatives: bool = False, visible=None) -> Linearisation:
        """:meth:`HeightModel.evaluate` on the fine grid (corners (fH + 1, fW + 1)); ``images`` on
        the scan grid, ``sharp``, ``partials`` and ``visible`` on the fine one."""
        lin = self.fine.evaluate(corners, derivatives=derivatives, visible=visible)
        lin.images = sub_pixel_mean(lin.images, self.factor) + self.later
        return lin

    def jacobian_dr(self, lin: Linearisation, dg) -> list:
        """d images . dg on the scan grid (K Floats) for a change ``dg`` of the fine corners (a Float)."""
        return self.fine.kernels.sub_pixel_mean(self.fine.jacobian_dr(lin, dg), self.factor)

    def jacobian_t_dr(self, lin: Linearisation, v: list):
        """The transpose of :meth:`jacobian_dr`: the fine corners (a Float) from scan-grid weights ``v``."""
        return self.fine.jacobian_t_dr(lin, self.fine.kernels.sub_pixel_spread(v, self.factor))

    def apply_jacobian(self, lin: Linearisation, dg) -> np.ndarray:
        """d images . dg on the scan grid (K, H, W) for a change ``dg`` of the fine corners."""
        mi = self.fine.facets.mi
        out = self.jacobian_dr(lin, floats(mi, dg))
        return np.stack([np.asarray(o, np.float32).reshape(self.coarse_shape) for o in out]).astype(float)

    def apply_jacobian_t(self, lin: Linearisation, v) -> np.ndarray:
        """The transpose of :meth:`apply_jacobian`: fine corners from scan-grid weights ``v`` (K, H, W)."""
        mi = self.fine.facets.mi
        out = self.jacobian_t_dr(lin, [floats(mi, x) for x in v])
        return np.asarray(out, np.float32).reshape(self.shape[0] + 1, self.shape[1] + 1).astype(float)

    def scan_heights(self, corners) -> np.ndarray:
        """Heights at the scan pixels' centres (H, W): the fine corners there (odd factors: the
        centre of the middle sub-pixel, :func:`pixels_from_corners`)."""
        g, f = np.asarray(corners, float), self.factor
        h, w = self.coarse_shape
        if f % 2 == 0:
            return g[f // 2::f, f // 2::f][:h, :w]
        return pixels_from_corners(g)[f // 2::f, f // 2::f][:h, :w]
