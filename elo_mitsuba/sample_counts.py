"""Sample counts a scene's sampler takes exactly, and render passes made of them.

The shipped scenes sample with Mitsuba's ``multijitter``: per pixel, the beam profile's offsets
(and every other 2-D sample) are stratified, which cuts the per-pixel error by about 40 % where
the signal changes inside the beam spot (a pore's rim) at no extra cost (docs/rendering.md, the
paragraph on the stratified beam profile).
Stratified samplers round a count they cannot stratify (``multijitter``: a x b with
a = floor(sqrt(n)), so 7 becomes 8; ``ldsampler``: powers of four), which would change how many
samples a pass renders while its weight counts the asked number. A render is therefore split
into passes of counts the sampler takes as they are (1 always is), and a top-up pass is rounded up
to one.

Every pass count is also a power of two. Mitsuba lays a pass out pixel by pixel, n lanes each,
Dr.Jit runs the lanes in blocks on several threads, and the film adds a pixel's samples
atomically. With n = 35 (``multijitter``'s 32) or 30 a pixel's lanes can straddle two blocks,
two threads add to it, and the order of the two sums, hence the last bits, changed from run to
run (athene_flat 64², 64 spp, 1st event: 10 of 10 re-renders differed, by up to 3 float32
roundoffs). Passes of 16 or 64 lanes never did, nor any render since the passes are powers of
two (the blocks' sizes evidently are too; tests/test_sample_counts.py).
"""

from __future__ import annotations

_TAKES: dict = {}


def _kind(sampler) -> str:
    return str(sampler).split("[", 1)[0]


def takes(sampler, n: int) -> bool:
    """Whether ``sampler`` renders ``n`` samples per pixel when asked for ``n`` (no rounding)."""
    key = (_kind(sampler), int(n))
    if key not in _TAKES:
        import mitsuba as mi  # on first use: importing the package stays light

        probe = sampler.clone()
        logger = mi.logger()
        level = logger.log_level()
        logger.set_log_level(mi.LogLevel.Error)  # the rounding's warning is what we probe for
        try:
            probe.set_sample_count(int(n))
        finally:
            logger.set_log_level(level)
        _TAKES[key] = int(probe.sample_count()) == int(n)
    return _TAKES[key]


def count_at_most(sampler, n: int) -> int:
    """The largest power of two <= ``n`` (>= 1) that ``sampler`` takes exactly."""
    m = 1 << (max(1, int(n)).bit_length() - 1)
    while m > 1 and not takes(sampler, m):
        m >>= 1
    return m


def count_at_least(sampler, n: int) -> int:
    """The smallest power of two >= ``n`` (>= 1) that ``sampler`` takes exactly."""
    m = 1 << (max(1, int(n)) - 1).bit_length()
    while not takes(sampler, m):
        m <<= 1
    return m


def pass_sizes(sampler, total: int, per_pass: int):
    """Split ``total`` samples per pixel into passes of at most ``per_pass``, each a power of two
    the sampler takes exactly (largest first: fewer, better stratified passes).

    Returns
    -------
    full : int
        The count of each of the first ``repeats`` passes.
    repeats : int
        How many passes of ``full`` samples come first (a huge ``total`` costs no list).
    rest : list of int
        The counts of the passes that follow (together below ``full``).
    """
    full = count_at_most(sampler, min(int(per_pass), max(int(total), 1)))
    repeats, left = divmod(int(total), full)
    rest = []
    while left > 0:
        n = count_at_most(sampler, left)
        rest.append(n)
        left -= n
    return full, repeats, rest


def pass_count(sizes) -> int:
    """How many passes :func:`pass_sizes`'s split makes."""
    return sizes[1] + len(sizes[2])


def each_pass(sizes):
    """The counts of :func:`pass_sizes`'s passes, in order."""
    full, repeats, rest = sizes
    for _ in range(repeats):
        yield full
    yield from rest
