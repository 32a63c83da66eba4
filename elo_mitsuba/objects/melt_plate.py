"""A synthetic Ti-6Al-4V melt plate after Fig. 3 of the paper, with its exact height and gradients.

The validation plate of the paper (Sec. 2.2, Fig. 3) carries 3 x 3 molten squares "with a side
length of 10 mm and 15 mm" on a blank plate, measured with an optical profilometer. That height
map is not published, so this module synthesises a plausible one, deterministically (seeded):

* **Layout** (our choice, the paper does not give it): square centres on a 25 mm grid at
  x, y in {-25, 0, +25} mm; checkerboard sizes: the centre and the four corner squares are 15 mm,
  the four edge-middle squares 10 mm. Everything lies within +-32.5 mm, inside the 80 mm field;
  the middle surface of Figs. 7, 11 and 14 is the centre square.
* **Blank plate**: exactly z = 0 (a machined start plate; its micrometre roughness is far below
  what the relief of the squares does to the images), so flat margins and gaps mesh coarsely.
* **Each square**: a level offset (raised or sunk, -30..+40 um), a dome (+-15 um), surface
  waviness (random sum of sinusoids, 2-8 mm wavelengths, ~8 um RMS), melt-track ripples
  (6 um, 0.8 mm period, tracks along x in the 15 mm squares, along y in the 10 mm ones; the real
  0.1 mm hatch spacing lies below the mesh grid and the 0.27 mm beam), and a raised rim
  (bulging, 60 um) 0.5 mm inside the border, all faded in by a smooth edge of 0.15 mm width.

:func:`melt_plate_height` evaluates the relief at any (x, y) (scene mm); :func:`melt_plate_gradient`
gives its exact gradient (central differences of the analytic function, step 1e-5 mm, error
~1e-9); :func:`melt_plate_heightmap` samples it on the shipped grid in the package orientation
(:mod:`elo_mitsuba.grid`). :func:`write_assets` regenerates
``scenes_xml/meshes/melt_plate.ply`` and ``melt_plate_height.npy``.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..heightmap import pixel_centres
from ..mesh import heightmap_to_mesh, write_mesh

#: Seed of the synthetic relief.
SEED = 20230426
#: Square centres along x and y (mm) and side lengths: checkerboard 15 / 10 mm (Sec. 2.2).
GRID_PITCH_MM = 25.0
SQUARE_SIDES_MM = (15.0, 10.0)  # (i + j) even -> 15 mm, odd -> 10 mm
#: Extent and grid of the shipped height map: 500 x 500 pixels of 0.2 mm = 100 mm (field + 10 mm
#: margin each side), pixel centres at +-49.9 mm.
PIXEL_SIZE_MM = 0.2
N_PIXELS = 500
#: Mesh simplification tolerance: flat rows/columns (blank plate) are dropped when their heights
#: are reproduced within this (0.1 um).
MESH_TOLERANCE_MM = 1e-4

# relief parameters, mm
EDGE_WIDTH_MM = 0.15          # tanh fade of the square border
LEVEL_RANGE_MM = (-0.030, 0.040)
DOME_MM = 0.015
RIM_HEIGHT_MM = 0.060
RIM_INSET_MM = 0.5
RIM_WIDTH_MM = 0.3
RIPPLE_AMPLITUDE_MM = 0.006
RIPPLE_PERIOD_MM = 0.8
WAVINESS_RMS_MM = 0.008
WAVINESS_WAVELENGTHS_MM = (2.0, 8.0)
WAVINESS_TERMS = 24

#: File names in scenes_xml/meshes/.
MESH_NAME = "melt_plate.ply"
HEIGHTMAP_NAME = "melt_plate_height.npy"


def _squares(seed: int = SEED):
    """List of per-square parameter dicts (deterministic)."""
    rng = np.random.default_rng(seed)
    squares = []
    centres = (-GRID_PITCH_MM, 0.0, GRID_PITCH_MM)
    for i, cy in enumerate(centres[::-1]):  # i = 0: the +y row
        for j, cx in enumerate(centres):
            side = SQUARE_SIDES_MM[(i + j) % 2]
            u = rng.uniform(size=(4 + 4 * WAVINESS_TERMS))
            lam_lo, lam_hi = WAVINESS_WAVELENGTHS_MM
            lam = lam_lo * (lam_hi / lam_lo) ** u[4 : 4 + WAVINESS_TERMS]
            ang = 2 * np.pi * u[4 + WAVINESS_TERMS : 4 + 2 * WAVINESS_TERMS]
            ph = 2 * np.pi * u[4 + 2 * WAVINESS_TERMS : 4 + 3 * WAVINESS_TERMS]
            amp = 0.5 + u[4 + 3 * WAVINESS_TERMS :]
            amp = amp * WAVINESS_RMS_MM * math.sqrt(2.0 / np.sum(amp**2))  # RMS of the sum
            squares.append(
                dict(
                    cx=cx,
                    cy=cy,
                    half=side / 2.0,
                    level=LEVEL_RANGE_MM[0] + (LEVEL_RANGE_MM[1] - LEVEL_RANGE_MM[0]) * u[0],
                    dome=DOME_MM * (2 * u[1] - 1),
                    ripple_phase=2 * np.pi * u[2],
                    tracks_along_x=(i + j) % 2 == 0,
                    wave_k=np.stack([np.cos(ang), np.sin(ang)], -1) * (2 * np.pi / lam)[:, None],
                    wave_phase=ph,
                    wave_amp=amp,
                )
            )
    return squares


_SQUARES = None


def squares():
    """Per-square parameters of the shipped plate (centre, half side, level, ...), cached."""
    global _SQUARES
    if _SQUARES is None:
        _SQUARES = _squares(SEED)
    return _SQUARES


def _smooth_in(d):
    """0 outside, 1 inside; d = signed distance inside the border (mm)."""
    return 0.5 * (1.0 + np.tanh(d / EDGE_WIDTH_MM))


def _rim(d):
    return np.exp(-0.5 * ((d - RIM_INSET_MM) / RIM_WIDTH_MM) ** 2)


def melt_plate_height(x_mm, y_mm) -> np.ndarray:
    """Height (mm, float64) of the synthetic melt plate at scene coordinates (x, y) in mm."""
    x = np.asarray(x_mm, dtype=float)
    y = np.asarray(y_mm, dtype=float)
    x, y = np.broadcast_arrays(x, y)
    z = np.zeros(x.shape)
    for sq in squares():
        u, v = x - sq["cx"], y - sq["cy"]
        a = sq["half"]
        near = (np.abs(u) < a + 2.0) & (np.abs(v) < a + 2.0)  # tanh tails < 1e-11 beyond
        if not near.any():
            continue
        u, v = u[near], v[near]
        dx, dy = a - np.abs(u), a - np.abs(v)
        mx, my = _smooth_in(dx), _smooth_in(dy)
        rx, ry = _rim(dx), _rim(dy)
        rim = RIM_HEIGHT_MM * (rx * my + ry * mx - rx * ry)
        dome = sq["dome"] * np.cos(0.5 * np.pi * np.clip(u / a, -1, 1)) * np.cos(
            0.5 * np.pi * np.clip(v / a, -1, 1)
        )
        across = v if sq["tracks_along_x"] else u
        ripple = RIPPLE_AMPLITUDE_MM * np.sin(2 * np.pi * across / RIPPLE_PERIOD_MM + sq["ripple_phase"])
        k = sq["wave_k"]
        wave = np.sin(u[..., None] * k[:, 0] + v[..., None] * k[:, 1] + sq["wave_phase"]) @ sq["wave_amp"]
        z[near] += mx * my * (sq["level"] + dome + ripple + wave + rim)
    return z


def melt_plate_gradient(x_mm, y_mm, h: float = 1e-5) -> tuple[np.ndarray, np.ndarray]:
    """Exact gradient (dZ/dx, dZ/dy) of :func:`melt_plate_height` at (x, y), scene axes."""
    x = np.asarray(x_mm, dtype=float)
    y = np.asarray(y_mm, dtype=float)
    gx = (melt_plate_height(x + h, y) - melt_plate_height(x - h, y)) / (2 * h)
    gy = (melt_plate_height(x, y + h) - melt_plate_height(x, y - h)) / (2 * h)
    return gx, gy


def melt_plate_heightmap(n_pixels: int = N_PIXELS, pixel_size_mm: float = PIXEL_SIZE_MM):
    """(height_mm float32 array (n, n), pixel_size_mm): row 0 = +y edge, columns towards +x."""
    x, y = pixel_centres((n_pixels, n_pixels), pixel_size_mm)
    xx, yy = np.meshgrid(x, y)
    return melt_plate_height(xx, yy).astype(np.float32), float(pixel_size_mm)


def melt_plate_mesh(height=None, pixel_size_mm: float = PIXEL_SIZE_MM):
    """The shipped mesh: the height map triangulated, flat rows/columns dropped (tolerance 0.1 um)."""
    if height is None:
        height, pixel_size_mm = melt_plate_heightmap()
    return heightmap_to_mesh(height, pixel_size_mm, tolerance_mm=MESH_TOLERANCE_MM)


def in_squares(x_mm, y_mm, inset_mm: float = 0.0) -> np.ndarray:
    """Mask of the points inside a molten square (shrunk by ``inset_mm``; negative grows it)."""
    x, y = np.broadcast_arrays(np.asarray(x_mm, dtype=float), np.asarray(y_mm, dtype=float))
    mask = np.zeros(x.shape, dtype=bool)
    for sq in squares():
        a = sq["half"] - inset_mm
        mask |= (np.abs(x - sq["cx"]) < a) & (np.abs(y - sq["cy"]) < a)
    return mask


def relief_statistics(height=None, pixel_size_mm: float = PIXEL_SIZE_MM) -> dict:
    """Summary (mm) of the relief: min, max, peak-to-valley, RMS and mean inside the squares
    (relative to the blank plate at z = 0), largest slope |grad Z|."""
    if height is None:
        height, pixel_size_mm = melt_plate_heightmap()
    h = np.asarray(height, dtype=float)
    x, y = pixel_centres(h.shape, pixel_size_mm)
    inside = in_squares(x[None, :], y[:, None])
    gx, gy = np.gradient(h, pixel_size_mm)
    return dict(
        min=float(h.min()),
        max=float(h.max()),
        peak_to_valley=float(h.max() - h.min()),
        rms_in_squares=float(np.sqrt(np.mean(h[inside] ** 2))),
        mean_in_squares=float(np.mean(h[inside])),
        max_slope=float(np.hypot(gx, gy).max()),
        fraction_in_squares=float(inside.mean()),
    )


def assets_dir() -> Path:
    """scenes_xml/meshes/ of this source tree (installed as elo_mitsuba.scenes)."""
    from ..scene_files import scenes_dir

    return scenes_dir() / "meshes"


def write_assets(directory=None, overwrite: bool = True) -> tuple[Path, Path]:
    """Regenerate the shipped height map (.npy, float32) and mesh (.ply) of the melt plate."""
    directory = Path(directory) if directory is not None else assets_dir()
    directory.mkdir(parents=True, exist_ok=True)
    height, p = melt_plate_heightmap()
    np.save(directory / HEIGHTMAP_NAME, height)
    mesh_path = write_mesh(melt_plate_mesh(height, p), directory / MESH_NAME, overwrite=overwrite)
    return directory / HEIGHTMAP_NAME, mesh_path

