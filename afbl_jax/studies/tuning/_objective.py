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
solver failure; a failed case keeps the costs accumulated until it stopped) and the smooth
failure margin m_i = `afbl_jax.smooth_margin` of the run's peak attitude and altitude errors
(temperature ``margin_temperature``; m < 0 inside the failure limits, m >= 0 at them).

Cases outside the vehicle's flight envelope (``envelope_cause`` not 0 in the case inputs,
decided before simulating, `afbl_jax.sim.Status.outside_envelope`) are left out: they carry
weight w_i = 0 in every mean below (the others w_i = 1).

Normalisation: each term is divided by its (weighted) mean at the reference gains (the
paper's) on the same cases (`reference_terms`), so the weights are relative importances. With
P_i = w_att ISE_att,i / ref_att + w_alt ISE_alt,i / ref_alt + w_effort effort_i / ref_effort
+ w_sat sat_i / ref_sat the per-case loss is, for ``failure="margin"`` (default, continuous in
the gains):

    surviving case:  L_i = (1 - S(m_i)) psi(P_i) + S(m_i) K + w_div H(m_i),
    failed case:     L_i = K + w_div,

    psi(P) = P - kappa softplus((P - K) / kappa)   (a smooth min(P, K), kappa = K / 10),
    H(m) = tau [softplus((m + rho) / tau) - softplus((m + 4 tau) / tau)] / (rho - 4 tau),
    S(m) = smoothstep((m + rho) / rho),

with K = ``loss_cap``, rho = ``reserve`` and tau = ``margin_temperature`` (rho > 4 tau). H is
a softplus hinge on m + rho, the reserve used up, saturated at 1: it starts to grow where the
margin has used up all but the reserve (m = -rho) and reaches 1 (within e^-4 tau / (rho -
4 tau)) at m = -4 tau, before the limit; S = 3x^2 - 2x^3 clipped to [0, 1] (0 for m <= -rho, 1
for m >= 0) moves the performance term to the cap K over the reserve. Every case's loss is
nondecreasing in its margin (psi < K) and at most K + w_div, the cost of a failed case. At the
gains where a case starts to fail its run stops early, its integrals jump and its margin
(peaks before the stop) no longer follows the gains; its loss does not jump where the margin
has reached the limit there (m >= 0, as for an error that crosses its divergence limit): both
sides are then K + w_div. It does jump, by at most (1 - S(m)) (K - psi) + w_div (1 - H(m)),
where a run fails with its margin short of the limit (a divergence of |phi| or |theta| while
the error to a nonzero reference stays below the limit, or a solver failure). A case whose
performance term is above K counts as a failure.
For ``failure="step"`` (the former staircase objective):

    L_i = P_i + w_div [failed_i] (1 + fraction of the run not simulated).

The aggregate over cases is a sum (``nominal``), the mean or the CVaR at level alpha
(``robust``). ``risk="cvar"`` with ``cvar_temperature`` beta > 0 is the smoothed
Rockafellar-Uryasev form

    CVaR_beta(L) = min_t  t + 1 / (1 - alpha) sum_i w_i beta softplus((L_i - t) / beta) / sum_i w_i,

with the level t minimised exactly for every evaluation (the objective is convex in t: a
bisection on the optimality condition sum_i w_i sigmoid((L_i - t*) / beta) / sum_i w_i =
1 - alpha), which equals minimising t jointly with the gains; by the envelope theorem the
gradient is that of the expression at t* held fixed, a soft tail weighting
w_i sigmoid((L_i - t*) / beta) / ((1 - alpha) sum w). It bounds the exact CVaR from above by at
most beta log 2 / (1 - alpha). beta = 0: the mean of the worst ceil((1 - alpha) n) cases.
Plus smooth quadratic penalties on the limits (relative violations squared, weight
``penalty``):

    mean effort <= effort_limit x paper's;  mean saturation <= saturation_limit x max(paper's,
    SATURATION_FLOOR).

`limit_report` says which limits are active.

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

