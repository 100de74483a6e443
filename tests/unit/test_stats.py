"""The package's one Wilson score interval: against the formula written out, at n = 0, and its
coverage of a known proportion."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from afbl_jax.studies import montecarlo as mc
from afbl_jax.studies import rare

Z95 = 1.959963984540054


def _written_out(k: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson (1927): (p + z^2/2n -+ z sqrt(p(1-p)/n + z^2/4n^2)) / (1 + z^2/n)."""
    p = k / n
    centre = p + z**2 / (2 * n)
    half = z * math.sqrt(p * (1 - p) / n + z**2 / (4 * n**2))
    return ((centre - half) / (1 + z**2 / n), (centre + half) / (1 + z**2 / n))


def test_one_interval_for_the_package():
    assert mc.wilson_interval is rare.wilson_interval


@pytest.mark.parametrize("k,n", [(0, 1), (0, 40), (1, 40), (7, 13), (50, 100), (99, 100)])
def test_wilson_against_the_formula_written_out(k, n):
    assert mc.wilson_interval(k, n) == pytest.approx(_written_out(k, n), abs=1e-12)


def test_wilson_other_confidence_and_no_trials():
    z90 = stats.norm.ppf(0.95)
    assert mc.wilson_interval(3, 20, 0.90) == pytest.approx(_written_out(3, 20, z90), abs=1e-12)
    assert mc.wilson_interval(0, 0) == (0.0, 1.0)  # nothing observed: every proportion
    with pytest.raises(ValueError):
        mc.wilson_interval(5, 3)


@pytest.mark.parametrize("n,p", [(30, 0.5), (60, 0.2), (100, 0.02)])
def test_wilson_coverage_of_a_known_proportion(n, p):
    """Exact coverage (binomial probabilities summed over the k whose interval holds p) and the
    coverage over 4000 seeded draws both lie near the nominal 95 %; the Wald interval, which
    undercovers small proportions, is shown to fail the same check where it should."""
    ks = np.arange(n + 1)
    covers = np.array([lo <= p <= hi for lo, hi in (mc.wilson_interval(int(k), n) for k in ks)])
    exact = float(np.sum(stats.binom.pmf(ks, n, p)[covers]))
    assert 0.93 <= exact <= 0.975
    draws = np.random.default_rng(n).binomial(n, p, size=4000)
    assert 0.925 <= covers[draws].mean() <= 0.975
    if p < 0.05:
        wald = np.abs(ks / n - p) <= Z95 * np.sqrt(ks / n * (1 - ks / n) / n)
        assert float(np.sum(stats.binom.pmf(ks, n, p)[wald])) < 0.93
