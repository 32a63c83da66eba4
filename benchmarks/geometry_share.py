"""Events >= 2 shared by the pixels of matching geometry (``bounce_share``, issue 26) on relief that
scatters onto itself, side by side with the per-pixel paths before it, and its bias.

* default: per scene, in its own process, `default` before (per-pixel paths, ``bounce_share`` 0)
  and now (the preset's block), interleaved after a warm-up render each (the first render of
  "now" builds the classes: its time is given apart), two rounds; the faster warm time, the
  render's own error estimate of the total and of each later event (worst detector).
* ``--bias N,M``: at ``--bias-res`` (512), N `default` renders (``--preset``: or `draft`,
  `reference`; shared) against M of `unbiased` (per-pixel paths, no sharing, the same events),
  per detector and event >= 2 the RMS per-pixel
  difference of the two means less the noise of both, relative to the event's mean; the worst
  pixel; the share of pixels beyond 4 standard errors (the per-pixel renders' variance pooled
  over each class: one pixel's own few-sample variance would give Student's tails).

    python -m benchmarks.geometry_share                          # corrugated_chamber 1500², events 2
    python -m benchmarks.geometry_share --bias 8,6               # corrugated_chamber 512² (about 2 min)
    python -m benchmarks.geometry_share --bias 8,6 --scene melt_chamber --events 3 --bias-res 256
    python -m benchmarks.geometry_share --bias 8,6 --bias-res 256 --fwhm 0.27   # under a beam profile
    python -m benchmarks.geometry_share --bias 8,6 --preset reference        # reference's bias

* ``--classes N``: how far the classes themselves are from "same expected value", apart from the
  estimator's noise: N per-pixel renders (`default`'s paths, no sharing), each shared in its
  classes as the shared render would be (each pixel's view factor times its class's ratio), for
  each probe count of ``--probes``: the RMS per pixel of (shared - own value)'s expectation (from
  two independent halves of the renders, so the noise drops out; of the mean e2 and of the mean
  total), and in 5 mm block means (classes straddle them) the RMS bias (the noise of
  the mean taken out) against one render's noise there, with mean z² over the blocks.
  ``--scene sawtooth`` is the sawtooth test plate (:mod:`elo_mitsuba.objects.sawtooth_plate`, no
  chamber): valleys ending at cliffs.

    python -m benchmarks.geometry_share --classes 144 --scene sawtooth --bias-res 256 --probes 16,32,64,128
    python -m benchmarks.geometry_share --classes 64 --scene sawtooth --bias-res 256 --fwhm 0.27 --probes 16/16,64/16,64/64
    python -m benchmarks.geometry_share --classes 8 --bias-res 1500 --probes 64      # corrugated_chamber (2 min)

* ``--paths KxS[/D],...``: what `default`'s path count buys (shared, one process): for each K
  continuation paths per sample, S samples per pixel and D detector points per later event
  (``bounce_detector_samples``, default 1) the faster of two warm renders and the render's own
  error estimate, after the classes' sizes and the gain an allocation of paths by class size
  could give at most, (mean of sqrt(size))^2 / mean size (Cauchy-Schwarz: 1 means none).

    python -m benchmarks.geometry_share --paths 8x2,6x2,5x2,8x1             # corrugated_chamber 1500²
    python -m benchmarks.geometry_share --paths 8x1,8x1/2,8x1/4 --res 512
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from elo_mitsuba.schema import event_channel

from .harness import DETS, estimated_rel, mean_difference, run_module

SCENES = ("corrugated_chamber", "melt_chamber", "sawtooth")
#: Side of the blocks whose means --classes compares (mm): not a multiple of the classes' 4 mm.
BLOCK_MEAN_MM = 5.0


def _load(name, res, fwhm=0.0):
    """A shipped scene, or the sawtooth test plate written into a temporary folder."""
    import elo_mitsuba as em

    em.ensure_variant()
    if name != "sawtooth":
        return em.load_scene(name, res=res, fwhm=fwhm)
    import tempfile
    from pathlib import Path

    from elo_mitsuba.objects import sawtooth_plate
    from elo_mitsuba.scene_files import write_object_scene

    folder = Path(tempfile.mkdtemp(prefix="elo_saw_"))
    return em.load_scene(str(write_object_scene(folder, "sawtooth", sawtooth_plate.sawtooth_mesh())), res=res, fwhm=fwhm)


def _worst_errors(result, events):
    """The render's own error estimate of the total and of each event >= 2, worst detector."""
    return [max(estimated_rel(result, event_channel(d, k) if k else d) for d in DETS) for k in [0] + list(range(2, events + 1))]


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
            worst = _worst_errors(r, events)
            rows.setdefault(label, []).append((dt, worst, block))
    out = {label: {"seconds": min(x[0] for x in v), "errors": np.mean([x[1] for x in v], axis=0).tolist(),
                   "block": v[0][2]} for label, v in rows.items()}
    out["now"]["first_seconds"] = first
    return out


