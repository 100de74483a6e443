"""Independent numpy + scipy reference implementation of the quadrotor closed loop.

This module deliberately uses only numpy and scipy so that it can cross-check the
JAX/diffrax implementation. All quantities are in SI units:

* angles in rad, angular rates in rad/s, angular accelerations in rad/s^2;
* positions in m, velocities in m/s, accelerations in m/s^2;
* forces in N, torques in N m, masses in kg, inertias in kg m^2;
* time in s.

Channel order for references, errors, virtual inputs and controller states is
``(phi, theta, psi, z)``.

The rotor gyroscopic term has eq. (14)'s sign (``afbl_jax.EQ14_GYRO_SIGN``).

Full ODE state (18 entries)::

    y[0:12]  plant state [x, y, z, phi, theta, psi, xd, yd, zd, phid, thetad, psid]
    y[12:16] controller state (integral of error for "fbl", disturbance estimate
             dhat for "afbl" / "afbl_paper"), channel order (phi, theta, psi, z)
    y[16]    ISE of attitude errors, integral of e_phi^2 + e_theta^2 + e_psi^2 [rad^2 s]
    y[17]    ISE of altitude error, integral of e_z^2 [m^2 s]
"""

from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp

__all__ = [
    "CONTROLLERS",
    "DEFAULT_PARAMS",
    "PROFILES",
    "SCENARIOS",
    "closed_loop_rhs",
    "disturbance",
    "hover_acceleration_check",
    "plant_acceleration",
    "reference_signal",
    "simulate_reference",
]

CONTROLLERS = ("fbl", "afbl", "afbl_paper")
SCENARIOS = ("ideal", "uncertain")
PROFILES = ("step", "sine")

DEFAULT_PARAMS: dict[str, float] = {
    "m": 0.650,  # nominal mass [kg]
    "Ix": 7.5e-3,  # roll inertia [kg m^2]
    "Iy": 7.5e-3,  # pitch inertia [kg m^2]
    "Iz": 1.3e-2,  # yaw inertia [kg m^2]
    "b": 3.13e-5,  # thrust coefficient [N s^2]
    "d": 7.5e-7,  # drag (yaw moment) coefficient [N m s^2]
    "Jr": 6e-5,  # rotor inertia [kg m^2]
    "l": 0.23,  # arm length [m]
    "g": 9.81,  # gravitational acceleration [m/s^2]
    "Omega_min": 0.0,  # minimum rotor speed [rad/s]
    "Omega_max": float("inf"),  # maximum rotor speed [rad/s]
}

# Controller gains, channel order (phi, theta, psi, z).
FBL_P = np.array([30.0, 30.0, 30.0, 80.0])
FBL_I = np.array([8.0, 8.0, 8.0, 10.0])
FBL_D = np.array([8.0, 8.0, 8.0, 10.0])
AFBL_LAMBDA = np.array([4.0, 4.0, 4.0, 4.0])
AFBL_GAMMA = np.array([8.0, 15.0, 8.0, 20.0])
AFBL_K = np.array([8.0, 15.0, 8.0, 80.0])

# Scenario constants.
UNCERTAIN_MASS_FACTOR = 1.5  # true mass = 1.5 * nominal mass
TORQUE_PULSE = np.array([0.01, 0.01, 0.01])  # body torque disturbance [N m]
TORQUE_PULSE_WINDOW = (10.0, 11.0)  # [s], active for t0 <= t < t1
FORCE_PULSE = -2.0  # vertical force disturbance [N]
FORCE_PULSE_WINDOW = (12.0, 13.0)  # [s], active for t0 <= t < t1

BLEND_DURATION = 1.0  # duration of a smooth step [s]

# Smooth steps as (channel index, start time t0 [s], increment (b - a)).
_Z_STEPS = ((3, 1.0, 1.0), (3, 16.0, -1.0))
_ATTITUDE_STEPS = (
    (0, 4.0, 0.1),
    (0, 8.0, -0.1),
    (1, 6.0, -0.1),
    (1, 10.0, 0.1),
    (2, 8.0, 0.2),
    (2, 12.0, -0.2),
)

# Initial plant state: phi = 0.05 rad, theta = -0.05 rad, psi = 0.05 rad, rest zero.
INITIAL_PLANT_STATE = np.zeros(12)
INITIAL_PLANT_STATE[3:6] = (0.05, -0.05, 0.05)