from ...metrics import smooth_margin
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
FAILURES = ("margin", "step")
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
        risk, cvar_level: "mean" or "cvar" at level alpha (module docstring).
        cvar_temperature: beta of the smoothed CVaR, in units of the normalised loss (0: the
            mean of the worst ceil((1 - alpha) n) cases).
        failure: "margin" (default: softplus hinge on the smooth failure margin, continuous
            in the gains) or "step" (a constant per failed case; module docstring).
        reserve: rho, the margin reserve [-] where the hinge starts (fraction of the failure
            limits).
        loss_cap: K, the cap of a case's performance term and the cost of a failure without
            the hinge (normalised units: the mean case at the paper's gains costs
            w_att + w_alt).
        margin_temperature: tau [-] of `afbl_jax.smooth_margin` and of the hinge's softplus.
        n_save: samples per run for the peak errors of the margin.
        w_attitude, w_altitude, w_effort, w_saturation: relative weights of the normalised
            terms; w_divergence: per failed case.
        effort_limit: mean effort <= effort_limit x the paper's (inf: no limit).
        saturation_limit: mean saturation <= saturation_limit x max(paper's, floor).
        penalty: weight of the squared relative limit violations.
        dtype: "float64" or "float32" solve; rtol, atol; max_steps per solve without digital
            control; max_steps_interval per sample interval with digital control (reverse mode
            keeps a checkpoint buffer of this many steps for every interval: memory grows with
            it; an interval of 2-5 ms takes a few steps).
        gradient_chunk: most cases one reverse pass differentiates at a time (a positive
            multiple of `afbl_jax.montecarlo.GROUP_SIZE`). A gradient over more cases is one
            forward pass over all of them, the objective's derivative with respect to each
            case's costs, then the sum of the chunks' vector-Jacobian products: the same
            gradient, with the reverse pass's memory bounded by the chunk instead of growing
            with the number of cases. With several local devices the cases are split into at
            least one chunk per device, and the devices' chunks run at the same time.
    """

    objective: str = "robust"
    risk: str = "mean"
    cvar_level: float = 0.9
    cvar_temperature: float = 0.05
    failure: str = "margin"
    reserve: float = 0.3
    loss_cap: float = 50.0
    margin_temperature: float = 0.025
    n_save: int = 201
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
    gradient_chunk: int = 32

    def __post_init__(self):
        if self.objective not in OBJECTIVES:
            raise ValueError(
                f"unknown objective {self.objective!r}; allowed: {', '.join(OBJECTIVES)}."
            )
        if self.risk not in RISKS:
            raise ValueError(f"unknown risk measure {self.risk!r}; allowed: {', '.join(RISKS)}.")
        if self.dtype not in DTYPES:
            raise ValueError(f"unknown dtype {self.dtype!r}; allowed: {', '.join(DTYPES)}.")
        if self.failure not in FAILURES:
            raise ValueError(
                f"unknown failure treatment {self.failure!r}; allowed: {', '.join(FAILURES)}."
            )
        if not (
            self.cvar_temperature >= 0
            and self.reserve > 0
            and self.margin_temperature > 0
            and self.loss_cap > 0
        ):
            raise ValueError(
                "need cvar_temperature >= 0 and reserve, margin_temperature, loss_cap > 0; got "
                f"{self.cvar_temperature}, {self.reserve}, {self.margin_temperature}, "
                f"{self.loss_cap}."
            )
        if not self.reserve > 4.0 * self.margin_temperature:
            raise ValueError(
                f"need reserve > 4 margin_temperature, got {self.reserve}, "
                f"{self.margin_temperature}."
            )
        if self.n_save < 2:
            raise ValueError(f"n_save must be >= 2, got {self.n_save}.")
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
        if not (self.gradient_chunk > 0 and self.gradient_chunk % GROUP_SIZE == 0):
            raise ValueError(
                f"gradient_chunk must be a positive multiple of {GROUP_SIZE} (the ensemble "
                f"group size), got {self.gradient_chunk}."
            )

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
    margin: jax.Array | None = None
    weight: jax.Array | None = None

    def weights(self) -> jax.Array:
        """w_i: 1 for a case inside the flight envelope, 0 outside (all 1 without the input)."""
        if self.weight is None:
            return jnp.ones_like(self.ise_attitude)
        return self.weight


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


def envelope_weights(cases) -> jax.Array:
    """w_i per case: 1 inside the flight envelope, 0 outside (the case inputs'
    ``envelope_cause``, decided before simulating; all 1 where the cases do not carry it)."""
    n = int(np.shape(cases.scenario.t1)[0])
    cause = getattr(cases, "inputs", {}).get("envelope_cause")
    if cause is None:
        return jnp.ones((n,))
    return jnp.where(jnp.reshape(cause, (n,)) == 0, 1.0, 0.0)


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
    margin = config.failure == "margin"
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
        n_save=config.n_save if margin else 0,
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
    if margin:
        sm, finite = _finite(smooth_margin(m, temperature=config.margin_temperature))
        # a run with no finite peak sample failed before its first sample: at the limit
        sm = jnp.where(finite | ~failed, sm, 0.0)
    else:
        sm = jnp.full_like(ise_att, jnp.nan)
    weight = envelope_weights(cases)
    return CaseCosts(ise_att, ise_alt, effort, sat, failed, missing, m.status, sm, weight)


def _wmean(x, w):
    """Weighted mean (entries with weight 0 do not enter, even non-finite ones)."""
    return jnp.sum(jnp.where(w > 0, x, 0.0) * w) / jnp.maximum(jnp.sum(w), 1e-300)


def reference_terms(costs: CaseCosts) -> Reference:
    """The normalising means of ``costs`` over the cases inside the envelope (saturation
    floored at `SATURATION_FLOOR`)."""
    w = costs.weights()
    return Reference(
        _wmean(costs.ise_attitude, w),
        _wmean(costs.ise_altitude, w),
        _wmean(costs.effort, w),
        jnp.maximum(_wmean(costs.saturation, w), SATURATION_FLOOR),
    )


def hinge(m: jax.Array, config: ObjectiveConfig) -> jax.Array:
    """H(m): the saturated softplus hinge, the failure penalty per unit w_div (module
    docstring); about 0 for m << -rho, 1 from m = -4 tau on."""
    tau, rho = config.margin_temperature, config.reserve
    d = 4.0 * tau
    return tau * (jax.nn.softplus((m + rho) / tau) - jax.nn.softplus((m + d) / tau)) / (rho - d)


def reach(m: jax.Array, config: ObjectiveConfig) -> jax.Array:
    """S(m) = smoothstep((m + rho) / rho): 0 for m <= -rho, 1 for m >= 0 (C^1)."""
    x = jnp.clip((m + config.reserve) / config.reserve, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def capped(p: jax.Array, config: ObjectiveConfig) -> jax.Array:
    """psi(P) = P - kappa softplus((P - K) / kappa), kappa = K / 10: a smooth min(P, K) < K."""
    kappa = 0.1 * config.loss_cap
    return p - kappa * jax.nn.softplus((p - config.loss_cap) / kappa)


def performance(costs: CaseCosts, ref: Reference, config: ObjectiveConfig) -> jax.Array:
    """P_i: the weighted sum of the normalised terms per case (as computed, failed or not)."""
    return (
        config.w_attitude * costs.ise_attitude / ref.ise_attitude
        + config.w_altitude * costs.ise_altitude / ref.ise_altitude
        + config.w_effort * costs.effort / ref.effort
        + config.w_saturation * costs.saturation / ref.saturation
    )


def case_losses(costs: CaseCosts, ref: Reference, config: ObjectiveConfig) -> jax.Array:
    """Per-case normalised loss L_i (module docstring). A failed case's terms (accumulated
    until it failed) carry no gradient: their derivative says nothing about the gains' merit."""
    failed = costs.failed
    if config.failure == "margin":
        k, w = config.loss_cap, config.w_divergence
        # double where: a failed case's values (and their gradients) never enter the branch
        # of the surviving cases
        m = jnp.where(failed, -10.0 * config.reserve, costs.margin)
        psi = capped(jnp.where(failed, 0.0, performance(costs, ref, config)), config)
        s = reach(m, config)
        survive = (1.0 - s) * psi + s * k + w * hinge(m, config)
        fail = jnp.full_like(survive, k + w)
        return jnp.where(failed, fail, survive)

    def term(x):
        return jnp.where(failed, jax.lax.stop_gradient(x), x)

    return (
        config.w_attitude * term(costs.ise_attitude) / ref.ise_attitude
        + config.w_altitude * term(costs.ise_altitude) / ref.ise_altitude
        + config.w_effort * term(costs.effort) / ref.effort
        + config.w_saturation * term(costs.saturation) / ref.saturation
        + config.w_divergence * jnp.where(failed, 1.0 + costs.missing, 0.0)
    )


