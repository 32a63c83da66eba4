"""The result of a render: detector images, the geometry that produced them, their error estimate.

:meth:`elo_mitsuba.EloScene.render` returns a :class:`RenderResult`; it writes itself to an EXR
and tells what each scattering event adds to the signal.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .error_estimate import DETERMINISTIC
from .errors import EloInputError
from .exr import write_exr
from .schema import error_channel, event_channel

#: An event order adding less than this share of the signal in 99 % of the pixels is reported as
#: negligible (0.1 %: below the default preset's per-pixel error of events >= 2, 0.2 %).
NEGLIGIBLE_EVENT_SHARE = 1e-3


#: What leaves a detector without a single electron over the whole scan (said with its note).
NO_SIGNAL_CAUSES = ("a missing or upside-down surface, a scan field wider than the surface, a detector below the "
                    "surface or behind a shield, or one in the beam's path")


@dataclass
class RenderResult:
    """Detector images (numpy float32, orientation of :mod:`elo_mitsuba.grid`), the geometry that
    produced them and the error estimate.

    ``errors`` maps each channel with an estimated sampling error to its per-pixel standard error
    (same units, from two independent halves of the samples, :mod:`elo_mitsuba.error_estimate`);
    ``metadata["error_estimate"]["channels"]`` summarises every channel (``status``: estimated,
    deterministic or not estimated; ``rms_rel``, ``p99_rel``, ``rms_abs``); see
    :meth:`error_summary`.

    Parameters
    ----------
    channels : dict of str to ndarray (H, W)
        ``<id>``: a detector's image (total over the events); ``<id>.e<k>``: event k alone. N_d/N_0,
        or V with ``units="voltage"``.
    metadata : dict
        The render's header (geometry in mm, options, spp, seed, error summary).
    errors : dict of str to ndarray (H, W)
        Per-pixel standard error of the channels that have one (same units).

    Examples
    --------
    >>> import numpy as np
    >>> from elo_mitsuba import RenderResult
    >>> result = RenderResult({"right": np.full((2, 3), 0.01, np.float32)}, {"events": 1})
    >>> result.detectors, result.channels["right"].shape
    (['right'], (2, 3))

    A render returns one:

    >>> import elo_mitsuba as em
    >>> result = em.load_scene("flat_plate", res=4).render(spp=4)
    >>> type(result).__name__, result.detectors
    ('RenderResult', ['right', 'left', 'back', 'front'])
    """

    channels: dict[str, np.ndarray]
    metadata: dict = field(default_factory=dict)
    errors: dict[str, np.ndarray] = field(default_factory=dict)

    def error_summary(self) -> dict[str, dict]:
        """Per channel: the summary of its error estimate (empty if the render made none).

        Returns
        -------
        dict of str to dict
            ``{channel: {"status": ..., "rms_rel": ..., "p99_rel": ..., "rms_abs": ...}}``: ``status``
            is ``estimated``, ``deterministic`` or ``not estimated``; ``rms_rel`` and ``p99_rel`` are
            relative (RMS and 99th percentile over the pixels), ``rms_abs`` in the channel's unit.

        Examples
        --------
        >>> import elo_mitsuba as em
        >>> result = em.load_scene("flat_plate", res=4).render(spp=4)
        >>> summary = result.error_summary()
        >>> summary["right"]["status"], bool(0 < summary["right"]["rms_rel"] < 1)
        ('estimated', True)
        """
        return dict(self.metadata.get("error_estimate", {}).get("channels", {}))

    @property
    def detectors(self) -> list[str]:
        """The detector ids: the channels without an event or error suffix, in render order.

        Examples
        --------
        >>> import numpy as np
        >>> image = np.zeros((2, 2), np.float32)
        >>> RenderResult({"right": image, "right.e1": image, "left": image}).detectors
        ['right', 'left']
        """
        return [name for name in self.channels if "." not in name]

    @property
    def dark_detectors(self) -> list[str]:
        """The detectors that received no electron anywhere in the scan (every pixel 0): a fact of
        the geometry or a mistake in it (:data:`NO_SIGNAL_CAUSES`), which a render says in a note.

        Examples
        --------
        >>> import numpy as np
        >>> RenderResult({"right": np.ones((2, 2)), "left": np.zeros((2, 2))}).dark_detectors
        ['left']
        """
        return [name for name in self.detectors if not np.any(self.channels[name])]

    def write_exr(self, path, overwrite: bool = False, error_channels: bool = False) -> Path:
        """Write the channels and metadata (error summary included) to an EXR; with
        ``error_channels`` also each channel's per-pixel standard error as ``<name>.err`` (zero
        for a deterministic channel; none where it is not estimated).

        Parameters
        ----------
        path : str or Path
            The EXR file to write.
        overwrite : bool
            Replace an existing file (otherwise refused).
        error_channels : bool
            Also write ``<name>.err`` channels.

        Returns
        -------
        Path
            The file written.

        Examples
        --------
        >>> import tempfile
        >>> from pathlib import Path
        >>> import elo_mitsuba as em
        >>> from elo_mitsuba.exr import read_exr
        >>> result = em.load_scene("flat_plate", res=4).render(spp=4)
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     path = result.write_exr(Path(folder) / "plate.exr", error_channels=True)
        ...     channels, header = read_exr(path)
        >>> sorted(channels)[:4], header["units"]
        (['back', 'back.err', 'front', 'front.err'], 'N_d/N_0')
        """
        channels = dict(self.channels)
        if error_channels:
            summary = self.error_summary()
            for name, img in self.channels.items():
                if name in self.errors:
                    channels[error_channel(name)] = self.errors[name]
                elif summary.get(name, {}).get("status") == DETERMINISTIC:
                    channels[error_channel(name)] = np.zeros_like(img)
        return write_exr(path, channels, self.metadata, overwrite=overwrite)

    def event_shares(self) -> list[dict]:
        """What each scattering event adds: per event k (1-based), ``mean`` = its share of the
        signal summed over detectors and pixels, and ``p99`` = the 99th percentile over pixels of
        its share of that pixel's total (where the total is > 0). Empty with one event.

        Returns
        -------
        list of dict
            ``[{"event": k, "mean": float, "p99": float}, ...]``, shares as fractions (0..1).

        Examples
        --------
        >>> import numpy as np
        >>> e1, e2 = np.full((2, 2), 0.03), np.full((2, 2), 0.01)
        >>> result = RenderResult({"right": e1 + e2, "right.e1": e1, "right.e2": e2}, {"events": 2})
        >>> [(s["event"], round(s["mean"], 4), round(s["p99"], 4)) for s in result.event_shares()]
        [(1, 0.75, 0.75), (2, 0.25, 0.25)]
        """
        events = int(self.metadata.get("events", 1))
        if events < 2:
            return []
        total = sum(self.channels[d].astype(np.float64) for d in self.detectors)
        lit = total > 0
        signal = float(total.sum())
        out = []
        for k in range(1, events + 1):
            ek = sum(self.channels[event_channel(d, k)].astype(np.float64) for d in self.detectors)
            mean = float(ek.sum()) / signal if signal > 0 else 0.0
            p99 = float(np.percentile(ek[lit] / total[lit], 99)) if np.any(lit) else 0.0
            out.append({"event": k, "mean": mean, "p99": p99})
        return out

    def negligible_events(self, threshold: float = NEGLIGIBLE_EVENT_SHARE, shares=None) -> int | None:
        """The number of events that would do: the smallest n such that every event above n adds
        less than ``threshold`` of the signal in 99 % of the pixels (None if all are needed).
        ``shares``: :meth:`event_shares` if already computed.

        Parameters
        ----------
        threshold : float
            Share of the signal (fraction, default :data:`NEGLIGIBLE_EVENT_SHARE` = 0.1 %).
        shares : list of dict, optional
            The result of :meth:`event_shares`.

        Returns
        -------
        int or None
            The number of events that would do, or None.

        Examples
        --------
        >>> import numpy as np
        >>> e1, e2 = np.full((2, 2), 0.03), np.full((2, 2), 1e-6)
        >>> result = RenderResult({"right": e1 + e2, "right.e1": e1, "right.e2": e2}, {"events": 2})
        >>> result.negligible_events()
        1
        >>> print(result.negligible_events(threshold=1e-6))
        None
        """
        if isinstance(threshold, bool) or not isinstance(threshold, (int, float)) or not 0 <= threshold <= 1:
            raise EloInputError(f"threshold={threshold!r}: must be a share of the signal from 0 to 1 "
                                f"(default {NEGLIGIBLE_EVENT_SHARE:g})")
        shares = self.event_shares() if shares is None else shares
        n = len(shares)
        while n > 1 and shares[n - 1]["p99"] < threshold:
            n -= 1
        return n if shares and n < len(shares) else None
