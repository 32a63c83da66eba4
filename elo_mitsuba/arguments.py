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


def vector3(what: str, value):
    """Three finite numbers (mm) as a float64 array, or one line naming ``what`` and the value.

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

    try:
        v = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError, OverflowError):
        v = np.array([np.nan])
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise EloInputError(f"{what} {shown(value)}; need 3 finite numbers (x, y, z)")
    return v
