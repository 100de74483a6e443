"""Rare failures: failure margin (sign = status, gradient = finite differences), the sampler's
variates (bit-identical cases), estimators on toy problems with known probabilities, the
falsification bounds, sensitivities on a toy function with a known ranking."""

import jax
import numpy as np
import pytest

import afbl_jax as A
import afbl_jax.studies.montecarlo as mc
from afbl_jax.metrics import FAILED_MARGIN, BatchMetrics, peak_margin
from afbl_jax.studies import rare

SHORT = {  # a short, cheap distribution (4 s runs, 8 turbulence lines)
    "time": {"t1": 4.0},
    "pulses": {"start": [0.5, 3.0]},
    "gust": {"start": [0.5, 3.0]},
    "turbulence": {"n_frequencies": 8},
}


def _metrics(att, alt, status):
    n = len(att)
    z = np.zeros(n)
    return BatchMetrics(
        z, z, z, z, np.asarray(status), z, z, z, np.asarray(att), np.asarray(alt), z, z, z, z, z
    )


def test_divergence_limits_are_the_failure_limits():
    lim = A.DivergenceLimits()
    assert float(lim.attitude) == A.metrics.FAILURE_ATTITUDE
    assert float(lim.altitude_error) == A.metrics.FAILURE_ALTITUDE


def test_margin_formula_and_smooth_upper_bound():
    m = _metrics([0.6, 1.5, 0.1, np.nan, 1.3], [2.0, 1.0, 12.0, np.nan, 1.0], [0, 1, 1, 1, 0])
    pm = np.asarray(peak_margin(m))
    np.testing.assert_allclose(pm[:3], [-0.5, 0.25, 0.2])
    assert pm[3] == np.inf
    fm = np.asarray(A.failure_margin(m))
    np.testing.assert_allclose(fm, [-0.5, 0.25, 0.2, np.inf, 0.0])  # ok run: min(pm, 0)
    assert np.all((fm > 0) == (np.asarray(m.status) != 0))
    m2 = _metrics([0.6, 0.1], [2.0, 1.0], [0, 1])  # failed between samples: small positive
    assert np.asarray(A.failure_margin(m2))[1] == FAILED_MARGIN
    # with limits given, ok runs beyond them fail too
    assert np.asarray(A.failure_margin(m, 0.5, 10.0))[0] > 0
    for t in (0.01, 0.05, 0.2):
        sm = np.asarray(A.smooth_margin(m, temperature=t))[:3]
        assert np.all(sm >= pm[:3]) and np.all(sm <= pm[:3] + t * np.log(2) + 1e-12)


def test_margin_sign_agrees_with_status():
    """On the Monte-Carlo default path (the single-case and vmap paths give the same columns:
    test_montecarlo compares every metric column across the paths), torque pulses up to about
    the vehicle's roll authority so that flyable cases fail too; the margin is that of the
    simulated run, also for the cases outside the flight envelope (their status says so)."""
    dist = mc.Distribution.from_dict(
        {**SHORT, "pulses": {**SHORT["pulses"], "torque": [-1.0, 1.0]}}
    )
    chunk = mc.sample_cases(dist, 64, 3)
    cols = mc.run_chunk(A.AFBL(), chunk)
    flyable = cols["status"] != A.sim.STATUS_OUTSIDE_ENVELOPE
    failed = cols["status"] != 0
    assert 0 < failed[flyable].sum() < flyable.sum()  # both kinds present at this size
    assert np.array_equal(cols["failure_margin"][flyable] > 0, failed[flyable])
    ok = ~failed
    expected = np.minimum(
        np.maximum(cols["peak_attitude_error"] / 1.2, cols["peak_altitude_error"] / 10.0) - 1, 0
    )
    # the default path computes the margin in float32 (eps 1.2e-7) from its float32 peaks
    np.testing.assert_allclose(cols["failure_margin"][ok], expected[ok], rtol=1e-6)


@pytest.mark.slow
def test_margin_sign_agrees_with_status_4096_case_study():
    chunk = mc.sample_cases(mc.default_distribution(), 4096, 0)
    for ctrl in (A.FBLPID(), A.AFBL()):
        cols = mc.run_chunk(ctrl, chunk)
        flyable = cols["status"] != A.sim.STATUS_OUTSIDE_ENVELOPE
        assert np.array_equal(cols["failure_margin"][flyable] > 0, cols["status"][flyable] != 0)


