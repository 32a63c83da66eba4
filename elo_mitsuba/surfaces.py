"""What a loaded scene's scattering surfaces (shapes with an ``elo_bse`` BSDF) are, as output
headers record it: each shape's material, its g_BSE lobe, and what was done to a user's material."""

from __future__ import annotations


def _elo_shapes(scene):
    """[(name, bsdf)] of the shapes with an ``elo_bse`` BSDF (unnamed ones as ``shape<k>``)."""
    out = []
    for shape in scene.shapes():
        bsdf = shape.bsdf()
        if getattr(bsdf, "material", None) is not None:
            out.append((shape.id() or f"shape{len(out)}", bsdf))
    return out


def materials(scene) -> dict[str, str]:
    """``{shape id: material}`` (header ``materials``)."""
    return {name: bsdf.material.describe() for name, bsdf in _elo_shapes(scene)}


def scattering(scene) -> dict[str, dict]:
    """``{shape id: {"lobe": bool, "lobe_width_deg": float}}`` (header ``scattering``): the analysis
    models the paper's lobe and says so when these differ (:func:`~elo_mitsuba.schema.scattering_note`)."""
    return {name: {"lobe": bool(bsdf.lobe), "lobe_width_deg": float(bsdf.lobe_width[0])}
            for name, bsdf in _elo_shapes(scene)}


def material_notes(scene) -> list[str]:
    """What was done to a user's material (a measured composition normalised), per shape."""
    return [f"material of {name!r}: {bsdf.material.note}" for name, bsdf in _elo_shapes(scene)
            if getattr(bsdf.material, "note", "")]
