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

from ..arguments import input_file
from ..constants import DETECTOR_NAMES
from ..errors import EloInputError
from ..exr import read_exr, write_exr
from ..files import check_output
from ..grid import field_xy
from ..schema import error_channels, event_channel, grid_header
from ..heightmap import HEIGHT_SUFFIXES, quiet_tifffile, write_height
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
    input_file(path)
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
            with quiet_tifffile():
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


def check_distinct_detectors(files: Mapping | None, what: str = "images") -> None:
    """Refuse one file given for two detectors (``{detector: path}``): its images are equal, and
    the differences of opposite detectors made a gradient of noise with exit status 0.

    Examples
    --------
    >>> check_distinct_detectors({"right": "r.npy", "left": "./r.npy"}, "object images")
    Traceback (most recent call last):
    ...
    elo_mitsuba.errors.EloInputError: ./r.npy: given for both the right and the left detector (object images); ...
    """
    seen: dict = {}
    for n, f in (files or {}).items():
        if not f:
            continue
        other = seen.setdefault(Path(f).resolve(), n)
        if other != n:
            raise EloInputError(f"{f}: given for both the {other} and the {n} detector ({what}); each detector has "
                                "its own image")


def check_distinct_scan_files(files: Mapping | None, flat_files: Mapping | None = None) -> None:
    """:func:`check_distinct_detectors` on a scan's single-channel object files ``{detector: path}``
    and on each set of its flat-plate files ``{detector: [path, ...]}`` (the i-th of each)."""
    check_distinct_detectors(files, "object images")
    lists = {n: list(v or []) for n, v in (flat_files or {}).items()}
    for i in range(max((len(v) for v in lists.values()), default=0)):
        check_distinct_detectors({n: v[i] for n, v in lists.items() if i < len(v)}, "flat-plate images")


def check_repeated_recordings(flat=(), flat_files: Mapping | None = None, what: str = "--flat") -> None:
    """Refuse a flat-plate recording given twice (the same file twice in ``flat``, or in one
    detector's list of ``flat_files``): their mean is the one recording, whose noise the summary
    and the uncertainties would take as halved.

    Examples
    --------
    >>> check_repeated_recordings(["a.exr", "b.exr"])
    >>> check_repeated_recordings(["a.exr", "./a.exr"])
    Traceback (most recent call last):
    ...
    elo_mitsuba.errors.EloInputError: --flat ./a.exr: the same file as --flat a.exr; ...
    """
    lists = [(what, list(flat or []))] + [(f"--flat-{n}", list(v or [])) for n, v in (flat_files or {}).items()]
    for flag, paths in lists:
        seen: dict = {}
        for i, p in enumerate(paths):
            first = seen.setdefault(Path(p).resolve(), i)
            if first != i:
                raise EloInputError(f"{flag} {p}: the same file as {flag} {paths[first]}; a mean of a recording with itself "
                                    "is one recording (its noise not lowered): give each recording once")


def read_later_events(path, shape) -> tuple[dict, dict]:
    """Events >= 2 per detector of a forward render with per-event channels (``--events >= 2``),
    e.g. the flat plate in the chamber: (later events in the render's units N_d/N_0, their share
    of each pixel's total)."""
    total, meta = read_detector_exr(path)
    if int(meta.get("events", 1)) < 2:  # before its per-event channels are looked for
        raise EloInputError(f"{path}: rendered with events={meta.get('events', 1)}; later events need --events >= 2")
    first, _ = read_detector_exr(path, 1)
    got = next(iter(total.values())).shape
    if got != tuple(shape):
        raise EloInputError(f"{path}: the second-event render is {got[1]}x{got[0]} px, the images {shape[1]}x{shape[0]} "
                            "px; render the flat plate's later events at the images' resolution")
    later, share = {}, {}
    for n in DETECTOR_NAMES:
        t = np.asarray(total[n], float)
        later[n] = t - np.asarray(first[n], float)
        share[n] = np.where(t > 0, later[n] / np.where(t > 0, t, 1.0), 0.0)
    return later, share


