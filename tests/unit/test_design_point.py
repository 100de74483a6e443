"""The design-point search (most likely failure) on toy limit states with known design points,
and `MarginProblem` on empty batches."""

import numpy as np
import pytest

import afbl_jax as A
import afbl_jax.studies.montecarlo as mc
from afbl_jax.studies import rare


def _pdf(z):
    return np.exp(-0.5 * z**2) / np.sqrt(2.0 * np.pi)


class ToyLimitState:
    """A `MarginProblem`-like object: margin g(z) of z = Phi^-1(u) (> 0 = failed), its gradient
    through u, the last variate discrete (not free). ``offset``: the smooth margin minus the
    exact one (the closed loop's smooth margin is an upper bound of the exact one)."""

    def __init__(self, g, grad_g, dimension, offset=0.0):
        self.g, self.grad_g, self.dimension, self.offset = g, grad_g, dimension, offset
        self.free = np.arange(dimension) < dimension - 1
        self.seen = []
        self.forward = 0

    def value_and_grad(self, u):
        z = rare.to_normal(u)
        self.seen.append(np.array(u))
        exact = self.g(z)
        grad_u = self.grad_g(z) / _pdf(z)  # dg/du = dg/dz / phi(z)
        return exact + self.offset, grad_u, exact

    def margin(self, u):
        self.forward += len(u)
        return self.g(rare.to_normal(u))


def _linear(beta, a):
    a = np.asarray(a, dtype=float) / np.linalg.norm(a)

    def g(z):
        return z[:, : len(a)] @ a - beta

    def grad(z):
        out = np.zeros_like(z)
        out[:, : len(a)] = a
        return out

    return g, grad, a


def test_design_point_of_a_linear_limit_state():
    """g = a . z - beta (|a| = 1): the design point is beta a, at distance beta."""
    beta = 3.0
    g, grad, a = _linear(beta, [1.0, -2.0, 0.5, 1.5])
    p = ToyLimitState(g, grad, 5)
    z_start = np.concatenate([1.6 * beta * a + np.array([0.8, 0.4, 0.0, -0.4]) * 0.5, [1.3]])
    u_start = rare.to_unit(z_start)
    assert p.margin(u_start[None])[0] > 0
    r = rare.design_point_search(p, u_start, budget=30, level=1e-6)
    assert r.margin > 0 and p.g(r.z[None])[0] > 0  # fails, re-checked forward
    assert r.distance == pytest.approx(beta, abs=1e-3)
    np.testing.assert_allclose(r.z[:4], beta * a, atol=1e-2)
    assert r.z[4] == pytest.approx(z_start[4])  # the discrete variate never moves
    np.testing.assert_allclose(np.concatenate(p.seen)[:, 4], u_start[4], rtol=1e-12)
    assert r.start_distance > 1.5 * beta
    assert r.gradient_simulations <= 30 and r.simulations == p.forward - 1
    assert 1 <= r.iterations <= r.gradient_simulations
    top = r.to_dict(names=list("abcde"), top=3)["top_variates"]
    assert [v["name"] for v in top] == ["b", "d", "a"]  # largest |z|: |a| ordered


def test_design_point_of_a_curved_limit_state():
    """g = z0 - beta + kappa |y|^2 (y = z1, z2): min z0^2 + |y|^2 on g = 0 is at
    |y|^2 = (beta - 1 / (2 kappa)) / kappa, z0 = 1 / (2 kappa) (beta kappa > 1/2), here
    |y|^2 = 4, z0 = 2, distance sqrt(8): off the axis, where the linearisation at the start
    (on the axis) does not point."""
    beta, kappa = 3.0, 0.25

    def g(z):
        return z[:, 0] - beta + kappa * (z[:, 1] ** 2 + z[:, 2] ** 2)

    def grad(z):
        out = np.zeros_like(z)
        out[:, 0] = 1.0
        out[:, 1:3] = 2 * kappa * z[:, 1:3]
        return out

    p = ToyLimitState(g, grad, 4)
    z_start = np.array([3.5, 0.3, -0.2, -0.7])
    r = rare.design_point_search(p, rare.to_unit(z_start), budget=40, level=1e-6)
    assert r.margin > 0
    assert r.distance == pytest.approx(np.sqrt(8.0), abs=2e-3)
    assert r.z[0] == pytest.approx(2.0, abs=1e-2)
    assert r.z[1] ** 2 + r.z[2] ** 2 == pytest.approx(4.0, abs=2e-2)


@pytest.mark.parametrize("budget", [1, 2, 3, 5])
def test_design_point_always_fails(budget):
    """Whatever the budget stops at, and with a smooth margin above the exact one (the search
    aims at points that do not fail), the result fails and is never farther than the start."""
    g, grad, a = _linear(2.5, [1.0, 1.0, -1.0])
    p = ToyLimitState(g, grad, 4, offset=0.05)
    z_start = np.concatenate([2.0 * 2.5 * a, [0.2]])
    r = rare.design_point_search(p, rare.to_unit(z_start), budget=budget)
    assert r.margin > 0 and p.g(r.z[None])[0] > 0
    assert r.distance <= r.start_distance + 1e-12
    assert r.gradient_simulations <= budget


