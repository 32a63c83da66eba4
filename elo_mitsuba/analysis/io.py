"""Reading detector images and writing gradient / height results (EXR, TIFF, NPY).

Arrays keep the package orientation (row 0 = +y edge, columns towards +x). Recorded machine
images must be stored the same way; :func:`read_image` does not flip anything.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np

from ..constants import DETECTOR_NAMES
from ..errors import EloInputError
from ..exr import read_exr, write_exr

IMAGE_SUFFIXES = (".exr", ".tif", ".tiff", ".npy")
HEIGHT_SUFFIXES = (".exr", ".npy", ".tif", ".tiff")


def read_image(path, channel: str | None = None) -> tuple[np.ndarray, dict]:
    """One 2-D image (float64) and the EXR metadata (empty for TIFF/NPY).

    An EXR must hold exactly one channel unless ``channel`` names one; a TIFF/NPY must be 2-D
    (singleton dimensions are dropped).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in IMAGE_SUFFIXES:
        raise EloInputError(f"{path}: unsupported image type {suffix or '(none)'}; use {', '.join(IMAGE_SUFFIXES)}")
    if not path.is_file():
        raise EloInputError(f"{path}: no such file")
    meta: dict = {}
    if suffix == ".exr":
        channels, meta = read_exr(path)
        if channel is None:
            if len(channels) != 1:
                raise EloInputError(f"{path}: holds channels {', '.join(sorted(channels))}; expected exactly one")
            arr = next(iter(channels.values()))
        elif channel in channels:
            arr = channels[channel]
        else:
            raise EloInputError(f"{path}: no channel {channel!r}; it has {', '.join(sorted(channels))}")
    elif suffix == ".npy":
        try:
            arr = np.load(path, allow_pickle=False)
        except Exception as exc:  # numpy raises ValueError/OSError with long messages
            raise EloInputError(f"{path}: not a readable .npy array ({str(exc).splitlines()[0]})") from None
    else:
        import tifffile

        try:
            arr = tifffile.imread(path)
        except Exception as exc:
            raise EloInputError(f"{path}: not a readable TIFF ({str(exc).splitlines()[0]})") from None
    arr = np.squeeze(np.asarray(arr))
    if arr.ndim != 2 or not np.issubdtype(arr.dtype, np.number):
        raise EloInputError(f"{path}: expected one 2-D numeric image, got shape {arr.shape} ({arr.dtype})")
    return arr.astype(float), meta


def read_detector_exr(path, event: int | None = None) -> tuple[dict[str, np.ndarray], dict]:
    """The four detector images of a forward-model EXR (channels ``right`` ... or ``right.e<K>``)."""
    channels, meta = read_exr(path)
    names = {n: n if event is None else f"{n}.e{int(event)}" for n in DETECTOR_NAMES}
    missing = [c for c in names.values() if c not in channels]
    if missing:
        raise EloInputError(
            f"{path}: missing channel(s) {', '.join(missing)}; it has {', '.join(sorted(channels)) or 'none'}"
        )
    return {n: channels[c].astype(float) for n, c in names.items()}, meta


def check_output_path(path, suffixes, overwrite: bool) -> Path:
    """Refuse an unsupported suffix, a missing directory, or an existing file without overwrite."""
    path = Path(path)
    if path.suffix.lower() not in suffixes:
        raise EloInputError(f"{path}: output type must be one of {', '.join(suffixes)}")
    if path.exists() and not overwrite:
        raise EloInputError(f"{path} exists; pass --overwrite to replace it")
    if not path.parent.exists():
        raise EloInputError(f"{path}: directory {path.parent} does not exist")
    return path


def write_height(path, height, mask=None, metadata: Mapping | None = None, overwrite: bool = False) -> Path:
    """Write a height map (mm) by suffix.

    ``.exr``: channels ``height`` and ``mask`` (1 = no height measured) and the metadata;
    ``.npy``: the float64 height array; ``.tif``: float32. NPY/TIFF carry no mask: masked pixels
    hold 0 there (use EXR to keep the mask).
    """
    path = check_output_path(path, HEIGHT_SUFFIXES, overwrite)
    height = np.asarray(height, dtype=float)
    if not np.all(np.isfinite(height)):
        raise EloInputError(f"{path}: height holds NaN or Inf; refusing to write it")
    mask = np.zeros(height.shape, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    suffix = path.suffix.lower()
    if suffix == ".exr":
        write_exr(path, {"height": height, "mask": mask.astype(np.float32)}, dict(metadata or {}),
                  overwrite=overwrite)
    elif suffix == ".npy":
        np.save(path, height)
    else:
        import tifffile

        tifffile.imwrite(path, height.astype(np.float32))
    return path
