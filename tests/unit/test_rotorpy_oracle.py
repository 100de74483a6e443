"""External oracle: RotorPy's multirotor model (rotorpy on PyPI) against our full rigid-body
plant and our rotor-drag model, driven with the same open-loop rotor speeds.

RotorPy side: ``Multirotor`` with our vehicle's mass, inertia, b, d, hub positions and yaw-torque
signs; its state equation (``Multirotor._s_dot_fn``, the function its own ``step`` integrates)
is integrated by scipy's DOP853 at tight tolerances. RotorPy has no rotor gyroscopic torque, so
the subclass below adds -omega x (Jr Omega_r e_z) with the rotor spin directions its
``rotor_directions`` imply (spin opposite to the reaction torque). Its first-order motor model
(time constant 1 ms) is fed the command Omega(t) + tau Omega'(t) and starts at Omega(0), so its
rotor states equal the prescribed speeds exactly (the lag ODE is linear with that solution).
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from rotorpy.vehicles import multirotor
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation

import afbl_jax as A
from afbl_jax.model import RotorDrag, full_plant_derivative, omega_d, rotor_drag_wrench

TAU_M = 1e-3  # RotorPy motor time constant [s]
T_END = 2.0  # [s]
ROTOR_DIRECTIONS = np.array([-1, 1, -1, 1])  # RotorPy yaw-moment signs of u3 = d(-W1+W2-W3+W4)


def _vehicle(**kw) -> A.QuadrotorParams:
    return A.QuadrotorParams(hub_height=0.04, **kw)


def _quad_params(p: A.QuadrotorParams, aero: bool) -> dict:
    hubs = np.asarray(p.rotor_positions())
    kh = float(p.rotor_drag_horizontal) if aero else 0.0
    return {
        "mass": float(p.m),
        "Ixx": float(p.Ix),
        "Iyy": float(p.Iy),
        "Izz": float(p.Iz),
        "Ixy": 0.0,
        "Iyz": 0.0,
        "Ixz": 0.0,
        "num_rotors": 4,
        "rotor_radius": 0.15,
        "rotor_pos": {f"r{i + 1}": hubs[i] for i in range(4)},
        "rotor_directions": ROTOR_DIRECTIONS,
        "rI": np.zeros(3),
        "c_Dx": float(p.parasitic_drag_horizontal),
        "c_Dy": float(p.parasitic_drag_horizontal),
        "c_Dz": float(p.parasitic_drag_vertical),
        "k_eta": float(p.b),
        "k_m": float(p.d),
        "k_d": kh,
        "k_z": float(p.rotor_drag_vertical),
        "k_h": 0.0,  # translational lift: not modelled here
        "k_flap": 0.0,
        "tau_m": TAU_M,
        "rotor_speed_min": 0.0,
        "rotor_speed_max": 1e4,
        "motor_noise_std": 0.0,
    }


class _GyroMultirotor(multirotor.Multirotor):
    """RotorPy's multirotor plus the rotor gyroscopic torque -omega x (Jr Omega_r e_z)."""

    def __init__(self, params, jr, aero):
        super().__init__(params, aero=aero)
        self.jr = jr

    def compute_body_wrench(self, body_rates, rotor_speeds, body_airspeed_vector):
        force, moment = super().compute_body_wrench(body_rates, rotor_speeds, body_airspeed_vector)
        spin = -self.rotor_dir  # a rotor spins opposite to the reaction torque it puts on the body
        h_rotors = np.array([0.0, 0.0, self.jr * np.sum(spin * rotor_speeds)])
        return force, moment - np.cross(body_rates, h_rotors)


def _rotor_speeds(t, omega0):
    """Hover plus differential sinusoids (roll, pitch, yaw) and their time derivative."""
    roll, droll = 1.0 * np.sin(np.pi * t), 1.0 * np.pi * np.cos(np.pi * t)
    a, w = 0.7, 1.3 * np.pi
    pitch, dpitch = a * np.sin(w * t + 0.3), a * w * np.cos(w * t + 0.3)
    yaw, dyaw = 10.0 * np.sin(2.0 * t), 20.0 * np.cos(2.0 * t)
    s = np.stack([-pitch - yaw, -roll + yaw, pitch - yaw, roll + yaw])
    ds = np.stack([-dpitch - dyaw, -droll + dyaw, dpitch - dyaw, droll + dyaw])
    return omega0 + s, ds


