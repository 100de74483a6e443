"""Training/held-out case batches for the robust tuning objective.

Used until the Monte-Carlo sampler (``afbl_jax.montecarlo.sample_cases``) lands; the lead
replaces the import at merge. Everything in the tuner obtains its cases through ONE function,
`training_cases`, so swapping the sampler is a one-line change there.

The returned `TuningCases` has the fields of the Monte-Carlo ``CaseBatch`` that the objective
uses: ``scenario`` (a `Scenario` batched on axis 0), ``vehicle`` (batched true vehicle),
``model`` (the controller's nominal model, unbatched) and ``inputs`` (the sampled numbers).

Distribution (each case drawn from ``jax.random.fold_in(PRNGKey(seed), i)``, so case i is the
same whatever the batch size n):

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

from .._params import QuadrotorParams
from .._plant import STATE_SIZE
from .._scenarios import (
    PAPER_INITIAL_ATTITUDE,
    PROFILES,
    Scenario,
    paper_disturbance,
    paper_reference,
    stack_scenarios,
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


def _sample_one(key, nominal: QuadrotorParams):
    k = jax.random.split(key, 5)
    profile = jax.random.bernoulli(k[0]).astype(int)
    payload = jax.random.uniform(k[1], (), minval=0.0, maxval=0.5)
    scales = jax.random.uniform(k[2], (5,), minval=0.9, maxval=1.1)  # Ix, Iy, Iz, b, d
    torque_amp = jax.random.uniform(k[3], (3,))
    force_amp = jax.random.uniform(k[4], ())
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
    keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.PRNGKey(int(seed)), i))(
        jnp.arange(int(n)))
    profile, payload, scales, torque_amp, force_amp = (
        np.asarray(a) for a in jax.vmap(lambda k: _sample_one(k, nominal))(keys))
    initial = np.zeros(STATE_SIZE)
    initial[3:6] = PAPER_INITIAL_ATTITUDE
    refs = {p: paper_reference(p) for p in PROFILES}
    base = paper_disturbance("uncertain")
    scenarios = []
    for i in range(int(n)):
        torque = np.asarray(base.torque) * np.concatenate([torque_amp[i][None], np.zeros((1, 3))])
        force = np.asarray(base.force) * np.array([[0.0], [force_amp[i]]])
        dist = eqx.tree_at(lambda d: (d.torque, d.force), base, (jnp.asarray(torque),
                                                                  jnp.asarray(force)))
        scenarios.append(Scenario(
            reference=refs[PROFILES[int(profile[i])]], disturbance=dist,
            payload_fraction=float(payload[i]), payload_time=0.0, initial_state=initial,
            t0=0.0, t1=20.0))
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
    return TuningCases(stack_scenarios(scenarios), vehicle, nominal, inputs)
