"""From four detector images to gradients and heights: the one pipeline of the commands and the API.

A :class:`Scan` holds one scan's object and flat-plate images with the geometry their headers
record (or the caller gives, for recorded machine images); :func:`read_scan` reads and checks
it. :func:`model_geometry` is the scan geometry the model inverts (the header's disc detectors,
or the nominal layout of Eq. 17, optionally moved by a calibration); :func:`gradient` turns a scan
into a surface gradient (model fit or Eq. 26) and :func:`invert` into heights (the forward model
inverted). ``elo-mitsuba gradient``, ``invert`` and ``calibrate`` parse their flags, call these and
print; a Python user calls the same functions with keywords.

Lengths are in mm; images keep the orientation of :mod:`elo_mitsuba.grid`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np

from ..constants import DETECTOR_DIAMETER_MM, DETECTOR_NAMES, WORK_DISTANCE_MM
from ..errors import EloInputError

__all__ = ["FlatRecording", "Scan", "calibration_start", "check_gradient_settings", "flat_recordings", "gradient", "invert", "model_geometry",
           "nominal_geometry", "read_calibration_flats", "read_scan", "read_start"]


@dataclass
class FlatRecording:
    """One recording of the flat plate: how messages name it, its files, images and header."""

    label: str
    files: str | dict
    images: dict
    header: dict


@dataclass
class Scan:
    """One scan's images and geometry as :func:`read_scan` found them.

    Attributes
    ----------
    images : dict of str to ndarray
        The object's detector images by name (any unit: N_d/N_0, V, counts).
    flats : dict of str to ndarray or None
        The flat plate's (the mean of its recordings); None: the images are already corrected.
    header : dict
        The geometry header (the object's, else the first flat's; empty for machine images).
    source : str
        How messages name the header's file.
    shape : (int, int)
        Image shape (H, W).
    geo : dict
        ``field_mm`` (fx, fy), ``d_h``, ``d_w`` (mm, the Eq. 17 layout) and ``resolution``.
    flat_files : list
        Each flat recording's file (an EXR path, or ``{detector: path}``).
    object_files : str or dict
        The object's EXR, or ``{detector: path}``, as output headers record it.
    """

    images: dict
    flats: dict | None
    header: dict
    source: str
    shape: tuple
    geo: dict
    flat_files: list = field(default_factory=list)
    object_files: str | dict | None = None

    @property
    def flat_count(self) -> int:
        return len(self.flat_files)

    def flat_provenance(self):
        """The flat plate's files as the output headers record them: one entry, or one per recording."""
        return self.flat_files[0] if len(self.flat_files) == 1 else list(self.flat_files)

    def flat_note(self) -> str:
        """What the summary line says of several flat recordings."""
        return f"; flat plate: the mean of {self.flat_count} recordings" if self.flat_count > 1 else ""

    def noise_shares(self) -> tuple[dict, str]:
        """The object's and the flat's relative noise and the summary line
        (:func:`~.noise.noise_shares`)."""
        from .noise import noise_shares

        return noise_shares(self.images, self.flats, self.flat_count)

    def beam_fwhm(self, fwhm_mm: float | None = None) -> float:
        """The beam profile's FWHM (mm): ``fwhm_mm`` if given, else the header's, else 0."""
        from ..schema import BEAM_FWHM

        return fwhm_mm if fwhm_mm is not None else float((self.header or {}).get(BEAM_FWHM, 0.0))


def flat_recordings(flat: Sequence = (), flat_files: Mapping | None = None,
                    event: int | None = None) -> list[FlatRecording]:
    """Each recording of the flat plate: every EXR of ``flat``, then every set of single-channel
    files (the i-th file of each detector in ``flat_files``, ``{detector: [path, ...]}``)."""
    from .io import load_detector_set

    files = {n: list((flat_files or {}).get(n) or []) for n in DETECTOR_NAMES}
    exrs = list(flat or [])
    sets = max(len(v) for v in files.values())
    what = "flat-plate images"
    out = []
    for path in exrs:
        images, header = load_detector_set(path, None, what, event)
        out.append(FlatRecording(str(path), path, images, header))
    for i in range(sets):
        given = {n: v[i] for n, v in files.items() if i < len(v)}
        label = f"{what} (set {i + 1} of --flat-<detector>)" if len(exrs) + sets > 1 else what
        images, header = load_detector_set(None, given, label, event)
        out.append(FlatRecording(", ".join(str(given[n]) for n in DETECTOR_NAMES), given, images, header))
    return out