def test_design_point_without_free_variates_is_the_start():
    g, grad, _ = _linear(2.0, [1.0])
    p = ToyLimitState(g, grad, 1)  # its only variate is the discrete one
    u = np.array([0.99])
    r = rare.design_point_search(p, u, budget=4)
    assert r.gradient_simulations == 0 and r.message == "no free variates"
    assert r.margin > 0 and r.distance == 0.0 and r.u[0] == pytest.approx(0.99)


def test_design_point_rejects_a_zero_budget():
    g, grad, _ = _linear(2.0, [1.0])
    with pytest.raises(ValueError, match="budget"):
        rare.design_point_search(ToyLimitState(g, grad, 2), np.full(2, 0.99), budget=0)


def test_margin_problem_on_an_empty_batch():
    dist = mc.Distribution.from_dict(
        {
            "time": {"t1": 2.0},
            "pulses": {"start": [0.5, 1.5]},
            "gust": {"start": [0.5, 1.5]},
            "turbulence": {"n_frequencies": 2},
        }
    )
    p = rare.MarginProblem(A.AFBL(), dist)
    empty = np.zeros((0, p.dimension))
    assert p.margin(empty).shape == (0,)
    m = p.metrics(empty)
    assert m.status.shape == (0,) and m.peak_attitude_error.shape == (0,)
    value, grad, exact = p.value_and_grad(empty)
    assert value.shape == (0,) and grad.shape == (0, p.dimension) and exact.shape == (0,)
    assert p.simulations == 0 and p.gradient_simulations == 0
    with pytest.raises(ValueError, match="shape"):
        p.margin(np.zeros((3, p.dimension + 1)))


def test_sobol_indices_of_several_outputs_share_one_sample():
    """Each output's indices equal `sobol_indices` of that output alone; n (D + 2) evaluations
    (first-order and total indices only), the function called once."""
    c = np.array([0.5, 4.0, 0.0, 2.0])
    calls = []

    def f(x):
        calls.append(len(x))
        return {"lin": x @ c, "sq": (x @ c) ** 2 / 40 + 3 * x[:, 2], "none": np.zeros(len(x))}

    both = rare.sobol_indices_outputs(f, 4, 256, seed=3)
    assert calls == [256 * 6]
    for key, g in (("lin", lambda x: x @ c), ("sq", lambda x: (x @ c) ** 2 / 40 + 3 * x[:, 2])):
        one = rare.sobol_indices(g, 4, 256, seed=3)
        assert one["evaluations"] == both[key]["evaluations"] == 256 * 6
        for k in ("ST", "S1", "ST_conf"):
            np.testing.assert_allclose(both[key][k], one[k], rtol=1e-12)
    assert both["sq"]["ST"][2] > 0.1 > 0.01 > both["lin"]["ST"][2]  # x2 only enters "sq"
    assert np.all(np.isnan(both["none"]["ST"])) and both["none"]["variance"] == 0  # constant


def test_sensitivity_figure_panels_with_intervals_and_missing_values():
    import matplotlib.pyplot as plt

    from afbl_jax.plotting.rare import figure_sensitivity

    names = ["a", "b", "c"]
    rankings = {
        f"panel {k}": (names, [0.1, np.nan, 0.5], "index [-]", [0.05, np.nan, 0.1])
        for k in range(4)
    }
    rankings["no intervals"] = (names, [1.0, 2.0, 3.0], "bound [-]")
    fig = figure_sensitivity(rankings)
    shown = [ax for ax in fig.axes if ax.get_visible()]
    assert len(shown) == 5 and len(fig.axes) == 6  # 2 rows of 3, the last one hidden
    labels = [t.get_text() for t in shown[0].get_yticklabels()]
    assert labels == ["c", "a", "b"]  # ranked: largest first (at the top), NaN last
    plt.close(fig)


def test_margin_of_one_case_and_of_identical_cases():
    """A batch whose cases are all the same (one case padded to an ensemble group) solves, and
    gives that case's margin as it has among other cases."""
    dist = mc.Distribution.from_dict(
        {
            "time": {"t1": 0.5},
            "pulses": {"start": [0.1, 0.4]},
            "gust": {"start": [0.1, 0.4]},
            "payload": {"attach_time": [0.1, 0.4]},
            "turbulence": {"n_frequencies": 2},
        }
    )
    p = rare.MarginProblem(A.AFBL(), dist, n_save=11, attitude_limit=0.05)
    u = np.asarray(mc.draw_variates(dist, 3, 0))
    alone = p.margin(u[:1])
    both = p.margin(np.concatenate([u[:1], u[:1]]))
    mixed = p.margin(u)
    assert alone.shape == (1,) and np.isfinite(alone[0])
    np.testing.assert_allclose(both, alone[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(alone[0], mixed[0], rtol=0, atol=1e-5)  # steps shared in a group
