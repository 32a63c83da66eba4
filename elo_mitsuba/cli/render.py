"""``elo-mitsuba render``: detector images of a scene as a multichannel EXR."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from ..errors import EloInputError
from ..files import check_output
from ..constants import BEAM_CURRENT_A, TRANSIMPEDANCE_V_PER_A
from ..options import QUALITIES
from ..scene_files import shipped_scenes
from ._args import add_yes, define, number, positive_int, seed

#: How messages name the settings of this command's flags.
_FLAGS = {"detector_layout": "--layout", "dh": "-D dh", "dw": "-D dw", "layout": "-D layout", "units": "--units",
          "beam_current": "--beam-current", "transimpedance": "--transimpedance",
          "detector_samples": "--detector-samples", "bounce_detector_samples": "--detector-samples",
          "quality": "--quality", "events": "--events"}

HELP = "render the detector images of an XML scene to a multichannel EXR"

DESCRIPTION = """\
Render the electron-optical images of a scene: the gun (sensor elo_beam) scans the field, the
electrons scatter by g_BSE (Eq. 13) on every surface with an elo_bse BSDF, and each detector
(a shape with an area emitter; its id is the channel name) collects what reaches it (Eqs. 4-8).

The EXR holds one float32 channel per detector with the total over the counted events, and with
--events > 1 also each event alone as <id>.e1, <id>.e2, ...; values are N_d/N_0, the fraction of
beam electrons (or volts with --units voltage, Eq. 9). The header stores the scan geometry
(field, resolution, work distance, detector centres/normals/radii, events, spp, materials) so
that 'elo-mitsuba gradient' needs no flags. Image orientation: row 0 is the +y edge, columns run
towards +x (the plate seen from above, +y up). Lengths are millimetres.

