"""Control allocation: eq. (16)/(18), its exact inverse, and rotor-speed saturation.

Inputs are ordered (u1, u2, u3, u4) = (roll force difference [N], pitch force difference [N],
yaw torque [N m], total thrust [N]); rotor quantities are ordered (1, 2, 3, 4) as in Fig. 2:

    u1 = b (W4 - W2),  u2 = b (W3 - W1),  u3 = d (W2 + W4 - W1 - W3),  u4 = b (W1 + W2 + W3 + W4)

with W_i = Omega_i^2 [rad^2/s^2]. (Eq. 18 prints these rows in the order u4, u1, u2, u3 and
eq. 19 divides u3 by b where it must be d; see docs/paper_notes.md.)
"""

from __future__ import annotations

import jax.numpy as jnp

from .._typing import Float, Scalar, Vec4
from ._params import QuadrotorParams


def allocation_matrix(params: QuadrotorParams) -> Float:
    """M such that u = M @ W, W = squared rotor speeds (eq. 16, rows ordered u1..u4)."""
    b, d = params.b, params.d
    z = jnp.zeros_like(b)
    return jnp.stack(
        [
            jnp.stack([z, -b, z, b]),
            jnp.stack([-b, z, b, z]),
            jnp.stack([-d, d, -d, d]),
            jnp.stack([b, b, b, b]),
        ]
    )


def inputs_from_rotor_speeds_sq(params: QuadrotorParams, w: Vec4) -> Vec4:
    """u from squared rotor speeds W [rad^2/s^2] (eq. 16)."""
    b, d = params.b, params.d
    return jnp.stack(
        [
            b * (w[3] - w[1]),
            b * (w[2] - w[0]),
            d * (w[1] + w[3] - w[0] - w[2]),
            b * (w[0] + w[1] + w[2] + w[3]),
        ]
    )


def rotor_speeds_sq_from_inputs(params: QuadrotorParams, u: Vec4) -> Vec4:
    """Exact inverse of eq. (16): squared rotor speeds W [rad^2/s^2] that produce u."""
    b, d = params.b, params.d
    t = u[3] / (4.0 * b)
    r = u[0] / (2.0 * b)
    p = u[1] / (2.0 * b)
    y = u[2] / (4.0 * d)
    return jnp.stack([t - p - y, t - r + y, t + p - y, t + r + y])


def saturate_rotor_speeds_sq(params: QuadrotorParams, w: Vec4) -> Vec4:
    """Clip squared rotor speeds to [omega_min^2, omega_max^2]."""
    return jnp.clip(w, params.omega_min**2, params.omega_max**2)


def safe_sqrt(w: Vec4) -> Vec4:
    """sqrt that is 0 (with zero gradient) for w <= 0, so a rotor stopped at 0 has no NaN."""
    positive = w > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, w, 1.0)), 0.0)


def omega_d(omega: Vec4) -> Scalar:
    """Signed rotor-speed sum -Omega1 + Omega2 - Omega3 + Omega4 [rad/s] (eq. 17)."""
    return -omega[0] + omega[1] - omega[2] + omega[3]


def mix(model: QuadrotorParams, vehicle: QuadrotorParams, u_cmd: Vec4) -> tuple[Vec4, Vec4]:
    """Commanded inputs -> (commanded W, saturated W): the mixer inverts eq. (16) with the
    controller's model coefficients (b, d), then the squared rotor speeds W [rad^2/s^2] are
    clipped to the vehicle's speed limits. The one mixer chain of every closed loop."""
    w_cmd = rotor_speeds_sq_from_inputs(model, u_cmd)
    return w_cmd, saturate_rotor_speeds_sq(vehicle, w_cmd)


def actuate(
    controller_model: QuadrotorParams, vehicle: QuadrotorParams, u_cmd: Vec4
) -> tuple[Vec4, Vec4]:
    """Commanded inputs -> (applied inputs, rotor speeds [rad/s]) with instantaneous rotors:
    `mix`, then the forces/torques the vehicle's true coefficients produce at the clipped
    speeds."""
    _, w = mix(controller_model, vehicle, u_cmd)
    return inputs_from_rotor_speeds_sq(vehicle, w), safe_sqrt(w)
