"""Confidence intervals for success rates: Wilson per arm, Newcombe for a difference.

Both are score intervals, so they stay inside [0, 1] (resp. [-1, 1]) and behave at
0/n and n/n, where the normal (Wald) interval collapses to a point.
"""

from __future__ import annotations

import math

Z_95 = 1.959964  # two-sided 95 % normal quantile


def _check(k: int, n: int) -> None:
    if n <= 0:
        raise ValueError(f"need at least one trial, got n={n}")
    if not 0 <= k <= n:
        raise ValueError(f"successes k={k} must lie in [0, n={n}]")


def wilson_ci(k: int, n: int, z: float = Z_95) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion k/n (Wilson 1927)."""
    _check(k, n)
    p = k / n
    z2 = z * z
    denom = 1.0 + z2 / n
    centre = (p + z2 / (2.0 * n)) / denom
    half = z * math.sqrt(p * (1.0 - p) / n + z2 / (4.0 * n * n)) / denom
    # At k=0 (k=n) the bound is exactly 0 (1); float noise would give -1e-17 or 0.9999...
    lo = 0.0 if k == 0 else max(0.0, centre - half)
    hi = 1.0 if k == n else min(1.0, centre + half)
    return lo, hi


def newcombe_diff_ci(k1: int, n1: int, k2: int, n2: int, z: float = Z_95) -> tuple[float, float]:
    """Interval for p1 - p2 from two independent arms: Newcombe's (1998) method 10,
    the hybrid score interval built from each arm's Wilson interval."""
    p1, p2 = k1 / n1 if n1 else 0.0, k2 / n2 if n2 else 0.0
    l1, u1 = wilson_ci(k1, n1, z)
    l2, u2 = wilson_ci(k2, n2, z)
    diff = p1 - p2
    lo = diff - math.sqrt((p1 - l1) ** 2 + (u2 - p2) ** 2)
    hi = diff + math.sqrt((u1 - p1) ** 2 + (p2 - l2) ** 2)
    return max(-1.0, lo), min(1.0, hi)


def excludes_zero(lo: float, hi: float) -> bool:
    """True when an interval for a difference lies strictly on one side of 0."""
    return lo > 0.0 or hi < 0.0
