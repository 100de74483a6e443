"""Actuators: how the commanded rotor speeds become the applied ones.

- `InstantRotors`: the rotors reach the (saturated) commanded speed at once; no ODE state.
- `FirstOrderRotors`: first-order motor lag, dOmega_i/dt = (Omega_cmd,i - Omega_i) / tau_m, with
  the rotor speeds Omega_1..4 [rad/s] as ODE states (``ClosedLoopState.rotors``). ``tau_m`` is a
  dynamic leaf (vmap/grad over it); tau_m = 0 means instantaneous rotors (the rotor states are
  then carried but unused), so a batch may mix both. The rotors start at the first command, so
  the lag adds no start-up transient.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._typing import Array, Scalar, Vec4
from .._validation import as_float, check_nonnegative, concrete


class AbstractActuators(eqx.Module):
    """Rotor dynamics between the mixer's saturated command and the applied speeds."""

    @abc.abstractmethod
    def init_state(self, omega_command: Vec4) -> Vec4 | None:
        """ODE state at t0 given the first saturated command [rad/s] (None: no state)."""

    @abc.abstractmethod
    def applied(
        self, state: Vec4 | None, omega_command: Vec4, w_command: Vec4
    ) -> tuple[Vec4, Vec4]:
        """(applied squared speeds W [rad^2/s^2], applied speeds Omega [rad/s]) from the ODE
        state and the saturated command (speeds and their squares)."""

    @abc.abstractmethod
    def derivative(self, state: Vec4 | None, omega_command: Vec4) -> Vec4 | None:
        """d state / dt (None: no state)."""


class InstantRotors(AbstractActuators):
    """Rotors at the commanded speed instantly (the paper's model)."""

    def init_state(self, omega_command):
        return None

    def applied(self, state, omega_command, w_command):
        return w_command, omega_command

    def derivative(self, state, omega_command):
        return None


class FirstOrderRotors(AbstractActuators):
    """First-order motor lag with time constant ``tau_m`` [s] (0 = instantaneous)."""

    tau_m: Scalar = eqx.field(default=0.03, converter=as_float)

    def __check_init__(self):
        check_nonnegative(type(self).__name__, "tau_m", self.tau_m)
        tau = concrete(self.tau_m)
        if tau is not None and not np.all(np.isfinite(tau)):
            raise ValueError(f"{type(self).__name__}.tau_m must be finite [s], got {tau!r}.")

    def init_state(self, omega_command):
        return omega_command

    def applied(self, state, omega_command, w_command) -> tuple[Array, Array]:
        omega = jnp.where(self.tau_m > 0, state, omega_command)
        return omega**2, omega

    def derivative(self, state, omega_command):
        lag = self.tau_m > 0
        tau = jnp.where(lag, self.tau_m, 1.0)
        return jnp.where(lag, (omega_command - state) / tau, 0.0)
