"""Subset simulation (Au & Beck 2001) with adaptive conditional sampling (aCS; Papaioannou,
Betz, Zwirglmaier & Straub 2015, Prob. Eng. Mech. 41), batched over the chains.

The failure event is ``g(z) > 0`` for a batched ``g: (n, D) -> (n,)`` over standard-normal z
(the same convention as `afbl_jax.studies.rare.crude` and the importance-sampling estimators).
Level 0 is a crude sample of ``n_per_level`` points; each further level takes the samples above
the previous level's threshold b (its (1 - p0) sample quantile, capped at 0) as the seeds of
``n_per_level * p0`` Markov chains that sample N(0, I) conditioned on g > b, run for 1 / p0
states each (the seed being the first). The estimate is the product of the levels' conditional
probabilities; it stops at the first level whose threshold reaches 0.

MCMC: every chain proposes, for all coordinates at once, z' = rho z + sqrt(1 - rho^2) xi
(xi ~ N(0, I), rho_i = sqrt(1 - sigma_i^2) per coordinate): the preconditioned Crank-Nicolson
move, reversible with respect to N(0, I), so a candidate is accepted exactly where g(z') > b.
sigma_i = min(1, lambda s_i), s_i the seeds' standard deviation in coordinate i; lambda starts
at 0.6 (level 1; each later level starts from the previous level's last value) and moves after
each step towards the acceptance rate 0.44: log lambda += (a - 0.44) / sqrt(k) (k: the step of
the level; a: the step's acceptance rate over all chains). Every step moves ALL
chains together, so a step is ONE call of g on the chains' candidates (aCS adapts between
groups of chains run one after another; here the groups are the steps of all chains, and each
step's kernel leaves the conditional distribution invariant whatever lambda it uses).

Coefficient of variation (Au & Beck 2001): delta_j^2 = (1 - P_j) / (N P_j) (1 + gamma_j) per
level, gamma_j = 2 sum_{k=1}^{Ns-1} (1 - k / Ns) rho_j(k) from the chains' indicator
autocorrelation (gamma_0 = 0: level 0 is independent), and cv = sqrt(sum_j delta_j^2). The sum
assumes the levels' estimates are uncorrelated; they are positively correlated through the
seeds, so this cv is in practice a lower bound (``cv_correlated`` = sum_j delta_j, the fully
correlated bound, is recorded as well). The 95 % interval is log-normal: p exp(+-1.96
sqrt(log(1 + cv^2))). The estimate is biased by O(1 / N) (the thresholds are taken from the
same samples).

OpenTURNS' ``SubsetSampling`` and UQpy's ``SubsetSimulation`` both evaluate a batch per MCMC
step, but neither offers adaptive conditional sampling (OpenTURNS: a fixed-width component-wise
random walk; UQpy: its generic MCMC samplers, and a correlation factor with p0 = 0.1 written in)
or takes a numpy Generator, and the chains of a fixed-width walk barely move in 230 dimensions;
hence this implementation (numpy / scipy only).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import stats

from ._estimators import Estimate, Margin, evaluate_margin

TARGET_ACCEPTANCE = 0.44
Z95 = float(stats.norm.ppf(0.975))


def correlation_factor(indicator) -> float:
    """Au & Beck's gamma of the chains' indicator sequences ``indicator`` (Nc chains, Ns
    states): 2 sum_{k=1}^{Ns-1} (1 - k / Ns) rho(k), rho(k) = R(k) / R(0), R(k) the
    autocovariance at lag k averaged over chains and positions (about the pooled mean). 0 when
    the indicator is constant (R(0) = 0) or the chains have one state."""
    ind = np.asarray(indicator, dtype=np.float64)
    nc, ns = ind.shape
    p = ind.mean()
    r0 = p * (1 - p)
    if ns < 2 or r0 <= 0:
        return 0.0
    gamma = 0.0
    for k in range(1, ns):
        rk = np.mean(ind[:, : ns - k] * ind[:, k:]) - p**2
        gamma += 2 * (1 - k / ns) * rk / r0
    return float(gamma)


def lognormal_interval(p: float, cv: float) -> tuple[float, float]:
    """The log-normal 95 % interval p exp(+-1.96 sqrt(log(1 + cv^2))) of an estimate p > 0 with
    coefficient of variation cv."""
    s = math.sqrt(math.log1p(cv**2))
    return (p * math.exp(-Z95 * s), p * math.exp(Z95 * s))


def conditional_chains(
    g: Margin,
    seeds,
    seed_margins,
    threshold: float,
    steps: int,
    rng: np.random.Generator,
    lam: float = 0.6,
    batch=None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Run ``steps`` aCS steps of the chains started at ``seeds`` (Nc, D) (margins
    ``seed_margins`` > ``threshold``) targeting N(0, I) conditioned on g > threshold (module
    docstring). Returns (states (steps + 1, Nc, D), margins (steps + 1, Nc), acceptance rate
    per step (steps,), the final lambda)."""
    z = np.asarray(seeds, dtype=np.float64)
    m = np.asarray(seed_margins, dtype=np.float64)
    nc, dim = z.shape
    s = np.std(z, axis=0, ddof=1) if nc > 1 else np.ones(dim)
    states, margins, rates = [z], [m], []
    for k in range(1, steps + 1):
        sigma = np.minimum(1.0, lam * s)
        rho = np.sqrt(1.0 - sigma**2)
        cand = rho * z + sigma * rng.standard_normal((nc, dim))
        mc = evaluate_margin(g, cand, batch)
        accept = mc > threshold
        z = np.where(accept[:, None], cand, z)
        m = np.where(accept, mc, m)
        rate = float(np.mean(accept))
        lam = math.exp(math.log(lam) + (rate - TARGET_ACCEPTANCE) / math.sqrt(k))
        states.append(z)
        margins.append(m)
        rates.append(rate)
    return np.stack(states), np.stack(margins), np.asarray(rates), lam


