"""Backscatter coefficients (paper Sec. 2.1.2, Eqs. 10-12).

Pure numpy functions. Angles ``theta`` are in **radians** unless the name ends in ``_deg``;
``theta`` is the angle between the surface normal and the reversed beam direction (docs/paper-notes.md §4).
"""

from __future__ import annotations

import numpy as np

from ..constants import DARLINGTON_B, ETA0_POLYNOMIAL, ETA0_Z_RANGE
from ..errors import EloInputError


def eta0_element(z):
    """Backscatter coefficient at normal incidence of a pure element, Eq. 11.

    eta0(Z) = -0.0254 + 0.016 Z - 1.86e-4 Z^2 + 8.3e-7 Z^3.

    Parameters
    ----------
    z : int or array_like
        Atomic number(s); must lie in ``ETA0_Z_RANGE`` (6..79), the range of the data Eq. 11 fits.

    Returns
    -------
    float or ndarray
        eta0 (fraction of the beam's electrons backscattered at normal incidence).

    Raises
    ------
    EloInputError
        If any Z lies outside that range.

    Examples
    --------
    >>> round(float(eta0_element(22)), 4)           # titanium
    0.2454
    >>> eta0_element([26, 28]).round(4).tolist()     # iron, nickel
    [0.2795, 0.295]
    """
    z_arr = np.asarray(z, dtype=float)
    lo, hi = ETA0_Z_RANGE
    bad = (z_arr < lo) | (z_arr > hi)
    if np.any(bad):
        raise EloInputError(
            f"atomic number Z={np.atleast_1d(z_arr)[np.atleast_1d(bad)][0]:g} is outside "
            f"{lo}..{hi}, the range where Eq. 11 (eta0 of Z) is fitted"
        )
    a0, a1, a2, a3 = ETA0_POLYNOMIAL
    return a0 + z_arr * (a1 + z_arr * (a2 + z_arr * a3))


def eta_darlington(theta, eta0, b=DARLINGTON_B):
    """Backscatter coefficient at incidence angle ``theta`` (rad) of a pure element, Eq. 10.

    eta(theta) = B (eta0 / B)^cos(theta), B = 0.89. eta(0) = eta0, eta(pi/2) = B.
    ``cos(theta)`` is clipped to [0, 1] so that grazing and below-horizon angles give B.

    Parameters
    ----------
    theta : array_like
        Incidence angle(s) in radians.
    eta0 : float or array_like
        eta at normal incidence (Eq. 11).
    b : float
        The limit at grazing incidence (0.89).

    Returns
    -------
    ndarray
        eta(theta) (fraction of the beam's electrons backscattered).

    Examples
    --------
    >>> import numpy as np
    >>> eta_darlington([0.0, np.pi / 3, np.pi / 2], 0.25).round(4).tolist()
    [0.25, 0.4717, 0.89]
    """
    cos_t = np.clip(np.cos(np.asarray(theta, dtype=float)), 0.0, 1.0)
    return b * np.power(np.asarray(eta0, dtype=float) / b, cos_t)


def eta_castaing(theta, fractions, eta0s, b=DARLINGTON_B):
    """Backscatter coefficient of a multicomponent target, Castaing's Eq. 12 applied to Eq. 10.

    eta(theta) = sum_i c_i B (eta0_i / B)^cos(theta), element by element (docs/paper-notes.md §5).

    Parameters
    ----------
    theta : array_like
        Incidence angle(s) in radians.
    fractions, eta0s : sequence of float
        Weight fractions c_i and the elements' eta0_i (Eq. 11).
    b : float
        The limit at grazing incidence (0.89).

    Returns
    -------
    ndarray
        eta(theta), the shape of ``theta``.

    Examples
    --------
    >>> import numpy as np
    >>> eta0s = eta0_element([22, 13, 23])              # Ti, Al, V
    >>> eta = eta_castaing([0.0, np.pi / 2], [0.9, 0.06, 0.04], eta0s)
    >>> eta.round(4).tolist()
    [0.2402, 0.89]
    """
    theta = np.asarray(theta, dtype=float)
    out = np.zeros(np.shape(theta))
    for c, e0 in zip(fractions, eta0s):
        out = out + c * eta_darlington(theta, e0, b)
    return out
