"""Position hold: the outer loop of a cascaded multirotor controller.

Real multirotors hold position: an outer loop on the horizontal position turns the position
error into a commanded horizontal acceleration, and that into the roll and pitch the inner
attitude loops (FBL+PID or AFBL, unchanged) track. Yaw and altitude keep their references.

Outer-loop law (earth frame, x and y; e_p = p_ref - p [m], e_v = v_ref - v [m/s], I the
integral state [m s])::

    a_cmd = a_ref + kp e_p + kd e_v + ki I                          [m/s^2]
    a_sat = a_cmd min(1, a_max / |a_cmd|),   a_max = g tan(tilt_max)  (tilt limit)
    dI/dt = e_p + (a_sat - a_cmd) / (ki T_w)                          (back-calculation
                                                                      anti-windup, T_w [s])

The attitude that points the thrust along (a_sat, g): with psi the measured yaw and
(b_x, b_y) = Rz(psi)^T a_sat the acceleration in the yaw frame,

    theta_cmd = atan2(b_x, g),   phi_cmd = atan2(-b_y, sqrt(b_x^2 + g^2))

(the third column of R = Rz Ry Rx is (cphi stheta, -sphi, cphi ctheta) in the yaw frame); the
tilt acos(cos phi cos theta) equals atan(|a_sat| / g) <= tilt_max. The inner loops need the
reference's first and second derivatives, so the command passes through a critically damped
second-order command filter of natural frequency w_f [rad/s] whose states are the attitude
reference (r, rd) and whose acceleration is its rdd::

    rdd = w_f^2 (cmd - r) - 2 w_f rd

Outer-loop state (`POSITION_LOOP_LAYOUT`, shape (6,)): (I_x, I_y [m s], phi_r, theta_r [rad],
phid_r, thetad_r [rad/s]). It follows the inner controller's own state in the closed loop's
controller state (`afbl_jax.sim.ClosedLoopState`), so digital control samples and holds both.

Default gains place the outer loop's three poles at s = -w_p (kd = 3 w_p, kp = 3 w_p^2,
ki = w_p^3) with w_p = `DEFAULT_POSITION_BANDWIDTH`, well below the inner attitude loops
(about 4-6 rad/s with the paper's gains) and the command filter (`DEFAULT_FILTER_FREQUENCY`).
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._typing import Array, Float, PlantState, Scalar
from .._validation import as_float, check_positive, concrete
from ._params import QuadrotorParams
from ._rotations import cos_sin

POSITION_LOOP_LAYOUT: tuple[str, ...] = (
    "integral_x",
    "integral_y",
    "phi_reference",
    "theta_reference",
    "phid_reference",
    "thetad_reference",
)
"""Names of the outer loop's 6 state entries, in order (m s, m s, rad, rad, rad/s, rad/s)."""
POSITION_LOOP_SIZE = len(POSITION_LOOP_LAYOUT)
DEFAULT_POSITION_BANDWIDTH = 0.8
"""w_p [rad/s]: the outer loop's triple pole of the default gains."""
DEFAULT_TILT_LIMIT = 0.7
"""Default tilt limit of the position loop's command [rad] (about 40 degrees)."""
DEFAULT_FILTER_FREQUENCY = 10.0
"""Default natural frequency of the attitude command filter [rad/s]."""


class PositionSample(NamedTuple):
    """Horizontal position reference at one instant: (x, y) [m], rates [m/s] and
    accelerations [m/s^2], each shaped (2,)."""

    r: Float[Array, 2]
    rd: Float[Array, 2]
    rdd: Float[Array, 2]


class AttitudeCommand(NamedTuple):
    """The position loop's attitude reference for the inner loops: (phi, theta) [rad], rates
    [rad/s] and accelerations [rad/s^2], each shaped (2,)."""

    r: Float[Array, 2]
    rd: Float[Array, 2]
    rdd: Float[Array, 2]


def _as_pair(x) -> Array:
    return as_float(x, broadcast=2)


def attitude_for_acceleration(acceleration, psi, g) -> Array:
    """(phi, theta) [rad] whose thrust direction gives the horizontal acceleration
    ``acceleration`` (x, y) [m/s^2] against gravity ``g`` [m/s^2] at yaw ``psi`` [rad]
    (module docstring)."""
    c, s = cos_sin(psi)
    bx = c * acceleration[..., 0] + s * acceleration[..., 1]
    by = -s * acceleration[..., 0] + c * acceleration[..., 1]
    theta = jnp.arctan2(bx, g)
    phi = jnp.arctan2(-by, jnp.sqrt(bx**2 + g**2))
    return jnp.stack([phi, theta], axis=-1)


