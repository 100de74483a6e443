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

``group_size`` (ensemble only) splits the batch into groups of that many cases, each group one
ODE system with its own shared step sequence, the groups vectorised with ``jax.vmap``. Groups
matter when cases have *different* jump times (Monte-Carlo cases: random pulse and payload
times): one ensemble of N such cases steps onto all of their jump times, a group only onto its
own few, while ``jax.vmap`` over groups still amortises the solver's per-step work over the group.

``chunk_size`` splits a batch into consecutive chunks solved one after the other inside the same
compiled call (``jax.lax.map``): smaller working sets stay in cache, and each ensemble chunk has
its own step sequence.

Devices: the case axis is split over ``devices`` (default: all local devices of the default
backend) with ``jax.shard_map``; every device solves its own cases independently (no
communication per step). On a CPU, XLA exposes one device unless
``XLA_FLAGS=--xla_force_host_platform_device_count=K`` is set before JAX is imported (the
``afbl`` command line sets it to the number of cores; see the README). The batch is padded with
copies of case 0 to a multiple of (devices x chunk x group); the padding is dropped.

Peaks: with ``n_save > 0`` the state is sampled at ``n_save`` equally spaced times (diffrax
``SubSaveAt(ts, fn)``: only three numbers per case and sample are kept) and `BatchMetrics` holds
the peak attitude error, peak altitude error and peak commanded rotor speed / omega_max over the
samples before each run's end (`sample_peaks`), as the Monte-Carlo results table needs.

Both strategies are jitted once per (strategy, solver, tolerances, dtype, batch shapes, devices):
chunks of the same size reuse the compiled program (`trace_count` counts traces, for tests).
"""

from __future__ import annotations

from typing import Literal

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._mixer import rotor_speeds_sq_from_inputs
from ._params import QuadrotorParams
from ._plant import diverged_from
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
    _signals_and_derivative,
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
        peak_attitude_error [rad], peak_altitude_error [m], peak_saturation [-]: maxima over
            the ``n_save`` samples before the run's end (`sample_peaks`); NaN when n_save = 0.
    """

    ise_attitude: Float[Array, " N"]
    ise_altitude: Float[Array, " N"]
    effort: Float[Array, " N"]
    saturation: Float[Array, " N"]
    status: Int[Array, " N"]
    t_final: Float[Array, " N"]
    num_steps: Int[Array, " N"]
    num_rejected_steps: Int[Array, " N"]
    peak_attitude_error: Float[Array, " N"]
    peak_altitude_error: Float[Array, " N"]
    peak_saturation: Float[Array, " N"]

    @property
    def ok(self) -> Array:
        return self.status == STATUS_OK


def sample_peaks(error: Float[Array, 4], u_command: Float[Array, 4], vehicle: QuadrotorParams,
                 model: QuadrotorParams) -> Array:
    """The three quantities whose maxima over the saved samples are a run's peaks, shape (3,):
    max(|e_phi|, |e_theta|, |e_psi|) [rad], |e_z| [m], and max over the rotors of commanded rotor
    speed / omega_max [-] (commanded speed = sqrt of the mixer's commanded Omega^2 through the
    controller's ``model``, clipped at 0; >= 1 means the command hit the rotor limit)."""
    err = jnp.abs(error)
    w_cmd = rotor_speeds_sq_from_inputs(model, u_command)
    sat = jnp.sqrt(jnp.maximum(w_cmd, 0.0)) / vehicle.omega_max
    return jnp.stack([jnp.max(err[:3]), err[3], jnp.max(sat)])


def peaks_over_samples(ts, samples, t_final) -> Array:
    """Max over the samples at ``ts`` (shape (n,)) with ts <= t_final of ``samples`` (n, 3);
    non-finite samples are skipped. Returns shape (3,)."""
    valid = (ts <= t_final)[:, None] & jnp.isfinite(samples)
    return jnp.max(jnp.where(valid, samples, 0.0), axis=0)


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
    axes = {"scenarios": 0}
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


def _per_case(fn, part, fixed, n):
    """``fn(args)`` for every case, shape (n, ...); ``args`` = the case's batched leaves
    (``part``) combined with the shared ones (``fixed``)."""
    return jax.vmap(lambda p: fn(eqx.combine(p, fixed)), axis_size=n)(part)