def _same(a, b, rtol=1e-6):
    return np.allclose(np.asarray(a, float), np.asarray(b, float), rtol=rtol, atol=0)


def read_scan(object_exr=None, *, files: Mapping | None = None, flat: Sequence = (),
              flat_files: Mapping | None = None, no_flat: bool = False, event: int | None = None,
              field_mm=None, d_h: float | None = None, d_w: float | None = None, material: str | None = None,
              model_discs: bool = False) -> Scan:
    """Read one scan's object and flat-plate images, checked: signs, one shape, every flat
    recorded with the object's geometry, the header's resolution.

    Parameters
    ----------
    object_exr : path, optional
        A forward-model EXR with channels right, left, back, front.
    files : mapping, optional
        ``{detector: path}`` of single-channel object images (EXR, TIFF, NPY).
    flat : sequence of path
        Flat-plate EXRs; several recordings are averaged.
    flat_files : mapping, optional
        ``{detector: [path, ...]}`` of single-channel flat-plate images (the i-th of each is one set).
    no_flat : bool
        The images are already STSA-corrected (no flat given).
    event : int, optional
        Read the per-event channels of this scattering event.
    field_mm : float or (float, float), optional
        Scan field (mm); overrides the header's.
    d_h, d_w : float, optional
        Detector height and distance from the z-axis (mm); override the header's.
    material : str, optional
        The plate's material (a preset name or composition), where the header's discs are read.
    model_discs : bool
        With a header that records detectors and no ``d_h``/``d_w``: ``geo``'s d_h and d_w are the
        discs' mean and the flats are compared disc by disc (the model takes the discs as they are).

    Returns
    -------
    Scan

    Examples
    --------
    Four single-channel images of a tilted plane and of the flat plate (point detectors, Lambert):

    >>> import tempfile, numpy as np
    >>> from pathlib import Path
    >>> from elo_mitsuba.analysis import flat_plate_images, point_detector_images
    >>> shape, field, d_h, d_w = (16, 16), (20.0, 20.0), 250.0, 150.0
    >>> obj = point_detector_images(np.full(shape, 0.1), np.zeros(shape), field, d_h, d_w, model="lambert")
    >>> flat = flat_plate_images(shape, field, d_h, d_w, model="lambert")
    >>> folder = Path(tempfile.mkdtemp())
    >>> for n in obj:
    ...     np.save(folder / f"{n}.npy", obj[n]); np.save(folder / f"flat_{n}.npy", flat[n])
    >>> scan = read_scan(files={n: folder / f"{n}.npy" for n in obj},
    ...                  flat_files={n: [folder / f"flat_{n}.npy"] for n in obj},
    ...                  field_mm=20.0, d_h=d_h, d_w=d_w)
    >>> scan.shape, scan.geo["field_mm"], scan.geo["d_h"]
    ((16, 16), (20.0, 20.0), 250.0)
    """
    from .io import check_signs, load_detector_set
    from .stsa import mean_flat

    given = {n: (files or {}).get(n) for n in DETECTOR_NAMES}
    images, meta = load_detector_set(object_exr, given, "object images", event)
    if images is None:
        raise EloInputError("no object images: give OBJECT.exr or --right/--left/--back/--front")
    recordings = flat_recordings(flat, flat_files, event)
    flats = mean_flat([r.images for r in recordings]) if recordings else None
    flat_meta = next((r.header for r in recordings if r.header), {})
    if flats is None and not no_flat:
        raise EloInputError("no flat-plate images: give --flat FLAT.exr (or --flat-right ...), "
                            "or --no-flat if the images are already STSA-corrected")
    if flats is not None and no_flat:
        raise EloInputError("--no-flat contradicts the flat-plate images given")
    check_signs(images, flats, {n: object_exr or given[n] for n in DETECTOR_NAMES})
    _check_distinct(object_exr, given, recordings)

    # Geometry: explicit values win; otherwise the object header, else the flat header.
    header = meta if meta else flat_meta
    # the file whose header is read (an object without one takes the flat's)
    source = (object_exr if meta else None) or next((r.label for r in recordings if r.header), None) \
        or object_exr or "command line"
    if not header and (field_mm is None or d_h is None or d_w is None):
        what = (f"{source} has no elo-mitsuba geometry header (not written by 'elo-mitsuba render')"
                if (object_exr or flat) else "single-channel inputs carry no geometry")
        raise EloInputError(f"{what}: pass --field, --dh and --dw (mm)")
    shape = next(iter(images.values())).shape
    from ..schema import PROJECTION, RESOLUTION, UNITS, WORK_DISTANCE, has_detectors, read_geometry
    from .layout import symmetric_layout
    from .scan_geometry import ScanGeometry

    header_discs = model_discs and d_h is None and d_w is None and has_detectors(header)

    def disc_view(hdr, label, mat=None):
        """Field, resolution and every disc of a header (what the flats must share with the object)."""
        discs = ScanGeometry.from_metadata(hdr, shape, label, field_mm=field_mm, material=mat)
        res = hdr.get(RESOLUTION)
        return discs, {"field_mm": discs.field_mm, "resolution": res,
                       **{f"{n} detector": np.r_[d.center, d.normal, d.radius] for n, d in discs.detectors.items()}}

    if header_discs:
        # the model takes the header's discs as they are: no symmetric layout needed
        disc_geo, geo_cmp = disc_view(header, str(source), material)
        res_hdr = geo_cmp["resolution"]
        dh_mean, dw_mean = disc_geo.symmetric_layout()
        geo = {"field_mm": disc_geo.field_mm, "d_h": dh_mean, "d_w": dw_mean,
               "resolution": None if res_hdr is None else (int(res_hdr[0]), int(res_hdr[1]))}
    else:
        geo = symmetric_layout(read_geometry(header, str(source), shape=shape, field_mm=field_mm), d_h=d_h, d_w=d_w)
        geo_cmp = geo
    # every flat must describe the object's scan, or the division mixes two geometries
    for rec in recordings if header else ():
        if not rec.header:
            continue
        if header_discs:
            fgeo = disc_view(rec.header, rec.label)[1]
        else:
            fgeo = symmetric_layout(read_geometry(rec.header, rec.label, shape=shape, field_mm=field_mm),
                                    d_h=d_h, d_w=d_w)
        for key in fgeo:
            a, b = geo_cmp.get(key), fgeo[key]
            if (a is None) != (b is None) or (a is not None and not _same(a, b)):
                raise EloInputError(
                    f"{rec.label}: flat-plate {key} {np.round(np.asarray(b, float), 4).tolist()} differs from "
                    f"the {'object' if meta else 'first flat'}'s {np.round(np.asarray(a, float), 4).tolist()}; "
                    "record all with one geometry"
                )
        # the beam's pivot and projection set where it lands and how it tilts across the field,
        # which the flat's images carry, and volts against N_d/N_0 is a factor I_b T in the
        # division (it masked every pixel as dark); headers without them (other tools) are not compared
        for key in (WORK_DISTANCE, PROJECTION, UNITS):
            a, b = header.get(key), rec.header.get(key)
            if a is None or b is None:
                continue
            if a != b if isinstance(a, str) or isinstance(b, str) else not _same(a, b):
                fix = "give all in one unit" if key == UNITS else "record all with one geometry"
                raise EloInputError(f"{rec.label}: flat-plate {key} {b!r} differs from the "
                                    f"{'object' if meta else 'first flat'}'s {a!r}; {fix}")
    check_resolution(geo["resolution"], shape, source)
    return Scan(images=images, flats=flats, header=header, source=str(source), shape=shape, geo=geo,
                flat_files=[r.files for r in recordings], object_files=object_exr or given)


