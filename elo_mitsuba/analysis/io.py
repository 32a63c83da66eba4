"""The analysis file formats: detector image sets in, gradient EXR and height maps out.

* :func:`read_image`, :func:`read_detector_exr`, :func:`load_detector_set`: the four detector
  images of one scan, from a forward-model EXR (with its geometry header) or from four
  single-channel files (EXR, TIFF, NPY) of a machine.
* :func:`write_gradient` / :func:`read_gradient`: the gradient EXR (channels
  :data:`GRADIENT_CHANNELS`, the scan geometry in the header) that ``elo-mitsuba gradient`` writes
  and ``elo-mitsuba reconstruct`` reads; the contract between the two, also for Python users.
* :func:`write_inversion`: an inversion's heights and what it knows of them (height map files
  alone: :func:`elo_mitsuba.heightmap.write_height`).

Arrays keep the package orientation (:mod:`elo_mitsuba.grid`). Recorded machine images must be
stored the same way; nothing here flips anything.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np

from ..constants import DETECTOR_NAMES
from ..errors import EloInputError
from ..exr import read_exr, write_exr
from ..files import check_output
from ..grid import field_xy
from ..schema import error_channels, event_channel, grid_header
from ..heightmap import HEIGHT_SUFFIXES, write_height
from .stsa import SPIKE, spike_bound

IMAGE_SUFFIXES = (".exr", ".tif", ".tiff", ".npy")
#: Channels of the gradient EXR, in the order written: the Eq. 26 gradient, the normalised
#: differences of Eq. 15, the sums of opposite detectors, the mask (1 = untrusted) and its reasons.
GRADIENT_CHANNELS = ("dzdx", "dzdy", "Mx", "My", "sum_rl", "sum_bf", "mask", "mask_reason")
#: Added by the model method: RMS misfit of the four corrected images, the one-sigma uncertainty
#: of dZ/dx and dZ/dy, and the common scale of the fit.
MODEL_CHANNELS = ("residual", "dzdx_sigma", "dzdy_sigma", "scale")
#: What the header's "quantity" says per method.
METHOD_QUANTITY = {
    "eq26": "surface gradient (Renner et al. 2023, Eq. 26)",
    "model": "surface gradient (per-pixel fit of the 1st-event model: full g_BSE of Eq. 13, disc detectors)",
}


def read_image(path, channel: str | None = None) -> tuple[np.ndarray, dict]:
    """One 2-D image (float64) and the EXR metadata (empty for TIFF/NPY).

    An EXR must hold exactly one channel unless ``channel`` names one; a TIFF/NPY must be 2-D
    (singleton dimensions are dropped).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in IMAGE_SUFFIXES:
        raise EloInputError(f"{path}: unsupported image type {suffix or '(none)'}; use {', '.join(IMAGE_SUFFIXES)}")
    if not path.is_file():
        raise EloInputError(f"{path}: no such file")
    meta: dict = {}
    if suffix == ".exr":
        channels, meta = read_exr(path)
        if channel is None:
            if len(channels) != 1:
                raise EloInputError(f"{path}: holds channels {', '.join(sorted(channels))}; expected exactly one")
            arr = next(iter(channels.values()))
        elif channel in channels:
            arr = channels[channel]
        else:
            raise EloInputError(f"{path}: no channel {channel!r}; it has {', '.join(sorted(channels))}")
    elif suffix == ".npy":
        with open(path, "rb") as f:
            magic = f.read(6)
        if magic != b"\x93NUMPY":
            raise EloInputError(f"{path}: not a readable .npy array ({'an empty file' if not magic else 'no NumPy header'})")
        try:
            arr = np.load(path, allow_pickle=False)
        except Exception as exc:  # numpy raises ValueError/OSError with long messages
            raise EloInputError(f"{path}: not a readable .npy array ({str(exc).splitlines()[0]})") from None
    else:
        import tifffile

        try:
            arr = tifffile.imread(path)
        except Exception as exc:
            raise EloInputError(f"{path}: not a readable TIFF ({str(exc).splitlines()[0]})") from None
    arr = np.squeeze(np.asarray(arr))
    # real numbers only: complex would lose its imaginary part (with a warning), bool is a mask,
    # not a signal, and datetime/timedelta/object/string arrays hold no intensities
    if arr.ndim != 2 or arr.dtype.kind not in "iuf":
        raise EloInputError(f"{path}: expected one 2-D numeric image of real values (integer or floating point), "
                            f"got shape {arr.shape} ({arr.dtype})")
    return arr.astype(float), meta


