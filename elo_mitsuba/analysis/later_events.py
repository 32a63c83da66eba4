"""The later events (2nd and more) of a reconstructed surface, by rendering it in the chamber.

The inversion (:mod:`.inversion`) holds the events >= 2 fixed. For a chamber, whose walls and
heat shields send electrons back, they depend on the object only weakly but not negligibly: on the
melt plate in the ATHENE chamber (validation row I5) the flat plate's 2nd event in place of the
object's leaves the height error where the model gradient has it, the object's own halves it. This
module renders the current estimate of the surface in the chamber (the forward model itself, not a
second physics) and returns its events >= 2 per detector, in the units of the images (N_d/N_0).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from ..constants import DETECTOR_NAMES
from ..error_estimate import later_events_error
from ..errors import EloInputError
from ..grid import pixel_size

#: The surface is extended by a flat margin to this half-width (mm): the chamber floor's opening
#: around the object is +-100 mm, and electrons that leave there towards the floor are lost alike.
PAD_HALF_MM = 100.0


def later_events(heights, geometry, *, fwhm_mm: float = 0.0, events: int = 2, quality: str = "reference",
                 seed: int = 0, with_errors: bool = False):
    """Events >= 2 per detector (H, W) of the surface ``heights`` (mm, scan grid) in the ATHENE-like
    chamber, rendered with the detectors and beam of ``geometry``.

    The heights are meshed at the scan pitch (square pixels) with a flat margin at their border
    median out to :data:`PAD_HALF_MM`; the beam lands where it aims (the perspective shrink of the
    landing points, h / wd < 1e-3, is below what the 2nd event resolves).
    """
    import elo_mitsuba as em

    from ..mesh import heightmap_to_mesh, write_mesh
    from ..scene_files import write_scene

    h = np.asarray(heights, float)
    shape = h.shape
    if shape != tuple(geometry.shape):
        raise EloInputError(f"heights are {shape[1]}x{shape[0]} px, the scan {geometry.shape[1]}x{geometry.shape[0]}")
    if int(events) < 2:
        raise EloInputError(f"events={events!r}: later events need events >= 2")
    dx, dy = pixel_size(shape, geometry.field_mm)
    if not np.isclose(dx, dy, rtol=1e-6):
        raise EloInputError(f"pixels of {dx:g} x {dy:g} mm: meshing the heights needs square pixels")
    pad = max(0, int(np.ceil((PAD_HALF_MM - 0.5 * max(geometry.field_mm)) / dx)))
    border = np.concatenate([h[0], h[-1], h[:, 0], h[:, -1]])
    padded = np.pad(h, pad, mode="constant", constant_values=float(np.median(border)))
    with tempfile.TemporaryDirectory() as d:
        mesh = Path(d) / "surface.ply"
        write_mesh(heightmap_to_mesh(padded, dx, tolerance_mm=1e-6), mesh)
        scene = write_scene(Path(d) / "surface.xml", mesh, material=geometry.material, chamber=True)
        s = em.load_scene(scene, res=shape[1], field=geometry.field_mm[0], fwhm=fwhm_mm, wd=geometry.work_distance_mm,
                          projection=geometry.projection)
        for name, disc in geometry.detectors.items():
            s.set_detector(name, center=disc.center, normal=disc.normal, radius=disc.radius)
        r = s.render(quality=quality, events=int(events), seed=seed, progress=False)
    later = {n: np.asarray(r.channels[n], float) - np.asarray(r.channels[f"{n}.e1"], float) for n in DETECTOR_NAMES}
    if not with_errors:
        return later
    return later, later_events_error(r.errors, DETECTOR_NAMES, int(events))
