"""Closed loop: hand-computable ISE, scipy agreement, transforms (jit/vmap/grad), failures."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

import afbl_jax as A

from ..helpers import tree_allclose
from ..numpy_reference import simulate_reference

TIGHT = dict(rtol=1e-10, atol=1e-12)


def _finite_horizon_ise(a, x0, c, t):
    """int_0^t (c x)^2 dt for x' = a x: x0^T (X - e^{a^T t} X e^{a t}) x0, a^T X + X a = -c^T c."""
    x = scipy.linalg.solve_continuous_lyapunov(a.T, -np.outer(c, c))
    e = scipy.linalg.expm(a * t)
    return float(x0 @ (x - e.T @ x @ e) @ x0)


def test_ise_of_hand_computable_case():
    """FBL, zero references, initial z and psi offsets: both channels are exactly linear."""
    y0 = np.zeros(12)
    y0[2], y0[5] = 0.1, 0.05  # z [m], psi [rad]
    sc = A.Scenario(A.make_reference(), A.no_disturbance(), initial_state=y0, t1=20.0)
    ctrl = A.FBLPID()
    r = A.simulate(ctrl, sc, n_save=0, **TIGHT)
    assert int(r.status) == 0

    def channel(p, i, d, e0):
        a = np.array([[0, 1, 0], [0, 0, 1], [-i, -p, -d]], dtype=float)  # (xi, e, ed)
        return _finite_horizon_ise(a, np.array([0.0, e0, 0.0]), np.array([0, 1.0, 0]), 20.0)

    expected_alt = channel(80.0, 10.0, 10.0, -0.1)
    expected_att = channel(30.0, 8.0, 8.0, -0.05)
    np.testing.assert_allclose(float(r.ise_altitude), expected_alt, rtol=1e-8)
    np.testing.assert_allclose(float(r.ise_attitude), expected_att, rtol=1e-8)


@pytest.mark.parametrize("controller", ["fbl", "afbl", "afbl_paper"])
def test_agrees_with_independent_numpy_scipy_integration(controller):
    ctrl = A.make_controller(controller)
    eq14 = A.QuadrotorParams(gyro_sign=A.EQ14_GYRO_SIGN)  # the reference writes eq. 14's sign
    for kind, profile in [("uncertain", "step"), ("ideal", "sine")]:
        ours = A.simulate(ctrl, A.paper_scenario(kind, profile), eq14, n_save=0, **TIGHT)
        ref = simulate_reference(controller, kind, profile, rtol=1e-11, atol=1e-12)
        assert int(ours.status) == 0
        for key in ("ise_attitude", "ise_altitude"):
            np.testing.assert_allclose(
                float(getattr(ours, key)),
                ref[key],
                rtol=1e-5,
                atol=1e-11,
                err_msg=f"{controller} {kind} {profile} {key}",
            )
        np.testing.assert_allclose(ours.final.plant, ref["plant_final"], rtol=1e-5, atol=1e-8)


def test_solution_converges_with_tolerance():
    """ISE error vs the tight solution shrinks as rtol shrinks (convergence, not a magic value)."""
    ctrl, sc = A.AFBL(), A.paper_scenario("uncertain", "step")
    best = float(A.simulate(ctrl, sc, n_save=0, **TIGHT).ise_attitude)
    errs = [
        abs(float(A.simulate(ctrl, sc, n_save=0, rtol=rt, atol=rt * 1e-2).ise_attitude) - best)
        for rt in (1e-4, 1e-6, 1e-8)
    ]
    assert errs[0] > errs[1] > errs[2]
    assert errs[2] < 1e-7 * best


def test_afbl_tracks_far_better_than_afbl_paper():
    sc = A.paper_scenario("ideal", "step")
    good = A.simulate(A.AFBL(), sc, n_save=0)
    paper = A.simulate(A.AFBLPaper(), sc, n_save=0)
    assert float(paper.ise_attitude) > 20 * float(good.ise_attitude)
    # the printed law keeps its initial attitude error (P = 1/gamma is tiny)
    r = A.simulate(A.AFBLPaper(), sc, n_save=101)
    assert abs(float(r.error[-1, 0]) + 0.05) < 5e-3
    # under a 50 % payload it sinks: altitude error grows, AFBL keeps it small
    unc = A.paper_scenario("uncertain", "step")
    assert float(A.simulate(A.AFBLPaper(), unc, n_save=0).ise_altitude) > 100 * float(
        A.simulate(A.AFBL(), unc, n_save=0).ise_altitude
    )