def limit_ratios(costs: CaseCosts, ref: Reference) -> dict:
    """Mean effort and saturation (cases inside the envelope) relative to their reference
    scales."""
    w = costs.weights()
    return {
        "effort": _wmean(costs.effort, w) / ref.effort,
        "saturation": _wmean(costs.saturation, w) / ref.saturation,
    }


def penalties(costs: CaseCosts, ref: Reference, config: ObjectiveConfig) -> jax.Array:
    """Smooth (C^1) penalty: ``penalty`` x sum of squared relative limit violations."""
    r = limit_ratios(costs, ref)
    over_e = jnp.maximum(r["effort"] / config.effort_limit - 1.0, 0.0)
    over_s = jnp.maximum(r["saturation"] / config.saturation_limit - 1.0, 0.0)
    return config.penalty * (over_e**2 + over_s**2)


def smooth_cvar(losses: jax.Array, weights: jax.Array, level: float, beta: float) -> jax.Array:
    """The smoothed Rockafellar-Uryasev CVaR at ``level`` (module docstring) of ``losses``
    with case weights (0: left out), the level t minimised exactly (bisection, 80 halvings of
    a bracket that holds t*; t* enters with no gradient, the envelope theorem)."""
    w = weights / jnp.sum(weights)
    x = jnp.where(weights > 0, losses, 0.0)
    xs = jax.lax.stop_gradient(x)
    inside = weights > 0
    lo = jnp.min(jnp.where(inside, xs, jnp.inf)) - 40.0 * beta
    hi = jnp.max(jnp.where(inside, xs, -jnp.inf)) + beta * (40.0 - math.log(1.0 - level))

    def tail(t):  # weighted fraction above t, decreasing in t
        return jnp.sum(w * jax.nn.sigmoid((xs - t) / beta))

    def halve(_, bracket):
        a, b = bracket
        c = 0.5 * (a + b)
        above = tail(c) > 1.0 - level
        return jnp.where(above, c, a), jnp.where(above, b, c)

    a, b = jax.lax.fori_loop(0, 80, halve, (lo, hi))
    t = jax.lax.stop_gradient(0.5 * (a + b))
    return t + jnp.sum(w * beta * jax.nn.softplus((x - t) / beta)) / (1.0 - level)


