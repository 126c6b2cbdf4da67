"""Campaign statistics: means with bootstrap 95% confidence intervals and paired policy comparisons.

Every policy meets the same scenes with the same episode seeds, so two policies compare *paired*, scene by
scene: the mean difference with a paired bootstrap CI, wins/ties/losses, and a sign-flip permutation
p-value (two-sided). All resampling is seeded. Failure rates get exact Clopper-Pearson intervals.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

N_BOOT = 10_000


def bootstrap_mean_ci(values: Sequence[float] | np.ndarray, seed: int, n_boot: int = N_BOOT,
                      level: float = 0.95) -> dict[str, float | int | None]:
    """Mean and percentile bootstrap CI of the mean (None when there are no values: JSON has no NaN)."""
    x = np.asarray(values, np.float64)
    if len(x) == 0:
        return {"mean": None, "ci_low": None, "ci_high": None, "n": 0}
    rng = np.random.default_rng(seed)
    means = x[rng.integers(0, len(x), (n_boot, len(x)))].mean(axis=1)
    lo, hi = np.quantile(means, [(1 - level) / 2, 1 - (1 - level) / 2])
    return {"mean": float(x.mean()), "ci_low": float(lo), "ci_high": float(hi), "n": int(len(x))}


def paired_comparison(a: Sequence[float], b: Sequence[float], seed: int, n_boot: int = N_BOOT) -> dict[str, Any]:
    """``a - b`` per scene: mean difference with bootstrap CI, wins (a > b), ties, losses, and the sign-flip
    permutation p-value of 'no difference'."""
    d = np.asarray(a, np.float64) - np.asarray(b, np.float64)
    out: dict[str, Any] = {"difference": bootstrap_mean_ci(d, seed, n_boot)}
    out.update(wins=int((d > 1e-9).sum()), ties=int((np.abs(d) <= 1e-9).sum()), losses=int((d < -1e-9).sum()))
    if len(d) == 0:
        out["p_value"] = None
        return out
    rng = np.random.default_rng(seed + 1)
    signs = rng.choice([-1.0, 1.0], size=(n_boot, len(d)))
    null = np.abs((signs * d).mean(axis=1))
    out["p_value"] = float((1 + (null >= abs(d.mean()) - 1e-12).sum()) / (n_boot + 1))
    return out


def _binom_cdf(k: int, n: int, p: float) -> float:
    """P(X <= k) for X ~ Binomial(n, p), summed in log space (no overflow at large n)."""
    if p <= 0.0:
        return 1.0
    if p >= 1.0:
        return 1.0 if k >= n else 0.0
    lp, lq = math.log(p), math.log1p(-p)
    return float(min(1.0, sum(math.exp(math.lgamma(n + 1) - math.lgamma(i + 1) - math.lgamma(n - i + 1)
                                       + i * lp + (n - i) * lq) for i in range(k + 1))))


def clopper_pearson(k: int, n: int, level: float = 0.95, digits: int | None = 4) -> dict[str, float | int | None]:
    """The exact (Clopper-Pearson) confidence interval of a rate of ``k`` events in ``n`` trials, found by
    bisection on the binomial tail probabilities (no SciPy needed); rounded to ``digits`` (None: not rounded,
    for rates far below 1e-4)."""
    if n == 0:
        return {"rate": None, "ci_low": None, "ci_high": None, "k": 0, "n": 0}
    alpha = (1 - level) / 2

    def solve(f: Callable[[float], bool]) -> float:  # the p in [0, 1] where f turns from False to True
        lo, hi = 0.0, 1.0
        for _ in range(60):
            mid = (lo + hi) / 2
            lo, hi = (lo, mid) if f(mid) else (mid, hi)
        return (lo + hi) / 2

    low = 0.0 if k == 0 else solve(lambda p: 1 - _binom_cdf(k - 1, n, p) >= alpha)
    high = 1.0 if k == n else solve(lambda p: _binom_cdf(k, n, p) <= alpha)
    def shown(v: float) -> float:
        return v if digits is None else round(v, digits)

    return {"rate": k / n, "ci_low": shown(low), "ci_high": shown(high), "k": k, "n": n}
