"""``elo-mitsuba mesh``: a height map to a triangle mesh (binary PLY) in scene coordinates."""

from __future__ import annotations

import argparse
import math

from ..errors import EloInputError
from ._args import material_arg, number, positive_int

HELP = "turn a height map (.exr/.tif/.gsf/.npy/.csv) into a triangle mesh (PLY) for a scene"

DESCRIPTION = """\
Triangulate a height map into a mesh in scene coordinates (millimetres): one vertex per pixel
centre, centred on the z-axis, x to the right, y up, z = height, two triangles per pixel cell with
normals pointing up (+z, out of the material): n = [-dZ/dx, -dZ/dy, 1] (Eq. 16).

Orientation of the map: row 0 is the +y edge, columns run towards +x (the surface seen from
above, +y up), as in the ELO images. Heights in mm (or --units um); the pixel size is always mm.
The package's own height maps (reconstruct/invert -o .exr, .tif, .gsf) record their pixel size and
height unit: --pixel-size and --units are then not needed, and refused when they contradict the
file. A TIFF of another tool gives its pixel size by its resolution tags (inch, cm, mm, um);
NPY and CSV record none. Pixels without a height (NaN) cannot be meshed: crop or fill them.
Render the mesh with face_normals=true (flat shading), as the shipped scenes do; --scene writes
such a scene (the four detectors of the ATHENE set-up, the parameters of scenes_xml/), its scan
field by default the square the mesh covers (the shorter side of the map between its outer pixel
centres).
"""

EPILOG = """\
examples:
  elo-mitsuba mesh height.exr -o plate.ply          # reconstruct's output: pixel size from its header
  elo-mitsuba mesh height.npy -o plate.ply --pixel-size 0.0533
  elo-mitsuba mesh scan.tif --units um -o plate.ply --pixel-size 0.1 --step 2
  elo-mitsuba mesh height.csv -o plate.ply --pixel-size 0.2 --tolerance 1e-4 --scene plate.xml
  elo-mitsuba render plate.xml -o plate.exr -D res=512
"""


def add_parser(subparsers):
    p = subparsers.add_parser(
        "mesh", help=HELP, description=DESCRIPTION, epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("heightmap", metavar="HEIGHTMAP", help="height map: .exr/.tif/.gsf (as reconstruct writes them), .npy or .csv (comma-separated), 2-D, rows = -y, columns = +x")
    p.add_argument("-o", "--output", required=True, metavar="MESH.ply", help="binary PLY to write")
    p.add_argument("--pixel-size", type=number, metavar="MM",
                   help="pixel pitch in mm (> 0); needed where the file records none (NPY, CSV, a plain TIFF)")
    p.add_argument("--units", choices=("mm", "um"),
                   help="units of the heights where the file records none (default mm)")
    p.add_argument("--step", type=positive_int, default=1, metavar="N", help="keep every N-th row and column (down-sampling; default 1)")
    p.add_argument("--tolerance", type=number, metavar="MM", help="drop whole rows/columns that linear interpolation reproduces within MM (exact for flat margins)")
    p.add_argument("--base", type=number, metavar="Z_MM", help="close the mesh with side walls and a bottom at z = Z_MM (watertight solid; not needed to render)")
    p.add_argument("--scene", metavar="SCENE.xml", help="also write a scene XML rendering this mesh with the four detectors")
    p.add_argument("--material", type=material_arg, help="material of the object in --scene: preset (Ti-6Al-4V, 316L, Cu, ...) or composition 'Ti:0.9,Al:0.06,V:0.04' (default Ti-6Al-4V)")
    p.add_argument("--overwrite", action="store_true", help="replace existing output files")
    p.set_defaults(run=run)
    return p


def run(args) -> int:
    from ..files import check_output
    from ..heightmap import read_heightmap, validate_pixel_size
    from ..mesh import heightmap_to_mesh, write_mesh
    from ..scene_files import write_scene

    if args.material is not None and args.scene is None:
        raise EloInputError("--material sets the object's material in --scene; give --scene SCENE.xml too")
    out = check_output(args.output, (".ply",), overwrite=args.overwrite, what="--output")
    if args.scene is not None:
        check_output(args.scene, (".xml",), overwrite=args.overwrite, what="--scene")
        from ..physics.materials import get_material

        get_material(args.material)
    given = None
    if args.pixel_size is not None:
        if not args.pixel_size > 0 or args.pixel_size == float("inf"):
            raise EloInputError(f"--pixel-size {args.pixel_size!r} mm must be a finite number > 0")
        given = validate_pixel_size(args.pixel_size)
    read = read_heightmap(args.heightmap, units=args.units)
    height, pixel = read.height, read.pixel_size_mm
    if pixel is None and given is None:
        raise EloInputError(f"{args.heightmap}: the file records no pixel size; give --pixel-size MM")
    if pixel is not None and given is not None and not math.isclose(given, pixel, rel_tol=1e-6):
        raise EloInputError(f"--pixel-size {given:g} mm contradicts the {read.pixel_source} of {args.heightmap} "
                            f"({pixel:g} mm); leave it out")
    pixel = pixel if pixel is not None else given
    mesh = heightmap_to_mesh(height, pixel, step=args.step, tolerance_mm=args.tolerance, base_mm=args.base)
    write_mesh(mesh, out, overwrite=args.overwrite)
    lo, hi = mesh.bounds
    print(
        f"{out}: {len(mesh.vertices)} vertices, {len(mesh.faces)} triangles, pixel {pixel:g} mm"
        f"{f' ({read.pixel_source})' if read.pixel_size_mm is not None else ''}, "
        f"x [{lo[0]:.4g}, {hi[0]:.4g}] y [{lo[1]:.4g}, {hi[1]:.4g}] z [{lo[2]:.4g}, {hi[2]:.4g}] mm, "
        f"{out.stat().st_size / 1e6:.2f} MB"
    )
    if args.scene is not None:
        # the scan field the mesh covers (vertices at the pixel centres; a square film: the shorter side),
        # not the template's 80 mm, which the beam would mostly scan beside a smaller mesh
        field = float(min(hi[0] - lo[0], hi[1] - lo[1]))
        write_scene(args.scene, out, material=args.material, field_mm=field, overwrite=args.overwrite)
        print(f"{args.scene}: scene with the four detectors, scan field {field:.4g} mm (the mesh's extent; "
              f"-D field=... for less) (render: elo-mitsuba render {args.scene} -o OUT.exr)")
    return 0
