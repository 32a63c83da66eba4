"""Height maps to triangle meshes in scene coordinates, and the generated test objects.

Orientation convention (the same as the ELO images of :mod:`elo_mitsuba.cli`): a height map is a
2-D array ``height[i, j]`` in millimetres seen from above; **row 0 is the +y edge**, columns run
towards **+x**. Pixel ``(i, j)`` of an ``H x W`` map with pixel size ``p`` has its centre at::

    x_j = (j - (W - 1) / 2) * p        y_i = ((H - 1) / 2 - i) * p        z = height[i, j]

so the map is centred on the z-axis. :func:`heightmap_to_mesh` puts one vertex at every pixel
centre and splits every cell into two triangles wound counter-clockwise seen from +z, so that the
face normals are ``[-dZ/dx, -dZ/dy, 1]`` normalised (Eq. 16 of the paper), pointing up and out of
the material. Render such meshes with Mitsuba's ``face_normals=true`` (flat shading: the normal the
electrons see is the facet's own).

:func:`corrugated_sheet_mesh` builds the corrugated sheet of Sec. 4.2 (Fig. 9) with exact normals.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from .constants import FIELD_MM
from .errors import EloInputError

#: File name extensions :func:`load_heightmap` reads.
HEIGHTMAP_EXTENSIONS = (".npy", ".tif", ".tiff", ".csv")
#: Units :func:`load_heightmap` accepts for heights, as factor to millimetres.
HEIGHT_UNITS = {"mm": 1.0, "um": 1e-3}


# --- reading and validating height maps ------------------------------------------------------------
def load_heightmap(path, units: str = "mm") -> np.ndarray:
    """Read a height map (.npy, .tif/.tiff, .csv with comma separators) as float64 millimetres.

    Raises :class:`EloInputError` (one line) for a missing file, an unknown extension or units, an
    unreadable file, a non-2-D array or non-finite heights.
    """
    path = Path(path)
    if units not in HEIGHT_UNITS:
        raise EloInputError(f"--units {units!r} is not known; use one of {', '.join(HEIGHT_UNITS)}")
    ext = path.suffix.lower()
    if ext not in HEIGHTMAP_EXTENSIONS:
        raise EloInputError(
            f"height map {str(path)!r} has extension {path.suffix or '(none)'!r}; "
            f"use one of {', '.join(HEIGHTMAP_EXTENSIONS)}"
        )
    if not path.is_file():
        raise EloInputError(f"height map {str(path)!r} does not exist")
    try:
        if ext == ".npy":
            data = np.load(path, allow_pickle=False)
        elif ext in (".tif", ".tiff"):
            import tifffile

            data = tifffile.imread(path)
        else:
            data = np.loadtxt(path, delimiter=",", dtype=float, ndmin=2)
    except Exception as exc:  # noqa: BLE001 - any reader failure is a bad file for the user
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise EloInputError(f"height map {str(path)!r} could not be read: {reason}") from exc
    height = validate_heightmap(data, what=f"height map {str(path)!r}")
    return height * HEIGHT_UNITS[units]


def validate_heightmap(height, what: str = "height map") -> np.ndarray:
    """Return ``height`` as a float64 2-D array, or raise :class:`EloInputError`."""
    arr = np.asarray(height)
    if arr.dtype.kind not in "fiub":
        raise EloInputError(f"{what} has dtype {arr.dtype}; heights must be real numbers")
    arr = arr.astype(np.float64, copy=False)
    if arr.ndim == 3 and 1 in (arr.shape[0], arr.shape[-1]):
        arr = arr.reshape([n for n in arr.shape if n != 1] or [1])  # single-channel TIFF/PNG
    if arr.ndim != 2:
        raise EloInputError(f"{what} has shape {arr.shape}; a height map must be a 2-D array (rows, columns)")
    if arr.shape[0] < 2 or arr.shape[1] < 2:
        raise EloInputError(f"{what} has shape {arr.shape}; it needs at least 2 rows and 2 columns")
    bad = ~np.isfinite(arr)
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise EloInputError(
            f"{what} has {int(bad.sum())} non-finite height(s) (first at row {i}, column {j}); "
            "fill or crop them before meshing"
        )
    return arr


def validate_pixel_size(pixel_size_mm) -> float:
    try:
        p = float(pixel_size_mm)
    except (TypeError, ValueError):
        raise EloInputError(f"pixel size {pixel_size_mm!r} is not a number; give it in mm (> 0)") from None
    if not math.isfinite(p) or p <= 0:
        raise EloInputError(f"pixel size {pixel_size_mm!r} mm must be a finite number > 0")
    return p


# --- coordinates -----------------------------------------------------------------------------------
def pixel_centres(shape, pixel_size_mm) -> tuple[np.ndarray, np.ndarray]:
    """Scene coordinates (x of the columns, y of the rows) of the pixel centres of a map.

    ``x`` increases with the column index, ``y`` decreases with the row index (row 0 = +y edge);
    both are centred on 0.
    """
    from .analysis.geometry import pixel_axes  # the one definition of the image orientation

    h, w = int(shape[0]), int(shape[1])
    p = float(pixel_size_mm)
    return pixel_axes((h, w), (w * p, h * p))


def heightmap_gradient(height_mm, pixel_size_mm) -> tuple[np.ndarray, np.ndarray]:
    """Central-difference ``(dZ/dx, dZ/dy)`` of a map in scene axes (note: y runs against rows)."""
    h = np.asarray(height_mm, dtype=float)
    d_rows, d_cols = np.gradient(h, float(pixel_size_mm))
    return d_cols, -d_rows


# --- simplification ----------------------------------------------------------------------------------
def _keep_lines(height: np.ndarray, coords: np.ndarray, tol: float) -> np.ndarray:
    """Indices of columns to keep so that dropped columns are reproduced by linear interpolation
    between the kept neighbours within ``tol`` in every row (greedy, first and last kept)."""
    n = height.shape[1]
    keep = [0]
    a = 0
    while a < n - 1:
        b = a + 1
        # extend the segment [a, b+1] while all interior columns stay within tol
        while b + 1 < n:
            c = b + 1
            t = (coords[a + 1 : c] - coords[a]) / (coords[c] - coords[a])
            interp = height[:, a : a + 1] * (1 - t) + height[:, c : c + 1] * t
            if np.max(np.abs(interp - height[:, a + 1 : c])) > tol:
                break
            b = c
        keep.append(b)
        a = b
    return np.asarray(keep)


# --- meshing ---------------------------------------------------------------------------------------
def heightmap_to_mesh(
    height_mm,
    pixel_size_mm,
    *,
    step: int = 1,
    tolerance_mm: float | None = None,
    base_mm: float | None = None,
):
    """Triangulate a height map (documented orientation) into a :class:`trimesh.Trimesh`.

    Parameters
    ----------
    height_mm : (H, W) array
        Heights in mm; row 0 is the +y edge, columns run towards +x.
    pixel_size_mm : float
        Pixel pitch in mm (square pixels).
    step : int
        Keep every ``step``-th row and column (plain down-sampling; the last row/column is always
        kept so the extent does not shrink by more than one coarse cell).
    tolerance_mm : float, optional
        Drop whole rows and columns whose heights the kept neighbours reproduce by linear
        interpolation within this tolerance (in every column/row). Exact for flat margins and
        gaps between features; the grid stays a tensor grid (no cracks, no T-junctions), and all
        vertices remain at pixel centres with their exact heights.
    base_mm : float, optional
        If given, add side walls down to ``z = base_mm`` and a flat bottom facing -z, so the mesh
        is watertight (a solid). Not needed for rendering.

    Returns
    -------
    trimesh.Trimesh
        Vertices in scene coordinates (x right, y up, z = height), faces wound so that the normals
        point to +z (outwards); the top surface's face normals are ``[-dZ/dx, -dZ/dy, 1]`` normalised.
    """
    import trimesh

    height = validate_heightmap(height_mm)
    p = validate_pixel_size(pixel_size_mm)
    if int(step) != step or step < 1:
        raise EloInputError(f"step {step!r} must be an integer >= 1")
    step = int(step)
    x_all, y_all = pixel_centres(height.shape, p)

    rows = np.arange(0, height.shape[0], step)
    cols = np.arange(0, height.shape[1], step)
    if rows[-1] != height.shape[0] - 1:
        rows = np.append(rows, height.shape[0] - 1)
    if cols[-1] != height.shape[1] - 1:
        cols = np.append(cols, height.shape[1] - 1)
    if tolerance_mm is not None:
        tol = float(tolerance_mm)
        if not math.isfinite(tol) or tol < 0:
            raise EloInputError(f"tolerance {tolerance_mm!r} mm must be a finite number >= 0")
        sub = height[np.ix_(rows, cols)]
        cols = cols[_keep_lines(sub, x_all[cols], tol)]
        sub = height[np.ix_(rows, cols)]
        rows = rows[_keep_lines(sub.T, -y_all[rows], tol)]

    z = height[np.ix_(rows, cols)]
    xs, ys = x_all[cols], y_all[rows]
    nr, nc = z.shape
    xx, yy = np.meshgrid(xs, ys)
    vertices = np.column_stack([xx.ravel(), yy.ravel(), z.ravel()])

    idx = np.arange(nr * nc).reshape(nr, nc)
    tl, tr = idx[:-1, :-1], idx[:-1, 1:]
    bl, br = idx[1:, :-1], idx[1:, 1:]
    # counter-clockwise seen from +z (x right, y up): BL -> BR -> TR and BL -> TR -> TL
    faces = np.concatenate(
        [np.stack([bl, br, tr], -1).reshape(-1, 3), np.stack([bl, tr, tl], -1).reshape(-1, 3)]
    )

    if base_mm is not None:
        base = float(base_mm)
        if not math.isfinite(base) or base >= z.min():
            raise EloInputError(
                f"base {base_mm!r} mm must lie below the lowest height ({z.min():.6g} mm)"
            )
        vertices, faces = _add_walls_and_base(vertices, faces, idx, base)

    return trimesh.Trimesh(vertices=vertices, faces=faces, process=False)


def _add_walls_and_base(vertices, faces, idx, base):
    """Close a grid surface with vertical side walls and a bottom at z = base."""
    # boundary loop, counter-clockwise seen from +z: bottom row left->right, right column
    # bottom->top, top row right->left, left column top->bottom (rows run towards -y)
    loop = np.concatenate([idx[-1, :-1], idx[::-1, -1][:-1], idx[0, ::-1][:-1], idx[:, 0][:-1]])
    n = len(vertices)
    low = vertices[loop].copy()
    low[:, 2] = base
    low_idx = n + np.arange(len(loop))
    centre = np.array([[vertices[:, 0].mean(), vertices[:, 1].mean(), base]])
    c_idx = n + len(loop)
    a, b = loop, np.roll(loop, -1)
    la, lb = low_idx, np.roll(low_idx, -1)
    # walls: outward normal = (edge direction) x (+z) for a ccw loop -> triangles (a, la, lb), (a, lb, b)
    walls = np.concatenate([np.stack([a, la, lb], -1), np.stack([a, lb, b], -1)])
    # bottom facing -z: clockwise seen from above
    bottom = np.stack([np.full_like(la, c_idx), lb, la], -1)
    vertices = np.concatenate([vertices, low, centre])
    faces = np.concatenate([faces, walls, bottom])
    return vertices, faces


def write_mesh(mesh, path, *, overwrite: bool = False) -> Path:
    """Write ``mesh`` as binary little-endian PLY (positions and triangles only, no normals).

    Raises :class:`EloInputError` if ``path`` does not end in ``.ply``, its folder does not exist,
    or it exists and ``overwrite`` is false.
    """
    from trimesh.exchange.ply import export_ply

    path = Path(path)
    if path.suffix.lower() != ".ply":
        raise EloInputError(f"output {str(path)!r} must end in .ply (binary PLY is written)")
    if path.exists() and not overwrite:
        raise EloInputError(f"output {str(path)!r} exists; pass --overwrite to replace it")
    if not path.parent.is_dir():
        raise EloInputError(f"output folder {str(path.parent)!r} does not exist")
    data = export_ply(mesh, encoding="binary", vertex_normal=False, include_attributes=False)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)
    return path


# --- the corrugated sheet of Sec. 4.2 ------------------------------------------------------------------
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


# --- a scene around a mesh ----------------------------------------------------------------------------
def scenes_dir() -> Path:
    """The shipped scenes (scenes_xml/, installed as the package ``elo_mitsuba.scenes``)."""
    from . import scenes

    return Path(scenes.__file__).parent


def write_scene(scene_path, mesh_path, *, material: str | None = None, overwrite: bool = False) -> Path:
    """Write a Mitsuba scene that renders ``mesh_path`` like ``scenes_xml/melt_plate.xml``.

    The scene is the shipped melt-plate scene with its mesh replaced: same parameters (layout,
    dh, dw, wd, field, res, spp, events, fwhm, projection, material), the four detectors and the
    layouts included from the installed ``scenes_xml`` by absolute path. The mesh is referenced
    relative to the scene file when possible. ``material`` (default Ti-6Al-4V) becomes the
    default of the ``material`` parameter; it is validated here.
    """
    from xml.sax.saxutils import escape

    from .constants import DEFAULT_MATERIAL
    from .physics.materials import get_material

    material = DEFAULT_MATERIAL if material is None else material
    get_material(material)  # raises EloInputError for an unknown material
    scene_path, mesh_path = Path(scene_path), Path(mesh_path)
    if scene_path.suffix.lower() != ".xml":
        raise EloInputError(f"scene {str(scene_path)!r} must end in .xml")
    if scene_path.exists() and not overwrite:
        raise EloInputError(f"scene {str(scene_path)!r} exists; pass --overwrite to replace it")
    if not scene_path.parent.is_dir():
        raise EloInputError(f"scene folder {str(scene_path.parent)!r} does not exist")
    try:
        mesh_ref = os.path.relpath(mesh_path.resolve(), scene_path.parent.resolve())
    except ValueError:  # other drive on Windows
        mesh_ref = str(mesh_path.resolve())
    src = scenes_dir()
    text = (src / "melt_plate.xml").read_text()
    text = text[text.index("<scene") :]
    replacements = {
        '<include filename="layouts/$layout.xml"/>':
            f'<include filename="{escape((src / "layouts").as_posix())}/$layout.xml"/>',
        '<include filename="parts/detectors.xml"/>':
            f'<include filename="{escape((src / "parts" / "detectors.xml").as_posix())}"/>',
        'value="meshes/melt_plate.ply"': f'value="{escape(Path(mesh_ref).as_posix(), {chr(34): "&quot;"})}"',
        'id="melt_plate"': 'id="object"',
        f'<default name="material" value="{DEFAULT_MATERIAL}"/>':
            f'<default name="material" value="{escape(material, {chr(34): "&quot;"})}"/>',
    }
    for old, new in replacements.items():
        if old not in text:  # the template changed: fail loudly rather than write a wrong scene
            raise RuntimeError(f"scenes_xml/melt_plate.xml no longer contains {old!r}")
        text = text.replace(old, new)
    header = (
        "<!--\n"
        f"  Generated by elo-mitsuba mesh from {mesh_path.name}: the object (id 'object', material\n"
        f"  parameter default {material!r}) with the four detectors of the ATHENE set-up, no chamber.\n"
        "  Parameters and conventions as scenes_xml/melt_plate.xml (see scenes_xml/README.md):\n"
        "  layout, dh, dw, wd, field, res, spp, events, fwhm, projection, material.\n"
        "-->\n"
    )
    scene_path.write_text(header + text)
    return scene_path
