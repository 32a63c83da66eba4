"""The image orientation and the scan grid: the one definition, used by every module.

Every image of the package (detector channels, EXR, PNG, gradients, height maps, meshes built
from height maps) is the build plate **seen from above with +y up**: array row 0 is the +y edge
of the scan field, columns run towards +x. Pixel (column i, row j) of an image of shape (H, W)
covering ``field = (field_x, field_y)`` mm is centred at

    x = -field_x/2 + (i + 1/2) field_x / W,    y = +field_y/2 - (j + 1/2) field_y / H   [mm],

so the field is centred on the z-axis. A scalar field is the width: field_y = field H / W (square
pixels), for the beam and for the images alike. The scanned beam (sensor ``elo_beam``) aims film
pixel (i, j) at this point (:func:`film_to_plane`) plus an offset below 1 % of a pixel and 3 um
that keeps beam rays off mesh edges (recorded in every header as ``beam_aim_offset_mm``);
:func:`pixel_axes` gives the same points for numpy images. Both are this one map, written once for Dr.Jit film coordinates and once for numpy
index grids; ``tests/test_grid.py`` holds them to each other.
"""

from __future__ import annotations

import numpy as np

from .errors import EloInputError

#: The orientation in words, stored in every output header.
ORIENTATION = "row 0 = +y edge, columns towards +x (plate seen from above, +y up)"


def field_xy(field_mm, shape=None) -> tuple[float, float]:
    """Return ``(field_x, field_y)`` in mm from a pair, or from a scalar width: with the image
    ``shape`` (H, W) the field is then ``(field, field H / W)`` (square pixels, as the beam
    scans), without it square. Validated > 0.

    Parameters
    ----------
    field_mm : float or (float, float)
        Scan field in mm: width, or (width x, height y).
    shape : (int, int), optional
        Image shape (H, W), for a scalar field.

    Returns
    -------
    (float, float)
        ``(field_x, field_y)`` in mm.

    Raises
    ------
    EloInputError
        A field that is not finite and > 0.

    Examples
    --------
    >>> field_xy(80)
    (80.0, 80.0)
    >>> field_xy(80, shape=(32, 64))           # H = 32 rows, W = 64 columns
    (80.0, 40.0)
    >>> field_xy((80, 60))
    (80.0, 60.0)
    """
    try:  # text and bools are not lengths, though numpy would convert them
        raw = np.asarray(field_mm)
        arr = np.atleast_1d(raw.astype(float)).ravel() if raw.dtype.kind in "iufO" else np.array([np.nan])
    except (TypeError, ValueError, OverflowError):
        arr = np.array([np.nan])
    if arr.size == 1:
        arr = np.array([arr[0], arr[0] if shape is None else arr[0] * shape_hw(shape)[0] / shape_hw(shape)[1]])
    if arr.size != 2 or not np.all(np.isfinite(arr)) or np.any(arr <= 0):
        raise EloInputError(f"field_mm={field_mm!r}: give one or two finite lengths > 0 in mm")
    return float(arr[0]), float(arr[1])


def shape_hw(shape) -> tuple[int, int]:
    """``(H, W)`` of an image shape (extra trailing dimensions ignored), validated >= 1."""
    shape = tuple(int(s) for s in shape)
    if len(shape) < 2 or shape[0] < 1 or shape[1] < 1:
        raise EloInputError(f"image shape {shape}: expected (H, W) with H, W >= 1")
    return shape[0], shape[1]


def pixel_size(shape, field_mm) -> tuple[float, float]:
    """Pixel pitch ``(dx, dy)`` in mm of an image of ``shape`` (H, W) covering ``field_mm``.

    Parameters
    ----------
    shape : tuple of int
        Image shape (H, W).
    field_mm : float or (float, float)
        Scan field in mm; a scalar is the width (square pixels).

    Returns
    -------
    (float, float)
        ``(dx, dy)`` in mm.

    Examples
    --------
    >>> pixel_size((4, 8), 80.0)
    (10.0, 10.0)
    >>> pixel_size((4, 8), (80.0, 20.0))
    (10.0, 5.0)
    """
    h, w = shape_hw(shape)
    fx, fy = field_xy(field_mm, shape)
    return fx / w, fy / h


