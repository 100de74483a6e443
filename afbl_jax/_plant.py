"""Rigid-body dynamics of the paper's eq. (15), with the physically right details.

State layout (documented here once; every other module refers to it)
---------------------------------------------------------------------
The plant state is a float array of shape ``(12,)``::

    index  0  1  2  3    4      5    6   7   8   9     10      11
    name   x  y  z  phi  theta  psi  xd  yd  zd  phid  thetad  psid

x, y, z: position of the centre of mass in the earth frame [m], z up;
phi, theta, psi: ZYX Euler angles (roll, pitch, yaw) [rad];
xd ... psid: their time derivatives [m/s], [rad/s].

The closed-loop ODE state (`ClosedLoopState` in `afbl_jax._simulate`) is this plant state plus
the controller's own states and the running cost integrals.

The full rigid-body plant (`afbl_jax._unmodeled`, ``simulate(..., unmodeled=...)`` with
``plant="full"``) uses the same layout except that entries 9-11 are the body rates (p, q, r)
[rad/s] (``FULL_STATE_LAYOUT``); with motor lag the rotor speeds are extra ODE states beside
the plant state (`afbl_jax._unmodeled.UnmodeledState`).

Controller channels are always ordered (phi, theta, psi, z); `CHANNEL_INDEX` picks them from the
plant state and `CHANNEL_RATE_INDEX` picks their rates.

Differences from the printed eq. (15) (see docs/paper_notes.md):
- roll/pitch torques are l*u1, l*u2 (eq. 12 and 24 have the arm length; eq. 15/16 drop it);
- xdd, ydd use the third column of the ZYX rotation matrix (eq. 5 and 13 have typos);
- gyroscopic term with Omega_d = -Omega1 + Omega2 - Omega3 + Omega4 (eq. 17) and the signs of
  eq. (14): phidd gets -(Jr/Ix) thetad Omega_d, thetadd gets +(Jr/Iy) phid Omega_d (times
  ``QuadrotorParams.gyro_sign``, default +1; -1 gives the sign consistent with the yaw-torque
  convention of eq. 12/16, see docs/paper_notes.md);
- the yaw row's Euler coupling is phid*thetad*(Ix - Iy)/Iz (Euler's equation; eq. 15 prints
  thetad*psid).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ._params import QuadrotorParams
from ._typing import Array, PlantState, Scalar, Vec3, Vec4

STATE_LAYOUT: tuple[str, ...] = (
    "x", "y", "z", "phi", "theta", "psi", "xd", "yd", "zd", "phid", "thetad", "psid",
)
"""Names of the 12 plant-state entries, in order (SI units, radians)."""
STATE_SIZE = len(STATE_LAYOUT)
CHANNELS: tuple[str, ...] = ("phi", "theta", "psi", "z")
"""Controlled channels, in the order used by gains, references and virtual inputs."""
CHANNEL_INDEX = np.array([3, 4, 5, 2])
CHANNEL_RATE_INDEX = np.array([9, 10, 11, 8])


def channel_values(state: PlantState) -> tuple[Vec4, Vec4]:
    """Return (q, qd): the controlled coordinates (phi, theta, psi, z) and their rates."""
    return state[..., CHANNEL_INDEX], state[..., CHANNEL_RATE_INDEX]


def thrust_direction(phi: Scalar, theta: Scalar, psi: Scalar) -> Vec3:
    """Third column of the ZYX rotation matrix R = Rz(psi) Ry(theta) Rx(phi)."""
    cphi, sphi = jnp.cos(phi), jnp.sin(phi)
    cth, sth = jnp.cos(theta), jnp.sin(theta)
    cpsi, spsi = jnp.cos(psi), jnp.sin(psi)
    return jnp.stack(
        [
            cphi * sth * cpsi + sphi * spsi,
            cphi * sth * spsi - sphi * cpsi,
            cphi * cth,
        ]
    )


def plant_derivative(
    params: QuadrotorParams,
    state: PlantState,
    u: Vec4,
    omega_d: Scalar,
    mass: Scalar,
    force: Vec3,
    torque: Vec3,
) -> PlantState:
    """Time derivative of the plant state (eq. 15, corrected).

    Args:
        params: true vehicle parameters (inertias, Jr, arm length, g).
        state: plant state, see `STATE_LAYOUT`.
        u: applied inputs (u1, u2, u3, u4): roll and pitch force differences [N], yaw torque
            [N m], total thrust [N], as produced by the (saturated) rotor speeds.
        omega_d: signed rotor-speed sum -Omega1 + Omega2 - Omega3 + Omega4 [rad/s] (eq. 17).
        mass: true mass [kg] (vehicle plus payload).
        force: external force in the earth frame [N].
        torque: external torque on the (phi, theta, psi) channels [N m].
    """
    phi, theta, psi = state[3], state[4], state[5]
    phid, thetad, psid = state[9], state[10], state[11]
    Ix, Iy, Iz, Jr, arm = params.Ix, params.Iy, params.Iz, params.Jr, params.arm_length

    acc_lin = thrust_direction(phi, theta, psi) * u[3] / mass + force / mass
    acc_lin = acc_lin.at[2].add(-params.g)
    gyro = params.gyro_sign * Jr * omega_d
    phidd = thetad * psid * (Iy - Iz) / Ix - gyro / Ix * thetad + (arm * u[0] + torque[0]) / Ix
    thetadd = phid * psid * (Iz - Ix) / Iy + gyro / Iy * phid + (arm * u[1] + torque[1]) / Iy
    psidd = phid * thetad * (Ix - Iy) / Iz + (u[2] + torque[2]) / Iz
    return jnp.concatenate([state[6:12], acc_lin, jnp.stack([phidd, thetadd, psidd])])


def feedback_linearize(params: QuadrotorParams, state: PlantState, v: Vec4) -> Vec4:
    """Inputs u = (u1, u2, u3, u4) that make (phidd, thetadd, psidd, zdd) = v on the model.

    Eq. (24) with the nominal model `params`. The gyroscopic Omega_d term is left out: the
    controller does not measure rotor speeds (and they depend on the u being computed).
    """
    phi, theta = state[3], state[4]
    phid, thetad, psid = state[9], state[10], state[11]
    Ix, Iy, Iz, arm = params.Ix, params.Iy, params.Iz, params.arm_length
    u1 = Ix / arm * (v[0] - thetad * psid * (Iy - Iz) / Ix)
    u2 = Iy / arm * (v[1] - phid * psid * (Iz - Ix) / Iy)
    u3 = Iz * (v[2] - phid * thetad * (Ix - Iy) / Iz)
    u4 = params.m * (params.g + v[3]) / (jnp.cos(phi) * jnp.cos(theta))
    return jnp.stack([u1, u2, u3, u4])


def hover_input(params: QuadrotorParams, mass: Scalar | None = None) -> Vec4:
    """Inputs (0, 0, 0, m g) that hold a level vehicle of `mass` [kg] (default m) still."""
    mass = params.m if mass is None else mass
    z = jnp.zeros_like(mass)
    return jnp.stack([z, z, z, mass * params.g])


def zero_state(dtype=None) -> Array:
    """A plant state at rest at the origin."""
    return jnp.zeros(STATE_SIZE, dtype=dtype or jnp.result_type(float))


def diverged_from(plant: PlantState, altitude_error, limits, *states) -> Array:
    """True past the divergence limits (``limits.attitude`` on |phi| and |theta| [rad],
    ``limits.altitude_error`` on |altitude_error| [m]) or when ``plant`` or any of ``states``
    (controller, rotor states) is not finite. Entries 2-4 of ``plant`` are z, phi, theta in
    both plant layouts."""
    att = jnp.maximum(jnp.abs(plant[3]), jnp.abs(plant[4]))
    finite = jnp.all(jnp.isfinite(plant))
    for x in states:
        finite = finite & jnp.all(jnp.isfinite(x))
    return (att > limits.attitude) | (jnp.abs(altitude_error) > limits.altitude_error) | ~finite