@pytest.mark.default_codegen
def test_cases_from_variates_are_the_sampled_cases():
    dist = mc.default_distribution()
    u = mc.draw_variates(dist, 12, 5, start=7)
    assert u.shape == (12, len(mc.variate_names(dist)))
    assert np.all((np.asarray(u) >= 0) & (np.asarray(u) < 1))
    a = mc.sample_cases(dist, 12, 5, start=7)
    b = mc.cases_from_variates(dist, u, index=np.arange(7, 19))
    la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
    assert len(la) == len(lb)
    for x, y in zip(la, lb, strict=True):
        assert np.array_equal(np.asarray(x), np.asarray(y), equal_nan=True)


def test_variates_draw_what_jax_random_draws():
    """Independent check of the split: inputs drawn directly with jax.random from the case
    keys, as the sampler always drew them (a distribution that draws every input: turbulence
    levels from a table, initial perturbations)."""
    dist = mc.Distribution.from_dict(
        {
            "mean_wind": {"source": "w20"},
            "turbulence": {"intensity": "table"},
            "initial": {"attitude": [-0.1, 0.1]},
        }
    )
    spec = dist.spec
    batch = mc.sample_cases(dist, 8, 11)
    keys = mc.case_keys(11, np.arange(8))
    for i in range(8):
        k = jax.random.split(keys[i], 24)
        lo, hi = spec["payload"]["fraction"]
        want = jax.random.uniform(k[0], minval=lo, maxval=hi)
        assert float(batch.inputs["payload_fraction"][i]) == float(want)
        lo, hi = spec["initial"]["attitude"]
        att = jax.random.uniform(k[19], (3,), minval=lo, maxval=hi)
        assert float(batch.inputs["initial_theta"][i]) == float(att[1])
        probs = spec["turbulence"]["intensity_probabilities"]
        p = np.array([probs[n] for n in A.scenario.TURBULENCE_INTENSITIES])
        level = jax.random.choice(k[17], 4, p=p / p.sum())
        assert int(batch.inputs["turbulence_level"][i]) == int(level)
        lo, hi = spec["gust"]["start"]
        start = jax.random.uniform(k[16], minval=lo, maxval=hi)
        assert float(batch.inputs["gust_start"][i]) == float(start)


def test_standard_normal_maps_round_trip():
    z = np.linspace(-6, 6, 13)
    np.testing.assert_allclose(rare.to_normal(rare.to_unit(z[2:-2])), z[2:-2], atol=1e-9)
    assert np.all(np.isfinite(rare.to_normal(np.array([0.0, 1.0]))))


# ---- estimators on toy problems: g(z) = a . z - beta, P(g > 0) = 1 - Phi(beta) -------------


def _toy(d=10, beta=3.5):
    a = np.ones(d) / np.sqrt(d)
    return (lambda z: z @ a - beta), a, rare.normal_tail(beta)


def test_importance_weights_are_unbiased_on_a_toy_problem():
    g, a, p = _toy()
    rng = np.random.default_rng(0)
    # a deliberately off-centre proposal: unbiased all the same
    est = [rare.importance_sampling(g, 2.5 * a + 0.3, 400, rng).probability for _ in range(200)]
    mean, se = np.mean(est), np.std(est, ddof=1) / np.sqrt(len(est))
    assert abs(mean - p) < 3.5 * se
    # the weights themselves have expectation 1 under the proposal
    z = 2.5 * a + rng.standard_normal((200000, a.size))
    from afbl_jax.studies.rare._estimators import _log_ratio

    w = np.exp(_log_ratio(z, 2.5 * a, np.ones(a.size)))
    assert abs(np.mean(w) - 1.0) < 4 * np.std(w) / np.sqrt(w.size)


