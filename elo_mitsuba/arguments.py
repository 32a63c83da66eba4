"""Checks of the Python API's arguments: each returns the value as used, or raises
:class:`~elo_mitsuba.errors.EloInputError` with one line naming the argument, its value and what is
allowed (the command line's own types are in ``cli/_args.py``)."""

from __future__ import annotations

import math

from .errors import EloInputError


def shown(value, limit: int = 80) -> str:
    """``repr(value)`` on one line and at most ``limit`` characters (an array's repr spans lines).

    Examples
    --------
    >>> import numpy as np
    >>> shown(np.zeros((2, 2)))
    'array([[0., 0.], [0., 0.]])'
    >>> len(shown(10 ** 400))
    80
    """
    text = " ".join(repr(value).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def whole_number(name: str, value, lo: int, hi: int | None) -> int:
    """``value`` as an int in [lo, hi] (a whole float such as 4.0 is taken; text, bools and
    numbers beyond float are not).

    Examples
    --------
    >>> whole_number("spp", 4.0, 1, None)
    4
    >>> whole_number("spp", "4", 1, None)
    Traceback (most recent call last):
    ...
    elo_mitsuba.errors.EloInputError: spp='4'; must be a whole number >= 1
    """
    try:
        number = float(value)
        ok = (math.isfinite(number) and number == int(number) and not isinstance(value, (bool, str, bytes))
              and type(value).__name__ != "bool_")
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok or int(number) < lo or (hi is not None and int(number) > hi):
        bound = f">= {lo}" if hi is None else f"in [{lo}, {hi}]"
        raise EloInputError(f"{name}={shown(value)}; must be a whole number {bound}")
    return int(number)


def flag(name: str, value, *, none: bool = False) -> bool | None:
    """``value`` if it is True or False (or None with ``none``): any other value would read as
    True (``force="no"`` would start a render the time check refused).

    Examples
    --------
    >>> flag("force", False)
    False
    >>> flag("force", "no")
    Traceback (most recent call last):
    ...
    elo_mitsuba.errors.EloInputError: force='no'; must be True or False
    """
    if value is None and none:
        return None
    if isinstance(value, bool) or type(value).__name__ == "bool_":
        return bool(value)
    raise EloInputError(f"{name}={shown(value)}; must be True or False" + (" (or None)" if none else ""))


def fraction(name: str, value, lo: float = 0.0, hi: float = 1.0) -> float:
    """``value`` as a real number in [lo, hi) (a threshold given as a share: NaN would mask
    every pixel, a negative one none).

    Examples
    --------
    >>> fraction("min_sum", 0.05)
    0.05
    >>> fraction("min_sum", float("nan"))
    Traceback (most recent call last):
    ...
    elo_mitsuba.errors.EloInputError: min_sum=nan; must be a number in [0, 1)
    """
    try:
        number = float(value)
        ok = not isinstance(value, (bool, str, bytes)) and lo <= number < hi
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok:
        raise EloInputError(f"{name}={shown(value)}; must be a number in [{lo:g}, {hi:g})")
    return number


def length(what: str, value) -> float:
    """``value`` as a finite length > 0 (mm); text and bools are refused, though float() takes them.

    Examples
    --------
    >>> length("radius", 25)
    25.0
    >>> length("detector 'right': radius", True)
    Traceback (most recent call last):
    ...
    elo_mitsuba.errors.EloInputError: detector 'right': radius True; need a finite number of mm > 0
    """
    try:
        number = float(value) if not isinstance(value, (bool, str, bytes)) else math.nan
    except (TypeError, ValueError, OverflowError):
        number = math.nan
    if not (math.isfinite(number) and number > 0) or type(value).__name__ == "bool_":
        raise EloInputError(f"{what} {shown(value)}; need a finite number of mm > 0")
    return number


def vector3(what: str, value, limit: float | None = None):
    """Three finite numbers (mm) as a float64 array, or one line naming ``what`` and the value;
    with ``limit``, each within +-limit.

    Examples
    --------
    >>> vector3("centre", (127, 0, 272)).tolist()
    [127.0, 0.0, 272.0]
    >>> vector3("detector 'right': centre", (1, 2))
    Traceback (most recent call last):
    ...
    elo_mitsuba.errors.EloInputError: detector 'right': centre (1, 2); need 3 finite numbers (x, y, z)
    """
    import numpy as np

    try:  # True is not 1 mm, nor "127" 127 mm
        raw = np.asarray(value)
        words = raw.dtype.kind in "bUS" or (isinstance(value, (list, tuple))
                                            and any(isinstance(x, (bool, np.bool_, str)) for x in value))
        v = np.array([np.nan]) if words else raw.astype(float).reshape(-1)
    except (TypeError, ValueError, OverflowError):
        v = np.array([np.nan])
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise EloInputError(f"{what} {shown(value)}; need 3 finite numbers (x, y, z)")
    if limit is not None and np.abs(v).max() > limit:
        raise EloInputError(f"{what} {shown(value)}; need 3 numbers (x, y, z) within +-{limit:g} mm")
    return v


def real_array(name: str, value, ndim: int | None = 2, *, shape=None):
    """``value`` as a float64 array of real numbers, ``ndim``-dimensional (and of ``shape``, when
    given), not empty. Complex numbers (whose imaginary part numpy would drop), bools, dates, text
    and objects are refused, not converted. NaN and Inf pass: callers that mask them say so.

    Examples
    --------
    >>> real_array("dzdx", [[0, 1], [2, 3]]).dtype
    dtype('float64')
    >>> real_array("image", [[1j, 0]])
    Traceback (most recent call last):
    ...
    elo_mitsuba.errors.EloInputError: image: an array of complex numbers; need real numbers
    >>> real_array("heights", [[0.0, 1.0]], shape=(2, 2))
    Traceback (most recent call last):
    ...
    elo_mitsuba.errors.EloInputError: heights: shape (1, 2); need (2, 2)
    """
    import numpy as np

    try:
        raw = np.asarray(value)
    except (TypeError, ValueError, OverflowError) as exc:
        raise EloInputError(f"{name}: {shown(value)} is not an array of numbers ({exc})") from None
    if raw.dtype.kind not in "iuf":
        kind = {"c": "complex numbers", "b": "bools", "M": "dates", "m": "time spans", "U": "text", "S": "text",
                "O": "Python objects"}.get(raw.dtype.kind, f"dtype {raw.dtype}")
        if raw.dtype.kind == "O":
            try:  # a list of arrays or numbers is fine
                raw = raw.astype(float)
            except (TypeError, ValueError, OverflowError):
                raise EloInputError(f"{name}: an array of {kind}; need real numbers") from None
        else:
            raise EloInputError(f"{name}: an array of {kind}; need real numbers")
    out = raw.astype(np.float64)
    if ndim is not None and out.ndim != ndim:
        raise EloInputError(f"{name}: {out.ndim}-D array of shape {out.shape}; need a {ndim}-D array")
    if shape is not None and out.shape != tuple(shape):
        raise EloInputError(f"{name}: shape {out.shape}; need {tuple(shape)}")
    if out.size == 0:
        raise EloInputError(f"{name}: an empty array (shape {out.shape})")
    return out


def input_file(path, what: str = "", missing: str = ": no such file"):
    """``path`` as a :class:`~pathlib.Path` of an existing file to read: a folder is named as one
    (it was reported as "no such file" or by its extension), a missing path by ``missing`` (appended
    to ``what`` and the path).

    Examples
    --------
    >>> import tempfile
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     input_file(folder, "calibration")
    Traceback (most recent call last):
    ...
    elo_mitsuba.errors.EloInputError: calibration ... is a folder; give a file
    """
    from pathlib import Path

    p = Path(path)
    label = f"{what} {p}" if what else str(p)
    if p.is_dir():
        raise EloInputError(f"{label} is a folder; give a file")
    if not p.is_file():
        raise EloInputError(label + missing)
    return p