def _rotorpy_final(p: A.QuadrotorParams, wind, aero: bool):
    quad = _GyroMultirotor(_quad_params(p, aero), float(p.Jr), aero)
    omega0 = float(p.hover_omega)
    speeds0, _ = _rotor_speeds(0.0, omega0)
    state = {
        "x": np.zeros(3),
        "v": np.zeros(3),
        "q": np.array([0.0, 0.0, 0.0, 1.0]),
        "w": np.zeros(3),
        "wind": np.asarray(wind, float),
        "rotor_speeds": speeds0,
    }

    def rhs(t, s):
        speeds, dspeeds = _rotor_speeds(t, omega0)
        return quad._s_dot_fn(t, s, speeds + TAU_M * dspeeds)

    s0 = multirotor.Multirotor._pack_state(state)
    sol = solve_ivp(rhs, (0.0, T_END), s0, method="DOP853", rtol=1e-12, atol=1e-12)
    assert sol.success
    final = multirotor.Multirotor._unpack_state(sol.y[:, -1])
    psi, theta, phi = Rotation.from_quat(final["q"]).as_euler("ZYX")
    return final["x"], np.array([phi, theta, psi])


def _ours_final(p: A.QuadrotorParams, wind, aero: bool):
    plant = A.RigidBodyPlant()
    omega0 = float(p.hover_omega)
    wind = jnp.asarray(wind, float)

    def field(t, y, args):
        roll = jnp.sin(jnp.pi * t)
        pitch = 0.7 * jnp.sin(1.3 * jnp.pi * t + 0.3)
        yaw = 10.0 * jnp.sin(2.0 * t)
        speeds = omega0 + jnp.stack([-pitch - yaw, -roll + yaw, pitch - yaw, roll + yaw])
        u = A.inputs_from_rotor_speeds_sq(p, speeds**2)
        if aero:
            force, torque = RotorDrag().wrench(wind, plant.to_paper_layout(y), p, speeds)
        else:
            force, torque = jnp.zeros(3), jnp.zeros(3)
        return full_plant_derivative(p, y, u, omega_d(speeds), p.m, force, torque)

    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(field),
        diffrax.Dopri8(),
        0.0,
        T_END,
        1e-3,
        jnp.zeros(12),
        stepsize_controller=diffrax.PIDController(rtol=1e-13, atol=1e-13),
        max_steps=100000,
    )
    y = np.asarray(sol.ys[-1])
    return y[0:3], y[3:6]


def test_open_loop_agrees_with_rotorpy_multirotor():
    """Aero off, gyroscopic term on both sides, a 0.5 rad manoeuvre: agreement to 1e-8."""
    p = _vehicle()
    pos_ref, ang_ref = _rotorpy_final(p, np.zeros(3), aero=False)
    pos, ang = _ours_final(p, np.zeros(3), aero=False)
    assert np.max(np.abs(ang_ref[:2])) > 0.4  # a large manoeuvre, not a hover
    np.testing.assert_allclose(pos, pos_ref, rtol=0, atol=1e-8)
    np.testing.assert_allclose(ang, ang_ref, rtol=0, atol=1e-8)
    # eq. 14's sign is the other one: the same run with it drifts far apart
    eq14 = eqx.tree_at(lambda q: q.gyro_sign, p, jnp.asarray(A.EQ14_GYRO_SIGN))
    _, ang_eq14 = _ours_final(eq14, np.zeros(3), aero=False)
    assert np.max(np.abs(ang_eq14 - ang_ref)) > 1e-2


def test_rotor_drag_trajectory_agrees_with_rotorpy_in_wind():
    """Rotor drag at the hubs + parasitic drag (same coefficients as RotorPy's, its
    translational lift and flapping off), steady wind, same open-loop rotor speeds."""
    p = _vehicle()
    wind = np.array([4.0, -2.5, 0.8])
    pos_ref, ang_ref = _rotorpy_final(p, wind, aero=True)
    pos, ang = _ours_final(p, wind, aero=True)
    pos_calm, _ = _ours_final(p, np.zeros(3), aero=False)
    assert np.linalg.norm(pos - pos_calm) > 0.1  # the wind moved the vehicle
    np.testing.assert_allclose(pos, pos_ref, rtol=0, atol=1e-8)
    np.testing.assert_allclose(ang, ang_ref, rtol=0, atol=1e-8)


