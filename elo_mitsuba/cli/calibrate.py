"""``elo-mitsuba calibrate``: flat-plate images -> each detector's real centre, tilt and gain."""

from __future__ import annotations

import argparse
import sys

import numpy as np

from ..constants import DETECTOR_NAMES
from ..schema import scattering_note
from ._args import field_arg, length_mm, material_arg, positive_float, positive_int

DESCRIPTION = """\
Fit where each detector really is, from the four images of a plane plate (any unit: volts,
N_d/N_0): per detector its centre (x, y, z mm), the tilt of its normal (two angles, deg) and its
amplifier gain (image units per N_d/N_0), optionally a constant offset, by least squares against
the 1st-event model (full g_BSE of Eq. 13, disc detectors, the beam of each scan point). Each
detector's image depends on that detector alone, so each is fitted on its own, on block means
of its image (48 to 95 a side, covering all of it but fewer pixels than a block's).

The start is the drawing: --dh/--dw (and --radius, --wd) or, without them, the detectors of the
EXR header. The radius is held: it scales the signal like the gain. The output CALIB.json holds,
per detector, center, normal, radius, gain, offset, one-sigma uncertainties, the parameter
correlations and the pairs the data cannot separate (|correlation| > 0.99): those are known only
in combination, which is what the images (and the model gradient) depend on.
Precision: with 0.5 % noise per pixel, about 0.2 mm in the centre from a 1024 x 1024 flat,
about 3 mm from 128 x 128 (the noise of the block means sets it). A centre whose two standard
errors exceed the detector's radius is reported as "position not determined", not "not moved".

Images that are not of a flat plate are refused (exit 2, nothing written): a flat plate's image is
smooth and leaves an rms misfit about the noise of its block means (the images' own noise per
pixel, from their second differences, counted up to 5 %, over sqrt(pixels per block)); a detector
whose misfit exceeds 3 x that, or 1 % if more, fails (--max-misfit PCT sets the bound). Isolated
dead or hot pixels do not pull the fit: blocks more than 5 robust standard deviations off are left
out and the fit repeated (the count is printed).

A flat in a chamber records the walls' later events too (athene_flat: 6.5 % of the signal), which
the 1st-event fit takes for moved detectors (9.5-17.5 mm) and larger gains: give --second-event with a
render of the flat plate in that chamber (--events 2) to take them out first.

Use the result with 'elo-mitsuba gradient --calibration CALIB.json'.
"""

EPILOG = """\
examples:
  elo-mitsuba calibrate flat.exr --dh 272 --dw 127 -o CALIB.json
  elo-mitsuba calibrate flat1.exr flat2.exr flat3.exr -o CALIB.json     # their mean; the header's detectors
  elo-mitsuba calibrate --right R0.tif --left L0.tif --back B0.tif --front F0.tif \\
      --field 80 --dh 272 --dw 127 --radius 25 -o CALIB.json
"""


