"""Sensor ``elo_beam``: the scanned electron gun (Renner et al. 2023, Sec. 2.1.1, Fig. 1a).

Film pixel (i, j) is scan point (i, j): the beam aims at the pixel centre of the package's image
orientation (:func:`elo_mitsuba.grid.film_to_plane`: columns towards +x, row 0 at the +y edge),
nudged by less than 1 % of a pixel (``_AIM_NUDGE``); field_y = field H/W keeps pixels square.
Every beam ray leaves the pivot (0, 0, wd) towards its grid point on the build plane z = 0 (``projection="perspective"``, deflection angle phi grows
towards the edges, so theta = phi on a flat plate), or runs parallel to -z from (x, y, wd)
(``"orthographic"``).

With ``fwhm = 0`` (default) each sample of a pixel is the paper's single ray through the grid
point. With ``fwhm > 0`` (mm, on the build plane; ATHENE's is about 0.27 mm, Sec. 3.2) the
sample's aim point is spread by an isotropic Gaussian of that FWHM around the grid point: the
image is convolved with the beam profile, the blur the paper's model lacks. The Gaussian offset
is drawn from the uniform sub-pixel position Mitsuba passes in (with a box filter each sample
lands in its own pixel), so no extra sample dimension is needed.

XML parameters: ``wd`` (mm, default 400: ATHENE's is not published), ``field`` (mm, 80),
``projection``, ``fwhm`` (mm, 0), and a nested ``hdrfilm`` (width, height, ``box`` filter).
"""

import drjit as dr
import mitsuba as mi
import numpy as np

from elo_mitsuba.constants import FIELD_MM, WORK_DISTANCE_MM
from elo_mitsuba.errors import EloInputError
from elo_mitsuba.grid import film_to_plane
from elo_mitsuba.schema import FWHM_RANGE, LENGTH_RANGE, MIN_LENGTH_MM, fwhm_to_sigma, is_fwhm, is_length

#: Aim-point nudge, in pixel pitches: Mitsuba's ray-triangle test is not watertight, so a beam ray
#: aimed exactly at a vertex or edge of a mesh built on the same grid as the scan (a height map
#: rendered at its own resolution) can pass through the surface, and with fwhm = 0 every sample of
#: that pixel repeats the miss. Unequal, irrational-ish fractions of a pixel (< 1 %, 0.4 um on
#: ATHENE's 53 um pixels; the beam spot is 270 um) keep the rays off regular grids' vertices and
#: edges, including the diagonals.
_AIM_NUDGE = (7.18e-3, 3.91e-3)
#: ... but never more than this in mm (3 um): coarse test grids must stay on their points.
_AIM_NUDGE_MAX_MM = (2.9e-3, 1.6e-3)
PROJECTIONS = ("perspective", "orthographic")


def _positive(props, name, default, allow_zero=False):
    return _check_length(name, float(props.get(name, default)), allow_zero)


def _check_length(name, value, allow_zero=False):
    """``value`` (mm) within the lengths an output header may hold (:func:`is_length`): a render
    never writes a file that the package's own reader refuses (wd=1e-300 did), and a field of
    1e-300 mm no longer reaches the presets' window arithmetic.
    ``allow_zero`` (the beam's FWHM): :func:`is_fwhm`, its upper bound being the scan field
    (checked with the film)."""
    if allow_zero:
        ok, bound = is_fwhm(value), FWHM_RANGE
    else:
        ok, bound = is_length(value), LENGTH_RANGE
    if not ok:
        raise EloInputError(f"elo_beam: {name}={value!r} mm; must be {bound}")
    return value


