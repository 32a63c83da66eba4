"""Multichannel EXR files with the scan geometry in the header.

Channels are float32 images named by detector id (``right``, ``left``, ``back``, ``front``, ...)
with per-event channels ``<id>.e<k>`` (EXR layers), or by quantity (``dzdx``, ``Mx``, ``mask``, ...).
The metadata dictionary is stored as JSON in the header attribute ``elo_mitsuba`` and, for the
most used scalars, also as plain attributes readable by any EXR viewer.

Arrays are stored in the package's image orientation (:mod:`elo_mitsuba.grid`), recorded in
every header as ``orientation``.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import sys
from pathlib import Path
from typing import Mapping

import numpy as np

from .arguments import input_file, real_array, shown
from .errors import EloInputError
from .files import atomic_write, check_output
from .grid import ORIENTATION
from .schema import check_header

METADATA_ATTRIBUTE = "elo_mitsuba"
#: Why EXRs are written uncompressed (measured on 2 cores, the 12 channels of athene_flat at
#: 1500^2, events 1 + 2; every option lossless): none 0.15-0.45 s, 108 MB; RLE 1.2 s, 108 MB;
#: PIZ 3 s, 64 MB; ZIP (used before) 2.4-6.5 s, 87 MB; ZSTD 2.4 s, 29 MB but unreadable by OpenEXR
#: before 3.4. Float images of Monte Carlo noise barely compress: ZIP saved 20 % of the size for
#: 15x the time of the write. Any EXR reader reads these files.
COMPRESSION_NOTE = "uncompressed: ZIP saved 20 % of the size for 15x the write time"
_PLAIN_ATTRIBUTES = ("units", "events", "spp", "material", "work_distance_mm")


def write_exr(path, channels: Mapping[str, np.ndarray], metadata: Mapping | None = None,
              overwrite: bool = False) -> Path:
    """Write float32 channels and metadata to ``path``.

    Refuses NaN/Inf (names the channel) and an existing file unless ``overwrite``. The file is
    written to a temporary name first and renamed, so a failure never leaves a partial result.

    Parameters
    ----------
    path : str or Path
        The EXR file.
    channels : mapping of str to ndarray (H, W)
        Images of one shape (stored as float32), e.g. detector images in N_d/N_0.
    metadata : mapping, optional
        JSON-serialisable header (geometry in mm, units, ...).
    overwrite : bool
        Replace an existing file.

    Returns
    -------
    Path
        The file written.

    Raises
    ------
    EloInputError
        A path not ending in ``.exr``, no channels, channels that are not 2-D images of one
        shape, NaN/Inf in a channel, or an existing file without ``overwrite``.

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> import numpy as np
    >>> from elo_mitsuba.errors import EloInputError
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     path = write_exr(Path(folder) / "a.exr", {"left": np.zeros((2, 2))}, {"units": "N_d/N_0"})
    ...     try:
    ...         write_exr(path, {"left": np.zeros((2, 2))})
    ...     except EloInputError:
    ...         print("refused: the file exists")
    ...     path = write_exr(path, {"left": np.ones((2, 2))}, overwrite=True)
    ...     print(path.name, read_exr(path)[0]["left"].tolist())
    refused: the file exists
    a.exr [[1.0, 1.0], [1.0, 1.0]]
    """
    import OpenEXR

    if not isinstance(path, (str, os.PathLike)):
        raise EloInputError(f"EXR path {path!r} ({type(path).__name__}): give a file name ending in .exr")
    path = check_output(path, (".exr",), overwrite=overwrite)
    if not isinstance(channels, Mapping):
        raise EloInputError(f"{path}: channels {shown(channels)}: give a mapping {{channel name: 2-D image}}")
    if not channels:
        raise EloInputError(f"{path}: no channels to write")
    for name in channels:
        if not isinstance(name, str) or not name or "\0" in name:
            raise EloInputError(f"{path}: channel name {name!r}: need a non-empty text")
    shapes = {np.shape(v) for v in channels.values()}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2 or 0 in next(iter(shapes)):
        raise EloInputError(f"{path}: channels must be 2-D images of one shape with pixels, got {sorted(shapes)}")
    if metadata is not None and not isinstance(metadata, Mapping):
        raise EloInputError(f"{path}: metadata {shown(metadata)}: give a mapping (the header's JSON object)")
    data = {}
    for name, img in channels.items():
        raw = np.asarray(img)
        raw = raw.astype(np.float32) if raw.dtype == bool else raw  # a mask: 1 = True
        arr = np.ascontiguousarray(real_array(f"{path}: channel {name!r}", raw).astype(np.float32))
        if not np.all(np.isfinite(arr)):
            raise EloInputError(f"{path}: channel {name!r} holds NaN or Inf; refusing to write it")
        data[name] = arr
    meta = dict(metadata or {})
    meta.setdefault("orientation", ORIENTATION)
    header = {
        "compression": OpenEXR.NO_COMPRESSION,  # see COMPRESSION_NOTE
        "type": OpenEXR.scanlineimage,
        METADATA_ATTRIBUTE: metadata_json(path, meta),
    }
    for key in _PLAIN_ATTRIBUTES:
        if key in meta and isinstance(meta[key], (int, float, str)) and not isinstance(meta[key], bool):
            header[key] = meta[key] if not isinstance(meta[key], int) else int(meta[key])

    def write(tmp):
        with OpenEXR.File(header, data) as f:
            f.write(str(tmp))

    return atomic_write(path, write)


def read_exr(path) -> tuple[dict[str, np.ndarray], dict]:
    """Read all channels (float32 arrays) and the metadata dict (empty if not ours).

    Parameters
    ----------
    path : str or Path
        An EXR file.

    Returns
    -------
    channels : dict of str to ndarray (H, W)
        float32 images by channel name.
    metadata : dict
        The JSON header elo-mitsuba wrote (``{}`` for another EXR).

    Raises
    ------
    EloInputError
        A missing or unreadable file.

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> import numpy as np
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     path = write_exr(Path(folder) / "a.exr", {"right": np.full((2, 3), 0.5)}, {"field_mm": [3.0, 2.0]})
    ...     channels, meta = read_exr(path)
    >>> channels["right"].dtype, channels["right"].shape, meta["field_mm"]
    (dtype('float32'), (2, 3), [3.0, 2.0])
    """
    import OpenEXR

    if not isinstance(path, (str, os.PathLike)) or "\0" in str(path):
        raise EloInputError(f"EXR path {shown(path)}: give a file name")
    path = input_file(path)
    with open(path, "rb") as f:
        magic = f.read(4)
    if magic != EXR_MAGIC:
        raise EloInputError(f"{path}: not a readable EXR file (it does not start with the EXR magic number)")
    with _library_output() as said:
        try:
            with OpenEXR.File(str(path), separate_channels=True) as f:
                header = dict(f.header())  # the File clears its own dict on close
                channels = {name: np.array(ch.pixels, dtype=np.float32) for name, ch in f.channels().items()}
            error = None
        except Exception as exc:  # OpenEXR raises plain Exceptions with long messages
            error = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    if error is not None:
        # the C library's own report (what it printed) names the damage better than the binding's
        # exception ("file has 0 parts" for a file cut short in its pixel data)
        detail = next((line for line in said() if "EXR_ERR" in line or "corrupt" in line.lower()), None)
        reason = (f"truncated or corrupt: {detail.split(': ', 1)[-1]}" if detail else error)
        raise EloInputError(f"{path}: not a readable EXR file ({reason})")
    meta = {}
    if METADATA_ATTRIBUTE in header:
        try:
            meta = json.loads(header[METADATA_ATTRIBUTE])
        except (TypeError, ValueError, OverflowError):
            raise EloInputError(f"{path}: header attribute {METADATA_ATTRIBUTE!r} is not valid JSON") from None
        if not isinstance(meta, dict):
            raise EloInputError(f"{path}: header attribute {METADATA_ATTRIBUTE!r} holds a JSON "
                                f"{type(meta).__name__}, not an object (name: value, as elo-mitsuba writes it)")
        check_header(meta, str(path))
    return channels, meta


#: The first four bytes of every OpenEXR file.
EXR_MAGIC = bytes((0x76, 0x2F, 0x31, 0x01))


@contextlib.contextmanager
def _library_output():
    """Hold what the OpenEXR library prints on the process's stdout and stderr (file
    descriptors 1 and 2: it reports a damaged file there, then raises) instead of showing it;
    yields a function returning those lines."""
    import ctypes
    import tempfile

    lines: list[str] = []
    try:
        sys.stdout.flush()
        sys.stderr.flush()
        saved = (os.dup(1), os.dup(2))
    except (OSError, ValueError, AttributeError):  # no real descriptors (embedded): nothing to hold
        yield lambda: lines
        return
    libc = ctypes.CDLL(None)
    held = io.StringIO()  # what the binding prints through Python's sys.stdout/sys.stderr
    with tempfile.TemporaryFile() as sink:
        try:
            os.dup2(sink.fileno(), 1)
            os.dup2(sink.fileno(), 2)
            with contextlib.redirect_stdout(held), contextlib.redirect_stderr(held):
                yield lambda: lines
        finally:
            libc.fflush(None)  # C and C++ streams buffered on the way to the descriptors
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])
            sink.seek(0)
            lines.extend(sink.read().decode("utf-8", "replace").splitlines() + held.getvalue().splitlines())


def metadata_json(path, meta) -> str:
    """The header as strict JSON: NaN or Inf in the geometry is a defect to refuse, not to store."""
    try:
        return json.dumps(meta, default=_json_default, allow_nan=False)
    except TypeError as exc:  # an object JSON cannot hold
        raise EloInputError(f"{path}: {exc}; metadata values must be numbers, text, lists or mappings") from None
    except ValueError:
        where = _first_non_finite(meta)
        raise EloInputError(f"{path}: the metadata holds NaN or Inf{f' at {where}' if where else ''}; "
                            "refusing to write it") from None


def _first_non_finite(value, where: str = "") -> str | None:
    """Where (``thresholds.min_corrected``, ``detectors.right.center[2]``) a metadata value is
    NaN or Inf, or None."""
    if isinstance(value, Mapping):
        items = ((f"{where}.{k}" if where else str(k), v) for k, v in value.items())
    elif isinstance(value, (list, tuple, np.ndarray)):
        items = ((f"{where}[{i}]", v) for i, v in enumerate(np.asarray(value).tolist() if isinstance(value, np.ndarray)
                                                            else value))
    else:
        try:
            return None if math.isfinite(value) else where
        except TypeError:
            return None
    for key, v in items:
        found = _first_non_finite(v, key)
        if found is not None:
            return found
    return None


def _json_default(obj):
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    raise TypeError(f"cannot store {type(obj).__name__} in EXR metadata")
