"""Plant, mixer, references, parameters: physics and math at the function level."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import afbl_jax as A
from afbl_jax.model import safe_sqrt

P = A.QuadrotorParams()


def _rot(phi, theta, psi):
    cx, sx, cy, sy, cz, sz = (
        np.cos(phi),
        np.sin(phi),
        np.cos(theta),
        np.sin(theta),
        np.cos(psi),
        np.sin(psi),
    )
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


def test_thrust_direction_is_third_column_of_zyx_rotation():
    rng = np.random.default_rng(0)
    for phi, theta, psi in rng.uniform(-1.2, 1.2, size=(20, 3)):
        r = _rot(phi, theta, psi)
        np.testing.assert_allclose(A.thrust_direction(phi, theta, psi), r[:, 2], atol=1e-14)
        np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-14)


def test_rotations_as_sums_equal_matrix_products_and_cos_sin_is_exact():
    rng = np.random.default_rng(3)
    for phi, theta, psi in rng.uniform(-3.0, 3.0, size=(10, 3)):
        r = A.model.rotation_matrix(phi, theta, psi)
        v = jnp.asarray(rng.normal(size=3))
        np.testing.assert_allclose(A.model.rotate(r, v), np.asarray(r) @ v, rtol=0, atol=1e-15)
        np.testing.assert_allclose(A.model.rotate_transposed(r, v), np.asarray(r).T @ v, atol=1e-15)
        c, s = A.model.cos_sin(jnp.asarray(psi))
        assert float(c) == float(jnp.cos(psi)) and float(s) == float(jnp.sin(psi))
    # the barrier is an identity for transforms too: vmap and grad through it
    angles = jnp.asarray(rng.uniform(-1.0, 1.0, size=5))
    np.testing.assert_array_equal(jax.vmap(A.model.cos_sin)(angles)[1], jnp.sin(angles))
    np.testing.assert_allclose(jax.grad(lambda a: A.model.cos_sin(a)[0])(0.3), -np.sin(0.3))


def test_hover_is_an_equilibrium():
    state = jnp.zeros(12).at[0:3].set(jnp.array([1.0, -2.0, 3.0])).at[5].set(0.7)
    u = A.hover_input(P)
    w = A.rotor_speeds_sq_from_inputs(P, u)
    np.testing.assert_allclose(w, np.full(4, P.m * P.g / (4 * P.b)), rtol=1e-14)
    u_applied, omega = A.actuate(P, P, u)
    d = A.plant_derivative(P, state, u_applied, A.omega_d(omega), P.m, jnp.zeros(3), jnp.zeros(3))
    np.testing.assert_allclose(d, np.zeros(12), atol=1e-13)
    np.testing.assert_allclose(float(A.omega_d(omega)), 0.0, atol=1e-10)


def test_payload_falls_at_the_right_rate():
    # hover thrust for m, true mass 1.5 m: zdd = g (1/1.5 - 1)
    d = A.plant_derivative(
        P, jnp.zeros(12), A.hover_input(P), 0.0, 1.5 * P.m, jnp.zeros(3), jnp.zeros(3)
    )
    np.testing.assert_allclose(d[8], P.g * (1 / 1.5 - 1), rtol=1e-14)


def test_pure_roll_torque_moves_only_phi():
    def rhs(t, y, args):
        return A.plant_derivative(
            P, y, A.hover_input(P), 0.0, P.m, jnp.zeros(3), jnp.array([1e-3, 0.0, 0.0])
        )

    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(rhs),
        diffrax.Tsit5(),
        0.0,
        1.0,
        1e-3,
        jnp.zeros(12),
        saveat=diffrax.SaveAt(t1=True),
        stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-12),
    )
    y = np.asarray(sol.ys[-1])
    # phi = tau t^2 / (2 Ix) exactly (no coupling when theta, psi rates are 0)
    np.testing.assert_allclose(y[3], 1e-3 / (2 * P.Ix), rtol=1e-9)
    np.testing.assert_allclose(y[9], 1e-3 / P.Ix, rtol=1e-9)
    assert y[4] == 0 and y[5] == 0 and y[10] == 0 and y[11] == 0
    assert y[0] == 0  # roll tilts thrust along -y only
    assert y[1] < 0


def test_gyroscopic_term_signs_and_energy():
    # eq. 14: phidd gets -(Jr/Ix) thetad Omega_d, thetadd gets +(Jr/Iy) phid Omega_d
    P = A.QuadrotorParams(gyro_sign=A.EQ14_GYRO_SIGN)
    state = jnp.zeros(12).at[9].set(0.3).at[10].set(-0.2)
    u0 = jnp.array([0.0, 0.0, 0.0, P.m * P.g])
    omega_d = 50.0
    d0 = A.plant_derivative(P, state, u0, 0.0, P.m, jnp.zeros(3), jnp.zeros(3))
    d1 = A.plant_derivative(P, state, u0, omega_d, P.m, jnp.zeros(3), jnp.zeros(3))
    np.testing.assert_allclose(d1[9] - d0[9], -P.Jr / P.Ix * (-0.2) * omega_d, rtol=1e-12)
    np.testing.assert_allclose(d1[10] - d0[10], P.Jr / P.Iy * 0.3 * omega_d, rtol=1e-12)
    # a gyroscopic torque does no work: Ix phid dphid + Iy thetad dthetad = 0
    work = P.Ix * 0.3 * (d1[9] - d0[9]) + P.Iy * (-0.2) * (d1[10] - d0[10])
    np.testing.assert_allclose(work, 0.0, atol=1e-15)
    # the default is the other sign: spin directions s = (+, -, +, -) of the eq. 16 yaw torque
    # give Omega_r = -Omega_d and Euler's -omega x (Jr Omega_r e_z) = Jr Omega_r (-q, p, 0)
    physical = A.QuadrotorParams()
    assert float(physical.gyro_sign) == A.PHYSICAL_GYRO_SIGN == -1.0
    d2 = A.plant_derivative(physical, state, u0, omega_d, P.m, jnp.zeros(3), jnp.zeros(3))
    omega_r = -omega_d
    np.testing.assert_allclose(d2[9] - d0[9], P.Jr / P.Ix * (-(-0.2)) * omega_r, rtol=1e-12)
    np.testing.assert_allclose(d2[10] - d0[10], P.Jr / P.Iy * 0.3 * omega_r, rtol=1e-12)


def test_euler_coupling_conserves_rotational_energy():
    # torque-free, gyro-free: d/dt (Ix phid^2 + Iy thetad^2 + Iz psid^2)/2 = 0 for eq. 15 rows
    p = A.QuadrotorParams(Ix=5e-3, Iy=7e-3, Iz=1.1e-2)
    state = jnp.zeros(12).at[9:12].set(jnp.array([0.4, -0.3, 0.8]))
    u = jnp.array([0.0, 0.0, 0.0, 0.0])
    d = A.plant_derivative(p, state, u, 0.0, p.m, jnp.zeros(3), jnp.zeros(3))
    rates = np.array([0.4, -0.3, 0.8])
    power = p.Ix * rates[0] * d[9] + p.Iy * rates[1] * d[10] + p.Iz * rates[2] * d[11]
    np.testing.assert_allclose(power, 0.0, atol=1e-15)


def test_feedback_linearization_inverts_the_nominal_plant():
    rng = np.random.default_rng(1)
    for _ in range(10):
        state = jnp.asarray(rng.normal(size=12) * 0.3)
        v = jnp.asarray(rng.normal(size=4))
        u = A.feedback_linearize(P, state, v)
        d = A.plant_derivative(P, state, u, 0.0, P.m, jnp.zeros(3), jnp.zeros(3))
        np.testing.assert_allclose(d[jnp.array([9, 10, 11, 8])], v, rtol=1e-10, atol=1e-12)


def test_mixer_inverse_is_exact():
    rng = np.random.default_rng(2)
    M = np.asarray(A.allocation_matrix(P))
    for _ in range(10):
        w = rng.uniform(1e4, 1e5, size=4)
        u = A.inputs_from_rotor_speeds_sq(P, jnp.asarray(w))
        np.testing.assert_allclose(u, M @ w, rtol=1e-13)
        np.testing.assert_allclose(A.rotor_speeds_sq_from_inputs(P, u), w, rtol=1e-12)
    # exact inverse of eq. 16 (eq. 19 with u3 divided by d, not b)
    Minv = np.stack(
        [np.asarray(A.rotor_speeds_sq_from_inputs(P, jnp.asarray(e))) for e in np.eye(4)], axis=1
    )
    np.testing.assert_allclose(Minv @ M, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(Minv[:, 2], np.array([-1, 1, -1, 1]) / (4 * float(P.d)))


def test_saturation_clips_rotor_speeds_and_forces():
    limited = P.with_thrust_to_weight(2.0)
    omega_max = float(limited.omega_max)
    np.testing.assert_allclose(4 * float(P.b) * omega_max**2, 2.0 * float(P.m * P.g), rtol=1e-12)
    u_cmd = jnp.array([0.5, 0.0, 0.0, 3.0 * float(P.m * P.g)])  # asks for too much
    u, omega = A.actuate(limited, limited, u_cmd)
    assert np.all(np.asarray(omega) <= omega_max * (1 + 1e-12))
    assert float(u[3]) < float(u_cmd[3])
    np.testing.assert_allclose(u, A.inputs_from_rotor_speeds_sq(limited, omega**2), rtol=1e-12)
    # below the minimum: rotor stops at omega_min = 0, no NaN in value or gradient
    u_neg = jnp.array([0.0, 0.0, 0.0, -1.0])
    u2, omega2 = A.actuate(P, P, u_neg)
    np.testing.assert_array_equal(omega2, np.zeros(4))
    g = jax.grad(lambda x: jnp.sum(A.actuate(P, P, u_neg * x)[1]))(1.0)
    assert np.isfinite(g)
    np.testing.assert_array_equal(safe_sqrt(jnp.array([4.0, 0.0, -1.0])), [2.0, 0.0, 0.0])


@pytest.mark.parametrize("profile", ["step", "sine"])
def test_reference_derivatives_match_finite_differences(profile):
    ref = A.paper_reference(profile)
    h = 1e-5
    for t in np.linspace(0.0, 20.0, 401) + 0.0123:
        s = ref(t)
        sp, sm = ref(t + h), ref(t - h)
        np.testing.assert_allclose((sp.r - sm.r) / (2 * h), s.rd, atol=1e-8)
        np.testing.assert_allclose((sp.rd - sm.rd) / (2 * h), s.rdd, atol=1e-7)


def test_paper_reference_values():
    step = A.paper_reference("step")
    np.testing.assert_allclose(step(0.5).r, [0, 0, 0, 0])
    np.testing.assert_allclose(step(2.0).r, [0, 0, 0, 1.0])
    np.testing.assert_allclose(step(4.5).r, [0.05, 0, 0, 1.0])  # blend midpoint
    np.testing.assert_allclose(step(6.0).r, [0.1, 0, 0, 1.0])
    np.testing.assert_allclose(step(9.5).r, [0, -0.1, 0.2, 1.0])
    np.testing.assert_allclose(step(19.0).r, [0, 0, 0, 0.0], atol=1e-15)
    sine = A.paper_reference("sine")
    t = 3.3
    np.testing.assert_allclose(
        sine(t).r, [0.1 * np.sin(t), 0.1 * np.sin(0.8 * t), 0.2 * np.sin(0.5 * t), 1.0]
    )
    # min-jerk blend: C2 at both ends
    for tau in (0.0, 1.0):
        s, ds, dds = A.min_jerk_blend(jnp.asarray(tau))
        assert float(ds) == 0 and float(dds) == 0 and float(s) == tau


def test_disturbance_pulses_are_half_open():
    d = A.paper_disturbance("uncertain")
    f, tq = d(10.0)
    np.testing.assert_array_equal(tq, [0.01, 0.01, 0.01])
    f, tq = d(11.0)
    np.testing.assert_array_equal(tq, [0, 0, 0])
    f, tq = d(12.5)
    np.testing.assert_array_equal(f, [0, 0, -2.0])
    f, tq = A.paper_disturbance("ideal")(10.5)
    np.testing.assert_array_equal(np.concatenate([f, tq]), np.zeros(6))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(m=0.0), "m must be > 0"),
        (dict(m=-1.0), "m must be > 0"),
        (dict(Ix=float("nan")), "Ix must be a number > 0"),
        (dict(Iz=0.0), "Iz must be > 0"),
        (dict(b=float("inf")), "b must be finite"),
        (dict(omega_min=-1.0), "omega_min must be >= 0"),
        (dict(omega_min=500.0, omega_max=400.0), "omega_max .* greater than omega_min"),
        (dict(gyro_sign=0.5), "gyro_sign must be"),
    ],
)
def test_bad_params_raise_clear_errors(kwargs, match):
    with pytest.raises(ValueError, match=match):
        A.QuadrotorParams(**kwargs)


def test_params_validation_does_not_block_transforms():
    def mass_of(m):
        return A.QuadrotorParams(m=m).hover_omega

    np.testing.assert_allclose(jax.jit(mass_of)(0.65), P.hover_omega)
    assert jax.vmap(mass_of)(jnp.array([0.5, 0.65])).shape == (2,)
    assert np.isfinite(jax.grad(mass_of)(0.65))


def test_bad_gains_and_scenarios_raise():
    with pytest.raises(ValueError, match="k must be > 0"):
        A.AFBL(k=[1.0, -2.0, 3.0, 4.0])
    with pytest.raises(ValueError, match="last dimension of 4"):
        A.FBLPID(P=[1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="unknown controller"):
        A.make_controller("lqr")
    with pytest.raises(ValueError, match="unknown gains|has gains"):
        A.make_controller("fbl", gamma=1.0)
    with pytest.raises(ValueError, match="payload_fraction must be > -1"):
        A.Scenario(A.paper_reference("step"), A.no_disturbance(), payload_fraction=-1.0)
    with pytest.raises(ValueError, match="t1 .* greater than t0"):
        A.Scenario(A.paper_reference("step"), A.no_disturbance(), t0=5.0, t1=1.0)
    with pytest.raises(ValueError, match="unknown profile"):
        A.paper_scenario("ideal", "ramp")
    with pytest.raises(ValueError, match="unknown scenario"):
        A.paper_scenario("windy", "step")
    with pytest.raises(ValueError, match="steps must chain"):
        A.make_reference(steps={"z": [(1.0, 0.0, 1.0), (2.0, 0.5, 0.0)]})
