"""Gain tuning: gradients of the batched objective (finite differences, single-case path,
float32 vs float64), L-BFGS / Adam / CMA-ES loops, time budget, resume, cases, gains files,
held-out statistics, CLI errors."""

from __future__ import annotations

import dataclasses
import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from afbl_jax import simulate
from afbl_jax.io import load_gains, save_gains
from afbl_jax.model import make_controller
from afbl_jax.studies.montecarlo import Distribution, default_distribution, wilson_interval
from afbl_jax.studies.tuning import (
    TUNING_UNMODELED,
    GainSpace,
    ObjectiveConfig,
    TuneConfig,
    Tuner,
    aggregate,
    nominal_vehicle,
    training_cases,
)
from afbl_jax.studies.tuning._objective import case_costs
from afbl_jax.studies.tuning._optimize import (
    LS_INCREASE,
    _costs,
    _costs_cotangent,
    _on_devices,
    _value_and_grad,
    chunked_value_and_grad,
    gradient_chunks,
    make_optimizer,
    strongly_typed,
)
from afbl_jax.studies.tuning._study import cvar, distribution_stats

# A short realistic distribution (full plant, motor lag, 200-250 Hz digital control, delay):
# every capability at a test size. 4 cases = one sampler group (one control rate).
SHORT = Distribution.from_dict(
    {
        "unmodeled": {**TUNING_UNMODELED, "control_rate": [200.0, 250.0]},
        "pulses": {"start": [0.3, 1.2], "duration": [0.1, 0.4]},
        "gust": {"start": [0.3, 1.2], "buildup_time": [0.2, 0.5]},
        "time": {"t1": 1.5},
    },
    "short test distribution",
)
OBJ = ObjectiveConfig(rtol=1e-8, atol=1e-10)
CONFIG = TuneConfig(controller="afbl", objective=OBJ, n_cases=4, steps=2, checkpoint_every=1)


@pytest.fixture(scope="module")
def cases():
    return training_cases(4, seed=3, distribution=SHORT, noise=False)


@pytest.fixture(scope="module")
def tuners(cases):
    out = {
        m: Tuner(dataclasses.replace(CONFIG, method=m, population=8, sigma=0.1), cases=cases)
        for m in ("lbfgs", "adam", "cmaes")
    }
    # one CMA-ES generation, then two L-BFGS iterations (the programs of the two above)
    hybrid = dataclasses.replace(
        CONFIG, method="hybrid", population=8, sigma=0.1, steps=3, cmaes_generations=1
    )
    out["hybrid"] = Tuner(hybrid, cases=cases)
    return out


def _perturbed_z(space: GainSpace) -> dict:
    # away from the paper gains, so the check is generic
    return {k: 0.1 * jnp.sin(jnp.arange(4.0) + 3 * i) for i, k in enumerate(space.names)}


def _assert_matches_central_differences(grad: dict, f, z0: dict, seed: int) -> None:
    """grad . d against (f(z0 + h d) - f(z0 - h d)) / 2h to 1e-3 relative, along 4 random
    directions d (h = 1e-4); ``f`` maps gains z to the objective."""
    rng = np.random.default_rng(seed)
    h = 1e-4
    for _ in range(4):
        d = {k: jnp.asarray(rng.normal(size=4)) for k in z0}
        ad = sum(float(jnp.dot(grad[k], d[k])) for k in z0)
        plus = f({k: z0[k] + h * d[k] for k in z0})
        minus = f({k: z0[k] - h * d[k] for k in z0})
        fd = (plus - minus) / (2 * h)
        assert abs(ad - fd) <= 1e-3 * abs(fd), (ad, fd)


def test_batched_gradient_matches_central_differences_realistic(tuners, cases):
    """d objective / dz along 4 directions (x64): RecursiveCheckpointAdjoint through the
    ensemble's scan of interval solves vs central differences of the same solver."""
    tuner = tuners["lbfgs"]
    key = CONFIG.objective_key()
    z0 = _perturbed_z(tuner.space)
    (value, costs), grad = _value_and_grad(key, z0, cases, tuner.reference)
    assert np.isfinite(float(value)) and not np.any(np.asarray(costs.failed))

    def f(z):
        return float(_value_and_grad(key, z, cases, tuner.reference)[0][0])

    _assert_matches_central_differences(grad, f, z0, seed=0)


