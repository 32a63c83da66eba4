"""The presets at the paper's resolution on the chamber scenes (issue 26's targets): each scene in
its own process, ``default`` and ``reference`` interleaved over three rounds at events 1 + 2; per
preset the first render (kernels compiled, tables built), the faster of the warm ones, the
render's own error estimate (two independent halves; RMS over pixels, worst detector) of the total
and of e2, and the process's peak resident memory.

    python -m benchmarks.presets_1500                                  # the four chamber scenes
    python -m benchmarks.presets_1500 --scenes shield_chamber --res 512
    python -m benchmarks.presets_1500 --passes     # each preset also in two passes, interleaved

``--passes``: each preset also as two passes (one per half of the error estimate) instead of the
one pass that traces both (elo_mitsuba/passes.py), in the same process and rounds: the ratio of
their times is the one pass's gain, the errors are those of other random numbers.

Prints a Markdown table (benchmarks/RESULTS.md, section Far field).
"""

from __future__ import annotations

import argparse
import json
import sys
import time

from .harness import DETS, estimated_rel, run_module

SCENES = ("athene_flat", "shield_chamber", "melt_chamber", "corrugated_chamber")
PRESETS = ("default", "reference")
ROUNDS = 3


def measure(scene: str, res: int, passes: bool = False) -> list[dict]:
    """One scene in this process: a row per preset (and per way of passes, with ``passes``)."""
    import importlib
    import resource

    import elo_mitsuba as em
    from elo_mitsuba.schema import event_channel

    render = importlib.import_module("elo_mitsuba.render")  # the module (the package's name is a function)

    loaded = em.load_scene(scene, res=res)
    fits = render.fits_in_memory
    runs: dict[str, list] = {}
    for round_ in range(ROUNDS):
        for preset in PRESETS:
            for two in ((False, True) if passes else (False,)):
                # two passes: as where both halves' film would not fit in memory
                render.fits_in_memory = (lambda *a, **k: False) if two else fits
                try:
                    t = time.perf_counter()
                    result = loaded.render(quality=preset, progress=False, events=2, seed=round_ + 1)
                    seconds = time.perf_counter() - t
                finally:
                    render.fits_in_memory = fits
                total = max(estimated_rel(result, d) for d in DETS)
                e2 = max(estimated_rel(result, event_channel(d, 2)) for d in DETS)
                runs.setdefault(preset + (", two passes" if two else ""), []).append((seconds, total, e2))
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return [{"scene": scene, "preset": p, "first": v[0][0], "warm": min(x[0] for x in v[1:]), "total": v[-1][1],
             "e2": v[-1][2], "peak_mb": peak} for p, v in runs.items()]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.presets_1500", description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), help="shipped scenes (default: the chamber scenes)")
    ap.add_argument("--res", type=int, default=1500, help="film side in pixels (default 1500)")
    ap.add_argument("--passes", action="store_true",
                    help="each preset also in two passes (one per half), interleaved: the one pass's gain")
    ap.add_argument("--one", help=argparse.SUPPRESS)  # the worker: one scene, a RESULT line on stdout
    args = ap.parse_args(argv)
    if args.one:
        print("RESULT " + json.dumps(measure(args.one, args.res, args.passes)))
        return 0
    from elo_mitsuba.scene_files import shipped_scenes

    unknown = [s for s in args.scenes if s not in shipped_scenes()]
    if unknown or not 8 <= args.res <= 4000:  # before minutes of work
        ap.error(f"--scenes {unknown[0]}: not a shipped scene ({', '.join(shipped_scenes())})" if unknown else
                 f"--res {args.res}: must be 8 to 4000 pixels")
    print(f"| scene, {args.res}² | preset | warm time | first render | total | e2 | peak memory |")
    print("|---|---|---|---|---|---|---|")
    for scene in args.scenes:
        for row in run_module("benchmarks.presets_1500", ["--one", scene, "--res", str(args.res)]
                              + (["--passes"] if args.passes else [])):
            print(f"| {row['scene']} | {row['preset']} | {row['warm']:.2f} s | {row['first']:.2f} s | "
                  f"{100 * row['total']:.3f} % | {100 * row['e2']:.2f} % | {row['peak_mb']:.0f} MB |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