def _shared_or_per_case(fn, part, fixed, n):
    """``fn(args)`` once (unbatched) if it does not depend on the batched leaves, else for
    every case (leading axis n)."""
    try:
        return jax.vmap(lambda p: fn(eqx.combine(p, fixed)), axis_size=n, out_axes=None)(part)
    except ValueError:  # the result depends on batched leaves
        return _per_case(fn, part, fixed, n)


def _union_jump_times(part, fixed, n, dtype) -> Array:
    # sorted, duplicates kept (a fixed shape per batch shape, so chunks never recompile);
    # diffrax's ClipStepSizeController steps onto each distinct time once. Shared jump times
    # (every case the same) are taken once.
    jumps = _shared_or_per_case(lambda a: a.scenario.jump_times(), part, fixed, n)
    return jnp.sort(jumps.reshape(-1)).astype(dtype)


def _status_from(result, finite, diverged):
    solver_status = jnp.where(
        result == diffrax.RESULTS.successful,
        STATUS_OK,
        jnp.where(result == diffrax.RESULTS.max_steps_reached, STATUS_MAX_STEPS,
                  STATUS_SOLVER_FAILED),
    )
    status = jnp.where(diverged | ~finite, STATUS_DIVERGED, solver_status)
    return status.astype(jnp.int32)


def _ensemble(part: _Args, fixed: _Args, n, solver, rtol, atol, dtype, max_steps,
              n_save) -> BatchMetrics:
    """One ODE system for the n cases of ``part`` (batched leaves, leading axis n) sharing
    ``fixed`` (leaves equal for every case, unbatched: computed once per evaluation)."""
    t0 = _shared_or_per_case(lambda a: a.scenario.t0, part, fixed, n).reshape(-1)[0]
    t1 = _shared_or_per_case(lambda a: a.scenario.t1, part, fixed, n).reshape(-1)[0]

    # ODE state: (ClosedLoopState with leaves (n, ...), frozen time (n,)); the divergence test
    # reuses the vector field's own reference and error (one evaluation of each per stage)
    def one_case(t, state, frozen_time, p, fx):
        a = eqx.combine(p, fx)
        signals, dstate = _signals_and_derivative(t, state, a)
        frozen = diverged_from(state.plant, signals.error[3], a.limits, state.controller) | (
            frozen_time > 0)
        dstate = jax.tree.map(lambda d: jnp.where(frozen, jnp.zeros_like(d), d), dstate)
        return dstate, jnp.where(frozen, jnp.ones_like(frozen_time), jnp.zeros_like(frozen_time))

    def field(t, y, args):
        (state, frozen_time), (p, fx) = y, args
        return jax.vmap(one_case, in_axes=(None, 0, 0, 0, None), axis_size=n)(
            t, state, frozen_time, p, fx)

    y0 = (
        ClosedLoopState(
            _per_case(lambda a: a.scenario.initial_state, part, fixed, n).astype(dtype),
            _per_case(lambda a: a.controller.init_state(), part, fixed, n).astype(dtype),
            jnp.zeros((n, len(COST_LAYOUT)), dtype),
        ),
        jnp.zeros((n,), dtype),
    )
    stepsize = diffrax.ClipStepSizeController(
        diffrax.PIDController(rtol=rtol, atol=atol, norm=ensemble_rms_norm),
        jump_ts=_union_jump_times(part, fixed, n, dtype),
    )
    subs = [diffrax.SubSaveAt(t1=True)]
    if n_save:
        ts = t0 + (t1 - t0) * jnp.linspace(0.0, 1.0, n_save, dtype=dtype)

        def one_sample(t, state, p, fx):
            a = eqx.combine(p, fx)
            sig = _signals_and_derivative(t, state, a)[0]
            return sample_peaks(sig.error, sig.u_command, a.vehicle, a.model)

        def save_peaks(t, y, args):
            return jax.vmap(one_sample, in_axes=(None, 0, 0, None), axis_size=n)(
                t, y[0], *args)

        subs.append(diffrax.SubSaveAt(ts=ts, fn=save_peaks))
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(field),
        solver,
        t0,
        t1,
        None,
        y0,
        args=(part, fixed),
        saveat=diffrax.SaveAt(subs=subs),
        stepsize_controller=stepsize,
        max_steps=max_steps,
        throw=False,
    )
    state, frozen_time = jax.tree.map(lambda a: a[-1], sol.ys[0])
    finite = jnp.all(jnp.isfinite(state.plant), axis=1) & jnp.all(
        jnp.isfinite(state.cost), axis=1)
    status = _status_from(sol.result, finite, frozen_time > 0)
    ones = jnp.ones((n,), jnp.int32)
    t_final = jnp.where(finite, t1 - frozen_time, jnp.nan).astype(dtype)
    if n_save:
        peaks = jax.vmap(peaks_over_samples, in_axes=(None, 1, 0))(sol.ts[1], sol.ys[1], t_final)
    else:
        peaks = jnp.full((n, 3), jnp.nan, dtype)
    return BatchMetrics(
        ise_attitude=state.cost[:, 0],
        ise_altitude=state.cost[:, 1],
        effort=state.cost[:, 2],
        saturation=state.cost[:, 3],
        status=status,
        t_final=t_final,
        num_steps=ones * sol.stats["num_steps"],
        num_rejected_steps=ones * sol.stats["num_rejected_steps"],
        peak_attitude_error=peaks[:, 0],
        peak_altitude_error=peaks[:, 1],
        peak_saturation=peaks[:, 2],
    )


