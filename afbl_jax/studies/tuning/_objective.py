"""Differentiable tuning objectives over log-gains.

Parametrisation: every gain g > 0 of the tuned controller is optimised as log g, kept inside a
box [log(lo * g_paper), log(hi * g_paper)] (default lo = 0.1, hi = 10) by projection after each
optimiser step, so gains stay positive and bounded. AFBL tunes gamma, k and lambda (paper value
for lambda: our default 4 1/s); FBL+PID tunes P, I, D.

Per-case cost (all from the closed-loop cost states, `afbl_jax.COST_LAYOUT`):

    J = ISE_att + w_alt ISE_alt + w_effort effort + w_sat saturation
        + w_div [failed] (1 + (t1 - t_stop) / (t1 - t0))

- ISE_att [rad^2 s], ISE_alt [m^2 s]: eqs. (42), (43);
- effort: integral of |u - u_hover|^2 dt (u in N, N, N m, N), default weight 1e-4, so that at
  the paper's AFBL gains it is about a third of the ISE (ISE alone is bought with ever larger
  gains);
- saturation: integral of sum_i (excess_i / W_hover)^2 dt [s], a C^1 penalty that is zero while
  no rotor saturates and grows smoothly as the gains push the rotors past the limit;
- divergence / solver failure: a run that stops early (|phi| or |theta| > 1.2 rad, altitude
  error > 10 m, non-finite state, step budget) keeps the costs accumulated until it stopped
  (non-finite ones replaced by 0) plus w_div (1 + fraction of the run not simulated). This term
  is a step function of the gains (zero gradient); the smooth saturation penalty, which grows
  before a failure, and the gain box are what keep the optimiser away from failing gains.

Objectives: ``nominal`` = sum of J over the four canonical scenarios (paper scenarios, vehicle
with the rotor limit); ``robust`` = mean of J over a fixed batch of sampled cases, or its CVaR at
level alpha (the mean of the worst ceil((1 - alpha) n) cases).

Gradients: `jax.value_and_grad` through `afbl_jax.simulate`, whose diffrax solve uses
`diffrax.RecursiveCheckpointAdjoint` (discretise-then-optimise). That is the right adjoint here:
it gives the exact derivative of the discretised solution the loss is computed from (so it agrees
with finite differences of the same solver), it needs no backward-in-time ODE solve (the
`BacksolveAdjoint` alternative re-integrates the closed loop backwards, which is unstable for
this strongly damped loop and only approximates the gradient of the discrete solution, more so
across the pulse and reference kinks), and memory stays bounded by a logarithmic number of
checkpoints in the step count.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import equinox as eqx
import jax
import jax.numpy as jnp

from ...model import CONTROLLERS, AbstractController, QuadrotorParams
from ...model.controllers import DEFAULT_LAMBDA, PAPER_AFBL_GAINS, PAPER_FBL_GAINS
from ...scenario import PROFILES, SCENARIO_KINDS, paper_scenario, stack_scenarios
from ...sim import STATUS_OK, simulate
from ._cases import DEFAULT_THRUST_TO_WEIGHT, TuningCases, nominal_vehicle, training_cases

TUNABLE_CONTROLLERS = ("afbl", "fbl")
PAPER_GAINS = {
    "afbl": {**PAPER_AFBL_GAINS, "lam": DEFAULT_LAMBDA},
    "fbl": dict(PAPER_FBL_GAINS),
}
"""Centre of the default gain box: Tables 2/3 (and lambda = 4 1/s, our default)."""
OBJECTIVES = ("nominal", "robust")
RISKS = ("mean", "cvar")


@dataclass(frozen=True)
class GainSpace:
    """Which gains are tuned, around which values, within which box.

    Attributes:
        controller: "afbl" (tunes gamma, k, lam) or "fbl" (tunes P, I, D).
        base: gains the box is scaled from (default: the paper's; lam: 4 1/s), name -> 4 floats.
        lower, upper: the box is [lower * base, upper * base] (0 < lower < 1 < upper).
    """

    controller: str = "afbl"
    base: dict | None = None
    lower: float = 0.1
    upper: float = 10.0

    def __post_init__(self):
        if self.controller not in TUNABLE_CONTROLLERS:
            raise ValueError(
                f"GainSpace: controller {self.controller!r} cannot be tuned; "
                f"allowed: {', '.join(TUNABLE_CONTROLLERS)}."
            )
        if not (0.0 < self.lower <= 1.0 <= self.upper and math.isfinite(self.upper)):
            raise ValueError(
                f"GainSpace: need 0 < lower <= 1 <= upper < inf, got lower="
                f"{self.lower}, upper={self.upper}."
            )
        if self.base is None:
            object.__setattr__(
                self, "base", {k: list(v) for k, v in PAPER_GAINS[self.controller].items()}
            )

    @property
    def names(self) -> tuple[str, ...]:
        return CONTROLLERS[self.controller].gain_names

    def init_params(self) -> dict[str, jax.Array]:
        """Log-gains of the base gains (the optimiser's starting point)."""
        return {n: jnp.log(jnp.asarray(self.base[n], dtype=float)) for n in self.names}

    def bounds(self) -> tuple[dict, dict]:
        lo = {n: p + math.log(self.lower) for n, p in self.init_params().items()}
        hi = {n: p + math.log(self.upper) for n, p in self.init_params().items()}
        return lo, hi

    def controller_of(self, params: dict) -> AbstractController:
        """Controller with gains exp(params)."""
        return CONTROLLERS[self.controller](**{n: jnp.exp(params[n]) for n in self.names})


@dataclass(frozen=True)
class ObjectiveConfig:
    """Weights and solver settings of the tuning objective (see the module docstring)."""

    objective: str = "robust"
    risk: str = "mean"
    cvar_level: float = 0.9
    w_altitude: float = 1.0
    w_effort: float = 1e-4
    w_saturation: float = 1.0
    w_divergence: float = 1.0
    rtol: float = 1e-6
    atol: float = 1e-8
    max_steps: int = 8192

    def __post_init__(self):
        if self.objective not in OBJECTIVES:
            raise ValueError(
                f"unknown objective {self.objective!r}; allowed: {', '.join(OBJECTIVES)}."
            )
        if self.risk not in RISKS:
            raise ValueError(f"unknown risk measure {self.risk!r}; allowed: {', '.join(RISKS)}.")
        if not 0.0 <= self.cvar_level < 1.0:
            raise ValueError(f"cvar_level must be in [0, 1), got {self.cvar_level}.")
        for name in ("w_altitude", "w_effort", "w_saturation", "w_divergence"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}.")
        if not (self.rtol > 0 and self.atol > 0 and self.max_steps > 0):
            raise ValueError("rtol, atol and max_steps must be > 0.")

    def to_dict(self) -> dict:
        return asdict(self)


class CaseCosts(eqx.Module):
    """Per-case terms (arrays of shape (n,)): the loss J and what it is made of."""

    loss: jax.Array
    ise_attitude: jax.Array
    ise_altitude: jax.Array
    effort: jax.Array
    saturation: jax.Array
    failed: jax.Array
    status: jax.Array


def canonical_cases(vehicle: QuadrotorParams) -> TuningCases:
    """The four canonical scenarios as a case batch (ideal/uncertain x step/sine)."""
    scen = stack_scenarios([paper_scenario(k, p) for k in SCENARIO_KINDS for p in PROFILES])
    batched = jax.tree.map(lambda a: jnp.broadcast_to(a, (4, *jnp.shape(a))), vehicle)
    return TuningCases(scen, batched, vehicle, {})


def _finite(x):
    ok = jnp.isfinite(x)
    return jnp.where(ok, x, 0.0), ok


def case_costs(controller: AbstractController, cases, config: ObjectiveConfig) -> CaseCosts:
    """Simulate every case (vmap) and return its cost terms. ``cases`` has batched
    ``.scenario`` and ``.vehicle``, a ``.model`` (batched or not) and the ``.aerodynamics``
    model of its cases."""
    model_batched = jax.tree.leaves(cases.model)[0].ndim > 0
    aerodynamics = cases.aerodynamics

    def one(scenario, vehicle, model):
        return simulate(
            controller,
            scenario,
            vehicle,
            model,
            rtol=config.rtol,
            atol=config.atol,
            n_save=0,
            max_steps=config.max_steps,
            aerodynamics=aerodynamics,
        )

    res = jax.vmap(one, in_axes=(0, 0, 0 if model_batched else None))(
        cases.scenario, cases.vehicle, cases.model
    )
    ise_att, f1 = _finite(res.ise_attitude)
    ise_alt, f2 = _finite(res.ise_altitude)
    effort, f3 = _finite(res.effort)
    sat, f4 = _finite(res.saturation)
    failed = (res.status != STATUS_OK) | ~(f1 & f2 & f3 & f4)
    t0, t1 = cases.scenario.t0, cases.scenario.t1
    t_stop, _ = _finite(res.t_final)
    missing = jnp.clip((t1 - t_stop) / (t1 - t0), 0.0, 1.0)
    loss = (
        ise_att
        + config.w_altitude * ise_alt
        + config.w_effort * effort
        + config.w_saturation * sat
        + config.w_divergence * jnp.where(failed, 1.0 + jax.lax.stop_gradient(missing), 0.0)
    )
    return CaseCosts(loss, ise_att, ise_alt, effort, sat, failed, res.status)


def aggregate(losses: jax.Array, config: ObjectiveConfig) -> jax.Array:
    """Scalar objective from per-case losses: sum (nominal), mean or CVaR (robust)."""
    if config.objective == "nominal":
        return jnp.sum(losses)
    if config.risk == "mean":
        return jnp.mean(losses)
    n = losses.shape[0]
    k = max(1, math.ceil((1.0 - config.cvar_level) * n))
    return jnp.mean(jax.lax.top_k(losses, k)[0])


def objective(params: dict, space: GainSpace, cases, config: ObjectiveConfig):
    """(scalar objective, `CaseCosts`) of the log-gains ``params`` on ``cases``."""
    costs = case_costs(space.controller_of(params), cases, config)
    return aggregate(costs.loss, config), costs


def cases_for(
    config: ObjectiveConfig,
    n_cases: int,
    seed: int,
    thrust_to_weight: float | None = DEFAULT_THRUST_TO_WEIGHT,
):
    """The case batch an objective is evaluated on: the canonical four (``nominal``) or
    ``n_cases`` from `training_cases` (``robust``), with the rotor limit ``thrust_to_weight``."""
    if config.objective == "nominal":
        return canonical_cases(nominal_vehicle(thrust_to_weight))
    return training_cases(n_cases, seed, thrust_to_weight=thrust_to_weight)
