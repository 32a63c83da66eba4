"""Output files: the one guard checked before any work starts, and the one atomic write.

Every file the package writes (EXR, PNG, NPY, TIFF, PLY, XML, reports) goes through
:func:`check_output` before the work that produces it begins, so that a bad path costs nothing,
and through :func:`atomic_write`, so that a failure never leaves a partial file and never
destroys an existing one.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable, Iterable

from .errors import EloInputError


def check_output(path, suffixes: Iterable[str] | None = None, *, overwrite: bool = False,
                 what: str = "output") -> Path:
    """Return ``path`` as a :class:`~pathlib.Path`, or raise :class:`EloInputError` (one line).

    Parameters
    ----------
    path : str or Path
        The file to be written.
    suffixes : iterable of str, optional
        Allowed suffixes, lower case with the dot (``(".exr",)``); None allows any.
    overwrite : bool
        Whether an existing file may be replaced (CLI: ``--overwrite``).
    what : str
        How the message names the file (``"output"``, ``"preview"``, ``"--scene"``, ...).

    Raises
    ------
    EloInputError
        For a suffix not in ``suffixes``, an existing file without ``overwrite``, a path that is
        a folder, or a parent folder that does not exist or is a file.
    """
    path = Path(path)
    if suffixes is not None:
        suffixes = tuple(suffixes)
        if path.suffix.lower() not in suffixes:
            raise EloInputError(f"{what} {path}: must end in {' or '.join(suffixes)}")
    if path.is_dir():
        raise EloInputError(f"{what} {path} is a folder; give a file name")
    if path.exists() and not overwrite:
        raise EloInputError(f"{what} {path} exists; pass --overwrite (Python: overwrite=True) to replace it")
    parent = path.parent
    if not parent.exists():
        raise EloInputError(f"{what} {path}: directory {parent} does not exist")
    if not parent.is_dir():
        raise EloInputError(f"{what} {path}: {parent} is a file, not a directory")
    return path


def atomic_write(path, write: Callable[[Path], None]) -> Path:
    """Call ``write(tmp)`` on a temporary file beside ``path``, then rename it onto ``path``.

    The temporary file keeps the suffix (writers such as OpenEXR and matplotlib choose the format
    by it) and is removed whatever happens, so ``path`` either holds the complete new file or
    is left as it was.
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.partial-{os.getpid()}{path.suffix}")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path
