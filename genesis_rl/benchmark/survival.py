"""Time to the first failure as a survival curve (Magma's time-to-bug): trials that never failed within their
budget are censored there, not dropped, so an adversary that fails late is not scored as one that never did."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def kaplan_meier(times: Sequence[float], observed: Sequence[bool]) -> tuple[np.ndarray, np.ndarray]:
    """The Kaplan-Meier estimate: ``t`` = 0 then every distinct observed time, ascending; ``survival`` the
    share still without a failure just after each. A trial censored at a time when another fails is at risk
    at that time (the usual convention: events before censoring)."""
    t = np.asarray(times, dtype=float)
    event = np.asarray(observed, dtype=bool)
    if t.shape != event.shape or t.ndim != 1:
        raise ValueError(f"times {t.shape} and observed {event.shape} must be 1-d and of one length")
    if not np.isfinite(t).all() or (t < 0).any():
        raise ValueError("times must be finite and >= 0")
    at = np.unique(t[event])
    at_risk = (t[None, :] >= at[:, None]).sum(axis=1)
    failed = ((t[None, :] == at[:, None]) & event[None, :]).sum(axis=1)
    survival = np.cumprod(1.0 - failed / at_risk)
    return np.concatenate([[0.0], at]), np.concatenate([[1.0], survival])


def median_time(t: np.ndarray, survival: np.ndarray) -> float | None:
    """The first time the survival curve reaches 0.5 or below (None: it stays above, too few failures)."""
    below = np.flatnonzero(survival <= 0.5)
    return float(t[below[0]]) if below.size else None
