"""Height maps: reading, validating and pixel positions (millimetres).

A height map is a 2-D array ``height[i, j]`` in millimetres in the package's image orientation
(:mod:`elo_mitsuba.grid`: row 0 is the +y edge, columns run towards +x), centred on the z-axis.
:mod:`elo_mitsuba.mesh` turns one into a triangle mesh.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .errors import EloInputError
from .grid import pixel_axes

#: File name extensions :func:`load_heightmap` reads.
HEIGHTMAP_EXTENSIONS = (".npy", ".tif", ".tiff", ".csv")
#: Units :func:`load_heightmap` accepts for heights, as factor to millimetres.
HEIGHT_UNITS = {"mm": 1.0, "um": 1e-3}


def load_heightmap(path, units: str = "mm") -> np.ndarray:
    """Read a height map (.npy, .tif/.tiff, .csv with comma separators) as float64 millimetres.

    Raises :class:`EloInputError` (one line) for a missing file, an unknown extension or units, an
    unreadable file, a non-2-D array or non-finite heights.
    """
    path = Path(path)
    if units not in HEIGHT_UNITS:
        raise EloInputError(f"--units {units!r} is not known; use one of {', '.join(HEIGHT_UNITS)}")
    ext = path.suffix.lower()
    if ext not in HEIGHTMAP_EXTENSIONS:
        raise EloInputError(
            f"height map {str(path)!r} has extension {path.suffix or '(none)'!r}; "
            f"use one of {', '.join(HEIGHTMAP_EXTENSIONS)}"
        )
    if not path.is_file():
        raise EloInputError(f"height map {str(path)!r} does not exist")
    try:
        if ext == ".npy":
            data = np.load(path, allow_pickle=False)
        elif ext in (".tif", ".tiff"):
            import tifffile

            data = tifffile.imread(path)
        else:
            if not path.read_text(errors="replace").strip():  # numpy would warn and return shape (0, 1)
                raise EloInputError(f"height map {str(path)!r} is empty (no numbers)")
            data = np.loadtxt(path, delimiter=",", dtype=float, ndmin=2)
    except EloInputError:
        raise
    except Exception as exc:  # noqa: BLE001 - any reader failure is a bad file for the user
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise EloInputError(f"height map {str(path)!r} could not be read: {reason}") from exc
    height = validate_heightmap(data, what=f"height map {str(path)!r}")
    return height * HEIGHT_UNITS[units]


def validate_heightmap(height, what: str = "height map") -> np.ndarray:
    """Return ``height`` as a float64 2-D array, or raise :class:`EloInputError`."""
    arr = np.asarray(height)
    if arr.dtype.kind not in "fiub":
        raise EloInputError(f"{what} has dtype {arr.dtype}; heights must be real numbers")
    arr = arr.astype(np.float64, copy=False)
    if arr.ndim == 3 and 1 in (arr.shape[0], arr.shape[-1]):
        arr = arr.reshape([n for n in arr.shape if n != 1] or [1])  # single-channel TIFF/PNG
    if arr.ndim != 2:
        raise EloInputError(f"{what} has shape {arr.shape}; a height map must be a 2-D array (rows, columns)")
    if arr.shape[0] < 2 or arr.shape[1] < 2:
        raise EloInputError(f"{what} has shape {arr.shape}; it needs at least 2 rows and 2 columns")
    bad = ~np.isfinite(arr)
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
    except (TypeError, ValueError):
        raise EloInputError(f"pixel size {pixel_size_mm!r} is not a number; give it in mm (> 0)") from None
    if not math.isfinite(p) or p <= 0:
        raise EloInputError(f"pixel size {pixel_size_mm!r} mm must be a finite number > 0")
    return p


def pixel_centres(shape, pixel_size_mm) -> tuple[np.ndarray, np.ndarray]:
    """Scene coordinates (x of the columns, y of the rows) of the pixel centres of a map.

    ``x`` increases with the column index, ``y`` decreases with the row index (row 0 = +y edge);
    both are centred on 0.
    """
    h, w = int(shape[0]), int(shape[1])
    p = float(pixel_size_mm)
    return pixel_axes((h, w), (w * p, h * p))