def test_gradient_in_chunks_matches_central_differences(tuners, cases):
    """The gradient over 12 cases in chunks of 8 (the forward pass's cotangent, a vector-
    Jacobian product per chunk, the last chunk filled up with zero-weight cases; on one device,
    then with each chunk's forward pass kept for its reverse pass on two) against
    central differences of the objective along 4 directions (x64; forward passes over the 12
    cases, the one-pass reverse mode is checked the same way above). The 12 are three copies
    of the 4 test cases, so the CVaR's tail mixes the chunks; a padding case counted, or a
    chunk left out, changes the gradient by a third or more."""
    tuner = tuners["lbfgs"]
    cfg = dataclasses.replace(
        CONFIG, objective=dataclasses.replace(OBJ, risk="cvar", gradient_chunk=8)
    )
    key = cfg.objective_key()
    many = cases.take(np.tile(np.arange(4), 3))
    z0 = _perturbed_z(tuner.space)
    (value, costs), grad = chunked_value_and_grad(key, z0, many, tuner.reference)
    assert max(_amax(g) for g in grad.values()) > 0

    def f(z):
        c = _costs(key, key.space().log_gains(z), many)
        return float(_costs_cotangent(key, c, tuner.reference)[0])

    np.testing.assert_allclose(float(value), f(z0), rtol=1e-12)
    _assert_matches_central_differences(grad, f, z0, seed=1)
    # the chunks spread over two devices (here the one device twice: two threads): one chunk
    # per device, so each chunk's forward pass gives its costs and keeps its residuals for its
    # reverse pass; the same costs, objective and gradient as the path above, to round-off
    device = jax.local_devices()[0]
    (value2, costs2), grad2 = chunked_value_and_grad(
        key, z0, many, tuner.reference, devices=[device, device]
    )
    np.testing.assert_allclose(float(value2), float(value), rtol=1e-12)
    np.testing.assert_allclose(
        np.asarray(costs2.ise_attitude), np.asarray(costs.ise_attitude), rtol=1e-12
    )
    scale = max(_amax(g) for g in grad.values())
    for k in grad:
        np.testing.assert_allclose(
            np.asarray(grad2[k]), np.asarray(grad[k]), rtol=1e-9, atol=1e-12 * scale
        )
    with pytest.raises(ValueError, match="multiple of 4"):
        ObjectiveConfig(gradient_chunk=6)


def test_gradient_chunks_cover_every_device():
    """Cases per reverse pass: one pass where one device holds every case, else whole groups
    of 4, at most the chunk, one chunk per device at least; work items land on the devices in
    turn and come back in order."""
    assert gradient_chunks(8, 32, 1) == 0  # one device, one pass
    assert gradient_chunks(4, 32, 2) == 0  # one group: nothing to split
    assert gradient_chunks(10, 8, 2) == 0  # not whole groups
    assert gradient_chunks(8, 32, 2) == 4
    assert gradient_chunks(16, 32, 2) == 8
    assert gradient_chunks(12, 32, 2) == 8  # 8 + 4 (the last chunk filled up)
    assert gradient_chunks(64, 8, 1) == 8 and gradient_chunks(64, 8, 2) == 8
    assert gradient_chunks(256, 32, 16) == 16
    seen = []

    def work(item, device):
        seen.append((item, device))
        return item * 10

    assert _on_devices(work, [0, 1, 2, 3, 4], ["a", "b"]) == [0, 10, 20, 30, 40]
    assert sorted(seen) == [(0, "a"), (1, "b"), (2, "a"), (3, "b"), (4, "a")]


