"""External disturbances: rectangular pulses of torque and force (the paper's Figs. 14-15).

A `PulseDisturbance` holds P pulses; pulse k is on for start_k <= t < start_k + duration_k and
adds ``torque[k]`` [N m] on the (phi, theta, psi) channels and ``force[k]`` [N] in the earth
frame (x, y, z; the paper's altitude pulse is a z force). A disturbance with zero amplitudes is
"no disturbance" with the same structure, so ideal and disturbed cases stack into one batch.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._typing import Array, Float, Vec3
from .._validation import as_float, check_finite, check_nonnegative


class PulseDisturbance(eqx.Module):
    """Rectangular torque/force pulses.

    Attributes:
        start: pulse start times, shape (P,) [s].
        duration: pulse durations, shape (P,) [s], >= 0.
        torque: torque on (phi, theta, psi), shape (P, 3) [N m].
        force: force in the earth frame (x, y, z), shape (P, 3) [N].
    """

    start: Float[Array, " P"] = eqx.field(converter=as_float)
    duration: Float[Array, " P"] = eqx.field(converter=as_float)
    torque: Float[Array, "P 3"] = eqx.field(converter=as_float)
    force: Float[Array, "P 3"] = eqx.field(converter=as_float)

    def __check_init__(self):
        owner = type(self).__name__
        p = np.shape(self.start)
        if (
            np.shape(self.duration) != p
            or np.shape(self.torque) != (*p, 3)
            or np.shape(self.force) != (*p, 3)
        ):
            raise ValueError(
                f"{owner}: expected start (P,), duration (P,), torque (P, 3), force (P, 3); got "
                f"{np.shape(self.start)}, {np.shape(self.duration)}, {np.shape(self.torque)}, "
                f"{np.shape(self.force)}."
            )
        for name in ("start", "torque", "force"):
            check_finite(owner, name, getattr(self, name))
        check_nonnegative(owner, "duration", self.duration)

    def _active(self, t) -> Array:
        return ((t >= self.start) & (t < self.start + self.duration)).astype(self.torque.dtype)

    def __call__(self, t) -> tuple[Vec3, Vec3]:
        """(force [N] in the earth frame, torque [N m] on phi, theta, psi) at time t [s]."""
        on = self._active(t)[..., None]
        return jnp.sum(on * self.force, axis=-2), jnp.sum(on * self.torque, axis=-2)

    def jump_times(self) -> Array:
        """Every pulse edge [s]: the disturbance is discontinuous there."""
        return jnp.concatenate([self.start, self.start + self.duration], axis=-1)


def no_disturbance(n_pulses: int = 1) -> PulseDisturbance:
    """A disturbance of ``n_pulses`` zero-amplitude pulses (placed at t = 0, zero length)."""
    z = np.zeros(n_pulses)
    return PulseDisturbance(z, z, np.zeros((n_pulses, 3)), np.zeros((n_pulses, 3)))
