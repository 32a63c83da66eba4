"""The 2nd scattering event of a shipped chamber scene in plain numpy, independent of Mitsuba's ray
tracing (issue 26's independent check; used by tests/test_e2_independent.py).

What is shared with the package: only the physics, g_BSE of Eq. 13 from
:mod:`elo_mitsuba.physics` (the plate's leg by :func:`~elo_mitsuba.physics.scattering.g_bse`
itself; the walls' leg by the same ``lobe_weight_table`` the ``elo_bse`` BSDF tabulates, checked
against ``g_bse`` by :func:`check_fast_g`). Everything else is here: a small reader of the scene
XML (defaults, includes, ``rectangle``/``disk`` shapes, ``scale``/``lookat``/``rotate``, BSDF
references), segment-rectangle and segment-disc tests (occlusion), and deterministic quadratures.

The quantity (the ``elo`` integrator's ``<id>.e2`` with the shipped options: absorbing detector
plates, detectors counting on both faces, every other shape a one-sided ``elo_bse`` scatterer)::

    e2 = int_{H+} g_plate(wi, w1) V1(p, q(w1)) D(q(w1), w1) dw1,
    D(q, w1) = int_{disc} g_wall(-w1 at q, w2) |cos(n_det, w2)| / r^2 V2(q, x) dA(x),

with p the scan point on the plate, q the first surface the ray p + t w1 meets, V1 = 1 where q is
a scatterer seen from its front side (a detector absorbs; a back side scatters nothing; a ray out
of the gun opening is lost) and V2 the visibility of the disc point x from q. The w1 integral is
taken over the area of every scattering rectangle (dw1 = cos(n_S, -w1) dA / r^2,
:func:`second_event`), the disc integral by a midpoint rule in (r^2, phi) (equal-area cells).
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from elo_mitsuba.constants import LOBE_WIDTH_DEG
from elo_mitsuba.physics.materials import get_material
from elo_mitsuba.physics.scattering import g_bse, lobe_weight_table

SCENES = Path(__file__).resolve().parents[1] / "scenes_xml"
#: Nodes of the tabulated lobe weight W(theta) (as the elo_bse BSDF: linear interpolation).
TABLE_SIZE = 4097
_EPS = 1e-6
_GOLDEN = 0.6180339887498949


# ---- the scene files ---------------------------------------------------------------------------------
def _subst(text, values):
    return re.sub(r"\$(\w+)", lambda m: values[m.group(1)], text)


def _floats(text, values):
    return np.array([float(x) for x in _subst(text, values).replace(",", " ").split()])


def _lookat(origin, target, up):
    """Mitsuba's look-at: local z towards the target, x = up x z normalised, y = z x x."""
    d = target - origin
    d = d / np.linalg.norm(d)
    left = np.cross(up, d)
    left = left / np.linalg.norm(left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, np.cross(d, left), d, origin
    return m


def _rotate(axis, angle_deg):
    axis = axis / np.linalg.norm(axis)
    a = np.deg2rad(angle_deg)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    m = np.eye(4)
    m[:3, :3] = np.eye(3) + np.sin(a) * k + (1 - np.cos(a)) * k @ k
    return m


def _transform(node, values):
    """The 4 x 4 matrix of a <transform>: each child applied after the ones before it."""
    m = np.eye(4)
    for t in node:
        a = t.attrib
        if t.tag == "scale":
            s = np.eye(4)
            if "value" in a:
                s[0, 0] = s[1, 1] = s[2, 2] = float(_subst(a["value"], values))
            else:
                for i, c in enumerate("xyz"):
                    s[i, i] = float(_subst(a.get(c, "1"), values))
            step = s
        elif t.tag == "lookat":
            step = _lookat(*(_floats(a[k], values) for k in ("origin", "target", "up")))
        elif t.tag == "rotate":
            axis = np.array([float(_subst(a.get(c, "0"), values)) for c in "xyz"])
            step = _rotate(axis, float(_subst(a["angle"], values)))
        elif t.tag == "translate":
            step = np.eye(4)
            step[:3, 3] = [float(_subst(a.get(c, "0"), values)) for c in "xyz"]
        else:
            raise ValueError(f"transform <{t.tag}> not handled by this reader")
        m = step @ m
    return m


def _material_of(node, values, bsdfs):
    """The elo_bse material of a <bsdf> node; None for any other BSDF (an absorber here)."""
    if node.attrib.get("type") != "elo_bse":
        return None
    for s in node.findall("string"):
        if s.attrib["name"] == "material":
            return _subst(s.attrib["value"], values)
    return "Ti-6Al-4V"  # elo_bse's default (elo_mitsuba.constants.DEFAULT_MATERIAL)


def _read(path, values, bsdfs, shapes):
    root = ET.parse(path).getroot()
    for node in root:
        a = node.attrib
        if node.tag == "default":
            values.setdefault(a["name"], a["value"])
        elif node.tag == "include":
            _read(path.parent / _subst(a["filename"], values), values, bsdfs, shapes)
        elif node.tag == "bsdf":
            bsdfs[a["id"]] = _material_of(node, values, bsdfs)
        elif node.tag == "shape":
            if a["type"] not in ("rectangle", "disk"):
                raise ValueError(f"shape type {a['type']!r} not handled by this reader")
            m = _transform(node.find("transform"), values)
            material = None
            for child in node:
                if child.tag == "bsdf":
                    material = _material_of(child, values, bsdfs)
                elif child.tag == "ref":
                    material = bsdfs[child.attrib["id"]]
            shapes.append({"id": a.get("id", ""), "kind": "rect" if a["type"] == "rectangle" else "disc",
                           "c": m[:3, 3].copy(), "e1": m[:3, 0].copy(), "e2": m[:3, 1].copy(),
                           "n": m[:3, 2] / np.linalg.norm(m[:3, 2]),
                           "detector": node.find("emitter") is not None, "material": material})


def read_scene(name, **params):
    """(shapes, parameter values) of ``scenes_xml/<name>.xml``; ``params`` override defaults.

    Each shape: id, kind ('rect': |a|, |b| <= 1; 'disc': a^2 + b^2 <= 1 in x = c + a e1 + b e2),
    front normal n, detector (carries an area emitter), material (elo_bse material or None).
    """
    values = {k: str(v) for k, v in params.items()}
    shapes = []
    _read(SCENES / f"{name}.xml", values, {}, shapes)
    return shapes, values


# ---- occlusion --------------------------------------------------------------------------------------------
def blocked(shapes, o, v, skip=()):
    """Whether the segments o .. o + v cross any shape (the end points excluded)."""
    out = np.zeros(v.shape[:-1], bool)
    for i, s in enumerate(shapes):
        if i in skip:
            continue
        n, c = s["n"], s["c"]
        den = v @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((c - o) @ n) / den
        ok = np.isfinite(t) & (t > _EPS) & (t < 1 - _EPS)
        x = o + t[..., None] * v - c
        a = (x @ s["e1"]) / (s["e1"] @ s["e1"])
        b = (x @ s["e2"]) / (s["e2"] @ s["e2"])
        inside = (np.abs(a) <= 1) & (np.abs(b) <= 1) if s["kind"] == "rect" else a * a + b * b <= 1
        out |= ok & inside
    return out


# ---- g_BSE ----------------------------------------------------------------------------------------------
class FastG:
    """g_BSE (Eq. 13, cosine included) of one material for many out-directions per incidence:
    eta0/pi max(cos a, 0) + W(theta) max(cos b, 0)^k with W from the physics module's table."""

    def __init__(self, material, lobe_width_deg=LOBE_WIDTH_DEG):
        self.material = get_material(material)
        self.width = lobe_width_deg
        self.theta_deg, self.w = lobe_weight_table(self.material, lobe_width_deg, TABLE_SIZE)

    def setup(self, normal, beam_dir):
        """Per incidence (normal, travel direction of the arriving electrons): (n, mirror, k, W, ok)."""
        cos_t = -np.sum(normal * beam_dir, axis=-1)
        theta = np.rad2deg(np.arccos(np.clip(cos_t, 0.0, 1.0)))
        mirror = beam_dir - 2.0 * np.sum(beam_dir * normal, axis=-1)[..., None] * normal
        return normal, mirror, theta / self.width, np.interp(theta, self.theta_deg, self.w), cos_t > 0

    def eval(self, setup, out_dir):
        """g_BSE towards unit ``out_dir`` (..., m, 3) for a setup of shape (..., )."""
        n, mirror, k, w, ok = setup
        cos_a = np.einsum("...j,...mj->...m", n, out_dir)
        cos_b = np.einsum("...j,...mj->...m", mirror, out_dir)
        lobe = np.where(cos_b > 0, np.power(np.maximum(cos_b, 1e-300), k[..., None]), 0.0)
        g = self.material.eta0 / np.pi * cos_a + w[..., None] * lobe
        return np.where(ok[..., None] & (cos_a > 0), g, 0.0)


def check_fast_g(material, n=2000, seed=0):
    """Largest relative difference between :class:`FastG` and the exact ``g_bse`` on random
    incidences and directions (where g_BSE > 1e-3 of its maximum)."""
    rng = np.random.default_rng(seed)
    normal = rng.normal(size=(n, 3))
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    beam = rng.normal(size=(n, 3))
    beam /= np.linalg.norm(beam, axis=-1, keepdims=True)
    out = rng.normal(size=(n, 3))
    out /= np.linalg.norm(out, axis=-1, keepdims=True)
    fast = FastG(material)
    a = fast.eval(fast.setup(normal, beam), out[:, None, :])[:, 0]
    b = g_bse(normal, beam, out, fast.material)
    big = b > 1e-3 * b.max()
    return float(np.max(np.abs(a[big] - b[big]) / b[big])), int(big.sum())


# ---- the 2nd event ----------------------------------------------------------------------------------------
def _disc_points(shape, n_r, n_ang, turns):
    """Midpoints of n_r x n_ang equal-area cells of a disc, the pattern turned by ``turns`` (m,)
    of a full turn per point of the other leg; points (m, n_r n_ang, 3) and the area of a cell."""
    r = np.sqrt((np.arange(n_r) + 0.5) / n_r)
    ang = (np.arange(n_ang) + 0.5) * (2 * np.pi / n_ang)
    r, ang = (x.ravel() for x in np.meshgrid(r, ang, indexing="ij"))
    ang = ang[None, :] + 2 * np.pi * turns[:, None]
    a, b = (r * np.cos(ang))[..., None], (r * np.sin(ang))[..., None]
    pts = shape["c"] + a * shape["e1"] + b * shape["e2"]
    radius = np.linalg.norm(shape["e1"])
    return pts, np.pi * radius**2 / (n_r * n_ang)


def _cells(shape, cell_mm):
    """Midpoint cells of about ``cell_mm`` on a rectangle: (centres (m, 3), their (a, b) in
    [-1, 1]^2 (m, 2), (na, nb) cells along e1, e2, area of a cell)."""
    l1, l2 = np.linalg.norm(shape["e1"]), np.linalg.norm(shape["e2"])
    na, nb = max(1, int(np.ceil(2 * l1 / cell_mm))), max(1, int(np.ceil(2 * l2 / cell_mm)))
    a = -1 + (2 * np.arange(na) + 1) / na
    b = -1 + (2 * np.arange(nb) + 1) / nb
    ab = np.stack(np.meshgrid(a, b, indexing="ij"), axis=-1).reshape(-1, 2)
    centres = shape["c"] + ab[:, :1] * shape["e1"] + ab[:, 1:] * shape["e2"]
    return centres, ab, (na, nb), 4 * l1 * l2 / (na * nb)


def _sub_points(shape, ab, n_cells, n):
    """``n`` points in each cell (centre ab), as (m, n, 3): a golden-ratio lattice, whose points
    all differ in both coordinates, so that a shadow edge along the cell grid (the shield's and
    the sheet's edges are) is resolved to 1/n of a cell, not 1/sqrt(n)."""
    i = np.arange(n) + 0.5
    u, v = 2 * i / n - 1, 2 * np.mod(i * _GOLDEN, 1.0) - 1  # in cell half-widths
    sa = (ab[:, :1] + u[None, :] / n_cells[0])[..., None]
    sb = (ab[:, 1:] + v[None, :] / n_cells[1])[..., None]
    return shape["c"] + sa * shape["e1"] + sb * shape["e2"]


def _first_leg(shapes, index, p, beam, plate, points):
    """g_plate(w1) cos(n_S, -w1) / r^2 V1 at ``points`` (m, k, 3) on shape ``index``, and the
    visibility V1 (the segment from p reaches the point unblocked, on the shape's front side)."""
    s = shapes[index]
    v = points - p
    r2 = np.sum(v * v, axis=-1)
    w1 = v / np.sqrt(r2)[..., None]
    cos_q = -(w1 @ s["n"])
    f = g_bse(plate["n"], beam, w1, get_material(plate["material"])) * np.maximum(cos_q, 0.0) / r2
    seen = np.zeros(f.shape, bool)
    live = f > 0
    seen[live] = ~blocked(shapes, p, v[live], skip=(index,))
    return np.where(seen, f, 0.0), seen


def second_event(name, point, detector="right", cell_mm=5.0, sub=4, refine=64, n_r=2, n_ang=4, chunk=8192,
                 **params):
    """N_d/N_0 of the 2nd event for ``detector`` with the beam on ``point`` (x, y) of the plate.

    The beam comes from the pivot (0, 0, wd) (perspective, the scene's ``wd``) and meets the plate
    (the shape with id ``plate``, normal +z) at p = (x, y, 0). The integral over the directions
    leaving p is written over the area of every scattering rectangle S (the 2nd event's q),

        e2 = sum_S int_S g_plate(w1) cos(n_S, -w1) / |q - p|^2 V1(p, q) D(q, w1) dA,  w1 = (q - p)/|q - p|,

    on cells of about ``cell_mm``; g_plate cos / r^2 V1 (cheap, discontinuous at shadows) is
    averaged over ``sub`` points of each cell (``refine`` points in the cells a shadow edge
    crosses), D (costly; smooth but where the detector is partly hidden from q) is taken at the
    cell's centroid weighted by that factor (on the lit side of a shadow edge in the cell) with
    ``n_r`` x ``n_ang`` midpoints on the detector disc, the pattern turned by the golden angle
    from cell to cell so that the steps of the hidden part do not line up with the grid. The
    edges of the walls, the gun opening and the plate need no resolution: they are edges of the
    domains.

    Returns the value and, per shape id, its share (where the electrons scattered the 2nd time).
    """
    shapes, values = read_scene(name, **params)
    if values.get("projection", "perspective") != "perspective":
        raise ValueError("only the perspective beam is modelled here")
    by_id = {s["id"]: i for i, s in enumerate(shapes)}
    plate = shapes[by_id["plate"]]
    det_index = by_id[detector]
    det = shapes[det_index]
    p = np.array([point[0], point[1], 0.0])
    pivot = np.array([0.0, 0.0, float(values["wd"])])
    beam = (p - pivot) / np.linalg.norm(p - pivot)
    if blocked(shapes, pivot, p - pivot, skip=(by_id["plate"],)):
        raise ValueError(f"the beam from the pivot to {point} is blocked")
    if any(s["detector"] and s["material"] is not None for s in shapes):
        raise ValueError("backscattering detector plates (plates=copper) are not modelled here")
    fast = {m: FastG(m) for m in {s["material"] for s in shapes if s["material"] is not None}}

    total, shares = 0.0, {}
    for index, s in enumerate(shapes):
        if s["detector"] or s["material"] is None or s is plate:
            continue  # detectors absorb; an absorber scatters nothing
        if s["kind"] != "rect":
            raise ValueError(f"scatterer {s['id']!r}: only rectangles are integrated here")
        if abs((s["c"] - p) @ s["n"]) < _EPS:
            continue  # in the plane of p (the floor): no direction from p reaches it
        _, ab, n_cells, cell_area = _cells(s, cell_mm)
        # the cheap factor at sub points per cell; where V1 changes inside a cell (a shadow edge:
        # a detector, the sheet, the shield), again at refine points
        points = _sub_points(s, ab, n_cells, sub)
        f, seen = _first_leg(shapes, index, p, beam, plate, points)
        q = np.sum(f[..., None] * points, axis=1)  # the cell's centroid weighted by f
        f = f.sum(axis=-1)
        mixed = np.any(seen, axis=-1) & ~np.all(seen, axis=-1)
        if np.any(mixed) and refine > sub:
            points = _sub_points(s, ab[mixed], n_cells, refine)
            f_fine = _first_leg(shapes, index, p, beam, plate, points)[0]
            q[mixed] = np.sum(f_fine[..., None] * points, axis=1) * (sub / refine)
            f[mixed] = f_fine.sum(axis=-1) * (sub / refine)
        # D where the electrons land: at each cell's centroid of g_plate cos / r^2 V1 (on the
        # visible side of a shadow edge that crosses the cell, e.g. where the sheet meets the ceiling)
        keep = f > 0
        q, f = q[keep] / f[keep, None], f[keep] / sub
        w1c = q - p
        w1c /= np.linalg.norm(w1c, axis=-1, keepdims=True)
        targets, disc_area = _disc_points(det, n_r, n_ang, np.mod(np.flatnonzero(keep) * _GOLDEN, 1.0))
        g_wall = fast[s["material"]]
        d_val = np.zeros(len(q))
        for start in range(0, len(q), chunk):
            sl = slice(start, start + chunk)
            vq = targets[sl] - q[sl, None, :]  # (m, P, 3)
            rq2 = np.sum(vq * vq, axis=-1)
            w2 = vq / np.sqrt(rq2)[..., None]
            cos_d = np.abs(w2 @ det["n"])  # both faces collect
            normal = np.broadcast_to(s["n"], w1c[sl].shape)
            g2 = g_wall.eval(g_wall.setup(normal, w1c[sl]), w2)
            vis = ~blocked(shapes, q[sl, None, :], vq, skip=(det_index, index))
            d_val[sl] = np.sum(np.where(vis, g2 * cos_d / rq2, 0.0), axis=-1) * disc_area
        part = float(np.sum(f * d_val) * cell_area)
        if part > 0:
            shares[s["id"]] = part
            total += part
    return total, shares