def add_parser(subparsers):
    p = subparsers.add_parser(
        "calibrate", help="flat-plate images -> detector centres, tilts and gains (CALIB.json)",
        description=DESCRIPTION, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("flat", nargs="*", metavar="FLAT.exr",
                   help="flat-plate EXR with channels right, left, back, front; several recordings of one set-up "
                        "are averaged (the fit's noise falls as 1/sqrt(N))")
    p.add_argument("-o", "--output", required=True, metavar="CALIB.json", help="calibration file to write")
    src = p.add_argument_group("single-channel inputs (recorded machine images)")
    for n in DETECTOR_NAMES:
        src.add_argument(f"--{n}", metavar="FILE", help=f"{n} detector image of the flat plate (EXR/TIFF/NPY)")
    geo = p.add_argument_group("nominal geometry (the drawing: the start of the fit)")
    geo.add_argument("--field", type=field_arg, metavar="FX[,FY]", help="scan field in mm, e.g. 80")
    geo.add_argument("--dh", type=length_mm, metavar="MM", help="detector height d_h in mm")
    geo.add_argument("--dw", type=length_mm, metavar="MM", help="detector distance d_w from the z-axis in mm")
    geo.add_argument("--radius", type=length_mm, metavar="MM", help="detector disc radius (default 25)")
    geo.add_argument("--wd", "--work-distance", dest="wd", type=length_mm, metavar="MM",
                     help="work distance (default: header, else 400)")
    geo.add_argument("--projection", choices=("perspective", "orthographic"), help="beam projection")
    geo.add_argument("--material", type=material_arg, metavar="NAME", help="plate material (default: header, else Ti-6Al-4V)")
    fit = p.add_argument_group("fit")
    fit.add_argument("--fit-offset", action="store_true", help="also fit a constant offset per detector")
    fit.add_argument("--no-tilt", action="store_true", help="hold each normal at its nominal direction")
    fit.add_argument("--max-misfit", type=positive_float, metavar="PCT",
                     help="largest rms misfit in %% a detector's fit may leave (default: 3 x the noise of its block "
                          "means, from the images' own, at least 1 %%); above it the images are refused")
    fit.add_argument("--event", type=positive_int, metavar="K", help="use the per-event channels right.eK ... of the EXR")
    fit.add_argument("--second-event", metavar="SIM_FLAT.exr",
                     help="a render of the flat plate in its chamber with --events >= 2 (the drawing's geometry): "
                          "each pixel's share of events >= 2 is taken out of the images before the 1st-event fit, "
                          "which would otherwise move the detectors to mimic the chamber's later events")
    p.add_argument("--overwrite", action="store_true", help="replace an existing CALIB.json")
    p.set_defaults(run=run)
    return p


def run(args) -> int:
    from ..analysis.calibration import calibrate, describe_displacement, write_calibration
    from ..analysis.chain import calibration_start, read_calibration_flats
    from ..analysis.io import (check_distinct_detectors, check_field, check_repeated_recordings,
                                   check_second_event)
    from ..files import check_output

    out = check_output(args.output, (".json",), overwrite=args.overwrite, what="calibration")
    check_repeated_recordings(args.flat, what="FLAT.exr")
    flats, header, source = read_calibration_flats(args.flat, {n: getattr(args, n) for n in DETECTOR_NAMES},
                                                   args.event, second_event=args.second_event)
    if scattering_note(header, source):  # images of another g_BSE than the models' (a lobe study)
        print(f"note: {scattering_note(header, source)}", file=sys.stderr)
    if int(header.get("events", 1)) > 1 and args.event is None and args.second_event is None:
        print(f"note: {source} was rendered with events={header['events']}: the fit's model is the 1st event, and it "
              "moves the detectors to mimic the later events (athene_flat: 9.5-17.5 mm); use --event 1, or "
              "--second-event SIM_FLAT.exr for recordings", file=sys.stderr)
    check_distinct_detectors({n: getattr(args, n) for n in DETECTOR_NAMES}, "flat-plate images")
    shape = next(iter(flats.values())).shape
    check_field(args.field, header, shape, source)
    if args.second_event:
        check_second_event(args.second_event, header, source, shape, field_mm=args.field, d_h=args.dh, d_w=args.dw)
    nominal = calibration_start(header, shape, source, d_h=args.dh, d_w=args.dw, field_mm=args.field,
                                radius=args.radius, work_distance_mm=args.wd, projection=args.projection,
                                material=args.material)
    files = [str(f) for f in args.flat] or {n: str(getattr(args, n)) for n in DETECTOR_NAMES if getattr(args, n)}
    cal = calibrate(flats, nominal, fit_offset=args.fit_offset, fit_tilt=not args.no_tilt,
                    max_misfit=None if args.max_misfit is None else args.max_misfit / 100,
                    source=", ".join(files) if isinstance(files, list) else files)
    cal.source["input"] = [str(f) for f in args.flat] if len(args.flat) > 1 else source
    write_calibration(out, cal, overwrite=args.overwrite)
    for name, fit in cal.detectors.items():
        nom = np.asarray(nominal.detectors[name].center)
        c = np.asarray(fit.disc.center)
        sig = [fit.sigma.get(k, 0.0) for k in ("cx", "cy", "cz")]
        tilt = np.degrees(np.arccos(np.clip(np.dot(fit.disc.normal, nominal.detectors[name].normal), -1, 1)))
        note = f"; not separable: {', '.join(fit.degenerate)}" if fit.degenerate else ""
        moved = describe_displacement(float(np.linalg.norm(c - nom)), float(np.linalg.norm(sig)),
                                      scale_mm=float(nominal.detectors[name].radius))
        left_out = (f"; {fit.rejected} of {fit.blocks} blocks left out (dead or hot pixels)" if fit.rejected else "")
        print(f"  {name:6s} centre [{c[0]:.2f}, {c[1]:.2f}, {c[2]:.2f}] mm (+-{max(sig):.2f}; {moved}), "
              f"tilt {tilt:.2f} deg, gain {fit.gain:.5g}, "
              f"rms misfit {100 * fit.rms_residual:.3f} % (bound {100 * fit.misfit_bound:.3g} %){left_out}{note}")
    print(f"wrote {out}")
    return 0
