"""Height maps to triangle meshes in scene coordinates, and the binary PLY writer.

A height map is a 2-D array ``height[i, j]`` in millimetres in the package's image orientation
(:mod:`elo_mitsuba.grid`: row 0 is the +y edge, columns towards +x, centred on the z-axis).
:func:`heightmap_to_mesh` puts one vertex at every pixel
centre and splits every cell into two triangles wound counter-clockwise seen from +z, so that the
face normals are ``[-dZ/dx, -dZ/dy, 1]`` normalised (Eq. 16 of the paper), pointing up and out of
the material. Render such meshes with Mitsuba's ``face_normals=true`` (flat shading: the normal the
electrons see is the facet's own).

A surface known everywhere (the test objects of :mod:`elo_mitsuba.objects`) can give its own normals
at the vertices (``normals``): the renderer then interpolates them across each triangle, so that the
beam sees the surface's normal wherever it lands, to second order in the mesh pitch. Flat facets
sampled at the pixel centres would not do: every centre falls on the same spot of its cell (the
cell's diagonal at an odd oversampling), where a triangle's slope differs from the surface's by
half the pitch times the cross curvature d2Z/dxdy. On the hills at 128^2 (pitch a third of a
pixel) that is 4e-3 RMS in the slopes, a bias of the same sign over each hill's quadrant, and the
images of the true surface then differed from the model's by 0.0024 (corrected units) where the
smooth mesh leaves 0.0004.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .errors import EloInputError
from .files import atomic_write, check_output
from .heightmap import pixel_centres, validate_heightmap, validate_pixel_size


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
    normals=None,
    flat_cells=None,
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
    normals : (H, W, 3) array, optional
        The surface's own unit normals at the pixel centres (pointing up): the mesh carries them
        as vertex normals (``mesh.metadata["vertex_normals"]``, written by :func:`write_mesh`), to
        be rendered with ``face_normals=false`` (:func:`~elo_mitsuba.scene_files.write_object_scene`
        does). Only with ``step`` 1 and no simplification or base.
    flat_cells : (H - 1, W - 1) bool array, optional
        With ``normals``: cells whose two triangles keep their own normal (vertices of their own),
        e.g. the wall of a cliff, which the normals either side of it know nothing of.

    Returns
    -------
    trimesh.Trimesh
        Vertices in scene coordinates (x right, y up, z = height), faces wound so that the normals
        point to +z (outwards); the top surface's face normals are ``[-dZ/dx, -dZ/dy, 1]`` normalised.

    Examples
    --------
    >>> import numpy as np
    >>> height = np.array([[0.0, 0.1, 0.2], [0.0, 0.1, 0.2]])       # mm, 1 mm pixels
    >>> mesh = heightmap_to_mesh(height, 1.0)
    >>> mesh.vertices.shape, mesh.faces.shape
    ((6, 3), (4, 3))
    >>> mesh.bounds.round(4).tolist()
    [[-1.0, -0.5, 0.0], [1.0, 0.5, 0.2]]
    >>> heightmap_to_mesh(height, 1.0, base_mm=-1.0).is_watertight
    True
    """
    import trimesh

    height = validate_heightmap(height_mm)
    p = validate_pixel_size(pixel_size_mm)
    if int(step) != step or step < 1:
        raise EloInputError(f"step {step!r} must be an integer >= 1")
    step = int(step)
    if normals is not None and (step != 1 or tolerance_mm is not None or base_mm is not None):
        raise EloInputError("vertex normals: only with step 1, no tolerance and no base")
    if flat_cells is not None and normals is None:
        raise EloInputError("flat_cells: only with vertex normals")
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
        if not math.isfinite(base):
            raise EloInputError(f"base {base_mm!r} mm must be a finite number below the lowest height "
                                f"({z.min():.6g} mm)")
        if base >= z.min():
            raise EloInputError(
                f"base {base_mm!r} mm must lie below the lowest height ({z.min():.6g} mm)"
            )
        vertices, faces = _add_walls_and_base(vertices, faces, idx, base)

    # the PLY stores float32: a coordinate beyond its range would be written as Inf
    largest = float(np.abs(vertices).max())
    if not largest <= float(np.finfo(np.float32).max):
        axis = "xyz"[int(np.argmax(np.abs(vertices).max(axis=0)))]
        what = "heights or --base" if axis == "z" else "pixel size x map size"
        raise EloInputError(f"mesh {axis} coordinates reach {largest:.3g} mm ({what}), beyond the float32 range of a "
                            f"PLY ({np.finfo(np.float32).max:.3g}); check the units of the height map")
    if normals is None:
        return trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    vn = _vertex_normals(normals, height.shape)
    if flat_cells is not None:
        vertices, faces, vn = _flat_cells(vertices, faces, vn, flat_cells, height.shape)
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    mesh.metadata["vertex_normals"] = vn
    return mesh