def test_lbfgs_step_is_traced_once():
    """The L-BFGS state keeps its abstract types through a step (optax starts the line
    search's trial counter weakly typed; the step returns it strongly typed): a jitted step
    is traced once over iterations, from the initial state on (a toy objective, the real
    optimiser)."""
    opt = make_optimizer(CONFIG)
    z = {"gamma": jnp.zeros(4), "k": jnp.zeros(4), "lam": jnp.zeros(4)}
    traces = []

    def f(x):
        return sum(jnp.sum((v - 1.0) ** 2 + 0.1 * v**4) for v in jax.tree.leaves(x))

    @jax.jit
    def step(z, s):
        traces.append(1)
        v, g = jax.value_and_grad(f)(z)
        u, s = opt.update(g, s, z, value=v, grad=g, value_fn=f)
        return optax.apply_updates(z, u), s

    raw = opt.init(z)
    assert any(jax.typeof(x).weak_type for x in jax.tree.leaves(raw))  # what is fixed
    s = strongly_typed(raw)
    for _ in range(3):
        z, s = step(z, s)
    assert len(traces) == 1
    assert float(f(z)) < 12.0  # it descends (f = 12 at z = 0)


def test_lbfgs_search_starts_at_the_quasi_newton_step_after_an_accepted_step(tuners):
    """After an accepted L-BFGS step the next line search starts at a = 1 (the curvature
    memory scales the direction), not at LS_INCREASE times the step just accepted; after a
    search that found no step, the next starts below its last trial."""
    tuner = tuners["lbfgs"]
    z, state = tuner.init()
    accepted = 0
    for _ in range(3):
        before = float(optax.tree_utils.tree_get(state, "learning_rate"))
        z, state, *_ = tuner._lbfgs_iterate(z, state)
        rate = float(optax.tree_utils.tree_get(state, "learning_rate"))
        first_trial = min(LS_INCREASE * rate, 1.0)  # optax's start of the next search
        if float(optax.tree_utils.tree_get(state, "decrease_error")) <= 0.0:
            accepted += 1
            assert first_trial == 1.0
        else:
            assert first_trial < min(LS_INCREASE * before, 1.0)
    assert accepted >= 1


@pytest.mark.slow
def test_batched_gradient_matches_single_case_path(tuners, cases):
    """Gradient of one case's ISE through simulate_batch (ensemble) == through `simulate`."""
    space = tuners["lbfgs"].space
    params = space.log_gains(_perturbed_z(space))
    one = cases  # one sampler group
    i = 1

    def batched(p):
        c = case_costs(space.controller_of(p), one, OBJ)
        return c.ise_attitude[i] + c.ise_altitude[i]

    def single(p):
        scen, veh, mod = one.case(i)
        r = simulate(
            space.controller_of(p),
            scen,
            veh,
            mod,
            unmodeled=one.unmodeled_case(i),
            aerodynamics=one.aerodynamics,
            rtol=1e-10,
            atol=1e-12,
            max_steps=4096,
        )
        return r.ise_attitude + r.ise_altitude

    gb = jax.grad(batched)(params)
    gs = jax.grad(single)(params)
    for k in params:
        # the ensemble's shared steps meet every case's tolerance: agreement to the solver's
        np.testing.assert_allclose(
            gb[k], gs[k], rtol=2e-3, atol=2e-3 * max(map(_amax, gs.values()))
        )


def _amax(x):
    return float(jnp.max(jnp.abs(x)))


@pytest.mark.slow
def test_float32_gradient_within_measured_bound(tuners, cases):
    """float32 solve (the Monte-Carlo study's rtol 3e-6, atol 3e-7) gradient vs float64:
    largest deviation <= 5 % of the largest entry (README: gradient cost)."""
    space = tuners["lbfgs"].space
    z = _perturbed_z(space)
    g = {}
    for dtype, rtol, atol in (("float32", 3e-6, 3e-7), ("float64", 1e-8, 1e-10)):
        cfg = dataclasses.replace(
            CONFIG, objective=ObjectiveConfig(dtype=dtype, rtol=rtol, atol=atol)
        )
        g[dtype] = _value_and_grad(cfg.objective_key(), z, cases, tuners["lbfgs"].reference)[1]
    g32 = np.concatenate([np.asarray(g["float32"][k]) for k in space.names])
    g64 = np.concatenate([np.asarray(g["float64"][k]) for k in space.names])
    assert np.max(np.abs(g32 - g64)) <= 0.05 * np.max(np.abs(g64))
    assert np.max(np.abs(g32 - g64)) > 0  # really a float32 solve