class EloBeam(mi.Sensor):
    def __init__(self, props):
        mi.Sensor.__init__(self, props)
        self.wd = _positive(props, "wd", WORK_DISTANCE_MM)
        self.field = _positive(props, "field", FIELD_MM)
        self.fwhm = _positive(props, "fwhm", 0.0, allow_zero=True)
        self.projection = str(props.get("projection", "perspective"))
        if self.projection not in PROJECTIONS:
            raise EloInputError(
                f"elo_beam: projection={self.projection!r}; allowed: {', '.join(PROJECTIONS)}"
            )
        if "to_world" in props:  # the gun stands on the z-axis at wd, aiming down
            raise EloInputError("elo_beam: a to_world transform would be ignored; the gun stands on the z-axis, "
                                "wd mm above the plate (move the scene instead, or set wd / field)")
        res = self.film().size()
        self.resolution = (int(res[0]), int(res[1]))
        if min(self.resolution) < 1:
            raise EloInputError(f"elo_beam: film resolution {self.resolution}; must be >= 1 x 1")
        crop, offset = self.film().crop_size(), self.film().crop_offset()
        if (int(crop[0]), int(crop[1])) != self.resolution or int(offset[0]) or int(offset[1]):
            # the scan would be squeezed into the crop, and headers would describe the whole field
            raise EloInputError(f"elo_beam: the film crops {int(crop[0])}x{int(crop[1])} px at ({int(offset[0])}, "
                                f"{int(offset[1])}) of {self.resolution[0]}x{self.resolution[1]}; a crop is not "
                                "supported: set the scan field (field) and the resolution instead")
        if self.film().rfilter().radius() > 0.5 + 1e-6:
            raise EloInputError(
                "elo_beam: the film needs <rfilter type=\"box\"/> so that each beam position "
                "lands in its own pixel"
            )
        self.field_y = self.field * self.resolution[1] / self.resolution[0]
        if self.fwhm >= max(self.field, self.field_y):  # the larger side: a line scan has one row
            # such a beam lights the whole field at every scan point: no image (fwhm=1e30 rendered zeros)
            raise EloInputError(f"elo_beam: fwhm={self.fwhm:g} mm; must be below the scan field's "
                                f"{max(self.field, self.field_y):g} mm (a beam profile is a fraction of a millimetre)")
        pitch = (self.field / self.resolution[0], self.field_y / self.resolution[1])
        if min(pitch) < MIN_LENGTH_MM:  # the header's pixel size must read back (schema.check_header)
            raise EloInputError(f"elo_beam: field={self.field:g} mm over {self.resolution[0]}x{self.resolution[1]} px "
                                f"is a pixel of {min(pitch):.3g} mm; pixels must be >= {MIN_LENGTH_MM:g} mm "
                                "(a larger field or fewer pixels)")
        #: (dx, dy) mm: the beam aims at every pixel centre plus this (recorded in output headers)
        self.aim_offset_mm = tuple(min(f * p, cap) for f, p, cap in zip(_AIM_NUDGE, pitch, _AIM_NUDGE_MAX_MM))
        self.sigma = mi.Float(fwhm_to_sigma(self.fwhm))
        self._wd = mi.Float(self.wd)
        self._field = mi.Vector2f(self.field, self.field_y)
        dr.make_opaque(self.sigma, self._wd, self._field)

    def traverse(self, callback):
        mi.Sensor.traverse(self, callback)
        callback.put("wd", self._wd, mi.ParamFlags.NonDifferentiable)

    def parameters_changed(self, keys=[]):
        mi.Sensor.parameters_changed(self, keys)
        self.wd = _check_length("wd", float(self._wd[0]))

    def centre_rays(self, offset_mm=(0.0, 0.0)):
        """The beam's rays at the pixel centres (no profile), moved by ``offset_mm`` (dx, dy) on
        the build plane, pixel by pixel in film order (row j, column i at j W + i): origins and
        unit directions as float64 arrays (N, 3), computed on the host, so that they do not
        depend on the instruction set Dr.Jit compiles for (plugins/_geometry_classes.py)."""
        w, h = self.resolution
        u = (np.arange(w) + 0.5) / w
        v = (np.arange(h) + 0.5) / h
        x, y = film_to_plane(u[None, :], v[:, None], self.field, self.field_y)
        x = np.broadcast_to(x + self.aim_offset_mm[0] + offset_mm[0], (h, w)).ravel()
        y = np.broadcast_to(y + self.aim_offset_mm[1] + offset_mm[1], (h, w)).ravel()
        if self.projection == "perspective":
            o = np.zeros((x.size, 3))
            o[:, 2] = self.wd
            d = np.stack([x, y, np.full(x.size, -self.wd)], axis=1)
            d /= np.linalg.norm(d, axis=1, keepdims=True)
        else:
            o = np.stack([x, y, np.full(x.size, self.wd)], axis=1)
            d = np.zeros((x.size, 3))
            d[:, 2] = -1.0
        return o, d

    def beam_target(self, film_sample):
        """Build-plane point (x, y) in mm the sample aims at (grid point + beam profile offset)."""
        res = mi.Vector2f(self.resolution[0], self.resolution[1])
        scaled = film_sample * res
        pixel = self._film_pixel(scaled)
        centre = (pixel + 0.5) / res  # on the scan grid (up to _AIM_NUDGE)
        x, y = film_to_plane(centre.x, centre.y, self._field.x, self._field.y)
        x = x + self.aim_offset_mm[0]
        y = y + self.aim_offset_mm[1]
        if self.fwhm > 0:
            jitter = dr.clip(scaled - pixel, 1e-7, 1.0 - 1e-7)  # uniform in the pixel
            offset = mi.warp.square_to_std_normal(jitter) * self.sigma
            x += offset.x
            y += offset.y
        return x, y

    def _film_pixel(self, scaled):
        """The pixel whose sample ``scaled`` (film position x resolution) is.

        Mitsuba's render passes pixel + u (u uniform in [0, 1)) scaled to [0, 1], in float32,
        and puts the sample into the pixel itself (box filter). The sum and the scalings round: u
        within a few ulp of 1 reads as the next pixel (148 of the 2.25 M pixels of one render at
        1500², each then aimed at its neighbour's scan point). Its render lays the lanes out
        pixel by pixel, spp each, rows first; a wavefront of that shape takes the pixel from the
        lane where it is the floor's or one next to it (anything else: the floor's, e.g. a call
        with positions of its own)."""
        pixel = dr.floor(scaled)
        w, h = self.resolution
        n = dr.width(scaled)
        if not dr.is_jit_v(type(scaled)) or n < w * h or n % (w * h):
            return pixel
        lane = dr.arange(mi.UInt32, n) // dr.opaque(mi.UInt32, n // (w * h))
        row = lane // dr.opaque(mi.UInt32, w)
        mine = mi.Vector2f(mi.Float(lane - row * w), mi.Float(row))
        near = (dr.abs(mine.x - pixel.x) <= 1.0) & (dr.abs(mine.y - pixel.y) <= 1.0)
        return dr.select(near, mine, pixel)

    def sample_ray(self, time, sample1, sample2, sample3, active=True):
        x, y = self.beam_target(sample2)
        if self.projection == "perspective":
            origin = mi.Point3f(0.0, 0.0, self._wd)
            direction = dr.normalize(mi.Vector3f(x, y, -self._wd))
        else:
            origin = mi.Point3f(x, y, self._wd)
            direction = mi.Vector3f(0.0, 0.0, -1.0)
        ray = mi.Ray3f(origin, direction, time, mi.Color0f())
        return ray, mi.Spectrum(1.0)

    def sample_ray_differential(self, time, sample1, sample2, sample3, active=True):
        ray, weight = self.sample_ray(time, sample1, sample2, sample3, active)
        return mi.RayDifferential3f(ray), weight

    def bbox(self):
        return mi.ScalarBoundingBox3f(mi.ScalarPoint3f(0, 0, self.wd))

    def to_string(self):
        return (f"EloBeam[{self.projection}, wd={self.wd:g} mm, field={self.field:g} x "
                f"{self.field_y:g} mm, {self.resolution[0]} x {self.resolution[1]} px, "
                f"fwhm={self.fwhm:g} mm]")


PLUGIN_CLASS = EloBeam
