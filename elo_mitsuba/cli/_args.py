"""Argument types shared by the sub-commands: each rejects bad text with a one-line reason."""

from __future__ import annotations

import argparse


class OneLineParser(argparse.ArgumentParser):
    """Usage errors as one line (what is wrong, and where to look), exit status 2, no usage dump."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def _integer(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None


def number(text: str) -> float:
    """Any finite or infinite float (range checks belong to the library)."""
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None


def positive_int(text: str) -> int:
    value = _integer(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value} must be >= 1")
    return value


def non_negative_int(text: str) -> int:
    value = _integer(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"{value} must be >= 0")
    return value


def define(text: str) -> tuple[str, str]:
    """``NAME=VALUE`` of a scene parameter."""
    if "=" not in text or not text.split("=", 1)[0].strip():
        raise argparse.ArgumentTypeError(f"{text!r} is not NAME=VALUE (e.g. -D dh=250)")
    name, value = text.split("=", 1)
    return name.strip(), value.strip()


def seed(text: str) -> int:
    """A sampler seed: 0 .. 2^32 - 1."""
    value = non_negative_int(text)
    if value > (1 << 32) - 1:
        raise argparse.ArgumentTypeError(f"{value} is above 4294967295 (seeds are 32-bit)")
    return value


def add_yes(parser) -> None:
    """``--yes``: run work estimated to take longer than budget.REFUSE_SECONDS (refused otherwise)."""
    from ..budget import REFUSE_SECONDS

    parser.add_argument("--yes", action="store_true",
                        help=f"run even when the estimate says it takes longer than {REFUSE_SECONDS / 3600:g} h "
                             "(refused otherwise as likely a mistyped number); memory beyond what is available "
                             "is refused regardless")
