"""``elo-mitsuba invert``: four detector images -> the height map the forward model maps onto them."""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from ..arguments import fraction
from ..errors import EloInputError
from ..budget import check_inversion
from ..schema import BEAM_FWHM, scattering_note
from ._args import (add_scan_arguments, add_yes, fwhm_arg, model_inputs, noise_level, positive_float,
                    read_checked_scan, scan_files)

DESCRIPTION = """\
Solve for the height map itself: the heights whose modelled images (the renderer's 1st event with
g_BSE of Eq. 13 on the real disc detectors, the surface's own shadowing, the beam profile, and
optionally fixed later events) reproduce the four STSA-corrected images best. Starts from the
model gradient integrated (or --init), then Gauss-Newton on every height at once, so the four
images must come from one surface; a robust (Huber) misfit and a small curvature regulariser
(weight --alpha, default 30 x the noise variance). A step is kept only if it lowers the
objective (misfit and regulariser): the result's objective never exceeds its start's, though its
misfit can rise where a large --alpha flattens the relief. A start that already reproduces the
images to within their noise is kept (--discrepancy: the steps would fit the noise); otherwise it
stops when a step gains < --tol, after --iterations steps or after --time-budget seconds.
Then, region by region: where the misfit averaged over 7x7 pixels exceeds what noise reaches, the
region is re-inverted on its own (its edge held), and kept only if it fits better than both the
field's solve and the start (a pore or a bump on a layer that fits to the noise as a whole;
--no-local skips it). Where it holds a pit or peak far more curved than the relief around it, it
is solved once more on 2x2 sub-pixel facets with a robust curvature penalty there, kept where that
reproduces those pixels' images to within their noise and fits more than noise alone would
('refined (robust curvature)'): the quadratic one flattens a pore of 2-3 pixels to a third of its
depth (rough layer of row D1, 400^2: within 1 mm of the defects 11.9 -> 5.8 um, 9.5 um without
it; with sixteen recordings averaged, 0.25 % noise, 11.3 -> 4.1 um). Slopes recover only 12-62 % of a cliff of 0.1-1 mm (0.2 mm pixels): each
part a cliff cuts off (floating) is then lifted as a whole to the step its shadow shows (on the
stepped layer of row D2 the 0.1-1 mm steps within 0.5-9 %, each with its uncertainty; the summary
lists them; a small cliff whose misfit does not close round its part is found by the ramp the
solve left); a part whose shadow says no more keeps its step, and its error bar holds the offset;
a part behind a band that is no cliff (a melt square's rim on low-noise images) is not searched,
and its error bar holds the band's. Last, where the start's own misfit was at the noise, only the
long wavelengths of the correction are kept (there its finest ones are the noise the deconvolution
of the beam amplifies), and elsewhere its band finer than the beam only where the images demand
it (where the correction as the beam sees it leaves a misfit above the noise): on the melt plate
recorded sixteen times, 0.77 -> 0.63 -> 0.59 of the start's error, the squares' walls 1.73 -> 1.54
um.

Where it wins (validation/REPORT.md, rows I1-I5; 0.27 mm beam blur, 1 % noise): steep relief,
masked and shadowed pixels (a per-pixel fit must drop them; here the model predicts them): height
error 41 -> 4.9 um on hills with slopes to 1.26, 541 -> 82 um with a third of them shadowed. On a
nearly flat, noisy surface (the melt plate) the noise, not the model, limits the height: the
integrated model gradient (3.9 um) already fits the images to their noise and is returned as it is.
How much of the height the noise leaves uncertain is written with it (height_error, below; on the
melt plate 4.3 um RMS, and half of it is the flat's noise: repeat --flat with several recordings
of the flat plate and their mean is used; four take the start from 3.9 to 2.9 um, more than any
solver gains).

Output: .exr with channels height (mm, where each pixel's beam lands; row 0 = +y edge, columns
towards +x), mask (1 = untrusted: misfit above 4 noise levels), misfit (RMS over the detectors,
corrected units), start_height, scale (per-pixel material/current factor) and model.<detector>
(the modelled corrected images), height_error (mm: the standard error of each height, relative to
the mean: the images' noise propagated through the solution from --uncertainty-probes draws, the
channel height_error_noise, scaled up by the local Birge ratio where the misfit exceeds the noise,
with the regulariser's bias, the model's slope gain (channel height_error_model: in proportion to
the height above or below the mean, as the model and the renderer disagree on a facet's slope) and
a floating part's offset in quadrature; measured coverage in
validation/REPORT.md, rows D1-D4), floating (1 = a part cut off by bands of misfit or by a small
cliff's ramp, e.g. a raised part's cliff: no trusted pixel ties its offset to the field's;
height_error holds the whole step, the step its shadows show, or, where the band is no cliff,
the band's own error); the geometry, the solver's
history, the local refinement's regions and height_error_rms_mm in the header, with the object's
and the flat's own relative noise (noise_object, noise_flat; the summary line says the flat's
share). .npy/.tif: the height alone, NaN where the mask says untrusted.
"""

