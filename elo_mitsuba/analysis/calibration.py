"""Detector calibration from flat-plate images: where each detector really is, and its gain.

A flat plate (n_S = [0, 0, 1]) scanned over the field gives each detector an image whose shape
depends on where the detector sits and how it is tilted (distance, angles and the lobe of g_BSE
change across the field), and whose level is the amplifier gain times N_d/N_0. Each detector's
image depends on that detector alone, so each is fitted on its own: by least squares
(Levenberg-Marquardt, :func:`scipy.optimize.least_squares`) of

    image(x, y)  =  gain * S(x, y; centre, normal)  [+ offset]

against the 1st-event model :class:`~.detector_model.FacetModel` on a coarse grid of the image
(block means; the flat's image is smooth). Parameters: the centre (3, mm), the normal as two tilt
angles from the nominal one (deg), the gain, and optionally an offset. The radius is held at its
nominal value: it scales the signal like the gain (S ~ area), so the two cannot be separated.

Images that are not of a flat plate are refused (:class:`~elo_mitsuba.errors.EloInputError`):
a detector whose rms misfit exceeds what a flat plate's images with their own noise leave
(:func:`misfit_bound`) makes the fit's geometry meaningless, however small its stated error.
Isolated dead or hot pixels do not pull the fit: blocks whose residual is more than
:data:`OUTLIER_SIGMA` robust standard deviations off are left out and the fit repeated
(:attr:`DetectorFit.rejected` counts them).

The result, :class:`Calibration`, is written as ``CALIB.json`` (per detector: ``center``,
``normal``, ``radius``, ``gain``, ``offset``, one-sigma uncertainties, the parameter correlations
and which parameters the data cannot separate) and turns nominal geometry into calibrated
geometry (:meth:`Calibration.apply`). Gains cancel in the STSA correction when the flat and the
object are recorded with one amplifier setting; the geometry is what the model-based gradient
needs.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

import numpy as np

from ..arguments import input_file
from ..constants import DETECTOR_NAMES
from ..errors import EloInputError
from ..files import atomic_write, check_output
from ..scene_files import check_detector_placement
from .detector_model import FacetModel, to_vector
from .scan_geometry import Disc, ScanGeometry

#: Coarse grid the fit runs on (block means of the flat image): at least this many blocks a side
#: (fewer pixels: one per pixel), as many as whole blocks of h // FIT_GRID pixels fill (below 2 x FIT_GRID).
FIT_GRID = 48
#: Smallest image side the fit takes: 8 x 8 values against up to 7 parameters per detector.
MIN_SIDE = 8
#: The fit's own bias in a detector centre (mm): fitted to a noise-free 1st-event render of the
#: flat plate with the detectors at the drawn position (scenes_xml/flat_plate.xml, events=1,
#: 64, 128 and 256 px), every centre comes out 0.17-0.18 mm from where it is (the model's disc
#: quadrature against the render's). A displacement below it is not evidence of a moved detector.
FIT_BIAS_MM = 0.2


def describe_displacement(moved_mm: float, sigma_mm: float, scale_mm: float | None = None) -> str:
    """A fitted centre's distance from the drawing, against what the fit can tell: ``"not moved
    (within the fit's 0.2 mm bias and +-0.05 mm noise)"`` when ``moved_mm`` is within
    :data:`FIT_BIAS_MM` plus two standard errors ``sigma_mm``, else ``"moved 5.40 mm (+-0.05,
    bias 0.2)"``. Where two standard errors exceed ``scale_mm`` (the detector's radius: the fit
    cannot place the detector within its own size) or are not finite, "not moved" would claim what
    the images cannot tell: ``"position not determined (+-34 mm at 2 sigma, more than the
    detector's 25 mm radius)"``."""
    limit = FIT_BIAS_MM + 2.0 * sigma_mm
    if moved_mm <= limit or not math.isfinite(sigma_mm):
        if not math.isfinite(sigma_mm):
            return "position not determined (the fit's uncertainty is not finite)"
        if scale_mm is not None and 2.0 * sigma_mm > scale_mm:
            return (f"position not determined (+-{2 * sigma_mm:.2g} mm at 2 sigma, more than the detector's "
                    f"{scale_mm:g} mm radius)")
        return f"not moved (within the fit's {FIT_BIAS_MM:g} mm bias and +-{2 * sigma_mm:.2g} mm noise)"
    return f"moved {moved_mm:.2f} mm (+-{sigma_mm:.2f}, fit bias {FIT_BIAS_MM:g})"


