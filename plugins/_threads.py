"""Threads for numpy's passes over a render's planes (the filter's and the classes' per-channel
work after a pass): numpy lets go of the GIL in them, and the kernel's threads are idle then."""

import os
from concurrent.futures import ThreadPoolExecutor

#: Threads that work on a render's planes at once.
PLANE_THREADS = max(1, min(4, os.cpu_count() or 1))

_POOL = []


def each_plane(fn, jobs):
    """``fn(job)`` for every job, on :data:`PLANE_THREADS` threads where there are two jobs or
    more; in order on this thread otherwise. The jobs must not share what ``fn`` writes."""
    jobs = list(jobs)
    threads = PLANE_THREADS
    if len(jobs) < 2 or threads < 2:
        for job in jobs:
            fn(job)
        return
    if not _POOL or _POOL[0][1] != threads:
        _POOL[:] = [(ThreadPoolExecutor(threads, thread_name_prefix="elo-planes"), threads)]
    list(_POOL[0][0].map(fn, jobs))