EPILOG = """\
examples:
  elo-mitsuba invert --flat flat.exr melt.exr -o height.exr --preview height.png
  elo-mitsuba invert --flat flat.exr melt.exr -o height.exr --init grad.exr --iterations 20
  elo-mitsuba invert --flat flat.exr melt.exr -o height.exr --calibration CALIB.json
  elo-mitsuba invert --flat flat1.exr --flat flat2.exr --flat flat3.exr melt.exr -o height.exr  # mean flat
  elo-mitsuba invert --flat flat.exr obj.exr -o height.exr --second-event sim_flat.exr   # chamber
"""


def add_parser(subparsers):
    p = subparsers.add_parser(
        "invert", help="four detector images -> height map by inverting the forward model",
        description=DESCRIPTION, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_scan_arguments(p)
    p.add_argument("-o", "--output", required=True, metavar="HEIGHT.(exr|npy|tif)", help="height map to write")
    sol = p.add_argument_group("solver")
    sol.add_argument("--init", metavar="GRAD.exr|HEIGHT.(exr|npy)",
                     help="start: a gradient EXR ('elo-mitsuba gradient') to integrate, or heights (mm, scan grid); "
                          "default: the model gradient of the same images")
    sol.add_argument("--iterations", type=int, default=None, metavar="N",
                     help="Gauss-Newton steps at most, per scale (default 10)")
    sol.add_argument("--scales", type=int, default=None, metavar="K",
                     help="when full resolution alone does not fit the images to their noise, solve coarse to "
                          "fine over K scales (each half the resolution; default 4, 1 = full resolution only)")
    sol.add_argument("--tol", type=float, default=None, metavar="F",
                     help="stop when a step lowers the objective by less than this fraction (default 5e-3)")
    sol.add_argument("--discrepancy", type=float, default=None, metavar="F",
                     help="keep the start when its misfit RMS is <= F x the noise x sqrt(3/4), what the true "
                          "surface would leave (Morozov's discrepancy principle; default 1.05, 0 = off)")
    sol.add_argument("--time-budget", type=positive_float, default=None, metavar="S",
                     help="stop after the step that passes S seconds")
    sol.add_argument("--alpha", type=float, default=None, metavar="A",
                     help="weight of the curvature regulariser, 0 to 1e6 (default 30 x noise^2)")
    sol.add_argument("--noise", type=noise_level, default=None, metavar="SIGMA",
                     help="noise (std) of the corrected images, 1e-9 to 1 (e.g. 0.01); default: estimated from the images")
    sol.add_argument("--fwhm", type=fwhm_arg, default=None, metavar="MM",
                     help="beam profile FWHM in mm (default: the header's beam_fwhm_mm, else 0)")
    sol.add_argument("--uncertainty-probes", type=int, default=None, metavar="N",
                     help="noise draws propagated through the solution for the height_error channel (the "
                          "standard error the images' noise leaves in each height; each costs about one step; "
                          "default 8, 0 = skip)")
    sol.add_argument("--no-shadows", action="store_true", help="leave the surface's shadowing out of the model")
    sol.add_argument("--no-local", action="store_true",
                     help="skip the local refinement (regions whose misfit exceeds the noise are re-inverted on "
                          "their own after the field's solve; parts cut off by a cliff get the step their shadows "
                          "show; each is reported) and keep the field's correction whole, its finest band too")
    sol.add_argument("--second-event", metavar="SIM_FLAT.exr",
                     help="a render of the flat plate in the chamber with --events >= 2: its later events are held "
                          "fixed in the model of the flat (and of the object, unless --chamber-later); written "
                          "with --error-channels, their Monte Carlo error counts in --discrepancy")
    sol.add_argument("--chamber-later", action="store_true",
                     help="with --second-event: render the start surface in the ATHENE-like chamber (--quality "
                          "reference, events 2) and hold the object's own later events fixed; halves the height "
                          "error on the melt plate in the chamber (validation row I5), costs one render")
    p.add_argument("--preview", metavar="PNG", help="also write a PNG of the height map")
    p.add_argument("--overwrite", action="store_true", help="replace existing output files")
    p.add_argument("--quiet", action="store_true", help="no progress (the steps) on stderr; the summary still prints")
    add_yes(p)
    p.set_defaults(run=run, event=None, min_corrected=None, min_sum=None)
    return p


def floating_line(res) -> str:
    """The summary's line on the floating parts of an inversion result (``floating`` set).

    Examples
    --------
    >>> from types import SimpleNamespace
    >>> part = SimpleNamespace(status="not searched (no cliff: a clean step fits 17x worse than the solve)")
    >>> res = SimpleNamespace(floating=np.array([True, False]), steps=[part], height_error=np.ones(2))
    >>> floating_line(res).endswith("1 of them behind bands that are no cliff (relief the heights describe), "
    ...                             "whose offset carries the band's own error")
    True
    >>> line = floating_line(SimpleNamespace(floating=np.array([True]), steps=[part], height_error=None))
    >>> "no height_error without --uncertainty-probes" in line, "band's own error" in line
    (True, False)
    """
    rims = sum(p.status.startswith("not searched (no cliff") for p in res.steps)
    held = res.height_error is not None
    return (f"{100 * res.floating.mean():.2f} % of the field floats: parts cut off by cliffs (bands of misfit "
            "or steep ramps), their offset not measured (channel floating"
            + ("; height_error holds it)" if held else "; no height_error without --uncertainty-probes)")
            + (f"; {rims} of them behind bands that are no cliff (relief the heights describe), whose offset "
               "carries the band's own error" if rims and held else ""))


def run(args) -> int:
    from ..files import check_output

    from ..heightmap import HEIGHT_SUFFIXES

    read = [*scan_files(args), args.init, args.second_event]
    out = check_output(args.output, HEIGHT_SUFFIXES, overwrite=args.overwrite, inputs=read)
    if args.preview:
        check_output(args.preview, (".png",), overwrite=args.overwrite, what="preview", inputs=read)
    if args.iterations is not None and args.iterations < 0:
        raise EloInputError(f"--iterations {args.iterations}: must be >= 0")
    if args.uncertainty_probes is not None and args.uncertainty_probes < 0:
        raise EloInputError(f"--uncertainty-probes {args.uncertainty_probes}: must be >= 0")
    if args.scales is not None and args.scales < 1:
        raise EloInputError(f"--scales {args.scales}: must be >= 1")
    if args.tol is not None:  # a share of the objective: 2 stopped after the first step whatever it gained
        fraction("--tol", args.tol)
    for flag in ("alpha", "discrepancy"):
        v = getattr(args, flag)
        if v is not None and not (np.isfinite(v) and v >= 0):
            raise EloInputError(f"--{flag} {v}: must be a finite number >= 0")
    from ..analysis.height_solver import MAX_ALPHA

    if args.alpha is not None and args.alpha > MAX_ALPHA:
        raise EloInputError(f"--alpha {args.alpha:g}: must be at most {MAX_ALPHA:g} (default 30 x noise^2, at most 30; "
                            "a larger weight flattens any relief)")
    if args.no_flat:
        raise EloInputError("--no-flat: the inversion needs the flat-plate images (their ratio cancels the gains)")

    from ..analysis import chain, height_solver as solver
    from ..analysis.io import check_field, write_inversion

    scan = read_checked_scan(args, model_discs=True)
    if args.init and str(args.init).lower().endswith(".exr"):  # a start of another scan field fitted nothing
        from ..exr import read_exr

        check_field(scan.geo["field_mm"], read_exr(args.init)[1], scan.shape, f"--init {args.init}",
                    given="the images' field", fix="start from a gradient or heights of the images' scan")
    if args.scales is not None:  # more than the image can be halved into was cut without a word
        usable = len(solver.scale_factors(scan.shape, args.scales)) + 1
        if usable < args.scales:
            raise EloInputError(f"--scales {args.scales}: a {scan.shape[1]}x{scan.shape[0]} image allows at most "
                                f"{usable} (each scale halves both sides, down to {solver.MIN_SCALE_PX} px on the "
                                "shorter one)")
    if scattering_note(scan.header, scan.source):  # images of another g_BSE than the models' (a lobe study)
        print(f"note: {scattering_note(scan.header, scan.source)}", file=sys.stderr)
    for line in check_inversion(scan.shape, solver.ITERATIONS if args.iterations is None else args.iterations,
                                solver.SCALES if args.scales is None else args.scales,
                                solver.UNCERTAINTY_PROBES if args.uncertainty_probes is None
                                else args.uncertainty_probes, force=args.yes):  # before the model gradient
        print(f"note: {line}", file=sys.stderr)
    geometry = chain.model_geometry(scan, **model_inputs(args))
    fwhm = scan.beam_fwhm(args.fwhm)
    start = chain.read_start(args.init, scan.shape, geometry.field_mm) if args.init else None
    if args.fwhm is None and BEAM_FWHM not in (scan.header or {}):
        print(f"note: {scan.source} gives no beam profile (beam_fwhm_mm) and --fwhm is not set: the model's beam is "
              "a single ray; pass --fwhm MM, the beam's FWHM on the plate, if it is wider than a pixel",
              file=sys.stderr)
    if args.chamber_later and not args.second_event:
        raise EloInputError("--chamber-later needs --second-event SIM_FLAT.exr (the flat plate's later events)")
    t0 = time.perf_counter()

    def progress(step):
        if args.quiet:
            return
        at = f"scale 1/{step['scale']} " if step.get("scale", 1) > 1 else ""
        print(f"  {at}step {step['iteration']:2d}: objective {step['objective']:.6g}, misfit rms {step['rms']:.4g}, "
              f"{step['seconds']:.1f} s", file=sys.stderr, flush=True)

    res = chain.invert(
        scan, geometry, fwhm_mm=fwhm, start=start, second_event=args.second_event, chamber_later=args.chamber_later,
        notify=(lambda line: None) if args.quiet else (lambda line: print(line, file=sys.stderr, flush=True)),
        alpha=args.alpha,
        scales=solver.SCALES if args.scales is None else args.scales, noise=args.noise, shadows=not args.no_shadows,
        iterations=solver.ITERATIONS if args.iterations is None else args.iterations,
        tol=solver.TOL if args.tol is None else args.tol,
        discrepancy=solver.DISCREPANCY if args.discrepancy is None else args.discrepancy,
        time_budget_s=args.time_budget, progress=progress, force=args.yes, local=not args.no_local,
        uncertainty_probes=solver.UNCERTAINTY_PROBES if args.uncertainty_probes is None else args.uncertainty_probes)
    shares, noise_line = scan.noise_shares()
    meta = {"method": "inversion", BEAM_FWHM: fwhm, "noise": res.noise, "alpha": res.alpha,
            "stopped": res.stopped, "history": res.history, "shadows": not args.no_shadows,
            "grid": "scan grid: pixel (i, j) holds the height where its beam lands",
            "sources": {"object": scan.object_files,
                        "flat": scan.flat_provenance(),
                        "init": args.init, "second_event": args.second_event},
            "object_later_events": ("rendered from the start surface in the chamber" if args.chamber_later
                                    else "the flat plate's" if args.second_event else "none"),
            "calibration": args.calibration, **shares}
    if res.sampling is not None:
        meta["sampling"] = res.sampling
    if res.bowl is not None:
        meta["bowl"] = res.bowl
    write_inversion(out, res, geometry, untrusted=res.mask, metadata=meta, overwrite=args.overwrite)
    h = res.height
    print(f"wrote {out}: {scan.shape[1]}x{scan.shape[0]} px, {len(res.history) - 1} steps ({res.stopped}) in "
          f"{time.perf_counter() - t0:.1f} s; misfit rms {res.history[0]['rms']:.4g} -> {res.history[-1]['rms']:.4g} "
          f"(noise {res.noise:.3g}); height range {h.max() - h.min():.4g} mm; "
          f"{100 * res.mask.mean():.2f} % untrusted (misfit > {solver.MISFIT_SIGMAS:g} noise levels)"
          + scan.flat_note())
    if noise_line:
        print(noise_line)
    if res.regions:
        counts = {}
        for r in res.regions:
            key = "cannot fit" if "cannot fit" in r.status else r.status
            counts[key] = counts.get(key, 0) + 1
        print(f"{len(res.regions)} region(s) whose misfit exceeds the noise: "
              + ", ".join(f"{v} {k}" for k, v in counts.items()) + " (header: regions)")
    if res.steps:
        lifted = [p for p in res.steps if p.status == "lifted"]
        print(f"{len(res.steps)} floating part(s) searched for the step their shadows show, {len(lifted)} lifted"
              + "".join(f"; {p.step_before:+.3f} -> {p.step_after:+.3f} ± {p.error:.3f} mm ({p.wall} wall) at rows "
                        f"{p.rows[0]}-{p.rows[1]}, "
                        f"cols {p.cols[0]}-{p.cols[1]}" for p in lifted) + " (header: steps)")
    if res.floating is not None and res.floating.any():
        print(floating_line(res))
    if res.height_error is not None:
        noise_rms = float(np.sqrt(np.mean(res.height_error_noise ** 2)))
        print(f"height error: {1000 * res.height_error_rms:.3g} um RMS, of which the noise alone {1000 * noise_rms:.3g} "
              f"({1000 * float(res.height_error.max()):.3g} um at most; channels height_error, height_error_noise)")
    if res.sampling is not None and res.sampling["warning"]:
        print(f"elo-mitsuba: warning: the start's {res.sampling['warning']}; with a single-ray beam the images leave "
              "open what the slopes do; height_error holds this figure; smaller pixels help", file=sys.stderr)
    if res.bowl is not None:
        print(f"elo-mitsuba: warning: {res.bowl['warning']}", file=sys.stderr)
    if args.preview:
        from ..analysis.plots import preview_height

        flags = [said["flag"] for said in (res.sampling, res.bowl) if said is not None and said.get("warning")]
        preview_height(h, geometry.field_mm, args.preview, mask=res.mask if res.mask.any() else None,
                       title="Height map (inversion)", overwrite=args.overwrite,
                       warning="; ".join(flags) or None)
        print(f"wrote {args.preview}")
    return 0