def bias(name, res, events, n_shared, n_per_pixel, fwhm=0.0, preset="default"):
    scene = _load(name, res, fwhm)
    scene.set_events(events)
    channels = [event_channel(d, k) for k in range(2, events + 1) for d in DETS]

    def stack(quality, n, seed0):
        spp = scene.set_quality(quality)
        return np.array([np.stack([scene.render(quality="custom", spp=spp, seed=seed0 + k, progress=False)
                                   .channels[c] for c in channels]).astype(np.float64) for k in range(n)])

    f = stack(preset, n_shared, 1000)
    block, classes = scene.integrator.options.bounce_share, scene.integrator.geometry_classes()
    g = stack("unbiased", n_per_pixel, 5000)
    out = {c: mean_difference(f[:, i], g[:, i], classes) for i, c in enumerate(channels)}
    return block, out


def class_bias(name, res, n, probes, fwhm=0.0):
    """--classes: per probe count, the bias of sharing each pixel's e2 in its class (its view factor
    times the class's ratio, as the integrator does)."""
    import elo_mitsuba.plugins._geometry_classes as gc
    from elo_mitsuba.plugins._shapes import bbox_centre

    scene = _load(name, res, fwhm)
    scene.set_events(2)
    spp = scene.set_quality("default")
    block = scene.integrator.options.bounce_share
    scene.configure(bounce_share=0.0)
    channels = [event_channel(d, 2) for d in DETS]
    own, totals = [], np.zeros(len(DETS))
    for k in range(n):
        r = scene.render(quality="custom", spp=spp, seed=9000 + k, progress=False)
        own.append(np.stack([r.channels[c] for c in channels]).astype(np.float64))
        totals += [float(np.mean(r.channels[d], dtype=np.float64)) / n for d in DETS]
    own = np.array(own)
    centres = dict(scene.integrator.detectors)
    b = max(1, int(round(BLOCK_MEAN_MM * own.shape[-1] / float(scene.sensor.field))))
    nb = own.shape[-1] // b

    def block_means(x):
        return x[..., :nb * b, :nb * b].reshape(x.shape[:-2] + (nb, b, nb, b)).mean(axis=(-1, -3))

    rows, kept = [], (gc.PROBES, gc.FOOTPRINT_PROBES)
    try:
        for count, footprint in probes:
            gc.PROBES, gc.FOOTPRINT_PROBES = count, footprint or kept[1]
            classes = gc.GeometryClasses(scene.scene, scene.sensor, block, None)
            views = classes.view_factors([bbox_centre(centres[d]) for d in DETS])
            shared = np.empty_like(own)
            for k in range(n):  # as the integrator shares: each detector's view factor times the class's ratio
                for d in range(len(DETS)):
                    plane = own[k, d].astype(np.float32)
                    classes.share(plane, views[d])
                    shared[k, d] = plane
            dev = shared - own
            half = n // 2
            pixel = np.mean(dev[:half].mean(0) * dev[half:2 * half].mean(0), axis=(-1, -2))  # E[bias^2] per channel
            scale = own.mean(axis=(0, 2, 3))
            d = block_means(dev)
            mean, se = d.mean(0), d.std(0, ddof=1) / np.sqrt(n)
            one = block_means(own).std(0, ddof=1)
            squared = np.maximum(0.0, np.mean(mean**2 - se**2, axis=(-1, -2)))  # the noise of the mean taken out
            rows.append({"probes": f"{count}/{gc.FOOTPRINT_PROBES}" if fwhm > 0 else str(count), "classes": int(classes.counts.size),
                         "pixel": float(np.max(np.sign(pixel) * np.sqrt(np.abs(pixel)) / scale)),
                         "pixel_total": float(np.max(np.sign(pixel) * np.sqrt(np.abs(pixel)) / totals)),
                         "block": float(np.max(np.sqrt(squared) / scale)),
                         "ratio": float(np.max(np.sqrt(squared / np.mean(one**2, axis=(-1, -2))))),
                         "z2": float(np.max(np.mean((mean / np.maximum(se, 1e-300))**2, axis=(-1, -2))))})
    finally:
        gc.PROBES, gc.FOOTPRINT_PROBES = kept
    return block, b, rows


