"""From weighted episode outcomes to a failure-rate estimate (pure arithmetic, no simulation).

Importance sampling: each episode drawn from a proposal q carries the weight w = p/q of the nominal model p;
the mean of ``failed * w`` is unbiased for the nominal failure probability, also over adaptive stages (each
stage's proposal depends only on episodes before it). The interval is the normal one on that mean; the
effective sample size, (sum w)^2 / sum w^2, and the share of the estimate its largest failure carries say
whether it can be trusted. Crude Monte Carlo (every weight 1) gets the exact Clopper-Pearson interval instead.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from genesis_rl.core.stats import clopper_pearson

Z95 = 1.959963984540054
#: warn when the effective sample size falls below this share of the episodes
ESS_WARN_SHARE = 0.05
#: warn when one failure carries more than this share of the estimate
TOP_SHARE_WARN = 0.5


@dataclass(frozen=True)
class Estimate:
    """A failure probability per episode with its 95 % interval and the diagnostics that go with it."""

    method: str
    episodes: int
    failures: int
    probability: float
    ci95: tuple[float, float]
    ess: float
    top_share: float  # the share of the estimate its largest failure carries (0 without failures)
    warnings: tuple[str, ...] = field(default=())

    @property
    def relative_half_width(self) -> float | None:
        """Half the interval's width over the estimate (None without a failure)."""
        if self.probability <= 0:
            return None
        return (self.ci95[1] - self.ci95[0]) / 2 / self.probability

    def to_json(self) -> dict[str, Any]:
        rhw = self.relative_half_width
        return {"method": self.method, "episodes": self.episodes, "failures": self.failures,
                "probability": self.probability, "ci95": list(self.ci95),
                "relative_half_width": None if rhw is None else round(rhw, 4), "ess": round(self.ess, 2),
                "top_share": round(self.top_share, 4), "warnings": list(self.warnings)}


def crude(failed: Sequence[bool]) -> Estimate:
    """Crude Monte Carlo: the share of failed episodes, Clopper-Pearson's exact interval."""
    n, k = len(failed), int(sum(bool(f) for f in failed))
    if n == 0:
        raise ValueError("an estimate needs at least one episode")
    ci = clopper_pearson(k, n, digits=None)
    return Estimate("crude", n, k, k / n, (float(ci["ci_low"] or 0.0), float(ci["ci_high"] or 0.0)), float(n),
                    1.0 / k if k else 0.0)


def importance(failed: Sequence[bool], log_weights: Sequence[float]) -> Estimate:
    """The importance-sampling estimate from each episode's outcome and log likelihood ratio log(p/q)."""
    f = np.asarray(failed, bool)
    lw = np.asarray(log_weights, np.float64)
    n = len(f)
    if n == 0 or len(lw) != n:
        raise ValueError("an estimate needs one log weight per episode, and at least one episode")
    w = np.exp(lw)
    terms = np.where(f, w, 0.0)
    p = float(terms.mean())
    sd = float(terms.std(ddof=1)) if n > 1 else 0.0
    half = Z95 * sd / math.sqrt(n)
    ess = float(w.sum() ** 2 / np.sum(w * w)) if np.any(w > 0) else 0.0
    top = float(terms.max() / terms.sum()) if terms.sum() > 0 else 0.0
    warnings = []
    if ess < ESS_WARN_SHARE * n:
        warnings.append(f"the weights degenerate: effective sample size {ess:.1f} of {n} episodes (under "
                        f"{ESS_WARN_SHARE:.0%}); the proposal is far from the nominal model")
    if int(f.sum()) > 1 and top > TOP_SHARE_WARN:
        warnings.append(f"one failure carries {top:.0%} of the estimate: its interval is not to be trusted")
    if not f.any():
        warnings.append("no failure was drawn: the estimate is 0 and its interval says nothing; a proposal that "
                        "reaches a failure region, or crude Monte Carlo's upper bound, is needed")
    return Estimate("importance", n, int(f.sum()), p, (max(0.0, p - half), p + half), ess, top, tuple(warnings))


def running(failed: Sequence[bool], log_weights: Sequence[float] | None, every: int = 1) -> list[dict[str, float]]:
    """The estimate and its interval after every ``every`` episodes (for the convergence plot)."""
    out = []
    for n in range(every, len(failed) + 1, every):
        e = crude(failed[:n]) if log_weights is None else importance(failed[:n], log_weights[:n])
        out.append({"episodes": n, "probability": e.probability, "low": e.ci95[0], "high": e.ci95[1]})
    return out


def per_hour(probability: float, episode_s: float) -> float:
    """Failures per hour of driving: the episode's probability over its length in hours."""
    return probability * 3600.0 / episode_s


def episodes_for(probability: float, relative_half_width: float = 0.3) -> float:
    """The episodes crude Monte Carlo needs for a 95 % interval of ``relative_half_width`` at ``probability``
    (normal approximation: n = z^2 (1 - p) / (p r^2))."""
    return Z95**2 * (1 - probability) / (probability * relative_half_width**2)
