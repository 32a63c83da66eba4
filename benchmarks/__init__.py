"""Benchmarks of the ELO forward model: what a render costs and how accurate it is.

``python -m benchmarks [--quick] [--only SECTION ...] [--out FILE] [--fresh]`` (or
``elo-mitsuba benchmark ...`` from a source checkout) writes ``RESULTS.md`` in the current folder
(``--update-report``: the committed ``benchmarks/RESULTS.md``). Sections
(one module ``benchmarks.section_<name>`` each): the ray-cast ceiling, accuracy against time,
events 1-4, the 1500² targets, Mitsuba's ``path`` integrator at equal error, scaling. Every timed
configuration runs in its own process (:mod:`benchmarks.worker`), so that its peak memory is its
own; configurations that are compared are measured interleaved and reported as medians and ratios.

Importing the package is cheap; Mitsuba is loaded when a section runs.
"""

from __future__ import annotations

#: Section names, as ``--only`` takes them.
SECTIONS = ("ceiling", "accuracy", "events", "targets", "presets", "path", "scaling", "sweep", "analysis", "inversion")


def main(argv=None) -> int:
    """Run the benchmarks with command-line arguments ``argv`` (default ``sys.argv[1:]``).

    Parameters
    ----------
    argv : list of str, optional
        The arguments of ``python -m benchmarks`` (``--quick``, ``--out FILE``,
        ``--only SECTION ...``, ``--fresh``).

    Returns
    -------
    int
        Exit status (argparse raises SystemExit for ``--help`` and usage errors).
    """
    from .runner import main as run_main

    return run_main(argv)