def _vmap(part: _Args, fixed: _Args, n, solver, rtol, atol, dtype, max_steps,
          n_save) -> BatchMetrics:
    del dtype  # simulate runs in the default float dtype

    def one(a):
        r = simulate(a.controller, a.scenario, a.vehicle, a.model, solver=solver, rtol=rtol,
                     atol=atol, n_save=n_save, max_steps=max_steps, limits=a.limits)
        if n_save:
            samples = jax.vmap(lambda e, u: sample_peaks(e, u, a.vehicle, a.model))(
                r.error, r.u_command)
            peaks = peaks_over_samples(r.ts, samples, r.t_final)
        else:
            peaks = jnp.full((3,), jnp.nan, r.t_final.dtype)
        return BatchMetrics(r.ise_attitude, r.ise_altitude, r.effort, r.saturation, r.status,
                            r.t_final, r.num_steps, r.num_rejected_steps, *peaks)

    return _per_case(one, part, fixed, n)


def _grouped_ensemble(group_size, part, fixed, n, *rest):
    if group_size is None or group_size >= n:
        return _ensemble(part, fixed, n, *rest)
    groups = n // group_size
    split = jax.tree.map(lambda x: x.reshape(groups, group_size, *x.shape[1:]), part)
    out = jax.vmap(lambda p: _ensemble(p, fixed, group_size, *rest), axis_size=groups)(split)
    return jax.tree.map(lambda x: x.reshape(n, *x.shape[2:]), out)


def _pad_cases(x, n_pad):
    if not n_pad:
        return x
    return jnp.concatenate([x, jnp.broadcast_to(x[:1], (n_pad, *x.shape[1:]))])


