"""Integrator ``elo``: electrons traced forward from the gun to every detector (Sec. 2.1.1).

The gun is the sensor (``elo_beam``), so a film pixel is a scan point; surfaces carry the
``elo_bse`` BSDF whose ``eval`` is g_BSE (cosine included, ``wi`` towards where the electron came
from); detectors are the shapes carrying an area emitter (unit radiance). Scattering event n is
path vertex n. At every event the integrator estimates, separately for each detector and with
occlusion, the electrons that reach it directly,

    N_{n,d} / N_0 = throughput * int_{Omega_d} g_BSE dOmega          (Eq. 5, and Eq. 8 for n > 1),

and then continues the path by sampling g_BSE (Eq. 7): the sample weight carries the electrons
that leave in that direction. A continuation ray that hits a detector ends there (the electrons
are absorbed, Eq. 6; they were counted by the direct estimate, so nothing is counted twice); one
that leaves the scene is lost. No bounce ray is traced after the last counted event.

Detectors collect on both faces (a metal plate collects charge on either side; the paper's
detectors "integrate all incoming electrons"); ``front_only`` names detectors shielded on their
back, which collect on the front face only and absorb on the back. A detector whose shape
carries an ``elo_bse`` BSDF (e.g. copper plates, ``plates=copper`` in the shipped scenes)
backscatters: it keeps 1 - eta(theta) of what arrives at angle theta to its normal, and the
backscattered electrons travel on from it by its g_BSE (crosstalk onto other detectors, the
chamber); without such a BSDF a detector keeps everything (the paper's model).

Detector integral of the 1st event (``detector_sampling``):

* ``independent`` (default): ``detector_samples`` uniform points on each detector (Mitsuba's
  area-emitter sampling), each with its own shadow ray;
* ``stratified``: the same number of points, one in each stratum of the unit square (rows x
  columns, unequal strata weighted by their area) mapped onto the detector: unbiased, far less
  noise for the smooth 1st-event integrand;
* ``quadrature``: Appendix A, Eq. A2: the detector as ``quadrature_triangles`` triangles
  (:mod:`._detectors`), each weighted by its solid angle from the Van Oosterom-Strackee formula
  (Eq. A1 with the corrected denominator, :mod:`elo_mitsuba.physics.solid_angle`) and g_BSE at
  its centroid. Occlusion: ``quadrature_visibility="sampled"`` (default) casts ONE shadow ray per
  detector, to a point drawn in a triangle chosen with probability proportional to its weight:
  exact (no noise) wherever the detector is fully visible or fully hidden, unbiased in between;
  ``"triangle"`` casts one ray per triangle centroid (deterministic). Its error is deterministic
  (measured: < 5e-4 with 4 triangles, < 4e-4 with 8, < 2e-4 with 24 on the 50 mm discs); with
  ``fwhm = 0`` one sample per pixel gives the converged 1st event.

Events >= 2 sample ``bounce_detector_samples`` points per detector (independent, or stratified
when ``detector_sampling`` is stratified or quadrature). Their budget is set apart from the 1st
event's, without bias: ``bounce_fraction`` f traces the continuation for a fraction f of the
samples (whole blocks of 32 neighbouring lanes, chosen by a randomly shifted golden-ratio
sequence, weight 1/f; skipped blocks really skip the work), ``bounce_samples`` k traces k
continuation paths per sample (splitting, stratified: L of them sample g_BSE's lobe and k - L its
diffuse part, L = ceil(q k - xi) so that E[L] = q k with q the lobe's probability, each group spread
over its own sample space, each path weighted 1/k; where a scatterer has no ``elo_bse`` tables, one
path per cell of g_BSE's sample space weighted by the cell's area; :mod:`._strata`). ``bounce_filter`` (mm) estimates them in
space (:mod:`._bounce_filter`, biased where they vary inside the window; with ``far_table`` only
the 2nd event's residual about the tabulated mean M(p, n) is averaged, over the pixels the mean
covers, and M is added back per pixel: the residual changes little with the normal, so the
window may span relief); ``bounce_min`` (paths
per pixel) then tops up, in a second pass of continuation paths only, the pixels left with fewer
paths than that (e.g. at edges where the window had to shrink); both estimates are averaged by
path count. ``bounce_share`` (mm), the alternative to ``bounce_filter``, shares them between pixels whose geometry matches
(:mod:`._geometry_classes`: in blocks of that side, the pixels with the same normal and the same
distances along 64 probe rays, classified once per geometry; each pixel takes its view factor of
the detector times the class's ratio of events to view factors, so that a class seen from a
detector's near side counts more there, times the tilt across the block that the classes of its
normal share, fitted in each render): for relief that scatters onto itself, where events >= 2
vary along a flank but repeat where the relief repeats. The continuation
paths of a class's pixels then form one point set in g_BSE's sample space (:func:`._strata.spread_point`,
one random shift per class and render, so each pixel stays unbiased; the sampling frame made from
the normal alone, so one point means one direction in every pixel): they stratify the class's
integral together instead of k paths at a time (corrugated_chamber 1500^2, `default`: e2 1.8-2.1
-> 0.9-1.1 % per pixel for the same paths), and where a sample has at most ``PICK_MAX_PATHS`` (4)
the set also picks each path's component (:func:`._strata.spread_pick`; 8 mm blocks, 8 paths a
pixel: total 0.32 -> 0.28 %); the later continuations (events >= 3) take a 3D
Kronecker sequence over the class's paths (:func:`._strata.spread_later`; corrugated_chamber 256^2,
events 3: e3 10.4 -> 9.1 %; melt_chamber's e3, whose noise is not in the directions, unchanged).

Model only what the scene requires. Scenes whose only scattering surface is one plane
(``rectangle``, ``disk`` or a planar mesh) cannot scatter an electron twice: events >= 2 are
then exactly zero, no bounce ray is traced and ``notes`` says so. Shadow rays that provably
cannot be blocked are not cast: from the scanned surfaces (:mod:`._occlusion`) and, for events
>= 2, from the walls, shields and other few-faced meshes (:mod:`._occlusion_tiles`).

Outputs (one pass): for each detector ``<id>`` the total over the counted events and, when
``events > 1``, each event alone as ``<id>.e<k>``. Values are N_d/N_0, or detector voltages
U_d = (N_d/N_0) I_b T (Eq. 9 with Eq. 3) with ``units="voltage"``.

Options: :class:`elo_mitsuba.options.EloOptions`, read from the XML once and validated there;
between renders they change only through ``configure(options.replace(...))`` (same kernel where
only values change). They read back as attributes (``integrator.events``, ...). With
``count_rays`` the rays cast per sample are stored in ``ray_counts`` after each render.

Performance (benchmarks/RESULTS.md): shadow rays dominate; g_BSE is evaluated from per-BSDF
tables (:func:`~elo_mitsuba.plugins.bsdf_elo_bse.eval_world`, no virtual call per direction) when
every scattering surface has ``elo_bse``; the loop over events is unrolled in Python (faster than
``dr.while_loop``); everything runs in Mitsuba's default single-kernel (symbolic) mode, so memory
does not grow with spp.

XML parameters (name, type, default, meaning):

"""

import dataclasses
import functools
import math

import drjit as dr
import mitsuba as mi
import numpy as np

from elo_mitsuba.errors import EloInputError
from elo_mitsuba.film import film_tensor, raw_planes
from elo_mitsuba.options import EloOptions, parameter_table, paths_per_sample
from elo_mitsuba.physics.solid_angle import vos_denominator
from elo_mitsuba.sample_counts import count_at_least
from elo_mitsuba.schema import event_channel, event_channels

from ._bounce_filter import GUIDE_CHANNELS, filter_bounces
from ._geometry_classes import GeometryClasses
from ._geometry_classes import geometry_key as classes_key
from ._far_field import (NEAR_MM, TABLE_TRIANGLES, FarFieldTable, build_mean, build_rays, geometry_key,
                         near_share, reduce_table, scattering_key)
from ._detectors import find_detectors, parse_detector_list, quadrature_geometry
from ._occlusion import unblockable, unblockable_regions
from ._occlusion_tiles import WallTiles, worth_tiling
from ._shapes import GeometryKey, bbox_centre, shape_key
from ._strata import (PICK_MAX_PATHS, allocated, cell_area, cell_point, group_point, shifted_lattice, spread_later,
                      spread_pick, spread_point, strata_cells, stratum)
from ._relief import (beam_probe, detectors_in_beam, field_missed, may_meet_beam, relief_under_beam,
                      surfaces_met_from_behind, surfaces_overlapping, surfaces_seen_from_behind)
from ._scene_checks import SceneChecks
from .bsdf_elo_bse import collected_fraction, eval_world, is_elo_bse, lobe_probability, scene_tables, world_setup

__doc__ += parameter_table() + "\n"

#: Hidden film channels counting the rays cast per sample (``count_rays``).
COUNT_CHANNELS = ("_elo_intersections", "_elo_shadow_rays")
#: Prefix of the hidden film channels holding the far field's tabulated mean of a detector's 2nd
#: event (``far_table`` with ``bounce_filter``: the filter averages the residual about it).
MEAN_PREFIX = "_elo_mean."
#: bounce_fraction < 1 selects blocks of 2**_BLOCK_SHIFT consecutive lanes (neighbouring pixels)
_BLOCK_SHIFT = 5
#: Prefix of the hidden film channels of the error estimate's 2nd half where one pass traces both
#: halves (:meth:`EloIntegrator.render_halves`): that half's copy of every channel.
HALF_PREFIX = "_elo_half2."
_GOLDEN = 0.6180339887498949


