"""Batched closed-loop solving: many cases per compiled call.

`simulate_batch` runs N cases (a batch of scenarios and vehicles, and optionally of models and
controller gains) with one of these strategies:

- ``"vmap"``: ``jax.vmap`` over `simulate` (``n_save=0``). Every case has its own adaptive step
  sequence; under vmap the batched ``while_loop`` runs until the slowest case is done, and each
  iteration pays diffrax's per-step bookkeeping for every lane.
- ``"ensemble"``: the whole batch as ONE ODE system (state leaves of shape (N, ...)) with one
  shared step sequence. Step-size control uses `ensemble_rms_norm`, the maximum over cases of
  each case's RMS scaled error, so every case meets its own tolerance (rtol, atol) on every
  step. The vector field is evaluated for all cases at once (vectorised arithmetic, no
  per-lane control flow).

Ensemble details:

- Divergence: a case crossing the `DivergenceLimits` (or reaching a non-finite state) is
  *frozen*: its derivatives are set to zero from then on, so its cost integrals stop at the
  crossing time, it cannot stall the shared step size, and its status is ``diverged``
  (`STATUS_DIVERGED`). The freeze is made persistent by an extra per-case state that grows at
  rate 1 while frozen (``t_final = t1 - frozen_time``).
- Jump times: the shared step sequence steps exactly onto the union of all cases' jump times
  (pulse edges, reference kinks, payload times). Cases with many
  distinct jump times therefore cost every other case extra steps.
- Step counts: ``num_steps`` is the shared step count (the same for every case).
- All cases must share t0 and t1.
- ``dtype``: float64 (default under x64) or float32 (every input leaf and the state are cast;
  use a looser rtol, float32 resolves ~1e-7 relative; the accuracy of float32 is measured in
  `afbl bench`).

``chunk_size`` splits a batch into consecutive chunks solved one after the other inside the same
compiled call (``jax.lax.map``): smaller working sets stay in cache, and each ensemble chunk has
its own step sequence.

Both strategies are jitted once per (strategy, solver, tolerances, dtype, batch shapes): chunks
of the same size reuse the compiled program (`trace_count` counts traces, for tests).
"""

from __future__ import annotations

from typing import Literal

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._params import QuadrotorParams
from ._scenarios import Scenario
from ._simulate import (
    COST_LAYOUT,
    STATUS_DIVERGED,
    STATUS_MAX_STEPS,
    STATUS_OK,
    STATUS_SOLVER_FAILED,
    ClosedLoopState,
    DivergenceLimits,
    _Args,
    _diverged,
    closed_loop_vector_field,
    get_solver,
    simulate,
)
from ._typing import Array, Float, Int
from ._validation import check_positive, concrete
from .controllers import AbstractController

STRATEGIES = ("vmap", "ensemble")
"""Batched-solving strategies accepted by `simulate_batch`."""

_TRACES = {"count": 0}


def trace_count() -> int:
    """How many times a batched solve has been traced (compiled) in this process."""
    return _TRACES["count"]


class BatchMetrics(eqx.Module):
    """Per-case results of `simulate_batch` (every field has leading axis N).

    Attributes:
        ise_attitude, ise_altitude, effort, saturation: cost integrals at the end of each run
            (`afbl_jax.COST_LAYOUT`; a diverged run's integrals stop where it diverged).
        status: same codes as `simulate` (0 ok, 1 diverged, 2 max_steps, 3 solver failure).
        t_final: time each run ended [s] (t1, or the divergence time).
        num_steps: solver steps (accepted + rejected); for ``"ensemble"`` the shared count.
        num_rejected_steps: rejected steps (shared count for ``"ensemble"``).
    """

    ise_attitude: Float[Array, " N"]
    ise_altitude: Float[Array, " N"]
    effort: Float[Array, " N"]
    saturation: Float[Array, " N"]
    status: Int[Array, " N"]
    t_final: Float[Array, " N"]
    num_steps: Int[Array, " N"]
    num_rejected_steps: Int[Array, " N"]

    @property
    def ok(self) -> Array:
        return self.status == STATUS_OK


