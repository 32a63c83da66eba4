"""Height map files: writing, reading and validating them, pixel positions (millimetres).

A height map is a 2-D array ``height[i, j]`` in millimetres in the package's image orientation
(:mod:`elo_mitsuba.grid`: row 0 is the +y edge, columns run towards +x), centred on the z-axis.
:mod:`elo_mitsuba.mesh` turns one into a triangle mesh.

What :func:`write_height` stores, by suffix (``reconstruct`` and ``invert`` write these):

* ``.exr``: float32 channels ``height`` (mm) and ``mask`` (1 = no height measured / untrusted,
  0 = measured), the metadata as JSON in the header. The height channel holds 0 (not
  NaN) at masked pixels: the package's EXR writer refuses non-finite values, a guard
  against defects that every EXR reader here relies on, and the mask channel says
  where. :func:`read_heightmap` reads those pixels as NaN.
* ``.tif``: float32 height in mm (NaN where no height), the metadata as JSON in the
  ImageDescription, the pixel size in the resolution tags (pixels per centimetre,
  ResolutionUnit CENTIMETER: the unit of baseline TIFF that metrology readers take).
* ``.npy``: float64 height in mm (NaN where no height); no metadata, no pixel size.
* ``.gsf``: Gwyddion Simple Field: the ASCII header (XRes, YRes, XReal, YReal, XOffset, YOffset,
  XYUnits = m, ZUnits = m: Gwyddion asks for base SI units, so lengths and heights are
  in metres there), one to four NUL bytes to a multiple of 4, then little-endian float32
  heights row by row, row 0 first (NaN where no height). Gwyddion's y runs down the
  rows, so its y is the scene's -y (XOffset/YOffset put the map's centre at 0). The
  package metadata is the one-line JSON field ``ELOMitsuba``.

Untrusted pixels hold NaN, not 0, in TIFF, NPY and GSF (they have no mask: a 0 would read as a
measured height); the EXR holds 0 with its ``mask`` channel. ISO 25178-72 ``.x3p`` is not written:
no maintained PyPI library writes it (a zipped XML schema with MD5 checksums, not worth a private
writer beside GSF, which Gwyddion and MountainsMap read).

:func:`read_heightmap` reads these files back (and CSV) with the pixel size their header holds.
"""

from __future__ import annotations

import contextlib
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

import numpy as np

from .arguments import input_file
from .errors import EloInputError
from .files import atomic_write, check_output
from .grid import field_xy, pixel_axes
from .schema import LENGTH_RANGE, is_length

#: File name extensions :func:`write_height` writes.
HEIGHT_SUFFIXES = (".exr", ".npy", ".tif", ".tiff", ".gsf")
#: File name extensions :func:`load_heightmap` reads.
HEIGHTMAP_EXTENSIONS = (".npy", ".tif", ".tiff", ".csv", ".exr", ".gsf")
#: Units :func:`load_heightmap` accepts for heights, as factor to millimetres.
HEIGHT_UNITS = {"mm": 1.0, "um": 1e-3}
#: What the ``mask`` entry of a written header says.
MASK_NOTE = "1 = no height measured or untrusted (height 0 in EXR, NaN in TIFF/NPY/GSF), 0 = measured"
GSF_MAGIC = "Gwyddion Simple Field 1.0"
#: Length units of GSF headers and TIFF resolution units, as millimetres.
_LENGTH_MM = {"m": 1e3, "mm": 1.0, "um": 1e-3, "\u00b5m": 1e-3, "nm": 1e-6}
_TIFF_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 1e-3}  # INCH, CENTIMETER, MILLIMETER, MICROMETER


@dataclass
class HeightFile:
    """A height map read by :func:`read_heightmap`: ``height`` (mm), ``pixel_size_mm`` (None when
    the file does not record it) and where the pixel size came from (``pixel_source``)."""

    height: np.ndarray
    pixel_size_mm: float | None
    pixel_source: str = ""


