"""Where the time of a relief path goes: the later events' shadow rays (issue 26, a timing
diagnostic). Each variant in its own process, three warm renders after a first that compiles:

* ``shipped``: the integrator as it is;
* ``no-shadow``: the later events' shadow rays not cast (visibility taken as 1): wrong images,
  for the timing only;
* ``no-wall-shadow``: only those from points on surfaces that are not the scanned relief (the
  chamber's walls) not cast: the most any occlusion analysis of the walls could save.

    python -m benchmarks.shadow_cost                                   # corrugated_chamber 1024²
    python -m benchmarks.shadow_cost --scene melt_chamber --res 1500

The patch lives in this process only (it replaces ``EloIntegrator._sampled``, the later events'
detector estimate, with one whose visibility test skips the chosen rays); the 1st event's
quadrature keeps its rays.
"""

from __future__ import annotations

import subprocess
import sys
import time

VARIANTS = ("shipped", "no-shadow", "no-wall-shadow")


def _patch(variant: str, relief_keys) -> None:
    import drjit as dr
    import mitsuba as mi

    from elo_mitsuba.plugins import integrator_elo as ie

    if variant == "shipped":
        return
    sampled, visible = ie.EloIntegrator._sampled, ie.EloIntegrator._visible

    def skipping(self, scene, si, target, test, d):
        if variant == "no-shadow":
            return test
        sid = dr.reinterpret_array(mi.UInt32, si.shape)
        on_relief = mi.Bool(False)
        for k in relief_keys:
            on_relief |= sid == k
        return visible(self, scene, si, target, test & on_relief, d) | (test & ~on_relief)

    def later_sampled(self, *args, **kwargs):
        ie.EloIntegrator._visible = skipping
        try:
            return sampled(self, *args, **kwargs)
        finally:
            ie.EloIntegrator._visible = visible

    ie.EloIntegrator._sampled = later_sampled


def run_one(scene_name: str, res: int, variant: str) -> list[float]:
    import elo_mitsuba as em

    scene = em.load_scene(scene_name, res=res)
    from elo_mitsuba.plugins._relief import relief_under_beam
    from elo_mitsuba.plugins._shapes import shape_key

    surfaces = [s for s in scene.scene.shapes() if not s.is_emitter()]
    ids = set(relief_under_beam(scene.scene, scene.scene.sensors()[0], surfaces))
    relief = [s for s in surfaces if s.id() in ids]
    print(f"relief: {', '.join(sorted(ids)) or 'none'}", file=sys.stderr)
    _patch(variant, [shape_key(s) for s in relief])
    scene.render(progress=False)  # compiles
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        scene.render(progress=False)
        times.append(time.perf_counter() - t0)
    return times


def main(argv=None) -> int:
    from elo_mitsuba.cli._args import OneLineParser  # a usage error is one line, not the usage

    ap = OneLineParser(prog="python -m benchmarks.shadow_cost", description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="corrugated_chamber")
    ap.add_argument("--res", type=int, default=1024)
    ap.add_argument("--variant", choices=VARIANTS, help="run one variant here (the parent runs each in a process)")
    args = ap.parse_args(argv)
    from elo_mitsuba.arguments import whole_number
    from elo_mitsuba.errors import EloError
    from elo_mitsuba.scene_files import resolve_scene_path

    try:  # before any process starts
        resolve_scene_path(args.scene)
        whole_number("--res", args.res, 1, None)
    except EloError as exc:
        print(f"python -m benchmarks.shadow_cost: error: {exc}", file=sys.stderr)
        return 2
    if args.variant:
        times = run_one(args.scene, args.res, args.variant)
        print(f"{args.variant}: " + ", ".join(f"{t:.2f}" for t in times) + " s")
        return 0
    print(f"{args.scene} {args.res}², default preset, three warm renders each:")
    for variant in VARIANTS:
        out = subprocess.run([sys.executable, "-m", "benchmarks.shadow_cost", "--scene", args.scene, "--res",
                              str(args.res), "--variant", variant], capture_output=True, text=True)
        print(out.stdout.strip() or out.stderr.strip().splitlines()[-1])
    return 0


if __name__ == "__main__":
    sys.exit(main())
