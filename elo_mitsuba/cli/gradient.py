"""``elo-mitsuba gradient``: four detector images -> surface gradient (model fit or Eq. 26) + mask."""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..constants import DETECTOR_NAMES
from ..errors import EloInputError

DESCRIPTION = """\
Compute the surface gradient dZ/dx, dZ/dy of the build surface from four detector images
(right +x, left -x, back +y, front -y):

  1. STSA correction (Renner et al. 2023, Sec. 2.1.4):  R^C = R / R_flat, ... (flat = plane plate)
  2. --method model (default): per pixel, the facet normal whose modelled corrected images (1st
     event, full g_BSE of Eq. 13, the real disc detectors, that pixel's beam direction) match the
     four measured ones best (least squares; 4 values, slope p, q and a common scale). Exact for
     the 1st event of a facet; Eq. 26 is biased by the specular lobe (tens of % on slopes of
     0.6, measured in validation/REPORT.md). Adds channels residual (RMS misfit, corrected units),
     dzdx_sigma, dzdy_sigma (one-sigma uncertainty from the noise level and the Jacobian) and
     scale; pixels the model cannot explain (shadowing, strong later events, mixed facets) are
     masked (mask_reason bit 32).
     --method eq26: the paper's closed form, M_x = (R^C - L^C)/(R^C + L^C) (Eq. 15) and
     -dZ/dx = M_x d_h / (d_w + x M_x + y M_y), -dZ/dy = M_y d_h / (d_w + x M_x + y M_y) (Eq. 26),
     exact for point detectors and Lambert's law.

Geometry (field, d_h, d_w) comes from the EXR headers written by 'elo-mitsuba render'
(d_h = detector centre z, d_w = centre distance from the z-axis; the four must agree); --field,
--dh, --dw override it and are required for recorded machine images given as four single-channel
files (EXR/TIFF/NPY, same orientation: row 0 = +y edge, columns towards +x).

Output EXR channels: dzdx, dzdy (mm/mm), Mx, My, sum_rl, sum_bf (Eq. 23, material contrast),
mask (1 = untrusted pixel: a detector masked or dark, a sum or the Eq. 26 denominator near zero,
the model's misfit, bad input; gradient 0 there) and mask_reason (bit field, see the header).
The header carries the geometry so that 'elo-mitsuba reconstruct' needs no flags.
Run time at 1500 x 1500 on 2 idle CPU cores, end to end: eq26 3 s, model 12 s (14-30 s under load).
"""

EPILOG = """\
examples:
  elo-mitsuba gradient --flat flat.exr melt.exr -o grad.exr --preview grad.png
  elo-mitsuba gradient --flat flat.exr melt.exr -o grad26.exr --method eq26      # the paper's Eq. 26
  elo-mitsuba gradient --flat flat.exr melt.exr -o grad.exr --calibration CALIB.json
  elo-mitsuba gradient --flat flat.exr melt.exr -o grad_e1.exr --event 1      # 1st event only
  elo-mitsuba gradient --flat flat1.exr --flat flat2.exr melt.exr -o grad.exr  # the flats' mean
  elo-mitsuba gradient --right R.tif --left L.tif --back B.tif --front F.tif \\
      --flat-right R0.tif --flat-left L0.tif --flat-back B0.tif --flat-front F0.tif \\
      --field 80 --dh 272 --dw 127 -o grad.exr
"""


