"""Target materials: compositions by weight fraction and their backscatter coefficients.

A :class:`Material` is built from a preset name (``"Ti-6Al-4V"``, ``"316L"``, ``"Inconel 718"``,
``"Cu"``, ``"Ti"``) or from any ``{symbol: weight_fraction}`` mapping; see :func:`get_material`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import Mapping

import numpy as np

from ..constants import COMPOSITION_SUM_TOL, ETA0_Z_RANGE
from ..errors import EloInputError
from .backscatter import eta0_element, eta_castaing

# Symbols of elements 1..92, index + 1 = Z.
_SYMBOLS = (
    "H He Li Be B C N O F Ne Na Mg Al Si P S Cl Ar K Ca Sc Ti V Cr Mn Fe Co Ni Cu Zn Ga Ge As Se "
    "Br Kr Rb Sr Y Zr Nb Mo Tc Ru Rh Pd Ag Cd In Sn Sb Te I Xe Cs Ba La Ce Pr Nd Pm Sm Eu Gd Tb Dy "
    "Ho Er Tm Yb Lu Hf Ta W Re Os Ir Pt Au Hg Tl Pb Bi Po At Rn Fr Ra Ac Th Pa U"
).split()
ATOMIC_NUMBER = {s: i + 1 for i, s in enumerate(_SYMBOLS)}

#: Nominal compositions (weight fractions) of the presets.
PRESETS: dict[str, dict[str, float]] = {
    # ASTM F136 / Grade 5 nominal (docs/paper-notes.md §5: Ti 0.90, Al 0.06, V 0.04)
    "Ti-6Al-4V": {"Ti": 0.90, "Al": 0.06, "V": 0.04},
    # 316L nominal (ASTM A240 mid-range; Fe balance)
    "316L": {"Fe": 0.655, "Cr": 0.17, "Ni": 0.12, "Mo": 0.025, "Mn": 0.02, "Si": 0.01},
    # Inconel 718 nominal (AMS 5662 mid-range; Fe balance)
    "Inconel 718": {
        "Ni": 0.525, "Cr": 0.19, "Fe": 0.1892, "Nb": 0.0513, "Mo": 0.0305, "Ti": 0.009, "Al": 0.005,
    },
    "Cu": {"Cu": 1.0},
    "Ti": {"Ti": 1.0},
}
_ALIASES = {
    "ti64": "Ti-6Al-4V", "ti6al4v": "Ti-6Al-4V", "ti-6al-4v": "Ti-6Al-4V",
    "316l": "316L", "ss316l": "316L", "steel": "316L",
    "in718": "Inconel 718", "inconel718": "Inconel 718", "inconel 718": "Inconel 718",
    "inconel-718": "Inconel 718",
    "cu": "Cu", "copper": "Cu", "ti": "Ti", "titanium": "Ti",
}


@dataclass(frozen=True)
class Material:
    """A target material: weight fractions of its elements.

    Attributes
    ----------
    name : str
        Preset name or a composition string.
    composition : dict
        ``{symbol: weight fraction}``, validated: known symbols, Z inside the range of Eq. 11,
        fractions in (0, 1] summing to 1 within 1e-6.
    note : str
        How the composition was obtained from the user's, if not as given (normalised).
    """

    name: str
    composition: Mapping[str, float] = field(default_factory=dict)
    note: str = ""

    def __post_init__(self):
        validate_composition(self.composition, self.name)

    @cached_property
    def element_eta0(self) -> np.ndarray:
        """eta0 of each constituent, Eq. 11, in the order of ``composition``."""
        return eta0_element([ATOMIC_NUMBER[s] for s in self.composition])

    @cached_property
    def fractions(self) -> np.ndarray:
        return np.array(list(self.composition.values()), dtype=float)

    @cached_property
    def eta0(self) -> float:
        """Weight-averaged eta0 by Castaing's Eq. 12."""
        return float(np.dot(self.fractions, self.element_eta0))

    def eta(self, theta):
        """eta(theta) by Eq. 10 applied element by element and summed by Eq. 12 (theta in rad)."""
        return eta_castaing(theta, self.fractions, self.element_eta0)

    def eta_deg(self, theta_deg):
        return self.eta(np.deg2rad(theta_deg))

    def describe(self) -> str:
        parts = ",".join(f"{s}:{c:g}" for s, c in self.composition.items())
        return f"{self.name} ({parts})" + (f"; {self.note}" if self.note else "")


