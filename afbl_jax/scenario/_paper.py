"""The paper's canonical scenarios: {ideal, uncertain} x {step, sine} (one pytree structure, so
the four stack into one batch)."""

from __future__ import annotations

import numpy as np

from ..model import STATE_SIZE
from ._disturbances import PulseDisturbance
from ._references import Reference, make_reference
from ._scenario import Scenario

SCENARIO_KINDS = ("ideal", "uncertain")
PROFILES = ("step", "sine")


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