class EloIntegrator(mi.SamplingIntegrator):
    def __init__(self, props):
        mi.SamplingIntegrator.__init__(self, props)
        self.options = EloOptions.from_props(props)
        #: the options the scene file sets, which a quality preset must not override unseen
        self.scene_options = {k: v for k, v in self.options.as_dict().items() if k in props}
        self.detectors = []  # [(id, shape)], resolved from the scene at render time
        self.bounce_possible = True  # False: the scene cannot scatter an electron twice
        self.relief = []  # ids of scattering surfaces that are not one plane (can scatter onto themselves)
        self.notes = []  # what the integrator decided to skip, and why
        self.ray_counts = None  # {"intersections": ..., "shadow_rays": ...} per sample (count_rays)
        self._quadrature_geometry = []  # per detector, see _detectors.quadrature_geometry
        self._two_sided = []  # per detector: collects on both faces (False: front face only)
        self._plates = []  # per detector: its elo_bse BSDF when its plate backscatters, else None
        self._plate_keys = []  # [(detector index, opaque shape id)] of the backscattering detectors
        self._g_tables = None  # g_BSE tables of the scene's elo_bse BSDFs (None: dispatch)
        self._unblockable_regions = []  # per detector, see _occlusion.unblockable_regions
        self._wall_tiles = None  # _occlusion_tiles.WallTiles with a free cell, while events >= 2 are traced
        self._tiles = (None, None)  # (geometry and detectors, WallTiles) of the last set-up
        self._tiles_key = None  # the geometry and detectors of the last set-up (the key of _tiles)
        self._block_offset = dr.opaque(mi.Float, 0.5)  # per-render random shift of the block pattern
        self._roulette_key = dr.opaque(mi.UInt32, 0)  # per-render key of far_roulette's block numbers
        self._in_render = False
        self._checks = SceneChecks()  # what a scene must be, with the caches of its checks
        self._geometry_key = GeometryKey()
        self._occlusion = (None, None)  # (geometry and beam, unblockable_regions) of the last set-up
        self._near = (None, None)  # (geometry, beam, scattering law; near_share) of the last call
        # (geometry and beam; surfaces_seen_from_behind, field_missed, surfaces_overlapping)
        self._behind = (None, ([], 0.0, []))
        self._met_behind = (None, [])  # (geometry and beam; surfaces_met_from_behind)
        self._top_up_pass = None  # (pixel mask, spp) while the top-up pass of bounce_min renders
        self._first_traced = dr.opaque(mi.Bool, True)  # off in a pass whose 1st event render_planes was given
        self.first_event_fixed = False  # see _prepare_scene
        self._n_shadow = None  # shadow rays cast, while count_rays traces
        self._far = None  # the far-field table (_far_field.FarFieldTable) of the last geometry, or None
        self._far_mean_table = None  # its tabulated mean (_far_field.MeanTable, option far_table), or None
        self.far_field_builds = 0  # how many times the far-field table was built (tests, benchmarks)
        self._classes = None  # the geometry classes of bounce_share (_geometry_classes), or None
        self._other_classes = None  # the classes of the block used before, on the same geometry (another preset)
        self.class_builds = 0  # how many times their features were scanned (tests, benchmarks)
        self._spread = None  # (class, rank, size per pixel, spp, key) while a pass spreads a class's paths
        # while one pass traces both halves, per half: (class point sets, block offset, roulette
        # key, sampler seed, paths a sample)
        self._halves = None

    # ---- options --------------------------------------------------------------------------------
    def configure(self, options: EloOptions) -> None:
        """Use ``options`` (an :class:`EloOptions`, already validated) from the next render on."""
        if not isinstance(options, EloOptions):
            raise EloInputError(f"elo: configure() takes EloOptions, not {type(options).__name__}")
        self.options = options

    # ---- set-up ---------------------------------------------------------------------------------
    def prepare_scene(self, scene, sensor=None):
        """Find the detectors of ``scene`` and prepare what the options need; called by
        :meth:`render` (and the Python API) before every render, so moved detectors are seen."""
        # a transform beyond float32 (a detector scaled by 1e300) makes NaN in the host geometry
        # below, which the scene's checks then name in one line; numpy's warnings would precede it
        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            return self._prepare_scene(scene, sensor)

    def _prepare_scene(self, scene, sensor):
        detectors = find_detectors(scene)
        if not detectors:
            raise EloInputError(
                "the scene has no detector: mark a shape as detector with <emitter type=\"area\"/> "
                "and give it an id (its channel name)"
            )
        self.detectors = detectors
        geometry = self._geometry_key(scene)  # where every shape is: the key of the set-up's caches
        mesh_notes = self._checks.refuse(scene, detectors, self._geometry_key, geometry)  # what no render may use
        names = [name for name, _ in detectors]
        front_only = parse_detector_list(self.front_only, names, "front_only")
        self._two_sided = [name not in front_only for name in names]
        self._plates = [shape.bsdf() if is_elo_bse(shape.bsdf()) else None for _, shape in detectors]
        plate_shapes = [shape for (_, shape), plate in zip(detectors, self._plates) if plate is not None]
        self._plate_keys = [(d, dr.opaque(mi.UInt32, shape_key(shape)))
                            for d, ((_, shape), plate) in enumerate(zip(detectors, self._plates)) if plate is not None]
        scatterers = [s for s in scene.shapes() if not s.is_emitter()]
        surfaces = scatterers + plate_shapes  # where an electron can scatter
        self.bounce_possible = not (len(surfaces) <= 1 and all(self._geometry_key.planar(s) for s in surfaces))
        # relief under the beam can scatter onto itself, so events >= 2 vary on the scale of its
        # relief, also along a flank whose normals agree (where the bounce filter is biased)
        beam = sensor if sensor is not None else (scene.sensors()[0] if scene.sensors() else None)
        probed = []

        def probe():  # the beam probe, cast once per prepare for whoever needs it
            if not probed:
                probed.append(beam_probe(scene, beam))
            return probed[0]

        self.relief = (relief_under_beam(scene, beam, surfaces, probe, self._geometry_key.planar)
                       if self.bounce_possible and beam is not None else [])
        self.notes = mesh_notes
        #: [(detector, share of the field)] of the detectors the beam meets before the surface
        self.in_beam = detectors_in_beam(detectors, beam, probe) if beam is not None else []
        for name, share in self.in_beam:
            self.notes.append(
                f"detector {name!r} lies in the beam's path over about {100 * share:.3g} % of the scan field: "
                "there the beam lands on it, not on the build surface, and those pixels show no surface (move "
                "it out of the cone from the gun to the field)")
        if beam is not None:
            # once per surfaces and beam: a probe over the field, not cast again when only detectors
            # out of the beam's cone move (a cast after a move compiles: the scene's pointer changes)
            blockers = [sh for _, sh in detectors if may_meet_beam(sh, beam)]
            key = (tuple(self._geometry_key.entry(sh) for sh in scatterers + blockers), _beam_key(beam))
            if self._behind[0] != key:
                self._behind = (key, (surfaces_seen_from_behind(scatterers, beam, probe),
                                      field_missed(scene, beam, probe),
                                      surfaces_overlapping(scatterers + blockers, beam, probe)))
            behind, missed, overlapping = self._behind[1]
            for pair in overlapping:
                where = ", ".join(f"{v:g}" for v in pair["point"])
                self.notes.append(
                    f"{pair['names'][0]} and {pair['names'][1]} lie in one plane and overlap over about "
                    f"{100 * pair['share']:.3g} % of the scan field (about ({where}) mm): "
                    "the ray tracer meets either there, point by point, so those pixels mix the two; cut "
                    "the one below out of the other (a floor is a frame around the plate, not a sheet under it)")
            if missed > 0:
                self.notes.append(
                    f"the beam meets no surface over about {100 * missed:.3g} % of the scan field (a field wider "
                    "than the scene's surfaces?): those pixels are 0")
            for name, share in behind:
                self.notes.append(
                    f"surface {name!r}: the beam meets the back of its triangles over about {100 * share:.3g} % of "
                    "the scan field, where g_BSE sends nothing back and the pixels are dark (triangles wound "
                    "clockwise seen from the gun: a mesh oriented inconsistently); wind them counter-clockwise "
                    "seen from above (trimesh.repair.fix_normals; a surface upside down as a whole: <boolean "
                    "name=\"flip_normals\" value=\"true\"/>)")
            if self.events > 1 and self.bounce_possible:  # a wall turned away matters to events >= 2 only
                if self._met_behind[0] != key:
                    scattering = [s for s in scatterers if is_elo_bse(s.bsdf())]
                    self._met_behind = (key, surfaces_met_from_behind(scene, scattering, beam, probe))
                for plane in self._met_behind[1]:
                    n, p = (", ".join(f"{v:g}" for v in plane[k] or ()) for k in ("normal", "point"))
                    self.notes.append(
                        f"{'surface ' + repr(plane['name']) if plane['name'] else 'a surface'}, "
                        + (f"its plane of normal ({n}) " if plane["normal"] is not None else "")
                        + f"about ({p}) mm: "
                        f"{100 * plane['own']:.3g} % of the electrons leaving the scan field that reach it arrive at "
                        f"its back ({100 * plane['share']:.3g} % of all that leave), where g_BSE sends nothing back: "
                        "it absorbs them, and events >= 2 come out too small. A wall or shield turned away from the "
                        "field? Turn its front towards the field (a look-at target on the field's side, or <boolean "
                        "name=\"flip_normals\" value=\"true\"/>); a slab needs both faces and its rims")
        if self.events > 1 and not self.bounce_possible:
            self.notes.append(
                "events >= 2 are exactly zero: the only scattering surface is one plane (no chamber, "
                "nothing to scatter an electron twice); no bounce was traced")
        self._quadrature_geometry = []
        if self.detector_sampling == "quadrature":
            self._quadrature_geometry = quadrature_geometry(detectors, self.quadrature_triangles)
        self._g_tables = scene_tables(surfaces)
        self._unblockable_regions = [[] for _ in detectors]
        if self.occlusion_analysis and beam is not None:
            # once per geometry and beam (the two halves of a render, a sweep over anything else)
            key = (geometry, tuple(name for name, _ in detectors), _beam_key(beam))
            if self._occlusion[0] != key:
                self._occlusion = (key, unblockable_regions(scene, beam, detectors))
            self._unblockable_regions = self._occlusion[1]
        self._wall_tiles = None  # set by a render that traces enough paths (_use_wall_tiles)
        self._tiles_key = (geometry, tuple(name for name, _ in detectors))
        #: whether every pass computes the 1st event alike (nothing drawn at random): the quadrature
        #: under a single-ray beam, with one ray per triangle or no shadow ray cast anywhere in the
        #: field (every beam hit unblockable for every detector: a flat plate, also in the chamber, or
        #: relief too shallow to hide one, _occlusion.relief_graph)
        self.first_event_fixed = self._first_event_fixed(beam, probe)
        if self._far_on() and self.traced_events() > 1 and beam is not None:
            self._update_far_field(scene, beam)
            if self.far_table:
                self._update_mean_table(scene, beam, probe())
        if self._shares_bounces() and beam is not None:
            self._update_classes(scene, beam)
        if self.events > 1 and self.relief and self._filters_bounces() and not (
                self._filters_residual() and self.traced_events() == 2):
            self.notes.append(
                f"bounce_filter={self.bounce_filter:g} mm on relief that scatters onto itself "
                f"({', '.join(self.relief)}): the window average of events >= 2 is biased where they vary "
                "along a flank (+9 % in e2 on the corrugated sheet in the chamber) and the error estimate "
                "does not see it; the presets turn it off on such scenes unless far_table holds the "
                "2nd event's mean and only events 1 + 2 are traced")

    def _far_on(self):
        return self.far_field > 0 or self.far_table

    def _shares_bounces(self):
        return self.bounce_share > 0 and self.traced_events() > 1

    def geometry_classes(self):
        """The geometry classes in use (:class:`._geometry_classes.GeometryClasses`: ``index``,
        ``counts``), or None without ``bounce_share``."""
        return self._classes if self._shares_bounces() else None

    def reuses_first_event(self):
        """Whether a render's later passes take the 1st event of its first (render_planes' ``first``):
        where it is the same in every pass and later events are traced (rays not counted)."""
        return self.first_event_fixed and self.traced_events() > 1 and not self.count_rays

    def _first_event_fixed(self, beam, probe):
        if beam is None or self.detector_sampling != "quadrature" or getattr(beam, "fwhm", None) != 0:
            return False
        if self.quadrature_visibility == "triangle":
            return True
        if not all(self._unblockable_regions):
            return False
        si = probe()  # a single-ray beam: the probe's grid is the field's, with its edges
        hit = si.is_valid()
        return all(bool(dr.all(~hit | unblockable(si, regions))) for regions in self._unblockable_regions)

    def _update_classes(self, scene, sensor):
        """Sort the pixels into geometry classes (``bounce_share``, :mod:`._geometry_classes`)
        unless the classes held were made for this geometry, beam, film and block size."""
        if not hasattr(sensor, "centre_rays"):
            raise EloInputError(f"elo: bounce_share={self.bounce_share:g} mm classifies the scan points of the "
                                f"elo_beam sensor; this scene's sensor is {type(sensor).__name__}; set bounce_share=0")
        key = (classes_key(scene, sensor, self._geometry_key), float(self.bounce_share))
        if self._classes is not None and self._classes.key == key:
            return
        if self._other_classes is not None and self._other_classes.key == key:  # back to the block before
            self._classes, self._other_classes = self._other_classes, self._classes
            return
        # another block on the same geometry sorts the same features anew, and the last block is kept
        like = self._classes if self._classes is not None and self._classes.key[0] == key[0] else None
        self._classes = self._other_classes = None  # old classes' arrays go before new ones are made
        self._classes = GeometryClasses(scene, sensor, self.bounce_share, key, like)
        self._other_classes = like
        self.class_builds += like is None

    def near_share(self, scene, sensor):
        """The share of the 2nd event's electrons that meet a surface again within NEAR_MM of the
        beam's hit (:func:`._far_field.near_share`) in ``scene`` (prepared: its relief known); 0
        without relief under the beam (a plane cannot scatter onto itself) or when nothing scatters
        twice. The scene is not kept: an integrator holding its scene would keep both alive, and
        every live scene slows the compilation of every render's kernels."""
        if not self.relief or not self.bounce_possible:
            return 0.0
        # once per geometry, beam and scattering law (a ray cast from a grid over the field)
        key = (self._geometry_key(scene), _beam_key(sensor), scattering_key(scene))
        if self._near[0] != key:
            self._near = (key, near_share(scene, sensor))
        return self._near[1]

    def _update_mean_table(self, scene, sensor, si):
        """Tabulate the far field's mean (option ``far_table``) for the BSDF the beam meets most
        and the normals it meets at the beam probe's hits ``si`` (:func:`._far_field.build_mean`),
        unless held for this table."""
        hit = np.array(si.is_valid() & ~si.shape.is_emitter())
        ids = np.array(dr.reinterpret_array(mi.UInt32, si.bsdf()))[hit]
        bsdfs = {int(dr.reinterpret_array(mi.UInt32, mi.BSDFPtr(sh.bsdf()))[0]): sh.bsdf()
                 for sh in scene.shapes() if not sh.is_emitter() and is_elo_bse(sh.bsdf())}
        keys = ids[np.isin(ids, list(bsdfs))]
        if keys.size == 0:
            self._far_mean_table = None
            return
        values, counts = np.unique(keys, return_counts=True)
        bsdf_key = int(values[np.argmax(counts)])
        normals = np.stack([np.array(c) for c in si.sh_frame.n], axis=1)[hit][ids == bsdf_key]
        key = (self._far.key, bsdf_key, np.round(normals, 6).tobytes())
        held = self._far_mean_table
        if held is not None and held.key == key:
            return
        self._far_mean_table = build_mean(self._far, bsdfs[bsdf_key], bsdf_key, sensor, normals, key)

    def _update_far_field(self, scene, sensor):
        """Build the far-field table (:mod:`._far_field`) unless the one held was built for this
        geometry: a table is never used for a geometry other than its own."""
        traced = self._table_events()
        key = geometry_key(scene, sensor, traced, self._two_sided, self._geometry_key)
        if self._far is not None and self._far.key == key:
            return
        o, d, nodes = build_rays(scene, sensor)
        ray = mi.Ray3f(o, d)
        sampler = mi.load_dict({"type": "independent"})
        sampler.seed(0x26F4, dr.width(o))
        ctx = mi.BSDFContext()
        outer = self._n_shadow
        self._n_shadow = mi.Float(0.0) if self.count_rays else None
        try:
            with dr.suspend_grad():
                si = scene.ray_intersect(ray)
                alive = si.is_valid() & ~si.shape.is_emitter()
                bsdf = si.bsdf(ray)
                later = (self._bounces(scene, sampler, si, ray, bsdf, ctx, alive, traced - 1)[0] if traced > 2
                         else [[] for _ in self.detectors])
                # the 2nd event by the quadrature, one shadow ray per triangle: deterministic
                saved, saved_geometry = self.options, self._quadrature_geometry
                self.options = saved.replace(quadrature_visibility="triangle", quadrature_triangles=TABLE_TRIANGLES)
                self._quadrature_geometry = quadrature_geometry(self.detectors, TABLE_TRIANGLES)
                try:
                    direct = self._quadrature(scene, sampler, si, bsdf, ctx, ray, alive)
                finally:
                    self.options, self._quadrature_geometry = saved, saved_geometry
                responses = [x for dd in range(len(self.detectors)) for x in [direct[dd]] + later[dd]]
                dr.eval(responses)
        finally:
            self._n_shadow = outer
        self._far = FarFieldTable(key, reduce_table(responses), nodes, len(responses))
        self.far_field_builds += 1

    def _table_events(self):
        """The last event the far-field table holds: the 2nd (events >= 3 are traced without a
        control variate: it lowered their error by < 3 % on athene_flat, for the cost of looking
        them up in every cheap sample; benchmarks/RESULTS.md, Far field), or every traced event
        with the option ``far_field_later`` (as before; benchmarks/events_cost.py compares both)."""
        return self.traced_events() if self.far_field_later else min(self.traced_events(), 2)

    def far_field_table(self):
        """The far-field table in use (:class:`._far_field.FarFieldTable`), or None."""
        return self._far if self._far_on() else None

    def _far_mean(self, scene, sampler, si, ctx, bsdf, alive, k_paths):
        """The cheap samples of the far field: s x s stratified samples of g_BSE at the 1st event
        (no ray on a flat scene; on relief a ray test of NEAR_MM splits them into near and far).

        Returns the control variate's mean per channel ((1/K) sum over the far samples of S L),
        and ``k_paths`` picks per stratum (near, far) for the traced paths: each a sample drawn uniformly among the stratum's cheap
        samples (reservoir sampling), as (direction, S, share of the stratum n/K over its picks,
        is_near). A traced path from a pick, times its share, is an unbiased
        estimate of the stratum's part of the integral (near: all of it; far: less the variate).
        """
        far, s = self._far, self.far_field
        n = far.n_channels
        near_test = bool(self.relief)
        strata = (True, False) if near_test else (False,)  # is_near per stratum
        # picks per stratum (halving the far stratum's on relief was measured worse: 5.7 -> 6.8 %
        # total on corrugated_chamber at default for 3 % less time)
        per = [k_paths for _ in strata]
        n_k = s * s

        def body(i, sampler, acc, counts, picks):
            u1 = sampler.next_1d(alive)
            u2 = stratum(i, s, sampler.next_2d(alive))
            bs, w = bsdf.sample(ctx, si, u1, u2, alive)
            wo = si.to_world(bs.wo)
            weight = dr.select(alive, w[0], 0.0)
            near = mi.Bool(False)
            if near_test:  # relief: directions that meet a surface within NEAR_MM are near field
                ray = si.spawn_ray(wo)
                ray.maxt = NEAR_MM
                near = scene.ray_test(ray, alive & (weight > 0))
            vals = far.lookup(si.p, wo, alive & (weight > 0) & ~near)
            acc = [dr.fma(weight, v, a) for a, v in zip(acc, vals)]
            new_counts, new_picks = [], []
            for j, is_near in enumerate(strata):
                member = near if is_near else ~near
                c = counts[j] + dr.select(member, 1.0, 0.0)
                new_counts.append(c)
                for r in range(per[j]):
                    pwo, pw = picks[j][r]
                    take = member & (sampler.next_1d(alive) * c < 1.0)  # reservoir: keep with prob 1/c
                    new_picks.append((dr.select(take, wo, pwo), dr.select(take, weight, pw)))
            starts = [sum(per[:j]) for j in range(len(strata) + 1)]
            picks = [new_picks[starts[j]:starts[j + 1]] for j in range(len(strata))]
            return i + 1, sampler, acc, new_counts, picks

        zero_pick = [[(mi.Vector3f(0.0, 0.0, 1.0), mi.Float(0.0)) for _ in range(per[j])] for j in range(len(strata))]
        out = dr.while_loop(state=(mi.UInt32(0), sampler, [mi.Float(0.0) for _ in range(n)],
                                   [mi.Float(0.0) for _ in strata], zero_pick),
                            cond=lambda i, *rest: i < n_k, body=body)
        _, _, acc, counts, picks = out
        mean = [a * (1.0 / n_k) for a in acc]
        chosen = [(wo, w, counts[j] * (1.0 / (n_k * per[j])), is_near)
                  for j, is_near in enumerate(strata) for wo, w in picks[j]]
        return mean, chosen

    def unblockable_detectors(self):
        """Ids of the detectors whose shadow rays the occlusion analysis skips somewhere (from
        the last :meth:`prepare_scene`)."""
        return [name for (name, _), regions in zip(self.detectors, self._unblockable_regions) if regions]

    def traced_events(self):
        """Events actually traced (1 when the scene cannot scatter twice)."""
        return self.events if self.bounce_possible else 1

    def channel_names(self):
        names = []
        for name, _ in self.detectors:
            names.append(name)
            if self.events > 1:
                names += event_channels([name], self.events)
        return names

    def _bounce_channels(self):
        return event_channels([d for d, _ in self.detectors], self.events, first=2)

    def _filters_bounces(self):
        return self.bounce_filter > 0 and self.traced_events() > 1

    def _filters_residual(self):
        """The bounce filter averages the 2nd event less the far field's tabulated mean (which
        stays per pixel), over the pixels the mean covers: with ``far_table`` and a mean table."""
        return self._filters_bounces() and self.far_table and self._far_mean_table is not None

    def mean_channels(self):
        """The hidden film channels of the far field's tabulated mean (per detector) that the bounce
        filter adds back, or none (see :meth:`_filters_residual`)."""
        return [MEAN_PREFIX + name for name, _ in self.detectors] if self._filters_residual() else []

    def _hidden_channels(self):
        return (list(GUIDE_CHANNELS) if self._filters_bounces() else []) + self.mean_channels() + \
            (list(COUNT_CHANNELS) if self.count_rays else [])

    def aov_names(self):
        names = self.channel_names()
        return names + self._hidden_channels() + ([HALF_PREFIX + n for n in names] if self._halves else [])

    # ---- rendering: one pass, then the bounce filter and the top-up -----------------------------
    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        """Mitsuba's render: the developed film (H x W x C), 'Y' = the sum over detectors, then
        the channels of :meth:`channel_names`. :meth:`render_planes` is the same render without
        the interleaved copy."""
        if self._in_render:
            # the base class's render dispatches back to this override once: render plainly
            return mi.SamplingIntegrator.render(self, scene, sensor, seed, spp, develop, evaluate)
        if not develop:  # the film keeps its raw samples: nothing of ours applies
            self._in_render = True
            try:
                self.prepare_scene(scene, scene.sensors()[sensor] if isinstance(sensor, int) else sensor)
                return mi.SamplingIntegrator.render(self, scene, sensor, seed, spp, develop, evaluate)
            finally:
                self._in_render = False
        planes, buffer = self.render_planes(scene, sensor, seed, spp)
        total = None
        for name, _ in self.detectors:
            plane = planes[self.channel_names().index(name)]
            total = plane.copy() if total is None else total + plane
        h, w = planes.shape[1:]
        if dr.backend_v(buffer) != dr.JitBackend.LLVM:
            # on a GPU the planes are a host copy that the filter and totals changed
            buffer = type(buffer)(np.ascontiguousarray(planes).ravel())
        return film_tensor(buffer, planes.shape[0], h, w, first=total)

    def render_planes(self, scene, sensor=0, seed=0, spp=0, first=None):
        """Render and return the channels of :meth:`channel_names` as planes.

        ``first``: the 1st event's planes of an earlier pass of the same render
        (:meth:`first_event_planes`), where every pass computes it alike (:attr:`first_event_fixed`):
        this pass does not trace it again and takes these (events >= 2 draw the same random numbers
        either way: each event's planes are bit for bit the same, their totals to float32 rounding).

        Returns
        -------
        planes : ndarray, float32, (channels, H, W)
            A writable view of ``buffer`` (:func:`elo_mitsuba.film.raw_planes`).
        buffer : Dr.Jit array
            The buffer behind ``planes`` (it may hold hidden channels after them).
        """
        self._in_render = True
        sampler = (scene.sensors()[sensor] if isinstance(sensor, int) else sensor).sampler()
        scene_spp = sampler.sample_count()
        try:
            with dr.suspend_grad():
                return self._render_planes(scene, sensor, seed, spp, first)
        finally:
            self._in_render = False
            self._first_traced = dr.opaque(mi.Bool, True)
            # the base class's render(spp=n) leaves the sampler at n; the scene's own count must
            # survive for the next render that relies on it (render(), mi.render without spp)
            sampler.set_sample_count(scene_spp)

    def first_event_planes(self, planes):
        """A copy of the 1st event's planes (detectors' order) in ``planes`` of :meth:`render_planes`."""
        names = self.channel_names()
        return np.stack([planes[names.index(event_channel(d, 1) if self.events > 1 else d)] for d, _ in self.detectors])

    def merges_halves(self):
        """Whether one pass can trace both halves of a render's error estimate at 1 spp with
        events >= 2 (:meth:`render_halves`): the 1st event is the same in every pass (traced once,
        shared), and each half's continuation paths are drawn as its own pass would (no sampled far
        field, no roulette, rays not counted). The pass saves the second pass's beam rays, set-up and
        film: athene_flat 1500^2, `default`, 1.27 -> 1.08 s (elo_mitsuba/passes.py)."""
        return (self.reuses_first_event() and self.far_field == 0
                and (self.far_roulette >= 1.0 or self.traced_events() <= 2))

    def render_halves(self, scene, sensor, seeds, spp=1, options=None):
        """Both halves of a render (seeds ``seeds``) in one pass (:meth:`merges_halves`): each
        half's events >= 2 from its own continuation paths, with the block pattern and class point
        sets its own pass would draw from its seed; the 1st event shared. ``options``: each half's
        (:func:`~elo_mitsuba.options.half_budgets`; they may differ in ``bounce_samples`` alone), or
        the integrator's for both. Returns [planes of half 1, planes of half 2], each as
        :meth:`render_planes` returns its planes (views of one buffer), or None where the scene,
        once prepared, does not allow it (then render the halves apart)."""
        own = self.options
        options = list(options) if options is not None else [own, own]
        if any(o.replace(bounce_samples=options[0].bounce_samples) != options[0] for o in options):
            raise ValueError("render_halves: the halves' options may differ in bounce_samples alone")
        self._in_render = True
        sensor_obj = scene.sensors()[sensor] if isinstance(sensor, int) else sensor
        scene_spp = sensor_obj.sampler().sample_count()
        try:
            with dr.suspend_grad():
                self.options = options[0]
                self.prepare_scene(scene, sensor_obj)
                if not self.merges_halves():
                    return None
                self._use_wall_tiles(scene, sensor_obj, spp, sum(paths_per_sample(o) for o in options))
                values = [self._seed_value(x) for x in seeds]
                states = [self._half_state(sensor_obj, v, spp) + (dr.opaque(mi.UInt32, v), o.bounce_samples)
                          for v, o in zip(values, options)]
                self._halves = states
                self._spread, self._block_offset, self._roulette_key = states[0][:3]
                aovs = self.aov_names()
                try:
                    planes, _ = self._pass_planes(scene, sensor, sensor_obj, seeds[0], spp, aovs)
                finally:
                    self._halves = self._spread = None
                names = self.channel_names()
                index = {name: i for i, name in enumerate(aovs)}
                second = dict(index, **{n: index[HALF_PREFIX + n] for n in names})
                out, plan = [], None
                for value, state, idx, half in zip(values, states, (index, second), options):
                    self._block_offset, self._roulette_key = state[1:3]
                    self.options = half
                    plan = self._finish(planes, idx, scene, sensor, sensor_obj, value, spp, False, plan)
                    start = idx[names[0]]  # each half's channels lie together, in the order of names
                    out.append(planes[start:start + len(names)])
                sensor_obj.sampler().seed(0, 1)
                return out
        finally:
            self._in_render = False
            self._halves = self._spread = None
            self.options = own
            sensor_obj.sampler().set_sample_count(scene_spp)

    @staticmethod
    def _seed_value(seed):
        return int(np.array(seed, dtype=np.uint64).ravel()[0]) if not isinstance(seed, int) else seed

    def _half_state(self, sensor_obj, seed_value, spp):
        """(class point sets, block offset, roulette key) a pass of seed ``seed_value`` draws: the
        block selection of bounce_fraction a fresh uniform shift per seed (unbiased), the classes'
        continuation paths one point set per class (:func:`._strata.spread_point`), the lanes per
        pixel the count the sampler takes (as Mitsuba's render sets it)."""
        offset = dr.opaque(mi.Float, float(np.random.default_rng([seed_value, 7]).random()))
        roulette = dr.opaque(mi.UInt32, int(np.random.default_rng([seed_value, 26]).integers(1 << 32)))
        points = None
        if self._shares_bounces() and self._g_tables is not None:
            if int(spp) > 0:
                sensor_obj.sampler().set_sample_count(int(spp))
            n_spp = int(sensor_obj.sampler().sample_count())
            key = int(np.random.default_rng([seed_value, 28]).integers(1 << 32))
            points = self._classes.ranks() + (dr.opaque(mi.UInt32, n_spp), dr.opaque(mi.UInt32, key))
        return points, offset, roulette

    def _render_planes(self, scene, sensor, seed, spp, first=None):
        sensor_obj = scene.sensors()[sensor] if isinstance(sensor, int) else sensor
        self.prepare_scene(scene, sensor_obj)
        self._use_wall_tiles(scene, sensor_obj, spp)
        seed_value = self._seed_value(seed)
        self._spread, self._block_offset, self._roulette_key = self._half_state(sensor_obj, seed_value, spp)
        aovs = self.aov_names()
        if first is not None and not self.reuses_first_event():
            raise ValueError("render_planes: first given where the 1st event is not the same in every pass")
        self._first_traced = dr.opaque(mi.Bool, first is None)
        try:
            planes, buffer = self._pass_planes(scene, sensor, sensor_obj, seed, spp, aovs)
        finally:
            self._spread = None
            self._first_traced = dr.opaque(mi.Bool, True)
        index = {name: i for i, name in enumerate(aovs)}
        if first is not None:
            for d, (name, _) in enumerate(self.detectors):
                planes[index[event_channel(name, 1) if self.events > 1 else name]] = first[d]
        if self.count_rays:
            self.ray_counts = {"intersections": float(np.mean(planes[index[COUNT_CHANNELS[0]]])),
                               "shadow_rays": float(np.mean(planes[index[COUNT_CHANNELS[1]]]))}
        self._finish(planes, index, scene, sensor, sensor_obj, seed_value, spp, first is not None)
        sensor_obj.sampler().seed(0, 1)  # as mi.render: the sampler's state no longer depends on the render
        return planes[:len(self.channel_names())], buffer

    def _finish(self, planes, index, scene, sensor, sensor_obj, seed_value, spp, totals, plan=None):
        """A pass's events >= 2 in the planes of ``index`` (channel -> plane), in place: the bounce
        filter or the classes' share, the top-up, each detector's total (also with ``totals``
        where the 1st event's planes were set after the pass). ``plan``: the filter's decisions
        from the same guide channels (the other half of one pass). Returns them, or None."""
        if self._sums_totals():
            n_spp = int(spp) if int(spp) > 0 else int(sensor_obj.sampler().sample_count())
            rate = paths_per_sample(self.options) * n_spp  # paths per pixel, expected
            paths = np.full(planes.shape[1:], rate, np.float32)
            if self.bounce_filter > 0:
                # with the far field's tabulated mean, only the residual about it is averaged: the
                # mean keeps each pixel's own normal and position (relief), the residual is smooth
                means = [(index[event_channel(name, 2)], index[MEAN_PREFIX + name])
                         for name, _ in self.detectors] if self._filters_residual() else []
                for c, m in means:
                    planes[c] -= planes[m]
                plan = filter_bounces(planes, index, self._bounce_channels(), getattr(sensor_obj, "field", None),
                                      self.bounce_filter, self.bounce_filter_angle, paths, plan)
                for c, m in means:
                    planes[c] += planes[m]
            if self._shares_bounces():
                # pixels of one geometry class take its mean, scaled across the block by each
                # detector's view factor (both halves of the error estimate share the classes, so
                # its noise is seen and any bias is not)
                views = self._classes.view_factors([bbox_centre(shape) for _, shape in self.detectors])
                self._classes.share_all((planes[index[event_channel(name, k)]], views[d])
                                        for d, (name, _) in enumerate(self.detectors)
                                        for k in range(2, self.events + 1))
                paths *= self._classes.pixels_per_class()
            if self.bounce_min > 0:
                self._top_up(planes, index, scene, sensor, sensor_obj, seed_value, paths)
            self._totals(planes, index)
        elif totals and self.events > 1:
            self._totals(planes, index)
        return plan

    def _sums_totals(self):
        """Whether :meth:`_finish` changes a pass's events >= 2 (filter, shares, top-up) and so
        sums each detector's total again from its events."""
        return self.traced_events() > 1 and (self.bounce_filter > 0 or self.bounce_share > 0 or self.bounce_min > 0)

    def _use_wall_tiles(self, scene, sensor, spp, per_sample=None):
        """The walls' free cells (:mod:`._occlusion_tiles`) for a pass that traces enough
        continuation paths to pay for them (:func:`._occlusion_tiles.worth_tiling`; ``per_sample``:
        the pass's paths a sample, the options' by default): once per geometry and detectors (a
        sweep that moves no detector reuses them)."""
        self._wall_tiles = None
        if not (self.occlusion_analysis and self.traced_events() > 1):
            return
        size = sensor.film().crop_size()
        n_spp = int(spp) if int(spp) > 0 else int(sensor.sampler().sample_count())
        per_sample = paths_per_sample(self.options) if per_sample is None else per_sample
        paths = int(size[0]) * int(size[1]) * n_spp * per_sample
        if not worth_tiling(scene, self.detectors, paths):
            return
        if self._tiles[0] != self._tiles_key:
            self._tiles = (self._tiles_key, WallTiles(scene, self.detectors))
        self._wall_tiles = self._tiles[1] if self._tiles[1].any_free() else None

    def _pass_planes(self, scene, sensor, sensor_obj, seed, spp, names):
        """One render pass of the base class; the film channels ``names`` (of :meth:`aov_names`)
        as planes, developed straight from the film's raw storage."""
        mi.SamplingIntegrator.render(self, scene, sensor, seed, spp, False, True)
        raw = sensor_obj.film().develop(raw=True)  # R, G, B, weight (, alpha), then the AOVs
        aovs = self.aov_names()
        first = int(raw.shape[2]) - len(aovs)
        # the detectors' totals that _finish sums again from the events are not developed (a
        # third of the planes at events 1 + 2: 77 -> 54 ms at 1500^2 for both halves' channels)
        summed = {n for d, _ in self.detectors for n in (d, HALF_PREFIX + d)} if self._sums_totals() else ()
        return raw_planes(raw, [None if n in summed else first + aovs.index(n) for n in names],
                          weight_column=first - 1)

    def _top_up(self, planes, index, scene, sensor, sensor_obj, seed, paths):
        """bounce_min: pixels whose events >= 2 rest on fewer continuation paths than that (e.g.
        where the filter must stop at edges) get a second pass of bounce paths only; the two
        estimates are averaged with their path counts as weights."""
        need = paths < self.bounce_min
        if not np.any(need):
            return
        missing = float(np.max(self.bounce_min - paths[need]))
        k = max(1, min(8, math.ceil(missing)))
        spp2 = count_at_least(sensor_obj.sampler(), max(1, math.ceil(missing / k)))  # weighted as rendered
        saved = self.options
        self._top_up_pass = (mi.Bool(need.ravel()), dr.opaque(mi.UInt32, spp2))
        saved_key = self._roulette_key  # far_roulette: other block numbers than the main pass's
        self._roulette_key = dr.opaque(mi.UInt32, int(np.random.default_rng([seed, 27]).integers(1 << 32)))
        # same film channels as the main pass (hidden ones included) so the columns agree
        self.options = saved.replace(bounce_samples=k, bounce_fraction=1.0)
        names = self._bounce_channels()
        try:
            extra, _ = self._pass_planes(scene, sensor, sensor_obj, seed + 0x5EED, spp2, names)
        finally:
            self._top_up_pass = None
            self.options = saved
            self._roulette_key = saved_key
        n2 = float(k * spp2)
        w1 = np.where(need, paths / (paths + n2), 1.0).astype(np.float32)
        for i, name in enumerate(names):
            c = index[name]
            planes[c] = planes[c] * w1 + extra[i] * (1.0 - w1)
        paths[need] += n2

    def _totals(self, planes, index):
        """Each detector's total from its event channels (in place)."""
        for d, _ in self.detectors:
            total = planes[index[event_channel(d, 1)]]
            for e in range(2, self.events + 1):
                total = total + planes[index[event_channel(d, e)]]
            planes[index[d]] = total

    # ---- the estimator --------------------------------------------------------------------------
    def sample(self, scene, sampler, ray, medium=None, active=True):
        ctx = mi.BSDFContext()
        n_det = len(self.detectors)
        traced = self.traced_events()
        counting = self.count_rays
        self._n_shadow = mi.Float(0.0) if counting else None

        # ---- 1st event: where the beam hits
        alive = mi.Bool(active)
        si = scene.ray_intersect(ray, alive)
        n_isect = dr.select(alive, 1.0, 0.0) if counting else None
        # electrons scatter only on surfaces that are not detectors (detectors absorb)
        alive &= si.is_valid() & ~si.shape.is_emitter()
        bsdf = si.bsdf(ray)
        if self._top_up_pass is not None:  # top-up pass of bounce_min: events >= 2 only
            first = [mi.Float(0.0) for _ in range(n_det)]
        elif self.detector_sampling == "quadrature" and self.reuses_first_event():
            # traced in a render's first pass only (render_planes' first): one kernel for every
            # pass, the branch skipped where the opaque flag is off (no second kernel to compile);
            # its shadow rays' numbers are drawn either way, so later events draw the same ones
            rand = self._quadrature_numbers(sampler, alive)
            first = list(dr.if_stmt((si, ray, alive, rand), alive & self._first_traced,
                                    lambda si, ray, alive, rand: tuple(
                                        self._quadrature(scene, None, si, si.bsdf(ray), ctx, ray, alive, rand)),
                                    lambda *args: tuple(mi.Float(0.0) for _ in range(n_det))))
        elif self.detector_sampling == "quadrature":
            first = self._quadrature(scene, sampler, si, bsdf, ctx, ray, alive)
        else:
            first = self._sampled(scene, sampler, si, bsdf, ctx, ray, alive, self.detector_samples,
                                  self.detector_sampling != "independent")
        per_event = [[first[d]] for d in range(n_det)]
        si_first, alive_first = si, mi.Bool(alive)

        # ---- events 2 .. traced: continue by sampling g_BSE (Eq. 7)
        if traced > 1:
            outer_shadow = self._n_shadow

            k_paths = self.bounce_samples
            far = self._far if self._far_on() else None
            mean = picks = block_u = q_far = None
            far_mask = True
            if far is not None and self.far_table:  # the mean tabulated: the variate where it covers
                table = self._far_mean_table
                if table is None:
                    far = None
                else:
                    mean, far_mask = table.lookup(si_first.p, si_first.sh_frame.n,
                                                  dr.reinterpret_array(mi.UInt32, bsdf), alive_first)
            elif far is not None:  # the cheap samples: the variate's mean and the traced paths' directions
                mean, picks = self._far_mean(scene, sampler, si_first, ctx, bsdf, alive_first, k_paths)
                if self.far_roulette < 1.0 and traced > 2:
                    # far_roulette: one uniform number per block of lanes (neighbouring pixels) and
                    # render, independent between blocks (a hash of the block and the render's key)
                    block = dr.arange(mi.UInt32, dr.width(alive_first)) >> _BLOCK_SHIFT
                    block_u = mi.sample_tea_float32(block, self._roulette_key, 4)
                    q_far = dr.opaque(mi.Float, self.far_roulette)

            def bounces(si, ray, alive, sampler, k_paths=k_paths):
                self._n_shadow = mi.Float(0.0) if counting else None
                if picks is not None:  # one path per pick, times its stratum's share over its picks
                    later, n_hit = None, mi.Float(0.0)
                    n_far = sum(1 for pick in picks if not pick[3])
                    j_far = 0
                    for wo, w, share, is_near in picks:
                        roulette = None
                        if not is_near and block_u is not None:
                            # the far picks of a block spread evenly over [0, 1): each uniform
                            u = block_u + j_far / n_far
                            roulette = (u - dr.floor(u), q_far)
                            j_far += 1
                        more, more_hit = self._bounces(scene, sampler, si, ray, bsdf_of(si, ray), ctx, alive,
                                                       traced, None if is_near else far, first=(wo, w),
                                                       roulette=roulette)
                        more = [[x * share for x in per] for per in more]
                        later = more if later is None else [[a + b for a, b in zip(x, y)] for x, y in zip(later, more)]
                        n_hit = n_hit + more_hit
                    extra = [n_hit, self._n_shadow] if counting else []
                    return tuple(x for per_det in later for x in per_det) + tuple(extra)
                # k continuation paths from the same 1st event (splitting), stratified: with g_BSE's
                # tables, L of them go to its lobe and k - L to its diffuse part (E[L] = q k, q the
                # lobe's probability), each group spread over its own sample space, each path
                # weighted 1/k; else one per cell of the sample space, weighted by its area
                later, n_hit = None, mi.Float(0.0)
                groups = shift = None
                if (k_paths > 1 or self._spread is not None) and self._g_tables is not None:
                    groups = self._component_groups(si, ray, alive, k_paths, sampler)
                    if groups[-1] is not None:
                        si = self._normal_frame(si, ray)
                elif k_paths > 1:
                    shift = sampler.next_1d(alive)
                for j, cell in enumerate(strata_cells(k_paths)):
                    if groups is not None:
                        first = self._direction_grouped(j, k_paths, groups, si, ray, ctx, sampler, alive)
                    else:
                        first = self._direction_in(cell, j, k_paths, shift, si, ray, ctx, sampler, alive) \
                            if k_paths > 1 else None
                    path = None
                    if groups is not None and groups[-1] is not None:  # the path's index in its class
                        sample, _, _, c, _, _ = groups[-1]
                        path = (sample * k_paths + j, c)
                    more, more_hit = self._bounces(scene, sampler, si, ray, bsdf_of(si, ray), ctx, alive, traced,
                                                   far, first=first, far_mask=far_mask, spread=path)
                    if k_paths > 1:
                        w_path = (1.0 / k_paths) if groups is not None else cell_area(cell)
                        more = [[a * w_path for a in x] for x in more]
                    later = more if later is None else [[a + b for a, b in zip(x, y)] for x, y in zip(later, more)]
                    n_hit = n_hit + more_hit
                extra = [n_hit, self._n_shadow] if counting else []
                return tuple(x for per_det in later for x in per_det) + tuple(extra)

            def bsdf_of(si_, ray_):
                return si_.bsdf(ray_)

            n_out = n_det * (traced - 1) + (2 if counting else 0)
            halves = []
            for h, state in enumerate(self._halves or [None]):
                own = sampler
                if state is not None:  # one pass traces both halves: each with its own paths
                    self._spread, self._block_offset, self._roulette_key = state[:3]
                    if h > 0:
                        # the 2nd half's numbers from a sampler seeded as its own pass's: draws
                        # inside a symbolic branch (bounce_fraction's blocks, the detectors' points)
                        # do not advance the state outside it, so the 1st half's sampler would
                        # hand the 2nd the same numbers again
                        own = sampler.fork()
                        own.seed(state[3], dr.width(alive))
                half_bounces = bounces if state is None else functools.partial(bounces, k_paths=state[4])
                halves.append(self._later_out(half_bounces, si, ray, alive, own, n_det, traced, n_out, mean))
            out = halves[0]
            for d in range(n_det):
                per_event[d] += list(out[d * (traced - 1):(d + 1) * (traced - 1)])
            if counting:
                n_isect = n_isect + out[-2]
                self._n_shadow = outer_shadow + out[-1]

        # ---- channels
        scale = self.beam_current * self.transimpedance if self.units == "voltage" else 1.0
        aovs = self._channels(per_event, scale)
        total_all = mi.Float(0.0)
        for d in range(n_det):
            total_all = total_all + aovs[d * (len(aovs) // n_det)]
        if self._filters_bounces():
            residual = self._filters_residual()
            if self._top_up_pass is not None:
                aovs += [mi.Float(0.0)] * (3 + (n_det if residual else 0))
            else:
                # the guide: the 1st event's normal; with the residual filtered, only where the
                # tabulated mean covers the hit (elsewhere the whole 2nd event is in the channel)
                valid = alive_first & far_mask if residual else alive_first
                n = dr.select(valid, si_first.sh_frame.n, mi.Vector3f(0.0))
                aovs += [n.x, n.y, n.z]
                if residual:
                    held = len(mean) // n_det
                    aovs += [mean[d * held] * scale for d in range(n_det)]
        if counting:
            aovs += [n_isect, self._n_shadow]
            self._n_shadow = None
        if self._halves:  # the 2nd half's channels: the same 1st event, its own later ones
            aovs += self._channels([[per_event[d][0]] + list(halves[1][d * (traced - 1):(d + 1) * (traced - 1)])
                                    for d in range(n_det)], scale)
        return mi.Spectrum(total_all), mi.Bool(True), aovs

    def _channels(self, per_event, scale):
        """The film channels of :meth:`channel_names` from each detector's traced events."""
        aovs = []
        for events in per_event:
            events = [e * scale for e in events]
            events += [mi.Float(0.0)] * (self.events - len(events))  # not traced: exactly zero
            total = events[0]
            for e in events[1:]:
                total = total + e  # not +=: Dr.Jit's in-place add would alias events[0]
            aovs.append(total)
            if self.events > 1:
                aovs += events
        return aovs

    def _later_out(self, bounces, si, ray, alive, sampler, n_det, traced, n_out, mean):
        """Events >= 2 of every detector from ``bounces`` (the continuation paths of a sample), as
        the options ask: only in the top-up pass's pixels, in a fraction of the blocks, or
        everywhere; plus the far field's tabulated mean where it holds them."""
        if self._top_up_pass is not None:
            # only the pixels in the mask (Mitsuba orders lanes pixel by pixel, spp each)
            mask, spp2 = self._top_up_pass
            pixel = dr.arange(mi.UInt32, dr.width(alive)) // spp2
            chosen = dr.gather(mi.Bool, mask, pixel, alive)
            out = dr.if_stmt((si, ray, alive, sampler), alive & chosen, bounces,
                             lambda *args: tuple(mi.Float(0.0) for _ in range(n_out)))
        elif self.bounce_fraction < 1.0:
            # whole blocks of lanes (neighbouring pixels) trace the bounce or skip it, so that
            # the skipped work is really not done; each block with probability f, weight 1/f
            lane = dr.arange(mi.UInt32, dr.width(alive))
            u = mi.Float(lane >> _BLOCK_SHIFT) * _GOLDEN + self._block_offset
            fraction = dr.opaque(mi.Float, self.bounce_fraction)
            keep = (u - dr.floor(u)) < fraction
            out = dr.if_stmt((si, ray, alive, sampler), alive & keep, bounces,
                             lambda *args: tuple(mi.Float(0.0) for _ in range(n_out)))
            inv = 1.0 / fraction
            out = tuple(x * inv for x in out[: n_det * (traced - 1)]) + tuple(out[n_det * (traced - 1):])
        else:
            out = bounces(si, ray, alive, sampler)
        if mean is not None:  # the control variate's mean, from the cheap samples
            held = len(mean) // n_det  # events the table holds, from the 2nd on
            out = list(out)
            for d in range(n_det):
                for e in range(held):
                    out[d * (traced - 1) + e] = out[d * (traced - 1) + e] + mean[d * held + e]
        return out

    def _bounces(self, scene, sampler, si, ray, bsdf, ctx, alive, traced, far=None, first=None, roulette=None,
                 far_mask=True, spread=None):
        """Events 2 .. traced for the paths alive after the 1st: per detector a list of their
        direct contributions, and the number of bounce rays cast (for count_rays). With ``far``
        (a far-field table) each contribution is less the control variate of the path's first
        direction (S L(node, wo); only where ``far_mask``): the caller adds the variate's mean. ``first`` = (world
        direction, weight S) gives the first continuation instead of sampling it.

        The table holds the 2nd event (or, with ``far_field_later``, events 2 .. traced): only the
        events it holds get the variate; later ones are traced as they are.

        ``roulette`` = (u, q), with ``far`` and traced >= 3 (``far_roulette``): Russian roulette of
        events >= 3: the path goes on past its 2nd event only where u < q (u is one uniform
        number per block of 2**_BLOCK_SHIFT lanes, so whole SIMD packets skip the work), and its
        events >= 3 (less the variate where the table holds them) are weighted 1/q there, 0
        elsewhere: unbiased.

        ``spread`` = (the path's index among its class's paths, the class), while a pass spreads a
        class's paths (``bounce_share``): the later continuations take the class's point set
        (:func:`._strata.spread_later`) in a frame made from the normal (:meth:`_normal_frame`)."""
        control = None
        n_det = len(self.detectors)
        later = [[] for _ in range(n_det)]
        alive = mi.Bool(alive)  # a copy: the &= below must not change the caller's mask
        throughput = mi.Float(1.0)
        n_hit = mi.Float(0.0)
        counting = self.count_rays
        tail = 2 if (roulette is not None and far is not None and traced > 2) else traced
        for event in range(1, tail):
            if first is not None and event == 1:
                wo, w = first
            elif spread is None:
                bs, weight = bsdf.sample(ctx, si, sampler.next_1d(alive), sampler.next_2d(alive), alive)
                wo, w = si.to_world(bs.wo), weight[0]
            else:
                si = self._normal_frame(si, ray)
                u1, u2 = spread_later(spread[0], self._class_shifts(spread[1], event)[:3])
                bs, weight = bsdf.sample(ctx, si, u1, u2, alive)
                wo, w = si.to_world(bs.wo), weight[0]
            throughput = throughput * w
            alive &= throughput > 0
            if far is not None and event == 1:  # a far pick: less the variate of its direction
                control = [w * v for v in far.lookup(si.p, wo, alive & far_mask)]
                held = len(control) // n_det  # events the table holds, from the 2nd on
            si, ray, bsdf, alive, out = self._event(scene, sampler, si, wo, ctx, alive)
            n_hit = n_hit + out[-1]
            for d in range(n_det):
                later[d].append(throughput * out[d])
        if tail < traced:  # the roulette of events >= 3 (a far pick)
            u, q = roulette
            n_tail = traced - tail

            def go_on(si, ray, alive, throughput, sampler):
                outer = self._n_shadow
                self._n_shadow = mi.Float(0.0) if counting else None
                bsdf = si.bsdf(ray)
                hits = mi.Float(0.0)
                res = [[] for _ in range(n_det)]
                for _ in range(n_tail):
                    bs, weight = bsdf.sample(ctx, si, sampler.next_1d(alive), sampler.next_2d(alive), alive)
                    throughput = throughput * weight[0]
                    alive &= throughput > 0
                    si, ray, bsdf, alive, out = self._event(scene, sampler, si, si.to_world(bs.wo), ctx, alive)
                    hits = hits + out[-1]
                    for d in range(n_det):
                        res[d].append(throughput * out[d])
                extra = [self._n_shadow] if counting else []
                self._n_shadow = outer
                return tuple(x for per in res for x in per) + (hits,) + tuple(extra)

            keep = u < q
            n_out = n_det * n_tail + 1 + (1 if counting else 0)
            out = dr.if_stmt((si, ray, alive, throughput, sampler), alive & keep, go_on,
                             lambda *args: tuple(mi.Float(0.0) for _ in range(n_out)))
            n_hit = n_hit + out[n_det * n_tail]
            if counting:
                self._n_shadow = self._n_shadow + out[-1]
            inv = 1.0 / q
            for d in range(n_det):
                for j in range(n_tail):
                    e = tail - 1 + j  # index in later[d] (0 = the 2nd event)
                    residual = out[d * n_tail + j]
                    if e < held:
                        residual = residual - control[d * held + e]
                    later[d].append(dr.select(keep, residual * inv, 0.0))
        if control is not None:
            later = [[x - control[d * held + e] if e < held and e < tail - 1 else x for e, x in enumerate(later[d])]
                     for d in range(n_det)]
        return later, n_hit

    def _component_groups(self, si, ray, alive, k, sampler):
        """Per sample, for k continuation paths: how many go to g_BSE's lobe, L = ceil(q k - xi)
        with xi uniform (so E[L] = q k; q = the lobe's share of eta, as ``elo_bse.sample`` picks
        it), and a random rotation per group (:func:`._strata.group_point`). While a pass spreads
        a class's paths (``bounce_share``), also the sample's place in its class's point set, and
        the rotations and shift are the class's (:func:`._strata.spread_point`)."""
        diffuse, weight, exponent, _, _, ok = world_setup(self._g_tables, si, -ray.d, alive)
        q = dr.select(ok, lobe_probability(diffuse * dr.pi, weight, exponent), 0.0)
        n_lobe = allocated(q, k, sampler.next_1d(alive))
        rot_lobe, rot_diffuse = sampler.next_1d(alive), sampler.next_1d(alive)
        if self._spread is None:
            return n_lobe, rot_lobe, rot_diffuse, None
        cls, rank, size, spp, _ = self._spread
        lane = dr.arange(mi.UInt32, dr.width(alive))
        pixel = lane // spp  # Mitsuba orders the lanes pixel by pixel, spp each
        c = dr.gather(mi.UInt32, cls, pixel, alive)
        sample = dr.gather(mi.UInt32, rank, pixel, alive) * spp + (lane - pixel * spp)
        n_samples = dr.gather(mi.UInt32, size, pixel, alive) * spp
        rot_lobe, rot_diffuse, shift_x, shift_pick = self._class_shifts(c, 1)
        return n_lobe, rot_lobe, rot_diffuse, (sample, n_samples, shift_x, c, q, shift_pick)

    def _class_shifts(self, c, event):
        """Four uniform numbers of class ``c`` for its paths' continuation ``event`` (1 = the
        first) in this render, the random shifts of its point set: hashes of the class and the
        render's key, one key per continuation."""
        key = self._spread[4] ^ mi.UInt32(0x9E3779B9 * event % (1 << 32))
        a, b = mi.sample_tea_32(c, key, 4)
        d, e = mi.sample_tea_32(c, key ^ 0x5BD1E995, 4)
        return [mi.Float(x) * (1.0 / 4294967296.0) for x in (a, b, d, e)]

    @staticmethod
    def _normal_frame(si, ray):
        """``si`` with a shading frame made from its normal alone. Where a class's pixels share
        one point set, one sample point must mean one direction in all of them: a mesh's tangents
        turn from triangle to triangle, and g_BSE is isotropic, so the frame changes which point
        gives which direction, not the law."""
        si = mi.SurfaceInteraction3f(si)
        si.sh_frame = mi.Frame3f(si.sh_frame.n)
        si.wi = si.to_local(-ray.d)
        return si

    @staticmethod
    def _direction_grouped(j, k, groups, si, ray, ctx, sampler, alive):
        """Path j of k (world direction, weight S): the lobe's if j < L, else the diffuse part's;
        g_BSE sampled at its group's point (the component forced: u1 = 0 picks the lobe, 1 the
        diffuse part). Weight 1/k per path: with E[L] = q k this is the mixture's estimate. While a
        class spreads its paths over one point set and k <= PICK_MAX_PATHS, the set picks each
        path's component instead (with probability q, :func:`._strata.spread_pick`)."""
        n_lobe, rot_lobe, rot_diffuse, spread = groups
        u = sampler.next_1d(alive)
        if spread is None:
            is_lobe, u2 = group_point(j, k, n_lobe, rot_lobe, rot_diffuse, u)
        elif k <= PICK_MAX_PATHS:  # few paths a sample: the class's point set picks the component too
            sample, n_samples, shift_x, _, q, shift_pick = spread
            is_lobe, u2 = spread_pick(j, k, sample, n_samples, q, shift_pick, shift_x, rot_lobe, u)
        else:
            sample, n_samples, shift_x, _, _, _ = spread
            is_lobe, u2 = spread_point(j, k, n_lobe, sample, n_samples, shift_x, rot_lobe, rot_diffuse, u)
        return _sample_direction(si, ray, ctx, dr.select(is_lobe, 0.0, 1.0), u2, alive)

    @staticmethod
    def _direction_in(cell, j, k, shift, si, ray, ctx, sampler, alive):
        """The j-th of k stratified continuation directions (world) and its weight S: g_BSE
        sampled at a point of ``cell`` of the 2D sample space, the lobe chosen by the j-th point
        of a shifted lattice (:mod:`._strata`)."""
        u2 = cell_point(cell, sampler.next_2d(alive))
        return _sample_direction(si, ray, ctx, shifted_lattice(j, k, shift), u2, alive)

    def _event(self, scene, sampler, si, wo, ctx, alive):
        """One more event of a path at ``si`` continuing towards ``wo`` (world): the continuation
        ray, where it meets a surface and that surface's direct estimate per detector (times 1:
        the caller multiplies by the throughput). Returns (si, ray, bsdf, alive, out) with out =
        per detector the direct estimate, then the bounce rays cast (1 per alive lane)."""
        n_det = len(self.detectors)
        ray = si.spawn_ray(wo)
        si = scene.ray_intersect(ray, alive)
        hit = dr.select(alive, 1.0, 0.0)
        if self._plate_keys:
            # a backscattering detector plate is a surface too: its backscattered electrons
            # travel on (crosstalk); a shielded back face absorbs
            on_plate, back = self._plate_hit(si, ray)
            alive &= si.is_valid() & (~si.shape.is_emitter() | on_plate)
            bsdf = si.bsdf(ray)
            si.sh_frame = mi.Frame3f(dr.select(back, -si.sh_frame.n, si.sh_frame.n))
            si.wi = si.to_local(-ray.d)
        else:
            alive &= si.is_valid() & ~si.shape.is_emitter()
            bsdf = si.bsdf(ray)
        counting = self.count_rays
        stratify = self.detector_sampling != "independent"

        def direct_fn(si, ray, alive, sampler, bsdf=bsdf):
            outer = self._n_shadow
            self._n_shadow = mi.Float(0.0) if counting else None
            out = self._sampled(scene, sampler, si, bsdf, ctx, ray, alive, self.bounce_detector_samples,
                                stratify)
            extra = [self._n_shadow] if counting else []
            self._n_shadow = outer
            return tuple(out) + tuple(extra)

        # paths that left the scene (most, without a chamber) skip the detector estimate:
        # whole SIMD packets of escaped paths do no work at all
        out = dr.if_stmt((si, ray, alive, sampler), alive, direct_fn,
                         lambda *args: tuple(mi.Float(0.0) for _ in range(n_det + (1 if counting else 0))))
        if counting:
            self._n_shadow = self._n_shadow + out[-1]
        return si, ray, bsdf, alive, list(out[:n_det]) + [hit]

    def _plate_hit(self, si, ray):
        """(lanes on a backscattering detector plate that scatters them, lanes that hit it from
        behind): a front-only detector's back face absorbs (it is shielded)."""
        key = dr.reinterpret_array(mi.UInt32, si.shape)
        on_plate, back = mi.Bool(False), mi.Bool(False)
        behind = dr.dot(si.sh_frame.n, -ray.d) < 0
        for d, k in self._plate_keys:
            hit = key == k
            ok = hit if self._two_sided[d] else hit & ~behind
            on_plate |= ok
            back |= ok & behind
        return on_plate, back

    def _ray_test(self, scene, ray, active):
        if self.count_rays:
            self._n_shadow = self._n_shadow + dr.select(active, 1.0, 0.0)
        return scene.ray_test(ray, active)

    def _visible(self, scene, si, target, test, d):
        """test & not occluded on the way from si to target (a point on detector d)."""
        skip = unblockable(si, self._unblockable_regions[d])
        wall = self._wall_tiles.free(si, d) if self._wall_tiles is not None else None
        if wall is not None:
            skip = wall if skip is None else skip | wall
        cast = test if skip is None else test & ~skip
        return test & ~self._ray_test(scene, si.spawn_ray_to(target), cast)

    def _sampled(self, scene, sampler, si, bsdf, ctx, ray, alive, n_pts, stratify):
        """Per detector: sum over n_pts sampled points of g_BSE / pdf, with occlusion."""
        cells = strata_cells(n_pts) if stratify else None
        wos, weights = [], []
        for d, (_, shape) in enumerate(self.detectors):
            emitter = shape.emitter()
            for i in range(n_pts):
                u = sampler.next_2d(alive)
                w = 1.0 / n_pts
                if stratify:
                    u, w = cell_point(cells[i], u), cell_area(cells[i])
                if self._two_sided[d]:
                    # a point by area on the detector, either face: weight |cos| A / r^2 = 1/pdf
                    ps = shape.sample_position(si.time, u, alive)
                    to = ps.p - si.p
                    dist2 = dr.squared_norm(to)
                    wo = to * dr.rsqrt(dist2)
                    cos_d = dr.abs(dr.dot(ps.n, wo))
                    test = alive & (ps.pdf > 0) & (cos_d > 0) & (dist2 > 0)
                    em_weight = dr.select(test, cos_d / (dist2 * ps.pdf), 0.0)
                    target, normal = ps.p, ps.n
                else:
                    ds, em_spectrum = emitter.sample_direction(si, u, alive)
                    # em_spectrum = 1/pdf (unit radiance), 0 at the detector's back face
                    test = alive & (ds.pdf > 0)
                    em_weight, wo, target, normal = em_spectrum[0], ds.d, ds.p, ds.n
                if self._plates[d] is not None:
                    em_weight = em_weight * collected_fraction(self._plates[d], dr.abs(dr.dot(normal, wo)))
                visible = self._visible(scene, si, target, test, d)
                wos.append(wo)
                weights.append(dr.select(visible, em_weight * w, 0.0))
        g = eval_world(self._g_tables, si, bsdf, ctx, ray, alive, wos)
        out = []
        k = 0
        for _ in self.detectors:
            acc = mi.Float(0.0)
            for _ in range(n_pts):
                acc = dr.fma(g[k], weights[k], acc)
                k += 1
            out.append(acc)
        return out

    def _quadrature_numbers(self, sampler, alive):
        """The random numbers :meth:`_quadrature` draws (per detector, for its sampled shadow ray:
        the triangle, then the point in it), in its order; none with one ray per triangle."""
        if self.quadrature_visibility == "triangle":
            return []
        return [(sampler.next_1d(alive), sampler.next_2d(alive)) for _ in self.detectors]

    def _quadrature(self, scene, sampler, si, bsdf, ctx, ray, alive, rand=None):
        """Appendix A (Eq. A2): sum over detector triangles of Omega_p (Eq. A1, corrected) times
        g_BSE at the centroid direction; occlusion by one sampled ray or one per triangle. The
        random numbers from ``sampler``, or drawn before (``rand``, :meth:`_quadrature_numbers`)."""
        if rand is None:
            rand = self._quadrature_numbers(sampler, alive)
        p = si.p
        omegas, dirs, per_det = [], [], []
        for d, (verts, tris) in enumerate(self._quadrature_geometry):
            v = [q - p for q in verts]
            lengths = [dr.norm(x) for x in v]
            dots = {}

            def dot(i, j):
                key = (min(i, j), max(i, j))
                if key not in dots:
                    dots[key] = dr.dot(v[i], v[j])
                return dots[key]

            per_det.append(len(tris))
            for (i, j, k), twice_area_normal in tris:
                num = dr.dot(v[i], twice_area_normal)
                den = vos_denominator(lengths[i], lengths[j], lengths[k], dot(i, j), dot(i, k), dot(j, k))
                # counter-clockwise about the front normal: num < 0 seen from the front
                signed = 2.0 * dr.atan2(-num, den)
                omega = dr.abs(signed) if self._two_sided[d] else dr.maximum(signed, 0.0)
                centroid_dir = dr.normalize(v[i] + v[j] + v[k])
                if self._plates[d] is not None:
                    cos_inc = dr.abs(dr.dot(centroid_dir, twice_area_normal)) * dr.rsqrt(
                        dr.squared_norm(twice_area_normal))
                    omega = omega * collected_fraction(self._plates[d], cos_inc)
                omegas.append(omega)
                dirs.append(centroid_dir)
        g = eval_world(self._g_tables, si, bsdf, ctx, ray, alive, dirs)
        out = []
        base = 0
        for d, ((verts, tris), n_tri) in enumerate(zip(self._quadrature_geometry, per_det)):
            ws = [omegas[base + j] * g[base + j] for j in range(n_tri)]
            if self.quadrature_visibility == "triangle":
                acc = mi.Float(0.0)
                for j, ((a, b, c), _) in enumerate(tris):
                    test = alive & (ws[j] > 0)
                    centroid = (verts[a] + verts[b] + verts[c]) * (1.0 / 3.0)
                    acc = acc + dr.select(self._visible(scene, si, centroid, test, d), ws[j], 0.0)
                out.append(acc)
                base += n_tri
                continue
            total = ws[0]
            for w in ws[1:]:
                total = total + w
            # pick triangle j with probability w_j / total, a uniform point in it, one ray
            u = rand[d][0] * total
            bary = mi.warp.square_to_uniform_triangle(rand[d][1])
            target = mi.Point3f(0.0)
            cum = mi.Float(0.0)
            for j, ((a, b, c), _) in enumerate(tris):
                point = verts[a] * (1.0 - bary.x - bary.y) + verts[b] * bary.x + verts[c] * bary.y
                nxt = cum + ws[j]
                pick = (u >= cum) & (u < nxt) if j + 1 < n_tri else (u >= cum)
                target = dr.select(pick, point, target)
                cum = nxt
            test = alive & (total > 0)
            out.append(dr.select(self._visible(scene, si, target, test, d), total, 0.0))
            base += n_tri
        return out

    def to_string(self):
        names = ", ".join(n for n, _ in self.detectors) or "(resolved at render time)"
        return (f"EloIntegrator[events={self.events}, detector_sampling={self.detector_sampling}, "
                f"detector_samples={self.detector_samples}, units={self.units}, detectors={names}]")


def _beam_key(beam) -> tuple:
    """What the set-up's analyses read of the ``elo_beam`` sensor (None where another sensor lacks it)."""
    return tuple(getattr(beam, a, None) for a in ("wd", "field", "field_y", "projection", "fwhm"))


def _sample_direction(si, ray, ctx, u1, u2, alive):
    """g_BSE at ``si`` sampled with (u1, u2): the world direction and its weight S."""
    bs, weight = si.bsdf(ray).sample(ctx, si, u1, u2, alive)
    return si.to_world(bs.wo), weight[0]


def _option_property(name):
    def get(self):
        return getattr(self.options, name)

    def refuse(self, value):
        raise EloInputError(f"elo: option {name!r} is read-only; use integrator.configure("
                            f"integrator.options.replace({name}={value!r}))")

    return property(get, refuse, doc=f"The ``{name}`` option (read-only; see :class:`EloOptions`).")


for _name in (f.name for f in dataclasses.fields(EloOptions)):
    setattr(EloIntegrator, _name, _option_property(_name))

PLUGIN_CLASS = EloIntegrator
