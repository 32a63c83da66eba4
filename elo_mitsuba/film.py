"""Channel planes of a film: its raw storage developed into contiguous planes, and back.

Mitsuba's film keeps the accumulated samples interleaved (pixel-major: R, G, B, weight, then the
AOVs); numpy work on a channel wants it contiguous. :func:`raw_planes` develops the channels
(value / weight, as Mitsuba's ``hdrfilm`` does, bit for bit) straight from the raw storage into
planes, in one blocked Dr.Jit kernel: a block of :data:`PLANE_BLOCK` pixels is read channel by
channel while its floats stay in the cache. Going through Mitsuba's own develop would first make
a developed interleaved copy of the whole film (plus its index arrays, ~280 MB at 1500^2 x 15
channels), and a new process pays about 2 s/GB to touch fresh pages on the machines we measured
(benchmarks/RESULTS.md, section ``targets``). The planes live in a Dr.Jit buffer (taken from its
cache of freed blocks) of which ``np.asarray`` is a writable view on the CPU (on a GPU, one
transfer). :func:`film_tensor` builds the developed H x W x C tensor from planes, for callers of
``mi.render``.
"""

from __future__ import annotations

import numpy as np

#: Pixels per block: a block's channels (512 x ~20 floats) stay in the cache while they are moved.
PLANE_BLOCK = 512


def _order(dr, index_t, pixels: int, count: int):
    """(plane, pixel) of each lane: blocks of PLANE_BLOCK pixels, channel by channel in a block."""
    block = PLANE_BLOCK
    i = dr.arange(index_t, count * ((pixels + block - 1) // block) * block)
    rem = i % (block * count)
    return rem // block, (i // (block * count)) * block + rem % block


def raw_planes(raw, columns, weight_column: int | None = 3):
    """Developed channels ``columns`` of a film's raw storage, as planes.

    Parameters
    ----------
    raw : TensorXf (H, W, C)
        ``film.develop(raw=True)``: the accumulated values with the sample weight in column
        ``weight_column`` (None: take the values as they are).
    columns : list of int or None
        Columns to develop, in the order of the planes; None: a plane the caller fills itself
        (left as the buffer's memory holds it: not developed, not cleared).

    Returns
    -------
    planes : ndarray, float32, (len(columns), H, W)
        ``value / weight`` (``value`` where the weight is 0), a writable view of ``buffer``
        on the CPU.
    buffer : Dr.Jit array
        The flat buffer behind ``planes``.
    """
    import drjit as dr

    h, w, c = (int(n) for n in raw.shape)
    flat = raw.array
    index_t = dr.uint32_array_t(type(flat))
    count, pixels = len(columns), h * w
    developed = [i for i, col in enumerate(columns) if col is not None]
    buffer = dr.empty(type(flat), count * pixels)
    if developed:
        slot, pixel = _order(dr, index_t, pixels, len(developed))
        inside = pixel < pixels
        column = dr.gather(index_t, index_t(np.asarray([columns[i] for i in developed], np.uint32)), slot)
        plane = dr.gather(index_t, index_t(np.asarray(developed, np.uint32)), slot)
        value = dr.gather(type(flat), flat, pixel * c + column, inside)
        if weight_column is not None:
            weight = dr.gather(type(flat), flat, pixel * c + weight_column, inside)
            value = value / dr.select(weight == 0, 1.0, weight)  # hdrfilm's develop
        dr.scatter(buffer, value, plane * pixels + pixel, inside)
    dr.eval(buffer)
    return np.asarray(buffer).reshape(count, h, w), buffer


def film_tensor(buffer, count: int, h: int, w: int, first=None):
    """The H x W x (count [+ 1]) tensor of ``count`` planes in ``buffer`` (flat, plane-major),
    with ``first`` (a plane of H x W, optional) as channel 0."""
    import drjit as dr

    index_t = dr.uint32_array_t(type(buffer))
    pixels = h * w
    extra = 0 if first is None else 1
    slot, pixel = _order(dr, index_t, pixels, count + extra)
    inside = pixel < pixels
    if first is None:
        value = dr.gather(type(buffer), buffer, slot * pixels + pixel, inside)
    else:
        head = slot == 0
        value = dr.select(head, dr.gather(type(buffer), type(buffer)(np.ascontiguousarray(first).ravel()), pixel,
                                          inside & head),
                          dr.gather(type(buffer), buffer, (slot - 1) * pixels + pixel, inside & ~head))
    out = dr.empty(type(buffer), (count + extra) * pixels)
    dr.scatter(out, value, pixel * (count + extra) + slot, inside)
    tensor_t = dr.tensor_t(type(buffer))
    return tensor_t(out, (h, w, count + extra))