def read_detector_exr(path, event: int | None = None) -> tuple[dict[str, np.ndarray], dict]:
    """The four detector images of a forward-model EXR (channels ``right`` ... or ``right.e<K>``)."""
    channels, meta = read_exr(path)
    names = {n: n if event is None else event_channel(n, event) for n in DETECTOR_NAMES}
    missing = [c for c in names.values() if c not in channels]
    if missing:
        raise EloInputError(
            f"{path}: missing channel(s) {', '.join(missing)}; it has {', '.join(sorted(channels)) or 'none'}"
        )
    return {n: channels[c].astype(float) for n, c in names.items()}, meta


def load_detector_set(exr_path=None, files: Mapping | None = None, what: str = "images",
                      event: int | None = None) -> tuple[dict[str, np.ndarray] | None, dict]:
    """The four detector images of one scan, from one EXR or from four single-channel files.

    Parameters
    ----------
    exr_path : path, optional
        A forward-model EXR with channels ``right`` ... (or ``right.e<event>``).
    files : mapping, optional
        ``{detector: path}`` of single-channel images; all four are needed.
    what : str
        How messages name the set ("object images", "flat-plate images").
    event : int, optional
        Read the per-event channels of this scattering event.

    Returns
    -------
    images : dict or None
        ``{detector: float64 image}``; None if neither an EXR nor files were given.
    metadata : dict
        The EXR header (empty for TIFF/NPY).
    """
    given = {n: f for n, f in (files or {}).items() if f}
    if exr_path and given:
        raise EloInputError(f"{what}: give either one EXR or the four single files, not both")
    if exr_path:
        images, meta = read_detector_exr(exr_path, event)
        check_detector_images(images, {n: f"{exr_path} channel {n!r}" for n in images})
        return images, meta
    if not given:
        return None, {}
    missing = [n for n in DETECTOR_NAMES if n not in given]
    if missing:
        raise EloInputError(f"{what}: missing {', '.join(missing)} image(s); all four detectors are needed")
    images, meta = {}, {}
    for n, f in given.items():
        images[n], m = read_image(f)
        meta = meta or m
    shapes = {n: img.shape for n, img in images.items()}
    if len(set(shapes.values())) != 1:
        raise EloInputError(f"{what}: the four images differ in shape ({', '.join(f'{n} {s}' for n, s in shapes.items())})")
    check_detector_images(images, {n: str(given[n]) for n in images})
    return images, meta


def read_later_events(path, shape) -> tuple[dict, dict]:
    """Events >= 2 per detector of a forward render with per-event channels (``--events >= 2``),
    e.g. the flat plate in the chamber: (later events in the render's units N_d/N_0, their share
    of each pixel's total)."""
    total, meta = read_detector_exr(path)
    if int(meta.get("events", 1)) < 2:  # before its per-event channels are looked for
        raise EloInputError(f"{path}: rendered with events={meta.get('events', 1)}; later events need --events >= 2")
    first, _ = read_detector_exr(path, 1)
    if next(iter(total.values())).shape != tuple(shape):
        raise EloInputError(f"{path}: {next(iter(total.values())).shape} px, the images {tuple(shape)}")
    later, share = {}, {}
    for n in DETECTOR_NAMES:
        t = np.asarray(total[n], float)
        later[n] = t - np.asarray(first[n], float)
        share[n] = np.where(t > 0, later[n] / np.where(t > 0, t, 1.0), 0.0)
    return later, share