Quality (--quality, default "default"; measured in benchmarks/RESULTS.md): draft, default,
reference and unbiased set the spp and how the detectors are integrated: the 1st event by the triangle
quadrature of Appendix A (no noise with a single-ray beam), events >= 2 traced for a fraction of
the pixels and averaged over a window that stops at changes of the surface normal. "scene" keeps
the scene file's settings (independent sampling, 2.4%/sqrt(spp) noise per pixel on the 1st event).
An explicit --spp or --detector-samples wins over the preset. The presets are chosen per scene.
Where few of the 2nd event's electrons meet the relief again (every shipped chamber scene but
corrugated_chamber) they add the far-field control variate of events >= 2 with its mean
tabulated once per geometry, and the window averages only the 2nd event's residual about that
mean (the mean stays per pixel), also on relief at events 1 + 2 (bias on the melt plate 0.2 % of
e2 per pixel). Where relief scatters much onto itself (corrugated_chamber's facing flanks) events
>= 2 are traced per pixel (a window average was biased by +9 % in e2 on flanks) and draft,
default and reference share them between pixels of matching geometry (same normal, same distances along 64
probe rays; under a beam profile also around its footprint) in blocks of 16 mm (12 mm for
reference; 4 mm where the far field makes those events), scaled across a block by each
detector's view factor and a tilt fitted per normal, their paths one point set per class (at
1500^2, default: 0.33 % total from 3 paths per pixel, and a bias of 0.19 % that the render's own
estimate cannot see, where 16 own paths per pixel gave 6.2 %). Measured on every
shipped scene at 128 x 128 (benchmarks/RESULTS.md, section presets; per-pixel RMS error of a
detector's total against a converged reference), each preset's WORST scene:

  preset      worst scene           total    time (128^2)   athene_flat
  draft       corrugated_chamber     3.3 %   0.06 s         0.54 %
  default     corrugated_chamber     2.65 %  0.03 s         0.23 % (0.10 % at 1500^2, own estimate)
  reference   corrugated_chamber     1.0 %   0.20 s         0.22 % (0.05 % at 1500^2, own estimate)
  unbiased    corrugated_chamber     2.0 %   0.41 s         0.51 % (0.47 % at 1500^2, in 27x default's time)

reference is default's averaging with 4x its paths (at 1500^2 half default's noise in 1.5-2x its
time); unbiased averages nothing between pixels (128 paths per pixel of their own): the ground
truth for checking the averages' bias, slow and, at high resolution, noisier than default.

Every render estimates its own error from two independent halves of the samples and prints it
per channel (RMS relative error per pixel; within 0.9-1.03x of the actual error in the benchmarks
for the totals; a single event's figure divides by its own noisy values: on relief with
far_field it overstated e2 up to 3.6x, benchmarks/RESULTS.md, Far field;
it sees noise only, not the quadrature's deterministic error of the 1st event, < 0.05 %);
channels without sampling error (the 1st event by the quadrature with a single-ray beam) say
"deterministic". The estimate is stored in the EXR header (error_estimate) and, with
--error-channels, as <channel>.err images. A render whose estimate is above its preset's worst
figure gets a note.

With a beam profile (fwhm > 0) the presets take more spp (4 / 16 / 256 / 256) to average over it.
"""

EPILOG = """\
examples:
  elo-mitsuba render flat_plate -o flat.exr --preview flat.png
  elo-mitsuba render athene_flat -o chamber.exr --events 2 --spp 64 --resolution 512
  elo-mitsuba render melt_plate -o melt.exr --layout zeta50          # Table 1 layout
  elo-mitsuba render my_scene.xml -o out.exr -D dh=250 -D dw=140 --units voltage
"""


def add_parser(subparsers):
    p = subparsers.add_parser(
        "render", help=HELP, description=DESCRIPTION, epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("scene", metavar="SCENE", help="XML scene file, or a shipped scene name ("
                   + ", ".join(shipped_scenes()) + ")")
    p.add_argument("-o", "--output", required=True, metavar="OUT.exr", help="EXR file to write")
    p.add_argument("--spp", type=positive_int, help="beam samples per pixel (default: the quality preset's, 1 without a beam profile and "
                   "4 / 16 / 256 with one; with --quality scene the scene file's sampler)")
    p.add_argument("--events", type=positive_int, help="scattering events counted: 1 = first event only, 2 adds one bounce off walls or the object, ... (default: the scene's)")
    p.add_argument("--resolution", type=positive_int, metavar="N", help="N x N scan points (sets the scene parameter 'res')")
    p.add_argument("--seed", type=seed, default=0, help="random seed, 0 .. 4294967295 (default 0)")
    p.add_argument("--variant", help="Mitsuba variant: llvm_ad_mono (CPU, default) or cuda_ad_mono (NVIDIA GPU); also $ELO_MITSUBA_VARIANT")
    p.add_argument("-D", dest="defines", action="append", type=define, default=[], metavar="NAME=VALUE", help="set a scene parameter, e.g. -D dh=250 -D dw=140 -D wd=450 -D field=80 -D fwhm=0.27")
    p.add_argument("--layout", metavar="zetaNN", help="detector layout of Table 1: zeta25, zeta50, zeta60, zeta75 (sets dh and dw)")
    p.add_argument("--units", choices=("fraction", "voltage"),
                   help=f"N_d/N_0 (default) or detector voltage U_d = N_d/N_0 * I_b * T (Eq. 9), with the beam current "
                        f"I_b (--beam-current, default {BEAM_CURRENT_A:g} A) and the amplifier transimpedance T "
                        f"(--transimpedance, default {TRANSIMPEDANCE_V_PER_A:g} V/A)")
    p.add_argument("--beam-current", type=number, metavar="A", help="beam current I_b in A for --units voltage")
    p.add_argument("--transimpedance", type=number, metavar="V_PER_A",
                   help="detector amplifier transimpedance T in V/A for --units voltage")
    p.add_argument("--detector-samples", type=positive_int, help="points sampled on each detector per event (default 1); the presets integrate the 1st event by "
                   "the triangle quadrature, so there it sets events >= 2 only")
    p.add_argument("--quality", choices=QUALITIES, default="default",
                   help="speed/accuracy preset (default: default); 'unbiased' averages nothing between pixels (the "
                        "ground truth for bias checks, slow); 'scene' keeps the scene file's sampling settings")
    p.add_argument("--error-channels", action="store_true",
                   help="also write each channel's per-pixel standard error as <channel>.err (from two independent "
                        "halves of the samples; zero for deterministic channels)")
    p.add_argument("--preview", metavar="PNG", help="also write the detector images side by side as a PNG (axes in mm, colour bars)")
    p.add_argument("--overwrite", action="store_true", help="replace OUT.exr (and the preview) if they exist")
    p.add_argument("--quiet", action="store_true", help="no progress or summary output")
    add_yes(p)
    p.set_defaults(run=run)
    return p


def run(args) -> int:
    from ..options import check_combination
    from ..render import NEGLIGIBLE_EVENT_SHARE, NO_SIGNAL_CAUSES, load_scene
    from ..scene_files import scene_values

    out = check_output(args.output, (".exr",), overwrite=args.overwrite)
    preview = check_output(args.preview, (".png",), overwrite=args.overwrite, what="preview") if args.preview else None
    params = {}
    for name, value in args.defines:
        if name in params and params[name] != value:
            raise EloInputError(f"-D {name}={params[name]} and -D {name}={value}: the parameter is given twice with "
                                "different values; give it once")
        params[name] = value
    if "spp" in params and args.quality != "scene":
        raise EloInputError(f"-D spp={params['spp']} sets the scene file's sampler, which --quality {args.quality} "
                            "replaces; give --spp instead (or --quality scene)")
    for name, flag, value in (("spp", "--spp", args.spp), ("events", "--events", args.events)):
        if name in params and value is not None:  # the flag would win and the header record the other
            raise EloInputError(f"{flag} {value} and -D {name}={params[name]} both set {name}; give one")
    if args.resolution is not None:
        if "res" in params:
            raise EloInputError(f"--resolution {args.resolution} and -D res={params['res']} both set the resolution; "
                                "give one")
        params["res"] = args.resolution
    scene_values(args.layout, params, names=_FLAGS)  # a layout and its dh/dw both given, named by their flags
    t0 = time.perf_counter()
    scene = load_scene(args.scene, variant=args.variant, detector_layout=args.layout, **params)
    # the integrator options of the flags, refused where a render would record but not apply them
    # (the one rule of every entry point: options.check_combination)
    given = {"units": args.units} if args.units else {}
    given.update({k: v for k, v in (("beam_current", args.beam_current), ("transimpedance", args.transimpedance))
                  if v is not None})
    if args.detector_samples:  # explicit wins over the preset (which does not set it)
        given.update(detector_samples=args.detector_samples, bounce_detector_samples=args.detector_samples)
    check_combination(given, base=scene.options, qualities=[args.quality],
                      events=args.events if args.events is not None else scene.integrator.events,
                      bounce_possible=scene.integrator.bounce_possible, flags=_FLAGS)
    if given:
        scene.configure(**given)
    result = scene.render(spp=args.spp, seed=args.seed, events=args.events, quality=args.quality,
                          progress=None if not args.quiet else False, force=args.yes)
    if len(result.dark_detectors) == len(result.detectors):
        raise EloInputError(f"{args.scene}: no electron reached any detector anywhere in the scan ({NO_SIGNAL_CAUSES}); "
                            f"nothing written to {out}")
    result.write_exr(out, overwrite=args.overwrite, error_channels=args.error_channels)
    if preview is not None:
        from ..analysis.plots import preview_detectors

        m = result.metadata
        preview_detectors(result.channels, m["field_mm"], preview, unit=m["units"],
                          title=f"{Path(m['scene']).stem}, {m['events']} event(s): ", overwrite=args.overwrite)
    if not args.quiet:
        m = result.metadata
        w, h = m["resolution"]
        print(f"wrote {out}: {w}x{h} px, {m['spp']} spp, events={m['events']}, "
              f"channels {', '.join(result.channels)} ({m['units']}) in {time.perf_counter() - t0:.1f} s",
              file=sys.stderr)
        for note in m.get("notes", []):
            print(f"note: {note}", file=sys.stderr)
        for line in error_lines(result, args.quality):
            print(line, file=sys.stderr)
        shares = result.event_shares()  # what each event order adds
        if shares:
            print("event shares of the signal (mean; 99th-percentile pixel): " + ", ".join(
                f"e{s['event']} {100 * s['mean']:.2f}% ({100 * s['p99']:.2f}%)" for s in shares), file=sys.stderr)
            enough = result.negligible_events(shares=shares)
            if enough is not None:
                print(f"note: events above {enough} add less than {100 * NEGLIGIBLE_EVENT_SHARE:g}% of the signal "
                      f"in 99% of the pixels: --events {enough} gives the same images within that, faster",
                      file=sys.stderr)
    return 0


def error_lines(result, quality: str) -> list[str]:
    """The error estimate of a render as text: one line per detector (its total and each event),
    and a note when the worst total is above what the preset promises (QUALITY_ACCURACY)."""
    from ..error_estimate import ESTIMATED, ROUNDING, describe
    from ..options import QUALITY_ACCURACY

    def say(s: dict) -> str:
        # halves that differ by float32 summation order only: no sampling error to report as "%"
        if s.get("status") == ESTIMATED and s.get("p99_rel", 1.0) < ROUNDING:
            return "deterministic (the halves agree to float32 rounding)"
        return describe(s)

    summary = result.error_summary()
    if not summary:
        return []
    lines = ["estimated error per pixel (two independent halves of the samples; RMS over pixels, relative):"]
    for d in result.detectors:
        parts = [f"{d}: {say(summary[d])}"]
        parts += [f"{name[len(d) + 1:]} {say(summary[name])}" for name in summary if name.startswith(f"{d}.")]
        lines.append("  " + "; ".join(parts))
    totals = [(summary[d]["rms_rel"], d) for d in result.detectors if summary[d].get("status") == ESTIMATED]
    stated = QUALITY_ACCURACY.get(quality)
    if totals and stated is not None and max(totals)[0] > stated:
        worst, d = max(totals)
        lines.append(f"note: the estimated error of {d} ({100 * worst:.3g} % RMS) is above the {100 * stated:.3g} % "
                     f"that --quality {quality} promises (its worst shipped scene): use a higher --quality or --spp")
    return lines
