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
- `cross_entropy_mixture`: the cross-entropy method on a few selected coordinates with a
  defensive Gaussian mixture proposal. Each stage tests, on its weighted elite samples, which
  coordinates the elite set has moved (the weighted elite mean and variance of every candidate
  coordinate against N(0, 1), Bonferroni-corrected), keeps those (at most ``max_selected``,
  once kept always kept) and fits a ``components``-component diagonal normal mixture to the
  elite samples of those coordinates only (weighted EM); the proposal is
  ``alpha N(0, I) + (1 - alpha) mixture`` on the selected coordinates and N(0, 1) on all the
  others, so the likelihood ratio involves the selected coordinates only and is bounded by
  1 / alpha. A final importance-sampling stage gives the estimate (every stage counted).

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

from .._stats import wilson_interval

Margin = Callable[[np.ndarray], np.ndarray]


@dataclass
class Estimate:
    """A failure-probability estimate.

    Attributes:
        method: "crude", "is", "ce", "ce-mixture" or "subset".
        probability: the estimate; cv: its coefficient of variation (std / mean; inf without
            a failing sample); ci95: 95 % confidence interval (low, high).
        simulations: margin evaluations used (every stage); failures: failing samples in the
            estimating stage; n_final: samples of the estimating stage.
        stages: per stage (CE): level, number of samples, proposal mean norm; per level
            (subset, `afbl_jax.studies.rare.subset_simulation`): threshold, samples,
            acceptance rate, correlation factor gamma, conditional probability.
        z, margin, log_weight: the estimating stage's samples, margins and log weights.
        proposal: the final importance-sampling proposal (``cross_entropy_mixture``).
        cv_correlated: subset simulation: the cv if the levels' estimates were fully
            correlated (sum of the levels' cvs; ``cv`` assumes them uncorrelated).
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
    proposal: dict | None = None
    cv_correlated: float | None = None

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
            **({} if self.proposal is None else {"proposal": self.proposal}),
            **({} if self.cv_correlated is None else {"cv_correlated": self.cv_correlated}),
        }


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
    margin = evaluate_margin(g, z, batch)
    k = int(np.sum(margin > 0))
    p = k / n
    cv = math.sqrt((1 - p) / (n * p)) if k else float("inf")
    return Estimate("crude", p, cv, wilson_interval(k, n), n, k, n, [], z, margin, np.zeros(n))


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
    margin = evaluate_margin(g, z, batch)
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
        margin = evaluate_margin(g, z, batch)
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


@dataclass
class MixtureProposal:
    """``alpha N(0, I) + (1 - alpha) sum_k pi_k N(mu_k, diag(sigma_k^2))`` on the coordinates
    ``selected``, N(0, 1) on every other coordinate.

    Attributes:
        dimension: D; selected: indices (S,) of the coordinates the mixture acts on.
        alpha: weight of the nominal (defensive) component; weights (K,), means (K, S),
            sigmas (K, S): the mixture's components (K = 0: the nominal density).
    """

    dimension: int
    selected: np.ndarray
    alpha: float
    weights: np.ndarray
    means: np.ndarray
    sigmas: np.ndarray

    @classmethod
    def nominal(cls, dimension: int) -> MixtureProposal:
        e = np.zeros((0, 0))
        return cls(dimension, np.zeros(0, int), 1.0, np.zeros(0), e, e)

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        z = rng.standard_normal((n, self.dimension))
        if self.weights.size:
            pick = rng.choice(
                self.weights.size + 1, n, p=[self.alpha, *((1 - self.alpha) * self.weights)]
            )
            mixed = pick > 0
            k = pick[mixed] - 1
            zs = z[np.ix_(mixed, self.selected)]
            z[np.ix_(mixed, self.selected)] = self.means[k] + self.sigmas[k] * zs
        return z

    def log_ratio(self, z) -> np.ndarray:
        """log phi(z) - log q(z) (the selected coordinates only: the others cancel)."""
        if not self.weights.size:
            return np.zeros(z.shape[0])
        zs = z[:, self.selected]
        log_phi = stats.norm.logpdf(zs).sum(axis=-1)
        log_mix = special.logsumexp(
            np.log(self.weights)
            + stats.norm.logpdf(zs[:, None, :], self.means, self.sigmas).sum(axis=-1),
            axis=1,
        )
        log_q = np.logaddexp(math.log(self.alpha), math.log1p(-self.alpha) + log_mix - log_phi)
        return -log_q

    def tempered(self) -> MixtureProposal:
        """The square root of (this mixture x nominal), renormalised, component by component:
        a component N(mu, s^2) (per coordinate) becomes N(mu / (1 + s^2), 2 s^2 / (1 + s^2)),
        its weight pi becomes ~ sqrt(pi) x the Bhattacharyya coefficient of N(mu, s^2) and
        N(0, 1). Where the fitted mixture approximates the failure density phi(z_S) P(F | z_S)
        on the selected coordinates, this approximates phi(z_S) sqrt(P(F | z_S)), the proposal
        of least variance for the failure indicator when the other coordinates stay nominal;
        where P(F | z_S) is 0 or 1 (the selected coordinates decide failure), it is wider than
        needed."""
        if not self.weights.size:
            return self
        s2 = self.sigmas**2
        log_bc = np.sum(
            0.5 * np.log(2 * self.sigmas / (1 + s2)) - self.means**2 / (4 * (1 + s2)), axis=1
        )
        lw = 0.5 * np.log(self.weights) + log_bc
        return MixtureProposal(
            self.dimension,
            self.selected,
            self.alpha,
            np.exp(lw - special.logsumexp(lw)),
            self.means / (1 + s2),
            np.sqrt(2 * s2 / (1 + s2)),
        )

    def to_dict(self) -> dict:
        return {
            "selected": self.selected.tolist(),
            "alpha": self.alpha,
            "weights": self.weights.tolist(),
            "means": self.means.tolist(),
            "sigmas": self.sigmas.tolist(),
        }


def select_coordinates(z, w, candidates, level: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Coordinates whose weighted sample (z (n, D), normalised weights w (n,)) departs from
    N(0, 1): per candidate coordinate j, the statistics t_mean = m_j sqrt(n_eff) and t_var =
    (v_j - 1) sqrt(n_eff / 2) (m_j, v_j: weighted mean and second moment about it, n_eff =
    1 / sum w^2) are approximately N(0, 1) where z_j does not affect the weights; a coordinate
    is selected where max(|t_mean|, |t_var|) exceeds the two-sided Bonferroni bound at
    ``level`` over the candidates. Returns (selected indices sorted by decreasing statistic,
    the statistic (D,), 0 off the candidates)."""
    candidates = np.flatnonzero(np.asarray(candidates, dtype=bool))
    n_eff = 1.0 / np.sum(w**2)
    m = w @ z[:, candidates]
    v = w @ (z[:, candidates] - m) ** 2
    t = np.maximum(np.abs(m) * math.sqrt(n_eff), np.abs(v - 1) * math.sqrt(n_eff / 2))
    stat = np.zeros(z.shape[1])
    stat[candidates] = t
    bound = stats.norm.isf(level / (2 * max(candidates.size, 1)))
    order = candidates[np.argsort(-t)]
    return order[stat[order] > bound], stat


