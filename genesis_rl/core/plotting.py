"""matplotlib for the package's figures: the file backend, and text drawn as given.

Figures carry names from a campaign's files (policies, members, failure modes); with mathtext on, a policy
named ``$\\undefinedcmd$`` ends a report in a parser traceback, so text is never parsed as math (the package's
own labels use none). A log axis's default labels are mathtext (``10^{3}``): :func:`plain_log_ticks` writes
them as plain numbers.
"""

from __future__ import annotations

from typing import Any


def pyplot() -> Any:
    """``matplotlib.pyplot``, set to draw into files (Agg) and to draw ``$...$`` as the characters it is."""
    import matplotlib

    matplotlib.use("Agg")
    matplotlib.rcParams["text.parse_math"] = False
    import matplotlib.pyplot as plt

    return plt


def plain_log_ticks(axis: Any) -> None:
    """Label a log-scaled ``axis`` with plain numbers (``10``, ``100``, ``1000``) and no minor labels: its
    default labels are mathtext, drawn as their source when text is not parsed as math."""
    from matplotlib.ticker import FuncFormatter, NullFormatter

    axis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
    axis.set_minor_formatter(NullFormatter())
