"""Benchmarks of the ELO forward model (issue 6): ``python -m benchmarks [--quick]``.

Writes ``benchmarks/RESULTS.md``. Every configuration whose time or memory is reported runs in
its own subprocess (:mod:`benchmarks.worker`) so that its peak memory (``ru_maxrss``) is its own;
configurations that are compared are measured side by side, interleaved, in one run, and reported
as medians and ratios.
"""