def test_vmap_equals_unbatched_and_jit():
    sc = A.paper_scenario("uncertain", "sine")
    ks = jnp.array([[8.0, 15.0, 8.0, 80.0], [4.0, 10.0, 6.0, 40.0], [12.0, 20.0, 10.0, 60.0]])

    def run(k):
        return A.simulate(A.AFBL(k=k), sc, n_save=11)

    batched = jax.vmap(run)(ks)
    for i in range(3):
        single = run(ks[i])
        assert tree_allclose(jax.tree.map(lambda a: a[i], batched), single, rtol=1e-9, atol=1e-12)
    jitted = jax.jit(lambda k: run(k).ise_attitude)(ks[1])
    np.testing.assert_allclose(jitted, batched.ise_attitude[1], rtol=1e-12)
    # A batch over scenarios of different kinds and profiles. Lanes may take slightly different
    # step sequences than the unbatched call (batched arithmetic rounds differently and an
    # accept/reject decision can flip), so they agree to the solver tolerance: compare tight.
    scs = A.stack_scenarios([A.paper_scenario(k, p) for k in A.SCENARIO_KINDS for p in A.PROFILES])
    by_scenario = jax.vmap(lambda s: A.simulate(A.AFBL(), s, n_save=0, **TIGHT).ise_attitude)(scs)
    for i, (k, p) in enumerate([(k, p) for k in A.SCENARIO_KINDS for p in A.PROFILES]):
        single = A.simulate(A.AFBL(), A.paper_scenario(k, p), n_save=0, **TIGHT)
        np.testing.assert_allclose(by_scenario[i], single.ise_attitude, rtol=1e-10)
    masses = jnp.array([0.6, 0.65, 0.7])
    by_mass = jax.vmap(
        lambda m: A.simulate(A.AFBL(), sc, A.QuadrotorParams(m=m), n_save=0).ise_altitude
    )(masses)
    np.testing.assert_allclose(
        by_mass[2],
        A.simulate(A.AFBL(), sc, A.QuadrotorParams(m=0.7), n_save=0).ise_altitude,
        rtol=1e-9,
    )


def test_grad_of_ise_matches_finite_differences():
    sc = A.paper_scenario("uncertain", "step")

    def ise(k_phi, gamma_z):
        ctrl = A.AFBL(
            k=jnp.stack([k_phi, 15.0, 8.0, 80.0]), gamma=jnp.stack([8.0, 15.0, 8.0, gamma_z])
        )
        r = A.simulate(ctrl, sc, n_save=0, **TIGHT)
        return r.ise_attitude + r.ise_altitude

    x = (jnp.asarray(8.0), jnp.asarray(20.0))
    grads = jax.grad(ise, argnums=(0, 1))(*x)
    for i, g in enumerate(grads):
        h = 1e-3 * float(x[i])
        xp = list(x)
        xm = list(x)
        xp[i] = x[i] + h
        xm[i] = x[i] - h
        fd = (float(ise(*xp)) - float(ise(*xm))) / (2 * h)
        np.testing.assert_allclose(float(g), fd, rtol=1e-4)


def test_no_retracing_for_new_gain_values():
    traces = []

    class CountingAFBL(A.AFBL):
        def virtual_input(self, e, ed, ref, state):
            traces.append(1)
            return super().virtual_input(e, ed, ref, state)

    sc = A.paper_scenario("ideal", "step")
    A.simulate(CountingAFBL(), sc, n_save=0)
    n = len(traces)
    assert n > 0
    for k in (5.0, 6.0, 7.0):
        A.simulate(CountingAFBL(k=k), sc, n_save=0)
    assert len(traces) == n


def test_divergence_and_solver_failure_are_reported_not_raised():
    sc = A.paper_scenario("uncertain", "step")
    # thrust-to-weight 1.2 at nominal mass cannot lift a 50 % payload: it falls > 10 m
    weak = A.QuadrotorParams().with_thrust_to_weight(1.2)
    r = A.simulate(A.FBLPID(), sc, weak, n_save=51)
    assert int(r.status) == 1 and "diverged" in A.status_message(r.status)
    assert 1.0 < float(r.t_final) < 20.0
    assert abs(float(r.final.plant[2]) - 1.0) > 10.0 - 1e-6
    r2 = A.simulate(A.FBLPID(), sc, n_save=0, max_steps=20)
    assert int(r2.status) == 2 and "max_steps" in A.status_message(r2.status)
    # inside a batch one bad case does not stop the others
    vehicles = jax.tree.map(lambda *x: jnp.stack(x), A.QuadrotorParams(), weak)
    rb = jax.vmap(lambda v: A.simulate(A.FBLPID(), sc, v, n_save=0))(vehicles)
    np.testing.assert_array_equal(rb.status, [0, 1])
    assert np.isfinite(float(rb.ise_attitude[0]))


def test_samples_after_an_early_stop_are_inf():
    """States, signals and (continuous control) times after a divergence are inf, never
    numbers computed from the padding."""
    weak = A.QuadrotorParams().with_thrust_to_weight(1.2)
    r = A.simulate(A.FBLPID(), A.paper_scenario("uncertain", "step"), weak, n_save=51)
    assert int(r.status) == 1
    dead = ~np.isfinite(np.asarray(r.ts))
    assert 0 < dead.sum() < 50  # some samples before the stop, some after
    for name in ("plant", "reference", "error", "u_command", "u_applied", "rotor_speeds"):
        a = np.asarray(getattr(r, name))
        assert np.all(np.isinf(a[dead])), name
        assert np.all(np.isfinite(a[~dead])), name