def check_field(field_mm, meta: Mapping | None, shape, source, *, given: str = "--field",
                fix: str = "leave it out") -> None:
    """Refuse a scan field that contradicts the one a header records (``field_mm``): the images
    (or a gradient) were recorded over the header's field, and slopes and the model's beam taken
    over another are wrong without a word (--field 40 on 80 mm images: 13x the noise). Nothing to
    compare without either.

    Examples
    --------
    >>> check_field((80.0, 80.0), {"field_mm": [80, 80]}, (4, 4), "a.exr")
    >>> check_field((40.0, 40.0), {"field_mm": [80, 80]}, (4, 4), "a.exr")
    Traceback (most recent call last):
    ...
    elo_mitsuba.errors.EloInputError: a.exr: --field 40x40 mm contradicts the header's field_mm 80x80 mm ...
    """
    from ..schema import FIELD

    recorded = (meta or {}).get(FIELD)
    if field_mm is None or recorded is None:
        return
    try:
        recorded = field_xy(recorded, shape)
    except (TypeError, ValueError, EloInputError):
        raise EloInputError(f"{source}: header field_mm {recorded!r} is not one or two lengths in mm") from None
    field = field_xy(field_mm, shape)
    if not np.allclose(field, recorded, rtol=1e-6, atol=0):
        raise EloInputError(f"{source}: {given} {field[0]:g}x{field[1]:g} mm contradicts the header's field_mm "
                            f"{recorded[0]:g}x{recorded[1]:g} mm (the scan field it was recorded over); {fix}")


def check_second_event(path, meta: Mapping | None, source, shape, *, field_mm=None, d_h=None, d_w=None) -> None:
    """Refuse a ``--second-event`` render of another set-up than the images: its header's field,
    work distance and projection must be the images' (``meta``, or ``field_mm`` given for images
    without a header) and each detector centre within that detector's radius of the images'
    (or of the layout ``d_h``, ``d_w``): a calibration's few mm pass, another layout does not.
    A render at field 40 mm taken out of 80 mm images raised the gradient's noise 100-fold and
    gave the calibration tilts of 9 degrees, all with exit status 0.
    """
    from ..constants import DETECTOR_DIRECTIONS
    from ..schema import DETECTORS, FIELD, PROJECTION, WORK_DISTANCE

    _, later = read_exr(path)
    meta = dict(meta or {})
    fix = "render the flat plate's later events with the images' geometry"
    if field_mm is not None:  # images without a header: their field is the one given
        check_field(field_mm, later, shape, path, fix=fix)
    else:
        check_field(meta.get(FIELD), later, shape, path, given=f"the images' ({source}) field", fix=fix)
    for key in (WORK_DISTANCE, PROJECTION):
        a, b = meta.get(key), later.get(key)
        if a is not None and b is not None and (a != b if isinstance(a, str) or isinstance(b, str)
                                                else not np.isclose(float(a), float(b), rtol=1e-6, atol=0)):
            raise EloInputError(f"{path}: the second-event render's {key} {b!r} differs from {source}'s {a!r}; {fix}")
    ours = meta.get(DETECTORS) if isinstance(meta.get(DETECTORS), Mapping) else None
    if ours is None and d_h is not None and d_w is not None:
        ours = {n: {"center": [d_w * ex, d_w * ey, d_h], "radius": None} for n, (ex, ey) in DETECTOR_DIRECTIONS.items()}
        source = "--dh/--dw"
    theirs = later.get(DETECTORS)
    if not isinstance(ours, Mapping) or not isinstance(theirs, Mapping):
        return
    for n in DETECTOR_NAMES:
        a, b = ours.get(n), theirs.get(n)
        if not (isinstance(a, Mapping) and isinstance(b, Mapping)):
            continue
        try:
            gap = float(np.linalg.norm(np.subtract(np.asarray(a["center"], float), np.asarray(b["center"], float))))
            radius = float(a.get("radius") or b["radius"])
        except (KeyError, TypeError, ValueError):
            continue  # a header's own defects are named where it is read
        if not gap <= radius:
            raise EloInputError(f"{path}: the second-event render's {n} detector at "
                                f"{np.round(np.asarray(b['center'], float), 2).tolist()} mm is {gap:.3g} mm from "
                                f"{source}'s {np.round(np.asarray(a['center'], float), 2).tolist()} (allowed: within its "
                                f"radius, {radius:g} mm); {fix}")


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


