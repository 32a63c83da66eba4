"""Dr.Jit arrays from numpy arrays, in memory aligned to 64 bytes, so that a kernel compiles once.

On the LLVM backend Dr.Jit maps a numpy array's memory instead of copying it, and writes the
pointer's alignment into the kernel (64 bytes or 1): the same computation on arrays that numpy
happened to place differently is a different kernel, compiled again. The inversion's model passes
a dozen fresh arrays per evaluation, so nearly every evaluation missed the kernel cache: measured on
a 25 x 25 window (the rough layer's, 0.27 mm beam, shadows on, AMD EPYC), an evaluation with
derivatives took 0.43-0.45 s, five kernels built each time (57-142 ms each) for 625 lanes of work.
Copied into aligned memory first, every evaluation after the first reuses the kernels.

Examples
--------
>>> a = aligned(np.arange(5.0)[1:], np.float32)
>>> a.ctypes.data % ALIGNMENT, a.dtype.name, a.tolist()
(0, 'float32', [1.0, 2.0, 3.0, 4.0])
"""

from __future__ import annotations

import numpy as np

#: Bytes: the alignment Dr.Jit writes into a kernel for memory it maps when the pointer allows.
ALIGNMENT = 64


def aligned(a, dtype) -> np.ndarray:
    """A flat copy of ``a`` as ``dtype``, starting on an :data:`ALIGNMENT`-byte boundary."""
    a = np.asarray(a)
    dtype = np.dtype(dtype)
    size = a.size
    buffer = np.empty(size * dtype.itemsize + ALIGNMENT, np.uint8)
    start = -buffer.ctypes.data % ALIGNMENT
    out = buffer[start:start + size * dtype.itemsize].view(dtype)
    out[...] = a.reshape(-1)
    return out


def floats(mi, a):
    """``mi.Float`` of ``a`` (any shape, flattened in C order) from aligned memory."""
    return mi.Float(aligned(a, np.float32))


def bools(mi, a):
    """``mi.Bool`` of ``a`` (any shape, flattened in C order) from aligned memory."""
    return mi.Bool(aligned(a, bool))
