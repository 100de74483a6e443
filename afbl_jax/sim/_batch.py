"""Batched closed-loop solving: many cases per compiled call (`simulate_batch`).

Strategies:

- ``"vmap"``: ``jax.vmap`` over `simulate`. Every case has its own adaptive step sequence;
  under vmap the batched ``while_loop`` runs until the slowest case is done, and each iteration
  pays diffrax's per-step bookkeeping for every lane.
- ``"ensemble"``: groups of cases solved as ONE ODE system each (`afbl_jax.sim.solve_group`:
  shared steps, every case meeting its own tolerance, divergent cases frozen).

Both run every closed loop: the paper's, or any ``unmodeled`` settings (full plant, motor lag,
digital control with delay and noise). With digital control each ensemble group needs one
control rate (its cases share their sample instants): `simulate_batch` checks this on concrete
values and says which cases differ.

``group_size`` (ensemble only) splits the batch into groups of that many consecutive cases, each
its own ensemble, the groups vectorised with ``jax.vmap``. Groups matter when cases have
*different* jump times (Monte-Carlo cases: random pulse and payload times): one ensemble of N
such cases steps onto all of their jump times, a group only onto its own few.

``chunk_size`` splits each device's cases into consecutive chunks solved one after the other
inside the same compiled call (``jax.lax.map``): smaller working sets stay in cache.

Devices: the case axis is split over ``devices`` (default: all local devices of the default
backend) with ``jax.shard_map``; every device solves its own cases independently (no
communication per step). On a CPU, XLA exposes one device unless
``XLA_FLAGS=--xla_force_host_platform_device_count=K`` is set before JAX starts
(`afbl_jax.configure_cpu_devices`). Case i goes to device i // ceil(N / devices); each device's
block is padded with copies of its last case to a whole number of chunks; padding is dropped.

Case-invariant inputs are hoisted: every input leaf equal in every case (checked on concrete
values) is passed unbatched, so it is evaluated once per vector-field call for the whole batch.

Both strategies compile once per (strategy, solver, tolerances, dtype, batch shapes, devices):
chunks of the same size reuse the compiled program.
"""

from __future__ import annotations

import functools
import threading
from typing import Literal

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._validation import check_positive, concrete
from ..metrics import BatchMetrics, metrics_from_result
from ..model import (
    AbstractAerodynamics,
    AbstractController,
    PositionHold,
    QuadrotorParams,
    UnmodeledDynamics,
)
from ..scenario import Scenario
from ._closed_loop import CaseInputs, ClosedLoop, DivergenceLimits
from ._ensemble import INTEGRATORS, EnsembleField, solve_group
from ._executables import CachedJit
from ._solve import get_solver, simulate

STRATEGIES = ("vmap", "ensemble")
"""Batched-solving strategies accepted by `simulate_batch`."""
FIRST_STEP = 1e-3
"""First step [s] of every ensemble group (`simulate_batch`'s default ``dt0``). The step-size
controller adapts from it as from any rejected or accepted step (a step too large is
rejected and shrunk, one too small grows by up to a factor 10 per step), so it costs a case a
few steps. diffrax's initial-step heuristic instead (``dt0=None``) evaluates the vector field
twice before the first step, which puts a further copy of the closed loop into the compiled
program."""


def _vmap(part, fixed, n, solver, rtol, atol, dtype, max_steps, n_save, integrator) -> BatchMetrics:
    del dtype, integrator  # simulate runs diffeqsolve in the default float dtype

    def one(p):
        loop, inputs = eqx.combine(p, fixed)
        r = simulate(
            loop,
            inputs.scenario,
            inputs.vehicle,
            inputs.model,
            solver=solver,
            rtol=rtol,
            atol=atol,
            n_save=n_save,
            max_steps=max_steps,
            limits=inputs.limits,
        )
        return metrics_from_result(r, inputs.vehicle, inputs.model)

    return jax.vmap(one, axis_size=n)(part)


def _ensemble(group_size, part, fixed, n, *rest, lanes=None, dt0=None) -> BatchMetrics:
    return solve_group(
        part,
        fixed,
        n,
        *rest,
        group_size=None if group_size is None else min(group_size, n),
        lanes=lanes,
        dt0=dt0,
    )