def ensemble_rms_norm(tree) -> Array:
    """Max over cases (leading axis) of each case's RMS over all its other entries.

    Used as the `diffrax.PIDController` norm of the ensemble: the shared step is accepted only
    when every case's own RMS scaled error is below 1. Non-finite errors stay non-finite (the
    step is rejected).
    """
    leaves = jax.tree.leaves(tree)
    sq = sum(jnp.sum(jnp.reshape(x, (x.shape[0], -1)) ** 2, axis=1) for x in leaves)
    count = sum(int(np.prod(x.shape[1:])) for x in leaves)
    return jnp.sqrt(jnp.max(sq) / count)


def _leading(x) -> int | None:
    return None if np.ndim(x) == 0 else int(np.shape(x)[0])


def _batch_sizes(controller, scenarios, vehicles, models):
    n = _leading(scenarios.t0)
    if n is None:
        raise ValueError(
            "simulate_batch: scenarios must be batched (leading axis = cases; use "
            "stack_scenarios), got an unbatched Scenario."
        )
    axes = {}
    for name, tree, probe, base_ndim in (
        ("vehicles", vehicles, lambda p: p.m, 0),
        ("models", models, lambda p: p.m, 0),
        ("controller", controller, lambda c: getattr(c, c.gain_names[0]), 1),
    ):
        leaf = probe(tree)
        if np.ndim(leaf) == base_ndim:
            axes[name] = None
        elif np.ndim(leaf) == base_ndim + 1 and np.shape(leaf)[0] == n:
            axes[name] = 0
        else:
            raise ValueError(
                f"simulate_batch: {name} must be unbatched or have leading axis {n} (the number "
                f"of scenarios), got a leaf of shape {np.shape(leaf)}."
            )
    return n, axes


def _cast(tree, dtype):
    return jax.tree.map(
        lambda x: x.astype(dtype) if jnp.issubdtype(jnp.result_type(x), jnp.floating) else x, tree
    )


def _union_jump_times(scenarios: Scenario, dtype) -> Array:
    # sorted, duplicates kept (a fixed shape per batch shape, so chunks never recompile);
    # diffrax's ClipStepSizeController steps onto each distinct time once
    jumps = jax.vmap(lambda s: s.jump_times())(scenarios).reshape(-1)
    return jnp.sort(jumps).astype(dtype)


def _status_from(result, finite, diverged):
    solver_status = jnp.where(
        result == diffrax.RESULTS.successful,
        STATUS_OK,
        jnp.where(result == diffrax.RESULTS.max_steps_reached, STATUS_MAX_STEPS,
                  STATUS_SOLVER_FAILED),
    )
    status = jnp.where(diverged | ~finite, STATUS_DIVERGED, solver_status)
    return status.astype(jnp.int32)