def _pixel_of(path, field_mm, shape, where: str) -> float:
    """The square pixel pitch of a field over ``shape``; non-square pixels are refused."""
    try:
        fx, fy = field_xy(field_mm, shape)
    except (TypeError, ValueError, EloInputError):
        raise EloInputError(f"{path}: {where} field {field_mm!r} is not one or two lengths in mm") from None
    px, py = fx / shape[1], fy / shape[0]
    if not (math.isfinite(px) and px > 0 and math.isfinite(py) and py > 0):
        raise EloInputError(f"{path}: {where} gives pixel size {px:g} x {py:g} mm; it must be finite and > 0")
    if not math.isclose(px, py, rel_tol=1e-6):
        raise EloInputError(f"{path}: {where} gives pixels of {px:g} x {py:g} mm; only square pixels can be meshed")
    return px


def write_height(path, height, mask=None, metadata: Mapping | None = None, overwrite: bool = False) -> Path:
    """Write a height map (mm) by suffix (:data:`HEIGHT_SUFFIXES`; formats in the module text).

    Pixels where ``mask`` is True (no height measured, untrusted) are stored as NaN (EXR: 0 and
    the mask channel). The pixel size comes from the metadata's ``field_mm`` (the scan field,
    mm); TIFF and GSF record it (GSF needs it). Heights at trusted pixels must be finite.

    Parameters
    ----------
    path : str or Path
        The file; its suffix (``.exr``, ``.npy``, ``.tif``/``.tiff``, ``.gsf``) picks the format.
    height : ndarray (H, W)
        Heights in mm, package orientation (row 0 = +y edge).
    mask : ndarray of bool (H, W), optional
        True = no height measured or untrusted.
    metadata : mapping, optional
        Header entries; ``field_mm`` (scan field, mm) gives the pixel size.
    overwrite : bool
        Replace an existing file (otherwise refused).

    Returns
    -------
    Path
        The file written.

    Raises
    ------
    EloInputError
        An unknown suffix, an existing file, non-finite trusted heights, or GSF without a field.

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> import numpy as np
    >>> height = np.array([[0.0, 0.1, 0.2], [0.0, 0.1, 0.2]])        # mm
    >>> mask = np.array([[False, False, False], [True, False, False]])
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     path = write_height(Path(folder) / "height.exr", height, mask, metadata={"field_mm": [3.0, 2.0]})
    ...     back = read_heightmap(path, allow_nan=True)
    >>> path.name, back.pixel_size_mm, np.isnan(back.height).tolist()
    ('height.exr', 1.0, [[False, False, False], [True, False, False]])
    """
    path = check_output(path, HEIGHT_SUFFIXES, overwrite=overwrite)
    from .arguments import real_array

    height = real_array("height", height)
    if mask is None:
        mask = np.zeros(height.shape, dtype=bool)
    else:
        mask = np.asarray(mask)
        if mask.dtype != bool and not np.all(np.isin(real_array("mask", mask, ndim=None), (0.0, 1.0))):
            raise EloInputError("mask: holds values other than 0 and 1 (True = no height); give bools")
        mask = mask.astype(bool)
        if mask.shape != height.shape:
            raise EloInputError(f"mask shape {mask.shape} differs from the height map's {height.shape}")
    if not np.all(np.isfinite(height[~mask])):
        raise EloInputError(f"{path}: height holds NaN or Inf at trusted pixels; refusing to write it")
    stored = np.where(mask, np.nan, height)
    meta = dict(metadata or {})
    if mask.any() or "mask" in meta:
        meta["mask"] = MASK_NOTE
    field = meta.get("field_mm")
    pixel = _pixel_of(path, field, height.shape, "metadata") if field is not None else None
    suffix = path.suffix.lower()
    if suffix == ".exr":
        from .exr import write_exr

        write_exr(path, {"height": np.where(mask, 0.0, height), "mask": mask.astype(np.float32)}, meta,
                  overwrite=overwrite)
    elif suffix == ".npy":
        atomic_write(path, lambda tmp: np.save(tmp, stored))
    elif suffix == ".gsf":
        if pixel is None:
            raise EloInputError(f"{path}: a GSF file needs the pixel size; the metadata has no field_mm")
        data = _gsf_bytes(path, stored, pixel, meta)
        atomic_write(path, lambda tmp: Path(tmp).write_bytes(data))
    else:
        import tifffile

        from .exr import metadata_json

        text = metadata_json(path, meta)
        extra = {} if pixel is None else {"resolution": (10.0 / pixel, 10.0 / pixel), "resolutionunit": "CENTIMETER"}
        atomic_write(path, lambda tmp: tifffile.imwrite(tmp, stored.astype(np.float32), description=text, **extra))
    return path


