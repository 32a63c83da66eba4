"""The corrugated sheet of Sec. 4.2 (Fig. 9): 45-degree flanks of 1 mm, exact normals.

``scenes_xml/meshes/corrugated_sheet.ply`` is :func:`corrugated_sheet_mesh` with its defaults.
"""

from __future__ import annotations

import math

import numpy as np

from ..constants import FIELD_MM


#: Flank length of the corrugated sheet (Sec. 4.2), mm.
CORRUGATED_FLANK_MM = 1.0
#: Number of flanks: odd, so that x = 0 lies in the middle of a (rising) flank and the sheet,
#: 129 / sqrt(2) = 91.2 mm wide, covers the 80 mm field with a margin of 5.6 mm on each side.
CORRUGATED_N_FLANKS = 129
#: Length of the ridges along y, mm: the field plus a 5 mm margin on each side.
CORRUGATED_LENGTH_MM = FIELD_MM + 10.0


def corrugated_profile(flank_mm: float = CORRUGATED_FLANK_MM, n_flanks: int = CORRUGATED_N_FLANKS):
    """Vertices ``(x, z)`` of the corrugated profile: ``n_flanks + 1`` points, 45-degree flanks.

    Flank k spans ``flank_mm / sqrt(2)`` in x and in z. Flanks with even k rise towards +x
    (normal ``[-1, 0, 1]``, "n_-" of the paper), odd ones fall (``[1, 0, 1]``, "n_+"). The profile is
    centred on x = 0 (for odd ``n_flanks`` the middle flank, which rises, is centred on x = 0) and
    alternates between z = -a/2 and +a/2 with a = flank_mm / sqrt(2), so the mean height is 0.
    """
    # a is rounded to a multiple of 2^-17 mm (7.6 nm): then every x and z below is exact in float32
    # (|x| < 64 mm), the flanks' x and z extents are equal also in a float32 PLY, and the normals
    # are exactly [+-1, 0, 1]/sqrt 2; the flank length is then flank_mm within 1e-5 mm.
    a = round(flank_mm / math.sqrt(2.0) * 2.0**17) / 2.0**17
    k = np.arange(n_flanks + 1)
    x = (k - n_flanks / 2.0) * a
    z = np.where(k % 2 == 0, -a / 2.0, a / 2.0)
    return x, z


def corrugated_sheet_mesh(
    flank_mm: float = CORRUGATED_FLANK_MM,
    n_flanks: int = CORRUGATED_N_FLANKS,
    length_mm: float = CORRUGATED_LENGTH_MM,
):
    """The corrugated sheet of Sec. 4.2 / Fig. 9: ridges along y, 2 triangles per flank."""
    import trimesh

    x, z = corrugated_profile(flank_mm, n_flanks)
    n = len(x)
    half = length_mm / 2.0
    top = np.column_stack([x, np.full(n, half), z])  # y = +half
    bottom = np.column_stack([x, np.full(n, -half), z])  # y = -half
    vertices = np.concatenate([bottom, top])
    b = np.arange(n - 1)
    # quad (b_k, b_k+1, t_k+1, t_k) counter-clockwise seen from +z
    faces = np.concatenate(
        [np.stack([b, b + 1, n + b + 1], -1), np.stack([b, n + b + 1, n + b], -1)]
    )
    return trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
