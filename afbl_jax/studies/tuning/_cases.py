"""Case batches for the robust tuning objective: the Monte-Carlo sampler.

Everything in the tuner (training, held-out evaluation, CLI) obtains its cases through ONE
function, `training_cases`, which draws them with `afbl_jax.montecarlo.sample_cases` from a
Monte-Carlo `Distribution` (default: `afbl_jax.montecarlo.DEFAULT_DISTRIBUTION`: payload,
model errors, pulses, 1-cosine gusts, Dryden turbulence, initial offsets, step or sine
reference) with the rotor limit set to the tuner's thrust-to-weight ratio. Case i of a seed is
the same whatever the batch size. `canonical_cases` (in `_objective`) uses `TuningCases`, a
container with the same fields as the Monte-Carlo ``CaseBatch`` (``scenario``, ``vehicle``,
``model``, ``inputs``).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ...model import AbstractAerodynamics, LinearDrag, QuadrotorParams
from ...scenario import Scenario
from ..montecarlo import Distribution, default_distribution, sample_cases

DEFAULT_THRUST_TO_WEIGHT = 2.5
"""Rotor limit used for tuning and evaluation by default: max thrust / nominal weight."""


class TuningCases(eqx.Module):
    """A batch of cases (fields as the Monte-Carlo ``CaseBatch``).

    Attributes:
        scenario: `Scenario` with a leading batch axis (n,).
        vehicle: true `QuadrotorParams`, batched (n,).
        model: the controller's nominal `QuadrotorParams` (unbatched).
        inputs: sampled numbers per case (arrays of shape (n,) or (n, k)).
        aerodynamics: the cases' aerodynamic model (static; coefficients in ``vehicle``).
    """

    scenario: Scenario
    vehicle: QuadrotorParams
    model: QuadrotorParams
    inputs: dict
    aerodynamics: AbstractAerodynamics = eqx.field(default_factory=LinearDrag)

    @property
    def n_cases(self) -> int:
        return int(np.shape(self.scenario.t1)[0])


def nominal_vehicle(thrust_to_weight: float | None = DEFAULT_THRUST_TO_WEIGHT) -> QuadrotorParams:
    """Table 1 vehicle with the rotor limit for ``thrust_to_weight`` (None: unlimited)."""
    vehicle = QuadrotorParams()
    return vehicle if thrust_to_weight is None else vehicle.with_thrust_to_weight(thrust_to_weight)


def training_cases(
    n: int,
    seed: int,
    thrust_to_weight: float | None = DEFAULT_THRUST_TO_WEIGHT,
    distribution=None,
):
    """``n`` cases of the Monte-Carlo ``distribution`` (default: the default distribution),
    reproducible from ``seed``, with the rotor limit at ``thrust_to_weight`` (max thrust /
    nominal weight at the nominal b; None = unlimited rotors).

    Returns an ``afbl_jax.montecarlo.CaseBatch``.
    """
    if int(n) < 1:
        raise ValueError(f"training_cases: n must be >= 1, got {n}.")
    dist = default_distribution() if distribution is None else distribution
    if thrust_to_weight is not None:
        spec = dist.to_dict()
        spec["model_error"]["thrust_to_weight"] = [float(thrust_to_weight)] * 2
        dist = Distribution(spec, dist.source)
    cases = sample_cases(dist, int(n), int(seed))
    if thrust_to_weight is None:
        unlimited = jnp.full_like(cases.vehicle.omega_max, jnp.inf)
        cases = eqx.tree_at(lambda c: c.vehicle.omega_max, cases, unlimited)
    return cases
