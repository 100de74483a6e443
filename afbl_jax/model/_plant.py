"""Plants: the paper's eq. (15) with the physically right details, and the full rigid body.

State layouts (documented here once; every other module refers to them)
------------------------------------------------------------------------
Both plants have a float state of shape ``(12,)``.

`PaperPlant` (``STATE_LAYOUT``)::

    index  0  1  2  3    4      5    6   7   8   9     10      11
    name   x  y  z  phi  theta  psi  xd  yd  zd  phid  thetad  psid

`RigidBodyPlant` (``FULL_STATE_LAYOUT``): the same except that entries 9-11 are the body rates
(p, q, r) [rad/s] instead of the Euler-angle rates.

x, y, z: position of the centre of mass in the earth frame [m], z up; phi, theta, psi: ZYX
Euler angles (roll, pitch, yaw) [rad]; xd, yd, zd: earth-frame velocity [m/s]. Scenario initial
states are always given in the paper layout; `AbstractPlant.from_paper_layout` converts them.
Controllers always receive a paper-layout state (`AbstractPlant.to_paper_layout`: an attitude
estimator giving etad = T(eta) omega).

The closed-loop ODE state (`afbl_jax.sim.ClosedLoopState`) is the plant state plus rotor
speeds (with motor lag), the controller's own states and the running cost integrals.

Controller channels are always ordered (phi, theta, psi, z); `CHANNEL_INDEX` picks them from a
paper-layout state and `CHANNEL_RATE_INDEX` picks their rates.

Differences from the printed eq. (15) (see docs/paper_notes.md):
- roll/pitch torques are l*u1, l*u2 (eq. 12 and 24 have the arm length; eq. 15/16 drop it);
- xdd, ydd use the third column of the ZYX rotation matrix (eq. 5 and 13 have typos);
- gyroscopic term with Omega_d = -Omega1 + Omega2 - Omega3 + Omega4 (eq. 17): phidd gets
  -(Jr/Ix) thetad Omega_d and thetadd +(Jr/Iy) phid Omega_d times ``QuadrotorParams.gyro_sign``:
  +1 is eq. (14) as printed (`afbl reproduce`), -1 (the default) the sign that matches the
  rotor spin directions implied by the yaw torque of eq. (16) (docs/paper_notes.md section 5);
- the yaw row's Euler coupling is phid*thetad*(Ix - Iy)/Iz (Euler's equation; eq. 15 prints
  thetad*psid).
"""

from __future__ import annotations

import abc
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._typing import Array, PlantState, Scalar, Vec3, Vec4
from ._params import QuadrotorParams
from ._rotations import (
    body_rates_from_euler_rates,
    cos_sin,
    euler_rates_from_body_rates,
    thrust_direction,
)

STATE_LAYOUT: tuple[str, ...] = (
    "x",
    "y",
    "z",
    "phi",
    "theta",
    "psi",
    "xd",
    "yd",
    "zd",
    "phid",
    "thetad",
    "psid",
)
"""Names of the 12 paper-plant state entries, in order (SI units, radians)."""
FULL_STATE_LAYOUT: tuple[str, ...] = (
    "x",
    "y",
    "z",
    "phi",
    "theta",
    "psi",
    "xd",
    "yd",
    "zd",
    "p",
    "q",
    "r",
)
"""Names of the 12 rigid-body plant state entries (body rates p, q, r at 9-11)."""
STATE_SIZE = len(STATE_LAYOUT)
CHANNELS: tuple[str, ...] = ("phi", "theta", "psi", "z")
"""Controlled channels, in the order used by gains, references and virtual inputs."""
CHANNEL_INDEX = np.array([3, 4, 5, 2])
CHANNEL_RATE_INDEX = np.array([9, 10, 11, 8])


def channel_values(state: PlantState) -> tuple[Vec4, Vec4]:
    """Return (q, qd): the controlled coordinates (phi, theta, psi, z) and their rates from a
    paper-layout state."""
    return state[..., CHANNEL_INDEX], state[..., CHANNEL_RATE_INDEX]


def _translation(params: QuadrotorParams, state, u, mass, force) -> Vec3:
    acc_lin = thrust_direction(state[3], state[4], state[5]) * u[3] / mass + force / mass
    return acc_lin.at[2].add(-params.g)