def field_arg(text: str) -> tuple[float, float]:
    """argparse type for ``--field FX[,FY]`` in mm."""
    try:
        vals = [float(v) for v in text.replace("x", ",").split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: give FX or FX,FY in mm, e.g. 80 or 80,60") from None
    if len(vals) not in (1, 2) or not all(np.isfinite(v) and v > 0 for v in vals):
        raise argparse.ArgumentTypeError(f"{text!r}: give one or two lengths > 0 in mm, e.g. 80 or 80,60")
    return (vals[0], vals[-1])


def positive_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (np.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"{text!r}: must be finite and > 0")
    return v


def add_scan_arguments(p):
    """The inputs of one scan (object and flat-plate images, geometry): shared by gradient and invert."""
    p.add_argument("object", nargs="?", metavar="OBJECT.exr",
                   help="object images: EXR with channels right, left, back, front")
    src = p.add_argument_group("single-channel inputs (recorded machine images)")
    for n in DETECTOR_NAMES:
        src.add_argument(f"--{n}", metavar="FILE", help=f"{n} detector image (EXR/TIFF/NPY)")
    flat = p.add_argument_group("STSA correction (flat plate)")
    flat.add_argument("--flat", metavar="FLAT.exr", action="append",
                      help="flat-plate EXR with channels right, left, back, front; repeat it for several "
                           "recordings: their mean is used (the flat's noise falls as 1/sqrt(N))")
    for n in DETECTOR_NAMES:
        flat.add_argument(f"--flat-{n}", metavar="FILE", action="append",
                          help=f"flat-plate image of the {n} detector (repeatable, as --flat)")
    flat.add_argument("--no-flat", action="store_true",
                      help="the inputs are already STSA-corrected (skip the division)")
    geo = p.add_argument_group("geometry (overrides the EXR headers)")
    geo.add_argument("--field", type=field_arg, metavar="FX[,FY]", help="scan field in mm, e.g. 80")
    geo.add_argument("--dh", type=positive_float, metavar="MM", help="detector height d_h in mm")
    geo.add_argument("--dw", type=positive_float, metavar="MM", help="detector distance d_w from the z-axis in mm")
    geo.add_argument("--radius", type=positive_float, metavar="MM",
                     help="detector disc radius (model method, without a header; default 25)")
    geo.add_argument("--wd", type=positive_float, metavar="MM",
                     help="work distance: beam pivot height (model method, without a header; default 400)")
    geo.add_argument("--projection", choices=("perspective", "orthographic"),
                     help="beam from the pivot or parallel to -z (model method, without a header)")
    geo.add_argument("--material", metavar="NAME",
                     help="surface material for the model (default: the header's, else Ti-6Al-4V)")
    geo.add_argument("--calibration", metavar="CALIB.json",
                     help="detector centres and normals from 'elo-mitsuba calibrate' (model method)")


def add_parser(subparsers):
    p = subparsers.add_parser(
        "gradient", help="four detector images -> surface gradient (model fit or Eq. 26) and mask",
        description=DESCRIPTION, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_scan_arguments(p)
    p.add_argument("-o", "--output", required=True, metavar="GRAD.exr", help="gradient EXR to write")
    mod = p.add_argument_group("method")
    mod.add_argument("--method", choices=("model", "eq26"), default="model",
                     help="model: per-pixel fit of the 1st-event model (default); eq26: the paper's Eq. 26")
    mod.add_argument("--iterations", type=int, default=None, metavar="N",
                     help="Levenberg-Marquardt iterations of the model fit (default 10)")
    mod.add_argument("--noise", type=positive_float, default=None, metavar="SIGMA",
                     help="noise (std) of the corrected images for the uncertainty; default: estimated")
    mod.add_argument("--second-event", metavar="SIM_FLAT.exr",
                     help="a render of the flat plate in the chamber with --events >= 2: its share of later "
                          "events is taken out of the flat and the object images (the model is 1st-event only)")
    mod.add_argument("--height-passes", type=int, default=1, metavar="N",
                     help="2: refit with the landing points on the integrated heights (relief of several mm)")
    p.add_argument("--event", type=int, metavar="K",
                   help="use the per-event channels right.eK ... instead of the totals")
    thr = p.add_argument_group("mask thresholds")
    thr.add_argument("--min-corrected", type=float, default=None, metavar="V",
                     help="a corrected image R^C <= V marks the pixel (detector masked); default 0.02")
    thr.add_argument("--min-sum", type=float, default=None, metavar="V",
                     help="R^C+L^C or B^C+F^C below V marks the pixel; default 0.05 (flat plate: 2)")
    thr.add_argument("--min-denominator", type=float, default=None, metavar="F",
                     help="Eq. 26 denominator <= F*d_w marks the pixel; default 0.05")
    p.add_argument("--preview", metavar="PNG", help="also write a PNG of dZ/dx, dZ/dy with the mask")
    p.add_argument("--overwrite", action="store_true", help="replace existing output files")
    p.set_defaults(run=run)
    return p


def nominal_geometry(args, header, shape, field_mm, d_h, d_w):
    """The drawing's layout of Eq. 17 from --dh/--dw and --radius/--wd/--projection/--material,
    each defaulting to the header's value, else the package's (shared by gradient and calibrate)."""
    from ..analysis.scan_geometry import ScanGeometry
    from ..constants import DETECTOR_DIAMETER_MM, WORK_DISTANCE_MM

    header = header or {}
    kw = {"work_distance_mm": args.wd or header.get("work_distance_mm", WORK_DISTANCE_MM),
          "projection": args.projection or header.get("projection", "perspective")}
    if args.material:
        kw["material"] = args.material
    return ScanGeometry.nominal(shape, field_mm, d_h, d_w, radius=args.radius or DETECTOR_DIAMETER_MM / 2, **kw)


def _model_geometry(args, header, shape, geo, source):
    """The scan geometry the model inverts: the header's discs, or the nominal layout of
    --dh/--dw/--radius; --calibration replaces the detectors."""
    from ..analysis.scan_geometry import ScanGeometry

    explicit = args.dh is not None or args.dw is not None or not (header or {}).get("detectors")
    if explicit:
        if (args.dh is None) != (args.dw is None) and (header or {}).get("detectors"):
            raise EloInputError("give both --dh and --dw (a nominal layout), or neither (the header's detectors)")
        model = nominal_geometry(args, header, shape, geo["field_mm"], geo["d_h"], geo["d_w"])
    else:
        for flag in ("radius", "wd", "projection"):
            if getattr(args, flag) is not None:
                raise EloInputError(f"--{flag} applies to images without a header (or with --dh/--dw); "
                                    f"{source} records the geometry")
        model = ScanGeometry.from_metadata(header, shape, source, field_mm=geo["field_mm"], material=args.material)
    if args.calibration:
        from ..analysis.calibration import read_calibration

        model = read_calibration(args.calibration).apply(model)
    from ..scene_files import check_detector_placement

    where = args.calibration or ("--dh/--dw" if explicit and args.dh is not None else source)
    for name, disc in model.detectors.items():  # the rule of every detector (a scene's, a moved one's)
        check_detector_placement(name, disc.center, disc.normal, disc.radius, where=str(where))
    return model


def _same(a, b, rtol=1e-6):
    return np.allclose(np.asarray(a, float), np.asarray(b, float), rtol=rtol, atol=0)


def _report_mask(res) -> None:
    """Why pixels are masked (share per reason of MASK_BITS), and a warning when most are."""
    import sys

    from ..analysis.gradient import MASK_BITS

    if not res.mask.any():
        return
    shares = [f"{name} {100 * np.mean((res.reasons & bit) > 0):.2f} %" for name, bit in MASK_BITS.items()
              if np.any(res.reasons & bit)]
    print(f"masked pixels by reason (a pixel may have several): {', '.join(shares)}")
    if res.mask.mean() > 0.5:
        print(f"elo-mitsuba: warning: {100 * res.mask.mean():.1f} % of the pixels are masked; see the reasons above "
              "and the mask thresholds in 'elo-mitsuba gradient --help'", file=sys.stderr)


@dataclass
class Scan:
    """One scan's images and geometry as :func:`read_scan` found them."""

    images: dict
    flats: dict | None
    header: dict
    source: str
    shape: tuple
    geo: dict
    flat_files: list = field(default_factory=list)

    @property
    def flat_count(self) -> int:
        return len(self.flat_files)

    def flat_provenance(self):
        """The flat plate's files as the output headers record them: one entry, or one per recording."""
        return self.flat_files[0] if len(self.flat_files) == 1 else list(self.flat_files)


@dataclass
class FlatRecording:
    """One recording of the flat plate: how messages name it, its files, images and header."""

    label: str
    files: str | dict
    images: dict
    header: dict


def flat_recordings(args) -> list[FlatRecording]:
    """Each recording of the flat plate that ``args`` names: every ``--flat`` EXR, then every set
    of ``--flat-<detector>`` files (the i-th of each flag)."""
    from ..analysis.io import load_detector_set

    files = {n: getattr(args, f"flat_{n}") or [] for n in DETECTOR_NAMES}
    exrs = args.flat or []
    sets = max(len(v) for v in files.values())
    what = "flat-plate images"
    out = []
    for path in exrs:
        images, header = load_detector_set(path, None, what, args.event)
        out.append(FlatRecording(str(path), path, images, header))
    for i in range(sets):
        given = {n: v[i] for n, v in files.items() if i < len(v)}
        label = f"{what} (set {i + 1} of --flat-<detector>)" if len(exrs) + sets > 1 else what
        images, header = load_detector_set(None, given, label, args.event)
        out.append(FlatRecording(", ".join(str(given[n]) for n in DETECTOR_NAMES), given, images, header))
    return out


def flat_note(scan) -> str:
    """What the summary line says of several flat recordings."""
    return f"; flat plate: the mean of {scan.flat_count} recordings" if scan.flat_count > 1 else ""


#: The flat's share of the noise variance from which the summary suggests more recordings of it.
FLAT_SHARE_ADVICE = 0.1


def noise_shares(scan) -> tuple[dict, str]:
    """The object's and the flat's relative noise (:func:`~..analysis.inversion.relative_noise`)
    for the header, and a line saying how much of the corrected images' noise the flat holds and
    what more recordings of it would leave ("" without a flat)."""
    from ..analysis.inversion import relative_noise

    if scan.flats is None:
        return {}, ""
    so, sf = relative_noise(scan.images), relative_noise(scan.flats)
    if not (np.isfinite(so) and np.isfinite(sf) and so + sf > 0):
        return {}, ""
    n = scan.flat_count
    share = sf ** 2 / (so ** 2 + sf ** 2)
    more = sf ** 2 / 4 / (so ** 2 + sf ** 2 / 4)
    what = "1 recording" if n == 1 else f"the mean of {n} recordings"
    line = (f"image noise: object {100 * so:.2g} %, flat plate {100 * sf:.2g} % ({what}): the flat holds "
            f"{100 * share:.0f} % of the corrected images' noise variance")
    if share >= FLAT_SHARE_ADVICE:
        line += f"; the mean of {4 * n} flat recordings would hold {100 * more:.0f} % (repeat --flat)"
    return {"noise_object": so, "noise_flat": sf, "flat_recordings": n}, line


def read_scan(args, *, model_discs: bool) -> Scan:
    """The object and flat-plate images of ``args`` (:func:`add_scan_arguments`), checked: signs,
    one shape, the flat recorded with the object's geometry, the header's resolution. ``geo`` holds
    field_mm, d_h, d_w and resolution; with ``model_discs`` and a header with detectors, d_h and
    d_w are the discs' mean (the model takes the discs as they are)."""
    from ..analysis import geometry_from_metadata
    from ..analysis.io import check_signs, load_detector_set
    from ..analysis.stsa import mean_flat

    images, meta = load_detector_set(args.object, {n: getattr(args, n) for n in DETECTOR_NAMES}, "object images",
                                     args.event)
    if images is None:
        raise EloInputError("no object images: give OBJECT.exr or --right/--left/--back/--front")
    recordings = flat_recordings(args)
    flats = mean_flat([r.images for r in recordings]) if recordings else None
    flat_meta = next((r.header for r in recordings if r.header), {})
    if flats is None and not args.no_flat:
        raise EloInputError("no flat-plate images: give --flat FLAT.exr (or --flat-right ...), "
                            "or --no-flat if the images are already STSA-corrected")
    if flats is not None and args.no_flat:
        raise EloInputError("--no-flat contradicts the flat-plate images given")
    check_signs(images, flats, {n: args.object or getattr(args, n) for n in DETECTOR_NAMES})

    # Geometry: explicit flags win; otherwise the object header, else the flat header.
    header = meta if meta else flat_meta
    source = args.object or next((r.label for r in recordings if r.header), None) or "command line"
    if not header and (args.field is None or args.dh is None or args.dw is None):
        what = (f"{source} has no elo-mitsuba geometry header (not written by 'elo-mitsuba render')"
                if (args.object or args.flat) else "single-channel inputs carry no geometry")
        raise EloInputError(f"{what}: pass --field, --dh and --dw (mm)")
    shape = next(iter(images.values())).shape
    header_discs = model_discs and args.dh is None and args.dw is None and bool((header or {}).get("detectors"))
    if header_discs:
        # the model takes the header's discs as they are: no symmetric layout needed
        from ..analysis.scan_geometry import ScanGeometry

        disc_geo = ScanGeometry.from_metadata(header, shape, str(source), field_mm=args.field, material=args.material)
        res_hdr = header.get("resolution")
        d_h, d_w = disc_geo.symmetric_layout()
        geo = {"field_mm": disc_geo.field_mm, "d_h": d_h, "d_w": d_w,
               "resolution": None if res_hdr is None else (int(res_hdr[0]), int(res_hdr[1]))}
    else:
        geo = geometry_from_metadata(header, str(source), d_h=args.dh, d_w=args.dw, field_mm=args.field, shape=shape)
    # every flat must describe the object's scan, or the division mixes two geometries
    geo_cmp = geo if not header_discs else {
        "field_mm": geo["field_mm"], "resolution": geo["resolution"],
        **{f"{n} detector": np.r_[d.center, d.normal, d.radius] for n, d in disc_geo.detectors.items()}}
    for rec in recordings if header else ():
        flat_source, flat_header = rec.label, rec.header
        if not flat_header:
            continue
        if header_discs:
            fdisc = ScanGeometry.from_metadata(flat_header, shape, flat_source, field_mm=args.field)
            fgeo = {"field_mm": fdisc.field_mm, "resolution": flat_header.get("resolution"),
                    **{f"{n} detector": np.r_[d.center, d.normal, d.radius] for n, d in fdisc.detectors.items()}}
        else:
            fgeo = geometry_from_metadata(flat_header, flat_source, d_h=args.dh, d_w=args.dw, field_mm=args.field,
                                          shape=shape)
        for key in fgeo:
            a, b = geo_cmp.get(key), fgeo[key]
            if (a is None) != (b is None) or (a is not None and not _same(a, b)):
                raise EloInputError(
                    f"{flat_source}: flat-plate {key} {np.round(np.asarray(b, float), 4).tolist()} differs from "
                    f"the {'object' if meta else 'first flat'}'s {np.round(np.asarray(a, float), 4).tolist()}; "
                    "record all with one geometry"
                )
    if geo["resolution"] is not None and tuple(geo["resolution"]) != (shape[1], shape[0]):
        raise EloInputError(
            f"{source}: header resolution {list(geo['resolution'])} (W, H) does not match the image "
            f"shape {shape[1]}x{shape[0]}"
        )
    return Scan(images=images, flats=flats, header=header, source=str(source), shape=shape, geo=geo,
                flat_files=[r.files for r in recordings])


def run(args) -> int:
    from ..analysis import surface_gradient
    from ..analysis.gradient import MIN_CORRECTED, MIN_DENOMINATOR
    from ..analysis.io import write_gradient
    from ..analysis.model_gradient import ITERATIONS
    from ..analysis.plots import preview_gradient
    from ..analysis.stsa import MIN_SUM
    from ..files import check_output

    if args.iterations is not None and args.iterations < 1:
        raise EloInputError(f"--iterations {args.iterations}: need at least 1")
    if args.height_passes not in (1, 2, 3):
        raise EloInputError(f"--height-passes {args.height_passes}: choose 1, 2 or 3")
    if args.method == "eq26":
        for flag in ("calibration", "iterations", "noise", "radius", "wd", "projection", "material", "second_event"):
            if getattr(args, flag) is not None:
                raise EloInputError(f"--{flag.replace('_', '-')} applies to --method model only")
        if args.height_passes != 1:
            raise EloInputError("--height-passes applies to --method model only")
    elif args.min_denominator is not None:
        raise EloInputError("--min-denominator applies to --method eq26 only (the model has no denominator)")
    for flag in ("min_corrected", "min_sum", "min_denominator"):
        value = getattr(args, flag)
        if value is not None and not np.isfinite(value):
            raise EloInputError(f"--{flag.replace('_', '-')} {value}: must be a finite number")
    out = check_output(args.output, (".exr",), overwrite=args.overwrite)
    if args.preview:
        check_output(args.preview, (".png",), overwrite=args.overwrite, what="preview")
    scan = read_scan(args, model_discs=args.method == "model")
    images, flats, header, shape, geo = scan.images, scan.flats, scan.header, scan.shape, scan.geo
    source = scan.source
    kw = dict(min_corrected=MIN_CORRECTED if args.min_corrected is None else args.min_corrected,
              min_sum=MIN_SUM if args.min_sum is None else args.min_sum,
              min_denominator=MIN_DENOMINATOR if args.min_denominator is None else args.min_denominator)
    model = None
    if args.method == "model":
        model = _model_geometry(args, header, shape, geo, str(source))
        from ..analysis.model_gradient import model_gradient_refined

        from ..analysis.io import read_later_events

        share = read_later_events(args.second_event, shape)[1] if args.second_event else None
        if share is not None and flats is None:
            raise EloInputError("--second-event corrects the flat-plate images; give --flat")
        res = model_gradient_refined(images, flats, model, passes=args.height_passes, noise=args.noise,
                                     flat_second_event=share,
                                     iterations=ITERATIONS if args.iterations is None else args.iterations,
                                     min_corrected=kw["min_corrected"], min_sum=kw["min_sum"])
        kw.pop("min_denominator")
    else:
        res = surface_gradient(images, flats, geo["field_mm"], geo["d_h"], geo["d_w"], **kw)

    sources = {"object": args.object or {n: getattr(args, n) for n in DETECTOR_NAMES},
               "flat": scan.flat_provenance()}
    write_gradient(out, res, geo["field_mm"], geo["d_h"], geo["d_w"], thresholds=kw, stsa_corrected=not args.no_flat,
                   event=args.event, sources=sources, header=header, overwrite=args.overwrite,
                   method=args.method, model_geometry=model, calibration=args.calibration)
    extra = ""
    if model is not None:
        extra = (f", noise {res.noise:.2g}, median uncertainty of dZ/dx "
                 f"{np.median(res.dzdx_sigma[~res.mask]) if (~res.mask).any() else float('nan'):.2g}")
    print(f"wrote {out}: {shape[1]}x{shape[0]} px, field {geo['field_mm'][0]:g}x{geo['field_mm'][1]:g} mm, "
          f"d_h={geo['d_h']:g} mm, d_w={geo['d_w']:g} mm, method {args.method}, {100 * res.mask.mean():.2f} % masked"
          + extra + flat_note(scan))
    noise_line = noise_shares(scan)[1]
    if noise_line:
        print(noise_line)
    _report_mask(res)
    if args.preview:
        title = "Surface gradient (model fit)" if args.method == "model" else "Surface gradient (Eq. 26)"
        preview_gradient(res.dzdx, res.dzdy, geo["field_mm"], Path(args.preview), mask=res.mask, title=title,
                         overwrite=args.overwrite)
        print(f"wrote {args.preview}")
    return 0