@pytest.mark.parametrize("method", ["lbfgs", "adam", "cmaes", "hybrid"])
def test_methods_lower_the_loss_keep_gains_in_box_and_resume_exactly(tuners, method, tmp_path):
    tuner = tuners[method]
    full = tuner.run(tmp_path / "full", progress=False, log=lambda *a: None)
    losses = [h["loss"] for h in full.history]
    assert len(losses) == tuner.config.steps + 1
    if method == "hybrid":  # a generation (no gradient), then L-BFGS iterations
        assert math.isnan(full.history[1]["grad_norm"])
        assert all(math.isfinite(h["grad_norm"]) for h in full.history[2:])
    if method != "adam":  # L-BFGS (line search) and CMA-ES (best so far) never go up
        assert all(b <= a + 1e-12 for a, b in zip(losses, losses[1:], strict=False))
        assert losses[-1] < losses[0]
    lo, hi = tuner.space.bounds()
    for name in tuner.space.names:
        p = np.asarray(full.params[name])
        assert np.all(p >= np.asarray(lo[name]) - 1e-12) and np.all(p <= np.asarray(hi[name]))
    # interrupted after 1 iteration (the hybrid: 2, inside its L-BFGS phase), resumed: the
    # same iterates and objective values
    stop = 2 if method == "hybrid" else 1
    part = tuner.run(tmp_path / "part", progress=False, stop_after=stop, log=lambda *a: None)
    assert len(part.history) == stop + 1
    resumed = Tuner(tuner.config, cases=tuner.cases).run(
        tmp_path / "part", resume=True, progress=False, log=lambda *a: None
    )
    for name in tuner.space.names:
        np.testing.assert_allclose(resumed.params[name], full.params[name], rtol=1e-12, atol=0)
    assert [h["loss"] for h in resumed.history] == pytest.approx(losses, rel=1e-12)
    # the tuned gains go through the gains-file format at full precision
    save_gains(full.controller, tmp_path / "gains.json")
    doc = json.loads((tmp_path / "gains.json").read_text())
    assert set(doc) == {"controller", "gamma", "k", "lambda"}
    back = load_gains(tmp_path / "gains.json")
    np.testing.assert_array_equal(back.k, full.controller.k)


def test_time_budget_is_honoured(tuners):
    tuner = tuners["cmaes"]
    t_iter = tuner.run(progress=False).history[1]["time_s"]  # one generation, compiled
    budget = 2.5 * t_iter
    cfg = dataclasses.replace(tuner.config, steps=1000, time_budget=budget)
    res = Tuner(cfg, cases=tuner.cases).run(progress=False, log=lambda *a: None)
    assert 1 <= len(res.history) - 1 < 1000
    times = [h["time_s"] for h in res.history]
    # no iteration starts once the budget is spent; the last one was started because the
    # estimate (the iteration before) fitted in what was left, so it overruns the budget by
    # no more than its excess over that estimate (slack for timing noise on a shared machine)
    assert times[-2] <= budget
    assert times[-1] <= budget + 2.0 * t_iter


def test_objective_is_normalised_by_the_paper_gains(tuners):
    """At the paper's gains each normalised term is 1 (mean over cases), so the objective is
    w_att + w_alt when no case fails, every margin keeps its reserve and no limit is violated
    (less the soft cap's kappa softplus((P - K) / kappa) per case, below 1e-3 here)."""
    from afbl_jax.studies.tuning._objective import objective_of_costs

    tuner = tuners["lbfgs"]
    loss, costs = tuner.loss_and_costs(tuner.space.init_z())
    assert not np.any(np.asarray(costs.failed))
    assert np.all(np.asarray(costs.margin) < -OBJ.reserve - 4 * OBJ.margin_temperature)
    target = OBJ.w_attitude + OBJ.w_altitude
    assert target - 1e-3 < float(loss) < target
    step = dataclasses.replace(OBJ, failure="step")
    assert float(objective_of_costs(costs, tuner.reference, step)) == pytest.approx(target, 1e-12)