def test_cross_entropy_intervals_cover_the_true_probability():
    g, a, p = _toy(d=8, beta=4.0)  # p = 3.2e-5
    rng = np.random.default_rng(1)
    runs = [rare.cross_entropy(g, 8, 300, 600, rng) for _ in range(60)]
    cover = np.mean([r.ci95[0] <= p <= r.ci95[1] for r in runs])
    assert 0.85 <= cover <= 1.0
    est = np.array([r.probability for r in runs])
    assert abs(est.mean() - p) < 3.5 * est.std(ddof=1) / np.sqrt(len(est))
    # crude Monte-Carlo needs (1 - p) / (p cv^2) samples for the same cv: >= 10x more
    assert all(10 * r.simulations < (1 - p) / (p * r.cv**2) for r in runs)
    assert np.median([r.cv for r in runs]) < 0.15


def _two_modes(d=30):
    """Two failure modes in different coordinates: (z0 + z2) / sqrt 2 > 3 or z1 < -3.2
    (independent, so P = 1 - (1 - Q(3)) (1 - Q(3.2)) = 2.04e-3); the other coordinates inert."""

    def g(z):
        return np.maximum((z[:, 0] + z[:, 2]) / np.sqrt(2) - 3.0, -z[:, 1] - 3.2)

    p = 1 - (1 - rare.normal_tail(3.0)) * (1 - rare.normal_tail(3.2))
    return g, d, p


def test_mixture_proposal_density_and_weights():
    from scipy import stats

    q = rare.MixtureProposal(
        4,
        np.array([0, 2]),
        0.2,
        np.array([0.7, 0.3]),
        np.array([[2.0, 1.0], [-1.0, 3.0]]),
        np.array([[0.5, 1.5], [1.0, 0.7]]),
    )
    rng = np.random.default_rng(0)
    z = q.sample(200000, rng)
    # log phi - log q against the densities written out with scipy (selected coordinates)
    zs = z[:50, [0, 2]]
    nominal = stats.multivariate_normal(np.zeros(2)).pdf(zs)
    mix = sum(
        wk * stats.multivariate_normal(m, np.diag(s**2)).pdf(zs)
        for wk, m, s in zip(q.weights, q.means, q.sigmas, strict=True)
    )
    np.testing.assert_allclose(q.log_ratio(z[:50]), np.log(nominal / (0.2 * nominal + 0.8 * mix)))
    w = np.exp(q.log_ratio(z))
    assert abs(w.mean() - 1) < 4 * w.std() / np.sqrt(w.size)  # E_q[phi / q] = 1
    assert w.max() <= 1 / 0.2 + 1e-12  # the defensive component bounds the weights
    # the unselected coordinates stay standard normal
    np.testing.assert_allclose(z[:, [1, 3]].std(0), 1, atol=0.01)


def test_mixture_fit_and_coordinate_selection():
    rng = np.random.default_rng(1)
    x = np.concatenate(
        [rng.normal([3, 0], 0.6, (600, 2)), rng.normal([-1, -3], [1.0, 0.7], (400, 2))]
    )
    pi, mu, sigma = rare.fit_mixture(x, np.ones(len(x)), 2, rng)
    order = np.argsort(-pi)
    np.testing.assert_allclose(pi[order], [0.6, 0.4], atol=0.03)
    np.testing.assert_allclose(mu[order], [[3, 0], [-1, -3]], atol=0.15)
    np.testing.assert_allclose(sigma[order], [[0.6, 0.6], [1.0, 0.7]], atol=0.1)
    z = rng.standard_normal((400, 20))
    z[:, 3] += 0.5  # mean moved
    z[:, 7] *= 1.6  # spread moved
    chosen, stat = rare.select_coordinates(z, np.full(400, 1 / 400), np.ones(20, bool))
    assert set(chosen) == {3, 7} and stat.shape == (20,)


def test_cross_entropy_mixture_on_two_failure_modes():
    g, d, p = _two_modes()
    rng = np.random.default_rng(3)
    runs = [rare.cross_entropy_mixture(g, d, 400, 1000, rng) for _ in range(40)]
    est = np.array([r.probability for r in runs])
    assert abs(est.mean() - p) < 3.5 * est.std(ddof=1) / np.sqrt(len(est))
    cover = np.mean([r.ci95[0] <= p <= r.ci95[1] for r in runs])
    assert cover >= 0.8

    # both modes found (in most runs; EM and the selection tests may miss one, and the
    # defensive component keeps the estimate unbiased then): the driving coordinates are
    # adapted, and a component points towards each mode
    def both(r):
        sel = list(r.proposal["selected"])
        if not {0, 1, 2} <= set(sel):
            return False
        mu = np.asarray(r.proposal["means"])
        return np.any(mu[:, sel.index(0)] + mu[:, sel.index(2)] > 2) and np.any(
            mu[:, sel.index(1)] < -2
        )

    assert np.mean([both(r) for r in runs]) >= 0.8
    # crude Monte-Carlo needs (1 - p) / (p cv^2) samples for the spread these estimates show
    cv = est.std(ddof=1) / p
    assert 10 * np.median([r.simulations for r in runs]) < (1 - p) / (p * cv**2)
    # the reported cv is the spread's order of magnitude
    assert 0.5 < np.median([r.cv for r in runs]) / cv < 2.0


