"""Case batches for the robust tuning objective: the Monte-Carlo sampler.

Everything in the tuner (training, held-out evaluation, CLI) obtains its cases through ONE
function, `training_cases`, which draws them with `afbl_jax.montecarlo.sample_cases` from a
Monte-Carlo `Distribution` with the rotor limit set to the tuner's thrust-to-weight ratio. The
default is `tuning_distribution()`: the Monte-Carlo default (payload, model errors, pulses,
1-cosine gusts, mean wind, Dryden turbulence, rotor-drag aerodynamics, initial offsets, step or
sine reference) plus unmodeled dynamics (`TUNING_UNMODELED`: rigid-body plant, motor lag
20-50 ms, digital control 200-500 Hz, measurement delay 0-1 sample, sensor noise). Training cases
are drawn with ``noise=False`` (noise std set to 0: a smooth objective to differentiate); the
held-out evaluation keeps the noise. The sampler draws one control rate per ensemble group of 4
consecutive cases (`afbl_jax.montecarlo.GROUP_SIZE`). Case i of a seed is the same whatever the
batch size. `canonical_cases` (in `_objective`) uses `TuningCases`, a
container with the same fields as the Monte-Carlo ``CaseBatch`` (``scenario``, ``vehicle``,
``model``, ``inputs``).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ...model import AbstractAerodynamics, LinearDrag, PositionHold, QuadrotorParams
from ...scenario import Scenario
from ..montecarlo import Distribution, sample_cases

DEFAULT_THRUST_TO_WEIGHT = 2.5
"""Rotor limit used for tuning and evaluation by default: max thrust / nominal weight."""

TUNING_UNMODELED = {
    "enabled": True,
    "plant": "full",
    "motor_tau": [0.02, 0.05],
    "control_rate": [200.0, 500.0],
    "delay_samples": [0, 1],
    "noise_angle": [0.0, 0.003],
    "noise_rate": [0.0, 0.03],
    "noise_altitude": [0.0, 0.01],
    "noise_vertical_speed": [0.0, 0.03],
}
"""Unmodeled dynamics of the default tuning distribution: rigid-body plant, rotor time constant
[s], controller rate [Hz], measurement delay [samples], sensor noise std [rad, rad/s, m, m/s]."""

NOISE_FIELDS = ("noise_angle", "noise_rate", "noise_altitude", "noise_vertical_speed")


def tuning_distribution() -> Distribution:
    """The Monte-Carlo default distribution with `TUNING_UNMODELED` (realistic vehicles)."""
    return Distribution.from_dict({"unmodeled": TUNING_UNMODELED}, "tuning default")


def without_noise(cases):
    """``cases`` with every sensor-noise std set to 0 (no-op without unmodeled dynamics)."""
    if getattr(cases, "unmodeled", None) is None:
        return cases
    zero = {n: jnp.zeros_like(getattr(cases.unmodeled, n)) for n in NOISE_FIELDS}
    return eqx.tree_at(
        lambda c: [getattr(c.unmodeled, n) for n in NOISE_FIELDS],
        cases,
        [zero[n] for n in NOISE_FIELDS],
    )


class TuningCases(eqx.Module):
    """A batch of cases (fields as the Monte-Carlo ``CaseBatch``).

    Attributes:
        scenario: `Scenario` with a leading batch axis (n,).
        vehicle: true `QuadrotorParams`, batched (n,).
        model: the controller's nominal `QuadrotorParams` (unbatched).
        inputs: sampled numbers per case (arrays of shape (n,) or (n, k)).
        aerodynamics: the cases' aerodynamic model (static; coefficients in ``vehicle``).
        position_loop: the position loop the cases fly with (`afbl_jax.PositionHold`), or
            None.
    """

    scenario: Scenario
    vehicle: QuadrotorParams
    model: QuadrotorParams
    inputs: dict
    aerodynamics: AbstractAerodynamics = eqx.field(default_factory=LinearDrag)
    position_loop: PositionHold | None = None

    @property
    def n_cases(self) -> int:
        return int(np.shape(self.scenario.t1)[0])

    def take(self, indices) -> TuningCases:
        """The cases at positions ``indices`` (an int array, repeats allowed) of this batch."""
        idx = np.asarray(indices)

        def pick(tree):
            return jax.tree.map(lambda x: x[idx], tree)

        model = pick(self.model) if np.ndim(self.model.m) == 1 else self.model
        return TuningCases(
            pick(self.scenario),
            pick(self.vehicle),
            model,
            {k: v[idx] for k, v in self.inputs.items()},
            self.aerodynamics,
            self.position_loop,
        )


def nominal_vehicle(thrust_to_weight: float | None = DEFAULT_THRUST_TO_WEIGHT) -> QuadrotorParams:
    """Table 1 vehicle with the rotor limit for ``thrust_to_weight`` (None: unlimited)."""
    vehicle = QuadrotorParams()
    return vehicle if thrust_to_weight is None else vehicle.with_thrust_to_weight(thrust_to_weight)


def training_cases(
    n: int,
    seed: int,
    thrust_to_weight: float | None = DEFAULT_THRUST_TO_WEIGHT,
    distribution=None,
    noise: bool = True,
):
    """``n`` cases of the Monte-Carlo ``distribution`` (default: `tuning_distribution()`),
    reproducible from ``seed``, with the rotor limit at ``thrust_to_weight`` (max thrust /
    nominal weight at the nominal b; None = unlimited rotors); ``noise=False`` zeroes the
    sensor noise (training: the objective must be smooth in the gains).

    Returns an ``afbl_jax.montecarlo.CaseBatch``.
    """
    if int(n) < 1:
        raise ValueError(f"training_cases: n must be >= 1, got {n}.")
    dist = tuning_distribution() if distribution is None else distribution
    if thrust_to_weight is not None:
        spec = dist.to_dict()
        spec["model_error"]["thrust_to_weight"] = [float(thrust_to_weight)] * 2
        dist = Distribution(spec, dist.source)
    cases = sample_cases(dist, int(n), int(seed))
    if thrust_to_weight is None:
        unlimited = jnp.full_like(cases.vehicle.omega_max, jnp.inf)
        cases = eqx.tree_at(lambda c: c.vehicle.omega_max, cases, unlimited)
    return cases if noise else without_noise(cases)