def _check_choice(name: str, value: str, allowed: tuple[str, ...]) -> None:
    if value not in allowed:
        raise ValueError(f"unknown {name} {value!r}; expected one of {allowed}")


def _smooth_step(t: float, t0: float) -> tuple[float, float, float]:
    """Quintic smooth step 10 tau^3 - 15 tau^4 + 6 tau^5 and its time derivatives.

    ``tau = clip((t - t0) / BLEND_DURATION, 0, 1)``. Returns ``(s, ds/dt, d2s/dt2)``
    in units (1, 1/s, 1/s^2); the derivatives are zero outside ``0 < tau < 1``.
    """
    tau = (t - t0) / BLEND_DURATION
    if tau <= 0.0:
        return 0.0, 0.0, 0.0
    if tau >= 1.0:
        return 1.0, 0.0, 0.0
    s = tau**3 * (10.0 - 15.0 * tau + 6.0 * tau**2)
    ds = 30.0 * tau**2 * (1.0 - tau) ** 2 / BLEND_DURATION
    dds = 60.0 * tau * (1.0 - 3.0 * tau + 2.0 * tau**2) / BLEND_DURATION**2
    return s, ds, dds


def reference_signal(profile: str, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Reference ``(r, rdot, rddot)`` at time ``t`` [s], each shape (4,).

    Channel order (phi [rad], theta [rad], psi [rad], z [m]); ``rdot`` in rad/s or
    m/s and ``rddot`` in rad/s^2 or m/s^2.
    """
    _check_choice("profile", profile, PROFILES)
    t = float(t)
    r = np.zeros(4)
    rd = np.zeros(4)
    rdd = np.zeros(4)
    steps = _Z_STEPS + (_ATTITUDE_STEPS if profile == "step" else ())
    for channel, t0, delta in steps:
        s, ds, dds = _smooth_step(t, t0)
        r[channel] += delta * s
        rd[channel] += delta * ds
        rdd[channel] += delta * dds
    if profile == "sine":
        # (amplitude [rad], angular frequency [rad/s]) for phi, theta, psi.
        for channel, (amp, w) in enumerate(((0.1, 1.0), (0.1, 0.8), (0.2, 0.5))):
            r[channel] = amp * np.sin(w * t)
            rd[channel] = amp * w * np.cos(w * t)
            rdd[channel] = -amp * w**2 * np.sin(w * t)
    return r, rd, rdd


def disturbance(scenario: str, t: float) -> tuple[np.ndarray, float]:
    """External disturbance at time ``t`` [s].

    Returns ``(tau, f_z)``: body torque ``tau`` [N m] on (phi, theta, psi), shape (3,),
    and vertical force ``f_z`` [N]. Windows are half-open, ``t0 <= t < t1``.
    """
    _check_choice("scenario", scenario, SCENARIOS)
    tau = np.zeros(3)
    f_z = 0.0
    if scenario == "uncertain":
        if TORQUE_PULSE_WINDOW[0] <= t < TORQUE_PULSE_WINDOW[1]:
            tau = TORQUE_PULSE.copy()
        if FORCE_PULSE_WINDOW[0] <= t < FORCE_PULSE_WINDOW[1]:
            f_z = FORCE_PULSE
    return tau, f_z


def _true_mass(scenario: str, params: dict[str, float]) -> float:
    """True plant mass [kg] for the scenario."""
    return params["m"] * (UNCERTAIN_MASS_FACTOR if scenario == "uncertain" else 1.0)


def _mixer(u: np.ndarray, params: dict[str, float]) -> tuple[np.ndarray, float]:
    """Map commanded ``u`` to applied inputs through saturated rotor speeds.

    ``u = (u1, u2, u3, u4)``: roll/pitch thrust differences [N], yaw moment [N m],
    total thrust [N]. Returns the applied ``U`` (same units) and the residual rotor
    speed ``Omega_d = -Omega1 + Omega2 - Omega3 + Omega4`` [rad/s].
    """
    b, d = params["b"], params["d"]
    u1, u2, u3, u4 = u
    w_cmd = np.array(
        [
            u4 / (4 * b) - u2 / (2 * b) - u3 / (4 * d),
            u4 / (4 * b) - u1 / (2 * b) + u3 / (4 * d),
            u4 / (4 * b) + u2 / (2 * b) - u3 / (4 * d),
            u4 / (4 * b) + u1 / (2 * b) + u3 / (4 * d),
        ]
    )  # squared rotor speeds [rad^2/s^2]
    w = np.clip(w_cmd, params["Omega_min"] ** 2, params["Omega_max"] ** 2)
    applied = np.array(
        [
            b * (w[3] - w[1]),
            b * (w[2] - w[0]),
            d * (w[1] + w[3] - w[0] - w[2]),
            b * (w[0] + w[1] + w[2] + w[3]),
        ]
    )
    omega = np.sqrt(w)
    omega_d = -omega[0] + omega[1] - omega[2] + omega[3]
    return applied, float(omega_d)


def plant_acceleration(
    plant: np.ndarray,
    applied: np.ndarray,
    omega_d: float,
    m_true: float,
    tau: np.ndarray,
    f_z: float,
    params: dict[str, float] = DEFAULT_PARAMS,
) -> np.ndarray:
    """Plant accelerations ``[xdd, ydd, zdd, phidd, thetadd, psidd]``.

    Units: m/s^2 for translations, rad/s^2 for rotations. ``applied`` are the applied
    inputs ``(U1 [N], U2 [N], U3 [N m], U4 [N])``, ``omega_d`` in rad/s, ``m_true`` in
    kg, ``tau`` in N m, ``f_z`` in N.
    """
    ix, iy, iz = params["Ix"], params["Iy"], params["Iz"]
    jr, arm, g = params["Jr"], params["l"], params["g"]
    phi, theta, psi = plant[3:6]
    phid, thetad, psid = plant[9:12]
    u1, u2, u3, u4 = applied
    cphi, sphi = np.cos(phi), np.sin(phi)
    cth, sth = np.cos(theta), np.sin(theta)
    cpsi, spsi = np.cos(psi), np.sin(psi)
    return np.array(
        [
            (cphi * sth * cpsi + sphi * spsi) * u4 / m_true,
            (cphi * sth * spsi - sphi * cpsi) * u4 / m_true,
            -g + cphi * cth * u4 / m_true + f_z / m_true,
            thetad * psid * (iy - iz) / ix
            - (jr / ix) * thetad * omega_d
            + arm * u1 / ix
            + tau[0] / ix,
            phid * psid * (iz - ix) / iy + (jr / iy) * phid * omega_d + arm * u2 / iy + tau[1] / iy,
            phid * thetad * (ix - iy) / iz + u3 / iz + tau[2] / iz,
        ]
    )


def _inversion(plant: np.ndarray, v: np.ndarray, params: dict[str, float]) -> np.ndarray:
    """Nominal feedback-linearising inversion from virtual input ``v`` to ``u``.

    ``v`` is in rad/s^2 (attitude) and m/s^2 (z). Returns ``(u1 [N], u2 [N], u3 [N m],
    u4 [N])``. The gyroscopic ``Omega_d`` term is not compensated.
    """
    ix, iy, iz = params["Ix"], params["Iy"], params["Iz"]
    arm, m, g = params["l"], params["m"], params["g"]
    phi, theta = plant[3], plant[4]
    phid, thetad, psid = plant[9:12]
    return np.array(
        [
            (ix / arm) * (v[0] - thetad * psid * (iy - iz) / ix),
            (iy / arm) * (v[1] - phid * psid * (iz - ix) / iy),
            iz * (v[2] - phid * thetad * (ix - iy) / iz),
            m * (g + v[3]) / (np.cos(phi) * np.cos(theta)),
        ]
    )


def _control_law(
    controller: str,
    ctrl_state: np.ndarray,
    e: np.ndarray,
    ed: np.ndarray,
    rdd: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Virtual input ``v`` and controller-state derivative for one controller."""
    if controller == "fbl":
        xi = ctrl_state
        v = FBL_P * e + FBL_I * xi + FBL_D * ed
        return v, e
    if controller == "afbl":
        dhat = ctrl_state
        s = ed + AFBL_LAMBDA * e
        v = rdd + AFBL_LAMBDA * ed - dhat + AFBL_K * s
        return v, -s / AFBL_GAMMA
    if controller == "afbl_paper":
        dhat = ctrl_state
        v = rdd - dhat + AFBL_K * ed
        return v, -ed / AFBL_GAMMA
    raise ValueError(f"unknown controller {controller!r}; expected one of {CONTROLLERS}")


def closed_loop_rhs(
    t: float,
    y: np.ndarray,
    controller: str,
    scenario: str,
    profile: str,
    params: dict[str, float] = DEFAULT_PARAMS,
    t_disturbance: float | None = None,
) -> np.ndarray:
    """Time derivative of the full 18-entry closed-loop state.

    ``t_disturbance`` [s] is the time at which the piecewise-constant disturbance is
    evaluated (defaults to ``t``). The piecewise integrator passes the midpoint of the
    current piece so that the solver's end-of-step stage at a pulse edge still sees the
    disturbance value belonging to that piece.
    """
    plant = y[0:12]
    ctrl_state = y[12:16]
    r, rd, rdd = reference_signal(profile, t)
    q = np.array([plant[3], plant[4], plant[5], plant[2]])
    qd = np.array([plant[9], plant[10], plant[11], plant[8]])
    e = r - q
    ed = rd - qd

    v, ctrl_dot = _control_law(controller, ctrl_state, e, ed, rdd)
    u = _inversion(plant, v, params)
    applied, omega_d = _mixer(u, params)
    tau, f_z = disturbance(scenario, t if t_disturbance is None else t_disturbance)
    m_true = _true_mass(scenario, params)
    acc = plant_acceleration(plant, applied, omega_d, m_true, tau, f_z, params)

    dy = np.empty(18)
    dy[0:6] = plant[6:12]
    dy[6:12] = acc
    dy[12:16] = ctrl_dot
    dy[16] = e[0] ** 2 + e[1] ** 2 + e[2] ** 2
    dy[17] = e[3] ** 2
    return dy


def _breakpoints(scenario: str, profile: str, t1: float) -> np.ndarray:
    """Sorted piece boundaries in [0, t1] [s]: blend starts/ends and pulse edges."""
    times = {0.0, float(t1)}
    steps = _Z_STEPS + (_ATTITUDE_STEPS if profile == "step" else ())
    for _, t0, _ in steps:
        times.update((t0, t0 + BLEND_DURATION))
    if scenario == "uncertain":
        times.update(TORQUE_PULSE_WINDOW)
        times.update(FORCE_PULSE_WINDOW)
    return np.array(sorted(t for t in times if 0.0 <= t <= t1))


def simulate_reference(
    controller: str,
    scenario: str,
    profile: str,
    rtol: float = 1e-11,
    atol: float = 1e-12,
    t1: float = 20.0,
) -> dict:
    """Simulate the closed loop on [0, t1] [s] with piecewise DOP853 integration.

    The interval is split at every reference blend start/end and disturbance pulse
    edge; each piece restarts from the previous piece's end state.

    Returns a dict with ``ise_attitude`` [rad^2 s], ``ise_altitude`` [m^2 s],
    ``y_final`` (full 18-entry state at ``t1``) and ``plant_final`` (shape (12,)).
    """
    _check_choice("controller", controller, CONTROLLERS)
    _check_choice("scenario", scenario, SCENARIOS)
    _check_choice("profile", profile, PROFILES)
    if not t1 > 0.0:
        raise ValueError(f"t1 must be positive, got {t1!r}")

    y = np.zeros(18)
    y[0:12] = INITIAL_PLANT_STATE
    edges = _breakpoints(scenario, profile, t1)
    for ta, tb in zip(edges[:-1], edges[1:], strict=True):
        t_mid = 0.5 * (ta + tb)
        sol = solve_ivp(
            closed_loop_rhs,
            (ta, tb),
            y,
            method="DOP853",
            rtol=rtol,
            atol=atol,
            args=(controller, scenario, profile, DEFAULT_PARAMS, t_mid),
        )
        if not sol.success:
            raise RuntimeError(
                f"solve_ivp failed on [{ta}, {tb}] for "
                f"({controller}, {scenario}, {profile}): {sol.message}"
            )
        y = sol.y[:, -1].copy()

    return {
        "ise_attitude": float(y[16]),
        "ise_altitude": float(y[17]),
        "y_final": y,
        "plant_final": y[0:12].copy(),
    }


def hover_acceleration_check(params: dict[str, float] = DEFAULT_PARAMS) -> np.ndarray:
    """Plant accelerations at level hover with ``u4 = m g`` and zero rates (expected 0)."""
    plant = np.zeros(12)
    u = np.array([0.0, 0.0, 0.0, params["m"] * params["g"]])
    applied, omega_d = _mixer(u, params)
    return plant_acceleration(plant, applied, omega_d, params["m"], np.zeros(3), 0.0, params)
