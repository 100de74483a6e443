"""Differentiable tuning objectives over log-gains, evaluated on the batched fast path.

Parametrisation: every gain g > 0 of the tuned controller is optimised as log g inside a box
[log(lo * g_paper), log(hi * g_paper)] (default lo = 0.1, hi = 10). The optimisers work on an
unconstrained vector z with log g = c + h tanh(z) (c, h: centre and half-width of the box), so
gains stay positive and inside the box without projections (which would break L-BFGS's line
search); z = 0 is the box centre (the paper's gains for the default box). AFBL tunes gamma, k
and lambda (paper value for lambda: our default 4 1/s); FBL+PID tunes P, I, D.

Per-case terms (closed-loop cost states, `afbl_jax.COST_LAYOUT`): ISE_att [rad^2 s], ISE_alt
[m^2 s] (eqs. 42, 43), effort = integral of |u - u_hover|^2 dt, saturation = integral of
sum_i (excess_i / W_hover)^2 dt [s] (C^1, zero while no rotor saturates), failure (divergence,
solver failure; a failed case keeps the costs accumulated until it stopped).

Normalisation: each term is divided by its mean at the reference gains (the paper's) on the
same cases (`reference_terms`), so the weights are relative importances and the objective at
the paper's gains is w_att + w_alt + w_effort + w_sat (+ the failure term). Per case:

    L_i = w_att ISE_att,i / ref_att + w_alt ISE_alt,i / ref_alt
          + w_effort effort_i / ref_effort + w_sat sat_i / ref_sat
          + w_div [failed_i] (1 + fraction of the run not simulated)

aggregated as a mean or CVaR over cases (``robust``; a sum for ``nominal``), plus smooth
quadratic penalties on the limits (relative violations squared, weight ``penalty``):

    mean effort <= effort_limit x paper's;  mean saturation <= saturation_limit x max(paper's,
    SATURATION_FLOOR).

Failures are a step function of the gains (zero gradient): gradient methods see them through
the value (L-BFGS's line search rejects a step into failing gains; CMA-ES ranks by value) and
through the saturation penalty, which grows before a run fails. Cases that fail at every gain
(unrecoverable gusts) add a constant. `limit_report` says which limits are active.

Gradients: `jax.value_and_grad` through `afbl_jax.simulate_batch` with ``strategy="ensemble"``
(diffrax's ``diffeqsolve`` per group of 4 cases, `diffrax.RecursiveCheckpointAdjoint`:
discretise-then-optimise, the exact derivative of the discretised solution, no backward ODE
solve) with the cases' unmodeled dynamics (rigid-body plant, motor lag, digital control: a scan
of interval solves). Sensor noise is off while differentiating (`training_cases(noise=False)`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ...model import CONTROLLERS, AbstractController, QuadrotorParams
from ...model.controllers import DEFAULT_LAMBDA, PAPER_AFBL_GAINS, PAPER_FBL_GAINS
from ...scenario import PROFILES, SCENARIO_KINDS, paper_scenario, stack_scenarios
from ...sim import STATUS_OK, simulate_batch
from ..montecarlo import GROUP_SIZE
from ._cases import DEFAULT_THRUST_TO_WEIGHT, TuningCases, nominal_vehicle, training_cases

TUNABLE_CONTROLLERS = ("afbl", "fbl")
PAPER_GAINS = {
    "afbl": {**PAPER_AFBL_GAINS, "lam": DEFAULT_LAMBDA},
    "fbl": dict(PAPER_FBL_GAINS),
}
"""Centre of the default gain box: Tables 2/3 (and lambda = 4 1/s, our default)."""
OBJECTIVES = ("nominal", "robust")
RISKS = ("mean", "cvar")
DTYPES = ("float64", "float32")
SATURATION_FLOOR = 1e-4
"""Smallest saturation scale [s] used to normalise (the paper's gains may not saturate)."""
BOX_TOLERANCE = 0.01
"""A gain is reported "on the box" within this fraction of the box's log-width of an edge."""


@dataclass(frozen=True)
class GainSpace:
    """Which gains are tuned, around which values, within which box.

    Attributes:
        controller: "afbl" (tunes gamma, k, lam) or "fbl" (tunes P, I, D).
        base: gains the box is scaled from (default: the paper's; lam: 4 1/s), name -> 4 floats.
        lower, upper: the box is [lower * base, upper * base] (0 < lower <= 1 <= upper).
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
        if not (0.0 < self.lower < 1.0 < self.upper and math.isfinite(self.upper)):
            raise ValueError(
                f"GainSpace: need 0 < lower < 1 < upper < inf, got lower="
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
        """Log-gains of the base gains."""
        return {n: jnp.log(jnp.asarray(self.base[n], dtype=float)) for n in self.names}

    def bounds(self) -> tuple[dict, dict]:
        lo = {n: p + math.log(self.lower) for n, p in self.init_params().items()}
        hi = {n: p + math.log(self.upper) for n, p in self.init_params().items()}
        return lo, hi

    def _centre_half(self):
        c = 0.5 * (math.log(self.lower) + math.log(self.upper))
        h = 0.5 * (math.log(self.upper) - math.log(self.lower))
        return c, h

    def log_gains(self, z: dict) -> dict:
        """Log-gains of the unconstrained vector z (inside the box for every finite z)."""
        c, h = self._centre_half()
        base = self.init_params()
        return {n: base[n] + c + h * jnp.tanh(z[n]) for n in self.names}

    def unconstrained(self, params: dict) -> dict:
        """z of the log-gains ``params`` (strictly inside the box)."""
        c, h = self._centre_half()
        base = self.init_params()
        return {n: jnp.arctanh((params[n] - base[n] - c) / h) for n in self.names}

    def init_z(self) -> dict:
        """z of the base gains (the starting point of every optimiser)."""
        return self.unconstrained(self.init_params())

    def controller_of(self, params: dict) -> AbstractController:
        """Controller with gains exp(params) (log-gains; leading batch axes allowed)."""
        return CONTROLLERS[self.controller](**{n: jnp.exp(params[n]) for n in self.names})

    def on_box(self, params: dict) -> list[str]:
        """Names "gain_channel" of the gains within `BOX_TOLERANCE` of a box edge."""
        lo, hi = self.bounds()
        width = math.log(self.upper) - math.log(self.lower)
        out = []
        for n in self.names:
            p = np.asarray(params[n])
            for j, ch in enumerate(("phi", "theta", "psi", "z")):
                if min(p[j] - float(lo[n][j]), float(hi[n][j]) - p[j]) <= BOX_TOLERANCE * width:
                    edge = "lower" if p[j] - float(lo[n][j]) < float(hi[n][j]) - p[j] else "upper"
                    out.append(f"{n}_{ch} ({edge})")
        return out


@dataclass(frozen=True)
class ObjectiveConfig:
    """Weights, limits and solver settings of the tuning objective (module docstring).

    Attributes:
        objective: "robust" (sampled cases) or "nominal" (the four canonical scenarios).
        risk, cvar_level: "mean" or "cvar" (mean of the worst ceil((1 - alpha) n) cases).
        w_attitude, w_altitude, w_effort, w_saturation: relative weights of the normalised
            terms; w_divergence: per failed case.
        effort_limit: mean effort <= effort_limit x the paper's (inf: no limit).
        saturation_limit: mean saturation <= saturation_limit x max(paper's, floor).
        penalty: weight of the squared relative limit violations.
        dtype: "float64" or "float32" solve; rtol, atol; max_steps per solve without digital
            control; max_steps_interval per sample interval with digital control (reverse mode
            keeps a checkpoint buffer of this many steps for every interval: memory grows with
            it; an interval of 2-5 ms takes a few steps).
    """

    objective: str = "robust"
    risk: str = "mean"
    cvar_level: float = 0.9
    w_attitude: float = 1.0
    w_altitude: float = 1.0
    w_effort: float = 0.0
    w_saturation: float = 0.0
    w_divergence: float = 10.0
    effort_limit: float = 1.0
    saturation_limit: float = 1.0
    penalty: float = 100.0
    dtype: str = "float64"
    rtol: float = 1e-6
    atol: float = 1e-8
    max_steps: int = 4096
    max_steps_interval: int = 64

    def __post_init__(self):
        if self.objective not in OBJECTIVES:
            raise ValueError(
                f"unknown objective {self.objective!r}; allowed: {', '.join(OBJECTIVES)}."
            )
        if self.risk not in RISKS:
            raise ValueError(f"unknown risk measure {self.risk!r}; allowed: {', '.join(RISKS)}.")
        if self.dtype not in DTYPES:
            raise ValueError(f"unknown dtype {self.dtype!r}; allowed: {', '.join(DTYPES)}.")
        if not 0.0 <= self.cvar_level < 1.0:
            raise ValueError(f"cvar_level must be in [0, 1), got {self.cvar_level}.")
        for name in (
            "w_attitude",
            "w_altitude",
            "w_effort",
            "w_saturation",
            "w_divergence",
            "penalty",
        ):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}.")
        if self.w_attitude + self.w_altitude <= 0:
            raise ValueError("w_attitude + w_altitude must be > 0 (attitude and altitude count).")
        for name in ("effort_limit", "saturation_limit"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0 (inf: no limit), got {getattr(self, name)}.")
        if not (
            self.rtol > 0 and self.atol > 0 and self.max_steps > 0 and self.max_steps_interval > 0
        ):
            raise ValueError("rtol, atol, max_steps and max_steps_interval must be > 0.")

    def to_dict(self) -> dict:
        return asdict(self)


class CaseCosts(eqx.Module):
    """Per-case terms (arrays of shape (n,)), un-normalised, in SI units."""

    ise_attitude: jax.Array
    ise_altitude: jax.Array
    effort: jax.Array
    saturation: jax.Array
    failed: jax.Array
    missing: jax.Array
    status: jax.Array


class Reference(eqx.Module):
    """Means of the terms at the reference (paper's) gains on the same cases: the scales the
    objective divides by."""

    ise_attitude: jax.Array
    ise_altitude: jax.Array
    effort: jax.Array
    saturation: jax.Array


def canonical_cases(vehicle: QuadrotorParams) -> TuningCases:
    """The four canonical scenarios as a case batch (ideal/uncertain x step/sine)."""
    scen = stack_scenarios([paper_scenario(k, p) for k in SCENARIO_KINDS for p in PROFILES])
    batched = jax.tree.map(lambda a: jnp.broadcast_to(a, (4, *jnp.shape(a))), vehicle)
    return TuningCases(scen, batched, vehicle, {})


def _finite(x):
    ok = jnp.isfinite(x)
    return jnp.where(ok, x, 0.0), ok


def case_costs(
    controller: AbstractController, cases, config: ObjectiveConfig, all_devices: bool = True
) -> CaseCosts:
    """Simulate every case with `simulate_batch` (ensemble of diffeqsolve groups of 4 cases,
    differentiable) and return its cost terms. ``cases``: a Monte-Carlo ``CaseBatch`` or
    `TuningCases`; ``controller`` shared or batched (gains with the cases' leading axis).

    ``all_devices``: split the cases over the local devices (forward evaluations); False: one
    device (what the gradients use: reverse mode through ``jax.shard_map`` around the
    digital-control scan fails in diffrax's closure conversion)."""
    n = int(np.shape(cases.scenario.t1)[0])
    local = jax.local_devices() if all_devices else jax.local_devices()[:1]
    # devices whose blocks hold whole sampler groups (their cases share one control rate)
    n_dev = max(d for d in range(1, len(local) + 1) if d == 1 or n % (GROUP_SIZE * d) == 0)
    unmodeled = getattr(cases, "unmodeled", None)
    digital = unmodeled is not None and unmodeled.digital
    m = simulate_batch(
        controller,
        cases.scenario,
        cases.vehicle,
        cases.model,
        unmodeled=unmodeled,
        aerodynamics=cases.aerodynamics,
        position_loop=cases.position_loop,
        strategy="ensemble",
        # the differentiable ensemble path (the lean loop is forward-mode only); every method
        # (gradient or CMA-ES) evaluates the same objective
        integrator="diffeqsolve",
        group_size=GROUP_SIZE,
        dtype=config.dtype,
        rtol=config.rtol,
        atol=config.atol,
        max_steps=config.max_steps_interval if digital else config.max_steps,
        devices=local[:n_dev],
    )
    m = jax.tree.map(lambda x: x.astype(float) if jnp.issubdtype(x.dtype, jnp.floating) else x, m)
    ise_att, f1 = _finite(m.ise_attitude)
    ise_alt, f2 = _finite(m.ise_altitude)
    effort, f3 = _finite(m.effort)
    sat, f4 = _finite(m.saturation)
    failed = (m.status != STATUS_OK) | ~(f1 & f2 & f3 & f4)
    t0, t1 = cases.scenario.t0, cases.scenario.t1
    t_stop, _ = _finite(m.t_final)
    missing = jax.lax.stop_gradient(jnp.clip((t1 - t_stop) / (t1 - t0), 0.0, 1.0))
    return CaseCosts(ise_att, ise_alt, effort, sat, failed, missing, m.status)


def reference_terms(costs: CaseCosts) -> Reference:
    """The normalising means of ``costs`` (saturation floored at `SATURATION_FLOOR`)."""
    return Reference(
        jnp.mean(costs.ise_attitude),
        jnp.mean(costs.ise_altitude),
        jnp.mean(costs.effort),
        jnp.maximum(jnp.mean(costs.saturation), SATURATION_FLOOR),
    )


def case_losses(costs: CaseCosts, ref: Reference, config: ObjectiveConfig) -> jax.Array:
    """Per-case normalised loss L_i (module docstring). A failed case's terms (accumulated
    until it failed) carry no gradient: their derivative says nothing about the gains' merit."""

    def term(x):
        return jnp.where(costs.failed, jax.lax.stop_gradient(x), x)

    return (
        config.w_attitude * term(costs.ise_attitude) / ref.ise_attitude
        + config.w_altitude * term(costs.ise_altitude) / ref.ise_altitude
        + config.w_effort * term(costs.effort) / ref.effort
        + config.w_saturation * term(costs.saturation) / ref.saturation
        + config.w_divergence * jnp.where(costs.failed, 1.0 + costs.missing, 0.0)
    )


def limit_ratios(costs: CaseCosts, ref: Reference) -> dict:
    """Mean effort and saturation relative to their reference scales."""
    return {
        "effort": jnp.mean(costs.effort) / ref.effort,
        "saturation": jnp.mean(costs.saturation) / ref.saturation,
    }


def penalties(costs: CaseCosts, ref: Reference, config: ObjectiveConfig) -> jax.Array:
    """Smooth (C^1) penalty: ``penalty`` x sum of squared relative limit violations."""
    r = limit_ratios(costs, ref)
    over_e = jnp.maximum(r["effort"] / config.effort_limit - 1.0, 0.0)
    over_s = jnp.maximum(r["saturation"] / config.saturation_limit - 1.0, 0.0)
    return config.penalty * (over_e**2 + over_s**2)


def aggregate(losses: jax.Array, config: ObjectiveConfig) -> jax.Array:
    """Scalar objective from per-case losses: sum (nominal), mean or CVaR (robust)."""
    if config.objective == "nominal":
        return jnp.sum(losses)
    if config.risk == "mean":
        return jnp.mean(losses)
    n = losses.shape[0]
    k = max(1, math.ceil((1.0 - config.cvar_level) * n))
    return jnp.mean(jax.lax.top_k(losses, k)[0])


def objective_of_costs(costs: CaseCosts, ref: Reference, config: ObjectiveConfig) -> jax.Array:
    return aggregate(case_losses(costs, ref, config), config) + penalties(costs, ref, config)


def objective(params: dict, space: GainSpace, cases, config: ObjectiveConfig, ref: Reference):
    """(scalar objective, `CaseCosts`) of the log-gains ``params`` on ``cases`` (one device:
    the form that is differentiated)."""
    costs = case_costs(space.controller_of(params), cases, config, all_devices=False)
    return objective_of_costs(costs, ref, config), costs


def limit_report(costs: CaseCosts, ref: Reference, config: ObjectiveConfig, ref_failed: int):
    """Which limits are active (at or beyond their bound, 1e-3 relative) at these costs."""
    r = {k: float(v) for k, v in limit_ratios(costs, ref).items()}
    failed = int(np.sum(np.asarray(costs.failed)))
    return {
        "effort_ratio": r["effort"],
        "effort_limit": config.effort_limit,
        "effort_active": r["effort"] >= config.effort_limit * (1 - 1e-3),
        "saturation_ratio": r["saturation"],
        "saturation_limit": config.saturation_limit,
        "saturation_active": r["saturation"] >= config.saturation_limit * (1 - 1e-3),
        "failures": failed,
        "failures_reference": int(ref_failed),
        "failures_active": failed > 0,
    }


def tile_cases(cases, copies: int):
    """``cases`` repeated ``copies`` times along the case axis (population evaluation)."""
    idx = np.tile(np.arange(cases.n_cases), copies)

    def pick(tree):
        return jax.tree.map(lambda x: x[idx], tree)

    fields = [cases.scenario, cases.vehicle]
    getters = [lambda c: c.scenario, lambda c: c.vehicle]
    if jax.tree.leaves(cases.model)[0].ndim > 0:
        fields.append(cases.model)
        getters.append(lambda c: c.model)
    if getattr(cases, "unmodeled", None) is not None:
        fields.append(cases.unmodeled)
        getters.append(lambda c: c.unmodeled)
    return eqx.tree_at(lambda c: [g(c) for g in getters], cases, [pick(f) for f in fields])


def cases_for(
    config: ObjectiveConfig,
    n_cases: int,
    seed: int,
    thrust_to_weight: float | None = DEFAULT_THRUST_TO_WEIGHT,
    distribution=None,
):
    """The case batch an objective is trained on: the canonical four (``nominal``) or
    ``n_cases`` noise-free cases from `training_cases` (``robust``)."""
    if config.objective == "nominal":
        return canonical_cases(nominal_vehicle(thrust_to_weight))
    return training_cases(
        n_cases, seed, thrust_to_weight=thrust_to_weight, distribution=distribution, noise=False
    )