def _check_distinct(object_exr, given, recordings) -> None:
    """Refuse an object file that is also a flat: the division gives 1 everywhere and the gradient
    0, which looks like a flat plate's rather than a mistake."""
    objects = {Path(p).resolve() for p in [object_exr, *given.values()] if p is not None}
    for rec in recordings:
        paths = rec.files.values() if isinstance(rec.files, Mapping) else [rec.files]
        for p in paths:
            if p is not None and Path(p).resolve() in objects:
                raise EloInputError(f"{p} is both an object image and a flat-plate image; give the flat plate's "
                                    "recording as --flat")


def check_resolution(resolution, shape, source) -> None:
    """Refuse images whose shape is not the header's ``resolution`` (W, H): cropped or resampled
    images with the scan's header would put every pixel elsewhere than it was recorded."""
    if resolution is None:
        return
    try:
        width, height = (int(r) for r in resolution)
    except (TypeError, ValueError):
        raise EloInputError(f"{source}: header resolution {resolution!r}: need two whole numbers (W, H)") from None
    if (width, height) != (shape[1], shape[0]):
        raise EloInputError(f"{source}: header resolution {list(resolution)} (W, H) does not match the image "
                            f"shape {shape[1]}x{shape[0]}")


def nominal_geometry(header: Mapping | None, shape, field_mm, d_h: float, d_w: float, *,
                     radius: float | None = None, work_distance_mm: float | None = None,
                     projection: str | None = None, material: str | None = None):
    """The drawing's layout of Eq. 17 (:meth:`~.scan_geometry.ScanGeometry.nominal`): the beam's
    work distance and projection given or the header's, else the package's; disc radius
    ``radius`` (mm, default 25)."""
    from ..schema import PROJECTION, WORK_DISTANCE
    from .scan_geometry import ScanGeometry

    header = header or {}
    kw = {"work_distance_mm": work_distance_mm or header.get(WORK_DISTANCE, WORK_DISTANCE_MM),
          "projection": projection or header.get(PROJECTION, "perspective")}
    if material:
        kw["material"] = material
    return ScanGeometry.nominal(shape, field_mm, d_h, d_w, radius=radius or DETECTOR_DIAMETER_MM / 2, **kw)


