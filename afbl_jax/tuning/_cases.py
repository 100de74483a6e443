"""Training/held-out case batches for the robust tuning objective.

Used until the Monte-Carlo sampler (``afbl_jax.montecarlo.sample_cases``) lands; the lead
replaces the import at merge. Everything in the tuner obtains its cases through ONE function,
`training_cases`, so swapping the sampler is a one-line change there.

The returned `TuningCases` has the fields of the Monte-Carlo ``CaseBatch`` that the objective
uses: ``scenario`` (a `Scenario` batched on axis 0), ``vehicle`` (batched true vehicle),
``model`` (the controller's nominal model, unbatched) and ``inputs`` (the sampled numbers).

Distribution (case i drawn from ``numpy.random.default_rng([seed, i])``, so case i is the same
whatever the batch size n):

- reference profile: the paper's ``step`` or ``sine`` attitude profile with probability 1/2
  (altitude 0 -> 1 -> 0 m in both), initial attitude (0.05, -0.05, 0.05) rad, 0-20 s;
- payload fraction p ~ U[0, 0.5] (true mass m (1 + p) for the whole run);
- true Ix, Iy, Iz, thrust coefficient b and drag coefficient d: nominal x U[0.9, 1.1] each
  (independently); the controller keeps the nominal Table 1 model;
- the paper's pulses (torque 0.01 N m on phi, theta, psi at 10-11 s; -2 N vertical force at
  12-13 s) with each amplitude scaled by U[0, 1] independently;
- rotor-speed limit: omega_max set for thrust-to-weight ``thrust_to_weight`` (2.5 by default)
  at the nominal mass and nominal b (the true rotors then give 2.5 x b_true / b_nominal).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._disturbances import PulseDisturbance
from .._params import QuadrotorParams
from .._plant import STATE_SIZE
from .._scenarios import (
    PAPER_INITIAL_ATTITUDE,
    PROFILES,
    Scenario,
    paper_disturbance,
    paper_reference,
)

DEFAULT_THRUST_TO_WEIGHT = 2.5
"""Rotor limit used for tuning and evaluation by default: max thrust / nominal weight."""


class TuningCases(eqx.Module):
    """A batch of cases (fields as the Monte-Carlo ``CaseBatch``).

    Attributes:
        scenario: `Scenario` with a leading batch axis (n,).
        vehicle: true `QuadrotorParams`, batched (n,).
        model: the controller's nominal `QuadrotorParams` (unbatched).
        inputs: sampled numbers per case (arrays of shape (n,) or (n, k)).
    """

    scenario: Scenario
    vehicle: QuadrotorParams
    model: QuadrotorParams
    inputs: dict

    @property
    def n_cases(self) -> int:
        return int(np.shape(self.scenario.t1)[0])


def nominal_vehicle(thrust_to_weight: float | None = DEFAULT_THRUST_TO_WEIGHT) -> QuadrotorParams:
    """Table 1 vehicle with the rotor limit for ``thrust_to_weight`` (None: unlimited)."""
    vehicle = QuadrotorParams()
    return vehicle if thrust_to_weight is None else vehicle.with_thrust_to_weight(
        thrust_to_weight)


def _sample_one(seed: int, i: int):
    rng = np.random.default_rng([int(seed), int(i)])  # case i depends on (seed, i) only
    profile = int(rng.integers(0, 2))
    payload = rng.uniform(0.0, 0.5)
    scales = rng.uniform(0.9, 1.1, size=5)  # Ix, Iy, Iz, b, d
    torque_amp = rng.uniform(0.0, 1.0, size=3)
    force_amp = rng.uniform(0.0, 1.0)
    return profile, payload, scales, torque_amp, force_amp


def training_cases(
    n: int, seed: int, thrust_to_weight: float | None = DEFAULT_THRUST_TO_WEIGHT
) -> TuningCases:
    """``n`` sampled cases, reproducible from ``seed`` (see the module docstring).

    The tuner, its held-out evaluation and the CLI get their cases only from here.
    """
    if int(n) < 1:
        raise ValueError(f"training_cases: n must be >= 1, got {n}.")
    nominal = nominal_vehicle(thrust_to_weight)
    draws = [_sample_one(seed, i) for i in range(int(n))]
    profile, payload, scales, torque_amp, force_amp = (
        np.array([d[j] for d in draws]) for j in range(5))
    n = int(n)
    initial = np.zeros(STATE_SIZE)
    initial[3:6] = PAPER_INITIAL_ATTITUDE
    refs = [paper_reference(p) for p in PROFILES]  # same structure: select per case
    reference = jax.tree.map(lambda *xs: jnp.stack(xs)[profile], *refs)
    base = paper_disturbance("uncertain")
    amp_torque = np.stack([torque_amp, np.zeros((n, 3))], axis=1)  # (n, pulses, 3)
    amp_force = np.stack([np.zeros(n), force_amp], axis=1)[..., None]
    disturbance = PulseDisturbance(
        np.broadcast_to(base.start, (n, 2)), np.broadcast_to(base.duration, (n, 2)),
        np.asarray(base.torque) * amp_torque, np.asarray(base.force) * amp_force)
    scenario = Scenario(
        reference=reference, disturbance=disturbance, payload_fraction=payload,
        payload_time=np.zeros(n), initial_state=np.broadcast_to(initial, (n, STATE_SIZE)),
        t0=np.zeros(n), t1=np.full(n, 20.0))
    ones = np.ones(int(n))
    vehicle = QuadrotorParams(
        m=nominal.m * ones, Ix=nominal.Ix * scales[:, 0], Iy=nominal.Iy * scales[:, 1],
        Iz=nominal.Iz * scales[:, 2], b=nominal.b * scales[:, 3], d=nominal.d * scales[:, 4],
        Jr=nominal.Jr * ones, arm_length=nominal.arm_length * ones, g=nominal.g * ones,
        omega_min=nominal.omega_min * ones, omega_max=nominal.omega_max * ones,
        gyro_sign=nominal.gyro_sign * ones,
    )
    inputs = {
        "profile": profile,  # index into PROFILES: 0 step, 1 sine
        "payload_fraction": payload,
        "inertia_scale": scales[:, :3],
        "thrust_coefficient_scale": scales[:, 3],
        "drag_coefficient_scale": scales[:, 4],
        "torque_pulse_scale": torque_amp,
        "force_pulse_scale": force_amp,
    }
    return TuningCases(scenario, vehicle, nominal, inputs)