def plant_derivative(
    params: QuadrotorParams,
    state: PlantState,
    u: Vec4,
    omega_d: Scalar,
    mass: Scalar,
    force: Vec3,
    torque: Vec3,
) -> PlantState:
    """Time derivative of the paper-layout state (eq. 15, corrected).

    Args:
        params: true vehicle parameters (inertias, Jr, arm length, g).
        state: plant state, see `STATE_LAYOUT`.
        u: applied inputs (u1, u2, u3, u4): roll and pitch force differences [N], yaw torque
            [N m], total thrust [N], as produced by the rotor speeds.
        omega_d: signed rotor-speed sum -Omega1 + Omega2 - Omega3 + Omega4 [rad/s] (eq. 17).
        mass: true mass [kg] (vehicle plus payload).
        force: external force in the earth frame [N].
        torque: external torque on the (phi, theta, psi) channels [N m].
    """
    phid, thetad, psid = state[9], state[10], state[11]
    Ix, Iy, Iz, Jr, arm = params.Ix, params.Iy, params.Iz, params.Jr, params.arm_length
    acc_lin = _translation(params, state, u, mass, force)
    gyro = params.gyro_sign * Jr * omega_d
    phidd = thetad * psid * (Iy - Iz) / Ix - gyro / Ix * thetad + (arm * u[0] + torque[0]) / Ix
    thetadd = phid * psid * (Iz - Ix) / Iy + gyro / Iy * phid + (arm * u[1] + torque[1]) / Iy
    psidd = phid * thetad * (Ix - Iy) / Iz + (u[2] + torque[2]) / Iz
    return jnp.concatenate([state[6:12], acc_lin, jnp.stack([phidd, thetadd, psidd])])


def full_plant_derivative(
    params: QuadrotorParams,
    state: PlantState,
    u: Vec4,
    omega_d: Scalar,
    mass: Scalar,
    force: Vec3,
    torque: Vec3,
) -> PlantState:
    """Time derivative of the rigid-body state (`FULL_STATE_LAYOUT`).

    Translation eq. (8) with the full rotation matrix; attitude kinematics etad = T(eta) omega
    (eq. 6-7); Euler's equation I omegad = -omega x I omega - omega x (0, 0, Jr Omega_d) + tau
    (eq. 10-11; gyroscopic sign as in `plant_derivative`, times ``gyro_sign``), with body
    torque tau = (l u1, l u2, u3) + external torque (taken in the body frame). Same arguments
    as `plant_derivative`; its eq. (15) is the small-angle form of this.
    """
    p, q, r = state[9], state[10], state[11]
    Ix, Iy, Iz, Jr, arm = params.Ix, params.Iy, params.Iz, params.Jr, params.arm_length
    acc_lin = _translation(params, state, u, mass, force)
    gyro = params.gyro_sign * Jr * omega_d
    pd = ((Iy - Iz) * q * r - gyro * q + arm * u[0] + torque[0]) / Ix
    qd = ((Iz - Ix) * p * r + gyro * p + arm * u[1] + torque[1]) / Iy
    rd = ((Ix - Iy) * p * q + u[2] + torque[2]) / Iz
    etad = euler_rates_from_body_rates(state[3], state[4], state[9:12])
    return jnp.concatenate([state[6:9], etad, acc_lin, jnp.stack([pd, qd, rd])])


class AbstractPlant(eqx.Module):
    """A plant model: a state layout and its time derivative (a static choice: no fields)."""

    name: eqx.AbstractClassVar[str]
    layout: eqx.AbstractClassVar[tuple[str, ...]]

    @abc.abstractmethod
    def derivative(
        self,
        params: QuadrotorParams,
        state: PlantState,
        u: Vec4,
        omega_d: Scalar,
        mass: Scalar,
        force: Vec3,
        torque: Vec3,
    ) -> PlantState:
        """d state / dt (arguments as `plant_derivative`)."""

    @abc.abstractmethod
    def to_paper_layout(self, state: PlantState) -> PlantState:
        """The paper-layout (Euler-rate) view of a state of this plant."""

    @abc.abstractmethod
    def from_paper_layout(self, state: PlantState) -> PlantState:
        """Inverse of `to_paper_layout` (initial states are given in the paper layout)."""


class PaperPlant(AbstractPlant):
    """Eq. (15), corrected (`plant_derivative`; layout `STATE_LAYOUT`)."""

    name: ClassVar[str] = "paper"
    layout: ClassVar[tuple[str, ...]] = STATE_LAYOUT

    def derivative(self, params, state, u, omega_d, mass, force, torque):
        return plant_derivative(params, state, u, omega_d, mass, force, torque)

    def to_paper_layout(self, state):
        return state

    def from_paper_layout(self, state):
        return state