def subset_simulation(
    g: Margin,
    dimension: int,
    n_per_level: int,
    rng: np.random.Generator,
    p0: float = 0.1,
    max_levels: int = 10,
    batch=None,
    echo=None,
) -> Estimate:
    """Subset simulation with batched aCS (module docstring).

    Args:
        g: margins (n,) of standard-normal points (n, D); failure: g > 0.
        dimension: D; n_per_level: samples per level N (N p0 chains of 1 / p0 states; both
            rounded to whole numbers, N p0 >= 2).
        rng: the random stream; p0: conditional probability of the intermediate levels, in
            (0, 0.5]; max_levels: most levels after level 0.
        batch: most points per call of g (None: one call per MCMC step, the default).
        echo: called with a line per level (None: quiet).

    Returns an `Estimate` (method "subset"): probability = product of the levels' conditional
    probabilities; cv and the log-normal 95 % interval of the module docstring; simulations:
    calls of g on points (level 0: N, each further level: the chains' candidates); failures and
    n_final: the last level's failing and total samples; stages: per level its threshold (the
    margin level it conditions the next on; 0 at the last), samples, failing samples,
    acceptance rate of the chains that made it (None at level 0), gamma, conditional
    probability and delta (its cv); z, margin: the last
    level's samples; log_weight: log of the product of the earlier levels' conditional
    probabilities, the same for every sample (each last-level sample represents that much
    nominal probability mass times the conditional density: the estimate is
    ``mean(exp(log_weight) * (margin > 0))``). If no level reaches 0 within ``max_levels`` (or
    ties at the top of the margins stop the levels), the last stage's threshold is below 0: the
    estimate is the last level's failing fraction times the product (0 if none failed: cv
    inf), and the last stage records ``p_above_threshold``, the estimate of
    P(g > threshold) >= P(failure), with the upper end of its log-normal 95 % interval,
    ``p_above_threshold_high``, which is the interval's upper end where no sample failed.
    """
    if not 0 < p0 <= 0.5:
        raise ValueError(f"p0 must lie in (0, 0.5], got {p0}.")
    nc = int(round(n_per_level * p0))
    if nc < 2:
        raise ValueError(f"n_per_level * p0 must be >= 2 chains, got {n_per_level} * {p0} = {nc}.")
    if max_levels < 0:
        raise ValueError(f"max_levels must be >= 0, got {max_levels}.")
    ns = int(math.ceil(n_per_level / nc))
    z = rng.standard_normal((n_per_level, dimension))
    margin = evaluate_margin(g, z, batch)
    simulations = n_per_level
    stages: list[dict] = []
    log_before = 0.0  # log of the product of the earlier levels' conditional probabilities
    gamma, rate, lam = 0.0, None, 0.6
    for level in range(max_levels + 1):
        n = margin.shape[0]
        b = _threshold(margin, nc)
        above = margin > b
        failing = margin > 0
        # stop at 0, after max_levels, or where ties at the top leave no sample above b
        last = b == 0.0 or level == max_levels or not above.any()
        # the factor of the product: P(g > b | previous level), at the last level P(g > 0 | .)
        p_level = float(np.mean(failing if last else above))
        stage = {
            "level": level,
            "threshold": float(b),
            "samples": int(n),
            "above_threshold": int(above.sum()),
            "failures": int(failing.sum()),
            "acceptance_rate": rate,
            "gamma": gamma,
            "conditional_probability": p_level,
            "delta": _delta(p_level, n, gamma),
        }
        if last and b < 0.0:
            # not converged: P(g > b) >= P(failure), estimated with its log-normal upper end
            p_above = math.exp(log_before) * float(np.mean(above))
            cv_above = math.sqrt(
                sum(st["delta"] ** 2 for st in stages) + _delta(np.mean(above), n, gamma) ** 2
            )
            stage["p_above_threshold"] = p_above
            stage["p_above_threshold_high"] = lognormal_interval(p_above, cv_above)[1]
        stages.append(stage)
        if echo is not None:
            echo(
                f"subset level {level}: {n} samples, threshold {b:+.4g}, conditional "
                f"probability {p_level:.4g}, failures {int(failing.sum())}"
                + ("" if rate is None else f", acceptance {rate:.3f}, gamma {gamma:.2f}")
            )
        if last:
            break
        log_before += math.log(p_level)
        # Nc = N p0 chains: where ties at the threshold (repeated states of rejected moves)
        # leave fewer samples above it, some of them seed two chains, so that every level
        # has N samples and every step calls g on Nc points (one compiled shape)
        idx = np.flatnonzero(above)
        if idx.size < nc:
            idx = np.concatenate([idx, rng.choice(idx, nc - idx.size)])
        states, margins, rates, lam = conditional_chains(
            g, z[idx], margin[idx], b, ns - 1, rng, lam, batch
        )
        simulations += (ns - 1) * nc
        # order by (step, chain): states (ns, Nc, D) -> (ns * Nc, D)
        z = states.reshape(-1, dimension)
        margin = margins.reshape(-1)
        rate = float(np.mean(rates)) if rates.size else None
        # gamma of the indicator the next level estimates, along each chain (chains x states)
        b_next = 0.0 if level + 1 == max_levels else _threshold(margin, nc)
        gamma = correlation_factor((margins > b_next).T)
    p = math.exp(log_before) * stages[-1]["conditional_probability"]
    deltas = [st["delta"] for st in stages]
    cv = math.sqrt(sum(d**2 for d in deltas)) if p > 0 else math.inf
    if p > 0:
        ci = lognormal_interval(p, cv)
    else:
        ci = (0.0, stages[-1].get("p_above_threshold_high", math.exp(log_before)))
    return Estimate(
        "subset",
        p,
        cv,
        ci,
        simulations,
        int(np.sum(margin > 0)),
        int(margin.shape[0]),
        stages,
        z,
        margin,
        np.full(margin.shape[0], log_before),
        cv_correlated=float(sum(deltas)) if p > 0 else math.inf,
    )


def _threshold(margin, nc: int) -> float:
    """The level between the nc-th and (nc + 1)-th largest margins, capped at 0."""
    top = np.sort(margin)[::-1][: nc + 1]
    return min(0.0, 0.5 * float(top[nc - 1] + top[nc]))


def _delta(p: float, n: int, gamma: float) -> float:
    """Au & Beck's cv of a level's conditional probability p from n samples with correlation
    factor gamma (inf for p = 0)."""
    return math.sqrt((1 - p) / (n * p) * (1 + gamma)) if p > 0 else math.inf