def validate_composition(composition: Mapping[str, float], what: str = "composition",
                         tolerance: float = COMPOSITION_SUM_TOL) -> None:
    """Raise :class:`EloInputError` naming the first problem with a composition (its fractions
    must sum to 1 within ``tolerance``)."""
    if not composition:
        raise EloInputError(f"{what}: empty composition; give {{element: weight fraction}}")
    lo, hi = ETA0_Z_RANGE
    for sym, frac in composition.items():
        if sym not in ATOMIC_NUMBER:
            raise EloInputError(f"{what}: unknown element symbol {sym!r} (use e.g. 'Ti', 'Al', 'V')")
        z = ATOMIC_NUMBER[sym]
        if not lo <= z <= hi:
            raise EloInputError(
                f"{what}: element {sym} (Z={z}) is outside Z={lo}..{hi}, where Eq. 11 holds"
            )
        try:
            f = float(frac)
        except (TypeError, ValueError, OverflowError):
            raise EloInputError(f"{what}: fraction of {sym} is {frac!r}, not a number") from None
        if not (np.isfinite(f) and 0.0 < f <= 1.0):
            raise EloInputError(f"{what}: fraction of {sym} is {frac!r}; allowed is (0, 1]")
    total = float(sum(float(v) for v in composition.values()))
    if abs(total - 1.0) > tolerance:
        raise EloInputError(
            f"{what}: weight fractions sum to {total:.9g}, not 1 (tolerance {tolerance:g}; a measured composition "
            "within 1e-3 of 1 is normalised)"
        )


def parse_composition(text: str) -> dict[str, float]:
    """Parse ``"Ti:0.9,Al:0.06,V:0.04"`` (also ``=`` or spaces) into a dict, validated."""
    comp: dict[str, float] = {}
    for item in text.replace(";", ",").split(","):
        item = item.strip()
        if not item:
            continue
        for sep in (":", "="):
            if sep in item:
                sym, val = (p.strip() for p in item.split(sep, 1))
                break
        else:
            raise EloInputError(
                f"composition {text!r}: item {item!r} is not 'Symbol:fraction' (e.g. 'Ti:0.9,Al:0.1')"
            )
        if sym in comp:
            raise EloInputError(f"composition {text!r}: element {sym} given twice")
        try:
            comp[sym] = float(val)
        except ValueError:
            raise EloInputError(f"composition {text!r}: fraction {val!r} of {sym} is not a number") from None
    from ..constants import MEASURED_COMPOSITION_TOL

    validate_composition(comp, f"composition {text!r}", MEASURED_COMPOSITION_TOL)  # normalised by get_material
    return comp


def _measured(name: str, composition: dict) -> Material:
    """A user's composition; one that misses a sum of 1 by at most MEASURED_COMPOSITION_TOL
    (rounded analysis values) is normalised, with a note saying so."""
    from ..constants import MEASURED_COMPOSITION_TOL

    try:
        total = float(sum(float(v) for v in composition.values()))
    except (TypeError, ValueError, OverflowError):
        total = math.nan  # validate_composition names the bad fraction
    if math.isfinite(total) and COMPOSITION_SUM_TOL < abs(total - 1.0) <= MEASURED_COMPOSITION_TOL:
        scaled = {s: float(v) / total for s, v in composition.items()}
        return Material(name, scaled, note=f"fractions summed to {total:.6g}; normalised to 1")
    return Material(name, composition)  # validated there: a real mismatch is refused


def get_material(spec: "str | Mapping[str, float] | Material | None" = None) -> Material:
    """Return a :class:`Material` from a preset name, a composition string or mapping.

    ``None`` gives the default Ti-6Al-4V. Preset names are matched case-insensitively
    (``"ti64"``, ``"steel"`` = 316L, ``"in718"`` ...). A string with ``:`` is a composition.

    Parameters
    ----------
    spec : str, mapping, Material or None
        A preset name, a composition string (``"Fe:0.7,Cr:0.3"``, weight fractions) or a mapping
        ``{symbol: weight fraction}``; fractions summing to 1 within the measured tolerance are
        normalised (noted in ``note``).

    Returns
    -------
    Material

    Raises
    ------
    EloInputError
        An unknown preset, or an invalid composition.

    Examples
    --------
    >>> m = get_material()
    >>> m.describe(), round(m.eta0, 4)
    ('Ti-6Al-4V (Ti:0.9,Al:0.06,V:0.04)', 0.2402)
    >>> get_material("steel").name
    '316L'
    >>> round(get_material("Fe:0.7,Cr:0.3").eta0, 4)
    0.2745
    >>> round(float(get_material({"Ti": 1.0}).eta(0.5)), 4)     # theta = 0.5 rad
    0.2873
    """
    from ..constants import DEFAULT_MATERIAL

    if spec is None:
        spec = DEFAULT_MATERIAL
    if isinstance(spec, Material):
        return spec
    if isinstance(spec, Mapping):
        return _measured("custom", dict(spec))
    if not isinstance(spec, str):
        raise EloInputError(f"material {spec!r}: expected a preset name or a composition")
    if spec in PRESETS:
        return Material(spec, PRESETS[spec])
    key = spec.strip().lower()
    if key in _ALIASES:
        name = _ALIASES[key]
        return Material(name, PRESETS[name])
    if ":" in spec or "=" in spec:
        return _measured(spec, parse_composition(spec))
    raise EloInputError(
        f"unknown material {spec!r}; presets are {', '.join(PRESETS)}, or give a composition "
        "such as 'Ti:0.9,Al:0.06,V:0.04'"
    )
