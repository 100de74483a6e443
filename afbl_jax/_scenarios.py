"""Scenarios: what the vehicle is asked to do and what happens to it.

A `Scenario` is data: reference, disturbances, payload, initial state and time span. The four
canonical scenarios of the paper reproduction ({ideal, uncertain} x {step, sine}) share one
structure, so they stack into one batch (`stack_scenarios`) and run under one `jax.vmap`.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._disturbances import PulseDisturbance
from ._plant import STATE_SIZE
from ._references import Reference, make_reference
from ._typing import Array, Float, Scalar
from ._validation import check_finite, check_last_dim, concrete
from ._wind import Wind, no_wind

SCENARIO_KINDS = ("ideal", "uncertain")
PROFILES = ("step", "sine")


def _as_float(x) -> Array:
    return jnp.asarray(x, dtype=jnp.result_type(float))


class Scenario(eqx.Module):
    """One simulation case.

    Attributes:
        reference: desired (phi, theta, psi, z) with derivatives.
        disturbance: external force/torque pulses.
        payload_fraction: payload as a fraction p of the vehicle mass; the true mass is
            m (1 + p) from ``payload_time`` on (p > -1).
        payload_time: time the payload is attached [s] (<= t0 means the whole run).
        initial_state: plant state at t0, shape (12,), layout in `afbl_jax._plant`.
        t0, t1: time span [s].
        wind: wind velocity field acting through the vehicle's aerodynamic model (default calm
            air with no gusts and no turbulence; see `afbl_jax._wind`).
    """

    reference: Reference
    disturbance: PulseDisturbance
    payload_fraction: Scalar = eqx.field(default=0.0, converter=_as_float)
    payload_time: Scalar = eqx.field(default=0.0, converter=_as_float)
    initial_state: Float[Array, 12] = eqx.field(
        default_factory=lambda: np.zeros(STATE_SIZE), converter=_as_float
    )
    t0: Scalar = eqx.field(default=0.0, converter=_as_float)
    t1: Scalar = eqx.field(default=20.0, converter=_as_float)
    wind: Wind = eqx.field(default_factory=no_wind)

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

    def jump_times(self) -> Array:
        """Times [s] where the closed-loop vector field is discontinuous or has a kink."""
        return jnp.concatenate(
            [
                self.disturbance.jump_times(),
                self.reference.kink_times(),
                jnp.atleast_1d(self.payload_time),
                self.wind.jump_times(),
            ]
        )


def stack_scenarios(scenarios: list[Scenario]) -> Scenario:
    """Stack same-structure scenarios along a new leading axis (for `jax.vmap`)."""
    if not scenarios:
        raise ValueError("stack_scenarios needs at least one scenario.")
    return jax.tree.map(lambda *xs: jnp.stack(xs), *scenarios)


PAPER_INITIAL_ATTITUDE = (0.05, -0.05, 0.05)
"""Initial (phi, theta, psi) [rad] of the canonical scenarios."""


def paper_reference(profile: str) -> Reference:
    """Reference of the canonical scenarios: ``"step"`` or ``"sine"`` attitude profile.

    Altitude (both): z 0 -> 1 m at 1 s, 1 -> 0 m at 16 s (1 s minimum-jerk blends).
    step: phi 0 -> 0.1 at 4 s and back at 8 s; theta 0 -> -0.1 at 6 s and back at 10 s;
    psi 0 -> 0.2 at 8 s and back at 12 s. sine: phi = 0.1 sin t, theta = 0.1 sin 0.8t,
    psi = 0.2 sin 0.5t [rad].
    """
    z_steps = [(1.0, 0.0, 1.0), (16.0, 1.0, 0.0)]
    if profile == "step":
        steps = {
            "phi": [(4.0, 0.0, 0.1), (8.0, 0.1, 0.0)],
            "theta": [(6.0, 0.0, -0.1), (10.0, -0.1, 0.0)],
            "psi": [(8.0, 0.0, 0.2), (12.0, 0.2, 0.0)],
            "z": z_steps,
        }
        return make_reference(steps=steps, max_steps=2)
    if profile == "sine":
        sines = {"phi": (0.1, 1.0, 0.0), "theta": (0.1, 0.8, 0.0), "psi": (0.2, 0.5, 0.0)}
        return make_reference(steps={"z": z_steps}, sines=sines, max_steps=2)
    raise ValueError(f"unknown profile {profile!r}; allowed: {', '.join(PROFILES)}.")


def paper_disturbance(kind: str) -> PulseDisturbance:
    """Pulses of the canonical scenarios (zero amplitudes for ``"ideal"``).

    uncertain: +0.01 N m on each of phi, theta, psi for 10 <= t < 11 s, and a -2 N vertical
    force for 12 <= t < 13 s.
    """
    if kind not in SCENARIO_KINDS:
        raise ValueError(f"unknown scenario {kind!r}; allowed: {', '.join(SCENARIO_KINDS)}.")
    scale = 1.0 if kind == "uncertain" else 0.0
    torque = scale * np.array([[0.01, 0.01, 0.01], [0.0, 0.0, 0.0]])
    force = scale * np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -2.0]])
    return PulseDisturbance(np.array([10.0, 12.0]), np.array([1.0, 1.0]), torque, force)


def paper_scenario(kind: str = "ideal", profile: str = "step") -> Scenario:
    """One of the four canonical scenarios: kind in {ideal, uncertain}, profile in {step, sine}.

    Time 0 -> 20 s; initial phi = 0.05, theta = -0.05, psi = 0.05 rad, all else 0. ``uncertain``
    carries a 50 % payload for the whole run and the pulses of `paper_disturbance`.
    """
    initial = np.zeros(STATE_SIZE)
    initial[3:6] = PAPER_INITIAL_ATTITUDE
    return Scenario(
        reference=paper_reference(profile),
        disturbance=paper_disturbance(kind),
        payload_fraction=0.5 if kind == "uncertain" else 0.0,
        payload_time=0.0,
        initial_state=initial,
        t0=0.0,
        t1=20.0,
    )
