"""Choosing the Mitsuba variant safely and registering our plugins.

Debian 12's default LLVM (15/16) makes Mitsuba's llvm variants abort the whole process (SIGABRT)
on the first float min/max; LLVM 14 is refused as too old. We therefore ask Dr.Jit which LLVM it
found *before* setting an llvm variant and stop with one actionable line instead of an abort.

The variant is chosen, in this order, by the ``variant`` argument, the environment variable
``ELO_MITSUBA_VARIANT``, and ``llvm_ad_mono``. ``cuda_ad_mono`` runs on NVIDIA GPUs.
Our plugins (``elo_bse``, ``elo_beam``, ``elo``) are registered whenever a supported variant
becomes active, whichever of ``import elo_mitsuba`` and ``mi.set_variant`` comes first.
"""

from __future__ import annotations

import os
import sys
import tempfile

from .constants import DEFAULT_VARIANT, MIN_LLVM_MAJOR, SUPPORTED_VARIANTS, VARIANT_ENV_VAR
from .errors import EloEnvironmentError, EloInputError

_registered_for: set[str] = set()
_callback_installed = False
#: What Dr.Jit printed on stderr while it was imported (kept for diagnosis; see import_backend).
backend_import_log = ""

LLVM_ADVICE = (
    "install Debian's libllvm19 (apt-get install -y libllvm19) or point DRJIT_LIBLLVM_PATH at a "
    f"libLLVM.so of version >= {MIN_LLVM_MAJOR}"
)


def import_backend() -> None:
    """Import Dr.Jit and Mitsuba, holding back what Dr.Jit prints while it looks for LLVM.

    With a missing or broken LLVM, Dr.Jit writes several lines of its own to file descriptor 2
    on import; our one actionable line (:func:`check_llvm`) replaces them. When LLVM is usable
    the captured text (normally nothing) is passed on to stderr unchanged.
    """
    global backend_import_log
    if "mitsuba" in sys.modules:
        return
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):  # no real fd 2 (embedded interpreters)
        import drjit  # noqa: F401
        import mitsuba  # noqa: F401
        return
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            import drjit
            import mitsuba  # noqa: F401

            version = tuple(drjit.detail.llvm_version())
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        tmp.seek(0)
        backend_import_log = tmp.read().decode(errors="replace")
    if backend_import_log and version[0] >= MIN_LLVM_MAJOR:
        sys.stderr.write(backend_import_log)


def llvm_version() -> tuple[int, int, int]:
    """The LLVM version Dr.Jit loaded, (-1, -1, -1) if none could be used."""
    import drjit as dr

    return tuple(dr.detail.llvm_version())


def check_llvm() -> None:
    """Raise :class:`EloEnvironmentError` (one line) unless a usable LLVM >= 17 was found."""
    version = llvm_version()
    where = os.environ.get("DRJIT_LIBLLVM_PATH")
    origin = f" (DRJIT_LIBLLVM_PATH={where})" if where else ""
    if version[0] < 0:
        raise EloEnvironmentError(
            f"Dr.Jit found no usable LLVM library{origin}; {LLVM_ADVICE}, or use "
            "--variant cuda_ad_mono on an NVIDIA GPU"
        )
    if version[0] < MIN_LLVM_MAJOR:
        raise EloEnvironmentError(
            f"Dr.Jit loaded LLVM {'.'.join(map(str, version))}{origin}, which aborts Mitsuba's llvm "
            f"variants; {LLVM_ADVICE}"
        )


def check_cuda() -> None:
    import drjit as dr

    if not dr.has_backend(dr.JitBackend.CUDA):
        raise EloEnvironmentError(
            "variant cuda_ad_mono needs an NVIDIA GPU with a CUDA driver, and none was found; "
            "use --variant llvm_ad_mono"
        )


def resolve_variant(variant: str | None = None) -> str:
    """The variant to use: argument, else $ELO_MITSUBA_VARIANT, else llvm_ad_mono."""
    name = variant or os.environ.get(VARIANT_ENV_VAR) or DEFAULT_VARIANT
    if name not in SUPPORTED_VARIANTS:
        source = "variant" if variant else f"${VARIANT_ENV_VAR}"
        raise EloInputError(
            f"{source} {name!r} is not supported; choose one of {', '.join(SUPPORTED_VARIANTS)}"
        )
    return name


def ensure_variant(variant: str | None = None):
    """Check the environment, set the Mitsuba variant and register our plugins; return ``mi``.

    If a supported variant is already active and no variant is requested, it is kept.

    Parameters
    ----------
    variant : str, optional
        ``llvm_ad_mono`` or ``cuda_ad_mono``; None: ``$ELO_MITSUBA_VARIANT`` if set, else the
        active supported variant, else the default of :func:`resolve_variant`.

    Returns
    -------
    module
        The ``mitsuba`` module, with the variant set and the plugins registered.

    Raises
    ------
    EloEnvironmentError
        The machine cannot run the variant (LLVM missing or too old, no CUDA).

    Examples
    --------
    >>> import elo_mitsuba as em
    >>> mi = em.ensure_variant()
    >>> mi.variant() in ("llvm_ad_mono", "cuda_ad_mono")
    True
    """
    import_backend()  # first import (the CLI defers it to here): Dr.Jit's LLVM noise held back
    import mitsuba as mi

    current = mi.variant()
    if variant is None and current in SUPPORTED_VARIANTS and not os.environ.get(VARIANT_ENV_VAR):
        name = current
    else:
        name = resolve_variant(variant)
    if name.startswith("llvm"):
        check_llvm()
    else:
        check_cuda()
    install_variant_callback()
    if mi.variant() != name:
        mi.set_variant(name)
    register_plugins()
    return mi


def register_plugins() -> None:
    """Register our plugins for the active variant (idempotent)."""
    import mitsuba as mi

    name = mi.variant()
    if name in SUPPORTED_VARIANTS:
        _register(name)


def _on_variant_change(old, new) -> None:
    if new in SUPPORTED_VARIANTS:
        _register(new)


def install_variant_callback() -> None:
    """Register our plugins automatically whenever the user switches to a supported variant."""
    global _callback_installed
    if _callback_installed:
        return
    import mitsuba as mi

    mi.detail.add_variant_callback(_on_variant_change)
    _callback_installed = True


def _register(name: str) -> None:
    if name in _registered_for:
        return
    from . import plugins

    plugins.register_all()
    _registered_for.add(name)


#: glibc's mallopt parameters (malloc.h).
_M_TRIM_THRESHOLD, _M_MMAP_MAX = -1, -4


def keep_freed_memory() -> bool:
    """Let glibc's malloc keep freed memory for reuse instead of handing it back to the system.

    By default glibc serves large blocks (above a threshold of at most 32 MB) by ``mmap`` and
    returns them on ``free``, and trims the heap's free top; each new image-sized numpy array is
    then fresh memory, which the kernel must fault in page by page (about 2 s/GB on the virtual
    machines we measured). In a sweep worker, which renders, measures and writes images point
    after point, that cost 31 % more CPU per point than a plain render loop at 1024^2
    (benchmarks/RESULTS.md, section "Design sweeps"). With every block from the heap and no
    trimming, freed memory is reused: the worker's resident set stays at its peak instead.
    Returns whether it applied (glibc only; elsewhere nothing changes)."""
    import ctypes

    try:
        libc = ctypes.CDLL("libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    return bool(mallopt(_M_MMAP_MAX, 0)) and bool(mallopt(_M_TRIM_THRESHOLD, 2**31 - 1))
