"""Progress of a render's passes on stderr: a bar on a terminal, plain lines everywhere else.

On a terminal :mod:`tqdm` redraws one bar in place. Off a terminal (a log file, a pipe, CI) a
redrawn bar would leave its carriage returns in the file, so a line is written per 10 % (or every
:data:`PROGRESS_EVERY_S` in between) once the render has run :data:`PROGRESS_AFTER_S`: short
renders stay quiet.
"""

from __future__ import annotations

import math
import sys

#: Off a terminal, progress lines start once a render has run this long (short renders stay quiet).
PROGRESS_AFTER_S = 3.0
#: ... and come at least this often between the 10 % steps.
PROGRESS_EVERY_S = 30.0


class RenderProgress:
    """The progress of a render's samples (both halves of the error estimate together).

    Parameters
    ----------
    total : int
        Samples per pixel to render in all.
    passes : int
        Passes they are rendered in; one pass has nothing to report between its start and end.
    enabled : bool or None
        None: shown for multi-pass renders; True: always (off a terminal without the initial
        quiet time); False: never.
    """

    def __init__(self, total: int, passes: int, enabled: bool | None):
        self.total, self.passes = total, passes
        self.enabled = (passes > 1) if enabled is None else bool(enabled)
        self.always = bool(enabled)
        self.next_step, self.last = 0.1, -math.inf
        self.bar = None
        if self.enabled and sys.stderr.isatty():
            from tqdm import tqdm

            self.bar = tqdm(total=total, unit="spp", desc="  render", file=sys.stderr, leave=True,
                            dynamic_ncols=True)

    def __call__(self, done: int, elapsed: float) -> None:
        """Report ``done`` samples per pixel rendered after ``elapsed`` seconds."""
        if not self.enabled or done <= 0:
            return
        if self.bar is not None:
            self.bar.update(done - self.bar.n)
            return
        if (self.always or elapsed >= PROGRESS_AFTER_S) and (
                done / self.total >= self.next_step - 1e-12 or elapsed - self.last >= PROGRESS_EVERY_S
                or self.last == -math.inf):
            eta = elapsed / done * (self.total - done)
            print(f"  render: {done}/{self.total} spp ({100 * done / self.total:.0f} %), {elapsed:.1f} s, "
                  f"{done / max(elapsed, 1e-9):.3g} spp/s, {eta:.1f} s left", file=sys.stderr, flush=True)
            self.next_step = math.floor(10 * done / self.total + 1e-9) / 10 + 0.1
            self.last = elapsed

    def end(self) -> None:
        """Close the bar (its last state stays on the terminal)."""
        if self.bar is not None:
            self.bar.close()
            self.bar = None
