"""argparse types shared by every subcommand, so a bad value fails the same way (exit 2, the flag named)."""

from __future__ import annotations

import argparse


def seed_int(text: str) -> int:
    """An integer >= 0: numpy's generators refuse negative seeds, and would do so with a traceback."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer >= 0, got '{text}'") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be an integer >= 0, got {value}")
    return value