def test_limits_penalise_effort_above_the_paper():
    from afbl_jax.studies.tuning._objective import CaseCosts, Reference, penalties

    ref = Reference(*(jnp.asarray(1.0) for _ in range(4)))

    def costs(effort):
        one = jnp.ones(4)
        return CaseCosts(one, one, effort * one, 0 * one, one < 0, 0 * one, 0 * one)

    cfg = ObjectiveConfig(effort_limit=1.0, penalty=100.0)
    assert float(penalties(costs(1.0), ref, cfg)) == 0.0
    assert float(penalties(costs(1.1), ref, cfg)) == pytest.approx(100 * 0.1**2)
    # C^1 at the limit: the derivative is 0 there
    d = jax.grad(lambda e: penalties(costs(e), ref, cfg))(1.0)
    assert float(d) == 0.0


def test_aggregate_mean_cvar_nominal():
    losses = jnp.arange(1.0, 11.0)  # 1..10
    assert float(aggregate(losses, ObjectiveConfig(objective="nominal"))) == 55.0
    assert float(aggregate(losses, ObjectiveConfig(risk="mean"))) == 5.5
    # CVaR_0.8 of 10 cases: mean of the worst 2 (exact: cvar_temperature 0; the smoothed one
    # is above it by at most beta log 2 / (1 - alpha))
    exact = ObjectiveConfig(risk="cvar", cvar_level=0.8, cvar_temperature=0.0)
    assert float(aggregate(losses, exact)) == 9.5
    smooth = float(aggregate(losses, ObjectiveConfig(risk="cvar", cvar_level=0.8)))
    assert 9.5 <= smooth <= 9.5 + 0.05 * math.log(2) / 0.2
    assert float(aggregate(losses, ObjectiveConfig(risk="cvar", cvar_level=0.0))) == 5.5


def test_heldout_statistics():
    v = np.arange(1.0, 101.0)
    s = distribution_stats(v)
    assert s["p50"] == pytest.approx(np.percentile(v, 50))
    assert s["cvar90"] == pytest.approx(np.mean(v[90:]))
    assert cvar(v, 0.9) == s["cvar90"]
    assert wilson_interval(0, 1024)[0] == 0.0


def test_heldout_leaves_out_cases_outside_the_envelope(cases):
    """A held-out case outside the flight envelope is no controller's failure: it is counted
    as outside and left out of every statistic and of the failure rate."""
    import equinox as eqx

    from afbl_jax.studies.tuning._study import _heldout_costs, evaluate_heldout

    solver = {"dtype": "float64", "rtol": 1e-6, "atol": 1e-8}
    cause = np.zeros(cases.n_cases, np.int32)
    cause[1] = 1
    outside = eqx.tree_at(lambda c: c.inputs, cases, {**cases.inputs, "envelope_cause": cause})
    ctrl = {"paper": make_controller("afbl")}
    every = evaluate_heldout(ctrl, cases, OBJ, solver)["paper"]
    some = evaluate_heldout(ctrl, outside, OBJ, solver)["paper"]
    assert (every["n_cases"], every["outside_envelope"]) == (4, 0)
    assert (some["n_cases"], some["outside_envelope"]) == (3, 1)
    c = _heldout_costs(dataclasses.replace(OBJ, **solver), ctrl["paper"], cases)
    keep = np.array([0, 2, 3])
    ise = np.asarray(c.ise_attitude + c.ise_altitude)
    assert some["ise"] == distribution_stats(ise[keep])
    assert every["ise"] == distribution_stats(ise)
    assert some["effort"]["mean"] == pytest.approx(np.mean(np.asarray(c.effort)[keep]), 1e-12)
    assert some["failures"] == int(np.sum(np.asarray(c.failed)[keep]))


def test_unconstrained_parametrisation_stays_in_the_box():
    space = GainSpace("fbl", lower=0.2, upper=5.0)
    z0 = space.init_z()
    for n in space.names:
        np.testing.assert_allclose(z0[n], 0.0, atol=1e-12)  # the paper's gains: box centre
    lo, hi = space.bounds()
    big = space.log_gains({n: jnp.full(4, 50.0) for n in space.names})
    small = space.log_gains({n: jnp.full(4, -50.0) for n in space.names})
    for n in space.names:
        np.testing.assert_allclose(big[n], hi[n], rtol=1e-12)
        np.testing.assert_allclose(small[n], lo[n], rtol=1e-12)
    assert len(space.on_box(big)) == 12 and not space.on_box(space.init_params())