def acceleration_for_attitude(attitude, psi, g) -> Array:
    """Inverse of `attitude_for_acceleration`: the horizontal acceleration (x, y) [m/s^2]
    the thrust of a vehicle at (phi, theta) = ``attitude`` [rad] and yaw ``psi`` gives when
    its vertical part carries gravity ``g``."""
    phi, theta = attitude[..., 0], attitude[..., 1]
    bx = g * jnp.tan(theta)
    by = -jnp.tan(phi) * jnp.sqrt(bx**2 + g**2)
    c, s = jnp.cos(psi), jnp.sin(psi)
    return jnp.stack([c * bx - s * by, s * bx + c * by], axis=-1)


class PositionHold(eqx.Module):
    """Cascaded position loop around the inner attitude loops (module docstring).

    All fields are dynamic leaves (vmap/grad over them).

    Attributes:
        kp: position gains [1/s^2], shape (2,) (x, y).
        kd: velocity gains [1/s], shape (2,).
        ki: integral gains [1/s^3], shape (2,).
        tilt_max: tilt limit of the command [rad], in (0, pi/2).
        filter_frequency: natural frequency w_f of the critically damped attitude command
            filter [rad/s].
        windup_time: back-calculation time constant T_w of the anti-windup [s].
    """

    kp: Array = eqx.field(default=3.0 * DEFAULT_POSITION_BANDWIDTH**2, converter=_as_pair)
    kd: Array = eqx.field(default=3.0 * DEFAULT_POSITION_BANDWIDTH, converter=_as_pair)
    ki: Array = eqx.field(default=DEFAULT_POSITION_BANDWIDTH**3, converter=_as_pair)
    tilt_max: Scalar = eqx.field(default=DEFAULT_TILT_LIMIT, converter=as_float)
    filter_frequency: Scalar = eqx.field(default=DEFAULT_FILTER_FREQUENCY, converter=as_float)
    windup_time: Scalar = eqx.field(default=1.0, converter=as_float)

    def __check_init__(self):
        owner = type(self).__name__
        for name in ("kp", "kd", "ki"):
            if np.shape(getattr(self, name))[-1:] != (2,):
                raise ValueError(
                    f"{owner}.{name} must have a last dimension of 2 (x, y), got shape "
                    f"{np.shape(getattr(self, name))}."
                )
            check_positive(owner, name, getattr(self, name))
        check_positive(owner, "filter_frequency", self.filter_frequency)
        check_positive(owner, "windup_time", self.windup_time)
        tilt = concrete(self.tilt_max)
        if tilt is not None and not np.all((tilt > 0) & (tilt < np.pi / 2)):
            raise ValueError(f"{owner}.tilt_max must lie in (0, pi/2) [rad], got {tilt!r}.")

    def acceleration_limit(self, g) -> Scalar:
        """a_max = g tan(tilt_max) [m/s^2]."""
        return g * jnp.tan(self.tilt_max)

    def acceleration_command(
        self, state: Float[Array, 6], measured: PlantState, position: PositionSample
    ) -> Array:
        """a_cmd [m/s^2], shape (2,): the commanded horizontal acceleration before the tilt
        limit, from a paper-layout ``measured`` state."""
        e_p = position.r - measured[0:2]
        e_v = position.rd - measured[6:8]
        return position.rdd + self.kp * e_p + self.kd * e_v + self.ki * state[0:2]

    def __call__(
        self,
        measured: PlantState,
        state: Float[Array, 6],
        position: PositionSample,
        model: QuadrotorParams,
    ) -> tuple[AttitudeCommand, Float[Array, 6]]:
        """The attitude reference for the inner loops and d(state)/dt, from a paper-layout
        ``measured`` state, the outer-loop ``state`` and the position reference; the
        controller's nominal ``model`` gives g."""
        g = model.g
        a_cmd = self.acceleration_command(state, measured, position)
        a_max = self.acceleration_limit(g)
        n2 = jnp.sum(a_cmd**2, axis=-1)
        over = n2 > a_max**2  # scaled onto the limit: a_max / |a_cmd| (one rsqrt)
        scale = jnp.where(over, a_max * jax.lax.rsqrt(jnp.where(over, n2, 1.0)), 1.0)
        a_sat = a_cmd * scale
        cmd = attitude_for_acceleration(a_sat, measured[5], g)
        wf = self.filter_frequency
        r, rd = state[2:4], state[4:6]
        rdd = wf**2 * (cmd - r) - 2.0 * wf * rd
        e_p = position.r - measured[0:2]
        dintegral = e_p + (a_sat - a_cmd) / (self.ki * self.windup_time)
        return AttitudeCommand(r, rd, rdd), jnp.concatenate([dintegral, rd, rdd])

    def init_state(self, attitude, psi, model: QuadrotorParams) -> Float[Array, 6]:
        """The state in which the loop commands ``attitude`` = (phi, theta) [rad] at zero
        position and velocity error (and zero reference acceleration) at yaw ``psi``: the
        filter at rest at that attitude, the integral holding the acceleration it gives."""
        attitude = jnp.asarray(attitude, dtype=self.kp.dtype)
        integral = acceleration_for_attitude(attitude, psi, model.g) / self.ki
        return jnp.concatenate([integral, attitude, jnp.zeros_like(attitude)])
