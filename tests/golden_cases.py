"""Golden outputs of the CLI on the shipped scenes at a fixed seed (regression guard).

Each case is one ``elo-mitsuba`` command line run in-process; its outputs (EXR channels, NPY
arrays, PLY/XML bytes) are stored as SHA-256 digests, shapes and means in
``tests/golden_cases.json``, together with a fingerprint of the machine and software that made
them. ``tests/test_golden.py`` re-runs the cases and demands
bit-identical arrays where the fingerprint matches (a refactoring must not change one bit).

A deliberate change of the physics or the sampling changes the goldens: regenerate them with

    python3 tests/golden_cases.py --update

and say in the commit which outputs changed and why.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import platform
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
GOLDEN = HERE / "golden_cases.json"
GOLDEN_ARRAYS = HERE / "golden_cases.npz"

#: (case name, argv with {d} = the output folder). Small resolutions: seconds each, yet every
#: estimator path runs (quadrature, sampled, bounce filter + top-up, splitting, beam profile,
#: voltage units, the chamber, meshes, gradient and normal integration, meshing).
CASES = (
    ("flat_default", ["render", "flat_plate", "-o", "{d}/flat.exr", "--resolution", "40", "--quiet"]),
    ("corr_default", ["render", "corrugated_sheet", "-o", "{d}/corr.exr", "--resolution", "40", "--quiet"]),
    ("athene_default", ["render", "athene_flat", "-o", "{d}/athene.exr", "--resolution", "120", "--events", "2",
                        "--quiet"]),
    ("athene_draft", ["render", "athene_flat", "-o", "{d}/athene_draft.exr", "--resolution", "64", "--events", "2",
                      "--quality", "draft", "--seed", "3", "--quiet"]),
    ("athene_reference", ["render", "athene_flat", "-o", "{d}/athene_ref.exr", "--resolution", "16",
                          "--events", "2", "--quality", "reference", "--quiet"]),
    ("athene_unbiased", ["render", "athene_flat", "-o", "{d}/athene_unb.exr", "--resolution", "16",
                         "--events", "2", "--quality", "unbiased", "--quiet"]),
    ("corr_events2", ["render", "corrugated_sheet", "-o", "{d}/corr2.exr", "--resolution", "48", "--events", "2",
                      "--quiet"]),
    ("melt_blur", ["render", "melt_plate", "-o", "{d}/melt.exr", "--resolution", "32", "--layout", "zeta50",
                   "-D", "fwhm=0.27", "--quiet"]),
    ("flat_scene_volts", ["render", "flat_plate", "-o", "{d}/flat_v.exr", "--resolution", "24", "--quality",
                          "scene", "--spp", "4", "--units", "voltage", "--detector-samples", "2", "--quiet"]),
    ("melt_scene_e3", ["render", "melt_plate", "-o", "{d}/melt3.exr", "--resolution", "24", "--quality", "scene",
                       "--spp", "2", "--events", "3", "-D", "projection=orthographic", "--quiet"]),
    ("gradient", ["gradient", "--flat", "{d}/flat.exr", "{d}/corr.exr", "-o", "{d}/grad.exr"]),
    ("gradient_eq26", ["gradient", "--flat", "{d}/flat.exr", "{d}/corr.exr", "-o", "{d}/grad26.exr", "--method", "eq26"]),
    ("reconstruct", ["reconstruct", "{d}/grad.exr", "-o", "{d}/height.exr"]),
    ("reconstruct_npy", ["reconstruct", "{d}/grad.exr", "-o", "{d}/height.npy", "--method", "dct"]),
    ("mesh", ["mesh", "{d}/hm.npy", "-o", "{d}/hm.ply", "--pixel-size", "0.5", "--scene", "{d}/hm.xml"]),
    ("mesh_render", ["render", "{d}/hm.xml", "-o", "{d}/hm.exr", "--resolution", "24", "--quiet"]),
)


def _drjit_core():
    import ctypes

    import drjit as dr

    return ctypes.CDLL(str(Path(dr.__file__).parent / "libdrjit-core.so"))


def llvm_target() -> dict:
    """The instruction set Dr.Jit's LLVM backend compiles for: CPU name, vector width, a digest
    of its feature string (read from Dr.Jit's core library; C++ symbols of its public API)."""
    import ctypes

    import drjit as dr

    dr.eval(dr.llvm.Float(0.0) + 1.0)  # the backend chooses its target when it starts
    lib = _drjit_core()
    cpu, features, width = (lib._Z19jit_llvm_target_cpuv, lib._Z24jit_llvm_target_featuresv,
                            lib._Z21jit_llvm_vector_widthv)
    cpu.restype = features.restype = ctypes.c_char_p
    width.restype = ctypes.c_uint32
    return {"cpu": cpu().decode(), "vector_width": int(width()),
            "features_sha256": hashlib.sha256(features()).hexdigest()[:16]}


def set_llvm_target(cpu: str, features: str, vector_width: int) -> None:
    """Make Dr.Jit compile for another instruction set (a subset of the host's), before any kernel
    is built: how the golden test sees another machine's rounding on this one."""
    import ctypes

    import drjit as dr

    dr.eval(dr.llvm.Float(0.0) + 1.0)
    fn = _drjit_core()._Z19jit_llvm_set_targetPKcS0_j
    fn.argtypes = [ctypes.c_char_p, ctypes.c_char_p, ctypes.c_uint32]
    fn(cpu.encode(), features.encode(), int(vector_width))


#: Another instruction set for the tolerance check (tests/test_golden.py), by the host's vector
#: width: AVX-512 hosts compile for AVX2 with 8 lanes, AVX2 hosts for AVX2 with 4 lanes (another
#: association of every reduction; AVX without AVX2 at 4 lanes makes LLVM emit a call Dr.Jit
#: cannot link).
_AVX2 = "+avx,+avx2,+fma,+f16c,+sse4.2,+sse4.1,-avx512f"
OTHER_ISA = {16: ("haswell", _AVX2, 8), 8: ("haswell", _AVX2, 4)}


def fingerprint() -> dict:
    """What decides the floating-point results bit for bit: the instruction set Dr.Jit compiles
    for, its thread count, Mitsuba, Dr.Jit, LLVM, numpy (the CPU's name is kept for reference)."""
    import drjit as dr
    import mitsuba as mi

    cpu = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        cpu = platform.processor() or cpu
    return {"cpu": cpu, "llvm_target": llvm_target(), "threads": int(dr.thread_count()),
            "mitsuba": mi.__version__, "drjit": dr.__version__,
            "llvm": ".".join(map(str, dr.detail.llvm_version())), "numpy": np.__version__,
            "variant": os.environ.get("ELO_MITSUBA_VARIANT", "llvm_ad_mono")}


def bit_identical_expected(recorded: dict, here: dict) -> bool:
    """Whether two fingerprints promise bit-identical outputs (the CPU's name does not matter)."""
    return all(recorded.get(k) == here.get(k) for k in here if k != "cpu")


def _prepare(folder: Path) -> None:
    """Inputs the cases need besides the shipped scenes: a small height map with a bump."""
    y, x = np.mgrid[-10:10, -12:12] * 0.5
    np.save(folder / "hm.npy", 0.4 * np.exp(-(x * x + y * y) / 8.0))


def _collect(folder: Path, before: set[str]) -> dict[str, np.ndarray]:
    """Arrays of the files a case wrote: EXR channels, NPY arrays, hashes of other files."""
    from elo_mitsuba.exr import read_exr

    out = {}
    for path in sorted(folder.iterdir()):
        if path.name in before or path.suffix.lower() == ".png":
            continue
        if path.suffix == ".exr":
            channels, _ = read_exr(path)
            for name, arr in channels.items():
                out[f"{path.name}:{name}"] = arr
        elif path.suffix == ".npy":
            out[path.name] = np.load(path)
        else:
            data = path.read_bytes()
            if path.suffix == ".xml":  # the generated scene names the output and install paths
                from elo_mitsuba.scene_files import scenes_dir

                data = data.replace(str(folder).encode(), b"<d>").replace(scenes_dir().as_posix().encode(), b"<s>")
            out[path.name] = np.frombuffer(hashlib.sha256(data).digest(), np.uint8)
    return out


def run_cases(folder: Path) -> dict[str, np.ndarray]:
    """Run every case in ``folder``; returns {"case/file:channel": array}."""
    from elo_mitsuba.cli import main

    _prepare(folder)
    results = {}
    for name, argv in CASES:
        before = {p.name for p in folder.iterdir()}
        rc = main([a.format(d=folder) for a in argv])
        if rc != 0:
            raise RuntimeError(f"golden case {name} exited {rc}")
        for key, arr in _collect(folder, before).items():
            results[f"{name}/{key}"] = arr
    return results


def digest(arr: np.ndarray) -> dict:
    """What is stored of one output: the SHA-256 of its bytes, its shape and dtype, its mean."""
    arr = np.ascontiguousarray(arr)
    mean = float(arr.astype(np.float64).mean()) if arr.dtype.kind == "f" else None
    return {"sha256": hashlib.sha256(arr.tobytes()).hexdigest(), "shape": list(arr.shape),
            "dtype": str(arr.dtype), "mean": mean}


def load_golden() -> tuple[dict[str, dict], dict]:
    data = json.loads(GOLDEN.read_text())
    return data["outputs"], data["fingerprint"]


def load_golden_arrays() -> dict[str, np.ndarray]:
    with np.load(GOLDEN_ARRAYS, allow_pickle=False) as z:
        return {key: z[key] for key in z.files}


#: Unit roundoff of float32, the precision every render and fit runs in.
ULP32 = 2.0 ** -24
#: Channels computed by the per-pixel fit of the corrected images (ratios to the flat plate, about
#: 1) and of slopes of order 1: their rounding is that of quantities of size 1, whatever their own
#: size (the noise-free residual, 4e-4, is a difference of two numbers near 1).
FIT_CHANNELS = ("dzdx", "dzdy", "dzdx_sigma", "dzdy_sigma", "residual", "scale", "Mx", "My", "sum_rl", "sum_bf")
#: How far an output may move on another instruction set, in float32 unit roundoffs of its
#: reference scale (its largest magnitude; at least 1 for the fit's channels). Another vector
#: width or FMA contraction re-associates the sums in the kernels (a pixel's samples, the
#: quadrature's triangles, the detectors, 400-path windows of later events): for a sum of n terms
#: of one sign the rounding error is bounded by about n u sum|x| (Higham, Accuracy and Stability
#: of Numerical Algorithms, 2nd ed., Sec. 4.2), and these sums have tens to hundreds of terms.
#: Measured between AVX-512 (16 lanes) and AVX2 (8 lanes) code on one machine
#: (``golden_cases.py --other-isa``): renders at most 63, so 256 here (1.5e-5 of the channel's
#: largest value). The fit (10 Levenberg-Marquardt steps with forward differences of step 1e-3 in
#: float32, stopping at a step of 2e-6) and the integration of its slopes amplify that: at most
#: 865 (a slope moved by 5.2e-5; heights by 167), so 4096 (2.4e-4 in slope). A change of the
#: physics or the sampling moves renders by 1e-3 and more (a different seed, a 0.1 % change of a
#: backscatter coefficient): 60x the render tolerance.
TOLERANCE_ULPS = 256.0
TOLERANCE_ULPS_FIT = 4096.0
#: A Monte Carlo path can also end otherwise on another instruction set (a ray that grazes a
#: detector disc's rim or a wall's edge hits on one and misses on the other; a sample next to a
#: table's step takes the other entry). That moves the pixels whose estimate holds the path (one
#: pixel, or the block of pixels that share their events >= 2, plugins/_geometry_classes.py) by
#: the path's share, not by a rounding. Measured between AVX-512 (Sapphire Rapids) and AVX2 code
#: on one machine: athene_default's e2 moved by 549-2394 roundoffs on one 3 x 3 block of 14 400
#: pixels (1.7e-4 of the channel's largest value), every other output within the tolerances
#: above. So up to FLIP_PIXELS pixels of an output may lie beyond its tolerance, each within
#: FLIP_BOUND of its reference scale; a change of the physics or the sampling moves every pixel.
FLIP_PIXELS = 27
FLIP_BOUND = 1e-3


def reference_scale(key: str, golden: np.ndarray) -> tuple[float, float]:
    """(scale, tolerance in ULP32 x scale) of output ``key`` (``case/file:channel``)."""
    finite = golden[np.isfinite(golden)]
    top = float(np.max(np.abs(finite), initial=0.0))
    channel = key.rsplit(":", 1)[-1]
    if channel in FIT_CHANNELS:
        return max(top, 1.0), TOLERANCE_ULPS_FIT
    if key.startswith("reconstruct"):  # heights: the integrated slopes
        return top, TOLERANCE_ULPS_FIT
    return top, TOLERANCE_ULPS


def compare(golden: dict[str, np.ndarray], results: dict[str, np.ndarray]) -> tuple[list[str], dict[str, float]]:
    """Outputs of ``results`` that are not ``golden`` within their tolerance
    (:func:`reference_scale`, but for up to :data:`FLIP_PIXELS` pixels within :data:`FLIP_BOUND`;
    integers, hashes and shapes exactly), and each float output's largest difference in units of
    ULP32 x its reference scale."""
    problems, ulps = [], {}
    for key in sorted(set(golden) | set(results)):
        if key not in golden or key not in results:
            problems.append(f"{key}: {'not written' if key in golden else 'not in the goldens'}")
            continue
        g, r = golden[key], results[key]
        if g.shape != r.shape or g.dtype != r.dtype:
            problems.append(f"{key}: {r.dtype}{list(r.shape)} instead of {g.dtype}{list(g.shape)}")
            continue
        if g.dtype.kind != "f":
            if not np.array_equal(g, r):
                problems.append(f"{key}: differs ({'a file' if g.dtype == np.uint8 else 'integers'})")
            continue
        if not np.array_equal(np.isfinite(g), np.isfinite(r)):
            problems.append(f"{key}: NaN/Inf elsewhere")
            continue
        scale, allowed = reference_scale(key, g)
        d = np.abs(g.astype(np.float64) - r)[np.isfinite(g)]
        diff = float(np.max(d, initial=0.0))
        ulps[key] = diff / (ULP32 * scale) if scale > 0 else (0.0 if diff == 0 else math.inf)
        beyond = int(np.count_nonzero(d > allowed * ULP32 * scale))
        if beyond and not (beyond <= FLIP_PIXELS and diff <= FLIP_BOUND * scale):
            problems.append(f"{key}: moved by {diff:.3g} = {ulps[key]:.3g} x {ULP32:.3g} x {scale:.3g} on "
                            f"{beyond} pixel(s) (allowed {allowed:g}, or up to {FLIP_BOUND:g} x {scale:.3g} on "
                            f"{FLIP_PIXELS}: a path ending otherwise; mean {g.mean():.6g} -> {r.mean():.6g})")
    return problems, ulps


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--update", action="store_true", help="rewrite tests/golden_cases.json and .npz")
    parser.add_argument("--digests", metavar="FILE", help="only write the digests of this run to FILE (JSON) and "
                        "its arrays beside it (FILE with .npz); tests/test_golden.py compares them")
    parser.add_argument("--other-isa", action="store_true", help="compile Dr.Jit's kernels for a narrower "
                        "instruction set than the host's (OTHER_ISA): another machine's rounding, on this one")
    args = parser.parse_args(argv)
    if not args.update and not args.digests:
        parser.error("nothing to do: pass --update to regenerate the goldens")
    if args.update and args.other_isa:
        parser.error("--update records the host's own instruction set; drop --other-isa")
    if args.other_isa:
        import elo_mitsuba

        elo_mitsuba.ensure_variant()
        width = llvm_target()["vector_width"]
        if width not in OTHER_ISA or platform.machine() not in ("x86_64", "AMD64"):
            Path(args.digests).write_text(json.dumps({"skipped": f"no narrower x86-64 instruction set known for "
                                                      f"{platform.machine()} with {width} lanes"}))
            return 0
        set_llvm_target(*OTHER_ISA[width])
    with tempfile.TemporaryDirectory() as tmp:
        results = run_cases(Path(tmp))
    outputs = {key: digest(arr) for key, arr in results.items()}
    record = json.dumps({"fingerprint": fingerprint(), "outputs": outputs}, indent=1) + "\n"
    target, arrays = (Path(args.digests), Path(args.digests).with_suffix(".npz")) if args.digests else \
        (GOLDEN, GOLDEN_ARRAYS)
    np.savez_compressed(arrays, **results)
    target.write_text(record)
    if args.update:
        print(f"wrote {GOLDEN} and {GOLDEN_ARRAYS.name} ({len(outputs)} outputs)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