@contextlib.contextmanager
def quiet_tifffile():
    """Hold back tifffile's log lines while a TIFF is read: of a damaged file it logs each tag it
    cannot read (``<TiffTag.fromfile> raised TiffFileError(...)``) before it raises, and the
    refusal's one line already names the file and the damage."""
    import logging

    logger = logging.getLogger("tifffile")
    level = logger.level
    logger.setLevel(logging.CRITICAL + 1)
    try:
        yield
    finally:
        logger.setLevel(level)


def _gsf_bytes(path, stored, pixel_mm: float, meta: Mapping) -> bytes:
    """A Gwyddion Simple Field file of ``stored`` (mm, NaN = no height) in metres."""
    from .exr import metadata_json

    h, w = stored.shape
    fx, fy = w * pixel_mm, h * pixel_mm
    lines = [GSF_MAGIC, f"XRes = {w}", f"YRes = {h}",
             f"XReal = {fx * 1e-3!r}", f"YReal = {fy * 1e-3!r}",
             f"XOffset = {-fx / 2 * 1e-3!r}", f"YOffset = {-fy / 2 * 1e-3!r}",
             "XYUnits = m", "ZUnits = m", f"Title = {meta.get('quantity', 'height map')}",
             f"ELOMitsuba = {metadata_json(path, meta)}"]
    head = ("\n".join(line.replace("\n", " ").replace("\0", "") for line in lines) + "\n").encode("utf-8")
    head += b"\0" * (4 - len(head) % 4)  # one to four NUL bytes
    return head + (stored * 1e-3).astype("<f4").tobytes()