def pixel_axes(shape, field_mm) -> tuple[np.ndarray, np.ndarray]:
    """Coordinates (mm) of the pixel-centre columns and rows of an image.

    Parameters
    ----------
    shape : tuple of int
        Image shape (H, W) (extra trailing dimensions are ignored).
    field_mm : float or (float, float)
        Scan field width (x) and height (y) in mm; a scalar is the width (square pixels).

    Returns
    -------
    xs : ndarray, shape (W,)
        x of each column, growing with the column index, centred on 0.
    ys : ndarray, shape (H,)
        y of each row, *decreasing* with the row index (row 0 is the +y edge), centred on 0.

    Examples
    --------
    >>> xs, ys = pixel_axes((2, 4), 80.0)
    >>> xs.tolist(), ys.tolist()
    ([-30.0, -10.0, 10.0, 30.0], [10.0, -10.0])
    """
    h, w = shape_hw(shape)
    fx, fy = field_xy(field_mm, shape)
    xs = -fx / 2 + (np.arange(w) + 0.5) * (fx / w)
    ys = fy / 2 - (np.arange(h) + 0.5) * (fy / h)
    return xs, ys


def pixel_coordinates(shape, field_mm) -> tuple[np.ndarray, np.ndarray]:
    """The 2-D grids ``(x, y)`` (each of shape (H, W)) of :func:`pixel_axes` (same parameters).

    Parameters
    ----------
    shape : tuple of int
        Image shape (H, W).
    field_mm : float or (float, float)
        Scan field in mm; a scalar is the width (square pixels).

    Returns
    -------
    x, y : ndarray (H, W)
        Position of each pixel centre in mm (row 0 = +y edge).

    Examples
    --------
    >>> x, y = pixel_coordinates((2, 4), 80.0)
    >>> x.shape, x[0].tolist(), y[:, 0].tolist()
    ((2, 4), [-30.0, -10.0, 10.0, 30.0], [10.0, -10.0])
    """
    return tuple(np.meshgrid(*pixel_axes(shape, field_mm)))


def at_pixel_centres(image, field_mm, aim_offset_mm) -> np.ndarray:
    """An image as the beam would record it landing on the pixel centres themselves.

    The beam lands at the pixel centres plus ``aim_offset_mm`` (header ``beam_aim_offset_mm``, a few
    um). A model evaluated at the centres, or a symmetry that maps centres onto centres (the four
    detectors of a flat plate are rotations of each other about z, but the nudged landing points
    are not), needs the image at the centres: here to first order in the offset, with the image's
    own gradient. The second order is below 1e-9 of the signal on the flat plate; across an edge
    of the relief, where the image changes within the offset, it is not small.

    Parameters
    ----------
    image : ndarray (H, W)
        Package orientation (row 0 at +y).
    field_mm : float or (float, float)
        Scan field (mm).
    aim_offset_mm : (float, float)
        The landing points less the pixel centres (mm), x and y.

    Returns
    -------
    ndarray (H, W), float64

    Examples
    --------
    >>> x, y = pixel_coordinates((8, 8), 80.0)
    >>> seen = 1.0 + 0.01 * (x + 0.003) - 0.02 * (y + 0.002)   # a linear signal at the nudged points
    >>> bool(np.allclose(at_pixel_centres(seen, 80.0, (0.003, 0.002)), 1.0 + 0.01 * x - 0.02 * y, rtol=0, atol=1e-14))
    True
    """
    image = np.asarray(image, float)
    dx, dy = (float(v) for v in aim_offset_mm)
    xs, ys = pixel_axes(image.shape, field_mm)
    d_dy, d_dx = np.gradient(image, ys, xs)  # ys run towards -y (row 0 at +y): the axes carry the sign
    return image - dx * d_dx - dy * d_dy


def film_to_plane(u, v, field_x, field_y):
    """Build-plane point ``(x, y)`` (mm) of film coordinates ``(u, v)`` in [0, 1]^2.

    ``u`` runs along the columns (towards +x), ``v`` down the rows (towards -y); a pixel centre
    (u = (i + 1/2)/W, v = (j + 1/2)/H) maps to the point of :func:`pixel_axes`. Works on numpy
    and Dr.Jit arrays alike (the sensor calls it on its film samples).
    """
    return (u - 0.5) * field_x, (0.5 - v) * field_y
