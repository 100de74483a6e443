"""Statistics shared by the studies: the Wilson score interval of a binomial proportion."""

from __future__ import annotations


def wilson_interval(k: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval (without continuity correction) of a proportion of ``k`` successes
    in ``n`` trials, at the two-sided ``confidence`` level: ``scipy.stats.binomtest(k, n)
    .proportion_ci(confidence, method="wilson")`` as floats.

    With no trial (n = 0) nothing is known and the interval is the whole (0.0, 1.0). Raises
    ValueError unless 0 <= k <= n and 0 < confidence < 1.
    """
    from scipy.stats import binomtest

    if n == 0 and k == 0:
        if not 0.0 < confidence < 1.0:
            raise ValueError(f"confidence must lie in (0, 1), got {confidence}.")
        return (0.0, 1.0)
    ci = binomtest(int(k), int(n)).proportion_ci(confidence, method="wilson")
    return (float(ci.low), float(ci.high))