def model_geometry(scan: Scan, *, d_h: float | None = None, d_w: float | None = None,
                   radius: float | None = None, work_distance_mm: float | None = None,
                   projection: str | None = None, material: str | None = None, calibration=None):
    """The scan geometry the model inverts.

    Parameters
    ----------
    scan : Scan
        As :func:`read_scan` read it.
    d_h, d_w : float, optional
        Detector height and distance (mm): the nominal layout of Eq. 17 instead of the header's discs.
    radius, work_distance_mm : float, optional
        Disc radius and beam pivot height (mm), for the nominal layout.
    projection : str, optional
        ``perspective`` or ``orthographic``, for the nominal layout.
    material : str, optional
        The plate's material (default: the header's, else Ti-6Al-4V).
    calibration : path, optional
        A CALIB.json of ``elo-mitsuba calibrate``: its detectors replace the layout's.

    Returns
    -------
    ScanGeometry
        Every detector checked against the placement rule of the scenes.

    Examples
    --------
    >>> from elo_mitsuba.analysis.chain import Scan, model_geometry
    >>> scan = Scan(images={}, flats=None, header={}, source="command line", shape=(8, 8),
    ...             geo={"field_mm": (20.0, 20.0), "d_h": 250.0, "d_w": 150.0, "resolution": None})
    >>> geo = model_geometry(scan)
    >>> geo.detectors["right"].center, geo.detectors["right"].radius
    ((150.0, 0.0, 250.0), 25.0)
    """
    from ..schema import has_detectors
    from .scan_geometry import ScanGeometry

    header, shape, geo, source = scan.header, scan.shape, scan.geo, scan.source
    explicit = d_h is not None or d_w is not None or not has_detectors(header)
    if explicit:
        if (d_h is None) != (d_w is None) and has_detectors(header):
            raise EloInputError("give both --dh and --dw (a nominal layout), or neither (the header's detectors)")
        model = nominal_geometry(header, shape, geo["field_mm"], geo["d_h"], geo["d_w"], radius=radius,
                                 work_distance_mm=work_distance_mm, projection=projection, material=material)
    else:
        for flag, value in (("radius", radius), ("wd", work_distance_mm), ("projection", projection)):
            if value is not None:
                raise EloInputError(f"--{flag} applies to images without a header (or with --dh/--dw); "
                                    f"{source} records the geometry")
        model = ScanGeometry.from_metadata(header, shape, source, field_mm=geo["field_mm"], material=material)
    if calibration:
        from .calibration import read_calibration

        model = read_calibration(calibration).apply(model)
    from ..scene_files import check_detector_placement

    where = calibration or ("--dh/--dw" if explicit and d_h is not None else source)
    for name, disc in model.detectors.items():  # the rule of every detector (a scene's, a moved one's)
        check_detector_placement(name, disc.center, disc.normal, disc.radius, where=str(where))
    return model