#: Refusing images that are not of a flat plate (:func:`misfit_bound`). A flat plate's image is
#: smooth, so the fit leaves about the noise of the block means: sigma_pixel / sqrt(pixels per
#: block), sigma_pixel the image's own relative noise (second differences over its smoothed level,
#: :func:`~.noise.relative_noise`). A detector's rms misfit (relative, block means) may reach
#: MISFIT_NOISE_FACTOR times that, at least MISFIT_FLOOR; sigma_pixel counts at most
#: PIXEL_NOISE_CAP: relief finer than a pixel (or edges of relief) passes for noise in one image,
#: and a flat-plate recording is not that noisy. Measured (misfit on the block means):
#:   flat_plate renders, 16-1024 px: noise-free 0.000 %; with 1 % and 5 % multiplicative noise per
#:   pixel the misfit is 0.88-1.07 x the estimated noise of the block means (1 % at 16-64 px,
#:   0.49 % at 128, 0.024 % for 0.5 % at 1024); Monte-Carlo renders (quality=scene) 0.04-0.10 %,
#:   0.9-1.15 x their noise; athene_flat (the plate in a chamber, events 1+2) 0.04-0.24 %.
#:   corrugated_sheet, the worst detector: 45 % (16 px), 66 % (32), 84 % (64), 20 % (128),
#:   9.5 % (256), 5.9 % (1024). Its noise estimate was the relief itself (20-55 % per pixel at 16,
#:   32, 128 and 256 px; bounds 15, 15, 1.3, 7.5, 3.0, 1.0 %) until :func:`~.noise.estimate_noise`
#:   took the second differences along the ridges too: 0.16-0.22 % at 16-256 px, the bound the floor,
#:   and at 32 px all four detectors refused (back and front at 8.5 %) where two were.
#:   One dead pixel at 32 px, before outliers were left out: 3.5 % (bound 1 %); a hot one (x10): 31 %.
#: The factor 3 leaves room for noise that is not white (neighbours' differences understate an
#: amplifier's low-pass along the lines); the floor, for a real machine's departures from the disc
#: model (the renders' own are < 1e-5); the cap, 5-10 x the noise of a usable flat (0.5-1 %; at
#: 32 px, 1 % already leaves the centres +-17 mm).
MISFIT_NOISE_FACTOR = 3.0
MISFIT_FLOOR = 0.01
PIXEL_NOISE_CAP = 0.05
#: A block whose residual is more than OUTLIER_SIGMA robust standard deviations (1.4826 MAD, at
#: least OUTLIER_FLOOR: the model's own error on noise-free renders is < 1e-5) from the median is
#: an outlier (a dead or hot pixel); the fit is repeated without it, at most OUTLIER_ROUNDS times.
#: More than MAX_OUTLIER_FRACTION of the blocks off is no isolated defect: nothing is left out
#: and the misfit check judges the images.
OUTLIER_SIGMA = 5.0
OUTLIER_FLOOR = 1e-3
OUTLIER_ROUNDS = 3
MAX_OUTLIER_FRACTION = 0.02


def misfit_bound(image, block_pixels: int) -> tuple[float, float]:
    """The largest rms misfit (relative) a flat plate's ``image`` may leave in a fit on block means
    of ``block_pixels`` pixels each, and the image's own relative noise per pixel it is based on:
    ``max(MISFIT_FLOOR, MISFIT_NOISE_FACTOR * min(noise, PIXEL_NOISE_CAP) / sqrt(block_pixels))``
    with ``noise`` from the image's second differences (:func:`~.noise.relative_noise`)."""
    from .noise import relative_noise

    noise = relative_noise({"image": image})
    noise = float(noise) if math.isfinite(noise) else 0.0
    block_noise = min(noise, PIXEL_NOISE_CAP) / math.sqrt(max(block_pixels, 1))
    return float(max(MISFIT_FLOOR, MISFIT_NOISE_FACTOR * block_noise)), noise


