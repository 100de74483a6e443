"""Aerodynamics: the force and torque the air-relative motion puts on the vehicle.

Every model receives the wind velocity w (earth frame) [m/s], the plant state in the paper
layout (`afbl_jax.model.STATE_LAYOUT`: Euler angles, earth-frame velocity v = (xd, yd, zd),
Euler-angle rates), the true vehicle (`QuadrotorParams`, where every coefficient lives as a
dynamic leaf) and the applied rotor speeds Omega_i [rad/s], and returns (force [N] in the earth
frame, torque [N m] about the body axes, added to the (phi, theta, psi) channels). The choice of
model is static (`afbl_jax.sim.ClosedLoop.aerodynamics`; ``aerodynamics=`` of `simulate` and
`simulate_batch`); its coefficients are dynamic (vmap/grad over them).

`LinearDrag` (name ``"linear"``, the default of `simulate`): a linear drag force at the centre of
pressure,

    F = c_d (w - v)    [N, earth frame],

with torque r_cp x F_body about the centre of mass, r_cp = (0, 0, h_cp) in the body frame and
F_body = R^T F, R the ZYX rotation matrix: tau = (-h_cp F_body_y, h_cp F_body_x, 0) [N m].
c_d is ``QuadrotorParams.drag_coefficient`` [N s/m] and h_cp ``QuadrotorParams.cp_offset``
[m]; both default to 0, so without wind or drag nothing changes.

`RotorDrag` (name ``"rotor_drag"``): rotor (H-force) drag at each hub plus quadratic parasitic
drag at the centre of pressure, the model of RotorPy's ``Multirotor`` (aero on, translational
lift and flapping off). In the body frame, with v_a = R^T (v - w) the vehicle's velocity
relative to the air, omega the body rates and r_i the hub positions
(`QuadrotorParams.rotor_positions`)::

    v_i = v_a + omega x r_i                                  (air-relative velocity at hub i)
    H_i = -Omega_i diag(k_d, k_d, k_z) v_i                   (rotor drag of rotor i) [N]
    D   = -|v_a| diag(c_Dxy, c_Dxy, c_Dz) v_a                (parasitic drag) [N]
    F_body = sum_i H_i + D,    tau = sum_i r_i x H_i + r_cp x D

k_d, k_z: ``rotor_drag_horizontal``, ``rotor_drag_vertical``; c_Dxy, c_Dz:
``parasitic_drag_horizontal``, ``parasitic_drag_vertical``; r_cp = (0, 0, ``cp_offset``).
The rotor drag is proportional to rotor speed, acts at the hubs (so with ``hub_height`` > 0 a
horizontal airspeed pitches the vehicle, and rolling/pitching moves the hubs vertically through
the air, which damps the rates through k_z) and differs between the rotor plane and its axis.
"""

from __future__ import annotations

import abc
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp

from .._typing import PlantState, Vec3, Vec4
from ._params import QuadrotorParams
from ._rotations import body_rates_from_euler_rates, rotate, rotate_transposed, rotation_matrix


def aerodynamic_wrench(
    wind_velocity: Vec3, state: PlantState, drag_coefficient, cp_offset
) -> tuple[Vec3, Vec3]:
    """(force [N] earth frame, torque [N m] body axes) of the linear drag model.
    Plant velocities (entries 6-8) are earth-frame in every plant layout."""
    force = drag_coefficient * (wind_velocity - state[6:9])
    f_body = rotate_transposed(rotation_matrix(state[3], state[4], state[5]), force)
    zero = jnp.zeros_like(cp_offset)
    torque = jnp.stack([-cp_offset * f_body[1], cp_offset * f_body[0], zero])
    return force, torque


def _safe_norm(v) -> jnp.ndarray:
    """|v| with a zero (not NaN) gradient at v = 0."""
    n2 = jnp.sum(v**2, axis=-1)
    positive = n2 > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, n2, 1.0)), 0.0)