def check_gradient_settings(method: str = "model", iterations: int | None = None,
                            height_passes: int | None = None) -> None:
    """Refuse settings :func:`gradient` cannot run with, before any image is read."""
    if iterations is not None and iterations < 1:
        raise EloInputError(f"--iterations {iterations}: need at least 1")
    if height_passes is not None and (isinstance(height_passes, bool) or height_passes not in (1, 2, 3)):
        raise EloInputError(f"--height-passes {height_passes}: choose 1, 2, 3 or auto")
    if method not in ("model", "eq26"):
        raise EloInputError(f"gradient method {method!r}: choose model or eq26")


def gradient(scan: Scan, *, method: str = "model", geometry=None, iterations: int | None = None,
             noise: float | None = None, second_event=None, height_passes: int | None = None,
             min_corrected: float | None = None, min_sum: float | None = None,
             min_denominator: float | None = None):
    """The surface gradient of one scan: the per-pixel model fit or the paper's Eq. 26.

    Parameters
    ----------
    scan : Scan
        As :func:`read_scan` read it.
    method : {"model", "eq26"}
        The 1st-event model fit (:func:`~.model_gradient.model_gradient_refined`) or Eq. 26
        (:func:`~.gradient.surface_gradient`, on ``scan.geo``'s d_h and d_w).
    geometry : ScanGeometry, optional
        The model's geometry (method model; default :func:`model_geometry` of the scan).
    iterations : int, optional
        Levenberg-Marquardt iterations of the model fit (default 10).
    noise : float, optional
        Noise (std) of the corrected images; default: estimated.
    second_event : path, optional
        A render of the flat plate with ``--events >= 2``: its share of later events is taken out.
    height_passes : int, optional
        Model fits, each with the landing points on the heights of the one before (1 to 3); None:
        2 where the relief needs them (:data:`~.model_gradient.AUTO_RELIEF_MM`).
    min_corrected, min_sum, min_denominator : float, optional
        Mask thresholds (corrected units; the denominator as a fraction of d_w, Eq. 26 only).

    Returns
    -------
    result : GradientResult or ModelGradientResult
        dZ/dx, dZ/dy (mm/mm), the mask and its reasons.
    thresholds : dict
        The mask thresholds used (for the header).

    Examples
    --------
    >>> from elo_mitsuba.analysis.chain import gradient
    >>> result, thresholds = gradient(scan, method="eq26")  # doctest: +SKIP
    >>> sorted(thresholds)  # doctest: +SKIP
    ['min_corrected', 'min_denominator', 'min_sum']
    """
    from .gradient import MIN_CORRECTED, MIN_DENOMINATOR, surface_gradient
    from .stsa import MIN_SUM

    check_gradient_settings(method, iterations, height_passes)
    kw = dict(min_corrected=MIN_CORRECTED if min_corrected is None else min_corrected,
              min_sum=MIN_SUM if min_sum is None else min_sum,
              min_denominator=MIN_DENOMINATOR if min_denominator is None else min_denominator)
    if method == "eq26":
        return surface_gradient(scan.images, scan.flats, scan.geo["field_mm"], scan.geo["d_h"], scan.geo["d_w"],
                                **kw), kw
    from .io import read_later_events
    from .model_gradient import ITERATIONS, model_gradient_refined

    geometry = model_geometry(scan) if geometry is None else geometry
    share = read_later_events(second_event, scan.shape)[1] if second_event else None
    if share is not None and scan.flats is None:
        raise EloInputError("--second-event corrects the flat-plate images; give --flat")
    res = model_gradient_refined(scan.images, scan.flats, geometry, passes=height_passes, noise=noise,
                                 flat_second_event=share,
                                 iterations=ITERATIONS if iterations is None else iterations,
                                 min_corrected=kw["min_corrected"], min_sum=kw["min_sum"])
    kw.pop("min_denominator")
    return res, kw