def read_later_errors(path) -> dict | None:
    """Standard errors of the events >= 2 per detector of a render written with
    ``--error-channels`` (channels ``<id>.e<k>.err``, k >= 2,
    :func:`~elo_mitsuba.error_estimate.later_events_error`), or None when it has none."""
    from ..error_estimate import later_events_error

    channels, meta = read_exr(path)
    return later_events_error(error_channels(channels), DETECTOR_NAMES, int(meta.get("events", 1)))


def check_detector_images(images: Mapping[str, np.ndarray], names: Mapping[str, str]) -> None:
    """Refuse detector images no gradient can come from, naming the file and what is wrong.

    A detector image is a collected signal (count, current or voltage): finite, of one sign, not
    zero everywhere and without pixels :data:`~.stsa.SPIKE` times its median. NaN/Inf, values of both
    signs (an offset not subtracted), an all-zero image (a detector not connected, a wrong
    channel) and saturated or glitched pixels would otherwise end as a masked gradient without a
    reason or as error bars of 1e16 um. An image <= 0 throughout (an inverting amplifier) is
    accepted here: the STSA division by a flat of the same sign cancels it (:func:`check_signs`).
    """
    for n, img in images.items():
        finite = np.isfinite(img)
        if not finite.all():
            raise EloInputError(f"{names[n]}: {int((~finite).sum())} of {img.size} pixels are NaN or Inf; "
                                "detector images must be finite")
        if not img.any():
            raise EloInputError(f"{names[n]}: all {img.size} pixels are 0; the {n} detector recorded nothing "
                                "(not connected, or the wrong channel/file)")
        low, high = float(img.min()), float(img.max())
        if low < 0 < high:
            raise EloInputError(f"{names[n]}: {int((img < 0).sum())} pixels are negative (min {low:.4g}) and "
                                f"others positive (max {high:.4g}); a detector signal has one sign: subtract a "
                                "dark offset only down to 0")
        mag = np.abs(img)
        bound = spike_bound(img)
        spikes = mag > bound
        if spikes.any():
            row, col = np.unravel_index(int(np.argmax(mag)), mag.shape)
            raise EloInputError(f"{names[n]}: {int(spikes.sum())} pixel(s) above {SPIKE:g} x the image's median "
                                f"{bound / SPIKE:.4g} (the largest {float(mag[row, col]):.4g} at row {row}, column {col}): "
                                "no surface scatters that contrast, a saturated or glitched pixel; replace it "
                                "(e.g. by its neighbours' median)")


def check_signs(images: Mapping[str, np.ndarray], flats: Mapping[str, np.ndarray] | None, names: Mapping[str, str]):
    """Negative detector images only with a flat-plate image of the same sign (the ratio is > 0).

    Without a flat the images are taken as already STSA-corrected ratios, which are >= 0.
    """
    for n, img in images.items():
        negative = float(img.min()) < 0
        if flats is None and negative:
            raise EloInputError(f"{names[n]}: {int((img < 0).sum())} pixels are negative (min {float(img.min()):.4g}); "
                                "STSA-corrected images (--no-flat) are ratios >= 0")
        if flats is not None and negative != (float(flats[n].min()) < 0):
            raise EloInputError(f"{names[n]}: the {n} image and its flat-plate image have opposite signs; "
                                "record both through the same amplifier")