def test_training_cases_reproducible_realistic_and_noise_free():
    a, b = training_cases(4, seed=7), training_cases(8, seed=7)
    c = training_cases(4, seed=8)
    for x, y in zip(jax.tree.leaves(a.scenario), jax.tree.leaves(b.scenario), strict=True):
        np.testing.assert_array_equal(x, y[:4])
    assert not np.allclose(a.vehicle.Ix, c.vehicle.Ix)
    u = b.unmodeled
    assert u.plant == "full" and u.max_delay == 1
    assert np.all((np.asarray(u.motor_tau) >= 0.02) & (np.asarray(u.motor_tau) <= 0.05))
    rate = np.asarray(u.control_rate)
    assert np.all((rate >= 200) & (rate <= 500))
    assert np.all(rate[:4] == rate[0]) and np.all(rate[4:] == rate[4])  # one rate per group
    assert np.any(np.asarray(u.noise_angle) > 0)  # held-out: noise on
    quiet = training_cases(8, seed=7, noise=False).unmodeled
    for n in ("noise_angle", "noise_rate", "noise_altitude", "noise_vertical_speed"):
        assert np.all(np.asarray(getattr(quiet, n)) == 0)
    np.testing.assert_array_equal(quiet.motor_tau, u.motor_tau)
    nominal = nominal_vehicle(2.5)
    w = 4 * float(nominal.b) * np.asarray(b.vehicle.omega_max) ** 2 / (0.65 * 9.81)
    np.testing.assert_allclose(w, 2.5, rtol=1e-12)
    lo, hi = default_distribution().spec["pulses"]["torque"]
    torque = np.asarray(b.scenario.disturbance.torque)
    assert np.all((torque >= lo - 1e-15) & (torque <= hi + 1e-15))
    unlimited = training_cases(4, seed=7, thrust_to_weight=None)
    assert np.all(np.isinf(np.asarray(unlimited.vehicle.omega_max)))


def test_tuned_gains_file_read_back_exactly_by_reproduce_and_montecarlo(tmp_path):
    """A gains.json as `afbl tune` writes it, with full float64 digits, becomes the same
    controller (bit for bit) in `afbl reproduce --gains` and `afbl montecarlo --gains`."""
    from afbl_jax.cli import build_parser
    from afbl_jax.cli._common import controllers_from_args

    space = GainSpace("fbl")
    params = space.log_gains({n: jnp.linspace(-0.7, 0.9, 4) + i for i, n in enumerate(space.names)})
    tuned = space.controller_of(params)
    path = tmp_path / "gains.json"
    save_gains(tuned, path)
    assert set(json.loads(path.read_text())) == {"controller", "P", "I", "D"}
    for cmd in ("reproduce", "montecarlo"):
        args = build_parser().parse_args(
            [cmd, "--out", str(tmp_path / cmd), "--controllers", "afbl,fbl", "--gains", str(path)]
        )
        ctrl = controllers_from_args(args)["fbl"]
        for n in ("P", "I", "D"):
            np.testing.assert_array_equal(np.asarray(getattr(ctrl, n)), getattr(tuned, n))


def test_bad_configs_are_rejected():
    with pytest.raises(ValueError, match="cannot be tuned"):
        GainSpace("afbl_paper")
    with pytest.raises(ValueError, match="lower"):
        GainSpace("afbl", lower=2.0)
    with pytest.raises(ValueError, match="objective"):
        ObjectiveConfig(objective="fast")
    with pytest.raises(ValueError, match="cvar_level"):
        ObjectiveConfig(risk="cvar", cvar_level=1.0)
    with pytest.raises(ValueError, match="effort_limit"):
        ObjectiveConfig(effort_limit=0.0)
    with pytest.raises(ValueError, match="method"):
        TuneConfig(method="sgd")
    with pytest.raises(ValueError, match="cmaes_generations"):
        TuneConfig(method="hybrid", cmaes_generations=0)
    with pytest.raises(ValueError, match="time_budget"):
        TuneConfig(time_budget=-1.0)
    with pytest.raises(ValueError, match="thrust_to_weight"):
        TuneConfig(thrust_to_weight=0.5)
    assert math.isinf(ObjectiveConfig(effort_limit=math.inf).effort_limit)