def heights(dzdx, dzdy, field_mm, *, mask=None, method: str = "auto", projection: str | None = None,
            work_distance_mm: float | None = None, min_component_size: int | None = None, progress=None) -> dict:
    """The height map of a gradient by normal integration, with how far it can be trusted: the
    ``reconstruct`` command's computation.

    Parameters
    ----------
    dzdx, dzdy : ndarray (H, W)
        The surface gradient (mm/mm) where each pixel's beam lands; NaN or ``mask`` where unknown.
    field_mm : float or (float, float)
        Scan field (mm).
    mask : ndarray of bool, optional
        Untrusted gradient pixels (True).
    method : str
        Solver of :func:`~.integrate.integrate_gradient` (``"auto"``: ``masked`` where a pixel is
        masked or not finite, else ``dct``; ``"robust"``: the discontinuity-preserving Cauchy
        estimator, :func:`~.integrate.integrate_robust`, for surfaces with cliffs).
    projection, work_distance_mm : str, float, optional
        The scan's beam (``perspective`` from a pivot ``work_distance_mm`` above the plate, or
        ``orthographic``). A perspective scan's slopes are converted to the scan grid first
        (:func:`~.integrate.scan_grid_gradient`): integrated as they are, a zero-mean relief
        becomes a bowl.
    min_component_size : int, optional
        ``masked`` solver: trusted regions with fewer pixels are dropped.
    progress : callable, optional
        ``robust``: called after each reweighted solve (:func:`~.integrate.integrate_robust`).

    Returns
    -------
    dict
        ``height`` (mm, zero mean over the measured pixels), ``mask`` (True: no height),
        ``method`` (the solver that ran), ``quality`` (:func:`~.integrate.reconstruction_quality`:
        integrability residual, masked share, bowl, relief, warnings) and ``grid`` (what pixel
        (i, j) holds).

    Examples
    --------
    >>> import numpy as np
    >>> out = heights(0.1 * np.ones((32, 32)), np.zeros((32, 32)), 16.0)
    >>> out["method"], round(float(out["height"][0, -1] - out["height"][0, 0]), 3)
    ('dct', 1.55)
    >>> step = np.zeros((32, 32)); step[:, 16] = 2.0             # a 1 mm cliff in one column
    >>> out = heights(step, np.zeros((32, 32)), 16.0, method="robust")
    >>> out["method"], round(float(out["height"][0, -1] - out["height"][0, 0]), 3)
    ('robust', 1.0)
    """
    from .integrate import integrate_gradient, reconstruction_quality, resolve_method, scan_grid_gradient
    from .sampling_check import half_sampling

    method = resolve_method(method, dzdx, dzdy, mask)  # what runs is what is reported
    gx, gy = dzdx, dzdy
    perspective = projection == "perspective" and bool(work_distance_mm)
    if perspective:
        gx, gy = scan_grid_gradient(gx, gy, field_mm, work_distance_mm, mask=mask)
        if mask is not None:
            gx, gy = np.where(mask, 0.0, gx), np.where(mask, 0.0, gy)
    kw = {} if min_component_size is None else {"min_component_size": min_component_size}
    height, mask_out = integrate_gradient(gx, gy, field_mm, method=method, mask=mask, progress=progress, **kw)
    # the resolution test re-solves on sub-lattices; 'robust' by 'masked', its least-squares core
    # (its reweighting at twice the pitch would give up other pairs and measure that instead)
    check = "masked" if method == "robust" else method

    def solve(gx_, gy_, field_, mask_):
        return integrate_gradient(gx_, gy_, field_, method=check, mask=mask_ if mask_.any() else None, **kw)

    return {"height": height, "mask": mask_out, "method": method,
            "quality": reconstruction_quality(gx, gy, field_mm, height, mask_out,
                                              half_sampling(gx, gy, field_mm, height, mask_out, solve)),
            "grid": ("scan grid of a perspective scan: pixel (i, j) holds the height where its beam lands "
                     "(slopes converted, analysis.integrate.scan_grid_gradient)") if perspective else "scan grid"}