def test_crude_wilson_interval_covers():
    g, a, p = _toy(d=3, beta=1.5)
    rng = np.random.default_rng(2)
    cover = np.mean(
        [(lambda r: r.ci95[0] <= p <= r.ci95[1])(rare.crude(g, 3, 400, rng)) for _ in range(100)]
    )
    assert 0.88 <= cover <= 1.0


# ---- subset simulation ---------------------------------------------------------------------------


def test_subset_simulation_on_a_linear_limit_state_at_1e6():
    """g = a.z - beta, |a| = 1, D = 200: p = Phi(-4.75) = 1.02e-6 exactly. Subset simulation is
    biased by O(1 / N) (thresholds from the same samples; a few per cent at N = 1000, far below
    the standard error of the mean of 60 runs, ~6 %): the mean of 60 runs lies within 3.5
    standard errors of the truth."""
    d, beta = 200, 4.75
    g, a, p = _toy(d=d, beta=beta)
    rng = np.random.default_rng(11)
    runs = [rare.subset_simulation(g, d, 1000, rng) for _ in range(60)]
    est = np.array([r.probability for r in runs])
    assert abs(est.mean() - p) < 3.5 * est.std(ddof=1) / np.sqrt(est.size)
    spread = est.std(ddof=1) / p
    cvs = np.array([r.cv for r in runs])
    # the reported cv assumes uncorrelated levels: a lower bound, of the spread's size
    assert 0.5 < np.median(cvs) / spread <= 1.1
    assert np.all([r.cv <= r.cv_correlated for r in runs])
    # the log-normal 95 % intervals cover the truth in most runs (less than 95 %: cv is low)
    cover = np.mean([r.ci95[0] <= p <= r.ci95[1] for r in runs])
    assert cover >= 0.75
    r = runs[0]
    levels = len(r.stages)
    assert 5 <= levels <= 8  # log(1e-6) / log(0.1) = 6 levels, give or take one
    assert r.simulations == 1000 + (levels - 1) * 900  # seeds are the chains' first states
    assert r.stages[-1]["threshold"] == 0.0
    assert all(s["threshold"] < 0 for s in r.stages[:-1])
    assert np.all(np.diff([s["threshold"] for s in r.stages]) > 0)
    assert all(0.2 < s["acceptance_rate"] < 0.7 for s in r.stages[1:])  # aCS near 0.44
    assert np.all(np.exp(r.log_weight) * (r.margin > 0)).mean() >= 0
    np.testing.assert_allclose(np.mean(np.exp(r.log_weight) * (r.margin > 0)), r.probability)


def test_subset_simulation_on_a_series_system_of_two_modes():
    """Failure if (z0 + z2) / sqrt 2 > 3 or z1 < -3.2 in 30 dimensions (p = 2.04e-3 exactly):
    the chains must keep both modes. Mean of 40 runs within 3.5 standard errors; intervals
    cover the truth in >= 75 % of the runs."""
    g, d, p = _two_modes()
    rng = np.random.default_rng(12)
    runs = [rare.subset_simulation(g, d, 1000, rng, p0=0.2) for _ in range(40)]
    est = np.array([r.probability for r in runs])
    assert abs(est.mean() - p) < 3.5 * est.std(ddof=1) / np.sqrt(est.size)
    assert np.mean([r.ci95[0] <= p <= r.ci95[1] for r in runs]) >= 0.75
    # both modes among the last level's failing samples in most runs
    both = [
        np.any((r.z[:, 0] + r.z[:, 2]) / np.sqrt(2) > 3) and np.any(r.z[:, 1] < -3.2) for r in runs
    ]
    assert np.mean(both) >= 0.75