def write_gradient(path, result, field_mm, d_h, d_w, *, thresholds: Mapping, stsa_corrected: bool,
                   event: int | None = None, sources=None, header: Mapping | None = None,
                   overwrite: bool = False, method: str = "eq26", model_geometry=None,
                   calibration=None) -> Path:
    """Write a :class:`~elo_mitsuba.analysis.GradientResult` as the gradient EXR.

    The header records the method, the geometry (``field_mm``, ``resolution``, ``d_h_mm``,
    ``d_w_mm``; for the model method the whole scan geometry it inverted), the mask thresholds,
    whether the images were STSA-corrected, the event, the input files, and from the forward
    model's ``header`` (if any) material, events, spp, work distance, projection and detectors.
    A :class:`~elo_mitsuba.analysis.model_gradient.ModelGradientResult` adds
    :data:`MODEL_CHANNELS` and the noise level.
    """
    from .gradient import MASK_BITS

    path = check_output(path, (".exr",), overwrite=overwrite)
    h, w = result.dzdx.shape
    if method not in METHOD_QUANTITY:
        raise EloInputError(f"gradient method {method!r}: choose {' or '.join(METHOD_QUANTITY)}")
    meta = {
        "quantity": METHOD_QUANTITY[method],
        "method": method,
        **grid_header(field_mm, (h, w)),
        "d_h_mm": d_h,
        "d_w_mm": d_w,
        "units": "mm/mm",
        "mask": "1 = untrusted pixel (gradient set to 0 there), 0 = trusted",
        "mask_reason_bits": MASK_BITS,
        "thresholds": dict(thresholds),
        "stsa_corrected": bool(stsa_corrected),
        "event": event,
        "sources": sources,
    }
    for key in ("material", "events", "spp", "work_distance_mm", "projection", "detectors"):
        if key in (header or {}):
            meta[key] = header[key]
    channels = {"dzdx": result.dzdx, "dzdy": result.dzdy, "Mx": result.mx, "My": result.my,
                "sum_rl": result.sum_x, "sum_bf": result.sum_y,
                "mask": result.mask.astype(np.float32), "mask_reason": result.reasons.astype(np.float32)}
    if getattr(result, "residual", None) is not None:
        channels.update({"residual": result.residual, "dzdx_sigma": result.dzdx_sigma,
                         "dzdy_sigma": result.dzdy_sigma, "scale": result.scale})
        meta["noise"] = result.noise if np.isfinite(result.noise) else None
        meta["iterations"] = result.iterations
        meta["height_passes"] = int(getattr(result, "height_passes", 1))
        meta["model_assumes"] = ("each pixel sees one flat facet (no shadowing by neighbours), a single-ray beam, "
                                 "the 1st event only")
    if model_geometry is not None:
        meta["model_geometry"] = model_geometry.as_dict()
        # reconstruct needs the beam of recorded images too (no forward-model header)
        meta.setdefault("work_distance_mm", model_geometry.work_distance_mm)
        meta.setdefault("projection", model_geometry.projection)
    if calibration is not None:
        meta["calibration"] = str(calibration)
    return write_exr(path, channels, meta, overwrite=overwrite)


