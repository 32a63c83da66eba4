"""The scan set-up that the model-based analysis inverts: beam, scan grid, disc detectors, material.

:class:`ScanGeometry` holds what an EXR header of the forward model records (field, resolution,
work distance, projection, aim offset, the detectors' centres, normals and radii, the plate's
material) or what a user gives for recorded machine images (``--field --dh --dw [--radius]``),
optionally corrected by a detector calibration (:mod:`elo_mitsuba.analysis.calibration`).

Pixel (i, j) is scan point (i, j) of :mod:`elo_mitsuba.grid`. The beam leaves the pivot
(0, 0, wd) towards that point of the build plane z = 0 (``perspective``) or runs parallel to -z
(``orthographic``), as the sensor ``elo_beam`` does; on a surface of height h the electron lands
where that ray crosses z = h (:meth:`ScanGeometry.beam`).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Mapping

import numpy as np

from ..constants import (
    DEFAULT_MATERIAL,
    DETECTOR_DIAMETER_MM,
    DETECTOR_DIRECTIONS,
    DETECTOR_NAMES,
    WORK_DISTANCE_MM,
)
from ..errors import EloInputError
from ..grid import field_xy, pixel_coordinates, pixel_size
from ..schema import LENGTH_RANGE, PROJECTIONS, is_length, HeaderGeometry, geometry_header, read_geometry
from .layout import check_detector_geometry


#: The most scan points a side (a 1 m field at 1 um pixels): a larger number is a slip.
MAX_SIDE = 1_000_000


@dataclass(frozen=True)
class Disc:
    """A disc detector: centre (mm), unit front normal (towards the scan field), radius (mm)."""

    center: tuple
    normal: tuple
    radius: float

    def __post_init__(self):
        c = np.asarray(self.center, dtype=float).reshape(-1)
        n = np.asarray(self.normal, dtype=float).reshape(-1)
        if c.shape != (3,) or n.shape != (3,) or not (np.all(np.isfinite(c)) and np.all(np.isfinite(n))):
            raise EloInputError(f"detector centre {self.center!r} / normal {self.normal!r}: need 3 finite values each")
        length = float(np.linalg.norm(n))
        if not length > 0:
            raise EloInputError(f"detector normal {self.normal!r}: must not be zero")
        r = float(self.radius)
        if not is_length(r):
            raise EloInputError(f"detector radius {self.radius!r} mm: must be {LENGTH_RANGE}")
        object.__setattr__(self, "center", tuple(float(v) for v in c))
        # a unit normal is kept as given: normalising it again can change its last bit, and a disc
        # read back from CALIB.json must equal the one written
        unit = n if abs(length - 1.0) <= 1e-12 else n / length
        object.__setattr__(self, "normal", tuple(float(v) for v in unit))
        object.__setattr__(self, "radius", r)

    def as_dict(self) -> dict:
        return {"center": list(self.center), "normal": list(self.normal), "radius": self.radius}


@dataclass(frozen=True)
class ScanGeometry:
    """Everything the 1st-event model needs about one scan.

    Attributes
    ----------
    field_mm : (float, float)
        Scan field (x, y) in mm.
    shape : (int, int)
        Image shape (H, W).
    detectors : dict of str to Disc
        By channel name.
    work_distance_mm : float
        Height of the beam pivot above z = 0.
    projection : str
        ``perspective`` or ``orthographic``.
    aim_offset_mm : (float, float)
        Constant offset of every aim point (the sensor's sub-pixel nudge).
    material : str
        The surface material (preset name or composition).
    """

    field_mm: tuple
    shape: tuple
    detectors: Mapping = field(default_factory=dict)
    work_distance_mm: float = WORK_DISTANCE_MM
    projection: str = "perspective"
    aim_offset_mm: tuple = (0.0, 0.0)
    material: str = DEFAULT_MATERIAL

    def __post_init__(self):
        if self.projection not in PROJECTIONS:
            raise EloInputError(f"projection {self.projection!r}: choose {' or '.join(PROJECTIONS)}")
        wd = float(self.work_distance_mm)
        if not (np.isfinite(wd) and wd > 0):
            raise EloInputError(f"work distance {self.work_distance_mm!r} mm: must be finite and > 0")
        try:  # (rows, columns): whole numbers, not a truncated 16.5 or a third axis
            h, w = (int(v) for v in self.shape)
            ok = (h, w) == tuple(self.shape) and 1 <= min(h, w) and max(h, w) <= MAX_SIDE
        except (TypeError, ValueError, OverflowError):
            ok = False
        if not ok:
            raise EloInputError(f"shape {self.shape!r}: give (rows, columns), two whole numbers from 1 to {MAX_SIDE}")
        object.__setattr__(self, "shape", (h, w))
        object.__setattr__(self, "field_mm", field_xy(self.field_mm, (h, w)))
        object.__setattr__(self, "work_distance_mm", wd)
        try:
            offset = np.asarray(self.aim_offset_mm, dtype=float).reshape(-1)
        except (TypeError, ValueError, OverflowError):
            offset = np.array([np.nan])
        if offset.shape != (2,) or not np.all(np.isfinite(offset)):
            raise EloInputError(f"aim_offset_mm {self.aim_offset_mm!r}: need 2 finite numbers (x, y) in mm")
        object.__setattr__(self, "aim_offset_mm", (float(offset[0]), float(offset[1])))
        object.__setattr__(self, "detectors", dict(self.detectors))
        from ..physics import get_material

        get_material(self.material)  # an unknown material fails here, with its one line

    # -- construction --
    @classmethod
    def nominal(cls, shape, field_mm, d_h, d_w, *, radius=DETECTOR_DIAMETER_MM / 2, **kw) -> "ScanGeometry":
        """The symmetric layout of Eq. 17: four discs at (+-d_w, 0, d_h), (0, +-d_w, d_h), facing the
        origin, of radius ``radius`` (mm; ATHENE's 50 mm discs by default)."""
        d_h, d_w = check_detector_geometry(d_h, d_w)
        dets = {}
        for name in DETECTOR_NAMES:
            ex, ey = DETECTOR_DIRECTIONS[name]
            c = np.array([d_w * ex, d_w * ey, d_h], dtype=float)
            dets[name] = Disc(c, -c, radius)
        return cls(field_mm=field_mm, shape=shape, detectors=dets, **kw)

    @classmethod
    def from_metadata(cls, meta: Mapping, shape, source: str = "header", *, field_mm=None,
                      material: str | None = None) -> "ScanGeometry":
        """The geometry an EXR header of ``elo-mitsuba render`` records (detectors as discs of the
        header's centre, normal and equivalent radius), read by :func:`~elo_mitsuba.schema.read_geometry`."""
        return cls.from_header(read_geometry(meta, source, shape=shape, field_mm=field_mm), shape, material=material)

    @classmethod
    def from_header(cls, header: HeaderGeometry, shape, *, material: str | None = None) -> "ScanGeometry":
        """The scan geometry of a header read by :func:`~elo_mitsuba.schema.read_geometry`: its
        detectors as discs (centre, normal, radius each required)."""
        dets, source = header.detectors, header.source
        if not isinstance(dets, Mapping) or not all(n in dets for n in DETECTOR_NAMES):
            missing = [n for n in DETECTOR_NAMES if not isinstance(dets, Mapping) or n not in dets]
            raise EloInputError(f"{source}: header lacks the detector{'s' if len(missing) > 1 else ''} "
                                f"{', '.join(missing)}; pass --dh and --dw (mm) and, if not 25, --radius")
        discs = {}
        for name in DETECTOR_NAMES:
            d = dets[name]
            try:
                discs[name] = Disc(d["center"], d["normal"], d["radius"])
            except (KeyError, TypeError) as exc:
                raise EloInputError(f"{source}: detector {name!r} lacks {exc} (need center, normal, radius)") from None
        if material is None and header.material is not None:  # the header's: its file is named
            from ..physics import get_material

            try:
                get_material(header.material)
            except EloInputError as exc:
                raise EloInputError(f"{source}: header {exc}") from None
        return cls(field_mm=header.field_mm, shape=shape, detectors=discs,
                   work_distance_mm=header.work_distance_mm, projection=header.projection,
                   aim_offset_mm=header.aim_offset_mm, material=header.material if material is None else material)

    def with_detectors(self, detectors: Mapping) -> "ScanGeometry":
        """A copy whose detectors are replaced (e.g. by a calibration's)."""
        return replace(self, detectors={**self.detectors, **dict(detectors)})

    def resized(self, shape) -> "ScanGeometry":
        """The same scan sampled on another grid (same field)."""
        return replace(self, shape=tuple(shape))

    def cropped(self, rows, cols) -> "ScanGeometry":
        """The scan geometry of the window ``rows`` x ``cols`` (start, stop) of this grid: the same
        pixels (their aim points, beam and detectors), a smaller field, offset aim points (the local
        refinement's and the step search's windows).

        Examples
        --------
        >>> geo = ScanGeometry.nominal((8, 8), 8.0, 100.0, 150.0)
        >>> sub = geo.cropped((2, 5), (4, 8))
        >>> bool(np.allclose(sub.aim_points()[0], geo.aim_points()[0][2:5, 4:8]))
        True
        """
        dx, dy = pixel_size(self.shape, self.field_mm)
        fx, fy = self.field_mm
        (r0, r1), (c0, c1) = rows, cols
        xc = -0.5 * fx + 0.5 * (c0 + c1) * dx + self.aim_offset_mm[0]
        yc = 0.5 * fy - 0.5 * (r0 + r1) * dy + self.aim_offset_mm[1]
        return replace(self, shape=(r1 - r0, c1 - c0), field_mm=((c1 - c0) * dx, (r1 - r0) * dy),
                       aim_offset_mm=(xc, yc))

    # -- the beam --
    def aim_points(self) -> tuple[np.ndarray, np.ndarray]:
        """Aim points (x, y) on z = 0 of every pixel (mm), each (H, W)."""
        x, y = pixel_coordinates(self.shape, self.field_mm)
        return x + self.aim_offset_mm[0], y + self.aim_offset_mm[1]

    def beam(self, heights=None) -> tuple[np.ndarray, np.ndarray]:
        """Landing points and unit directions of travel of the beam, each (H, W, 3).

        ``heights`` (mm, (H, W) or scalar): the surface height under each pixel; the electron lands
        where its ray crosses z = h. None: z = 0.
        """
        x, y = self.aim_points()
        h = np.zeros(self.shape) if heights is None else np.broadcast_to(np.asarray(heights, float), self.shape)
        wd = self.work_distance_mm
        if self.projection == "perspective":
            t = 1.0 - h / wd
            points = np.stack([t * x, t * y, h], axis=-1)
            dirs = np.stack([x, y, np.full(self.shape, -wd)], axis=-1)
            dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
        else:
            points = np.stack([x, y, h], axis=-1)
            dirs = np.broadcast_to(np.array([0.0, 0.0, -1.0]), points.shape).copy()
        return points, dirs

    def landing_heights(self, surface, iterations: int = 8) -> np.ndarray:
        """Heights (H, W) where each pixel's beam lands on the surface ``surface(x, y) -> z`` (mm):
        the fixed point h = Z(t x, t y), t = 1 - h / wd, of the perspective beam (a contraction for
        |grad Z| |x| / wd < 1); Z(x, y) of the aim points for the orthographic one."""
        x, y = self.aim_points()
        h = np.asarray(surface(x, y), float)
        if self.projection != "perspective":
            return h
        for _ in range(int(iterations)):
            t = 1.0 - h / self.work_distance_mm
            h = np.asarray(surface(x * t, y * t), float)
        return h

    def symmetric_layout(self) -> tuple[float, float]:
        """Mean d_h (centre z) and d_w (centre distance from the z-axis) of the four detectors,
        the Eq. 17 geometry closest to this one (Eq. 26's start needs it)."""
        c = np.array([self.detectors[n].center for n in DETECTOR_NAMES])
        return float(np.mean(c[:, 2])), float(np.mean(np.hypot(c[:, 0], c[:, 1])))

    def as_dict(self) -> dict:
        """The header's geometry block (:func:`~elo_mitsuba.schema.geometry_header`)."""
        return geometry_header(self.field_mm, self.shape, work_distance_mm=self.work_distance_mm,
                               projection=self.projection, aim_offset_mm=self.aim_offset_mm, material=self.material,
                               detectors={k: d.as_dict() for k, d in self.detectors.items()})
