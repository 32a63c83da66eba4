"""The physics of the model as pure numpy functions (paper Sec. 2.1, Eqs. 10-14).

Nothing here needs Mitsuba: analysis code and tests use it directly. The Mitsuba plugins build
on the same constants and tables; the Dr.Jit forms of g_BSE live in the ``elo_bse`` BSDF
(:mod:`elo_mitsuba.plugins.bsdf_elo_bse`).
"""

from .backscatter import eta0_element, eta_castaing, eta_darlington
from .materials import ATOMIC_NUMBER, PRESETS, Material, get_material, parse_composition
from .scattering import (
    g_bse,
    g_bse_local,
    lobe_exponent,
    lobe_normalisation,
    lobe_normalisation_eq14_repaired,
    lobe_normalisation_table,
)
from .solid_angle import triangle_solid_angle, vos_denominator

__all__ = [
    "ATOMIC_NUMBER", "PRESETS", "Material", "eta0_element", "eta_castaing", "eta_darlington",
    "g_bse", "g_bse_local", "get_material", "lobe_exponent", "lobe_normalisation",
    "lobe_normalisation_eq14_repaired", "lobe_normalisation_table", "parse_composition",
    "triangle_solid_angle", "vos_denominator",
]
