"""The bounce filter: events >= 2 estimated in space, on the developed film (numpy).

The event >= 2 channels are averaged over a window of about ``bounce_filter`` mm half-width,
shrunk (halved, three scales at most) wherever the 1st-event surface normals in the window differ
by more than ``bounce_filter_angle`` or the guide is not a unit vector there (the beam missed, or
the integrator marks the pixel apart), so that flanks, edges and object borders are not mixed.
Biased by the variation of what is averaged inside the window: use it where that varies slowly
(walls far away), after checking the error against a reference (benchmarks/). With the far
field's tabulated mean the integrator hands it the 2nd event less that mean (the residual), which
varies slowly also across relief (plugins/integrator_elo.py).
"""

import math
import threading

import numpy as np

from elo_mitsuba.options import filter_window_levels

from ._threads import each_plane

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


def _pyramid(plane, hp, wp, top, scratch):
    """Sum pyramid of one plane (H, W), zero-padded to (hp, wp) in ``scratch``: levels 0 .. top,
    level j holding tiles of 2^j pixels (level 0 is ``scratch`` itself)."""
    h, w = plane.shape
    scratch[:h, :w] = plane
    levels = [scratch]
    for _ in range(top):
        x = levels[-1]
        levels.append(x[0::2, 0::2] + x[1::2, 0::2] + x[0::2, 1::2] + x[1::2, 1::2])
    return levels


def _window(tiles):
    """Sum over the 3 x 3 tiles around each tile (zero outside)."""
    nt, ns = tiles.shape
    pad = np.pad(tiles, 1)
    return sum(pad[i:i + nt, j:j + ns] for i in range(3) for j in range(3))


def filter_bounces(planes, index, bounce_names, field_mm, half_width_mm, angle_deg, paths=None, plan=None):
    """Replace the event >= 2 channels of the film's ``planes`` (float32, C x H x W, in place,
    :mod:`elo_mitsuba.film`) by their normal-guided window average.

    ``index`` maps channel names to planes (it must hold :data:`GUIDE_CHANNELS`);
    ``bounce_names`` are the channels to filter (``<id>.e<k>``, k >= 2). Multi-scale and cheap: a
    sum pyramid of tiles of 2^j pixels (one pass over the image); the window of a tile is the
    3 x 3 tiles around it (2^j about the filter half-width at the top level); it counts as
    homogeneous if the mean of its unit normals (zero where the beam missed) is longer than
    cos(angle_deg). Pixels whose surrounding windows are all homogeneous take the bilinear
    interpolation of the window means; the others go on to tiles half as large (three scales at
    most); what is left keeps its own value. ``paths`` (H, W) is multiplied by the number of
    pixels each value now averages. The channels are filtered on threads
    (:func:`._threads.each_plane`), each as alone.

    ``plan``: what :func:`filter_plan` decided from the same guide channels (the two halves of
    a render traced in one pass share them), else decided here. Returns the plan.

    Memory: the decisions come from the guide channels alone, then each channel is filtered in
    one padded scratch plane, so a render touches little fresh memory (a new process pays for
    every fresh page).
    """
    if plan is None:
        plan = filter_plan(planes, index, field_mm, half_width_mm, angle_deg)
    if plan is None:
        return None
    top, hp, wp, steps, gain = plan
    if paths is not None:  # continuation paths behind each pixel's value now
        paths *= gain

    scratch = {}  # one padded plane per thread (its padding stays zero)

    def one(c):
        mine = scratch.get(threading.get_ident())
        if mine is None:
            mine = scratch[threading.get_ident()] = np.zeros((hp, wp), np.float32)
        levels = _pyramid(planes[c], hp, wp, top, mine)
        for level, take, ay, ax, count in steps:
            means = _window(levels[level]) / count
            smooth = ay @ means @ ax.T  # window centres -> pixel centres
            np.copyto(planes[c], smooth, where=take)

    each_plane(one, [index[name] for name in bounce_names])
    return plan


def filter_plan(planes, index, field_mm, half_width_mm, angle_deg):
    """The filter's decisions from the guide channels of ``planes`` (see :func:`filter_bounces`):
    (top level, padded height and width, steps, gain), steps = [(level, pixels taken,
    interpolation along y and x, window pixel counts)], gain the pixels each pixel's value
    averages (H x W); None where nothing is filtered."""
    h, w = int(planes.shape[1]), int(planes.shape[2])
    if not field_mm:
        return None
    top = filter_window_levels(half_width_mm, field_mm / w, max(h, w))
    if top is None:
        return None
    size = 1 << top
    hp, wp = -(-h // size) * size, -(-w // size) * size
    scratch = np.zeros((hp, wp), np.float32)
    guide = [planes[index[g]] for g in GUIDE_CHANNELS]
    # pixels whose beam hit a scattering surface (their film normal is a unit vector)
    undecided = (guide[0] * guide[0] + guide[1] * guide[1] + guide[2] * guide[2]) > 0.25
    normal_levels = []
    for k in range(3):
        normal_levels.append([t.copy() for t in _pyramid(guide[k], hp, wp, top, scratch)[top - min(top, 3):]])
    del guide
    ones = np.ones((h, w), np.float32)
    count_levels = [t.copy() for t in _pyramid(ones, hp, wp, top, scratch)[top - min(top, 3):]]
    del ones
    valid_levels = [t.copy() for t in _pyramid(undecided.astype(np.float32), hp, wp, top, scratch)[top - min(top, 3):]]
    first = top - min(top, 3)  # lowest level used (three scales at most)
    cos2 = math.cos(math.radians(angle_deg)) ** 2
    steps = []  # (level, pixels taken, interpolation, window pixel count)
    gain = np.ones((h, w), np.float32)
    for level in range(top, first - 1, -1):
        if not np.any(undecided):
            break
        win_count = _window(count_levels[level - first])
        count = np.maximum(win_count, 1.0)
        n_mean = np.stack([_window(n[level - first]) for n in normal_levels], axis=-1) / count[..., None]
        # homogeneous: every pixel of the window valid (|n| = 1; counted, as a wide angle would
        # let a few invalid ones through the length test) and the normals agree
        homogeneous = (_window(valid_levels[level - first]) > win_count - 0.5) & \
            (np.einsum("ijk,ijk->ij", n_mean, n_mean) > cos2)
        hh = np.pad(homogeneous, ((0, 1), (0, 1)), mode="edge")
        ok = hh[:-1, :-1] & hh[1:, :-1] & hh[:-1, 1:] & hh[1:, 1:]
        tile = 1 << level
        nt, ns = ok.shape
        iy, ay = _interpolation(h, nt, tile)
        ix, ax = _interpolation(w, ns, tile)
        take = undecided & ok[iy][:, ix]
        if not np.any(take):
            continue
        steps.append((level, take, ay, ax, count))
        np.copyto(gain, win_count[iy][:, ix], where=take)
        undecided &= ~take
    return (top, hp, wp, steps, gain) if steps else None
