"""Vehicle parameters (paper Table 1), rotor-speed limits and aerodynamic coefficients.

All fields are dynamic pytree leaves: a batch of vehicles is one `QuadrotorParams` whose
fields carry a leading batch axis, so `jax.vmap` and `jax.grad` see through it.

Rotor gyroscopic sign (see docs/paper_notes.md, section 5): `PHYSICAL_GYRO_SIGN` (-1, the
default) is the sign that matches the rotor spin directions implied by the yaw-torque
convention u3 = d (W2 + W4 - W1 - W3) of eq. (16); `EQ14_GYRO_SIGN` (+1) applies eq. (14) as
printed (the paper reproduction's faithful variant).

Rotor drag and parasitic drag defaults (used by `afbl_jax.model.RotorDrag` only) are the
identified coefficients of the AscTec Hummingbird (0.5 kg, 0.17 m arms, 0.10 m rotor radius) as
published with RotorPy (``rotorpy/vehicles/hummingbird_params.py``: k_d, k_z, c_Dx = c_Dy,
c_Dz), the closest published set for a vehicle of Table 1's size (0.65 kg, 0.23 m arms).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._typing import Array
from .._validation import as_float, check_finite, check_nonnegative, check_positive, concrete

PHYSICAL_GYRO_SIGN = -1.0
"""`QuadrotorParams.gyro_sign` consistent with the rotor spin directions of eq. (16) (default)."""
EQ14_GYRO_SIGN = 1.0
"""`QuadrotorParams.gyro_sign` of eq. (14) as printed (paper reproduction)."""


AERO_COEFFICIENTS: tuple[str, ...] = (
    "rotor_drag_horizontal",
    "rotor_drag_vertical",
    "parasitic_drag_horizontal",
    "parasitic_drag_vertical",
)
"""The `RotorDrag` coefficients of `QuadrotorParams` (each >= 0)."""


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
        gyro_sign: -1 (default, `PHYSICAL_GYRO_SIGN`) applies the rotor gyroscopic torque with
            the sign that matches the rotor spin directions implied by the yaw torque of eq. (16)
            (rotors 1, 3 counter-clockwise seen from above); +1 (`EQ14_GYRO_SIGN`) applies the
            signs of eq. (14) as printed (rotors 1, 3 clockwise as the paper's text says; the
            paper is not self-consistent here, see docs/paper_notes.md). Must be +1 or -1.
        drag_coefficient: linear aerodynamic drag c_d [N s/m] of `LinearDrag`, force
            c_d (wind - velocity); default 0 (no aerodynamic force).
        cp_offset: centre of pressure of the body drag above the centre of mass along body z
            [m], default 0 (the body drag then has no torque); used by both aerodynamic models.
        rotor_drag_horizontal: rotor (H-force) drag coefficient k_d [N / ((rad/s) (m/s))] of
            `RotorDrag` in the rotor plane: force -k_d Omega_i v_hub at each hub; default
            1.19e-4 (Hummingbird).
        rotor_drag_vertical: rotor drag (induced-inflow) coefficient k_z along the rotor axis
            [N / ((rad/s) (m/s))]; default 2.32e-4 (Hummingbird).
        parasitic_drag_horizontal: quadratic body drag c_D along body x and y [N / (m/s)^2],
            force -|v_a| c_D v_a; default 5e-3 (Hummingbird).
        parasitic_drag_vertical: quadratic body drag along body z [N / (m/s)^2]; default 1e-2
            (Hummingbird).
        hub_height: height of the rotor hubs above the centre of mass along body z [m]; the
            rotor drag acts at the hubs (body positions (l, 0, h), (0, -l, h), (-l, 0, h),
            (0, l, h) for rotors 1-4, see docs/paper_notes.md section 6); default 0.
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
    gyro_sign: Array = eqx.field(default=PHYSICAL_GYRO_SIGN, converter=as_float)
    drag_coefficient: Array = eqx.field(default=0.0, converter=as_float)
    cp_offset: Array = eqx.field(default=0.0, converter=as_float)
    rotor_drag_horizontal: Array = eqx.field(default=1.19e-4, converter=as_float)
    rotor_drag_vertical: Array = eqx.field(default=2.32e-4, converter=as_float)
    parasitic_drag_horizontal: Array = eqx.field(default=5e-3, converter=as_float)
    parasitic_drag_vertical: Array = eqx.field(default=1e-2, converter=as_float)
    hub_height: Array = eqx.field(default=0.0, converter=as_float)

    def __check_init__(self):
        owner = type(self).__name__
        for name in ("m", "Ix", "Iy", "Iz", "b", "d", "arm_length", "g"):
            check_positive(owner, name, getattr(self, name))
        check_nonnegative(owner, "Jr", self.Jr)
        check_nonnegative(owner, "drag_coefficient", self.drag_coefficient)
        check_finite(owner, "cp_offset", self.cp_offset)
        check_finite(owner, "hub_height", self.hub_height)
        for name in AERO_COEFFICIENTS:
            check_nonnegative(owner, name, getattr(self, name))
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

    def rotor_positions(self) -> Array:
        """Rotor hub positions relative to the centre of mass, body frame (FLU), shape (4, 3)
        [m]: rotors 1-4 at (l, 0, h), (0, -l, h), (-l, 0, h), (0, l, h) with l the arm length
        and h ``hub_height`` (the layout eq. 16 implies, docs/paper_notes.md section 6)."""
        arm, h = self.arm_length, self.hub_height
        z = jnp.zeros_like(arm * h)
        return jnp.stack(
            [
                jnp.stack([arm + z, z, h + z], axis=-1),
                jnp.stack([z, -arm + z, h + z], axis=-1),
                jnp.stack([-arm + z, z, h + z], axis=-1),
                jnp.stack([z, arm + z, h + z], axis=-1),
            ],
            axis=-2,
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
