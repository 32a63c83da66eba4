"""The package's file conventions: channel names, unit labels, header keys and the geometry header.

One place for what the renderer writes and the analysis reads:

* channel names: a detector's image is ``<id>``, its k-th scattering event alone ``<id>.e<k>``
  (:func:`event_channel`), a channel's per-pixel standard error ``<name>.err``
  (:func:`error_channel`);
* the unit label of detector images (:func:`signal_units`: N_d/N_0, or V);
* the header's key names, and the one reader (:func:`read_geometry`) and writer
  (:func:`geometry_header`) of its geometry block;
* the beam's FWHM -> Gaussian sigma (:func:`fwhm_to_sigma`; headers call the FWHM
  ``beam_fwhm_mm``, code ``fwhm_mm``).

This module imports only numpy and the package's core (constants, errors, grid), so that the
plugins and every layer above them can use it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterable, Mapping

import numpy as np

from .constants import DEFAULT_MATERIAL, WORK_DISTANCE_MM
from .arguments import shown
from .errors import EloInputError
from .grid import field_xy

# -- channel names --
#: Separator of a channel's event suffix: ``right.e2``.
EVENT_SEPARATOR = ".e"
#: Suffix of a channel's standard-error channel: ``right.err``.
ERROR_SUFFIX = ".err"


def event_channel(name: str, event: int) -> str:
    """The channel of detector ``name``'s ``event``-th scattering event alone.

    Parameters
    ----------
    name : str
        Detector (shape) id, e.g. ``right``.
    event : int
        Scattering event, 1 = the first.

    Returns
    -------
    str

    Examples
    --------
    >>> event_channel("right", 2)
    'right.e2'
    """
    return f"{name}{EVENT_SEPARATOR}{int(event)}"


def event_channels(names: Iterable[str], events: int, first: int = 1) -> list[str]:
    """Every per-event channel of ``names``, events ``first`` .. ``events``, detector by detector.

    Parameters
    ----------
    names : iterable of str
        Detector ids.
    events : int
        The last event.
    first : int
        The first event (1; 2 for the later events alone).

    Returns
    -------
    list of str

    Examples
    --------
    >>> event_channels(["right", "left"], 2)
    ['right.e1', 'right.e2', 'left.e1', 'left.e2']
    """
    return [event_channel(n, k) for n in names for k in range(first, int(events) + 1)]


def error_channel(name: str) -> str:
    """The channel holding channel ``name``'s per-pixel standard error.

    Parameters
    ----------
    name : str
        A channel, e.g. ``right`` or ``right.e2``.

    Returns
    -------
    str

    Examples
    --------
    >>> error_channel("right.e2")
    'right.e2.err'
    """
    return f"{name}{ERROR_SUFFIX}"


def error_channels(channels: Mapping) -> dict:
    """The standard-error channels of ``channels`` by the channel they belong to.

    Parameters
    ----------
    channels : mapping of str to ndarray
        An EXR's channels.

    Returns
    -------
    dict
        ``{name: error image}`` for each ``<name>.err``.

    Examples
    --------
    >>> error_channels({"right": 1.0, "right.err": 0.1})
    {'right': 0.1}
    """
    return {name[:-len(ERROR_SUFFIX)]: v for name, v in channels.items() if name.endswith(ERROR_SUFFIX)}


# -- units --
#: Detector images in the fraction of the beam's electrons that reach the detector (Eq. 5).
UNITS_FRACTION = "N_d/N_0"
#: Detector images as the amplifier's voltage U_d = N_d/N_0 I_b T (Eq. 9).
UNITS_VOLTAGE = "V"


def signal_units(units: str = "fraction") -> str:
    """The label of detector images for the integrator's ``units`` option.

    Parameters
    ----------
    units : str
        ``voltage`` or anything else (the fraction N_d/N_0).

    Returns
    -------
    str

    Examples
    --------
    >>> signal_units("voltage"), signal_units("fraction")
    ('V', 'N_d/N_0')
    """
    return UNITS_VOLTAGE if units == "voltage" else UNITS_FRACTION


# -- header keys --
FIELD = "field_mm"
RESOLUTION = "resolution"
DETECTORS = "detectors"
WORK_DISTANCE = "work_distance_mm"
PROJECTION = "projection"
AIM_OFFSET = "beam_aim_offset_mm"
BEAM_FWHM = "beam_fwhm_mm"
MATERIAL = "material"
MATERIALS = "materials"
#: g_BSE's specular lobe per elo_bse shape as rendered: {"lobe": bool, "lobe_width_deg": float}
SCATTERING = "scattering"
UNITS = "units"
#: What recordings averaged into one flat must share.
SETUP_KEYS = (FIELD, RESOLUTION, DETECTORS, WORK_DISTANCE, PROJECTION)
PROJECTIONS = ("perspective", "orthographic")

# -- the beam profile --
#: FWHM of a Gaussian over its sigma, 2 sqrt(2 ln 2).
FWHM_PER_SIGMA = 2.0 * np.sqrt(2.0 * np.log(2.0))


def fwhm_to_sigma(fwhm_mm: float) -> float:
    """The standard deviation of the Gaussian beam profile whose FWHM is ``fwhm_mm``.

    Parameters
    ----------
    fwhm_mm : float
        Full width at half maximum (mm).

    Returns
    -------
    float
        Sigma (mm).

    Examples
    --------
    >>> round(fwhm_to_sigma(0.27), 5)
    0.11466
    """
    return float(float(fwhm_mm) / FWHM_PER_SIGMA)


# -- the geometry header --
@dataclass(frozen=True)
class HeaderGeometry:
    """The scan geometry a header records, as read by :func:`read_geometry`.

    Attributes
    ----------
    source : str
        How messages name the header's file.
    field_mm : (float, float)
        Scan field (mm).
    resolution : (int, int) or None
        Image size (W, H) the header records.
    detectors : mapping or None
        ``{name: {"center": [x, y, z], "normal": [...], "radius": r}}`` as recorded (mm), checked
        by whoever interprets them (:func:`~elo_mitsuba.analysis.layout.symmetric_layout`,
        :meth:`~elo_mitsuba.analysis.scan_geometry.ScanGeometry.from_header`).
    work_distance_mm : float
        Height of the beam pivot.
    projection : str
        ``perspective`` or ``orthographic``.
    aim_offset_mm : (float, float)
        Offset of every aim point.
    material : str
        The surface material (:func:`material_from_metadata`).
    """

    source: str
    field_mm: tuple
    resolution: tuple | None
    detectors: Mapping | None
    work_distance_mm: float
    projection: str
    aim_offset_mm: tuple
    meta: Mapping = field(default_factory=dict, repr=False)

    @property
    def material(self) -> str:
        return material_from_metadata(self.meta)


def has_detectors(meta: Mapping | None) -> bool:
    """Whether a header records detectors (a forward model's; recorded images carry none).

    Examples
    --------
    >>> has_detectors({}), has_detectors({"detectors": {"right": {}}})
    (False, True)
    """
    return bool((meta or {}).get(DETECTORS))


#: The largest length (mm) read from a file (a header, a calibration): a kilometre, beyond any
#: chamber (1e300 overflowed the calibration's fits) ...
MAX_LENGTH_MM = 1e6
#: ... and the smallest positive one (a field, work distance or detector radius): a nanometre
#: (1e-300 divided the calibration by zero; a disc of that radius collects nothing).
MIN_LENGTH_MM = 1e-6


#: How messages state :func:`is_length`'s range.
LENGTH_RANGE = f"{MIN_LENGTH_MM:g} to {MAX_LENGTH_MM:g} mm"


def is_length(v) -> bool:
    """A length > 0 (mm) that a header may hold (:data:`MIN_LENGTH_MM` to :data:`MAX_LENGTH_MM`):
    the one test for fields, work distances, pixel sizes and radii wherever they enter, so that
    nothing is rendered or read that a header could not hold.

    >>> is_length(80.0), is_length(1e-300), is_length(1e300), is_length(float("nan")), is_length(True)
    (True, False, False, False, False)
    """
    return _is_number(v) and MIN_LENGTH_MM <= v <= MAX_LENGTH_MM


#: How messages state :func:`is_fwhm`'s range.
FWHM_RANGE = f"0 (a single ray) or {MIN_LENGTH_MM:g} to {MAX_LENGTH_MM:g} mm"


def is_fwhm(v) -> bool:
    """A beam profile's FWHM (mm) that a header may hold: 0 (the single ray of the paper) or a
    length (:func:`is_length`); the one test wherever a FWHM enters (a render, a header, the
    inversion), so that 1e-300 is not a profile in one place and refused in another. Its upper
    bound, the scan field, is checked where the field is known.

    >>> is_fwhm(0.0), is_fwhm(0.27), is_fwhm(1e-300), is_fwhm(-0.1), is_fwhm(float("inf"))
    (True, True, False, False, False)
    """
    return _is_number(v) and (v == 0 or is_length(v))


def _is_number(v) -> bool:
    """A finite real number, numpy's scalars included (an API caller's np.float32(0.27)); not a bool."""
    return (isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))
            and bool(np.isfinite(v)))


def _length(v) -> bool:
    """A finite number of mm within :data:`MAX_LENGTH_MM` of 0."""
    return _is_number(v) and abs(v) <= MAX_LENGTH_MM


def _lengths(v, n: int) -> bool:
    return isinstance(v, (list, tuple)) and len(v) == n and all(_length(x) for x in v)


def _positive_lengths(v) -> bool:
    """A length > 0, or two of them (x, y)."""
    items = v if isinstance(v, (list, tuple)) and len(v) == 2 else [v]
    return all(is_length(x) for x in items)


def _whole(v, least: int) -> bool:
    return _is_number(v) and float(v) == int(v) and int(v) >= least


def _detector_entry(v) -> bool:
    return (isinstance(v, Mapping) and _lengths(v.get("center"), 3) and _lengths(v.get("normal"), 3)
            and any(x != 0 for x in v["normal"]) and _positive_lengths(v.get("radius")))


# What each header key that the analysis reads must hold (a test, what is allowed): JSON as
# elo-mitsuba writes it; a header edited by hand or by another tool is checked before any work.
_HEADER_RULES = {
    FIELD: (_positive_lengths, f"a length or two [x, y] of {LENGTH_RANGE}"),
    RESOLUTION: (lambda v: isinstance(v, (list, tuple)) and len(v) == 2 and all(_whole(x, 1) for x in v),
                 "two whole numbers >= 1 [W, H]"),
    "pixel_size_mm": (_positive_lengths, f"a length or two [x, y] of {LENGTH_RANGE}"),
    WORK_DISTANCE: (_positive_lengths, f"a length of {LENGTH_RANGE}"),
    PROJECTION: (lambda v: v in PROJECTIONS, " or ".join(PROJECTIONS)),
    AIM_OFFSET: (lambda v: _lengths(v, 2), f"two lengths [x, y] within {MAX_LENGTH_MM:g} mm"),
    BEAM_FWHM: (is_fwhm, FWHM_RANGE),
    "events": (lambda v: _whole(v, 1), "a whole number >= 1"),
    DETECTORS: (lambda v: isinstance(v, Mapping) and all(isinstance(k, str) and _detector_entry(d) for k, d in v.items()),
                f"{{name: {{center: [x, y, z], normal: [x, y, z] (not zero), radius: r}}}}, lengths within {MAX_LENGTH_MM:g} mm, r >= {MIN_LENGTH_MM:g}"),
    MATERIAL: (lambda v: isinstance(v, str) and bool(v), "a material name or composition"),
    MATERIALS: (lambda v: isinstance(v, Mapping) and all(isinstance(x, str) for x in v.values()),
                "{shape: material}"),
    SCATTERING: (lambda v: isinstance(v, Mapping) and all(
        isinstance(x, Mapping) and isinstance(x.get("lobe", True), bool)
        and _is_number(x.get("lobe_width_deg", 1.0)) and x.get("lobe_width_deg", 1.0) > 0 for x in v.values()),
        "{shape: {lobe: true or false, lobe_width_deg: > 0}}"),
    UNITS: (lambda v: isinstance(v, str), "a unit label"),
}


def check_header(meta: Mapping, source: str = "header") -> None:
    """Refuse a header whose keys that the analysis reads (field, resolution, pixel size, work
    distance, projection, aim offset, beam FWHM, events, detectors, material(s), scattering, units)
    hold what elo-mitsuba never writes, naming the file, the key, its value and what is allowed;
    keys it lacks are left to their readers (which ask for ``--field`` and the like).

    Examples
    --------
    >>> check_header({"field_mm": [80.0, 80.0], "resolution": [64, 64]})
    >>> check_header({"resolution": "64x64"}, "a.exr")
    Traceback (most recent call last):
    ...
    elo_mitsuba.errors.EloInputError: a.exr: header resolution='64x64'; need two whole numbers >= 1 [W, H]
    """
    for key, (ok, allowed) in _HEADER_RULES.items():
        if key in meta and not ok(meta[key]):
            raise EloInputError(f"{source}: header {key}={shown(meta[key])}; need {allowed}")


def read_geometry(meta: Mapping | None, source: str = "header", *, shape=None, field_mm=None) -> HeaderGeometry:
    """The geometry block of a header: the one reader of its keys.

    Parameters
    ----------
    meta : mapping
        An EXR header of ``elo-mitsuba render`` (or of ``gradient``, ``invert``).
    source : str
        How messages name the file.
    shape : (int, int), optional
        Image shape (H, W): a scalar field is its width (field_y = field H / W); default: the
        header's resolution.
    field_mm : float or (float, float), optional
        Scan field (mm) overriding the header's.

    Returns
    -------
    HeaderGeometry

    Examples
    --------
    >>> g = read_geometry({"field_mm": 80, "resolution": [64, 32], "projection": "orthographic"})
    >>> g.field_mm, g.resolution, g.projection, g.work_distance_mm
    ((80.0, 40.0), (64, 32), 'orthographic', 400.0)
    >>> read_geometry({}, "melt.exr")
    Traceback (most recent call last):
    ...
    elo_mitsuba.errors.EloInputError: melt.exr: no 'field_mm' in the header; pass --field FX[,FY] (mm)
    """
    meta = dict(meta or {})
    if field_mm is None:
        if FIELD not in meta:
            raise EloInputError(f"{source}: no 'field_mm' in the header; pass --field FX[,FY] (mm)")
        field_mm = meta[FIELD]
    res = meta.get(RESOLUTION)
    resolution = None if res is None else (int(res[0]), int(res[1]))
    if shape is None and resolution is not None:
        shape = (resolution[1], resolution[0])
    dets = meta.get(DETECTORS)
    return HeaderGeometry(
        source=str(source), field_mm=field_xy(field_mm, shape), resolution=resolution,
        detectors=dets if isinstance(dets, Mapping) else None,
        work_distance_mm=float(meta.get(WORK_DISTANCE, WORK_DISTANCE_MM)),
        projection=str(meta.get(PROJECTION, "perspective")),
        aim_offset_mm=tuple(meta.get(AIM_OFFSET, (0.0, 0.0))), meta=meta)


def material_from_metadata(meta: Mapping) -> str:
    """The surface material a header records: the one material of the non-detector shapes.

    ``materials`` maps shape ids to ``"name (El:frac,...)"``; detector plates are left out. Several
    different surface materials (or none recorded) give the default material, since one facet
    model cannot mix them.

    Parameters
    ----------
    meta : mapping
        An EXR header of ``elo-mitsuba render``.

    Returns
    -------
    str
        The composition (or name) of the surface material.

    Examples
    --------
    >>> material_from_metadata({"materials": {"plate": "Ti-6Al-4V (Ti:0.9,Al:0.06,V:0.04)"}})
    'Ti:0.9,Al:0.06,V:0.04'
    """
    mats = dict(meta.get(MATERIALS) or {})
    dets = set((meta.get(DETECTORS) or {}).keys())
    found = {v for k, v in mats.items() if k not in dets}
    if len(found) != 1:
        return DEFAULT_MATERIAL
    text = next(iter(found))
    if "(" in text and text.endswith(")"):
        return text[text.index("(") + 1:-1]
    return text


def scattering_note(meta: Mapping | None, source: str = "header") -> str | None:
    """What the analysis must be told when the images were rendered with another g_BSE lobe than
    the paper's (on, 13 deg wide), which the analysis models assume: the slopes come out biased
    (a 25 deg lobe: median dZ/dx 1.072 for a true 1.000 on the 45 deg corrugated sheet); None when
    every surface has the paper's.

    Examples
    --------
    >>> scattering_note({"scattering": {"plate": {"lobe": True, "lobe_width_deg": 13.0}}}) is None
    True
    >>> scattering_note({"scattering": {"plate": {"lobe": False, "lobe_width_deg": 13.0}}})
    "header: the images were rendered with another g_BSE than the analysis models (the paper's: lobe on, 13 deg wide): lobe off on 'plate'; slopes from them are biased"
    """
    from .constants import LOBE_WIDTH_DEG

    dets = set(((meta or {}).get(DETECTORS) or {}).keys())
    odd = []
    for shape, lobe in (((meta or {}).get(SCATTERING) or {}).items()):
        if shape in dets or not isinstance(lobe, Mapping):
            continue
        if not lobe.get("lobe", True):
            odd.append(f"lobe off on {shape!r}")
        elif abs(float(lobe.get("lobe_width_deg", LOBE_WIDTH_DEG)) - LOBE_WIDTH_DEG) > 1e-9:
            odd.append(f"a {float(lobe['lobe_width_deg']):g} deg lobe on {shape!r}")
    if not odd:
        return None
    return (f"{source}: the images were rendered with another g_BSE than the analysis models (the paper's: lobe on, "
            f"{LOBE_WIDTH_DEG:g} deg wide): {', '.join(odd)}; slopes from them are biased")


def grid_header(field_mm, shape) -> dict:
    """The scan grid's part of a header: field (mm) and resolution (W, H) of an image of ``shape``.

    Examples
    --------
    >>> grid_header(80, (32, 64))
    {'field_mm': [80.0, 40.0], 'resolution': [64, 32]}
    """
    h, w = int(shape[0]), int(shape[1])
    return {FIELD: list(field_xy(field_mm, (h, w))), RESOLUTION: [w, h]}


def geometry_header(field_mm, shape, *, work_distance_mm: float, projection: str, aim_offset_mm, material: str,
                    detectors: Mapping) -> dict:
    """The geometry block of a header, as :func:`read_geometry` reads it back.

    Parameters
    ----------
    field_mm : float or (float, float)
        Scan field (mm).
    shape : (int, int)
        Image shape (H, W).
    work_distance_mm : float
        Height of the beam pivot (mm).
    projection : str
        ``perspective`` or ``orthographic``.
    aim_offset_mm : (float, float)
        Offset of every aim point (mm).
    material : str
        The surface material.
    detectors : mapping
        ``{name: {"center", "normal", "radius"}}`` (mm).

    Returns
    -------
    dict

    Examples
    --------
    >>> h = geometry_header(80, (64, 64), work_distance_mm=400.0, projection="perspective",
    ...                     aim_offset_mm=(0.0, 0.0), material="Ti-6Al-4V", detectors={})
    >>> read_geometry(h).field_mm == (80.0, 80.0), list(h)[:2]
    (True, ['field_mm', 'resolution'])
    """
    return {**grid_header(field_mm, shape), WORK_DISTANCE: work_distance_mm, PROJECTION: projection,
            AIM_OFFSET: list(aim_offset_mm), MATERIAL: material, DETECTORS: dict(detectors)}


__all__ = [n for n in dir() if not n.startswith("_") and n not in (
    "annotations", "dataclass", "field", "Iterable", "Mapping", "np", "EloInputError", "field_xy",
    "DEFAULT_MATERIAL", "WORK_DISTANCE_MM")]
