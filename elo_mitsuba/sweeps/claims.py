"""Claims on a sweep's points, so that two clients resuming one store never render a point twice.

A client claims each point it will send to its workers by creating ``<store>/.claims/<index>``
exclusively (written to a private file first, then hard-linked into place: ``link`` fails when the
name exists, and a claim is never seen half-written). The claim holds the client's id; the client
keeps ``.claims/client-<id>.json`` (host, pid) and touches it every :data:`HEARTBEAT_SECONDS`.
A claim is held while its client lives: on the same host while its process exists, elsewhere
while its file was touched within :data:`STALE_SECONDS`. A stale claim (a client that crashed) is
taken over by renaming it away first (``rename`` succeeds for one taker only). A client removes its
claims when it ends, whatever the outcome: failed points are retried by the next run.

Zarr ignores the folder (no ``.zarray``/``.zgroup`` in it); ``xarray.open_zarr`` reads the
consolidated metadata.
"""

from __future__ import annotations

import json
import os
import socket
import time
from collections import Counter
from pathlib import Path

CLAIMS_DIR = ".claims"
#: A client on another host whose file was not touched for this long is taken as gone.
STALE_SECONDS = 60.0
#: How often a running client touches its file.
HEARTBEAT_SECONDS = 10.0


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except (OSError, ValueError, OverflowError):
        return False
    return True


class Claims:
    """This client's claims on the points of the store at ``store``."""

    def __init__(self, store):
        self.dir = Path(store) / CLAIMS_DIR
        self.dir.mkdir(exist_ok=True)
        self.host = socket.gethostname()
        self.id = f"{self.host}-{os.getpid()}-{time.time_ns()}"
        self.owner_file = self.dir / f"client-{self.id}.json"
        self.owner_file.write_text(json.dumps({"host": self.host, "pid": os.getpid(), "started": time.time()}))
        self._beat = time.monotonic()
        self.mine: list[int] = []

    def heartbeat(self) -> None:
        if time.monotonic() - self._beat >= HEARTBEAT_SECONDS:
            try:
                os.utime(self.owner_file)
            except OSError:
                pass
            self._beat = time.monotonic()

    def _alive(self, owner: str, cache: dict) -> bool:
        if owner not in cache:
            f = self.dir / f"client-{owner}.json"
            try:
                mtime = f.stat().st_mtime
                info = json.loads(f.read_text())
                if info.get("host") == self.host:
                    cache[owner] = _pid_alive(int(info["pid"]))
                else:
                    cache[owner] = time.time() - mtime < STALE_SECONDS
            except (OSError, ValueError, KeyError, TypeError):
                cache[owner] = False
        return cache[owner]

    def claim(self, indices) -> tuple[list[int], Counter]:
        """Claim ``indices``; returns (the points now this client's, {other live client: points
        it holds})."""
        mine, others, alive = [], Counter(), {}
        tmp = self.dir / f"tmp-{self.id}"
        tmp.write_text(self.id)
        try:
            for i in indices:
                target = self.dir / str(int(i))
                for _ in range(2):  # a second try after taking over a stale claim
                    try:
                        os.link(tmp, target)
                        mine.append(int(i))
                        break
                    except FileExistsError:
                        pass
                    try:
                        owner = target.read_text()
                    except OSError:  # removed meanwhile: try again
                        continue
                    if owner == self.id:
                        mine.append(int(i))
                        break
                    if self._alive(owner, alive):
                        others[owner] += 1
                        break
                    stale = self.dir / f"stale-{i}-{self.id}"
                    try:
                        os.rename(target, stale)  # one taker wins; the others find the new claim
                        stale.unlink()
                    except OSError:
                        pass
        finally:
            tmp.unlink(missing_ok=True)
        self.mine += mine
        return mine, others

    def release(self) -> None:
        """Remove this client's claims and its file."""
        for i in self.mine:
            target = self.dir / str(i)
            try:
                if target.read_text() == self.id:
                    target.unlink()
            except OSError:
                pass
        self.mine = []
        self.owner_file.unlink(missing_ok=True)
