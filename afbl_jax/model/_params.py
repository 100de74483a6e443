"""Vehicle parameters (paper Table 1) and rotor-speed limits.

All fields are dynamic pytree leaves: a batch of vehicles is one `QuadrotorParams` whose
fields carry a leading batch axis, so `jax.vmap` and `jax.grad` see through it.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._typing import Array
from .._validation import as_float, check_finite, check_nonnegative, check_positive, concrete


class QuadrotorParams(eqx.Module):
    """Physical parameters of the quadrotor (SI units).

    Defaults are the paper's Table 1 (taken there from Bouabdallah 2007) with
    g = 9.81 m/s^2 and no rotor-speed limits.

    Attributes:
        m: vehicle mass [kg] (payload is a scenario setting, see `Scenario`).
        Ix, Iy, Iz: principal moments of inertia [kg m^2].
        b: thrust coefficient [N s^2] (thrust of rotor i = b * Omega_i^2).
        d: drag (yaw-torque) coefficient [N m s^2].
        Jr: rotor inertia [kg m^2].
        arm_length: distance from the centre of mass to each rotor, the paper's l [m].
        g: gravitational acceleration [m/s^2].
        omega_min: lowest rotor speed [rad/s], >= 0.
        omega_max: highest rotor speed [rad/s]; ``inf`` means unlimited.
        gyro_sign: +1 (default) applies the rotor gyroscopic torque with the signs of eq. (14)
            (rotors 1, 3 clockwise as the paper's text says); -1 flips it, which is the sign
            consistent with the yaw-torque convention of eq. (12)/(16) (the paper is not
            self-consistent here; see docs/paper_notes.md). Must be +1 or -1.
        drag_coefficient: linear aerodynamic drag c_d [N s/m], force c_d (wind - velocity);
            default 0 (no aerodynamic force; see `afbl_jax._wind`).
        cp_offset: centre of pressure above the centre of mass along body z [m], default 0
            (the drag force then has no torque).
    """

    m: Array = eqx.field(default=0.650, converter=as_float)
    Ix: Array = eqx.field(default=7.5e-3, converter=as_float)
    Iy: Array = eqx.field(default=7.5e-3, converter=as_float)
    Iz: Array = eqx.field(default=1.3e-2, converter=as_float)
    b: Array = eqx.field(default=3.13e-5, converter=as_float)
    d: Array = eqx.field(default=7.5e-7, converter=as_float)
    Jr: Array = eqx.field(default=6e-5, converter=as_float)
    arm_length: Array = eqx.field(default=0.23, converter=as_float)
    g: Array = eqx.field(default=9.81, converter=as_float)
    omega_min: Array = eqx.field(default=0.0, converter=as_float)
    omega_max: Array = eqx.field(default=float("inf"), converter=as_float)
    gyro_sign: Array = eqx.field(default=1.0, converter=as_float)
    drag_coefficient: Array = eqx.field(default=0.0, converter=as_float)
    cp_offset: Array = eqx.field(default=0.0, converter=as_float)

    def __check_init__(self):
        owner = type(self).__name__
        for name in ("m", "Ix", "Iy", "Iz", "b", "d", "arm_length", "g"):
            check_positive(owner, name, getattr(self, name))
        check_nonnegative(owner, "Jr", self.Jr)
        check_nonnegative(owner, "drag_coefficient", self.drag_coefficient)
        check_finite(owner, "cp_offset", self.cp_offset)
        check_nonnegative(owner, "omega_min", self.omega_min)
        check_positive(owner, "omega_max", self.omega_max, allow_inf=True)
        sign = concrete(self.gyro_sign)
        if sign is not None and not np.all(np.abs(sign) == 1.0):
            raise ValueError(f"{owner}.gyro_sign must be +1 or -1, got {sign}.")
        lo, hi = concrete(self.omega_min), concrete(self.omega_max)
        if lo is not None and hi is not None and not (lo < hi).all():
            raise ValueError(
                f"{owner}: omega_max ({hi}) must be greater than omega_min ({lo}) [rad/s]."
            )

    @property
    def hover_omega(self) -> Array:
        """Rotor speed [rad/s] at which the four rotors carry the vehicle mass m."""
        return jnp.sqrt(self.m * self.g / (4.0 * self.b))

    def with_thrust_to_weight(self, ratio: float, mass: float | Array | None = None):
        """Copy with ``omega_max`` set so that max total thrust = ratio * weight.

        ``mass`` [kg] defaults to the nominal mass ``m``.
        """
        check_positive("with_thrust_to_weight", "ratio", ratio)
        mass = self.m if mass is None else mass
        omega_max = jnp.sqrt(ratio * mass * self.g / (4.0 * self.b))
        return eqx.tree_at(lambda p: p.omega_max, self, as_float(omega_max))