def aggregate(
    losses: jax.Array, config: ObjectiveConfig, weights: jax.Array | None = None
) -> jax.Array:
    """Scalar objective from per-case losses: sum (nominal), mean or CVaR (robust), over the
    cases with weight 1 (``weights``: `envelope_weights`; None: every case)."""
    w = jnp.ones_like(losses) if weights is None else weights
    x = jnp.where(w > 0, losses, 0.0)
    if config.objective == "nominal":
        return jnp.sum(x * w)
    if config.risk == "mean" or config.cvar_level == 0.0:
        return _wmean(x, w)
    if config.cvar_temperature > 0:
        return smooth_cvar(x, w, config.cvar_level, config.cvar_temperature)
    if weights is None:
        k = max(1, math.ceil((1.0 - config.cvar_level) * int(losses.shape[0])))
        return jnp.mean(jax.lax.top_k(x, k)[0])
    # cases left out rank last and are not counted
    k = jnp.maximum(1, jnp.ceil((1.0 - config.cvar_level) * jnp.sum(w > 0)))
    ranked = jnp.sort(jnp.where(w > 0, x, -jnp.inf))[::-1]
    return jnp.sum(jnp.where(jnp.arange(ranked.shape[0]) < k, ranked, 0.0)) / k


def objective_of_costs(costs: CaseCosts, ref: Reference, config: ObjectiveConfig) -> jax.Array:
    losses = case_losses(costs, ref, config)
    return aggregate(losses, config, costs.weights()) + penalties(costs, ref, config)


def objective(params: dict, space: GainSpace, cases, config: ObjectiveConfig, ref: Reference):
    """(scalar objective, `CaseCosts`) of the log-gains ``params`` on ``cases`` (one device:
    the form that is differentiated)."""
    costs = case_costs(space.controller_of(params), cases, config, all_devices=False)
    return objective_of_costs(costs, ref, config), costs


def limit_report(costs: CaseCosts, ref: Reference, config: ObjectiveConfig, ref_failed: int):
    """Which limits are active (at or beyond their bound, 1e-3 relative) at these costs."""
    r = {k: float(v) for k, v in limit_ratios(costs, ref).items()}
    failed = int(np.sum(np.asarray(costs.failed) & (np.asarray(costs.weights()) > 0)))
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
    return cases.take(np.tile(np.arange(cases.n_cases), copies))


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