#: The largest ratio, either way, of a detector image's median to its flat-plate image's
#: (:func:`check_levels`). An object and its flat plate recorded with one amplifier setting and
#: unit give corrected images of about 0.1-10 (shadowed or bright facets); a factor 1000 is a
#: unit (V against mV, counts against N_d/N_0) or a gain setting. Images of 3e38 against a flat of
#: 0.0015 overflowed the float32 model (NaN refused only when the output was written) and a flat of
#: 3e38 masked every pixel of a valid object (exit 0).
MAX_LEVEL_RATIO = 1e3


def check_levels(images: Mapping[str, np.ndarray], flats: Mapping[str, np.ndarray], names: Mapping[str, str]):
    """Refuse an object image whose level is more than :data:`MAX_LEVEL_RATIO` times its flat-plate
    image's, or less than its inverse (medians of the magnitudes), naming the file and both levels.

    Examples
    --------
    >>> flat = {"right": np.full((4, 4), 0.0015)}
    >>> check_levels({"right": np.full((4, 4), 0.001)}, flat, {"right": "obj.exr"})
    >>> check_levels({"right": np.full((4, 4), 3e38)}, flat, {"right": "obj.exr"})
    Traceback (most recent call last):
    ...
    elo_mitsuba.errors.EloInputError: obj.exr: the right image's median 3e+38 is 2e+41 x its flat-plate image's 0.0015; ...
    """
    for n, img in images.items():
        level, flat_level = float(np.median(np.abs(img))), float(np.median(np.abs(flats[n])))
        ratio = level / flat_level if flat_level > 0 else np.inf
        if not 1.0 / MAX_LEVEL_RATIO <= ratio <= MAX_LEVEL_RATIO:
            raise EloInputError(f"{names[n]}: the {n} image's median {level:.4g} is {ratio:.3g} x its flat-plate "
                                f"image's {flat_level:.4g}; "
                                f"allowed 1/{MAX_LEVEL_RATIO:g} to {MAX_LEVEL_RATIO:g} x: record the object and the flat "
                                "plate with one amplifier setting and in one unit")


def check_signs(images: Mapping[str, np.ndarray], flats: Mapping[str, np.ndarray] | None, names: Mapping[str, str]):
    """Negative detector images only with a flat-plate image of the same sign (the ratio is > 0),
    and the object's level within :data:`MAX_LEVEL_RATIO` of the flat's (:func:`check_levels`).

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
    if flats is not None:
        check_levels(images, flats, names)


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
        and (unless ``use_mask`` is False) a mask channel with values other than 0 and 1 (no
        threshold is guessed for a mask of another tool) or NaN at a pixel the mask calls trusted.
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
    check_field(field_mm, meta, shape, path)
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
        # a pixel the mask calls trusted holds a gradient: NaN there is a defect like Inf, not
        # another tool's "unknown" (which comes without a mask, or with mask 1)
        trusted_nan = unknown & ~mask
        if trusted_nan.any():
            row, col = np.argwhere(trusted_nan)[0]
            raise EloInputError(f"{path}: {int(trusted_nan.sum())} pixel(s) hold NaN in dzdx or dzdy where the mask "
                                f"says trusted (first at row {row}, column {col}); a trusted pixel needs a finite "
                                "gradient (mark unknown pixels 1 in the mask, or --ignore-mask)")
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