@pytest.mark.default_codegen
@pytest.mark.parametrize("controller", ["fbl", "afbl"])
def test_dense_saving_gives_the_saveat_samples(controller):
    """``saving="dense"`` evaluates the steps' own interpolants after the solve: the same
    samples, end state, status and step counts as SaveAt(ts), finished and diverged runs."""
    ctrl = A.make_controller(controller)
    sc = A.paper_scenario("uncertain", "step")
    for vehicle in (A.QuadrotorParams(), A.QuadrotorParams().with_thrust_to_weight(1.2)):
        a = A.simulate(ctrl, sc, vehicle, n_save=101)
        b = A.simulate(ctrl, sc, vehicle, n_save=101, saving="dense")
        assert int(a.status) == int(b.status)
        assert int(a.num_steps) == int(b.num_steps)
        assert tree_allclose(a, b, rtol=1e-12, atol=1e-12)
    assert int(a.status) == 1  # the weak vehicle diverged: padding compared too


def test_dense_saving_compiles_without_host_callbacks():
    """The reason for ``saving="dense"``: diffrax checks SaveAt(ts) with host callbacks, which
    keep JAX's persistent compilation cache from storing the program; dense output has none."""
    sc = A.paper_scenario("uncertain", "step")

    def program(saving):
        run = jax.jit(lambda s: A.simulate(A.FBLPID(), s, n_save=11, saving=saving))
        return run.lower(sc).as_text()

    assert "callback" in program("saveat")
    assert "callback" not in program("dense")
    with pytest.raises(ValueError, match="saving must be one of saveat, dense"):
        A.simulate(A.FBLPID(), sc, n_save=11, saving="steps")


def test_saturation_limits_rotor_speeds_in_closed_loop():
    vehicle = A.QuadrotorParams().with_thrust_to_weight(1.6)
    r = A.simulate(A.AFBL(), A.paper_scenario("uncertain", "step"), vehicle, n_save=2001)
    assert float(np.max(r.rotor_speeds)) <= float(vehicle.omega_max) * (1 + 1e-9)
    assert np.any(r.u_applied[:, 3] < r.u_command[:, 3] - 1e-6)  # saturation was active
    assert float(r.saturation) > 0
    free = A.simulate(A.AFBL(), A.paper_scenario("uncertain", "step"), n_save=0)
    assert float(free.saturation) == 0.0


def test_result_signals_are_consistent():
    r = A.simulate(A.FBLPID(), A.paper_scenario("uncertain", "step"), n_save=201)
    q = r.plant[:, np.array([3, 4, 5, 2])]
    np.testing.assert_allclose(r.error, r.reference - q, atol=1e-14)
    np.testing.assert_allclose([r.ts[0], r.ts[-1]], [0.0, 20.0])
    np.testing.assert_allclose(
        r.rotor_speeds**2 @ np.full(4, float(A.QuadrotorParams().b)), r.u_applied[:, 3], rtol=1e-12
    )
    np.testing.assert_allclose(r.final.plant, r.plant[-1], rtol=1e-12, atol=1e-14)


def test_reproduction_keeps_eq14_gyro_sign_and_switches():
    """`afbl reproduce` runs eq. 14's sign by default (the README table); the physical sign, the
    library default, is one flag away and gives the default vehicle's numbers."""
    from afbl_jax.cli import build_parser
    from afbl_jax.studies.reproduce import ReproduceConfig, run_reproduction

    ctrl = {"fbl": A.FBLPID()}
    faithful = run_reproduction(ReproduceConfig(ctrl, n_save=2, rtol=1e-6, atol=1e-8))
    physical = run_reproduction(
        ReproduceConfig(ctrl, n_save=2, rtol=1e-6, atol=1e-8, gyro_sign=A.PHYSICAL_GYRO_SIGN)
    )
    assert faithful.config["vehicle"]["gyro_sign"] == 1.0
    assert physical.config["vehicle"]["gyro_sign"] == -1.0
    sc = A.paper_scenario("uncertain", "step")
    eq14 = A.QuadrotorParams(gyro_sign=A.EQ14_GYRO_SIGN)
    for result, vehicle in ((faithful, eq14), (physical, A.QuadrotorParams())):
        ref = A.simulate(A.FBLPID(), sc, vehicle, n_save=2, rtol=1e-6, atol=1e-8)
        got = result.ise()["uncertain_step"]["fbl"]["ise_attitude"]
        np.testing.assert_allclose(got, float(ref.ise_attitude), rtol=1e-9)
    a = faithful.ise()["uncertain_step"]["fbl"]["ise_attitude"]
    b = physical.ise()["uncertain_step"]["fbl"]["ise_attitude"]
    assert 1e-3 < abs(a - b) / a < 0.05
    args = build_parser().parse_args(["reproduce", "--out", "x"])
    assert args.gyro_sign == "eq14"
    args = build_parser().parse_args(["reproduce", "--out", "x", "--gyro-sign", "physical"])
    assert args.gyro_sign == "physical"
