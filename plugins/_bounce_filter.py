"""The bounce filter: events >= 2 estimated in space, on the developed film (numpy).

The event >= 2 channels are averaged over a window of about ``bounce_filter`` mm half-width,
shrunk (halved, three scales at most) wherever the 1st-event surface normals in the window differ
by more than ``bounce_filter_angle`` or the beam missed, so that flanks, edges and object borders
are not mixed. Biased by the variation of the events >= 2 inside the window: use it where they
vary slowly (walls far away), after checking the error against a reference (benchmarks/).
"""

import math

import mitsuba as mi
import numpy as np

from elo_mitsuba.options import filter_window_levels

#: Hidden film channels: the 1st-event surface normal that guides the filter.
GUIDE_CHANNELS = ("_elo_nx", "_elo_ny", "_elo_nz")


def _interpolation(n_fine, n_coarse, tile):
    """(index of the window at or before each pixel, (n_fine, n_coarse) matrix of the linear
    interpolation from window centres (tile centres) to pixel centres, clamped at the edges)."""
    c = (np.arange(n_fine) + 0.5) / tile - 0.5
    i0 = np.clip(np.floor(c).astype(np.int64), 0, n_coarse - 1)
    i1 = np.minimum(i0 + 1, n_coarse - 1)
    f = np.clip(c - i0, 0.0, 1.0)
    a = np.zeros((n_fine, n_coarse), np.float32)
    rows = np.arange(n_fine)
    np.add.at(a, (rows, i0), 1.0 - f)
    np.add.at(a, (rows, i1), f)
    return i0, a


def filter_bounces(image, col, bounce_names, field_mm, half_width_mm, angle_deg, paths=None):
    """Replace the event >= 2 channels of the developed film ``image`` (TensorXf, H x W x C,
    in place) by their normal-guided window average.

    ``col`` maps channel names to film columns (it must hold :data:`GUIDE_CHANNELS`);
    ``bounce_names`` are the channels to filter (``<id>.e<k>``, k >= 2). Multi-scale and cheap: a
    sum pyramid of tiles of 2^j pixels (one pass over the image); the window of a tile is the
    3 x 3 tiles around it (2^j about the filter half-width at the top level); it counts as
    homogeneous if the mean of its unit normals (zero where the beam missed) is longer than
    cos(angle_deg). Pixels whose surrounding windows are all homogeneous take the bilinear
    interpolation of the window means; the others go on to tiles half as large (three scales at
    most); what is left keeps its own value. ``paths`` (H, W) is multiplied by the number of
    pixels each value now averages.
    """
    h, w = int(image.shape[0]), int(image.shape[1])
    if not field_mm:
        return
    top = filter_window_levels(half_width_mm, field_mm / w)
    if top is None:
        return
    bounce_cols = [col[name] for name in bounce_names]
    n_later = len(bounce_cols)
    size = 1 << top
    hp, wp = -(-h // size) * size, -(-w // size) * size
    data = np.zeros((hp, wp, 4 + n_later), np.float32)  # normal, pixel count, events >= 2
    for i, g in enumerate(GUIDE_CHANNELS):
        data[:h, :w, i] = np.array(image[..., col[g]])
    data[:h, :w, 3] = 1.0
    later = np.empty((n_later, h, w), np.float32)
    for i, c in enumerate(bounce_cols):
        later[i] = np.array(image[..., c])
        data[:h, :w, 4 + i] = later[i]
    normal = data[:h, :w, :3]
    # pixels whose beam hit a scattering surface (their film normal is a unit vector)
    undecided = np.einsum("ijk,ijk->ij", normal, normal) > 0.25
    pyramid = [data]
    for _ in range(top):
        x = pyramid[-1]
        pyramid.append(x[0::2, 0::2] + x[1::2, 0::2] + x[0::2, 1::2] + x[1::2, 1::2])
    cos2 = math.cos(math.radians(angle_deg)) ** 2
    for level in range(top, max(top - 3, 0) - 1, -1):  # three scales at most
        if not np.any(undecided):
            break
        tiles = pyramid[level]
        nt, ns = tiles.shape[:2]
        pad = np.pad(tiles, ((1, 1), (1, 1), (0, 0)))
        win = sum(pad[i:i + nt, j:j + ns] for i in range(3) for j in range(3))
        count = np.maximum(win[..., 3:4], 1.0)
        n_mean = win[..., :3] / count
        # homogeneous: every pixel of the window valid (|n| = 1) and the normals agree
        homogeneous = np.einsum("ijk,ijk->ij", n_mean, n_mean) > cos2
        hh = np.pad(homogeneous, ((0, 1), (0, 1)), mode="edge")
        ok = hh[:-1, :-1] & hh[1:, :-1] & hh[:-1, 1:] & hh[1:, 1:]
        tile = 1 << level
        iy, ay = _interpolation(h, nt, tile)
        ix, ax = _interpolation(w, ns, tile)
        take = undecided & ok[iy][:, ix]
        if not np.any(take):
            continue
        means = np.ascontiguousarray((win[..., 4:] / count).transpose(2, 0, 1))
        for c in range(n_later):
            smooth = ay @ means[c] @ ax.T  # window centres -> pixel centres
            np.copyto(later[c], smooth, where=take)
        if paths is not None:  # continuation paths behind each pixel's value now
            np.copyto(paths, paths * win[..., 3][iy][:, ix], where=take)
        undecided &= ~take
    for i, c in enumerate(bounce_cols):
        image[..., c] = mi.Float(later[i].ravel())