#: A flat-plate image whose spread (max - min) is at most this fraction of its largest value is
#: uniform and refused: the fit places a detector by how its image varies over the field (the
#: flat plate's images vary by 20-40 % over an 80 mm field at d_h 272 mm), and a uniform one (a
#: stuck channel; all pixels 3e38) moved all four detectors 200 mm up with exit 0. Float32
#: rounding of a real image spreads it by far more than 1e-6.
UNIFORM_SPREAD = 1e-6
#: Disc rule of the calibration's model (more nodes than the gradient's: the fit is small).
CALIBRATION_NODES = (2, 6)
#: |correlation| above this: the pair is reported as not separable by the data.
DEGENERATE_CORRELATION = 0.99
PARAMETERS = ("cx", "cy", "cz", "tilt_a", "tilt_b", "gain", "offset")
#: Finite-difference steps of the geometry parameters (mm, mm, mm, deg, deg).
GEOMETRY_STEPS = (0.2, 0.2, 0.2, 0.1, 0.1)
FORMAT = "elo-mitsuba calibration 1"
#: The keys of a CALIB.json (:meth:`Calibration.as_dict`) and of each of its detectors
#: (:meth:`DetectorFit.as_dict`): any other is refused on reading, as the TOML specs do; a
#: misspelt "gian" was dropped without a word and the gain taken as 1.
FILE_KEYS = ("format", "units", "detectors", "source")
DETECTOR_KEYS = ("center", "normal", "radius", "gain", "offset", "sigma", "correlation", "not_separable",
                 "rms_residual_relative", "blocks_rejected", "blocks", "misfit_bound_relative",
                 "pixel_noise_relative")


@dataclass
class DetectorFit:
    """One detector's calibration: the fitted disc, gain, offset and what the fit knows of them."""

    disc: Disc
    gain: float
    offset: float
    sigma: dict
    correlation: dict
    degenerate: list
    rms_residual: float
    #: blocks of the fit grid left out as outliers (dead or hot pixels), of ``blocks``
    rejected: int = 0
    blocks: int = 0
    #: the largest rms misfit a flat plate's image may leave (:func:`misfit_bound`) and the
    #: image's own relative noise per pixel it is based on
    misfit_bound: float = float("nan")
    noise: float = float("nan")

    def as_dict(self) -> dict:
        return {**self.disc.as_dict(), "gain": self.gain, "offset": self.offset, "sigma": self.sigma,
                "correlation": self.correlation, "not_separable": self.degenerate,
                "rms_residual_relative": self.rms_residual, "blocks_rejected": self.rejected,
                "blocks": self.blocks, "misfit_bound_relative": _finite_or_none(self.misfit_bound),
                "pixel_noise_relative": _finite_or_none(self.noise)}


def _finite_or_none(value: float):
    return float(value) if math.isfinite(value) else None


@dataclass
class Calibration:
    """Calibrated detectors of one machine (:func:`calibrate`, :func:`read_calibration`)."""

    detectors: dict
    source: dict

    def discs(self) -> dict:
        return {k: v.disc for k, v in self.detectors.items()}

    def apply(self, geometry: ScanGeometry) -> ScanGeometry:
        """``geometry`` with its detectors replaced by the calibrated ones."""
        missing = [k for k in geometry.detectors if k not in self.detectors]
        if missing:
            raise EloInputError(f"calibration has no detector {', '.join(missing)} "
                                f"(it has {', '.join(self.detectors)})")
        return geometry.with_detectors(self.discs())

    def as_dict(self) -> dict:
        return {"format": FORMAT, "units": "mm; gain in image units per N_d/N_0",
                "detectors": {k: v.as_dict() for k, v in self.detectors.items()}, "source": self.source}


