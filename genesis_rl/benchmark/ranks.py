"""Ranks across systems, as FuzzBench and Demšar (2006) compare tools on many targets: each adversary's
average rank over the zoo's weakness members, Friedman's test of "all rank alike" (corrected for ties, as
scipy's ``friedmanchisquare``: zoo tables tie often, at 0 failures), Iman and Davenport's F form of it (less
conservative with few systems, the form Demšar recommends) and the Nemenyi critical difference (two
adversaries whose average ranks differ by less are not told apart at 5 %).

Written out rather than imported from scipy, which the default install does not carry: the chi-square tail
has closed forms for integer degrees of freedom, the F tail is a regularised incomplete beta (a continued
fraction), and Nemenyi's q values are Demšar's Table 5.
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


def _betacf(a: float, b: float, x: float) -> float:
    """The continued fraction of the regularised incomplete beta (modified Lentz)."""
    tiny, qab, qap, qam = 1e-300, a + b, a + 1.0, a - 1.0
    c, d = 1.0, 1.0 - qab * x / qap
    d = 1.0 / (d if abs(d) > tiny else tiny)
    h = d
    for m in range(1, 500):
        m2 = 2 * m
        for aa in (m * (b - m) * x / ((qam + m2) * (a + m2)), -(a + m) * (qab + m) * x / ((a + m2) * (qap + m2))):
            d = 1.0 + aa * d
            d = 1.0 / (d if abs(d) > tiny else tiny)
            c = 1.0 + aa / c
            c = c if abs(c) > tiny else tiny
            h *= d * c
        if abs(d * c - 1.0) < 1e-15:
            break
    return h


def betainc(a: float, b: float, x: float) -> float:
    """The regularised incomplete beta I_x(a, b)."""
    if x <= 0.0:
        return 0.0
    if x >= 1.0:
        return 1.0
    front = math.exp(math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b) + a * math.log(x) + b * math.log1p(-x))
    if x < (a + 1.0) / (a + b + 2.0):
        return front * _betacf(a, b, x) / a
    return 1.0 - front * _betacf(b, a, 1.0 - x) / b


def f_sf(x: float, dfn: float, dfd: float) -> float:
    """P(F > x) for an F variable with (``dfn``, ``dfd``) degrees of freedom."""
    if x <= 0.0:
        return 1.0
    if math.isinf(x):
        return 0.0
    return betainc(dfd / 2.0, dfn / 2.0, dfd / (dfd + dfn * x))


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


def _tie_sizes(values: Sequence[float]) -> list[int]:
    """The sizes of the groups of equal values (groups of one included: they add nothing to t^3 - t)."""
    counts: dict[float, int] = {}
    for v in values:
        counts[v] = counts.get(v, 0) + 1
    return list(counts.values())


def compare_ranks(table: Mapping[str, Mapping[str, float]], policies: Sequence[str]) -> dict[str, object]:
    """``table``: system -> policy -> score (higher is better). Average ranks, Friedman's statistic and p-value
    corrected for ties, Iman-Davenport's F and its p-value (None with fewer than 2 systems or policies) and the
    Nemenyi critical difference at 5 %."""
    systems = [s for s in table if all(p in table[s] for p in policies)]
    n, k = len(systems), len(policies)
    ranks = {s: rank_rows({p: table[s][p] for p in policies}) for s in systems}
    average = {p: (sum(ranks[s][p] for s in systems) / n if n else None) for p in policies}
    out: dict[str, object] = {"systems": systems, "ranks": ranks, "average_rank": average,
                              "friedman_chi2": None, "friedman_p": None, "critical_difference": None}
    out.update(iman_davenport_f=None, iman_davenport_p=None)
    if n >= 2 and k >= 2:
        chi2 = 12.0 * n / (k * (k + 1)) * sum((average[p] or 0.0) ** 2 for p in policies) - 3.0 * n * (k + 1)
        ties = sum(t**3 - t for s in systems for t in _tie_sizes([table[s][p] for p in policies]))
        correction = 1.0 - ties / (n * k * (k * k - 1))
        if correction <= 0.0:  # every system ties every policy: nothing tells them apart
            chi2, correction = 0.0, 1.0
        chi2 /= correction
        out["friedman_chi2"] = round(chi2, 4)
        out["friedman_p"] = round(chi2_sf(max(chi2, 0.0), k - 1), 6)
        denominator = n * (k - 1) - chi2
        f = math.inf if denominator <= 1e-12 else (n - 1) * chi2 / denominator
        out["iman_davenport_f"] = None if math.isinf(f) else round(f, 4)
        out["iman_davenport_p"] = round(f_sf(max(f, 0.0), k - 1, (k - 1) * (n - 1)), 6)
        if k in NEMENYI_Q05:
            out["critical_difference"] = round(NEMENYI_Q05[k] * math.sqrt(k * (k + 1) / (6.0 * n)), 4)
    return out