def read_start(path, shape, field_mm):
    """Starting heights (mm, zero mean) or a gradient to integrate, from a file: a gradient EXR
    (channels dzdx, dzdy), a height EXR (channel height) or a ``.npy`` of heights on the scan grid."""
    from .io import read_exr, read_gradient, read_image

    suffix = Path(path).suffix.lower()
    if not Path(path).is_file():
        raise EloInputError(f"--init {path}: no such file")
    if suffix == ".npy":
        try:
            h, _ = read_image(path)  # allow_pickle=False; a 2-D numeric array or one line why not
        except EloInputError as exc:
            raise EloInputError(f"--init {exc}") from None
    elif suffix == ".exr":
        channels, _ = read_exr(path)
        if "dzdx" in channels:
            g = read_gradient(path, field_mm=field_mm)
            from .gradient import GradientResult

            mask = g["mask"] if g["mask"] is not None else np.zeros(shape, bool)
            if g["dzdx"].shape != tuple(shape):
                raise EloInputError(f"--init {path}: {g['dzdx'].shape[1]}x{g['dzdx'].shape[0]} px, the images "
                                    f"{shape[1]}x{shape[0]}")
            return GradientResult(dzdx=g["dzdx"], dzdy=g["dzdy"], mx=None, my=None, sum_x=None, sum_y=None,
                                  mask=mask, reasons=mask.astype(np.uint8), corrected=None)
        if "height" not in channels:
            raise EloInputError(f"--init {path}: needs channels dzdx, dzdy (a gradient) or height")
        h = channels["height"]
    else:
        raise EloInputError(f"--init {path}: use a gradient or height .exr, or a .npy of heights")
    h = np.asarray(h, float)
    if h.shape != tuple(shape):
        got = f"{h.shape[1]}x{h.shape[0]} px" if h.ndim == 2 else f"shape {h.shape}"
        raise EloInputError(f"--init {path}: heights of {got}, the images {shape[1]}x{shape[0]} px; give the start "
                            "at the images' resolution")
    if not np.all(np.isfinite(h)):
        raise EloInputError(f"--init {path}: {int(np.sum(~np.isfinite(h)))} height(s) NaN or Inf; a start needs a "
                            "finite height at every pixel")
    return h - h.mean()


def invert(scan: Scan, geometry, *, fwhm_mm: float = 0.0, start=None, second_event=None,
           chamber_later: bool = False, notify: Callable[[str], None] | None = None, **solver):
    """The height map whose modelled images reproduce the scan's (the forward model inverted).

    Parameters
    ----------
    scan : Scan
        As :func:`read_scan` read it, with flat-plate images.
    geometry : ScanGeometry
        The model's geometry (:func:`model_geometry`).
    fwhm_mm : float
        Beam profile FWHM on the plate (mm; :meth:`Scan.beam_fwhm`).
    start : ndarray or GradientResult, optional
        Starting heights (mm) or a gradient to integrate (:func:`read_start`); default: the model
        gradient of the same images.
    second_event : path, optional
        A render of the flat plate in the chamber with ``--events >= 2``: its later events are held
        fixed in the model of the flat (and of the object unless ``chamber_later``).
    chamber_later : bool
        Render the start surface in the chamber and hold the object's own later events fixed.
    notify : callable, optional
        Called with a line before a long step (the chamber render).
    **solver
        Passed on to :func:`~.inversion.invert_heights` (iterations, scales, tol, discrepancy,
        alpha, noise, shadows, time_budget_s, progress, force, uncertainty_probes).

    Returns
    -------
    InversionResult
        Heights (mm), mask, misfit and the solver's history.

    Examples
    --------
    >>> from elo_mitsuba.analysis.chain import invert, model_geometry
    >>> result = invert(scan, model_geometry(scan), fwhm_mm=scan.beam_fwhm())  # doctest: +SKIP
    """
    from . import inversion

    if scan.flats is None:
        raise EloInputError("--no-flat: the inversion needs the flat-plate images (their ratio cancels the gains)")
    if chamber_later and not second_event:
        raise EloInputError("--chamber-later needs --second-event SIM_FLAT.exr (the flat plate's later events)")
    inversion.check_beam_and_start(geometry, fwhm_mm, None if start is None or hasattr(start, "dzdx") else start,
                                   what="--init heights")
    from .io import read_later_errors, read_later_events

    flat_later, share = read_later_events(second_event, scan.shape) if second_event else (None, None)
    flat_later_error = read_later_errors(second_event) if second_event else None
    if start is None and share is not None:  # the model gradient with the same later events removed
        from .model_gradient import model_gradient_refined

        start = model_gradient_refined(scan.images, scan.flats, geometry, flat_second_event=share)
    later, later_error = flat_later, flat_later_error
    if chamber_later:
        from .later_events import later_events

        h0 = inversion.start_heights(start, geometry) if hasattr(start, "dzdx") else start
        if notify is not None:
            notify("rendering the start surface in the chamber for its later events ...")
        later, later_error = later_events(h0, geometry, fwhm_mm=fwhm_mm, with_errors=True)
    return inversion.invert_heights(scan.images, scan.flats, geometry, start=start, fwhm_mm=fwhm_mm, later=later,
                                    flat_later=flat_later, later_error=later_error,
                                    flat_later_error=flat_later_error, **solver)


