"""Unmodeled dynamics: full plant vs eq. 15, motor lag and digital-control limits, noise, delay."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import afbl_jax as A

from ..helpers import tree_allclose

TOL = dict(rtol=1e-9, atol=1e-11)


def _short(scenario, t1):
    return eqx.tree_at(lambda s: s.t1, scenario, jnp.asarray(t1, dtype=float))


def _zero_ref_scenario(initial, t1):
    """Zero reference, no disturbance; same pytree structure as the canonical scenarios (so
    every test shares the compiled `_sim_traj`)."""
    sc = _short(A.paper_scenario("ideal", "step"), t1)
    sc = eqx.tree_at(lambda s: s.reference.step_size, sc, jnp.zeros_like(sc.reference.step_size))
    return eqx.tree_at(lambda s: s.initial_state, sc, jnp.asarray(initial, dtype=float))


MAX_SAMPLES = 1200
"""One static scan length for every digital test (one compile); lower rates idle at the end."""


@jax.jit
def _sim_traj(scenario, settings, ctrl=A.FBLPID()):  # noqa: B008 (same pytree every call)
    return A.simulate(ctrl, scenario, n_save=61, unmodeled=settings, **TOL)


def _digital(**kwargs):
    return A.UnmodeledDynamics.make(max_samples=MAX_SAMPLES, **kwargs)


# ------------------------------------------------------------------------------ plant physics


def test_body_euler_rate_maps_are_inverse_and_identity_at_level():
    key = jax.random.PRNGKey(3)
    ang = 0.6 * jax.random.uniform(key, (2,), minval=-1, maxval=1)
    w = jnp.array([0.3, -0.7, 1.1])
    etad = A.euler_rates_from_body_rates(ang[0], ang[1], w)
    np.testing.assert_allclose(A.body_rates_from_euler_rates(ang[0], ang[1], etad), w, rtol=1e-12)
    np.testing.assert_allclose(A.euler_rates_from_body_rates(0.0, 0.0, w), w, rtol=1e-15)
    # yaw rate about the vertical: a level vehicle spinning at psid has r = psid
    np.testing.assert_allclose(
        A.body_rates_from_euler_rates(0.0, 0.0, jnp.array([0.0, 0.0, 0.4])), [0, 0, 0.4]
    )


def test_hover_is_equilibrium_of_both_plants():
    p = A.QuadrotorParams()
    u = A.hover_input(p)
    omega = jnp.full(4, p.hover_omega)
    z3 = jnp.zeros(3)
    for f in (A.plant_derivative, A.full_plant_derivative):
        for yaw in (0.0, 1.0):
            x = jnp.zeros(12).at[5].set(yaw).at[0].set(2.0)
            d = f(p, x, u, A.omega_d(omega), p.m, z3, z3)
            np.testing.assert_allclose(d, 0.0, atol=1e-14)
    # closed loop (full plant, motor lag, digital control with delay): stays at rest
    sc = _zero_ref_scenario(np.zeros(12), 1.0)
    s = _digital(plant="full", motor_tau=0.03, control_rate=100, delay_samples=2)
    r = _sim_traj(sc, s)
    assert int(r.status) == 0
    np.testing.assert_allclose(r.plant, 0.0, atol=1e-10)
    np.testing.assert_allclose(r.rotor_speeds, float(p.hover_omega), rtol=1e-10)


def test_full_plant_matches_eq15_to_second_order_and_differs_at_large_angles():
    """Same FBL loop from an initial attitude/rate of size eps on both plants: the attitude
    trajectories differ by O(eps^2) (ratio 4 per doubling), and by > 5 % at eps = 0.5 rad."""
    paper, full = A.UnmodeledDynamics(plant="paper"), A.UnmodeledDynamics(plant="full")
    shape = np.zeros(12)
    shape[3:6] = (1.0, -1.0, 0.8)
    shape[9:12] = (2.0, 1.5, -2.0)

    def gap(eps):
        sc = _zero_ref_scenario(eps * shape, 3.0)
        rp, rf = _sim_traj(sc, paper), _sim_traj(sc, full)
        assert int(rp.status) == 0 and int(rf.status) == 0
        ang_p, ang_f = np.asarray(rp.plant[:, 3:6]), np.asarray(rf.plant[:, 3:6])
        return np.max(np.abs(ang_f - ang_p)), np.max(np.abs(ang_p))

    gaps = [gap(e)[0] for e in (0.01, 0.02, 0.04)]
    ratios = np.array(gaps[1:]) / np.array(gaps[:-1])
    np.testing.assert_allclose(ratios, 4.0, rtol=0.1)
    assert gaps[0] / 0.01 < 1e-2  # small relative to the motion itself
    big_gap, big_amp = gap(0.5)
    small_gap, small_amp = gap(0.01)
    assert big_gap / big_amp > 0.05  # 8 % of the motion
    assert big_gap / big_amp > 20 * small_gap / small_amp


def test_full_plant_state_reports_body_rates():
    shape = np.zeros(12)
    shape[3:6] = (0.3, -0.2, 0.1)
    shape[9:12] = (0.5, 0.2, -0.4)
    r = _sim_traj(_zero_ref_scenario(shape, 3.0), A.UnmodeledDynamics(plant="full"))
    # the initial state is given in the paper layout and converted to body rates
    np.testing.assert_allclose(A.RigidBodyPlant().to_paper_layout(r.plant[0]), shape, atol=1e-12)
    w0 = A.body_rates_from_euler_rates(0.3, -0.2, jnp.array([0.5, 0.2, -0.4]))
    np.testing.assert_allclose(r.plant[0, 9:12], w0, atol=1e-12)


# ------------------------------------------------------------------------------ limits


def test_default_settings_reproduce_the_paper_loop():
    sc = _short(A.paper_scenario("uncertain", "sine"), 3.0)
    base = A.simulate(A.FBLPID(), sc, n_save=61, **TOL)
    r = _sim_traj(sc, A.UnmodeledDynamics())
    assert tree_allclose(r.plant, base.plant, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(r.ise_attitude, base.ise_attitude, rtol=1e-7)


@pytest.fixture(scope="module")
def continuous_short():
    """Full plant, instantaneous rotors, continuous controller: the limit of both below."""
    sc = _short(A.paper_scenario("uncertain", "sine"), 3.0)
    return sc, _sim_traj(sc, A.UnmodeledDynamics(plant="full"))


def test_motor_lag_converges_to_instantaneous_rotors(continuous_short):
    sc, base = continuous_short
    taus = [0.02, 0.01, 0.005, 0.0025]
    batch = A.stack_unmodeled([A.UnmodeledDynamics(plant="full", motor_tau=t) for t in taus])
    r = jax.vmap(lambda s: _sim_traj(sc, s))(batch)
    assert np.all(np.asarray(r.status) == 0)
    err = np.max(np.abs(np.asarray(r.plant) - np.asarray(base.plant)[None]), axis=(1, 2))
    ise_err = np.abs(np.asarray(r.ise_attitude) - float(base.ise_attitude))
    assert np.all(np.diff(err) < 0) and np.all(np.diff(ise_err) < 0), (err, ise_err)
    # first order in tau_m: halving tau halves the error
    np.testing.assert_allclose(err[1:] / err[:-1], 0.5, rtol=0.15)
    # the vmapped run equals an unbatched one
    one = _sim_traj(sc, A.UnmodeledDynamics(plant="full", motor_tau=taus[1]))
    assert tree_allclose(one.plant, r.plant[1], rtol=1e-10, atol=1e-12)


def test_digital_control_converges_to_continuous_controller(continuous_short):
    sc, base = continuous_short
    rates = [50.0, 100.0, 200.0, 400.0]
    settings = [_digital(plant="full", control_rate=f) for f in rates]
    r = jax.vmap(lambda s: _sim_traj(sc, s))(A.stack_unmodeled(settings))
    assert np.all(np.asarray(r.status) == 0)
    np.testing.assert_allclose(r.t_final, 3.0)
    err = np.max(np.abs(np.asarray(r.plant) - np.asarray(base.plant)[None]), axis=(1, 2))
    ise_err = np.abs(np.asarray(r.ise_attitude) - float(base.ise_attitude))
    assert np.all(np.diff(err) < 0) and np.all(np.diff(ise_err) < 0), (err, ise_err)
    np.testing.assert_allclose(err[1:] / err[:-1], 0.5, rtol=0.2)  # first order in 1/f_c


# ------------------------------------------------------------------------------ noise, delay


def test_noise_statistics_match_settings_and_seed_reproduces():
    s = A.UnmodeledDynamics.make(
        control_rate=100,
        noise_angle=0.01,
        noise_rate=0.05,
        noise_altitude=0.03,
        noise_vertical_speed=0.07,
        seed=7,
    )
    n = 20000
    noise = np.asarray(jax.vmap(lambda k: A.measurement_noise(s, k))(jnp.arange(n)))
    std = np.asarray(s.noise_std())
    np.testing.assert_array_equal(noise[:, std == 0], 0.0)
    on = std > 0
    np.testing.assert_allclose(noise[:, on].std(axis=0), std[on], rtol=0.03)
    assert np.all(np.abs(noise[:, on].mean(axis=0)) < 4 * std[on] / np.sqrt(n))
    corr = np.corrcoef(noise[:, on].T)  # independent entries
    assert np.max(np.abs(corr - np.eye(on.sum()))) < 0.05
    lag1 = np.mean(noise[1:, 3] * noise[:-1, 3]) / std[3] ** 2  # white in time
    assert abs(lag1) < 0.05
    # what the controller measures: the paper-layout state plus exactly this noise
    x = jnp.arange(12.0) / 10
    np.testing.assert_allclose(A.measure(s, x, 5) - x, noise[5], atol=1e-15)
    same = A.UnmodeledDynamics.make(
        control_rate=100,
        noise_angle=0.01,
        noise_rate=0.05,
        noise_altitude=0.03,
        noise_vertical_speed=0.07,
        seed=7,
    )
    other = eqx.tree_at(lambda u: u.key, same, jax.random.PRNGKey(8))
    np.testing.assert_array_equal(A.measurement_noise(same, 123), noise[123])
    assert not np.allclose(A.measurement_noise(other, 123), noise[123])


def test_noisy_runs_are_reproducible_per_seed():
    sc = _short(A.paper_scenario("ideal", "step"), 2.0)

    def make(seed, level=1.0):
        return _digital(
            plant="full",
            motor_tau=0.02,
            control_rate=100,
            delay_samples=1,
            seed=seed,
            noise_angle=0.01 * level,
            noise_rate=0.05 * level,
            noise_altitude=0.02 * level,
            noise_vertical_speed=0.05 * level,
        )

    batch = A.stack_unmodeled([make(1), make(1), make(2), make(1, 0.0)])
    r = jax.vmap(lambda s: _sim_traj(sc, s))(batch)
    assert np.all(np.asarray(r.status) == 0)
    ise = np.asarray(r.ise_attitude)
    assert ise[0] == ise[1]
    assert np.array_equal(np.asarray(r.plant[0]), np.asarray(r.plant[1]))
    assert ise[2] != ise[0] and ise[3] != ise[0]
    # the noise really acts on the loop: u_command differs from the noise-free run
    assert np.max(np.abs(np.asarray(r.u_command[0] - r.u_command[3]))) > 1e-4


def test_controller_too_slow_for_delay_is_flagged_diverged():
    """FBL at 20 Hz: fine without delay, unstable with a 4-sample (200 ms) delay (also at 100 Hz
    with a 12-sample delay). Reported as diverged, never raised."""
    sc = _short(A.paper_scenario("ideal", "step"), 8.0)
    cases = [(20, 0), (20, 4), (100, 0), (100, 12)]
    batch = A.stack_unmodeled(
        [_digital(plant="full", control_rate=f, delay_samples=d, max_delay=12) for f, d in cases]
    )
    r = jax.vmap(lambda s: _sim_traj(sc, s))(batch)
    status = np.asarray(r.status)
    np.testing.assert_array_equal(status, [0, 1, 0, 1])
    assert A.STATUS_NAMES[int(status[1])] == "diverged"
    assert np.all(np.asarray(r.t_final)[[1, 3]] < 8.0)
    assert np.isinf(np.asarray(r.plant[1, -1])).all()  # samples after the stop are inf


def test_too_few_samples_reports_solver_failed():
    sc = A.paper_scenario("ideal", "step")  # 20 s, but 1200 samples at 100 Hz cover 12 s
    r = _sim_traj(sc, _digital(plant="full", control_rate=100))
    assert int(r.status) == 2 and abs(float(r.t_final) - 12.0) < 1e-9


def test_digital_loop_gradient_matches_finite_differences():
    """d ISE_altitude / d P_z through the digital loop (full plant, motor lag, delay, noise
    off): reverse mode through the sample scan and the inner diffrax solves vs central FD."""
    sc = _short(A.paper_scenario("uncertain", "step"), 1.0)
    s = A.UnmodeledDynamics.make(
        plant="full", motor_tau=0.02, control_rate=40, duration=1.0, delay_samples=1
    )

    @jax.jit
    @jax.value_and_grad
    def ise(p_gain):
        c = A.FBLPID(P=jnp.array([30.0, 30.0, 30.0, 0.0]) + jnp.array([0, 0, 0, 1.0]) * p_gain)
        r = A.simulate(c, sc, n_save=0, unmodeled=s, rtol=1e-10, atol=1e-12)
        return jnp.where(r.status == 0, r.ise_altitude, jnp.nan)

    value, g = ise(80.0)
    assert np.isfinite(value)
    h = 1e-3
    fd = (ise(80.0 + h)[0] - ise(80.0 - h)[0]) / (2 * h)
    assert abs(float(g)) > 1e-6
    np.testing.assert_allclose(g, fd, rtol=1e-4)


# ------------------------------------------------------------------------------ validation, CLI


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(plant="exact"), "plant must be one of"),
        (dict(motor_tau=-0.01), "motor_tau must be >= 0"),
        (dict(noise_angle=0.01), "need a digital controller"),
        (dict(max_samples=10, delay_samples=9), "delay_samples must be in"),
        (dict(max_samples=10, control_rate=0.0), "control_rate must be finite and > 0"),
    ],
)
def test_invalid_settings_are_rejected(kwargs, match):
    with pytest.raises(ValueError, match=match):
        A.UnmodeledDynamics(**kwargs)


def test_reproduce_flags_map_to_settings():
    from afbl_jax.cli import build_parser
    from afbl_jax.cli.unmodeled import unmodeled_from_args

    parse = build_parser().parse_args
    assert unmodeled_from_args(parse(["reproduce", "--out", "x"])) is None  # paper default
    s = unmodeled_from_args(
        parse(
            [
                "reproduce",
                "--out",
                "x",
                "--plant",
                "full",
                "--motor-tau",
                "0.03",
                "--control-rate",
                "250",
                "--delay-samples",
                "2",
                "--noise",
                "2",
                "--seed",
                "5",
            ]
        )
    )
    assert s.plant == "full" and s.max_samples == 5000 and int(s.delay_samples) == 2
    np.testing.assert_allclose([s.motor_tau, s.control_rate, s.noise_angle], [0.03, 250, 0.01])
    np.testing.assert_array_equal(s.key, jax.random.PRNGKey(5))
    with pytest.raises(ValueError, match="need --control-rate"):
        unmodeled_from_args(parse(["reproduce", "--out", "x", "--noise", "1"]))


def test_unmodeled_study_small_grid(tmp_path):
    import json

    from afbl_jax.cli import main

    study = tmp_path / "study"
    rc = main(
        [
            "unmodeled",
            "--out",
            str(study),
            "--controllers",
            "fbl",
            "--taus",
            "0,0.05",
            "--rates",
            "25",
            "--noise-levels",
            "0",
            "--delay-samples",
            "3",
        ]
    )
    assert rc == 0
    res = json.loads((study / "unmodeled_dynamics.json").read_text())
    fail = np.array(res["failure_rate"]["fbl"])
    assert fail.shape == (1, 2, 1) and np.all((fail >= 0) & (fail <= 1))
    assert res["meta"]["config"]["delay_samples"] == 3
    assert (study / "stability_boundary_fbl.png").exists()


@pytest.mark.slow
def test_cli_reproduce_with_unmodeled_flags(tmp_path):
    import json

    from afbl_jax.cli import main

    out = tmp_path / "rep"
    rc = main(
        [
            "reproduce",
            "--out",
            str(out),
            "--controllers",
            "fbl",
            "--no-figures",
            "--n-save",
            "2",
            "--rtol",
            "1e-6",
            "--atol",
            "1e-8",
            "--plant",
            "full",
            "--motor-tau",
            "0.03",
            "--control-rate",
            "250",
        ]
    )
    assert rc == 0
    doc = json.loads((out / "ise.json").read_text())
    cfg = doc["meta"]["config"]["unmodeled"]
    assert cfg["plant"] == "full" and cfg["motor_tau"] == 0.03 and cfg["control_rate"] == 250
    assert cfg["max_samples"] == 5000