def test_rotor_drag_wrench_matches_rotorpy_pointwise():
    rng = np.random.default_rng(0)
    p = _vehicle(cp_offset=0.0)
    quad = multirotor.Multirotor(_quad_params(p, True), aero=True)
    calm = multirotor.Multirotor(_quad_params(p, True), aero=False)
    for _ in range(20):
        eta = rng.uniform(-0.6, 0.6, 3)
        etad = rng.uniform(-2.0, 2.0, 3)
        vel, wind = rng.uniform(-6, 6, 3), rng.uniform(-8, 8, 3)
        speeds = rng.uniform(150.0, 330.0, 4)
        state = np.concatenate([rng.normal(size=3), eta, vel, etad])
        force, torque = rotor_drag_wrench(jnp.asarray(wind), jnp.asarray(state), p, speeds)
        rot = Rotation.from_euler("ZYX", eta[::-1]).as_matrix()
        rates = np.asarray(A.body_rates_from_euler_rates(eta[0], eta[1], jnp.asarray(etad)))
        airspeed = rot.T @ (vel - wind)
        f_on, m_on = quad.compute_body_wrench(rates, speeds, airspeed)
        f_off, m_off = calm.compute_body_wrench(rates, speeds, airspeed)
        np.testing.assert_allclose(np.asarray(force), rot @ (f_on - f_off), rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(np.asarray(torque), m_on - m_off, rtol=1e-12, atol=1e-14)


def test_rotor_drag_gradient_is_finite_at_zero_airspeed():
    p = A.QuadrotorParams()
    state = jnp.zeros(12)

    def fx(v):
        return rotor_drag_wrench(v, state, p, jnp.full(4, 225.0))[0][0]

    g = jax.grad(fx)(jnp.zeros(3))
    assert np.all(np.isfinite(np.asarray(g)))


def test_se3_hover_in_wind_settles_at_our_trim():
    """RotorPy's multirotor (rotor drag + parasitic drag, same coefficients) flown by RotorPy's
    own SE3 controller holding a point in a steady wind settles at our trim
    (`afbl_jax.solve_trim` at RotorPy's settled yaw): the same tilt (1e-6 rad) and rotor speeds
    (1e-6 relative). The controllers differ (SE3 has no integral action and settles off the
    point); the equilibrium is the physics'."""
    from rotorpy.controllers.quadrotor_control import SE3Control

    p = _vehicle(rotor_drag_horizontal=3e-4, rotor_drag_vertical=6e-4)
    params = {**_quad_params(p, True), "tau_m": 5e-3}
    quad = multirotor.Multirotor(params, aero=True)
    control = SE3Control(params)
    wind = np.array([5.0, -3.0, 0.0])
    zero = np.zeros(3)
    flat = {"x": zero, "x_dot": zero, "x_ddot": zero, "x_dddot": zero, "x_ddddot": zero}
    flat.update(yaw=0.0, yaw_dot=0.0, yaw_ddot=0.0)

    def rhs(t, s):
        state = multirotor.Multirotor._unpack_state(s)
        state["q"] = state["q"] / np.linalg.norm(state["q"])
        cmd = control.update(t, state, flat)["cmd_motor_speeds"]
        return quad._s_dot_fn(t, s, np.clip(cmd, 0.0, 1e4))

    omega0 = float(p.hover_omega)
    state0 = {
        "x": zero,
        "v": zero,
        "q": np.array([0.0, 0.0, 0.0, 1.0]),
        "w": zero,
        "wind": wind,
        "rotor_speeds": np.full(4, omega0),
    }
    s0 = multirotor.Multirotor._pack_state(state0)
    sol = solve_ivp(rhs, (0.0, 25.0), s0, method="DOP853", rtol=1e-11, atol=1e-11)
    assert sol.success
    final = multirotor.Multirotor._unpack_state(sol.y[:, -1])
    np.testing.assert_allclose(final["v"], 0.0, atol=1e-8)  # settled
    np.testing.assert_allclose(final["w"], 0.0, atol=1e-8)
    assert np.linalg.norm(final["x"]) > 0.05  # SE3 settles off the point (no integral action)
    psi, theta, phi = Rotation.from_quat(final["q"]).as_euler("ZYX")
    ours = A.solve_trim(p, p, RotorDrag(), jnp.asarray(wind), jnp.zeros(3), p.m, psi)
    assert bool(ours.converged)
    np.testing.assert_allclose(np.asarray(ours.trim.attitude), [phi, theta], atol=1e-6)
    assert np.hypot(phi, theta) > 0.2  # a real tilt into the wind
    np.testing.assert_allclose(
        np.sqrt(np.asarray(ours.rotor_speeds_sq)), final["rotor_speeds"], rtol=1e-6
    )
