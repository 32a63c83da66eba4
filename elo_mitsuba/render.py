"""Python API of the forward model: load a scene once, render detector images many times.

A session (not run as a doctest; each function's Examples section runs)::

    import elo_mitsuba as em
    scene = em.load_scene("athene_flat", dh=272, dw=127)   # shipped scene name or XML path
    scene = em.load_scene("melt_plate", detector_layout="zeta50")  # Table 1 layout
    result = scene.render(spp=64, events=2)                 # numpy channels + metadata
    result.channels["right"].shape, result.channels["right.e2"].mean()
    scene.set_detector("right", center=(150, 0, 250))       # move a detector: same kernel
    scene.set_material("plate", "316L")                     # change a material: same kernel
    result.write_exr("right.exr")

Channels are float32 images in the package orientation (:mod:`elo_mitsuba.grid`: row 0 at the
+y edge, columns towards +x): ``<id>`` is the total over the counted events, ``<id>.e<k>`` event k
alone (only when ``events > 1``). Values are N_d/N_0 (or volts with ``units="voltage"``).
"""

from __future__ import annotations

import sys

import numpy as np

from ._version import __version__
from .constants import MAX_SEED, MAX_SPP
from .errors import EloError, EloInputError
from .budget import check_render, detector_points, fits_in_memory
from .grid import ORIENTATION
from .error_estimate import DETERMINISTIC, METHOD, combine_channels, half_weights, split_render
from .passes import may_merge, render_passes
from .sample_counts import pass_count, pass_sizes
from .options import (PRESET_FIELDS, QUALITIES, check_scene_options, QUALITY_PRESETS, SAMPLE_OPTIONS, EloOptions, check_combination,
                      quality_options)
from .progress import RenderProgress
from .arguments import flag, length, shown, vector3, whole_number
from .result import NEGLIGIBLE_EVENT_SHARE, NO_SIGNAL_CAUSES, RenderResult  # noqa: F401 -- part of this module's API
from . import surfaces
from .runtime import ensure_variant
from .schema import (AIM_OFFSET, BEAM_FWHM, DETECTORS, MATERIALS, MAX_LENGTH_MM, PROJECTION, SCATTERING, UNITS,
                     WORK_DISTANCE, grid_header, signal_units)
from .scene_files import (check_detector_placement, check_detectors_apart, declared_parameters, detector_up,
                          explain_mitsuba_error, layout_name, not_finite, resolve_scene_path, scene_values)

#: Number of samples (pixels x spp) rendered in one pass; larger jobs are split into passes
#: (same kernel, different seeds) so that progress can be shown and memory stays bounded.
SAMPLES_PER_PASS = 1 << 24
#: Most samples per pixel in one pass: Mitsuba's film sums a pixel's samples in float32, whose
#: rounding grows with their number (2.6e5 identical samples drift by 5e-4); passes are summed
#: in float64, so more samples never make a result worse.
MAX_SPP_PER_PASS = 1024
#: Options whose validity depends on the scene (detector ids, detector shapes for the quadrature):
#: EloScene.configure checks them at once; the others are checked by EloOptions alone.
_NEEDS_THE_SCENE = {"front_only", "detector_sampling", "quadrature_triangles"}


