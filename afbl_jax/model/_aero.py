"""Aerodynamics: the force and torque the air-relative motion puts on the vehicle.

`LinearDrag` (the default model): a linear drag force at the centre of pressure,

    F = c_d (w - v)    [N, earth frame],  w the wind velocity, v = (xd, yd, zd),

and its torque about the centre of mass, tau = r_cp x F_body with r_cp = (0, 0, h_cp) in the
body frame (centre of pressure h_cp above the centre of mass) and F_body = R^T F, R the ZYX
rotation matrix: tau = (-h_cp F_body_y, h_cp F_body_x, 0) [N m] on (phi, theta, psi). c_d is
``QuadrotorParams.drag_coefficient`` [N s/m] and h_cp ``QuadrotorParams.cp_offset`` [m]; both
default to 0, so without wind or drag nothing changes. The wind velocity comes from the
scenario (`afbl_jax.scenario.Wind`).
"""

from __future__ import annotations

import abc
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp

from .._typing import PlantState, Vec3, Vec4
from ._params import QuadrotorParams
from ._rotations import rotation_matrix


def aerodynamic_wrench(
    wind_velocity: Vec3, state: PlantState, drag_coefficient, cp_offset
) -> tuple[Vec3, Vec3]:
    """(force [N] earth frame, torque [N m] on phi, theta, psi) of the linear drag model.
    Plant velocities (entries 6-8) are earth-frame in every plant layout."""
    force = drag_coefficient * (wind_velocity - state[6:9])
    f_body = rotation_matrix(state[3], state[4], state[5]).T @ force
    zero = jnp.zeros_like(cp_offset)
    torque = jnp.stack([-cp_offset * f_body[1], cp_offset * f_body[0], zero])
    return force, torque


class AbstractAerodynamics(eqx.Module):
    """An aerodynamic model: (force, torque) from the wind and the vehicle's motion."""

    name: eqx.AbstractClassVar[str]

    @abc.abstractmethod
    def wrench(
        self, wind_velocity: Vec3, state: PlantState, vehicle: QuadrotorParams, rotor_speeds: Vec4
    ) -> tuple[Vec3, Vec3]:
        """(force [N] earth frame, torque [N m] on phi, theta, psi)."""


class LinearDrag(AbstractAerodynamics):
    """Isotropic linear drag at the centre of pressure (module docstring)."""

    name: ClassVar[str] = "linear"

    def wrench(self, wind_velocity, state, vehicle, rotor_speeds):
        del rotor_speeds
        return aerodynamic_wrench(wind_velocity, state, vehicle.drag_coefficient, vehicle.cp_offset)


AERODYNAMICS: dict[str, type[AbstractAerodynamics]] = {LinearDrag.name: LinearDrag}
"""Aerodynamic models by name."""
