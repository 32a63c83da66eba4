"""The package version, read by ``elo_mitsuba`` and everything that records provenance."""

__version__ = "0.1.0"