def _read_gsf(path) -> tuple[np.ndarray, dict]:
    """Heights (the file's ZUnits) and header fields of a GSF file."""
    raw = Path(path).read_bytes()
    if not raw.startswith((GSF_MAGIC + "\n").encode()):
        raise EloInputError(f"{path}: not a Gwyddion Simple Field file (no '{GSF_MAGIC}' line)")
    end = raw.find(b"\0")
    if end < 0:
        raise EloInputError(f"{path}: GSF header without its NUL padding")
    fields = {}
    for line in raw[len(GSF_MAGIC) + 1:end].decode("utf-8", "replace").splitlines():
        if "=" in line:
            k, v = line.split("=", 1)
            fields[k.strip()] = v.strip()
    try:
        w, h = int(fields["XRes"]), int(fields["YRes"])
    except (KeyError, ValueError):
        raise EloInputError(f"{path}: GSF header needs integer XRes and YRes") from None
    start = (end // 4 + 1) * 4
    if w < 1 or h < 1 or len(raw) - start != 4 * w * h:
        raise EloInputError(f"{path}: GSF data hold {len(raw) - start} bytes; XRes x YRes = {w} x {h} needs {4 * w * h}")
    return np.frombuffer(raw, "<f4", count=w * h, offset=start).reshape(h, w).astype(np.float64), fields


def read_heightmap(path, units: str | None = None, *, allow_nan: bool = False) -> HeightFile:
    """Read a height map with the pixel size its file records.

    The formats of :func:`write_height` (EXR: channel ``height``, NaN where ``mask`` is 1, field
    and units from the header;
    TIFF: the JSON header, else the resolution tags; GSF: XReal/XYUnits, heights by ZUnits), NPY and
    CSV (comma-separated; neither records a pixel size). ``units`` (``mm`` or ``um``) gives the
    heights' unit where the file records none (default mm); a file that records its unit refuses
    another. NaN heights (unmeasured pixels) are refused by :func:`validate_heightmap` unless
    ``allow_nan``.

    Parameters
    ----------
    path : str or Path
        A ``.exr``, ``.npy``, ``.tif``/``.tiff``, ``.gsf`` or ``.csv`` file.
    units : {"mm", "um"}, optional
        Unit of the heights where the file records none (default mm).
    allow_nan : bool
        Accept NaN heights (unmeasured pixels).

    Returns
    -------
    HeightFile
        ``height`` (float64, mm), ``pixel_size_mm`` (mm, or None) and ``pixel_source``.

    Raises
    ------
    EloInputError
        A missing or unreadable file, an unknown extension or unit, a unit other than the
        file's, a non-2-D array, or NaN heights without ``allow_nan``.

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> import numpy as np
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     path = write_height(Path(folder) / "h.exr", np.zeros((2, 3)), metadata={"field_mm": [3.0, 2.0]})
    ...     exr = read_heightmap(path)
    ...     np.save(Path(folder) / "h.npy", np.full((2, 3), 50.0))     # micrometres, no pixel size
    ...     npy = read_heightmap(Path(folder) / "h.npy", units="um")
    >>> exr.height.shape, exr.pixel_size_mm, exr.pixel_source
    ((2, 3), 1.0, 'EXR header')
    >>> npy.height.round(4).tolist()[0], npy.pixel_size_mm
    ([0.05, 0.05, 0.05], None)
    """
    path = Path(path)
    if units is not None and units not in HEIGHT_UNITS:
        raise EloInputError(f"--units {units!r} is not known; use one of {', '.join(HEIGHT_UNITS)}")
    if path.is_dir():  # named as a folder, not by its extension or as missing
        input_file(path, "height map")
    ext = path.suffix.lower()
    if ext not in HEIGHTMAP_EXTENSIONS:
        raise EloInputError(
            f"height map {str(path)!r} has extension {path.suffix or '(none)'!r}; "
            f"use one of {', '.join(HEIGHTMAP_EXTENSIONS)}"
        )
    input_file(path, "height map", missing=" does not exist")
    pixel, source, recorded = None, "", None  # recorded: the file's height unit as factor to mm
    try:
        if ext == ".npy":
            with open(path, "rb") as f:  # numpy reads a file without its magic as a pickle, and says so
                if f.read(6) != b"\x93NUMPY":
                    raise EloInputError(f"height map {str(path)!r} could not be read: not a NumPy .npy file (it does "
                                        "not start with the .npy magic number); save heights with numpy.save")
            data = np.load(path, allow_pickle=False)
        elif ext == ".exr":
            from .exr import read_exr

            channels, meta = read_exr(path)
            if "height" not in channels:
                raise EloInputError(f"height map {str(path)!r} has no channel 'height' (it has "
                                    f"{', '.join(sorted(channels)) or 'none'})")
            data = channels["height"]
            if "mask" in channels:  # no height there (0 stored)
                data = np.where(channels["mask"] > 0.5, np.nan, data)
            recorded = _header_units(path, meta)
            if meta.get("field_mm") is not None:
                pixel, source = _pixel_of(path, meta["field_mm"], data.shape, "header field_mm"), "EXR header"
        elif ext in (".tif", ".tiff"):
            import tifffile

            with quiet_tifffile(), tifffile.TiffFile(path) as tif:
                page = tif.pages[0]
                data = page.asarray()
                meta = _json_description(page)
                tags = {t.name: t.value for t in page.tags}
            if meta is not None:
                recorded = _header_units(path, meta)
            if meta is not None and meta.get("field_mm") is not None:
                shape = tuple(n for n in np.shape(data) if n != 1)
                pixel, source = _pixel_of(path, meta["field_mm"], shape, "header field_mm"), "TIFF header"
            else:
                pixel = _tiff_resolution(path, tags)
                source = "TIFF resolution tags" if pixel is not None else ""
        elif ext == ".gsf":
            data, fields = _read_gsf(path)
            z = fields.get("ZUnits", "")
            if z:
                if z not in _LENGTH_MM:
                    raise EloInputError(f"height map {str(path)!r}: ZUnits {z!r} is not a length")
                recorded = _LENGTH_MM[z]
            xy = fields.get("XYUnits", "")
            if "XReal" in fields and xy:
                if xy not in _LENGTH_MM:
                    raise EloInputError(f"height map {str(path)!r}: XYUnits {xy!r} is not a length")
                scale = _LENGTH_MM[xy]
                field = (float(fields["XReal"]) * scale, float(fields.get("YReal", fields["XReal"])) * scale)
                pixel, source = _pixel_of(path, field, data.shape, "GSF XReal/YReal"), "GSF header"
        else:
            if not path.read_text(errors="replace").strip():  # numpy would warn and return shape (0, 1)
                raise EloInputError(f"height map {str(path)!r} is empty (no numbers)")
            data = np.loadtxt(path, delimiter=",", dtype=float, ndmin=2)
            # 3 columns and at least 16 rows is taken for an x, y, z point list (a common profilometer
            # export): as a height grid it would be a strip 3 px wide and over 5 times longer, which
            # a surface scan hardly gives, while meshing a point list as one is silently wrong
            if data.shape[1] == 3 and data.shape[0] >= 16:
                raise EloInputError(f"height map {str(path)!r} has 3 columns and {data.shape[0]} rows: it looks like "
                                    "an x, y, z point list, not a height grid; mesh needs a grid of heights (rows = "
                                    "y, columns = x): resample the points onto one (a grid 3 px wide: save it as .npy)")
    except EloInputError:
        raise
    except Exception as exc:  # noqa: BLE001 - any reader failure is a bad file for the user
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise EloInputError(f"height map {str(path)!r} could not be read: {reason}") from exc
    if recorded is not None and units is not None and not math.isclose(recorded, HEIGHT_UNITS[units]):
        raise EloInputError(f"height map {str(path)!r} records its heights in {_unit_name(recorded)}; "
                            f"--units {units} contradicts it (leave it out)")
    factor = recorded if recorded is not None else HEIGHT_UNITS[units or "mm"]
    height = validate_heightmap(data, what=f"height map {str(path)!r}", allow_nan=allow_nan)
    return HeightFile(height * factor, pixel, source)


def _unit_name(factor_mm: float) -> str:
    return next((k for k, v in _LENGTH_MM.items() if math.isclose(v, factor_mm)), f"{factor_mm:g} mm")


def _header_units(path, meta) -> float | None:
    """The height unit a package header records ("units": "mm"), as factor to mm."""
    u = meta.get("units") if isinstance(meta, dict) else None
    if u is None:
        return None
    if u not in _LENGTH_MM:
        raise EloInputError(f"height map {str(path)!r}: header units {u!r} are not a length (not a height map?)")
    return _LENGTH_MM[u]


def _json_description(page) -> dict | None:
    """The package's JSON header of a TIFF page (its ImageDescription), or None."""
    text = page.description or ""
    try:
        meta = json.loads(text) if text.lstrip().startswith("{") else None
    except ValueError:
        return None
    return meta if isinstance(meta, dict) and ("field_mm" in meta or "quantity" in meta) else None


def _tiff_resolution(path, tags) -> float | None:
    """The square pixel pitch (mm) the TIFF resolution tags record, or None without a unit."""
    unit = int(tags.get("ResolutionUnit", 1))
    if unit not in _TIFF_UNIT_MM or "XResolution" not in tags:
        return None

    def per_unit(v):
        num, den = v if isinstance(v, tuple) else (v, 1)
        return num / den if den else 0.0

    rx, ry = per_unit(tags["XResolution"]), per_unit(tags.get("YResolution", tags["XResolution"]))
    if not (rx > 0 and ry > 0):
        return None
    px, py = _TIFF_UNIT_MM[unit] / rx, _TIFF_UNIT_MM[unit] / ry
    if not math.isclose(px, py, rel_tol=1e-6):
        raise EloInputError(f"{path}: resolution tags give pixels of {px:g} x {py:g} mm; only square pixels can be meshed")
    return px


def load_heightmap(path, units: str = "mm") -> np.ndarray:
    """The heights (float64 mm) of a height map file (:func:`read_heightmap`, without the pixel size).

    Parameters
    ----------
    path : str or Path
        A ``.npy``, ``.tif``/``.tiff``, ``.csv``, ``.exr`` or ``.gsf`` file.
    units : {"mm", "um"}
        Unit of the heights where the file records none.

    Returns
    -------
    ndarray (H, W)
        Heights in mm (float64).

    Raises
    ------
    EloInputError
        (one line) for a missing file, an unknown extension or units, an unreadable file, a
        non-2-D array or non-finite heights.

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> import numpy as np
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     np.savetxt(Path(folder) / "h.csv", [[0.0, 0.5], [1.0, 1.5]], delimiter=",")
    ...     height = load_heightmap(Path(folder) / "h.csv")
    >>> height.dtype, height.tolist()
    (dtype('float64'), [[0.0, 0.5], [1.0, 1.5]])
    """
    return read_heightmap(path, units).height


def validate_heightmap(height, what: str = "height map", *, allow_nan: bool = False) -> np.ndarray:
    """Return ``height`` as a float64 2-D array, or raise :class:`EloInputError` (NaN, the pixels
    without a height, are kept with ``allow_nan``; infinities never)."""
    arr = np.asarray(height)
    if arr.dtype.kind not in "fiu":  # a bool array is a mask, not heights
        raise EloInputError(f"{what} has dtype {arr.dtype}; heights must be real numbers (integer or floating point)")
    arr = arr.astype(np.float64, copy=False)
    if arr.ndim == 3 and 1 in (arr.shape[0], arr.shape[-1]):
        arr = arr.reshape([n for n in arr.shape if n != 1] or [1])  # single-channel TIFF/PNG
    if arr.ndim != 2:
        raise EloInputError(f"{what} has shape {arr.shape}; a height map must be a 2-D array (rows, columns)")
    if arr.shape[0] < 2 or arr.shape[1] < 2:
        raise EloInputError(f"{what} has shape {arr.shape}; it needs at least 2 rows and 2 columns")
    bad = np.isinf(arr) if allow_nan else ~np.isfinite(arr)
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise EloInputError(
            f"{what} has {int(bad.sum())} non-finite height(s) (first at row {i}, column {j}); "
            "fill or crop them before meshing"
        )
    return arr


def validate_pixel_size(pixel_size_mm) -> float:
    try:
        p = float(pixel_size_mm)
    except (TypeError, ValueError, OverflowError):
        raise EloInputError(f"pixel size {pixel_size_mm!r} is not a number; give it in mm (> 0)") from None
    if not math.isfinite(p) or p <= 0:
        raise EloInputError(f"pixel size {pixel_size_mm!r} mm must be a finite number > 0")
    if not is_length(p):
        # a PLY holds float32: 1e-300 mm pixels put every vertex at x = y = 0 without a word
        raise EloInputError(f"pixel size {pixel_size_mm!r} mm must be {LENGTH_RANGE}")
    return p


def pixel_centres(shape, pixel_size_mm) -> tuple[np.ndarray, np.ndarray]:
    """Scene coordinates (x of the columns, y of the rows) of the pixel centres of a map.

    ``x`` increases with the column index, ``y`` decreases with the row index (row 0 = +y edge);
    both are centred on 0.
    """
    h, w = int(shape[0]), int(shape[1])
    p = float(pixel_size_mm)
    return pixel_axes((h, w), (w * p, h * p))