def _ensemble(controller, scenarios, vehicles, models, limits, axes, solver, rtol, atol, dtype,
              max_steps) -> BatchMetrics:
    n = scenarios.t0.shape[0]
    args = _Args(controller, scenarios, vehicles, models, limits)
    args = _cast(args, dtype)
    in_axes = _Args(axes["controller"], 0, axes["vehicles"], axes["models"], None)
    t0, t1 = args.scenario.t0[0], args.scenario.t1[0]

    def one_case(t, state, frozen_time, a):
        dstate = closed_loop_vector_field(t, state, a)
        frozen = _diverged(t, state, a) | (frozen_time > 0)
        dstate = jax.tree.map(lambda d: jnp.where(frozen, jnp.zeros_like(d), d), dstate)
        return dstate, jnp.where(frozen, jnp.ones_like(frozen_time), jnp.zeros_like(frozen_time))

    def field(t, y, a):
        state, frozen_time = y
        return jax.vmap(one_case, in_axes=(None, 0, 0, in_axes))(t, state, frozen_time, a)

    init_ctrl = jax.vmap(lambda c: c.init_state(), in_axes=(axes["controller"],),
                         axis_size=n)(args.controller)
    y0 = (
        ClosedLoopState(
            args.scenario.initial_state.astype(dtype),
            init_ctrl.astype(dtype),
            jnp.zeros((n, len(COST_LAYOUT)), dtype),
        ),
        jnp.zeros((n,), dtype),
    )
    stepsize = diffrax.ClipStepSizeController(
        diffrax.PIDController(rtol=rtol, atol=atol, norm=ensemble_rms_norm),
        jump_ts=_union_jump_times(scenarios, dtype),
    )
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(field),
        solver,
        t0,
        t1,
        None,
        y0,
        args=args,
        saveat=diffrax.SaveAt(t1=True),
        stepsize_controller=stepsize,
        max_steps=max_steps,
        throw=False,
    )
    state, frozen_time = jax.tree.map(lambda a: a[-1], sol.ys)
    finite = jnp.all(jnp.isfinite(state.plant), axis=1) & jnp.all(
        jnp.isfinite(state.cost), axis=1)
    status = _status_from(sol.result, finite, frozen_time > 0)
    ones = jnp.ones((n,), jnp.int32)
    return BatchMetrics(
        ise_attitude=state.cost[:, 0],
        ise_altitude=state.cost[:, 1],
        effort=state.cost[:, 2],
        saturation=state.cost[:, 3],
        status=status,
        t_final=jnp.where(finite, t1 - frozen_time, jnp.nan).astype(dtype),
        num_steps=ones * sol.stats["num_steps"],
        num_rejected_steps=ones * sol.stats["num_rejected_steps"],
    )


def _vmap(controller, scenarios, vehicles, models, limits, axes, solver, rtol, atol, dtype,
          max_steps) -> BatchMetrics:
    def one(c, s, v, m):
        r = simulate(c, s, v, m, solver=solver, rtol=rtol, atol=atol, n_save=0,
                     max_steps=max_steps, limits=limits)
        return BatchMetrics(r.ise_attitude, r.ise_altitude, r.effort, r.saturation, r.status,
                            r.t_final, r.num_steps, r.num_rejected_steps)

    return jax.vmap(one, in_axes=(axes["controller"], 0, axes["vehicles"], axes["models"]))(
        controller, scenarios, vehicles, models)


