"""The controller interface shared by FBL+PID and AFBL.

A controller is an `equinox.Module` whose gains are dynamic arrays of shape (4,), channel order
(phi, theta, psi, z). It is a pure function of (time, plant state, controller state, reference,
nominal model) returning the commanded inputs u = (u1, u2, u3, u4) and the time derivative of its
own state; that state (PID integrators, adaptive estimates) is part of the closed-loop ODE state.
"""

from __future__ import annotations

import abc
from typing import NamedTuple

import equinox as eqx
import jax.numpy as jnp

from ..._typing import Array, PlantState, Vec4
from ..._validation import as_float, check_last_dim, check_positive
from .._params import QuadrotorParams
from .._plant import channel_values, feedback_linearize


class ReferenceSample(NamedTuple):
    """Reference value, rate and acceleration at one instant, each shaped (4,), channel order
    (phi, theta, psi, z) [rad or m, per s, per s^2]."""

    r: Vec4
    rd: Vec4
    rdd: Vec4


def as_gain(x) -> Array:
    """Gains as float arrays; a scalar is broadcast to all four channels."""
    return as_float(x, broadcast=4)


class AbstractController(eqx.Module):
    """Feedback-linearizing controller: u = inversion(nominal model, v(errors, state))."""

    name: eqx.AbstractClassVar[str]
    gain_names: eqx.AbstractClassVar[tuple[str, ...]]

    def __check_init__(self):
        owner = type(self).__name__
        for g in self.gain_names:
            check_last_dim(owner, g, getattr(self, g), 4)
            check_positive(owner, g, getattr(self, g))

    def init_state(self) -> Vec4:
        """Controller state at t0 (zeros): one entry per channel (phi, theta, psi, z)."""
        return jnp.zeros(4, dtype=getattr(self, self.gain_names[0]).dtype)

    @abc.abstractmethod
    def state_for(self, v: Vec4, ref: ReferenceSample) -> Vec4:
        """The controller state for which the virtual input at zero tracking error (e = ed =
        0) with reference ``ref`` is ``v`` (a trimmed start: the controller already holds
        the equilibrium's inputs)."""

    @abc.abstractmethod
    def virtual_input(
        self, e: Vec4, ed: Vec4, ref: ReferenceSample, state: Vec4
    ) -> tuple[Vec4, Vec4]:
        """(v, d state/dt) from position errors e = r - q, rate errors ed = rd - qd."""

    def __call__(
        self,
        t,
        plant_state: PlantState,
        state: Vec4,
        ref: ReferenceSample,
        model: QuadrotorParams,
    ) -> tuple[Vec4, Vec4]:
        """Commanded inputs u (u1, u2, u3, u4) and the controller-state derivative at time t."""
        del t
        q, qd = channel_values(plant_state)
        v, dstate = self.virtual_input(ref.r - q, ref.rd - qd, ref, state)
        return feedback_linearize(model, plant_state, v), dstate
