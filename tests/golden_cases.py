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
import os
import platform
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
GOLDEN = HERE / "golden_cases.json"

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


def fingerprint() -> dict:
    """What decides the floating-point results: CPU model, Mitsuba, Dr.Jit, LLVM, numpy."""
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
    return {"cpu": cpu, "mitsuba": mi.__version__, "drjit": dr.__version__,
            "llvm": ".".join(map(str, dr.detail.llvm_version())), "numpy": np.__version__,
            "variant": os.environ.get("ELO_MITSUBA_VARIANT", "llvm_ad_mono")}


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


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--update", action="store_true", help="rewrite tests/golden_cases.json")
    parser.add_argument("--digests", metavar="FILE", help="only write the digests of this run to FILE (JSON; "
                        "tests/test_golden.py compares them, the run started by conftest.py beside the other tests)")
    args = parser.parse_args(argv)
    if not args.update and not args.digests:
        parser.error("nothing to do: pass --update to regenerate the goldens")
    with tempfile.TemporaryDirectory() as tmp:
        results = run_cases(Path(tmp))
    outputs = {key: digest(arr) for key, arr in results.items()}
    if args.digests:
        Path(args.digests).write_text(json.dumps({"fingerprint": fingerprint(), "outputs": outputs}, indent=1) + "\n")
        return 0
    GOLDEN.write_text(json.dumps({"fingerprint": fingerprint(), "outputs": outputs}, indent=1) + "\n")
    print(f"wrote {GOLDEN} ({len(outputs)} outputs)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