def fit_mixture(
    x,
    w,
    components: int,
    rng: np.random.Generator,
    sigma_floor: float = 0.5,
    iterations: int = 100,
    restarts: int = 4,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted EM for a diagonal normal mixture of ``components`` components (at most one per
    S + 1 effective samples) to the samples x (n, S) with weights w (n,) (normalised inside);
    ``restarts`` starts from weighted k-means++ picks of centres, the fit of the largest
    weighted log-likelihood kept; standard deviations floored at ``sigma_floor``; components
    with weight below 0.02 dropped. Returns (weights (K,), means (K, S), sigmas (K, S))."""
    w = np.asarray(w, dtype=np.float64)
    keep = w > 0
    x, w = np.asarray(x, dtype=np.float64)[keep], w[keep] / w[keep].sum()
    n_eff = 1.0 / np.sum(w**2)
    k = int(max(1, min(components, n_eff // (x.shape[1] + 1))))
    fits = [_em(x, w, k, rng, sigma_floor, iterations) for _ in range(restarts if k > 1 else 1)]
    return max(fits, key=lambda f: f[3])[:3]


def _em(x, w, k, rng, sigma_floor, iterations):
    centres = [x[rng.choice(x.shape[0], p=w)]]
    for _ in range(1, k):
        d2 = np.min(((x[:, None, :] - np.asarray(centres)[None]) ** 2).sum(-1), axis=1)
        q = w * d2
        centres.append(x[rng.choice(x.shape[0], p=q / q.sum())] if q.sum() > 0 else centres[0])
    d2 = ((x[:, None, :] - np.asarray(centres)[None]) ** 2).sum(-1)
    resp = np.eye(k)[np.argmin(d2, axis=1)]
    for _ in range(iterations):
        rw = resp * w[:, None]
        nk = rw.sum(0)
        live = nk > 0.02
        rw, nk = rw[:, live], nk[live]
        pi = nk / nk.sum()
        mu = (rw.T @ x) / nk[:, None]
        var = np.einsum("nk,nks->ks", rw, (x[:, None, :] - mu[None]) ** 2) / nk[:, None]
        sigma = np.sqrt(np.maximum(var, sigma_floor**2))
        log_r = np.log(pi) + stats.norm.logpdf(x[:, None, :], mu, sigma).sum(axis=-1)
        log_lik = special.logsumexp(log_r, axis=1, keepdims=True)
        new = np.exp(log_r - log_lik)
        if new.shape == resp.shape and np.max(np.abs(new - resp)) < 1e-6:
            break
        resp = new
    return pi, mu, sigma, float(w @ log_lik[:, 0])


def cross_entropy_mixture(
    g: Margin,
    dimension: int,
    n_per_stage: int,
    n_final: int,
    rng: np.random.Generator,
    rho: float = 0.1,
    max_stages: int = 12,
    candidates=None,
    max_selected: int = 8,
    components: int = 2,
    alpha: float = 0.1,
    selection_level: float = 0.05,
    temper: bool = True,
    batch=None,
) -> Estimate:
    """Cross-entropy method with coordinate selection and a defensive mixture (module
    docstring). The level of a stage is its (1 - rho)-quantile of the margin, or 0 once the
    pooled failing samples amount to rho n_per_stage / 2 effective samples.
    ``candidates``: boolean mask (D,) of the coordinates that may be selected
    (default all); ``alpha``: the nominal component's weight in every proposal after the
    first stage (weights <= 1 / alpha); ``selection_level``: family-wise level of the
    selection tests of one stage; ``temper``: the final stage samples
    `MixtureProposal.tempered` of the fitted mixture (for failures that the selected
    coordinates do not decide alone). The estimate uses the final stage only (unbiased for the
    proposal it was drawn from, whatever the earlier stages found)."""
    if not 0 < rho < 1:
        raise ValueError(f"rho must lie in (0, 1), got {rho}.")
    if not 0 < alpha < 1:
        raise ValueError(f"alpha must lie in (0, 1), got {alpha}.")
    if components < 1 or max_selected < 1:
        raise ValueError(
            f"components and max_selected must be >= 1, got {components}, {max_selected}."
        )
    candidates = np.ones(dimension, bool) if candidates is None else np.asarray(candidates, bool)
    proposal = MixtureProposal.nominal(dimension)
    selected: list[int] = []
    used, stages = 0, []
    pool_z, pool_m, proposals = [], [], []
    for _ in range(max_stages):
        z = proposal.sample(n_per_stage, rng)
        margin = evaluate_margin(g, z, batch)
        used += n_per_stage
        level = min(0.0, float(np.quantile(margin, 1 - rho)))
        pool_z.append(z)
        pool_m.append(margin)
        proposals.append(proposal)
        # every stage's samples, weighted against the equal mixture of the stages' proposals
        # (the balance heuristic: no stage's samples dominate through their own proposal)
        zz, mm = np.concatenate(pool_z), np.concatenate(pool_m)
        lw = -special.logsumexp([-q.log_ratio(zz) for q in proposals], axis=0)
        lw += math.log(len(proposals))
        # enough failures pooled to fit at level 0 (where the unselected variates decide
        # failure, no proposal on the selected ones makes a fraction rho of a stage fail)
        failed = mm > 0
        if failed.any():
            wf = np.exp(lw[failed] - lw[failed].max())
            if wf.sum() ** 2 / np.sum(wf**2) >= rho * n_per_stage / 2:
                level = 0.0
        elite = mm >= level
        w = np.where(elite, np.exp(lw - np.max(lw[elite])), 0.0)
        w /= w.sum()
        new, stat = select_coordinates(zz[elite], w[elite], candidates, selection_level)
        for j in new:
            if len(selected) < max_selected and j not in selected:
                selected.append(int(j))
        if not selected:  # nothing significant yet: the strongest candidate
            selected.append(int(np.argmax(stat)))
        sel = np.array(sorted(selected))
        pi, mu, sigma = fit_mixture(zz[:, sel], w, components, rng)
        proposal = MixtureProposal(dimension, sel, alpha, pi, mu, sigma)
        stages.append(
            {
                "level": level,
                "samples": n_per_stage,
                "failures": int(np.sum(margin > 0)),
                "elite_effective_samples": float(1.0 / np.sum(w**2)),
                "selected": sel.tolist(),
                "components": int(pi.size),
                "mean_norm": float(np.max(np.linalg.norm(mu, axis=1))),
            }
        )
        if level >= 0.0:
            break
    if temper:
        proposal = proposal.tempered()
    z = proposal.sample(n_final, rng)
    margin = evaluate_margin(g, z, batch)
    log_w = proposal.log_ratio(z)
    est = _weighted(margin > 0, log_w, "ce-mixture", used + n_final, z, margin, stages)
    est.proposal = proposal.to_dict()
    return est


def evaluate_margin(g: Margin, z, batch) -> np.ndarray:
    """g(z) in float64, in calls of at most ``batch`` points (None: one call)."""
    if batch is None or batch >= z.shape[0]:
        return np.asarray(g(z), dtype=np.float64)
    return np.concatenate(
        [np.asarray(g(z[i : i + batch]), dtype=np.float64) for i in range(0, z.shape[0], batch)]
    )


def normal_tail(beta: float) -> float:
    """P(N(0, 1) > beta) (for the toy problems' known probabilities)."""
    return float(stats.norm.sf(beta))
