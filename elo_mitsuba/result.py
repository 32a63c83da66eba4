"""The result of a render: detector images, the geometry that produced them, their error estimate.

:meth:`elo_mitsuba.EloScene.render` returns a :class:`RenderResult`; it writes itself to an EXR
and tells what each scattering event adds to the signal.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .error_estimate import DETERMINISTIC
from .exr import write_exr
from .schema import error_channel, event_channel

#: An event order adding less than this share of the signal in 99 % of the pixels is reported as
#: negligible (0.1 %: below the default preset's per-pixel error of events >= 2, 0.2 %).
NEGLIGIBLE_EVENT_SHARE = 1e-3


@dataclass
class RenderResult:
    """Detector images (numpy float32, orientation of :mod:`elo_mitsuba.grid`), the geometry that
    produced them and the error estimate.

    ``errors`` maps each channel with an estimated sampling error to its per-pixel standard error
    (same units, from two independent halves of the samples, :mod:`elo_mitsuba.error_estimate`);
    ``metadata["error_estimate"]["channels"]`` summarises every channel (``status``: estimated,
    deterministic or not estimated; ``rms_rel``, ``p99_rel``, ``rms_abs``); see
    :meth:`error_summary`.
    """

    channels: dict[str, np.ndarray]
    metadata: dict = field(default_factory=dict)
    errors: dict[str, np.ndarray] = field(default_factory=dict)

    def error_summary(self) -> dict[str, dict]:
        """Per channel: the summary of its error estimate (empty if the render made none)."""
        return dict(self.metadata.get("error_estimate", {}).get("channels", {}))

    @property
    def detectors(self) -> list[str]:
        return [name for name in self.channels if "." not in name]

    def write_exr(self, path, overwrite: bool = False, error_channels: bool = False) -> Path:
        """Write the channels and metadata (error summary included) to an EXR; with
        ``error_channels`` also each channel's per-pixel standard error as ``<name>.err`` (zero
        for a deterministic channel; none where it is not estimated)."""
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
        its share of that pixel's total (where the total is > 0). Empty with one event."""
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
        ``shares``: :meth:`event_shares` if already computed."""
        shares = self.event_shares() if shares is None else shares
        n = len(shares)
        while n > 1 and shares[n - 1]["p99"] < threshold:
            n -= 1
        return n if shares and n < len(shares) else None