QUEUE_POOL_CHUNKS = 16
"""With the work queue, at most this many chunks' cases share one queue (the pool's stored
states grow with it); a device with more chunks runs its pools one after the other."""


def _pool_chunks(n_chunks: int) -> int:
    """Chunks per work-queue pool: the largest divisor of ``n_chunks`` <= `QUEUE_POOL_CHUNKS`."""
    return max(k for k in range(1, min(n_chunks, QUEUE_POOL_CHUNKS) + 1) if n_chunks % k == 0)


def case_layout(n: int, n_dev: int, chunk_size: int | None, group: int):
    """(index array, chunk, chunks per device, per-device cases): position j of the laid-out
    batch holds case ``index[j]``; device d gets positions [d L, (d + 1) L), L = chunks x chunk,
    its real cases first, then copies of its last case."""
    per_dev = -(-n // n_dev)
    chunk = per_dev if chunk_size is None else min(chunk_size, per_dev)
    chunk = -(-chunk // group) * group
    n_chunks = -(-per_dev // chunk)
    local = n_chunks * chunk
    index = np.empty(n_dev * local, dtype=np.int64)
    for d in range(n_dev):
        real = np.arange(d * per_dev, min((d + 1) * per_dev, n))
        if real.size == 0:
            real = np.array([n - 1])
        index[d * local : (d + 1) * local] = np.concatenate(
            [real, np.full(local - real.size, real[-1])]
        )
    return index, chunk, n_chunks, per_dev


def _run(
    part,
    fixed,
    n,
    strategy,
    solver,
    rtol,
    atol,
    dtype,
    max_steps,
    chunk_size,
    group_size,
    n_save,
    devices,
    integrator,
    work_queue=True,
    dt0=None,
) -> BatchMetrics:
    """``part``: the leaves that differ between cases (leading axis n); ``fixed``: the leaves
    shared by every case (unbatched), so per-evaluation work on them is done once."""
    n_dev = len(devices)
    index, chunk, n_chunks, per_dev = case_layout(n, n_dev, chunk_size, group_size or 1)
    local_n = n_chunks * chunk
    digital = eqx.combine(part, fixed)[0].digital
    queue = (
        work_queue
        and strategy == "ensemble"
        and integrator == "lean"
        and group_size is not None
        and not digital
        and n_chunks > 1
    )
    # with the work queue, a pool of chunks is one solve whose lanes are one chunk's groups
    size = chunk * (_pool_chunks(n_chunks) if queue else 1)
    n_solves = n_chunks * chunk // size

    def solve(p, fx):
        args = (p, fx, size, solver, rtol, atol, np.dtype(dtype), max_steps, n_save, integrator)
        if strategy == "ensemble":
            lanes = chunk // group_size if queue else None
            return _ensemble(group_size, *args, lanes=lanes, dt0=dt0)
        return _vmap(*args)

    def local(p, fx):
        # this device's cases, as consecutive chunks (or pools) inside the one compiled program
        if n_solves == 1:
            return solve(p, fx)
        split = jax.tree.map(lambda x: x.reshape(n_solves, size, *x.shape[1:]), p)
        if jax.tree.leaves(split):
            # scanned over the chunks' inputs: each chunk's slice is materialised once (a
            # dynamic index inside the solve would be re-read at every use)
            out = jax.lax.map(lambda q: solve(q, fx), split)
        else:  # every leaf is shared: map over chunk indices
            out = jax.lax.map(lambda i: solve(split, fx), jnp.arange(n_solves))
        return jax.tree.map(lambda x: x.reshape(n_solves * size, *x.shape[2:]), out)

    part = jax.tree.map(lambda x: x[index], part)
    if n_dev == 1:
        out = local(part, fixed)
    else:
        from jax.sharding import Mesh, PartitionSpec

        mesh = Mesh(np.asarray(devices), ("cases",))
        # each device solves its own cases: no collective inside the solve (check_vma=False:
        # diffrax's while-loop carries start unvarying and become device-varying)
        out = jax.shard_map(
            local,
            mesh=mesh,
            in_specs=(PartitionSpec("cases"), PartitionSpec()),
            out_specs=PartitionSpec("cases"),
            check_vma=False,
        )(part, fixed)
    first = np.concatenate(
        [d * local_n + np.arange(max(0, min(per_dev, n - d * per_dev))) for d in range(n_dev)]
    )
    return jax.tree.map(lambda x: x[first], out)


CPU_COMPILER_OPTIONS: dict[str, object] = {
    "xla_cpu_copy_insertion_use_region_analysis": True,
    "xla_cpu_experimental_ynn_fusion_type": "LIBRARY_FUSION_TYPE_DOT",
    "xla_disable_hlo_passes": "cse_barrier_expander",
}
"""XLA options the batched solves are compiled with where the installed XLA has them:

- copy insertion by region analysis drops the copies of the Runge-Kutta stage buffers that the
  while loops carry (bitwise the same results);
- XLA's YNNPACK library fusions for dot products only: XLA's CPU backend also hands
  reductions to YNNPACK by default, and on an ensemble's reductions (the error norm over the
  cases, the per-case sums of the vector field) that is one library call per small sum instead
  of XLA's own fused loop. The sums then run in XLA's order, so results differ from the
  default compilation by rounding only;
- optimization barriers kept until code generation (XLA's ``cse_barrier_expander`` pass, which
  removes them before fusion, disabled): XLA's CPU fusion recomputes an expensive value such as
  a sine inside every fused consumer, and a barrier is the one way to have it computed once
  (`afbl_jax.model.cos_sin`: the Euler angles' cosines and sines, 3 + 3 per evaluation
  instead of 8-20; the controller's output, ``ClosedLoop.signals_and_derivative(...,
  materialise=True)``). Barriers are identities: on the benchmark's cases every metric is
  bitwise the same as without this option (tested); on Monte-Carlo cases the differently fused
  turbulence sum rounds differently (at most one float64 ulp in the field), so solves agree to
  the solver's tolerance. The docs' benchmark page describes their effect."""


@functools.cache
def batch_compiler_options(platform: str = "cpu") -> dict[str, object]:
    """The XLA options `simulate_batch` compiles with on devices of ``platform``: on CPUs,
    those of `CPU_COMPILER_OPTIONS` that this jax and XLA know (checked once, on a trivial
    program, all together and one by one where that fails); on other platforms none (the
    options concern XLA's CPU backend)."""
    if platform != "cpu":
        return {}
    x = jax.device_put(np.float32(0.0), jax.devices("cpu")[0])

    def compiles(options):
        try:
            jax.jit(lambda x: x + 1, compiler_options=options)(x)
        except Exception:  # an option (or jit's compiler_options) this version does not have
            return False
        return True

    # all at once first (one trivial program), then one by one where that fails
    if compiles(CPU_COMPILER_OPTIONS):
        return dict(CPU_COMPILER_OPTIONS)
    return {key: value for key, value in CPU_COMPILER_OPTIONS.items() if compiles({key: value})}


_plain_run = eqx.filter_jit(_run)
"""`_run` jitted with XLA's defaults (and inside another jit, where options are refused)."""


_compiled_runs: dict[str, CachedJit] = {}
_compiled_runs_lock = threading.Lock()


def _compiled_run(platform: str = "cpu") -> CachedJit:
    """`_run` jitted with `batch_compiler_options` of ``platform`` (one per platform, also
    when several threads ask at once)."""
    with _compiled_runs_lock:
        if platform not in _compiled_runs:
            _compiled_runs[platform] = CachedJit(
                _run, "simulate_batch", batch_compiler_options(platform)
            )
        return _compiled_runs[platform]


def _leading(x) -> int | None:
    return None if np.ndim(x) == 0 else int(np.shape(x)[0])


def _batch_axes(
    controller, scenarios, vehicles, models, unmodeled, position_loop=None
) -> tuple[int, dict]:
    n = _leading(scenarios.t0)
    if n is None:
        raise ValueError(
            "simulate_batch: scenarios must be batched (leading axis = cases; use "
            "stack_scenarios), got an unbatched Scenario."
        )
    axes = {"scenarios": True}
    probes = [
        ("vehicles", vehicles, lambda p: p.m, 0),
        ("models", models, lambda p: p.m, 0),
        ("controller", controller, lambda c: getattr(c, c.gain_names[0]), 1),
    ]
    if unmodeled is not None:
        probes.append(("unmodeled", unmodeled, lambda u: u.motor_tau, 0))
    if position_loop is not None:
        probes.append(("position_loop", position_loop, lambda p: p.tilt_max, 0))
    for name, tree, probe, base_ndim in probes:
        leaf = probe(tree)
        if np.ndim(leaf) == base_ndim:
            axes[name] = False
        elif np.ndim(leaf) == base_ndim + 1 and np.shape(leaf)[0] == n:
            axes[name] = True
        else:
            raise ValueError(
                f"simulate_batch: {name} must be unbatched or have leading axis {n} (the number "
                f"of scenarios), got a leaf of shape {np.shape(leaf)}."
            )
    axes.setdefault("unmodeled", False)
    axes.setdefault("position_loop", False)
    return n, axes


def _cast(tree, dtype):
    """Floating leaves cast to ``dtype``; concrete leaves on the host (NumPy rounds as XLA does),
    so the cast compiles no small device program per leaf shape."""

    def cast(x):
        if not jnp.issubdtype(jnp.result_type(x), jnp.floating):
            return x
        c = concrete(x)
        return x.astype(dtype) if c is None else c.astype(dtype, copy=False)

    return jax.tree.map(cast, tree)


def _first_row(x):
    c = concrete(x)
    return x[0] if c is None else c[0]


def _partition_cases(args, batched_mask):
    """Split ``args`` into leaves that differ between cases (leading axis = cases) and leaves
    that are the same for every case (their first row, unbatched). ``batched_mask``: a pytree
    of bools, True for leaves with a case axis. Equality is checked on concrete values; traced
    batched leaves count as differing. When every case is the same, the first batched leaf
    stays in the differing part (it carries the case axis for the vectorised solve)."""

    def differs(x, batched):
        if not batched:
            return False
        c = concrete(x)
        if c is None or np.ndim(c) == 0:
            return True
        return not np.array_equal(c, np.broadcast_to(c[:1], c.shape), equal_nan=True)

    specs = jax.tree.map(differs, args, batched_mask)
    leaves, treedef = jax.tree.flatten(specs)
    if not any(leaves):  # identical cases: keep one batched leaf per case (the case axis)
        batched = jax.tree.leaves(jax.tree.map(lambda _, b: b, args, batched_mask))
        if any(batched):
            leaves[batched.index(True)] = True
            specs = jax.tree.unflatten(treedef, leaves)
    part, fixed = eqx.partition(args, specs)
    fixed = jax.tree.map(  # the first row: sliced on the host where concrete (no device program)
        lambda x, b: _first_row(x) if (b and x is not None) else x,
        fixed,
        batched_mask,
        is_leaf=lambda x: x is None,
    )
    return part, fixed


def _check_group_rates(
    loop: ClosedLoop, batched: bool, n: int, n_dev: int, chunk_size, group_size
) -> None:
    if not (loop.digital and batched):
        return
    rate = concrete(loop.sampling.control_rate)
    if rate is None:
        return
    index, chunk, _, _ = case_layout(n, n_dev, chunk_size, group_size or 1)
    group = group_size or chunk
    laid = rate[index].reshape(-1, group)
    bad = np.nonzero(~np.all(laid == laid[:, :1], axis=1))[0]
    if bad.size:
        cases = sorted(set(index.reshape(-1, group)[bad[0]].tolist()))
        raise ValueError(
            f"simulate_batch: the cases of an ensemble group share their control sample "
            f"instants, but cases {cases} of one group have control rates "
            f"{sorted(set(rate[cases].tolist()))} Hz; give each group of {group} consecutive "
            f"cases one rate (or use strategy='vmap')."
        )


def _split_cases(loop: ClosedLoop, scenarios, vehicles, models, limits, axes, dtype):
    """(part, fixed) of the batch's (loop, inputs) cast to ``dtype``: the leaves that differ
    between cases (leading axis n) and those shared by all (unbatched)."""
    inputs = CaseInputs(scenarios, vehicles, models, limits)
    mask = (
        ClosedLoop(
            jax.tree.map(lambda _: axes["controller"], loop.controller),
            *(
                jax.tree.map(lambda _: axes["unmodeled"], part)
                for part in (loop.plant, loop.actuators, loop.aerodynamics, loop.sampling)
            ),
            jax.tree.map(lambda _: axes["position_loop"], loop.position_loop),
        ),
        CaseInputs(
            jax.tree.map(lambda _: True, scenarios),
            jax.tree.map(lambda _: axes["vehicles"], vehicles),
            jax.tree.map(lambda _: axes["models"], models),
            jax.tree.map(lambda _: False, limits),
        ),
    )
    args = _cast((loop, inputs), dtype)
    return _partition_cases(args, mask)


def ensemble_vector_field(
    controller: AbstractController,
    scenarios: Scenario,
    vehicles: QuadrotorParams | None = None,
    models: QuadrotorParams | None = None,
    *,
    unmodeled: UnmodeledDynamics | None = None,
    aerodynamics: AbstractAerodynamics | str | None = None,
    dtype=None,
    group_size: int | None = None,
    limits: DivergenceLimits | None = None,
    position_loop: PositionHold | None = None,
) -> EnsembleField:
    """The vector field `simulate_batch` (``strategy="ensemble"``, lean integrator, one
    device, one chunk) evaluates on these cases, as an `EnsembleField` (call it on a state
    with the case axis last: ``field(t, field.initial_state(dtype))``). Arguments as in
    `simulate_batch`; ``group_size`` None: one group. For profiling the closed loop on real
    batches (`benchmarks/vector_field.py`); continuous control only."""
    vehicles = QuadrotorParams() if vehicles is None else vehicles
    models = vehicles if models is None else models
    limits = DivergenceLimits() if limits is None else limits
    default = jnp.result_type(float)
    dtype = np.dtype(default if dtype is None else dtype)
    n, axes = _batch_axes(controller, scenarios, vehicles, models, unmodeled, position_loop)
    loop = ClosedLoop.make(controller, unmodeled, aerodynamics, position_loop)
    if loop.digital:
        raise ValueError(
            "ensemble_vector_field: continuous control only (the held command of digital "
            "control is a discrete state of the solve); got digital control."
        )
    part, fixed = _split_cases(loop, scenarios, vehicles, models, limits, axes, dtype)
    return EnsembleField(part, fixed, n, n if group_size is None else int(group_size))


def simulate_batch(
    controller: AbstractController,
    scenarios: Scenario,
    vehicles: QuadrotorParams | None = None,
    models: QuadrotorParams | None = None,
    *,
    unmodeled: UnmodeledDynamics | None = None,
    aerodynamics: AbstractAerodynamics | str | None = None,
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
    integrator: Literal["lean", "diffeqsolve"] = "lean",
    work_queue: bool = True,
    position_loop: PositionHold | None = None,
    dt0: float | None = FIRST_STEP,
) -> BatchMetrics:
    """Simulate N cases in one compiled call; returns per-case `BatchMetrics`.

    Args:
        controller: one controller (shared) or a batch (gains with leading axis N).
        scenarios: batch of N scenarios (`stack_scenarios`, or fields with leading axis N).
        vehicles: true vehicles, batched (leading axis N) or one shared (default Table 1).
        models: controller models, batched or shared (default: ``vehicles``).
        unmodeled: `UnmodeledDynamics`, shared or batched (`stack_unmodeled`); None: the
            paper's closed loop. With digital control and ``"ensemble"``, every group's cases
            must share one control rate.
        aerodynamics: aerodynamic model (name or instance, as in `simulate`; shared by all
            cases, its coefficients batched with the vehicles); None: `LinearDrag`.
        strategy: ``"ensemble"`` (groups of cases as one ODE system each; default) or
            ``"vmap"``.
        solver: diffrax solver or name (as in `simulate`).
        rtol, atol: tolerances; with ``"ensemble"`` every case meets them (max-over-cases norm).
        dtype: floating dtype of the solve (default: JAX's default float). ``"vmap"`` supports
            only the default float dtype.
        max_steps: step budget (for ``"ensemble"``: shared by a group; per sample interval with
            digital control).
        limits: divergence limits (default `DivergenceLimits()`).
        chunk_size: each device solves its cases this many at a time inside the one compiled
            call (``jax.lax.map``). None (default): one chunk per device.
        group_size: ``"ensemble"`` only: groups of this many consecutive cases are separate
            ensembles (own step sequences), vectorised with ``jax.vmap``. None (default): the
            whole chunk is one ensemble.
        n_save: number of equally spaced samples for the peak metrics (0: no peaks, NaN).
        devices: sequence of devices to split the case axis over (``jax.shard_map``); None
            (default): all local devices of the default backend.
        integrator: ``"ensemble"`` only: ``"lean"`` (default; `afbl_jax.sim.lean_loop`, our
            while loop over diffrax's solver step and step-size controller: fastest, not
            reverse-mode differentiable) or ``"diffeqsolve"`` (`diffrax.diffeqsolve`; use it
            for `jax.grad` through the ensemble). Both take the same steps and agree case by
            case.
        work_queue: ``"lean"`` with ``group_size``, continuous control and more than one chunk
            per device: a chunk's groups are the lanes of a work queue over the device's
            cases (up to `QUEUE_POOL_CHUNKS` chunks per queue): a group that is done hands its
            lane to the next group instead of the chunk waiting for its slowest group. The
            results are bitwise those of the chunks one after the other (False).
        position_loop: the outer position loop (`afbl_jax.model.PositionHold`, shared or
            batched: gains with leading axis N), as in `simulate`; None: none.
        dt0: ``"ensemble"`` only: every group's first step [s] (default `FIRST_STEP`); None:
            diffrax's initial-step heuristic (`diffrax.PIDController.init`). With digital
            control and ``integrator="diffeqsolve"`` every sample interval starts with the
            whole interval whatever ``dt0``.

    Never raises for failed or diverged cases; check ``status``.
    """
    if strategy not in STRATEGIES:
        raise ValueError(f"unknown strategy {strategy!r}; allowed: {', '.join(STRATEGIES)}.")
    if not isinstance(controller, AbstractController):
        raise TypeError(
            f"simulate_batch: controller must be an AbstractController, got "
            f"{type(controller).__name__} (give unmodeled settings separately)."
        )
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
    if dt0 is not None and (isinstance(dt0, bool) or not float(dt0) > 0):
        raise ValueError(f"simulate_batch: dt0 must be a step > 0 [s] or None, got {dt0!r}.")
    if integrator not in INTEGRATORS:
        raise ValueError(
            f"simulate_batch: unknown integrator {integrator!r}; allowed: {', '.join(INTEGRATORS)}."
        )
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
        raise ValueError(
            f"simulate_batch: strategy 'vmap' runs in the default float dtype "
            f"({default}); got dtype {dtype}. Use strategy='ensemble'."
        )
    if position_loop is not None and not isinstance(position_loop, PositionHold):
        raise TypeError(
            f"simulate_batch: position_loop must be a PositionHold or None, got "
            f"{type(position_loop).__name__}."
        )
    n, axes = _batch_axes(controller, scenarios, vehicles, models, unmodeled, position_loop)
    if strategy == "ensemble":
        for name in ("t0", "t1"):
            v = concrete(getattr(scenarios, name))
            if v is not None and not np.all(v == v.reshape(-1)[0]):
                raise ValueError(
                    f"simulate_batch: strategy 'ensemble' needs one {name} for all "
                    f"cases, got values from {v.min()} to {v.max()} [s]."
                )
    loop = ClosedLoop.make(controller, unmodeled, aerodynamics, position_loop)
    if strategy == "ensemble":
        _check_group_rates(
            loop,
            axes["unmodeled"],
            n,
            len(devices),
            None if chunk_size is None else int(chunk_size),
            None if group_size is None else int(group_size),
        )
    part, fixed = _split_cases(
        loop.shared_program(), scenarios, vehicles, models, limits, axes, dtype
    )
    traced = any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves((part, fixed)))
    # compiler options apply to a top-level compilation only (not inside another jit)
    run = _plain_run if traced else _compiled_run(devices[0].platform)
    return run(
        part,
        fixed,
        n,
        strategy,
        get_solver(solver),
        float(rtol),
        float(atol),
        dtype.name,
        int(max_steps),
        None if chunk_size is None else int(chunk_size),
        None if group_size is None else int(group_size),
        int(n_save),
        devices,
        integrator,
        bool(work_queue),
        None if dt0 is None else float(dt0),
    )