def _vertex_normals(normals, shape) -> np.ndarray:
    """(H, W, 3) unit normals pointing up -> (H W, 3) float64, checked."""
    try:
        n = np.asarray(normals, float)
    except (TypeError, ValueError):
        n = np.zeros(0)
    if n.shape != (*shape, 3):
        raise EloInputError(f"normals are {n.shape}, the height map needs {(*shape, 3)}")
    length = np.linalg.norm(n, axis=-1)
    if not (np.all(np.isfinite(n)) and np.all(np.abs(length - 1.0) < 1e-6) and np.all(n[..., 2] > 0)):
        raise EloInputError("normals: must be finite unit vectors pointing up (z > 0)")
    return n.reshape(-1, 3)


def _flat_cells(vertices, faces, vn, flat_cells, shape):
    """Vertices of their own, with the face's normal, for both triangles of each flagged cell."""
    flat = np.asarray(flat_cells, bool)
    if flat.shape != (shape[0] - 1, shape[1] - 1):
        raise EloInputError(f"flat_cells are {flat.shape}, the height map's cells {(shape[0] - 1, shape[1] - 1)}")
    pick = np.concatenate([flat.ravel(), flat.ravel()])  # faces: all (bl, br, tr), then all (bl, tr, tl)
    if not pick.any():
        return vertices, faces, vn
    own = faces[pick]
    corners = vertices[own]  # (F, 3, 3)
    fn = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    fn /= np.linalg.norm(fn, axis=1, keepdims=True)
    faces = faces.copy()
    faces[pick] = len(vertices) + np.arange(3 * len(own)).reshape(-1, 3)
    return (np.concatenate([vertices, corners.reshape(-1, 3)]), faces,
            np.concatenate([vn, np.repeat(fn, 3, axis=0)]))


def mesh_surface_height(height_mm, pixel_size_mm, x, y) -> np.ndarray:
    """The height of the surface :func:`heightmap_to_mesh` makes of ``height_mm`` (step 1, no
    simplification) at scene points (x, y): linear on each of its triangles (every cell split along
    its bottom-left to top-right diagonal), so exactly what the renderer intersects. Points outside
    the grid take the nearest border cell's plane."""
    height = validate_heightmap(height_mm)
    p = validate_pixel_size(pixel_size_mm)
    nr, nc = height.shape
    xs, ys = pixel_centres(height.shape, p)
    # fractional column from x (left to right) and row from y (row 0 is the +y edge)
    fc = (np.asarray(x, float) - xs[0]) / p
    fr = (ys[0] - np.asarray(y, float)) / p
    j = np.clip(np.floor(fc).astype(int), 0, nc - 2)
    i = np.clip(np.floor(fr).astype(int), 0, nr - 2)
    u = fc - j          # towards +x
    v = 1.0 - (fr - i)  # towards +y, from the cell's bottom (row i + 1)
    tl, tr = height[i, j], height[i, j + 1]
    bl, br = height[i + 1, j], height[i + 1, j + 1]
    lower = u >= v  # triangle (bl, br, tr); else (bl, tr, tl)
    return np.where(lower, bl + u * (br - bl) + v * (tr - br), bl + v * (tl - bl) + u * (tr - tl))


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


# --- PLY files ----------------------------------------------------------------------------------------
#: Largest vertex count whose face indices Mitsuba 3 (3.9) reads exactly when the PLY stores them as a
#: signed type (``int``): its loader converts those through float32, which rounds every index above
#: 2**24 (16777217 -> 16777216) and so joins triangles to the wrong vertices, silently. Indices stored
#: as ``uint`` (what :func:`write_mesh` writes) are copied exactly. A 1500^2 scan's mesh at three
#: facets per pixel has 22.3 M vertices (tests/test_mesh_ply.py shows both).
EXACT_SIGNED_INDICES = 1 << 24