# ---- the scene ----------------------------------------------------------------------------------------
class EloScene:
    """A loaded ELO scene, rendered again and again without reloading or recompiling.

    Parameters
    ----------
    scene : str or Path
        XML file, or the name of a shipped scene.
    variant : str, optional
        ``llvm_ad_mono`` (default) or ``cuda_ad_mono``; also ``$ELO_MITSUBA_VARIANT``.
    detector_layout : str, optional
        A Table 1 detector layout (``"zeta25"`` ... ``"zeta75"``), same as giving its dh and dw.
    **params
        Values for the scene's ``<default>`` parameters (``dh``, ``dw``, ``wd``, ``field``,
        ``res``, ...), as ``-D name=value`` does on the command line.

    Attributes
    ----------
    path : Path
        The scene file.
    params : dict of str to str
        The scene's ``<default>`` parameters with the values given.

    Examples
    --------
    >>> import elo_mitsuba as em
    >>> scene = em.EloScene("flat_plate", res=4)       # shipped scene, 4 x 4 pixels
    >>> scene.detector_names
    ['right', 'left', 'back', 'front']
    >>> scene.params["res"], scene.quality
    ('4', 'scene')
    """

    def __init__(self, scene, variant: str | None = None, detector_layout: str | None = None, **params):
        # the scene and its parameters are checked (XML only) before Mitsuba is imported: in a new
        # process a misspelt scene or parameter is refused in a fraction of a second
        self.path = resolve_scene_path(scene)
        values = scene_values(detector_layout, params)  # a layout and its dh/dw both given: refused
        declared = declared_parameters(self.path, {k: str(v) for k, v in values.items()})
        if detector_layout is not None and "layout" in declared:  # the header names the layout used, not the
            values["layout"] = layout_name(detector_layout)      # file's default (its dh/dw are given explicitly)
        unknown = [k for k in values if k not in declared]
        if unknown:
            allowed = ", ".join(sorted(declared)) or "none"
            raise EloInputError(
                f"{self.path}: parameter {unknown[0]!r} is not declared by this scene (it declares: {allowed})"
            )
        for k, v in values.items():  # Mitsuba would take inf and nan, and fail far from the cause
            if not_finite(v):
                raise EloInputError(f"{self.path}: parameter {k}={str(v)!r} is not a finite number (-D {k}=...): "
                                    "the scene's parameters are lengths (mm), angles and counts")
        if _number_below_zero(values.get("dw")):  # the shipped scenes place each detector at dw along its own side
            raise EloInputError(f"{self.path}: parameter dw={values['dw']} is negative (-D dw=...): dw is the "
                                "detectors' distance from the z-axis, >= 0 mm; a negative one would put the detector "
                                "named right on the left (and back at the front)")
        self.mi = ensure_variant(variant)
        self.params = {**declared, **{k: str(v) for k, v in values.items()}}
        try:
            self.scene = self.mi.load_file(str(self.path), **{k: str(v) for k, v in values.items()})
        except EloError:
            raise
        except Exception as exc:  # Mitsuba wraps everything in RuntimeError
            raise EloInputError(explain_mitsuba_error(exc, self.path, values)) from None
        self.integrator = self.scene.integrator()
        sensors = self.scene.sensors()  # a second one would be ignored without a word
        self.sensor = sensors[0] if len(sensors) == 1 else None
        if not hasattr(self.integrator, "prepare_scene"):
            raise EloInputError(f"{self.path}: the integrator must be <integrator type=\"elo\"/>")
        if not hasattr(self.sensor, "beam_target"):
            raise EloInputError(f"{self.path}: the scene needs one sensor, <sensor type=\"elo_beam\"> (the gun); it has "
                                f"{', '.join(type(x).__name__ for x in sensors) or 'none'}")
        try:
            self.integrator.prepare_scene(self.scene)
        except EloInputError as exc:  # the scene file is what holds the fault
            raise EloInputError(f"{self.path}: {exc}") from None
        # the scene file's spp, read once: Mitsuba's render(spp=n) sets the sensor's sampler to n,
        # so the sampler cannot be asked again after a render (each render would halve it)
        self.scene_spp = int(self.sensor.sampler().sample_count())
        #: the quality every render applies unless told another: a preset's name, ``"scene"``, or
        #: ``"custom"`` once configure() changed a field a preset sets (then the options stay as set)
        self.quality = "scene"
        #: the fields a preset sets as they were before the first preset overwrote them (the scene
        #: file's, with what configure() changed), restored by ``quality="scene"``; None: not overwritten
        self._own_fields = None
        #: the options set by configure(), for the check that a preset applied later uses them
        self._configured: dict = {}
        self.mi_params = self.mi.traverse(self.scene)
        #: each placed detector's transform as loaded (float64 copies), for restore_detectors()
        self._loaded = {name: np.array(self.mi_params[f"{name}.to_world"].matrix, dtype=np.float64).reshape(4, 4)
                        for name in self.detector_names if f"{name}.to_world" in self.mi_params}
        self._placed: dict = {}  # each moved detector's centre and radius as set_detector last set them
        self.check_detectors()

    # -- introspection --
    @property
    def detector_names(self) -> list[str]:
        return [name for name, _ in self.integrator.detectors]

    def detector_geometry(self) -> dict[str, dict]:
        """Centre, unit normal (front face) and equivalent radius of each detector, in mm.

        Returns
        -------
        dict of str to dict
            Per detector id: ``center`` (x, y, z in mm), ``normal`` (unit vector of the front face,
            towards the field), ``radius`` (mm; of a disc of the same area) and ``area_mm2`` (mm^2).

        Raises
        ------
        EloInputError
            A detector of zero area (a scale of 0 in its transform).

        Examples
        --------
        >>> import elo_mitsuba as em
        >>> scene = em.load_scene("flat_plate", res=4)
        >>> right = scene.detector_geometry()["right"]
        >>> [round(v, 4) for v in right["center"]], [round(v, 4) for v in right["normal"]]
        ([127.0, 0.0, 272.0], [-0.4231, 0.0, -0.9061])
        >>> round(right["radius"], 4), round(right["area_mm2"], 1)
        (25.0, 1963.5)
        """
        from .plugins._detectors import detector_geometry  # Mitsuba is imported by now

        out = {}
        for name, shape in self.integrator.detectors:
            key = f"{name}.to_world"
            with np.errstate(invalid="ignore", over="ignore"):  # NaN from a scale beyond float32: refused below
                out[name] = detector_geometry(shape, self.mi_params[key] if key in self.mi_params else None)
            if not (out[name]["area_mm2"] > 0 and np.all(np.isfinite(out[name]["normal"]))):
                why = "a scale of 0 in its transform?" if out[name]["area_mm2"] == 0 else "a scale beyond float32?"
                raise EloInputError(f"{self.path}: detector {name!r} has area {out[name]['area_mm2']:g} mm^2 "
                                    f"({why}); a detector needs a finite radius > 0")
        return out

    def materials(self) -> dict[str, str]:
        """``{shape id: material}`` of the shapes with an ``elo_bse`` BSDF."""
        return surfaces.materials(self.scene)

    def metadata(self, spp: int, seed: int) -> dict:
        s = self.sensor
        geometry = self.detector_geometry()
        w, h = s.resolution
        meta = {
            "generator": f"elo-mitsuba {__version__}",
            "scene": str(self.path),
            # the scene file's parameters as this render applied them (a preset replaces the sampler's spp)
            "parameters": {**self.params, **{k: str(v) for k, v in (("spp", spp), ("events", self.integrator.events))
                                             if k in self.params}},
            UNITS: signal_units(self.integrator.units),
            **grid_header((s.field, s.field_y), (h, w)),  # the key names of schema.py, its one writer
            "pixel_size_mm": s.field / s.resolution[0],
            WORK_DISTANCE: s.wd,
            PROJECTION: s.projection,
            BEAM_FWHM: s.fwhm,
            AIM_OFFSET: list(s.aim_offset_mm),
            "events": self.integrator.events,
            "detector_samples": self.integrator.detector_samples,
            "quality": self.quality,
            "integrator_options": self.integrator.options.as_dict(),
            "notes": list(getattr(self.integrator, "notes", [])) + surfaces.material_notes(self.scene),
            "spp": int(spp),
            "seed": int(seed),
            DETECTORS: geometry,
            MATERIALS: self.materials(),
            SCATTERING: surfaces.scattering(self.scene),
            "orientation": ORIENTATION,
            "variant": self.mi.variant(),
        }
        if self.integrator.units == "voltage":
            meta["beam_current_A"] = self.integrator.beam_current
            meta["transimpedance_V_per_A"] = self.integrator.transimpedance
        return meta

    def check_detectors(self, apart: bool = True) -> None:
        """Refuse a detector system no render can use: a disc through the build plane or facing
        away from the field (:func:`~elo_mitsuba.scene_files.check_detector_placement`) and, with
        ``apart``, two discs that intersect (:func:`~elo_mitsuba.scene_files.check_detectors_apart`).
        Called on loading, by :meth:`set_detector` (each disc; detectors moved one by one may cross
        on their way) and by :meth:`render` (all of them, before any work)."""
        geometry = self.detector_geometry()
        for name, geo in geometry.items():
            check_detector_placement(name, geo["center"], geo["normal"], geo["radius"], where=str(self.path))
        if apart:
            check_detectors_apart(geometry, where=str(self.path))

    # -- changing parameters without reloading --
    @property
    def options(self) -> EloOptions:
        """The integrator's options (:class:`~elo_mitsuba.options.EloOptions`) for the next render."""
        return self.integrator.options

    def configure(self, **changes) -> EloOptions:
        """Change integrator options for the following renders (validated; same kernel where only
        values change), e.g. ``scene.configure(units="voltage", detector_samples=4)``.

        Parameters
        ----------
        **changes
            Fields of :class:`~elo_mitsuba.options.EloOptions` and their new values (``events``,
            ``units``, ``detector_samples``, ...). Options that depend on the scene (``front_only``,
            ``detector_sampling``, ``quadrature_triangles``) are checked against it at once; a refused
            change leaves the options as they were.

        Returns
        -------
        EloOptions
            The options the next render uses.

        Examples
        --------
        >>> import elo_mitsuba as em
        >>> scene = em.load_scene("flat_plate", res=4)
        >>> options = scene.configure(units="voltage", detector_samples=4)
        >>> options.units, options.detector_samples
        ('voltage', 4)
        >>> scene.render(spp=4).metadata["units"]
        'V'
        """
        saved = self.integrator.options
        self.integrator.configure(saved.replace(**changes))
        if _NEEDS_THE_SCENE.intersection(changes):  # checked against the scene now, not at render
            try:
                self.integrator.prepare_scene(self.scene, self.sensor)
            except EloError:
                self.integrator.configure(saved)
                raise
        self._configured.update(changes)
        if set(PRESET_FIELDS).intersection(changes) and self.quality in QUALITY_PRESETS:
            self.quality = "custom"  # a preset re-applied at the next render would undo the change
        return self.integrator.options

    def set_events(self, events: int):
        self.configure(events=events)

    def set_material(self, shape_id: str, material) -> None:
        """Give the ``elo_bse`` BSDF of shape ``shape_id`` another material (same kernel).

        Parameters
        ----------
        shape_id : str
            The ``id`` of a shape with an ``elo_bse`` BSDF (e.g. ``"plate"``).
        material : str, mapping or Material
            A preset name (``"316L"``, ``"ti64"``, ...), a composition (``"Fe:0.7,Cr:0.3"`` or
            ``{"Fe": 0.7, "Cr": 0.3}``, weight fractions) or a
            :class:`~elo_mitsuba.physics.materials.Material`.

        Raises
        ------
        EloInputError
            No shape of that id, or the shape has no ``elo_bse`` BSDF.

        Examples
        --------
        >>> import elo_mitsuba as em
        >>> scene = em.load_scene("flat_plate", res=4)
        >>> scene.materials()
        {'plate': 'Ti-6Al-4V (Ti:0.9,Al:0.06,V:0.04)'}
        >>> scene.set_material("plate", "316L")
        >>> scene.materials()["plate"]
        '316L (Fe:0.655,...)'
        """
        for shape in self.scene.shapes():
            if shape.id() == shape_id:
                bsdf = shape.bsdf()
                if not hasattr(bsdf, "set_material"):
                    raise EloInputError(f"shape {shape_id!r} has no elo_bse BSDF")
                bsdf.set_material(material)
                self.params.pop("material", None)  # no longer what the shapes hold: the header's 'materials' says
                return
        ids = ", ".join(sorted(s.id() for s in self.scene.shapes() if s.id()))
        raise EloInputError(f"no shape with id {shape_id!r} (shapes: {ids})")

    def set_detector(self, name: str, center=None, radius: float | None = None, normal=None) -> None:
        """Move a disk detector to ``center`` (mm; default: where it is), facing the origin or along
        ``normal`` (its front normal, towards the field; any length); optionally resize it.

        Without ``normal`` the detector faces the origin, also when only the radius changes: the
        result depends on the arguments alone, not on earlier moves (a sweep's point equals a
        fresh scene with the same call, bit for bit).

        Parameters
        ----------
        name : str
            Detector id (a disk detector of the scene), e.g. ``"right"``.
        center : (float, float, float), optional
            New centre (x, y, z) in mm; default: the current centre. The origin is refused.
        radius : float, optional
            New radius in mm (> 0); default: the current radius.
        normal : (float, float, float), optional
            Front normal, towards the field (any length > 0); default: towards the origin.

        Raises
        ------
        EloInputError
            Unknown detector, a detector that is not a disk, or a placement refused by the scene's
            checks (the detector then stays where it was).

        Examples
        --------
        >>> import elo_mitsuba as em
        >>> scene = em.load_scene("flat_plate", res=4)
        >>> scene.set_detector("right", center=(150, 0, 250), radius=20)
        >>> right = scene.detector_geometry()["right"]
        >>> [round(v, 4) for v in right["center"]], round(right["radius"], 4)
        ([150.0, 0.0, 250.0], 20.0)
        >>> [round(v, 4) for v in right["normal"]]      # faces the origin
        [-0.5145, 0.0, -0.8575]
        """
        mi = self.mi
        key = f"{name}.to_world"
        if name not in self.detector_names:
            raise EloInputError(f"no detector {name!r} (detectors: {', '.join(self.detector_names)})")
        shape = dict(self.integrator.detectors)[name]  # a rectangle or sphere has a to_world too
        if key not in self.mi_params or shape.shape_type() != self.mi.ShapeType.Disk:
            raise EloInputError(f"detector {name!r} is not a disk; move it by editing the scene")
        # where it is: as last set (float64), not as read back from the float32 transform, so that a
        # move's result does not depend on the moves before it
        geo = {**self.detector_geometry()[name], **self._placed.get(name, {})}
        c = vector3(f"detector {name!r}: centre", center if center is not None else geo["center"],
                    limit=MAX_LENGTH_MM)
        r = length(f"detector {name!r}: radius", radius if radius is not None else geo["radius"])
        if not np.any(np.abs(c) > 1e-9):
            raise EloInputError(f"detector {name!r}: centre {c.tolist()} is the origin; a detector faces the field "
                                "from above it")
        n = vector3(f"detector {name!r}: normal", normal) if normal is not None else -c
        if not np.abs(n).max() > 0:  # not its norm: that of (1e300, 1e300, 1e300) overflows with a warning
            raise EloInputError(f"detector {name!r}: normal {n.tolist()} is zero")
        n = n / np.abs(n).max()  # no norm of (1e300, 0, -1e300) overflows to inf
        n = n / np.linalg.norm(n)
        up = detector_up(c, n)
        xf = (mi.ScalarTransform4f().look_at(origin=c.tolist(), target=(c + n).tolist(), up=up)
              @ mi.ScalarTransform4f().scale(r))
        previous = np.array(self.mi_params[key].matrix, dtype=np.float64).reshape(4, 4)  # a copy
        self.mi_params[key] = mi.Transform4f(xf)
        self.mi_params.update()
        try:
            self.check_detectors(apart=False)
        except EloError:  # a refused move is not kept
            self.mi_params[key] = mi.Transform4f(mi.ScalarTransform4f(previous))
            self.mi_params.update()
            raise
        self._placed[name] = {"center": c, "radius": r}

    def restore_detectors(self, names=None) -> None:
        """Put detectors ``names`` (default: all) back where the scene file placed them.

        The transform is rebuilt from its float32 values, so its inverse may differ in the last bit
        from a fresh load's (up to 2e-7 relative in the images): a caller that needs a fresh
        load's numbers bit for bit moves the detector again with :meth:`set_detector` (computed
        afresh, as in a new scene) or loads the scene anew.

        Parameters
        ----------
        names : iterable of str, optional
            Detector ids; default: every detector the scene file placed by a transform.

        Raises
        ------
        EloInputError
            A name that is not a placed detector.

        Examples
        --------
        >>> import elo_mitsuba as em
        >>> scene = em.load_scene("flat_plate", res=4)
        >>> scene.set_detector("right", center=(150, 0, 250))
        >>> scene.restore_detectors(["right"])
        >>> [round(v, 4) for v in scene.detector_geometry()["right"]["center"]]
        [127.0, 0.0, 272.0]
        """
        names = (list(self._loaded) if names is None else [names] if isinstance(names, str) or not hasattr(names, "__iter__")
                 else list(names))
        unknown = [n for n in names if n not in self._loaded]
        if unknown:
            raise EloInputError(f"no placed detector {unknown[0]!r} (detectors: {', '.join(self._loaded)})")
        for name in names:
            self.mi_params[f"{name}.to_world"] = self.mi.Transform4f(self.mi.ScalarTransform4f(self._loaded[name]))
            self._placed.pop(name, None)
        if names:
            self.mi_params.update()

    def set_quality(self, quality: str) -> int:
        """Apply a quality preset (:data:`~elo_mitsuba.options.QUALITY_PRESETS`) to the integrator for this scene's
        resolution, events and beam, for this and every later render; returns its spp. ``scene``:
        the scene file's sampler count, and the fields a preset sets as they were before a preset
        overwrote them (the scene file's, with what :meth:`configure` changed); ``custom``: the
        options as they are, the scene file's spp.

        Parameters
        ----------
        quality : str
            ``"draft"``, ``"default"``, ``"reference"``, ``"unbiased"`` (:data:`~elo_mitsuba.options.QUALITY_PRESETS`),
            ``"scene"`` or ``"custom"``.

        Returns
        -------
        int
            Samples per pixel of that quality (the scene file's for ``scene`` and ``custom``).

        Raises
        ------
        EloInputError
            An unknown quality.

        Examples
        --------
        >>> import elo_mitsuba as em
        >>> scene = em.load_scene("flat_plate", res=4)
        >>> scene.set_quality("scene")                   # the scene file's sampler count
        16
        >>> spp = scene.set_quality("draft")
        >>> scene.quality, spp >= 1
        ('draft', True)
        """
        _check_quality(quality)
        if quality in ("scene", "custom"):
            if quality == "scene" and self._own_fields is not None:
                self.integrator.configure(self.integrator.options.replace(**self._own_fields))
                self._own_fields = None
            self.quality = quality
            return self.scene_spp
        if self._own_fields is None:
            self._own_fields = {f: getattr(self.integrator.options, f) for f in PRESET_FIELDS}
        pixel_mm = self.sensor.field / self.sensor.resolution[0]
        options, spp = quality_options(quality, self.integrator.options, pixel_mm=pixel_mm,
                                       fwhm_mm=self.sensor.fwhm, traced_events=self.integrator.traced_events(),
                                       relief=bool(self.integrator.relief),
                                       near_share=self.integrator.near_share(self.scene, self.sensor),
                                       size_px=max(self.sensor.resolution))
        self.integrator.configure(options)
        self.quality = quality
        return spp

    # -- rendering --
    def render(self, spp: int | None = None, seed: int = 0, events: int | None = None,
               progress: bool | None = None, quality: str | None = None, force: bool = False) -> RenderResult:
        """Render all detector channels; returns numpy images and metadata.

        ``quality`` (a preset of :data:`~elo_mitsuba.options.QUALITY_PRESETS`, or ``"scene"``)
        applies to this and later renders; without it the scene's current quality
        (:meth:`set_quality`; ``"scene"`` when loaded) is applied again. ``spp`` defaults to the
        quality's (``scene``: the scene file's sampler count). A render depends on the scene's
        state and its arguments only, never on earlier renders. Large jobs run as several passes of one compiled
        kernel. Before any work, a render that cannot fit in memory is refused and a long one
        gets a note (:func:`elo_mitsuba.budget.check_render`). ``progress``: None (default) shows
        progress on stderr for multi-pass renders, as a bar on a terminal and otherwise as a line
        per 10 % once the render has run for :data:`~elo_mitsuba.progress.PROGRESS_AFTER_S`; True always, False never
        (no notes either). ``force=True`` (CLI ``--yes``) lets a render estimated to run longer than
        :data:`~elo_mitsuba.budget.REFUSE_SECONDS` start; memory beyond what is available is refused always.

        Parameters
        ----------
        spp : int, optional
            Samples per pixel (>= 1); default: the quality's.
        seed : int
            Seed of the samplers, in [0, 2^32 - 1]; the same seed gives the same images.
        events : int, optional
            Scattering events to trace (as :meth:`configure` ``events=``, kept for later renders).
        progress : bool, optional
            None: progress for multi-pass renders; True: always; False: never (no notes either).
        quality : str, optional
            A preset, ``"scene"`` or ``"custom"`` (:meth:`set_quality`), for this and later renders.
        force : bool
            Start a render estimated to run longer than :data:`~elo_mitsuba.budget.REFUSE_SECONDS`.

        Returns
        -------
        RenderResult
            Channels ``<id>`` (and ``<id>.e<k>`` with ``events > 1``) as float32 (H, W) images in
            N_d/N_0 (V with ``units="voltage"``), metadata and per-pixel standard errors.

        Raises
        ------
        EloInputError
            A bad argument, or a render that would not fit in memory (or run too long without
            ``force``).

        Examples
        --------
        >>> import elo_mitsuba as em
        >>> scene = em.load_scene("flat_plate", res=4)
        >>> result = scene.render(spp=4, events=2, progress=False)
        >>> result.detectors, result.channels["right"].shape, result.channels["right"].dtype
        (['right', 'left', 'back', 'front'], (4, 4), dtype('float32'))
        >>> sorted(n for n in result.channels if n.startswith("right"))
        ['right', 'right.e1', 'right.e2']
        >>> result.metadata["units"], result.metadata["spp"], result.metadata["events"]
        ('N_d/N_0', 4, 2)
        >>> bool(0 < result.channels["right"].mean() < 1)
        True
        """
        seed = whole_number("seed", seed, 0, MAX_SEED)  # checked before anything changes
        spp, force = None if spp is None else whole_number("spp", spp, 1, MAX_SPP), flag("force", force)
        progress = flag("progress", progress, none=True)
        if quality is not None:
            _check_quality(quality)
        self.check_detectors()
        before = (self.integrator.events, self.quality)  # what a refused render leaves as it was
        try:
            if events is not None:
                self.set_events(events)
            # the quality is applied at every render, so that the result depends on the scene's state
            # (events, resolution, beam) and the arguments, never on what was rendered before
            quality = quality if quality is not None else self.quality
            check_scene_options(self.integrator.scene_options, [quality], where=str(self.path))
            if quality in QUALITY_PRESETS:  # sample counts configured earlier that the preset would not use
                check_combination({k: v for k, v in self._configured.items() if k in SAMPLE_OPTIONS},
                                  base=self.integrator.options, qualities=[quality],
                                  events=events if events is not None else self.integrator.events,
                                  bounce_possible=self.integrator.bounce_possible)
            preset_spp = self.set_quality(quality)
            spp = int(preset_spp if spp is None else spp)
            pixels = self.sensor.resolution[0] * self.sensor.resolution[1]
            per_pass = max(1, min(spp, MAX_SPP_PER_PASS, SAMPLES_PER_PASS // max(pixels, 1)))
            halves, first_status = split_render(spp, self.integrator, self.sensor.fwhm)
            sampler = self.sensor.sampler()
            passes = [pass_sizes(sampler, n, per_pass) for n, _ in halves]
            n_passes = sum(pass_count(sizes) for sizes in passes)
            names = self.integrator.channel_names()
            # the mean channels are film channels too (the fit below them counted the named ones)
            channels = len(names) + 1 + len(self.integrator.mean_channels())
            points = detector_points(self.integrator)
            # one pass for both halves holds both halves' channels: only where that fits in memory
            merge = may_merge(spp, halves, self.integrator) and fits_in_memory(
                self.sensor.resolution, channels + len(names), spp, self.integrator.traced_events(), 1,
                detector_points=points)
            channels += len(names) if merge else 0
            notes = check_render(self.sensor.resolution, channels, spp, self.integrator.traced_events(),
                                 max(n_passes, 2 if len(halves) > 1 else 1), detector_points=points, force=force)
        except EloError:  # the next render applies its own quality (set_quality) from these
            self.set_events(before[0])
            self.quality = before[1]
            raise
        if progress is not False:
            for note in notes:
                print(f"elo-mitsuba: note: {note}", file=sys.stderr, flush=True)
        # progress counts samples of both halves (a half of a 1-spp render counts as one)
        work = sum(n for n, _ in halves)
        report = RenderProgress(work, n_passes, progress)
        # film channels ('Y', then the AOVs in our order) as (channels, H, W) float32 straight from the
        # film's storage (peak memory near the film's own); the passes of each half summed in float64
        saved = self.integrator.options
        try:
            sums, first_status = render_passes(self.integrator, self.scene, halves, passes, spp, seed, report,
                                               first_status, merge)
        finally:
            self.integrator.configure(saved)
            report.end()
        channels, errors, summary = combine_channels(names, sums, half_weights(halves), first_status)
        for name, img in channels.items():
            if not np.all(np.isfinite(img)):
                raise EloError(f"channel {name!r} holds NaN/Inf: a defect; please report the scene")
        meta = self.metadata(spp, seed)
        meta["error_estimate"] = {"method": METHOD, "channels": summary}
        result = RenderResult(channels, meta, errors)
        meta["notes"] += [f"detector {n!r} received no electron anywhere in the scan ({NO_SIGNAL_CAUSES})"
                          for n in result.dark_detectors]  # a fact of the geometry or a mistake in it: never silent
        if spp > 1 and summary and all(s.get("status") == DETERMINISTIC for s in summary.values()):
            # e.g. the 1st event by the quadrature under a single-ray beam, with nothing to scatter twice
            meta["notes"].append(f"every channel came out deterministic (the two halves of the {spp} spp agree to "
                                 f"rounding: nothing in this render is drawn at random); spp 1 gives the same images "
                                 f"in about 1/{spp} of the time")
        return result


def _check_quality(quality) -> None:
    """One line for a quality that is not a preset's name, ``scene`` or ``custom``."""
    if not isinstance(quality, str) or quality not in QUALITIES + ("custom",):
        raise EloInputError(f"quality {shown(quality)}; choose one of {', '.join(QUALITIES)}")


def _number_below_zero(value) -> bool:
    """True for a value that reads as a number < 0 (text such as a material's name is not one)."""
    try:
        return float(str(value)) < 0
    except ValueError:
        return False


def load_scene(scene, variant: str | None = None, detector_layout: str | None = None, **params) -> EloScene:
    """Load an XML scene (path or shipped name) for repeated rendering; see :class:`EloScene`.

    Parameters
    ----------
    scene : str or Path
        XML file, or the name of a shipped scene (``"flat_plate"``, ``"melt_plate"``, ...).
    variant : str, optional
        ``llvm_ad_mono`` (default) or ``cuda_ad_mono``; also ``$ELO_MITSUBA_VARIANT``.
    detector_layout : str, optional
        A Table 1 detector layout (``"zeta25"`` ... ``"zeta75"``), same as giving its dh and dw (mm).
    **params
        Values of the scene's ``<default>`` parameters (``dh``, ``dw``, ``wd``, ``field`` in mm;
        ``res`` in pixels; ``spp``, ...).

    Returns
    -------
    EloScene

    Raises
    ------
    EloInputError
        An unknown scene or parameter, or a scene Mitsuba cannot load.

    Examples
    --------
    >>> import elo_mitsuba as em
    >>> scene = em.load_scene("flat_plate", res=4, detector_layout="zeta50")
    >>> scene.params["dh"], scene.params["dw"], scene.params["res"]
    ('192.7', '229.6', '4')
    >>> [round(v, 1) for v in scene.detector_geometry()["right"]["center"]]
    [229.6, 0.0, 192.7]
    """
    return EloScene(scene, variant=variant, detector_layout=detector_layout, **params)


def render(scene, spp: int | None = None, events: int | None = None, seed: int = 0,
           variant: str | None = None, detector_layout: str | None = None, force: bool = False,
           **params) -> RenderResult:
    """Render a scene (path, shipped name or :class:`EloScene`) and return its detector images
    (``force``: see :meth:`EloScene.render`).

    Parameters
    ----------
    scene : str, Path or EloScene
        XML file, shipped scene name, or a loaded scene.
    spp, events, seed, force :
        As :meth:`EloScene.render`.
    variant, detector_layout, **params :
        As :func:`load_scene` (only when ``scene`` is not loaded yet).

    Returns
    -------
    RenderResult

    Raises
    ------
    EloInputError
        Scene parameters given with a loaded :class:`EloScene`, or as :func:`load_scene` and
        :meth:`EloScene.render`.

    Examples
    --------
    >>> import elo_mitsuba as em
    >>> result = em.render("flat_plate", spp=4, res=4)
    >>> sorted(result.channels), result.channels["left"].shape
    (['back', 'front', 'left', 'right'], (4, 4))
    """
    if not isinstance(scene, EloScene):
        scene = load_scene(scene, variant=variant, detector_layout=detector_layout, **params)
    elif params or detector_layout or variant is not None:
        raise EloInputError("scene parameters (and the variant) are fixed once an EloScene is loaded; use "
                            "set_detector/set_material, or load_scene anew")
    return scene.render(spp=spp, seed=seed, events=events, force=force)