def read_gradient(path, field_mm=None, use_mask: bool = True) -> dict:
    """Read a gradient EXR (:func:`write_gradient`, or any EXR with ``dzdx`` and ``dzdy``).

    Returns
    -------
    dict
        ``dzdx``, ``dzdy`` (float32 images, 0 where the file holds NaN), ``mask`` (bool, True =
        untrusted: the file's mask unless ``use_mask`` is False, and its NaN pixels; None if
        neither), ``field_mm`` (``field_mm`` if given, else the
        header's) and ``metadata`` (the header).

    Raises
    ------
    EloInputError
        Missing dzdx/dzdy, infinite gradients, a field that contradicts the header's or is missing,
        and (unless ``use_mask`` is False) a mask channel with values other than 0 and 1: no
        threshold is guessed for a mask of another tool.
    """
    channels, meta = read_exr(path)
    missing = [c for c in ("dzdx", "dzdy") if c not in channels]
    if missing:
        raise EloInputError(f"{path}: missing channel(s) {', '.join(missing)}; "
                            "expected the output of 'elo-mitsuba gradient'")
    for name in ("dzdx", "dzdy"):
        bad = np.isinf(channels[name])
        if bad.any():
            row, col = np.argwhere(bad)[0]
            raise EloInputError(f"{path}: channel {name!r} holds {int(bad.sum())} infinite value(s) (first at row "
                                f"{row}, column {col}); a gradient must be finite (NaN or 0 with mask 1 where unknown)")
    # NaN is another tool's 'unknown' ('gradient' writes 0 with mask 1): masked, and 0 where it was,
    # so that no NaN reaches an integration (it spread over the whole height map)
    unknown = np.isnan(channels["dzdx"]) | np.isnan(channels["dzdy"])
    shape = channels["dzdx"].shape
    recorded = None
    if meta.get("field_mm") is not None:
        try:
            recorded = field_xy(meta["field_mm"], shape)
        except (TypeError, ValueError, EloInputError):
            raise EloInputError(f"{path}: header field_mm {meta['field_mm']!r} is not one or two lengths in mm") from None
    if field_mm is not None and recorded is not None:
        given = field_xy(field_mm, shape)
        if not np.allclose(given, recorded, rtol=1e-6, atol=0):
            raise EloInputError(f"{path}: field {given[0]:g}x{given[1]:g} mm contradicts the header's field_mm "
                                f"{recorded[0]:g}x{recorded[1]:g} mm (the gradient's own scan field); leave it out")
    field = field_mm if field_mm is not None else recorded
    if field is None:
        raise EloInputError(f"{path}: no 'field_mm' in the header; pass --field FX[,FY] (mm)")
    mask = None
    if "mask" in channels and use_mask:
        m = channels["mask"]
        odd = ~((m == 0) | (m == 1))
        if odd.any():
            row, col = np.argwhere(odd)[0]
            raise EloInputError(f"{path}: channel 'mask' holds {int(odd.sum())} value(s) other than 0 and 1 (first "
                                f"{float(m[row, col]):g} at row {row}, column {col}); a mask is 1 = untrusted, "
                                "0 = trusted")
        mask = m == 1
    if unknown.any():
        mask = unknown if mask is None else mask | unknown
        channels = {**channels, **{c: np.where(unknown, np.float32(0), channels[c]) for c in ("dzdx", "dzdy")}}
    return {"dzdx": channels["dzdx"], "dzdy": channels["dzdy"], "mask": mask,
            "field_mm": field_xy(field, channels["dzdx"].shape),
            "metadata": meta}


#: Channels of an inversion EXR besides the predicted images (``model.<detector>``).
INVERSION_CHANNELS = ("height", "mask", "misfit", "start_height", "scale")


def write_inversion(path, result, geometry, *, untrusted, metadata: Mapping | None = None,
                    overwrite: bool = False) -> Path:
    """Write an :class:`~.height_solver.InversionResult`: ``.exr`` with channels height (mm), mask
    (1 = untrusted: the model does not reproduce the pixel's images), misfit, start_height, scale,
    height_error (mm, the standard error of each height, when computed: noise, misfit, regulariser
    bias, the model's slope gain, a floating part's offset), height_error_noise (its noise part),
    height_error_model (the model's systematic part), floating (1 = a part whose
    offset to the field no trusted pixel measures) and ``model.<detector>`` (the modelled corrected
    images), the scan geometry, the solver's history, the local refinement's regions, the floating parts' step search and
    ``height_error_rms_mm`` in the header; ``.npy`` / ``.tif`` the height alone (as
    :func:`write_height`)."""
    path = check_output(path, HEIGHT_SUFFIXES, overwrite=overwrite)
    meta = {**dict(metadata or {}), **geometry.as_dict()}
    if result.height_error is not None:
        meta["height_error_rms_mm"] = result.height_error_rms
    if result.regions:
        meta["regions"] = [r.as_dict() for r in result.regions]
    if result.steps:
        meta["steps"] = [p.as_dict() for p in result.steps]
    if path.suffix.lower() != ".exr":
        return write_height(path, result.height, untrusted, meta, overwrite=overwrite)
    channels = {"height": result.height, "mask": np.asarray(untrusted, np.float32), "misfit": result.misfit,
                "start_height": result.start_height, "scale": result.scale}
    if result.height_error is not None:
        channels["height_error"] = result.height_error
    if result.height_error_noise is not None:
        channels["height_error_noise"] = result.height_error_noise
    if result.height_error_model is not None:
        channels["height_error_model"] = result.height_error_model
    if result.floating is not None:
        channels["floating"] = np.asarray(result.floating, np.float32)
    channels.update({f"model.{n}": v for n, v in result.predicted.items()})
    return write_exr(path, channels, meta, overwrite=overwrite)