def test_subset_chains_keep_the_conditional_distribution():
    """The batched aCS steps leave N(0, I) restricted to {g > b} invariant: with an always-true
    g the chains stay standard normal; with g = z0 - 1 > 0 they stay truncated normal in z0 and
    standard normal elsewhere (KS tests on the final states of 2000 independent chains, started
    from exact draws), and every state satisfies g > b."""
    from scipy import stats

    from afbl_jax.studies.rare._subset import conditional_chains

    rng = np.random.default_rng(5)
    nc, d = 2000, 6
    z0 = rng.standard_normal((nc, d))
    states, margins, rates, _ = conditional_chains(
        lambda z: np.zeros(len(z)), z0, np.zeros(nc), -1.0, 10, rng
    )
    assert np.all(rates == 1.0)
    for j in range(d):
        assert stats.kstest(states[-1][:, j], "norm").pvalue > 1e-3
    np.testing.assert_allclose(states[-1].mean(0), 0, atol=0.1)
    np.testing.assert_allclose(states[-1].var(0), 1, atol=0.12)
    seeds = rng.standard_normal((nc, d))
    seeds[:, 0] = stats.truncnorm.rvs(1.0, np.inf, size=nc, random_state=rng)
    calls = []

    def g(z):
        calls.append(len(z))
        return z[:, 0] - 1.0

    states, margins, rates, _ = conditional_chains(g, seeds, g(seeds), 0.0, 12, rng)
    assert calls[1:] == [nc] * 12  # one call of g per step for all the chains
    assert np.all(margins > 0) and np.allclose(margins, states[..., 0] - 1.0)
    assert 0.2 < rates[-4:].mean() < 0.7 and np.any(states[-1] != seeds)
    assert stats.kstest(states[-1][:, 0], stats.truncnorm(1.0, np.inf).cdf).pvalue > 1e-3
    for j in range(1, d):
        assert stats.kstest(states[-1][:, j], "norm").pvalue > 1e-3


def test_subset_correlation_factor_and_arguments():
    from afbl_jax.studies.rare._subset import correlation_factor

    rng = np.random.default_rng(0)
    # chains constant along their states: rho(k) = 1, gamma = 2 sum (1 - k / Ns) = Ns - 1
    ind = np.repeat(rng.random((200, 1)) < 0.3, 10, axis=1)
    assert correlation_factor(ind) == pytest.approx(9.0)
    # independent states: gamma ~ 0 (standard error ~ 2 sqrt(Ns / (Nc Ns)) ~ 0.03)
    assert abs(correlation_factor(rng.random((2000, 10)) < 0.3)) < 0.15
    assert correlation_factor(np.ones((5, 10), bool)) == 0.0
    g, a, p = _toy(d=4, beta=1.0)
    for kw, msg in (({"p0": 0.7}, "p0 must lie in"), ({"p0": 0.0}, "p0 must lie in")):
        with pytest.raises(ValueError, match=msg):
            rare.subset_simulation(g, 4, 100, rng, **kw)
    with pytest.raises(ValueError, match="chains"):
        rare.subset_simulation(g, 4, 10, rng, p0=0.1)
    # a probability above p0: level 0 alone (crude), Wilson-sized cv
    r = rare.subset_simulation(g, 4, 4000, rng)
    assert len(r.stages) == 1 and r.simulations == 4000
    assert abs(r.probability - p) < 4 * np.sqrt(p * (1 - p) / 4000)
    # no failure within max_levels: estimate 0, an upper bound from the levels reached
    g2, _, _ = _toy(d=4, beta=30.0)
    r = rare.subset_simulation(g2, 4, 200, rng, max_levels=2)
    assert r.probability == 0 and r.cv == np.inf and len(r.stages) == 3
    last = r.stages[-1]
    assert last["threshold"] < 0 and r.ci95[1] == last["p_above_threshold_high"]
    assert 1e-3 * 0.5 < last["p_above_threshold"] < 1e-3 * 2  # p0^3 by construction


# ---- falsification on a toy problem (duck-typed MarginProblem) ---------------------------------


