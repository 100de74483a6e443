"""Failure-probability estimators over standard-normal inputs z (u = Phi(z) in the unit cube).

The failure event is ``g(z) > 0`` for a batched function ``g: (n, D) -> (n,)`` (the failure
margin of the cases at u = Phi(z)); the nominal density is the standard normal N(0, I).

- `crude`: plain Monte-Carlo.
- `importance_sampling`: samples from a shifted normal N(mu, I) (mu: e.g. the most likely
  failure found by `afbl_jax.studies.rare.falsify`), weights phi(z) / q(z).
- `cross_entropy`: the cross-entropy method (Rubinstein; De Boer et al. 2005): levels of the
  margin are raised adaptively, each stage refits the normal proposal's mean (and with
  ``adapt_scale`` its per-coordinate standard deviations) to the weighted elite samples
  (likelihood ratios to the nominal density), until the rho-quantile reaches 0; then a final
  importance-sampling stage with the fitted proposal gives the estimate. Only the final stage's
  samples enter the estimate (unbiased for any proposal that covers the failure region); every
  stage's simulations are counted.

Every estimator returns an `Estimate`: probability, coefficient of variation (of the
estimator), a 95 % confidence interval (crude: Wilson; importance sampling: normal
approximation of the weighted mean, clipped at 0), the simulations used and the samples.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy import special, stats

Margin = Callable[[np.ndarray], np.ndarray]


@dataclass
class Estimate:
    """A failure-probability estimate.

    Attributes:
        method: "crude", "is" or "ce".
        probability: the estimate; cv: its coefficient of variation (std / mean; inf without
            a failing sample); ci95: 95 % confidence interval (low, high).
        simulations: margin evaluations used (every stage); failures: failing samples in the
            estimating stage; n_final: samples of the estimating stage.
        stages: per stage (CE): level, number of samples, proposal mean norm.
        z, margin, log_weight: the estimating stage's samples, margins and log weights.
    """

    method: str
    probability: float
    cv: float
    ci95: tuple[float, float]
    simulations: int
    failures: int
    n_final: int
    stages: list = field(default_factory=list)
    z: np.ndarray | None = field(default=None, repr=False)
    margin: np.ndarray | None = field(default=None, repr=False)
    log_weight: np.ndarray | None = field(default=None, repr=False)

    def to_dict(self) -> dict:
        return {
            "method": self.method,
            "probability": self.probability,
            "cv": self.cv,
            "ci95": list(self.ci95),
            "simulations": self.simulations,
            "failures": self.failures,
            "n_final": self.n_final,
            "stages": self.stages,
        }


def wilson(k: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """Wilson score interval of k successes in n trials."""
    if n == 0:
        return (0.0, 1.0)
    p = k / n
    den = 1 + z**2 / n
    centre = (p + z**2 / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z**2 / (4 * n**2)) / den
    return (max(0.0, centre - half), min(1.0, centre + half))


def to_unit(z) -> np.ndarray:
    """u = Phi(z), clipped into [0, 1)."""
    return np.minimum(special.ndtr(np.asarray(z, dtype=np.float64)), np.nextafter(1.0, 0.0))


def to_normal(u) -> np.ndarray:
    """z = Phi^-1(u), u clipped into [1e-7, 1 - 1e-7] (the bounds 0, 1 map to |z| = 5.2)."""
    u = np.clip(np.asarray(u, dtype=np.float64), 1e-7, 1 - 1e-7)
    return special.ndtri(u)


def _log_ratio(z, mu, sigma) -> np.ndarray:
    """log phi(z) - log q(z) for q = N(mu, diag(sigma^2))."""
    zs = (z - mu) / sigma
    return np.sum(-0.5 * z**2 + 0.5 * zs**2 + np.log(sigma), axis=1)


def _weighted(indicator, log_w, method, simulations, z, margin, stages) -> Estimate:
    n = indicator.shape[0]
    w = np.where(indicator, np.exp(log_w), 0.0)
    p = float(np.mean(w))
    sd = float(np.std(w, ddof=1)) / math.sqrt(n) if n > 1 else float("inf")
    cv = sd / p if p > 0 else float("inf")
    ci = (max(0.0, p - 1.96 * sd), p + 1.96 * sd)
    return Estimate(
        method, p, cv, ci, simulations, int(indicator.sum()), n, stages, z, margin, log_w
    )


def crude(g: Margin, dimension: int, n: int, rng: np.random.Generator, batch=None) -> Estimate:
    """Plain Monte-Carlo: n standard-normal samples; Wilson interval; cv sqrt((1-p)/(n p))."""
    z = rng.standard_normal((n, dimension))
    margin = _evaluate(g, z, batch)
    k = int(np.sum(margin > 0))
    p = k / n
    cv = math.sqrt((1 - p) / (n * p)) if k else float("inf")
    return Estimate("crude", p, cv, wilson(k, n), n, k, n, [], z, margin, np.zeros(n))


def importance_sampling(
    g: Margin,
    mean,
    n: int,
    rng: np.random.Generator,
    scale=1.0,
    batch=None,
    simulations_before: int = 0,
    method: str = "is",
    stages=None,
) -> Estimate:
    """Importance sampling with the proposal N(mean, diag(scale^2)) (weights phi / q)."""
    mean = np.asarray(mean, dtype=np.float64)
    sigma = np.broadcast_to(np.asarray(scale, dtype=np.float64), mean.shape)
    z = mean + sigma * rng.standard_normal((n, mean.shape[0]))
    margin = _evaluate(g, z, batch)
    log_w = _log_ratio(z, mean, sigma)
    return _weighted(
        margin > 0, log_w, method, simulations_before + n, z, margin, list(stages or [])
    )


def cross_entropy(
    g: Margin,
    dimension: int,
    n_per_stage: int,
    n_final: int,
    rng: np.random.Generator,
    rho: float = 0.1,
    max_stages: int = 12,
    mean=None,
    adapt_scale: bool = False,
    batch=None,
    adapt=None,
) -> Estimate:
    """Cross-entropy method (module docstring) from the proposal N(mean, I) (default mean 0;
    e.g. the most likely failure found by falsification), then a final importance-sampling
    stage of ``n_final`` samples. ``adapt``: boolean mask (D,) of the coordinates whose
    proposal is fitted (default all); the others keep the nominal N(0, 1). In many
    dimensions, fitting coordinates that do not matter only adds noise to the mean and
    inflates the weights' variance (by about exp(|noise|^2))."""
    if not 0 < rho < 1:
        raise ValueError(f"rho must lie in (0, 1), got {rho}.")
    mu = np.zeros(dimension) if mean is None else np.asarray(mean, dtype=np.float64).copy()
    sigma = np.ones(dimension)
    adapt = np.ones(dimension, bool) if adapt is None else np.asarray(adapt, dtype=bool)
    mu = np.where(adapt, mu, 0.0)
    used, stages = 0, []
    for _ in range(max_stages):
        z = mu + sigma * rng.standard_normal((n_per_stage, dimension))
        margin = _evaluate(g, z, batch)
        used += n_per_stage
        level = min(0.0, float(np.quantile(margin, 1 - rho)))
        elite = margin >= level
        log_w = _log_ratio(z, mu, sigma)
        w = np.where(elite, np.exp(log_w - np.max(log_w[elite])), 0.0)
        w /= w.sum()
        mu = np.where(adapt, w @ z, 0.0)
        if adapt_scale:
            sigma = np.where(adapt, np.sqrt(np.maximum(w @ (z - mu) ** 2, 1e-4)), 1.0)
        stages.append(
            {"level": level, "samples": n_per_stage, "mean_norm": float(np.linalg.norm(mu))}
        )
        if level >= 0.0:
            break
    return importance_sampling(
        g, mu, n_final, rng, sigma, batch, simulations_before=used, method="ce", stages=stages
    )


def _evaluate(g: Margin, z, batch) -> np.ndarray:
    if batch is None or batch >= z.shape[0]:
        return np.asarray(g(z), dtype=np.float64)
    return np.concatenate(
        [np.asarray(g(z[i : i + batch]), dtype=np.float64) for i in range(0, z.shape[0], batch)]
    )


def normal_tail(beta: float) -> float:
    """P(N(0, 1) > beta) (for the toy problems' known probabilities)."""
    return float(stats.norm.sf(beta))
