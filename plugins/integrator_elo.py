"""Integrator ``elo``: electrons traced forward from the gun to every detector (Sec. 2.1.1).

The gun is the sensor (``elo_beam``), so a film pixel is a scan point; surfaces carry the
``elo_bse`` BSDF whose ``eval`` is g_BSE (cosine included, ``wi`` towards where the electron came
from); detectors are the shapes carrying an area emitter (unit radiance). Scattering event n is
path vertex n. At every event the integrator estimates, separately for each detector and with
occlusion, the electrons that reach it directly,

    N_{n,d} / N_0 = throughput * int_{Omega_d} g_BSE dOmega          (Eq. 5, and Eq. 8 for n > 1),

by sampling points on the detector (``detector_samples`` per detector and event), and then
continues the path by sampling g_BSE (Eq. 7): the sample weight carries the electrons that leave
in that direction. A continuation ray that hits a detector ends there (the electrons are absorbed,
Eq. 6; they were counted by the direct estimate, so nothing is counted twice); one that leaves
the scene is lost. No bounce ray is traced after the last counted event.

Outputs (one pass): for each detector ``<id>`` the total over the counted events and, when
``events > 1``, each event alone as ``<id>.e<k>``. Values are N_d/N_0, or detector voltages
U_d = (N_d/N_0) I_b T (Eq. 9 with Eq. 3) with ``units="voltage"``.

XML parameters: ``events`` (int >= 1, default 1; Mitsuba's max_depth = events + 1),
``detector_samples`` (int >= 1, default 1), ``units`` ("fraction" or "voltage"),
``beam_current`` (A, default 3e-3), ``transimpedance`` (V/A, default 1e5).
"""

import drjit as dr
import mitsuba as mi

from elo_mitsuba.constants import BEAM_CURRENT_A, DETECTOR_NAMES, TRANSIMPEDANCE_V_PER_A
from elo_mitsuba.errors import EloInputError

UNITS = ("fraction", "voltage")


def find_detectors(scene):
    """[(id, shape)] of the detector shapes (those carrying an emitter), in a stable order.

    right, left, back, front first (the paper's order), then other ids alphabetically.
    """
    found = {}
    for shape in scene.shapes():
        if shape.is_emitter():
            name = shape.id()
            if not name:
                raise EloInputError("a detector shape (one with an emitter) has no id; give it id=\"...\"")
            if name in found:
                raise EloInputError(f"two detector shapes share the id {name!r}")
            found[name] = shape
    order = [n for n in DETECTOR_NAMES if n in found] + sorted(n for n in found if n not in DETECTOR_NAMES)
    return [(n, found[n]) for n in order]


class EloIntegrator(mi.SamplingIntegrator):
    def __init__(self, props):
        mi.SamplingIntegrator.__init__(self, props)
        self.events = int(props.get("events", 1))
        if self.events < 1:
            raise EloInputError(f"elo: events={self.events}; must be >= 1 (1 = first event only)")
        self.detector_samples = int(props.get("detector_samples", 1))
        if self.detector_samples < 1:
            raise EloInputError(f"elo: detector_samples={self.detector_samples}; must be >= 1")
        self.units = str(props.get("units", "fraction"))
        if self.units not in UNITS:
            raise EloInputError(f"elo: units={self.units!r}; allowed: {', '.join(UNITS)}")
        self.beam_current = float(props.get("beam_current", BEAM_CURRENT_A))
        self.transimpedance = float(props.get("transimpedance", TRANSIMPEDANCE_V_PER_A))
        for name, value in (("beam_current", self.beam_current), ("transimpedance", self.transimpedance)):
            if not value > 0:
                raise EloInputError(f"elo: {name}={value!r}; must be > 0")
        self.detectors = []  # [(id, shape)], resolved from the scene at render time

    # ---- set-up ---------------------------------------------------------------------------------
    def prepare_scene(self, scene):
        """Find the detectors of ``scene``; called by :meth:`render` (and the Python API)."""
        detectors = find_detectors(scene)
        if not detectors:
            raise EloInputError(
                "the scene has no detector: mark a shape as detector with <emitter type=\"area\"/> "
                "and give it an id (its channel name)"
            )
        self.detectors = detectors

    def channel_names(self):
        names = []
        for name, _ in self.detectors:
            names.append(name)
            if self.events > 1:
                names += [f"{name}.e{k}" for k in range(1, self.events + 1)]
        return names

    def aov_names(self):
        return self.channel_names()

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        self.prepare_scene(scene)
        return mi.SamplingIntegrator.render(self, scene, sensor, seed, spp, develop, evaluate)

    # ---- the estimator --------------------------------------------------------------------------
    def sample(self, scene, sampler, ray, medium=None, active=True):
        ctx = mi.BSDFContext()
        scale = 1.0 / self.detector_samples
        if self.units == "voltage":
            scale *= self.beam_current * self.transimpedance
        n_det = len(self.detectors)
        per_event = [[mi.Float(0.0) for _ in range(self.events)] for _ in range(n_det)]

        throughput = mi.Float(1.0)
        alive = mi.Bool(active)
        si = scene.ray_intersect(ray, alive)
        for event in range(self.events):
            # electrons scatter only on surfaces that are not detectors (detectors absorb)
            alive &= si.is_valid() & ~si.shape.is_emitter()
            bsdf = si.bsdf(ray)
            for d, (_, shape) in enumerate(self.detectors):
                emitter = shape.emitter()
                for _ in range(self.detector_samples):
                    ds, em_weight = emitter.sample_direction(si, sampler.next_2d(alive), alive)
                    # em_weight = 1/pdf (unit radiance), 0 at the detector's back face
                    test = alive & (ds.pdf > 0)
                    visible = test & ~scene.ray_test(si.spawn_ray_to(ds.p), test)
                    g = bsdf.eval(ctx, si, si.to_local(ds.d), visible)[0]
                    per_event[d][event] += dr.select(visible, throughput * g * em_weight[0], 0.0)
            if event + 1 < self.events:
                bs, weight = bsdf.sample(ctx, si, sampler.next_1d(alive), sampler.next_2d(alive), alive)
                throughput *= weight[0]
                alive &= throughput > 0
                ray = si.spawn_ray(si.to_world(bs.wo))
                si = scene.ray_intersect(ray, alive)

        aovs = []
        total_all = mi.Float(0.0)
        for d in range(n_det):
            events = [e * scale for e in per_event[d]]
            total = events[0]
            for e in events[1:]:
                total = total + e  # not +=: Dr.Jit's in-place add would alias events[0]
            total_all = total_all + total
            aovs.append(total)
            if self.events > 1:
                aovs += events
        return mi.Spectrum(total_all), mi.Bool(True), aovs

    def to_string(self):
        names = ", ".join(n for n, _ in self.detectors) or "(resolved at render time)"
        return (f"EloIntegrator[events={self.events}, detector_samples={self.detector_samples}, "
                f"units={self.units}, detectors={names}]")


PLUGIN_CLASS = EloIntegrator