def test_tune_cli_rejects_bad_input(tmp_path, capsys):
    from afbl_jax.cli import main

    assert main(["tune", "--out", str(tmp_path), "--lower", "3", "--no-progress"]) == 2
    assert "lower" in capsys.readouterr().err
    assert main(["tune", "--out", str(tmp_path), "--time-budget", "0"]) == 2
    assert "--time-budget" in capsys.readouterr().err
    assert main(["tune", "--out", str(tmp_path), "--gradient-chunk", "6"]) == 2
    assert "gradient_chunk must be a positive multiple of 4" in capsys.readouterr().err
    assert main(["tune", "--out", str(tmp_path), "--cmaes-generations", "0"]) == 2
    assert "--cmaes-generations" in capsys.readouterr().err
    assert main(["tune-compare", "--study", "optimizers", "--out", str(tmp_path / "c")]) == 2
    assert "--time-budget" in capsys.readouterr().err
    assert not (tmp_path / "c").exists()
    args = ["tune", "--out", str(tmp_path / "x"), "--resume", "--no-progress"]
    args += ["--objective", "nominal", "--steps", "1", "--method", "adam", "--heldout-cases", "4"]
    assert main(args) == 2
    assert "no checkpoint" in capsys.readouterr().err


@pytest.mark.slow
def test_tune_cli_end_to_end(tmp_path):
    from afbl_jax.cli import main

    out = tmp_path / "tune"
    args = ["tune", "--controller", "fbl", "--cases", "4", "--steps", "2", "--method", "lbfgs"]
    args += ["--heldout-cases", "8", "--out", str(out), "--no-progress"]
    assert main(args) == 0
    for f in (
        "gains.json",
        "history.csv",
        "meta.json",
        "evaluation.json",
        "evaluation.txt",
        "convergence.png",
        "before_after.png",
    ):
        assert (out / f).exists(), f
    assert load_gains(out / "gains.json").name == "fbl"
    doc = json.loads((out / "evaluation.json").read_text())
    assert doc["meta"]["config"]["seed"] == 0 and doc["meta"]["config"]["heldout_seed"] == 1
    tuned = doc["heldout"]["tuned"]
    assert tuned["n_cases"] + tuned["outside_envelope"] == 8
    assert set(doc["limits"]) >= {"effort_active", "saturation_active", "failures"}


def test_tune_cli_time_budget_bounds_the_whole_command(tmp_path):
    """A budget shorter than sampling and compiling the objective: the command still ends
    within the budget (plus the interpreter's start and exit), prints progress before
    compiling, and writes the starting point."""
    import os
    import subprocess
    import sys
    import time

    out = tmp_path / "tune"
    budget = 6.0
    cmd = [sys.executable, "-m", "afbl_jax.cli", "tune", "--cases", "4", "--steps", "50"]
    cmd += ["--heldout-cases", "4", "--time-budget", str(budget), "--out", str(out)]
    t = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ), timeout=120)
    wall = time.perf_counter() - t
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "compiling the objective (first call)" in proc.stdout
    assert "time budget" in proc.stdout
    assert wall <= budget + 10.0  # interpreter start (imports) and exit
    back = load_gains(out / "gains.json")
    np.testing.assert_array_equal(back.k, make_controller("afbl").k)
    assert "time budget" in (out / "evaluation.txt").read_text()


@pytest.mark.slow
def test_gradient_cost_measures_both_precisions():
    """`gradient_cost` on 2 training cases: compiled timings of both passes in both precisions,
    a reverse pass costlier than the forward pass it differentiates, and a float32 gradient
    within 1e-3 of the float64 one (relative to its largest entry)."""
    from afbl_jax.studies.tuning import TuneConfig, gradient_cost

    d = gradient_cost(TuneConfig(n_cases=2, seed=0), repeats=1, log=lambda s: None)
    assert d["n_cases"] == 2
    for dtype in ("float32", "float64"):
        t = d[dtype]
        assert 0 < t["forward_s"] < t["gradient_s"]
        assert t["gradient_compile_s"] > 0
    assert d["ratio_gradient64_to_forward32"] > 1
    assert 0 < d["float32_gradient_rel_error"] < 1e-3