def _tilt_basis(normal):
    n = np.asarray(normal, float)
    a = np.cross(n, [0.0, 0.0, 1.0] if abs(n[2]) < 0.99 else [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    return a, np.cross(n, a)


def _disc_from(x, nominal: Disc) -> Disc:
    """The disc moved by x[:3] (mm) from the nominal centre and tilted by x[3], x[4] (deg) about
    two axes perpendicular to the nominal normal."""
    a, b = _tilt_basis(nominal.normal)
    ta, tb = np.radians(x[3]), np.radians(x[4])
    n = np.asarray(nominal.normal) + np.tan(ta) * a + np.tan(tb) * b
    return Disc(np.asarray(nominal.center) + np.asarray(x[:3]), n, nominal.radius)


def block_mean(image, grid: int) -> tuple[np.ndarray, tuple]:
    """Means of blocks of ``h // grid`` x ``w // grid`` pixels (one pixel below ``grid``), as many as
    fill the image (at least ``grid`` a side, fewer than ``2 grid``; trailing rows/columns that do
    not fill a block are dropped, fewer than a block's), and the (H, W) the blocks cover. Blocks of
    exactly ``grid`` a side left 44 % of a 64^2 image unused.

    Examples
    --------
    >>> means, covered = block_mean(np.ones((64, 100)), 48)
    >>> means.shape, covered
    ((64, 50), (64, 100))
    >>> block_mean(np.ones((1024, 32)), 48)[0].shape
    (48, 32)
    """
    image = np.asarray(image, float)
    h, w = image.shape
    by, bx = max(1, h // grid), max(1, w // grid)
    gy, gx = h // by, w // bx
    cut = image[: gy * by, : gx * bx]
    return cut.reshape(gy, by, gx, bx).mean(axis=(1, 3)), (gy * by, gx * bx)


def calibrate(flats: Mapping, nominal: ScanGeometry, *, fit_offset: bool = False, grid: int = FIT_GRID,
              fit_center: bool = True, fit_tilt: bool = True, max_misfit: float | None = None,
              source=None) -> Calibration:
    """Fit every detector's centre, tilt and gain (and offset) to its flat-plate image.

    Parameters
    ----------
    flats : mapping of str to ndarray (H, W)
        Flat-plate images by detector name (any unit: volts, N_d/N_0, counts).
    nominal : ScanGeometry
        The drawing's geometry: the start of the fit, the radii, the beam and the material.
    fit_offset : bool
        Also fit a constant offset per detector (an amplifier's dark level).
    grid : int
        The fit runs on ``grid`` x ``grid`` block means of each image.
    fit_center, fit_tilt : bool
        Hold the centre / the normal at the nominal value when False.
    max_misfit : float, optional
        The largest rms misfit (relative, e.g. 0.03) a detector's fit may leave; default: per
        detector :func:`misfit_bound` (3 x the noise of its block means, at least 1 %);
        ``math.inf`` accepts any.
    source : str or mapping of str to str, optional
        How the refusal names the images: one name, or a file per detector.

    Returns
    -------
    Calibration

    Raises
    ------
    EloInputError
        A detector's fit misfits its image by more than the bound: the images do not look like a
        flat plate (or are far too noisy); nothing of the fit is returned. Isolated dead or hot
        pixels are left out of the fit instead (:attr:`DetectorFit.rejected`).
    """
    from scipy.optimize import least_squares

    if max_misfit is not None:
        try:
            ok = not isinstance(max_misfit, bool) and float(max_misfit) > 0
        except (TypeError, ValueError, OverflowError):
            ok = False
        if not ok:
            raise EloInputError(f"max_misfit {max_misfit!r}: need a relative misfit > 0 (e.g. 0.03), or None for "
                                "the images' own bound")
    from ..arguments import flag, real_array, shown, whole_number

    grid = whole_number("grid", grid, 2, None)
    fit_offset, fit_center, fit_tilt = (flag(k, v) for k, v in
                                        (("fit_offset", fit_offset), ("fit_center", fit_center), ("fit_tilt", fit_tilt)))
    if not hasattr(nominal, "detectors") or not hasattr(nominal, "field_mm"):
        raise EloInputError(f"nominal={shown(nominal)}: must be a ScanGeometry (the drawing's detectors, beam and field)")
    if not isinstance(flats, Mapping):
        raise EloInputError(f"flats={shown(flats)}: must map each detector's name to its flat-plate image")
    if not nominal.detectors:
        raise EloInputError("the nominal geometry has no detectors: nothing to calibrate")
    names = [n for n in nominal.detectors if n in flats]
    missing = [n for n in nominal.detectors if n not in flats]
    if missing:  # a detector left out would keep the drawing's geometry without a word
        raise EloInputError(f"flat-plate images for {', '.join(nominal.detectors)} are needed; "
                            f"{', '.join(missing)} missing (got {', '.join(map(str, flats)) or 'none'})")
    first = real_array(f"flat-plate image {names[0]!r}", flats[names[0]], ndim=None)
    if first.ndim != 2 or first.shape != tuple(nominal.shape):
        raise EloInputError(f"flat-plate images are {first.shape}, the geometry {nominal.shape}: one scan needed")
    if min(first.shape) < MIN_SIDE:
        raise EloInputError(f"flat-plate images of {first.shape[1]}x{first.shape[0]} px: need at least {MIN_SIDE} "
                            "pixels a side to fit a detector's centre, tilt and gain")
    coarse_shape = None
    data = {}
    for n in names:
        img = real_array(f"flat-plate image {n!r}", flats[n], ndim=None)
        if img.shape != first.shape:
            raise EloInputError(f"flat-plate image {n!r} is {img.shape}, {names[0]!r} {first.shape}")
        if not np.all(np.isfinite(img)):
            raise EloInputError(f"flat-plate image {n!r} holds NaN or Inf; cannot calibrate")
        if np.ptp(img) <= UNIFORM_SPREAD * np.max(np.abs(img)):
            where = source.get(n) if isinstance(source, Mapping) else source
            raise EloInputError(f"{where + ': ' if where else ''}flat-plate image {n!r} holds one value ({float(img.flat[0]):.4g}) at every pixel; a "
                                "flat plate's image varies over the field with the detector's distance and angle, "
                                "which is what places it (a stuck or saturated channel, or a test pattern?)")
        data[n], covered = block_mean(img, grid)
        block_pixels = (covered[0] // data[n].shape[0]) * (covered[1] // data[n].shape[1])
        coarse_shape = data[n].shape
        if not np.median(data[n]) > 0:
            raise EloInputError(f"flat-plate image {n!r} is not positive (median {np.median(data[n]):g}); "
                                "is the detector connected?")
    # the blocks' centres: the coarse grid over the covered part of the field
    fx, fy = nominal.field_mm
    h, w = nominal.shape
    covered_field = (fx * covered[1] / w, fy * covered[0] / h)
    shift = (-(fx - covered_field[0]) / 2, (fy - covered_field[1]) / 2)
    coarse = ScanGeometry(field_mm=covered_field, shape=coarse_shape, detectors=nominal.detectors,
                          work_distance_mm=nominal.work_distance_mm, projection=nominal.projection,
                          aim_offset_mm=(nominal.aim_offset_mm[0] + shift[0], nominal.aim_offset_mm[1] + shift[1]),
                          material=nominal.material)
    pts, dirs = coarse.beam(None)
    free = [fit_center] * 3 + [fit_tilt] * 2 + [True, fit_offset]
    fits = {}
    for name in names:
        nominal_disc = nominal.detectors[name]
        y = data[name].ravel()
        level = float(np.median(y))

        def models(xs, nominal_disc=nominal_disc):
            """Flat-plate signals of the disc moved/tilted by each x[:5], in one kernel."""
            discs = {str(i): _disc_from(x, nominal_disc) for i, x in enumerate(xs)}
            fm = FacetModel(discs, nominal.material, nodes=CALIBRATION_NODES)
            mi = fm.mi
            sig = fm.signals(mi.Point3f(to_vector(mi, pts)), to_vector(mi, dirs), [mi.Vector3f(0.0, 0.0, 1.0)])[0]
            fm.dr.eval(sig)
            return [np.asarray(v, dtype=np.float64) for v in sig]

        # x = centre offset from nominal (mm, 3), tilt (deg, 2), gain, offset
        (s0,) = models([np.zeros(5)])
        x0 = np.r_[np.zeros(5), level / float(np.median(s0)), 0.0]
        idx = np.nonzero(free)[0]

        def full(xf):
            x = x0.copy()
            x[idx] = xf
            return x

        def residual(xf, keep):
            x = full(xf)
            (m,) = models([x[:5]])
            return ((x[5] * m + x[6] - y) / level)[keep]

        def jac(xf, keep):
            # central differences of the geometry, absolute steps well above float32 round-off
            # (the model is float32: a 1e-3 mm step would change the signal by ~1e-6)
            x = full(xf)
            probes = [x[:5]]
            for i in range(5):
                for sign in (1.0, -1.0):
                    xp = x[:5].copy()
                    xp[i] += sign * GEOMETRY_STEPS[i]
                    probes.append(xp)
            sig = models(probes)
            cols = []
            for i in idx:
                if i < 5:
                    cols.append(x[5] * (sig[1 + 2 * i] - sig[2 + 2 * i]) / (2 * GEOMETRY_STEPS[i]) / level)
                elif i == 5:
                    cols.append(sig[0] / level)
                else:
                    cols.append(np.full(sig[0].shape, 1.0 / level))
            return np.stack(cols, axis=1)[keep]

        def solve(keep):
            return least_squares(residual, x0[idx], jac=jac, args=(keep,), method="trf", x_scale="jac",
                                 xtol=1e-8, ftol=1e-10, max_nfev=30)

        # isolated dead/hot pixels: leave out blocks far off a robust spread of the residuals and
        # fit again from the drawing (the first fit may have been pulled far off by them)
        everything = np.ones(y.shape, bool)
        keep = everything
        sol = first = solve(keep)
        for _ in range(OUTLIER_ROUNDS):
            r = residual(sol.x, everything)
            centre = float(np.median(r[keep]))
            spread = max(1.4826 * float(np.median(np.abs(r[keep] - centre))), OUTLIER_FLOOR)
            new_keep = np.abs(r - centre) <= OUTLIER_SIGMA * spread
            if np.count_nonzero(~new_keep) > MAX_OUTLIER_FRACTION * y.size:  # no isolated defect
                keep, sol = everything, first
                break
            if np.array_equal(new_keep, keep):
                break
            keep = new_keep
            sol = solve(keep)
        x = full(sol.x)
        r = sol.fun
        dof = max(len(r) - len(idx), 1)
        s2 = float(np.sum(r * r) / dof)
        J = sol.jac
        try:
            cov = np.linalg.inv(J.T @ J) * s2
            sig = np.sqrt(np.clip(np.diag(cov), 0, None))
            corr = cov / np.outer(sig, sig)
        except np.linalg.LinAlgError:
            sig = np.full(len(idx), np.inf)
            corr = np.full((len(idx), len(idx)), np.nan)
        names_free = [PARAMETERS[i] for i in idx]
        sigma = {k: float(v) for k, v in zip(names_free, sig)}
        correlation = {f"{names_free[i]}~{names_free[j]}": round(float(corr[i, j]), 4)
                       for i in range(len(idx)) for j in range(i + 1, len(idx))}
        degenerate = [k for k, v in correlation.items() if not abs(v) < DEGENERATE_CORRELATION]
        bound, noise = misfit_bound(flats[name], block_pixels)
        if max_misfit is not None:
            bound = float(max_misfit)
        fits[name] = DetectorFit(disc=_disc_from(x, nominal_disc), gain=float(x[5]), offset=float(x[6]),
                                 sigma=sigma, correlation=correlation, degenerate=degenerate,
                                 rms_residual=float(np.sqrt(np.mean(r * r))), rejected=int(np.count_nonzero(~keep)),
                                 blocks=int(y.size), misfit_bound=bound, noise=noise)
    _refuse_misfits(fits, source, max_misfit is not None)
    return Calibration(detectors=fits, source={"nominal": nominal.as_dict(), "grid": list(coarse_shape),
                                               "fit_offset": bool(fit_offset)})


def _refuse_misfits(fits: Mapping, source, given: bool) -> None:
    """One line naming every detector whose fit misfits its image beyond its bound, if any."""
    bad = [(n, f) for n, f in fits.items() if not f.rms_residual <= f.misfit_bound]
    if not bad:
        return
    where = ""
    if isinstance(source, Mapping):
        where = ", ".join(dict.fromkeys(str(source[n]) for n, _ in bad if n in source))
    elif source:
        where = str(source)
    parts = ", ".join(f"{n} {100 * f.rms_residual:.3g} % > {100 * f.misfit_bound:.3g} %" for n, f in bad)
    why = ("the given bound" if given else
           f"bound {MISFIT_NOISE_FACTOR:g} x the noise of the block means from the images' own, at least "
           f"{100 * MISFIT_FLOOR:g} %")
    raise EloInputError(f"{where + ': ' if where else ''}rms misfit of the flat-plate fit: {parts} ({why}; a flat "
                        "plate's images leave about their noise): these images do not look like a flat plate (or are "
                        "too noisy to calibrate; --max-misfit / max_misfit= sets the bound)")


def write_calibration(path, calibration: Calibration, *, overwrite: bool = False) -> Path:
    """Write ``CALIB.json``."""
    path = check_output(path, (".json",), overwrite=overwrite, what="calibration")
    text = json.dumps(calibration.as_dict(), indent=2, allow_nan=False)
    return atomic_write(path, lambda tmp: Path(tmp).write_text(text + "\n"))


def _known_keys(doc, allowed, where: str, what: str) -> None:
    """Refuse a key of ``doc`` not in ``allowed`` (a misspelt one would be ignored), naming ``where``."""
    unknown = [k for k in doc if k not in allowed]
    if unknown:
        raise EloInputError(f"{where} unknown key {unknown[0]!r}; {what} has: {', '.join(allowed)}")


def read_calibration(path) -> Calibration:
    """Read a ``CALIB.json`` of :func:`write_calibration` (or one written by hand with, per
    detector, ``center``, ``normal``, ``radius`` and optionally ``gain``)."""
    path = input_file(path, "calibration file")
    try:
        doc = json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError) as exc:
        raise EloInputError(f"{path}: not a JSON calibration ({str(exc).splitlines()[0]})") from None
    dets = doc.get("detectors") if isinstance(doc, dict) else None
    if not isinstance(dets, dict) or not dets:
        raise EloInputError(f"{path}: no 'detectors' object (per detector: center, normal, radius, gain)")
    _known_keys(doc, FILE_KEYS, f"{path}:", "a calibration file")
    if "format" in doc and doc["format"] != FORMAT:  # a hand-written file may leave it out
        raise EloInputError(f"{path}: format {doc['format']!r}; this version reads {FORMAT!r} (written by "
                            "'elo-mitsuba calibrate')")
    # the models have these four detectors: another one (a fifth, a misspelt name) ended in a KeyError
    # after the images were read
    others = [n for n in dets if n not in DETECTOR_NAMES]
    if others:
        raise EloInputError(f"{path}: detector {others[0]!r} is not one of the scan's detectors "
                            f"{', '.join(DETECTOR_NAMES)}")
    fits = {}
    for name, d in dets.items():
        if not isinstance(d, dict):
            raise EloInputError(f"{path}: detector {name!r} is a JSON {type(d).__name__}; need an object with center, "
                                "normal, radius")
        _known_keys(d, DETECTOR_KEYS, f"{path}: detector {name!r}:", "a detector")
        missing = [k for k in ("center", "normal", "radius") if k not in d]
        if missing:
            raise EloInputError(f"{path}: detector {name!r} lacks {', '.join(missing)} (need center, normal, radius)")
        try:
            disc = Disc(d["center"], d["normal"], d["radius"])
        except EloInputError as exc:  # (an EloInputError is a ValueError too: caught first)
            raise EloInputError(f"{path}: detector {name!r}: {exc}") from None
        except (TypeError, ValueError, OverflowError):  # text where numbers belong
            raise EloInputError(f"{path}: detector {name!r}: center {d['center']!r}, normal {d['normal']!r}, radius "
                                f"{d['radius']!r}; need 3 numbers, 3 numbers and a number of mm > 0") from None
        check_detector_placement(name, disc.center, disc.normal, disc.radius, where=str(path))
        numbers = {}
        for key, default in (("gain", 1.0), ("offset", 0.0), ("rms_residual_relative", float("nan"))):
            try:
                numbers[key] = float(d.get(key, default))
            except (TypeError, ValueError, OverflowError):
                raise EloInputError(f"{path}: detector {name!r}: {key} {d[key]!r} is not a number") from None
        if not (math.isfinite(numbers["gain"]) and numbers["gain"] != 0 and math.isfinite(numbers["offset"])):
            raise EloInputError(f"{path}: detector {name!r}: gain {numbers['gain']!r}, offset {numbers['offset']!r}; "
                                "need a finite gain other than 0 and a finite offset")
        for key, kind in (("sigma", dict), ("correlation", dict), ("not_separable", list)):
            if not isinstance(d.get(key, kind()), kind):
                raise EloInputError(f"{path}: detector {name!r}: {key} {d[key]!r} is not a JSON "
                                    f"{'object' if kind is dict else 'list'}")
        fits[name] = DetectorFit(disc=disc, gain=numbers["gain"], offset=numbers["offset"],
                                 sigma=dict(d.get("sigma", {})), correlation=dict(d.get("correlation", {})),
                                 degenerate=list(d.get("not_separable", [])),
                                 rms_residual=numbers["rms_residual_relative"])
    if not isinstance(doc.get("source", {}), dict):
        raise EloInputError(f"{path}: 'source' {doc['source']!r} is not a JSON object")
    return Calibration(detectors=fits, source=dict(doc.get("source", {})))
