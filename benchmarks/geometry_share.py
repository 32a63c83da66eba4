"""Events >= 2 shared by the pixels of matching geometry (``bounce_share``, issue 26) on relief that
scatters onto itself, side by side with the per-pixel paths before it, and its bias.

* default: per scene, in its own process, `default` before (per-pixel paths, ``bounce_share`` 0)
  and now (the preset's block), interleaved after a warm-up render each (the first render of
  "now" builds the classes: its time is given apart), two rounds; the faster warm time, the
  render's own error estimate of the total and of each later event (worst detector).
* ``--bias N,M``: at ``--bias-res`` (512), N `default` renders (shared) against M of `reference`
  (per-pixel paths, no sharing, the same events), per detector and event >= 2 the RMS per-pixel
  difference of the two means less the noise of both, relative to the event's mean; the worst
  pixel; the share of pixels beyond 4 standard errors (the per-pixel renders' variance pooled
  over each class: one pixel's own few-sample variance would give Student's tails).

    python -m benchmarks.geometry_share                          # corrugated_chamber 1500², events 2
    python -m benchmarks.geometry_share --bias 8,6               # corrugated_chamber 512² (about 2 min)
    python -m benchmarks.geometry_share --bias 8,6 --scene melt_chamber --events 3 --bias-res 256
    python -m benchmarks.geometry_share --bias 8,6 --bias-res 256 --fwhm 0.27   # under a beam profile
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from elo_mitsuba.schema import event_channel

from .harness import DETS, estimated_rel, mean_difference, run_module

SCENES = ("corrugated_chamber", "melt_chamber")


def side_by_side(name, res, events):
    import elo_mitsuba as em

    em.ensure_variant()
    scene = em.load_scene(name, res=res)
    scene.set_events(events)
    rows, first = {}, None
    for rnd in range(2):
        for label in ("now", "before"):
            spp = scene.set_quality("default")
            block = scene.integrator.options.bounce_share
            if label == "before":
                scene.configure(bounce_share=0.0)
            if rnd == 0:
                t = time.perf_counter()
                scene.render(quality="custom", spp=spp, seed=7, progress=False)
                if label == "now":
                    first = time.perf_counter() - t
            t = time.perf_counter()
            r = scene.render(quality="custom", spp=spp, seed=11 + rnd, progress=False)
            dt = time.perf_counter() - t
            worst = [max(estimated_rel(r, event_channel(d, k) if k else d) for d in DETS) for k in [0] + list(range(2, events + 1))]
            rows.setdefault(label, []).append((dt, worst, block))
    out = {label: {"seconds": min(x[0] for x in v), "errors": np.mean([x[1] for x in v], axis=0).tolist(),
                   "block": v[0][2]} for label, v in rows.items()}
    out["now"]["first_seconds"] = first
    return out


def bias(name, res, events, n_shared, n_per_pixel, fwhm=0.0):
    import elo_mitsuba as em

    em.ensure_variant()
    scene = em.load_scene(name, res=res, fwhm=fwhm)
    scene.set_events(events)
    channels = [event_channel(d, k) for k in range(2, events + 1) for d in DETS]

    def stack(quality, n, seed0):
        spp = scene.set_quality(quality)
        return np.array([np.stack([scene.render(quality="custom", spp=spp, seed=seed0 + k, progress=False)
                                   .channels[c] for c in channels]).astype(np.float64) for k in range(n)])

    f = stack("default", n_shared, 1000)
    block, classes = scene.integrator.options.bounce_share, scene.integrator.geometry_classes()
    g = stack("reference", n_per_pixel, 5000)
    out = {c: mean_difference(f[:, i], g[:, i], classes) for i, c in enumerate(channels)}
    return block, out


def _positive(text):
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: a whole number >= 1")
    return int(text)


def _events(text):
    if not text.isdigit() or not 2 <= int(text) <= 4:
        raise argparse.ArgumentTypeError(f"{text!r}: a whole number in 2 .. 4")
    return int(text)


def _fwhm(text):
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not 0.0 <= value <= 5.0:
        raise argparse.ArgumentTypeError(f"{text!r}: a FWHM in mm, 0 .. 5")
    return value


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m benchmarks.geometry_share", description=__doc__.split("\n\n")[0])
    p.add_argument("--res", type=_positive, default=1500)
    p.add_argument("--scene", choices=SCENES, default="corrugated_chamber")
    p.add_argument("--events", type=_events, default=2)
    p.add_argument("--bias", help="N,M: N shared against M per-pixel `reference` renders")
    p.add_argument("--bias-res", type=_positive, default=512)
    p.add_argument("--fwhm", type=_fwhm, default=0.0, help="with --bias: the beam profile's FWHM (mm)")
    p.add_argument("--one", action="store_true", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.bias:
        parts = a.bias.split(",")
        if len(parts) != 2 or not all(x.strip().isdigit() and int(x) >= 2 for x in parts):
            p.error(f"--bias {a.bias!r}: give N,M, two whole numbers >= 2 (renders of each side)")
        n, m = (int(x) for x in parts)
        block, rows = bias(a.scene, a.bias_res, a.events, n, m, a.fwhm)
        print(f"{a.scene} {a.bias_res}², events {a.events}, fwhm {a.fwhm:g} mm, {n} `default` renders (shared in {block:g} mm blocks) "
              f"against {m} per-pixel `reference` ones:\n")
        print("| channel | bias, RMS per pixel (of the event) | one render's noise | worst pixel | "
              "pixels beyond 4 standard errors |")
        print("|---|---|---|---|---|")
        for c, v in rows.items():
            print(f"| {c} | {100 * v['bias']:.2f} % | {100 * v['noise']:.2f} % | {100 * v['worst']:.1f} % | "
                  f"{100 * v['beyond4']:.2f} % |")
        return 0
    if a.one:
        print("RESULT " + json.dumps(side_by_side(a.scene, a.res, a.events)))
        return 0
    r = run_module("benchmarks.geometry_share", ["--one", "--scene", a.scene, "--res", str(a.res),
                                                 "--events", str(a.events)])
    names = ["total"] + [f"e{k}" for k in range(2, a.events + 1)]
    print(f"{a.scene} {a.res}², `default`, events 1 .. {a.events}, per-pixel paths before and shared in "
          f"{r['now']['block']:g} mm blocks now; the faster of two warm renders, the render's own error "
          "estimate (worst detector):\n")
    print("| | warm time | " + " | ".join(names) + " |")
    print("|---|---|" + "---|" * len(names))
    for label in ("before", "now"):
        cells = " | ".join(f"{100 * e:.2f} %" for e in r[label]["errors"])
        print(f"| {label} | {r[label]['seconds']:.2f} s | {cells} |")
    print(f"\nThe first render of \"now\" (the classes built): {r['now']['first_seconds']:.2f} s.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