@eqx.filter_jit
def _run(controller, scenarios, vehicles, models, limits, axes_items, strategy, solver, rtol,
         atol, dtype, max_steps, chunk_size) -> BatchMetrics:
    _TRACES["count"] += 1
    impl = _ensemble if strategy == "ensemble" else _vmap
    axes = dict(axes_items)
    n = scenarios.t0.shape[0]
    if chunk_size is None or chunk_size >= n:
        return impl(controller, scenarios, vehicles, models, limits, axes, solver, rtol, atol,
                    np.dtype(dtype), max_steps)
    # chunks run one after the other inside this one compiled program (lax.map); the last
    # chunk is padded with copies of case 0 and the padding is dropped
    n_chunks = -(-n // chunk_size)
    pad = n_chunks * chunk_size - n

    def split(x):
        x = jnp.concatenate([x, jnp.broadcast_to(x[:1], (pad, *x.shape[1:]))]) if pad else x
        return x.reshape(n_chunks, chunk_size, *x.shape[1:])

    batched = {"scenarios": scenarios, "controller": controller, "vehicles": vehicles,
               "models": models}
    mapped = {k: jax.tree.map(split, v) for k, v in batched.items() if k == "scenarios"
              or axes[k] == 0}
    fixed = {k: v for k, v in batched.items() if k not in mapped}

    def one_chunk(part):
        b = {**fixed, **part}
        return impl(b["controller"], b["scenarios"], b["vehicles"], b["models"], limits, axes,
                    solver, rtol, atol, np.dtype(dtype), max_steps)

    out = jax.lax.map(one_chunk, mapped)
    return jax.tree.map(lambda x: x.reshape(n_chunks * chunk_size, *x.shape[2:])[:n], out)


def simulate_batch(
    controller: AbstractController,
    scenarios: Scenario,
    vehicles: QuadrotorParams | None = None,
    models: QuadrotorParams | None = None,
    *,
    strategy: Literal["vmap", "ensemble"] = "ensemble",
    solver: str | diffrax.AbstractSolver = "tsit5",
    rtol: float = 1e-6,
    atol: float = 1e-8,
    dtype=None,
    max_steps: int = 16384,
    limits: DivergenceLimits | None = None,
    chunk_size: int | None = None,
) -> BatchMetrics:
    """Simulate N cases in one compiled call; returns per-case `BatchMetrics`.

    Args:
        controller: one controller (shared) or a batch (gains with leading axis N).
        scenarios: batch of N scenarios (`stack_scenarios`, or fields with leading axis N).
        vehicles: true vehicles, batched (leading axis N) or one shared (default Table 1).
        models: controller models, batched or shared (default: ``vehicles``).
        strategy: ``"ensemble"`` (one ODE system, shared steps; default) or ``"vmap"``.
        solver: diffrax solver or name (as in `simulate`).
        rtol, atol: tolerances; with ``"ensemble"`` every case meets them (max-over-cases norm).
        dtype: floating dtype of the solve (default: JAX's default float). ``"vmap"`` supports
            only the default float dtype.
        max_steps: step budget (for ``"ensemble"``: shared by the whole batch).
        limits: divergence limits (default `DivergenceLimits()`).
        chunk_size: solve the batch as consecutive chunks of this many cases inside the one
            compiled call (``jax.lax.map``); with ``"ensemble"`` each chunk has its own shared
            step sequence. Smaller chunks keep the working set in cache (the benchmark's
            ``ensemble_chunked`` rows). None (default): one chunk.

    Never raises for failed or diverged cases; check ``status``.
    """
    if strategy not in STRATEGIES:
        raise ValueError(f"unknown strategy {strategy!r}; allowed: {', '.join(STRATEGIES)}.")
    vehicles = QuadrotorParams() if vehicles is None else vehicles
    models = vehicles if models is None else models
    limits = DivergenceLimits() if limits is None else limits
    check_positive("simulate_batch", "rtol", rtol)
    check_positive("simulate_batch", "atol", atol)
    if int(max_steps) <= 0:
        raise ValueError(f"simulate_batch: max_steps must be > 0, got {max_steps}.")
    if chunk_size is not None and int(chunk_size) <= 0:
        raise ValueError(f"simulate_batch: chunk_size must be > 0 or None, got {chunk_size}.")
    default = jnp.result_type(float)
    dtype = np.dtype(default if dtype is None else dtype)
    if not jnp.issubdtype(dtype, jnp.floating):
        raise ValueError(f"simulate_batch: dtype must be a floating dtype, got {dtype}.")
    if strategy == "vmap" and dtype != default:
        raise ValueError(f"simulate_batch: strategy 'vmap' runs in the default float dtype "
                         f"({default}); got dtype {dtype}. Use strategy='ensemble'.")
    _, axes = _batch_sizes(controller, scenarios, vehicles, models)
    if strategy == "ensemble":
        for name in ("t0", "t1"):
            v = concrete(getattr(scenarios, name))
            if v is not None and not np.all(v == v.reshape(-1)[0]):
                raise ValueError(f"simulate_batch: strategy 'ensemble' needs one {name} for all "
                                 f"cases, got values from {v.min()} to {v.max()} [s].")
    return _run(controller, scenarios, vehicles, models, limits, tuple(sorted(axes.items())),
                strategy, get_solver(solver), float(rtol), float(atol), dtype.name,
                int(max_steps), None if chunk_size is None else int(chunk_size))