def rotor_drag_wrench(
    wind_velocity: Vec3, state: PlantState, vehicle: QuadrotorParams, rotor_speeds: Vec4
) -> tuple[Vec3, Vec3]:
    """(force [N] earth frame, torque [N m] body axes) of the rotor-drag + parasitic-drag
    model (module docstring) on a paper-layout ``state``."""
    phi, theta, psi = state[3], state[4], state[5]
    rot = rotation_matrix(phi, theta, psi)
    omega = body_rates_from_euler_rates(phi, theta, state[9:12])
    v_air = rotate_transposed(rot, state[6:9] - wind_velocity)
    hubs = vehicle.rotor_positions()
    v_hub = v_air + jnp.cross(omega, hubs)
    k_d, k_z = vehicle.rotor_drag_horizontal, vehicle.rotor_drag_vertical
    rotor_k = jnp.stack([k_d, k_d, k_z])
    h_force = -rotor_speeds[:, None] * rotor_k * v_hub
    c_xy, c_z = vehicle.parasitic_drag_horizontal, vehicle.parasitic_drag_vertical
    parasitic = -_safe_norm(v_air) * jnp.stack([c_xy, c_xy, c_z]) * v_air
    f_body = jnp.sum(h_force, axis=0) + parasitic
    zero = jnp.zeros_like(vehicle.cp_offset)
    r_cp = jnp.stack([zero, zero, vehicle.cp_offset])
    torque = jnp.sum(jnp.cross(hubs, h_force), axis=0) + jnp.cross(r_cp, parasitic)
    return rotate(rot, f_body), torque


class AbstractAerodynamics(eqx.Module):
    """An aerodynamic model: (force, torque) from the wind and the vehicle's motion."""

    name: eqx.AbstractClassVar[str]

    @abc.abstractmethod
    def wrench(
        self, wind_velocity: Vec3, state: PlantState, vehicle: QuadrotorParams, rotor_speeds: Vec4
    ) -> tuple[Vec3, Vec3]:
        """(force [N] earth frame, torque [N m] about the body axes) for the wind velocity
        [m/s] (earth frame), a paper-layout plant ``state`` and the applied rotor speeds
        [rad/s]."""


class LinearDrag(AbstractAerodynamics):
    """Isotropic linear drag at the centre of pressure (module docstring)."""

    name: ClassVar[str] = "linear"

    def wrench(self, wind_velocity, state, vehicle, rotor_speeds):
        del rotor_speeds
        return aerodynamic_wrench(wind_velocity, state, vehicle.drag_coefficient, vehicle.cp_offset)


class RotorDrag(AbstractAerodynamics):
    """Rotor (H-force) drag at the hubs plus quadratic parasitic drag (module docstring)."""

    name: ClassVar[str] = "rotor_drag"

    def wrench(self, wind_velocity, state, vehicle, rotor_speeds):
        return rotor_drag_wrench(wind_velocity, state, vehicle, rotor_speeds)


AERODYNAMICS: dict[str, type[AbstractAerodynamics]] = {
    LinearDrag.name: LinearDrag,
    RotorDrag.name: RotorDrag,
}
"""Aerodynamic models by name: "linear" (`LinearDrag`) and "rotor_drag" (`RotorDrag`)."""
AERODYNAMIC_MODELS: tuple[str, ...] = tuple(AERODYNAMICS)


def make_aerodynamics(
    model: str | AbstractAerodynamics | None = None,
) -> AbstractAerodynamics:
    """The aerodynamic model of a name (`AERODYNAMICS`), an instance (returned as is) or None
    (`LinearDrag`)."""
    if model is None:
        return LinearDrag()
    if isinstance(model, AbstractAerodynamics):
        return model
    try:
        return AERODYNAMICS[model]()
    except (KeyError, TypeError):
        raise ValueError(
            f"unknown aerodynamic model {model!r}; allowed: {', '.join(AERODYNAMICS)}."
        ) from None