def ply_header(path) -> dict:
    """The element counts and the face index type of a PLY file, from its header alone.

    Returns
    -------
    dict
        ``format`` (``ascii``, ``binary_little_endian``, ...), ``vertices`` and ``faces`` (counts,
        0 when absent), ``index_type`` (the scalar type of the face list's indices, ``None``
        without faces), ``elements`` (in file order: name, count and each property's words after
        ``property``) and ``body`` (the byte offset of the data after the header).

    Raises :class:`EloInputError` naming the file when it has no PLY header.
    """
    with open(path, "rb") as f:
        head = f.read(65536)
    if not head.startswith(b"ply") or b"end_header" not in head:
        raise EloInputError(f"mesh file {path} is not a PLY file (no 'ply' ... 'end_header' header)")
    end = head.index(b"end_header")
    out = {"format": None, "vertices": 0, "faces": 0, "index_type": None, "elements": [],
           "body": head.find(b"\n", end) + 1 or len(head)}
    for line in head[:end].decode("ascii", "replace").splitlines():
        words = line.split()
        if len(words) >= 2 and words[0] == "format":
            out["format"] = words[1]
        elif len(words) == 3 and words[0] == "element" and words[2].isdigit():
            out["elements"].append((words[1], int(words[2]), []))
            if words[1] in ("vertex", "face"):
                out["vertices" if words[1] == "vertex" else "faces"] = int(words[2])
        elif words[:1] == ["property"] and out["elements"]:
            out["elements"][-1][2].append(words[1:])
            if len(words) == 5 and words[1] == "list" and out["elements"][-1][0] == "face":
                out["index_type"] = words[3]
    return out


def check_ply_indices(path) -> None:
    """Refuse, in one line, a PLY file whose face indices Mitsuba would read wrongly
    (:data:`EXACT_SIGNED_INDICES`; :func:`write_mesh`, and so ``elo-mitsuba mesh``, stores them as
    ``uint``: ``write_mesh(trimesh.load(path), new_path)`` re-saves such a file), or that name a
    vertex the file does not have (:func:`ply_index_range`): Mitsuba reads past its vertex buffer
    while building the scene, which gave a different surface area at each run and, with an index of
    1e8, a segmentation fault."""
    h = ply_header(path)
    if h["vertices"] > EXACT_SIGNED_INDICES and h["index_type"] not in ("uint", "uint32"):
        raise EloInputError(
            f"mesh file {path}: {h['vertices']} vertices with face indices of type {h['index_type']!r}; Mitsuba "
            f"reads such indices through float32 and corrupts every one above {EXACT_SIGNED_INDICES} (2^24): "
            "store them as 'uint' (elo_mitsuba.mesh.write_mesh does) or use fewer vertices")
    span = ply_index_range(path)
    if span is not None and (span[0] < 0 or span[1] >= h["vertices"]):
        bad = span[0] if span[0] < 0 else span[1]
        raise EloInputError(f"mesh file {path}: a triangle names vertex {bad}, but the file has {h['vertices']} "
                            "(indices 0 to n-1): the file is damaged")


#: Bytes of the PLY scalar types.
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def ply_index_range(path) -> tuple[int, int] | None:
    """The smallest and largest face index of a PLY file of triangles, read without loading it.

    None where the layout is not one this reads (faces other than triangles, list properties
    outside the face list, an unknown type, a truncated file): the check after loading
    (``elo`` integrator) still refuses such a mesh, after Mitsuba has read it.

    Examples
    --------
    >>> import tempfile, trimesh
    >>> from pathlib import Path
    >>> tri = trimesh.Trimesh(vertices=[[0, 0, 0], [1, 0, 0], [0, 1, 0]], faces=[[0, 2, 1]], process=False)
    >>> ply_index_range(write_mesh(tri, Path(tempfile.mkdtemp()) / "t.ply"))
    (0, 2)
    """
    try:
        h = ply_header(path)
    except EloInputError:
        return None
    elements = h["elements"]
    try:
        if h["format"] == "ascii":
            with open(path, "rb") as f:
                f.seek(h["body"])
                return _ascii_index_range(f.read(), elements)
        if h["format"] in ("binary_little_endian", "binary_big_endian"):
            data = np.memmap(path, dtype=np.uint8, mode="r")  # the faces are read where they lie
            return _binary_index_range(data, h["body"], elements, "<" if h["format"] == "binary_little_endian" else ">")
    except (ValueError, KeyError, IndexError):
        return None
    return None


