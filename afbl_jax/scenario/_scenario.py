"""Scenarios: what the vehicle is asked to do and what happens to it.

A `Scenario` is data: reference, disturbances, payload, wind, initial state and time span.
Scenarios of one structure stack into one batch (`stack_scenarios`) and run under one
`jax.vmap` or one batched solve.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._typing import Array, Float, Scalar
from .._validation import as_float, check_finite, check_last_dim, concrete
from ..model import STATE_SIZE, PositionSample, Trim
from ._disturbances import PulseDisturbance
from ._references import PositionReference, Reference
from ._wind import Wind, no_wind


class Scenario(eqx.Module):
    """One simulation case.

    Attributes:
        reference: desired (phi, theta, psi, z) with derivatives.
        disturbance: external force/torque pulses.
        payload_fraction: payload as a fraction p of the vehicle mass; the true mass is
            m (1 + p) from ``payload_time`` on (p > -1).
        payload_time: time the payload is attached [s] (<= t0 means the whole run).
        initial_state: plant state at t0, shape (12,), paper layout (`afbl_jax.model.STATE_LAYOUT`).
        t0, t1: time span [s].
        wind: wind velocity field acting through the vehicle's aerodynamic model (default calm
            air with no gusts and no turbulence; see `afbl_jax.scenario.Wind`).
        position: horizontal position reference (x, y) of a loop with a position loop
            (`afbl_jax.model.PositionHold`); None: hold the initial position. Loops without a
            position loop ignore it (their roll and pitch follow ``reference``).
        trim: the equilibrium the case starts in (`afbl_jax.model.Trim`, e.g. from
            `trim_scenario`): the controllers' states at t0 are set so that they command its
            inputs at zero error (and a position loop its attitude). None: zero controller
            states (the paper's start).
    """

    reference: Reference
    disturbance: PulseDisturbance
    payload_fraction: Scalar = eqx.field(default=0.0, converter=as_float)
    payload_time: Scalar = eqx.field(default=0.0, converter=as_float)
    initial_state: Float[Array, 12] = eqx.field(
        default_factory=lambda: np.zeros(STATE_SIZE), converter=as_float
    )
    t0: Scalar = eqx.field(default=0.0, converter=as_float)
    t1: Scalar = eqx.field(default=20.0, converter=as_float)
    wind: Wind = eqx.field(default_factory=no_wind)
    position: PositionReference | None = None
    trim: Trim | None = None

    def __check_init__(self):
        owner = type(self).__name__
        check_last_dim(owner, "initial_state", self.initial_state, STATE_SIZE)
        for name in ("initial_state", "payload_time", "t0", "t1", "payload_fraction"):
            check_finite(owner, name, getattr(self, name))
        p = concrete(self.payload_fraction)
        if p is not None and not np.all(p > -1.0):
            raise ValueError(f"{owner}.payload_fraction must be > -1 (true mass > 0), got {p}.")
        t0, t1 = concrete(self.t0), concrete(self.t1)
        if t0 is not None and t1 is not None and not np.all(t1 > t0):
            raise ValueError(f"{owner}: t1 ({t1}) must be greater than t0 ({t0}) [s].")

    def mass_factor(self, t) -> Scalar:
        """True mass / vehicle mass at time t [s]."""
        return 1.0 + jnp.where(t >= self.payload_time, self.payload_fraction, 0.0)

    def position_at(self, t) -> PositionSample:
        """The position reference (x, y) at time t [s]: ``position``, or the initial position
        held (zero rate and acceleration) when it is None."""
        if self.position is None:
            r = self.initial_state[..., 0:2]
            return PositionSample(r, jnp.zeros_like(r), jnp.zeros_like(r))
        return self.position(t)

    def jump_times(self) -> Array:
        """Times [s] where the closed-loop vector field is discontinuous or has a kink."""
        parts = [
            self.disturbance.jump_times(),
            self.reference.kink_times(),
            jnp.atleast_1d(self.payload_time),
            self.wind.jump_times(),
        ]
        if self.position is not None:
            parts.append(self.position.kink_times())
        return jnp.concatenate(parts)


def stack_scenarios(scenarios: list[Scenario]) -> Scenario:
    """Stack same-structure scenarios along a new leading axis (for `jax.vmap`)."""
    if not scenarios:
        raise ValueError("stack_scenarios needs at least one scenario.")
    return jax.tree.map(lambda *xs: jnp.stack(xs), *scenarios)
