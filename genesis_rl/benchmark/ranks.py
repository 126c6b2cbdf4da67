"""Ranks across systems, as FuzzBench and Demšar (2006) compare tools on many targets: each adversary's
average rank over the zoo's weakness members, Friedman's test of "all rank alike", and the Nemenyi critical
difference (two adversaries whose average ranks differ by less are not told apart at 5 %).

Written out rather than imported from scipy, which the default install does not carry: the chi-square tail
has closed forms for integer degrees of freedom, and Nemenyi's q values are Demšar's Table 5.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

#: Nemenyi's two-tailed q at alpha = 0.05 for k = 2..10 compared methods (Demšar 2006, Table 5a)
NEMENYI_Q05 = {2: 1.960, 3: 2.343, 4: 2.569, 5: 2.728, 6: 2.850, 7: 2.949, 8: 3.031, 9: 3.102, 10: 3.164}


def chi2_sf(x: float, dof: int) -> float:
    """P(X > x) for a chi-square variable with ``dof`` (integer >= 1) degrees of freedom."""
    if dof < 1:
        raise ValueError(f"dof = {dof}; allowed: an integer >= 1")
    if x <= 0.0:
        return 1.0
    h = x / 2.0
    if dof % 2 == 0:
        return math.exp(-h) * sum(h**i / math.factorial(i) for i in range(dof // 2))
    tail = math.erfc(math.sqrt(h))
    return tail + math.exp(-h) * sum(h ** (i - 0.5) / math.gamma(i + 0.5) for i in range(1, (dof - 1) // 2 + 1))


def rank_rows(scores: Mapping[str, float]) -> dict[str, float]:
    """Ranks 1..k of one system's scores, higher score first; ties share the mean of their ranks."""
    order = sorted(scores, key=lambda p: -scores[p])
    out: dict[str, float] = {}
    i = 0
    while i < len(order):
        j = i
        while j + 1 < len(order) and scores[order[j + 1]] == scores[order[i]]:
            j += 1
        for p in order[i:j + 1]:
            out[p] = (i + j) / 2.0 + 1.0
        i = j + 1
    return out


def compare_ranks(table: Mapping[str, Mapping[str, float]], policies: Sequence[str]) -> dict[str, object]:
    """``table``: system -> policy -> score (higher is better). Average ranks, Friedman's statistic and p-value
    (None with fewer than 2 systems or policies) and the Nemenyi critical difference at 5 %."""
    systems = [s for s in table if all(p in table[s] for p in policies)]
    n, k = len(systems), len(policies)
    ranks = {s: rank_rows({p: table[s][p] for p in policies}) for s in systems}
    average = {p: (sum(ranks[s][p] for s in systems) / n if n else None) for p in policies}
    out: dict[str, object] = {"systems": systems, "ranks": ranks, "average_rank": average,
                              "friedman_chi2": None, "friedman_p": None, "critical_difference": None}
    if n >= 2 and k >= 2:
        chi2 = 12.0 * n / (k * (k + 1)) * sum((average[p] or 0.0) ** 2 for p in policies) - 3.0 * n * (k + 1)
        out["friedman_chi2"] = round(chi2, 4)
        out["friedman_p"] = round(chi2_sf(max(chi2, 0.0), k - 1), 6)
        if k in NEMENYI_Q05:
            out["critical_difference"] = round(NEMENYI_Q05[k] * math.sqrt(k * (k + 1) / (6.0 * n)), 4)
    return out