class RigidBodyPlant(AbstractPlant):
    """The full rigid body (`full_plant_derivative`; layout `FULL_STATE_LAYOUT`)."""

    name: ClassVar[str] = "full"
    layout: ClassVar[tuple[str, ...]] = FULL_STATE_LAYOUT

    def derivative(self, params, state, u, omega_d, mass, force, torque):
        return full_plant_derivative(params, state, u, omega_d, mass, force, torque)

    def to_paper_layout(self, state):
        etad = euler_rates_from_body_rates(state[3], state[4], state[9:12])
        return jnp.concatenate([state[:9], etad])

    def from_paper_layout(self, state):
        omega = body_rates_from_euler_rates(state[3], state[4], state[9:12])
        return jnp.concatenate([state[:9], omega])


PLANTS: dict[str, type[AbstractPlant]] = {
    PaperPlant.name: PaperPlant,
    RigidBodyPlant.name: RigidBodyPlant,
}
"""Plant models by name: "paper" (eq. 15) and "full" (rigid body)."""
PLANT_MODELS: tuple[str, ...] = tuple(PLANTS)


def make_plant(name: str) -> AbstractPlant:
    """Plant model by name (`PLANTS`)."""
    try:
        return PLANTS[name]()
    except KeyError:
        raise ValueError(f"unknown plant {name!r}; allowed: {', '.join(PLANTS)}.") from None


def feedback_linearize(params: QuadrotorParams, state: PlantState, v: Vec4) -> Vec4:
    """Inputs u = (u1, u2, u3, u4) that make (phidd, thetadd, psidd, zdd) = v on the model.

    Eq. (24) with the nominal model `params` and a paper-layout ``state``. The gyroscopic
    Omega_d term is left out: the controller does not measure rotor speeds (and they depend on
    the u being computed).
    """
    phi, theta = state[3], state[4]
    phid, thetad, psid = state[9], state[10], state[11]
    Ix, Iy, Iz, arm = params.Ix, params.Iy, params.Iz, params.arm_length
    u1 = Ix / arm * (v[0] - thetad * psid * (Iy - Iz) / Ix)
    u2 = Iy / arm * (v[1] - phid * psid * (Iz - Ix) / Iy)
    u3 = Iz * (v[2] - phid * thetad * (Ix - Iy) / Iz)
    u4 = params.m * (params.g + v[3]) / (cos_sin(phi)[0] * cos_sin(theta)[0])
    return jnp.stack([u1, u2, u3, u4])


def virtual_input_for(params: QuadrotorParams, state: PlantState, u: Vec4) -> Vec4:
    """Inverse of `feedback_linearize`: the v (phidd, thetadd, psidd, zdd targets) for which
    ``feedback_linearize(params, state, v)`` gives the inputs ``u`` on a paper-layout
    ``state``."""
    phi, theta = state[3], state[4]
    phid, thetad, psid = state[9], state[10], state[11]
    Ix, Iy, Iz, arm = params.Ix, params.Iy, params.Iz, params.arm_length
    v0 = arm * u[0] / Ix + thetad * psid * (Iy - Iz) / Ix
    v1 = arm * u[1] / Iy + phid * psid * (Iz - Ix) / Iy
    v2 = u[2] / Iz + phid * thetad * (Ix - Iy) / Iz
    v3 = u[3] * cos_sin(phi)[0] * cos_sin(theta)[0] / params.m - params.g
    return jnp.stack([v0, v1, v2, v3])


def hover_input(params: QuadrotorParams, mass: Scalar | None = None) -> Vec4:
    """Inputs (0, 0, 0, m g) that hold a level vehicle of `mass` [kg] (default m) still."""
    mass = params.m if mass is None else mass
    z = jnp.zeros_like(mass)
    return jnp.stack([z, z, z, mass * params.g])


def diverged_from(plant: PlantState, altitude_error, limits, *states) -> Array:
    """True past the divergence limits (``limits.attitude`` on |phi| and |theta| [rad],
    ``limits.altitude_error`` on |altitude_error| [m]) or when ``plant`` or any of ``states``
    (controller, rotor states) is not finite. Entries 3-4 of ``plant`` are phi, theta in both
    plant layouts. This is the one divergence test of every solve path."""
    att = jnp.maximum(jnp.abs(plant[3]), jnp.abs(plant[4]))
    finite = jnp.all(jnp.isfinite(plant))
    for x in states:
        if x is not None:
            finite = finite & jnp.all(jnp.isfinite(x))
    return (att > limits.attitude) | (jnp.abs(altitude_error) > limits.altitude_error) | ~finite