def read_calibration_flats(flat: Sequence = (), files: Mapping | None = None, event: int | None = None,
                           second_event=None):
    """The flat-plate images a calibration fits (the mean of several EXR recordings of one set-up,
    or four single-channel files), their header and how messages name its file.

    ``second_event`` (a render of the flat plate in its chamber with ``--events >= 2``): each
    pixel's share of events >= 2 in that render is taken out of the images (times 1 - share), so
    that the 1st-event fit sees the 1st event; a chamber's later events are smooth over the field
    and a fit without them moves the detectors to mimic them (athene_flat, 128^2: 10-16 mm).
    """
    from ..schema import SETUP_KEYS
    from .io import load_detector_set
    from .stsa import mean_flat

    files = dict(files or {})
    flat = list(flat or [])
    if flat and any(files.values()):
        raise EloInputError("flat-plate images: give FLAT.exr files or the four single files, not both")
    if second_event is not None and event is not None:
        raise EloInputError(f"--event {event} already takes one event's channels; --second-event removes the later "
                            "events of the total: give one")
    sets = [load_detector_set(f, None, "flat-plate images", event) for f in flat] or \
        [load_detector_set(None, files, "flat-plate images", event)]
    if sets[0][0] is None:
        raise EloInputError("no flat-plate images: give FLAT.exr or --right/--left/--back/--front")
    header = sets[0][1]
    for path, (_, other) in zip(flat[1:], sets[1:]):
        for key in SETUP_KEYS:
            if other.get(key) != header.get(key):
                raise EloInputError(f"{path}: header {key} {other.get(key)!r} differs from {flat[0]}'s "
                                    f"{header.get(key)!r}; average only recordings of one set-up")
    flats = mean_flat([images for images, _ in sets])
    source = str(flat[0]) if flat else "command line"  # the header's file
    if second_event is not None:
        from .io import read_later_events

        _, share = read_later_events(second_event, next(iter(flats.values())).shape)
        flats = {n: img * (1.0 - share[n]) for n, img in flats.items()}
    return flats, header, source


def calibration_start(header: Mapping, shape, source: str, *, d_h=None, d_w=None, field_mm=None,
                      radius=None, work_distance_mm=None, projection=None, material=None):
    """The start of a calibration fit: the nominal layout of ``d_h``/``d_w`` or the header's detectors."""
    from ..grid import field_xy
    from ..schema import FIELD, has_detectors
    from .scan_geometry import ScanGeometry

    if (d_h is None) != (d_w is None):
        raise EloInputError("give both --dh and --dw (the nominal layout), or neither (the header's detectors)")
    check_resolution((header or {}).get("resolution"), shape, source)
    if d_h is not None or not has_detectors(header):
        if d_h is None:
            raise EloInputError(f"{source}: no detector geometry in the input; pass --dh and --dw (mm)")
        field = field_mm if field_mm is not None else header.get(FIELD)
        if field is None:
            raise EloInputError(f"{source}: no scan field in the input; pass --field FX[,FY] (mm)")
        return nominal_geometry(header, shape, field_xy(field, shape), d_h, d_w, radius=radius,
                                work_distance_mm=work_distance_mm, projection=projection, material=material)
    for flag, value in (("radius", radius), ("wd", work_distance_mm), ("projection", projection)):
        if value is not None:
            raise EloInputError(f"--{flag} applies with --dh/--dw (the nominal layout); {source} records it")
    return ScanGeometry.from_metadata(header, shape, str(source), field_mm=field_mm, material=material)