def path_trade(name, res, events, configs):
    """--paths: per (K, S, D) the faster of two warm renders, worst detector's total and later events."""
    scene = _load(name, res)
    scene.set_events(events)
    spp = scene.set_quality("default")
    scene.render(quality="custom", spp=spp, seed=3, progress=False)  # the classes and kernels
    counts = scene.integrator.geometry_classes().counts
    sizes = {"classes": int(counts.size), "pixels_per_class": float(counts.sum() / counts.size),
             "small": float(counts[counts <= 50].sum() / counts.sum()),
             "gain": float(np.sqrt(counts).sum() ** 2 / (counts.size * counts.sum()))}
    rows = []
    for k, s, d in configs:
        scene.configure(bounce_samples=k, bounce_detector_samples=d)
        best = np.inf
        for rnd in range(2):
            t = time.perf_counter()
            r = scene.render(quality="custom", spp=s, seed=11 + rnd, progress=False)
            best = min(best, time.perf_counter() - t)
        worst = _worst_errors(r, events)
        rows.append({"k": k, "spp": s, "d": d, "seconds": best, "errors": worst})
    return sizes, rows


def _paths(text):
    out = []
    for item in text.split(","):
        head, _, d = item.partition("/")
        k, _, s = head.partition("x")
        if not (k.isdigit() and s.isdigit() and (d.isdigit() or not d)) or min(int(k), int(s), int(d or 1)) < 1 \
                or int(k) > 16 or int(s) & (int(s) - 1) or int(d or 1) > 16:
            raise argparse.ArgumentTypeError(f"{item!r}: give KxS or KxS/D, K paths per sample (1 .. 16), S samples per "
                                             "pixel (a power of two), D detector points per later event (1 .. 16)")
        out.append((int(k), int(s), int(d or 1)))
    return out


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
    p.add_argument("--bias", help="N,M: N shared against M per-pixel `unbiased` renders")
    p.add_argument("--bias-res", type=_positive, default=512)
    p.add_argument("--fwhm", type=_fwhm, default=0.0, help="with --bias: the beam profile's FWHM (mm)")
    p.add_argument("--preset", choices=("draft", "default", "reference"), default="default",
                   help="with --bias: the shared preset measured (default: default)")
    p.add_argument("--classes", type=_positive, help="N: the classes' own bias from N per-pixel renders")
    p.add_argument("--probes", default="16,64", help="with --classes: probe counts to compare (powers of two; "
                   "C/F under a beam profile: C at the grid point, F at each footprint point)")
    p.add_argument("--paths", type=_paths, help="KxS[/D],...: `default` with K paths per sample, S spp (D detector "
                   "points per later event) side by side")
    p.add_argument("--one", action="store_true", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    chosen = [f"--{n}" for n in ("paths", "classes", "bias") if getattr(a, n)]
    if len(chosen) > 1:
        p.error(f"{' and '.join(chosen)}: give one of --paths, --classes, --bias (each is its own measurement)")
    if a.preset != "default" and not a.bias:
        p.error(f"--preset {a.preset} applies to --bias only")
    if a.paths:
        sizes, rows = path_trade(a.scene, a.res, a.events, a.paths)
        print(f"{a.scene} {a.res}², events {a.events}, `default` shared ({sizes['classes']} classes, "
              f"{sizes['pixels_per_class']:.1f} pixels each on average, {100 * sizes['small']:.2f} % of the pixels in "
              f"classes of <= 50; allocating paths by class size could gain at most a factor {sizes['gain']:.3f} in "
              "variance); the faster of two warm renders, the render's own estimate (worst detector):\n")
        names = ["total"] + [f"e{k}" for k in range(2, a.events + 1)]
        print("| paths per pixel (K x S) | detector points per later event | warm time | " + " | ".join(names) + " |")
        print("|---|---|---|" + "---|" * len(names))
        for r in rows:
            cells = " | ".join(f"{100 * e:.3f} %" for e in r["errors"])
            print(f"| {r['k'] * r['spp']} ({r['k']} x {r['spp']}) | {r['d']} | {r['seconds']:.2f} s | {cells} |")
        return 0
    if a.classes:
        try:
            probes = [tuple(int(y) for y in (x.split("/") + ["0"])[:2]) for x in a.probes.split(",")]
        except ValueError:
            probes = []
        if not probes or any(x < 1 or x & (x - 1) or y < 0 or y & (y - 1) or max(x, y) > 1024 for x, y in probes):
            p.error(f"--probes {a.probes!r}: give powers of two up to 1024, e.g. 16,64 (under a beam profile C/F: "
                    "C at the grid point, F at each footprint point)")
        if a.classes < 4:
            p.error(f"--classes {a.classes}: give N >= 4 renders (two halves estimate the bias)")
        block, b, rows = class_bias(a.scene, a.bias_res, a.classes, probes, a.fwhm)
        print(f"{a.scene} {a.bias_res}², e2, fwhm {a.fwhm:g} mm, {a.classes} per-pixel `default` renders each shared in "
              f"its classes ({block:g} mm blocks, view factors); worst detector:\n")
        print(f"| probes | classes | bias per pixel (of mean e2) | the same, of the mean total | bias in {BLOCK_MEAN_MM:g} mm "
              "means (of mean e2) | the same, of one render's noise there | mean z² over the blocks |")
        print("|---|---|---|---|---|---|---|")
        for r in rows:
            print(f"| {r['probes']} | {r['classes']} | {100 * r['pixel']:.2f} % | {100 * r['pixel_total']:.3f} % | {100 * r['block']:.2f} % | "
                  f"{r['ratio']:.2f} | {r['z2']:.1f} |")
        return 0
    if a.bias:
        parts = a.bias.split(",")
        if len(parts) != 2 or not all(x.strip().isdigit() and int(x) >= 2 for x in parts):
            p.error(f"--bias {a.bias!r}: give N,M, two whole numbers >= 2 (renders of each side)")
        n, m = (int(x) for x in parts)
        block, rows = bias(a.scene, a.bias_res, a.events, n, m, a.fwhm, a.preset)
        print(f"{a.scene} {a.bias_res}², events {a.events}, fwhm {a.fwhm:g} mm, {n} `{a.preset}` renders (shared in {block:g} mm blocks) "
              f"against {m} per-pixel `unbiased` ones:\n")
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