def _binary_index_range(data, offset: int, elements, order: str):
    for name, count, props in elements:
        fields = []
        for k, p in enumerate(props):
            if p[0] == "list":
                if name != "face" or p[-1] != "vertex_indices":
                    return None
                fields += [("n", order + _PLY_TYPES[p[1]]), ("i", order + _PLY_TYPES[p[2]], (3,))]
            else:
                fields.append((f"p{k}", order + _PLY_TYPES[p[0]]))
        dtype = np.dtype(fields)
        if name == "face":
            rows = np.frombuffer(data, dtype, count, offset)  # as triangles: valid only if every count is 3
            if count == 0 or not np.all(rows["n"] == 3):
                return None
            return int(rows["i"].min()), int(rows["i"].max())
        offset += dtype.itemsize * count
    return None


def _ascii_index_range(text: bytes, elements):
    lines = text.split(b"\n")
    at = 0
    for name, count, props in elements:
        if name == "face":
            if [p[0] for p in props].count("list") != 1 or props[0][0] != "list" or count == 0:
                return None
            rows = [line.split() for line in lines[at:at + count]]
            if len(rows) < count or any(len(r) < 4 or r[0] != b"3" for r in rows):
                return None
            idx = np.array([r[1:4] for r in rows], dtype=np.int64)
            return int(idx.min()), int(idx.max())
        at += count
    return None


def write_mesh(mesh, path, *, overwrite: bool = False) -> Path:
    """Write ``mesh`` as binary little-endian PLY: float32 positions and triangles with ``uint``
    (uint32) indices; float32 vertex normals where the mesh carries its surface's own
    (``mesh.metadata["vertex_normals"]``, :func:`heightmap_to_mesh`), no other attributes.

    The indices are unsigned because Mitsuba reads signed ones through float32
    (:data:`EXACT_SIGNED_INDICES`).

    Raises :class:`EloInputError` if ``path`` does not end in ``.ply``, its folder does not exist,
    or it exists and ``overwrite`` is false.

    Examples
    --------
    >>> import tempfile, trimesh
    >>> from pathlib import Path
    >>> tri = trimesh.Trimesh(vertices=[[0, 0, 0], [1, 0, 0], [0, 1, 0]], faces=[[0, 1, 2]], process=False)
    >>> p = write_mesh(tri, Path(tempfile.mkdtemp()) / "t.ply")
    >>> ply_header(p)["index_type"], ply_header(p)["faces"]
    ('uint', 1)
    """
    path = check_output(path, (".ply",), overwrite=overwrite)
    vertices = np.ascontiguousarray(mesh.vertices, dtype="<f4")
    normals = mesh.metadata.get("vertex_normals") if hasattr(mesh, "metadata") else None
    normal_props = ""
    if normals is not None:
        if np.shape(normals) != vertices.shape:
            raise EloInputError(f"{path}: the mesh's vertex normals are {np.shape(normals)}, its vertices "
                                f"{vertices.shape} (a mesh changed after heightmap_to_mesh gave it normals?)")
        table = np.empty(len(vertices), dtype=[("p", "<f4", (3,)), ("n", "<f4", (3,))])
        table["p"], table["n"] = vertices, np.asarray(normals, float)
        vertices, normal_props = table, "property float nx\nproperty float ny\nproperty float nz\n"
    faces = np.asarray(mesh.faces)
    if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise EloInputError(f"{path}: face indices outside 0..{len(vertices) - 1}")
    rows = np.empty(len(faces), dtype=[("n", "u1"), ("i", "<u4", (3,))])
    rows["n"] = 3
    rows["i"] = faces
    header = ("ply\nformat binary_little_endian 1.0\ncomment elo-mitsuba write_mesh\n"
              f"element vertex {len(vertices)}\nproperty float x\nproperty float y\nproperty float z\n"
              f"{normal_props}element face {len(faces)}\nproperty list uchar uint vertex_indices\nend_header\n").encode("ascii")

    def write(tmp):
        with open(tmp, "wb") as f:
            f.write(header)
            f.write(vertices.tobytes())
            f.write(rows.tobytes())

    return atomic_write(path, write)