@eqx.filter_jit
def _run(part: _Args, fixed: _Args, n, strategy, solver, rtol, atol, dtype, max_steps,
         chunk_size, group_size, n_save, devices) -> BatchMetrics:
    """``part``: the leaves that differ between cases (leading axis n); ``fixed``: the leaves
    shared by every case (unbatched), so per-evaluation work on them is done once."""
    _TRACES["count"] += 1
    n_dev = len(devices)
    # layout: case i goes to device i // per_dev (consecutive blocks, so groups of consecutive
    # cases are the same with any device count when per_dev is a multiple of group_size); each
    # device pads its block with copies of case 0 to n_chunks chunks of `chunk` cases (a whole
    # number of groups); the padding is dropped at the end
    group = group_size or 1
    per_dev = -(-n // n_dev)
    chunk = per_dev if chunk_size is None else min(chunk_size, per_dev)
    chunk = -(-chunk // group) * group
    n_chunks = -(-per_dev // chunk)
    local_n = n_chunks * chunk

    def layout(x):
        x = _pad_cases(x, n_dev * per_dev - n).reshape(n_dev, per_dev, *x.shape[1:])
        if local_n > per_dev:
            fill = jnp.broadcast_to(x[:1, :1], (n_dev, local_n - per_dev, *x.shape[2:]))
            x = jnp.concatenate([x, fill], axis=1)
        return x.reshape(n_dev * local_n, *x.shape[2:])

    def unlayout(x):
        return x.reshape(n_dev, local_n, *x.shape[1:])[:, :per_dev].reshape(
            n_dev * per_dev, *x.shape[1:])[:n]

    def solve(p, fx):
        args = (p, fx, chunk, solver, rtol, atol, np.dtype(dtype), max_steps, n_save)
        if strategy == "ensemble":
            return _grouped_ensemble(group_size, *args)
        return _vmap(*args)

    def local(p, fx):
        # this device's cases, as consecutive chunks inside the one compiled program
        if n_chunks == 1:
            return solve(p, fx)
        split = jax.tree.map(lambda x: x.reshape(n_chunks, chunk, *x.shape[1:]), p)
        # map over chunk indices (not over `split`, which is empty when every leaf is shared)
        out = jax.lax.map(lambda i: solve(jax.tree.map(lambda x: x[i], split), fx),
                          jnp.arange(n_chunks))
        return jax.tree.map(lambda x: x.reshape(n_chunks * chunk, *x.shape[2:]), out)

    part = jax.tree.map(layout, part)
    if n_dev == 1:
        out = local(part, fixed)
    else:
        from jax.sharding import Mesh, PartitionSpec

        mesh = Mesh(np.asarray(devices), ("cases",))
        # each device solves its own cases: no collective inside the solve (check_vma=False:
        # diffrax's while-loop carries start unvarying and become device-varying)
        out = jax.shard_map(local, mesh=mesh, in_specs=(PartitionSpec("cases"), PartitionSpec()),
                            out_specs=PartitionSpec("cases"), check_vma=False)(part, fixed)
    return jax.tree.map(unlayout, out)


_TREES = (("controller", "controller"), ("scenarios", "scenario"), ("vehicles", "vehicle"),
          ("models", "model"))
"""(`simulate_batch` argument, `_Args` field) of the inputs that may carry the case axis."""


def _partition_cases(args: _Args, axes: dict) -> tuple[_Args, _Args]:
    """Split the inputs into leaves that differ between cases (leading axis = cases) and leaves that
    are the same for every case (their first row, unbatched). Equality is checked on concrete
    values; traced leaves of a batched input count as differing."""
    def batched(x):
        c = concrete(x)
        if c is None or np.ndim(c) == 0:
            return True
        return not np.array_equal(c, np.broadcast_to(c[:1], c.shape), equal_nan=True)

    specs = _Args(limits=False, **{
        attr: jax.tree.map(batched, getattr(args, attr)) if axes[name] == 0 else False
        for name, attr in _TREES})
    part, fixed = eqx.partition(args, specs)
    # the shared leaves of a batched input keep their first row
    fixed = _Args(limits=fixed.limits, **{
        attr: jax.tree.map(lambda x: x[0], getattr(fixed, attr)) if axes[name] == 0
        else getattr(fixed, attr) for name, attr in _TREES})
    return part, fixed


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
    group_size: int | None = None,
    n_save: int = 0,
    devices=None,
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
            ``ensemble_f32_chunked`` rows). None (default): one chunk per device.
        group_size: ``"ensemble"`` only: groups of this many cases are separate ensembles (own
            step sequences), vectorised with ``jax.vmap``; for cases with different jump times
            (module docstring). None (default): the whole chunk is one ensemble.
        n_save: number of equally spaced samples for the peak metrics (0: no peaks, NaN).
        devices: sequence of devices to split the case axis over (``jax.shard_map``); None
            (default): all local devices of the default backend.

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
    for name, v in (("chunk_size", chunk_size), ("group_size", group_size)):
        if v is not None and (isinstance(v, bool) or int(v) <= 0):
            raise ValueError(f"simulate_batch: {name} must be an integer > 0 or None, got {v!r}.")
    if group_size is not None and strategy != "ensemble":
        raise ValueError("simulate_batch: group_size applies to strategy 'ensemble' only.")
    if isinstance(n_save, bool) or int(n_save) < 0 or int(n_save) == 1:
        raise ValueError(f"simulate_batch: n_save must be 0 or >= 2, got {n_save!r}.")
    devices = tuple(jax.local_devices() if devices is None else devices)
    if not devices:
        raise ValueError("simulate_batch: devices must not be empty.")
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
    n = int(np.shape(scenarios.t0)[0])
    args = _cast(_Args(controller, scenarios, vehicles, models, limits), dtype)
    part, fixed = _partition_cases(args, axes)
    return _run(part, fixed, n, strategy, get_solver(solver), float(rtol), float(atol),
                dtype.name, int(max_steps), None if chunk_size is None else int(chunk_size),
                None if group_size is None else int(group_size), int(n_save), devices)