class ToyProblem:
    """margin(u) = 3 (u0 + u1) - 5 on [0, 1]^3 (fails only near the corner u0 = u1 = 1); u2 is
    discrete and must stay put; records every point it is asked about."""

    dimension = 3
    free = np.array([True, True, False])

    def __init__(self):
        self.seen = []

    def margin(self, u):
        u = np.asarray(u)
        self.seen.append(u.copy())
        return 3 * (u[:, 0] + u[:, 1]) - 5

    def value_and_grad(self, u, output="margin"):
        u = np.asarray(u)
        self.seen.append(u.copy())
        m = 3 * (u[:, 0] + u[:, 1]) - 5
        return m, np.tile([3.0, 3.0, 1.0], (len(u), 1)), m


def test_falsification_respects_the_bounds_and_finds_the_failure():
    starts = np.random.default_rng(0).random((4, 3)) * 0.5
    for search in (
        lambda p: rare.gradient_ascent(p, starts, 200, learning_rate=0.1),
        lambda p: rare.cmaes_search(p, starts, 200, seed=0),
    ):
        p = ToyProblem()
        r = search(p)
        seen = np.concatenate(p.seen)
        assert np.all((seen >= 0) & (seen <= 1))
        assert r.first_failure is not None and r.best_margin > 0
        assert set(seen[:, 2]) <= set(starts[:, 2])  # the discrete variate never moves


# ---- sensitivities: known ranking of a toy function ---------------------------------------------


def test_sensitivities_recover_the_known_ranking():
    c = np.array([0.5, 4.0, 0.0, 2.0])  # ranking x1 > x3 > x0 > x2 (inert)
    rng = np.random.default_rng(0)
    u = rng.random((256, 4))
    d = rare.dgsm(np.tile(c, (256, 1)), u @ c)
    assert list(np.argsort(-d["nu"])) == [1, 3, 0, 2]
    s = rare.sobol_indices(lambda x: x @ c + 0.3 * x[:, 1] * x[:, 3], 4, 512)
    assert list(np.argsort(-s["ST"])) == [1, 3, 0, 2]
    # DGSM bound holds for the total index (uniform inputs): S_T <= nu / (pi^2 V)
    d = rare.dgsm(np.tile(c, (256, 1)), u @ c)
    s = rare.sobol_indices(lambda x: x @ c, 4, 512)
    assert np.all(s["ST"][:2] <= d["bound"][:2] * 1.1 + 0.02)


# ---- the closed loop: gradient of the smooth margin against finite differences ----------------


@pytest.fixture(scope="module")
def short_problem():
    dist = mc.Distribution.from_dict(
        {
            "time": {"t1": 2.0},
            "pulses": {"start": [0.5, 1.5]},
            "gust": {"start": [0.5, 1.5]},
            "turbulence": {"n_frequencies": 4},
        }
    )
    # the problem of notebook 04 (one compiled program for both)
    return rare.MarginProblem(A.AFBL(), dist, attitude_limit=0.3, rtol=1e-8, atol=1e-10, n_save=51)


def test_margin_gradient_matches_finite_differences(short_problem):
    p = short_problem
    u = np.asarray(mc.draw_variates(p.distribution, 4, 2))
    value, grad, exact = p.value_and_grad(u)
    i = int(np.argmax(np.where(exact < -0.05, value, -np.inf)))  # an ok case, away from kinks
    names = p.names
    picks = [names.index(n) for n in ("payload_fraction", "mean_wind_speed", "pulse_torque[0]")]
    h = 1e-4
    plus, minus = np.repeat(u[i : i + 1], 4, 0), np.repeat(u[i : i + 1], 4, 0)
    for r, j in enumerate(picks):
        plus[r, j] += h
        minus[r, j] -= h
    fd = (p.value_and_grad(plus)[0][:3] - p.value_and_grad(minus)[0][:3]) / (2 * h)
    # agreement to 2e-3 of the gradient's scale (the adaptive solve and the sampled peaks leave
    # ~1e-3 of noise in the differences: measured 7e-4 on the smallest component)
    np.testing.assert_allclose(grad[i, picks], fd, rtol=0, atol=2e-3 * np.max(np.abs(fd)))
    # a gradient that matters: far above the differences' noise (against the 0.3 rad limit the
    # margin is -0.84 to -0.91 on these 2 s position-hold flights, moved by the wind and the
    # torque pulse)
    assert np.max(np.abs(fd)) > 1e-3
