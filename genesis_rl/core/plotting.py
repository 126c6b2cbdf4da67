"""matplotlib for the package's figures: the file backend, and text drawn as given.

Figures carry names from a campaign's files (policies, members, failure modes); with mathtext on, a policy
named ``$\\undefinedcmd$`` ends a report in a parser traceback, so text is never parsed as math (the package's
own labels use none).
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
