"""Output files: the one guard checked before any work starts, and the one atomic write.

Every file the package writes (EXR, PNG, NPY, TIFF, PLY, XML, reports) goes through
:func:`check_output` before the work that produces it begins, so that a bad path costs nothing,
and through :func:`atomic_write`, so that a failure never leaves a partial file and never
destroys an existing one.
"""

from __future__ import annotations

import errno
import os
import stat
import tempfile
from pathlib import Path
from typing import Callable, Iterable

from .errors import EloInputError


def check_output(path, suffixes: Iterable[str] | None = None, *, overwrite: bool = False,
                 what: str = "output", inputs: Iterable = ()) -> Path:
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
    inputs : iterable of str or Path
        The files the command reads: the output may not be one of them, even with ``overwrite``
        (the command would replace what it is reading, and the user's data would be lost).

    Raises
    ------
    EloInputError
        For a suffix not in ``suffixes``, one of ``inputs``, an existing file (or a symbolic link,
        even a dangling one) without ``overwrite``, a path that is a folder, a parent folder that does
        not exist, is a file or cannot be written (read-only, immutable, ``/proc``:
        :func:`check_writable_folder`), or, with ``overwrite``, an existing
        file that cannot be replaced (immutable or append-only).
    """
    if not (isinstance(overwrite, bool) or type(overwrite).__name__ == "bool_"):  # 'no' or 1 would read as consent
        raise EloInputError(f"overwrite={overwrite!r}: must be True or False")
    if not str(path).strip():
        raise EloInputError(f"{what}: the path is empty; give a file name")
    if "\x00" in str(path):  # C libraries cut the name there and write to another file
        raise EloInputError(f"{what} {str(path)!r}: a path cannot hold a NUL character")
    path = Path(path)
    if suffixes is not None:
        suffixes = tuple(suffixes)
        if path.suffix.lower() not in suffixes:
            raise EloInputError(f"{what} {path}: must end in {' or '.join(suffixes)}")
    if path.is_dir():
        raise EloInputError(f"{what} {path} is a folder; give a file name")
    if path.exists():
        for source in inputs:
            if source is not None and Path(source).exists() and path.samefile(source):
                raise EloInputError(f"{what} {path} is also an input of this command; write to another file "
                                    "(--overwrite does not replace what is being read)")
    if path.exists() and not overwrite:
        raise EloInputError(f"{what} {path} exists; pass --overwrite (Python: overwrite=True) to replace it")
    if path.is_symlink() and not path.exists() and not overwrite:  # exists() follows the link: False when dangling
        raise EloInputError(f"{what} {path} exists (a symbolic link to {os.readlink(path)!r}, which does not exist); "
                            "pass --overwrite (Python: overwrite=True) to replace the link")
    check_parent_folder(path, what)
    if path.exists():
        _check_replaceable(path, what)
    return path


def check_parent_folder(path, what: str = "output") -> Path:
    """Refuse (one line, naming ``what`` and ``path``) an output whose folder does not exist, is a
    file, or takes no new files (:func:`check_writable_folder`); return that folder. The one check
    of an output's folder, for single files (:func:`check_output`) and stores (folders) alike.

    Examples
    --------
    >>> check_parent_folder("/no/such/folder/out.zarr")
    Traceback (most recent call last):
    ...
    elo_mitsuba.errors.EloInputError: output /no/such/folder/out.zarr: directory /no/such/folder does not exist
    """
    path = Path(path)
    parent = path.parent
    if not parent.exists():
        raise EloInputError(f"{what} {path}: directory {parent} does not exist")
    if not parent.is_dir():
        raise EloInputError(f"{what} {path}: {parent} is a file, not a directory")
    return check_writable_folder(parent, f"{what} {path}")


def check_writable_folder(folder, what: str) -> Path:
    """Refuse (one line, naming ``what``) an existing folder in which no file can be created: not
    writable for this user, read-only or immutable (``chattr +i``), or a virtual file system such
    as ``/proc``. Root ignores permission bits, so the test is an actual probe: a temporary file
    is created in ``folder`` and removed at once (nothing else is touched)."""
    folder = Path(folder)
    try:
        fd, probe = tempfile.mkstemp(prefix=".elo-mitsuba-probe-", dir=folder)
    except OSError as exc:
        reason = _flag_reason(folder) or ("the folder does not take new files" if exc.errno == errno.ENOENT
                                          else f"{exc.strerror or exc}".lower())
        raise EloInputError(f"{what}: cannot write in folder {folder} ({reason}); "
                            "choose a folder you can write to") from None
    os.close(fd)
    os.unlink(probe)
    return folder


#: Linux inode flags (``chattr``) under which nothing in a folder, or a file itself, can be
#: created, renamed or replaced: immutable, append-only (ioctl FS_IOC_GETFLAGS).
_FS_IOC_GETFLAGS = 0x80086601
_FLAGS = {0x00000010: "immutable (chattr +i)", 0x00000020: "append-only (chattr +a)"}


def _flag_reason(path: Path) -> str | None:
    """"immutable (chattr +i)" or "append-only (chattr +a)" where ``path`` carries that flag; None
    otherwise, and where the system or file system has no such flags."""
    try:
        import fcntl
        import struct

        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
        try:
            flags = struct.unpack("l", fcntl.ioctl(fd, _FS_IOC_GETFLAGS, struct.pack("l", 0)))[0]
        finally:
            os.close(fd)
    except (OSError, ImportError):
        return None
    return next((text for bit, text in _FLAGS.items() if flags & bit), None)


def _check_replaceable(path: Path, what: str) -> None:
    """Refuse an existing file that ``os.replace`` could not replace: immutable or append-only
    (Linux inode flags), or in a sticky folder (``/tmp``) and owned by another user."""
    reason = _flag_reason(path)
    if reason is None and os.geteuid() != 0:
        parent, own = path.parent.stat(), path.stat()
        if parent.st_mode & stat.S_ISVTX and os.geteuid() not in (own.st_uid, parent.st_uid):
            reason = "owned by another user in a sticky folder"
    if reason is not None:
        raise EloInputError(f"{what} {path} is {reason} and cannot be replaced, even with --overwrite; "
                            "choose another name")


def atomic_write(path, write: Callable[[Path], None]) -> Path:
    """Call ``write(tmp)`` on a temporary file beside ``path``, then rename it onto ``path``.

    The temporary file keeps the suffix (writers such as OpenEXR and matplotlib choose the format
    by it) and is removed whatever happens, so ``path`` either holds the complete new file or
    is left as it was.
    """
    path = Path(path)
    # the suffix in lower case: writers test it case-sensitively (np.save appended ".npy" to ".NPY",
    # so the rename found no file and a stray one was left)
    tmp = path.with_name(f".{path.name}.partial-{os.getpid()}{path.suffix.lower()}")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path
