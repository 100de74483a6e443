"""Ensembles: groups of cases, each solved as ONE ODE system with one shared step sequence.

A group's step-size control uses `ensemble_rms_norm`, the maximum over its cases of each case's
RMS scaled error, so every case meets its own tolerance on every step, and the vector field is
evaluated for all cases at once. `solve_group` solves n cases in groups of ``group_size``
consecutive cases (each group its own steps) with one of two integrators (`INTEGRATORS`):

- ``"lean"`` (default): `afbl_jax.sim.lean_loop`, our while loop over diffrax's solver step
  and step-size controller, all groups advanced together on one state whose leaves have the
  case axis last. Divergence: after every accepted step each case is tested
  (`ClosedLoop.diverged_at`); a case past the limits (or non-finite) is frozen from then on
  (zero derivatives: its cost integrals stop, it cannot stall its group's step size), its
  status is ``diverged`` and it ends at the end of that step, as `simulate`'s divergence
  event stops a single run. Peaks: the states at the save times inside each accepted step,
  from diffrax's dense interpolation, are stored and the peak samples (reference error and
  the controller's command) computed from them after the loop, once per save time rather than
  once per step (digital control: the states at the sample instants, linearly interpolated,
  and the held command, as `simulate`, folded into running maxima,
  `afbl_jax.metrics.fold_peaks`). Digital control: a group's steps land on its sample
  instants (the held command jumps there); a step ending on one runs
  `afbl_jax.sim.sample_instant` for the group's cases. Not reverse-mode differentiable.
- ``"diffeqsolve"``: `diffrax.diffeqsolve` per group (groups vectorised with `jax.vmap`),
  differentiable with `jax.grad` (diffrax's checkpointed adjoint). Divergence freezes a case
  inside the vector field (any stage past the limits), made persistent by an extra per-case
  state growing at rate 1 while frozen (``t_final = t_stop - frozen_time``). Peaks: diffrax
  ``SubSaveAt(ts, fn)`` keeping three numbers per case and save time (digital: the states at
  the sample instants, interpolated), then `afbl_jax.metrics.peaks_over_samples`. Digital
  control: a scan over the sample instants with one ensemble solve per sample interval.

Both control the step on the closed-loop state only and start from diffrax's initial-step
heuristic, so on cases that do not diverge they take the same steps (tested to agree to
round-off). In both, the steps land on the union of the group's jump times.
"""

from __future__ import annotations

from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._typing import Array
from ..metrics import (
    N_PEAKS,
    BatchMetrics,
    finish_peaks,
    fold_peaks,
    no_peaks,
    peaks_over_samples,
    sample_peaks,
)
from ._closed_loop import ClosedLoopState
from ._digital import held_index, initial_buffer, interpolate, sample_instant, sample_time
from ._lean import Groups, ensemble_field, lean_loop
from ._solve import step_size_controller
from ._status import STATUS_DIVERGED, STATUS_MAX_STEPS, STATUS_OK, status_from

INTEGRATORS = ("lean", "diffeqsolve")
"""How an ensemble is integrated: ``"lean"`` (`afbl_jax.sim.lean_loop` over diffrax's solver
step and step-size controller; fastest, not reverse-mode differentiable) or ``"diffeqsolve"``
(`diffrax.diffeqsolve`; differentiable with `jax.grad`)."""


def ensemble_rms_norm(tree, case_axis: int = 0) -> Array:
    """Max over cases (axis ``case_axis``: 0, the leading axis, or -1, the last) of each
    case's RMS over all its other entries.

    Used as the `diffrax.PIDController` norm of the ensemble: the shared step is accepted only
    when every case's own RMS scaled error is below 1. Non-finite errors stay non-finite (the
    step is rejected).
    """
    if case_axis not in (0, -1):
        raise ValueError(f"case_axis must be 0 or -1, got {case_axis!r}.")
    leaves = [x if case_axis == 0 else jnp.moveaxis(x, -1, 0) for x in jax.tree.leaves(tree)]
    sq = sum(jnp.sum(jnp.reshape(x, (x.shape[0], -1)) ** 2, axis=1) for x in leaves)
    count = sum(int(np.prod(x.shape[1:])) for x in leaves)
    return jnp.sqrt(jnp.max(sq) / count)


def _last_axis_norm(tree) -> Array:
    return ensemble_rms_norm(tree, case_axis=-1)


def _per_case(fn, part, fixed, n):
    """``fn(loop, inputs)`` for every case, leading axis n."""
    return jax.vmap(lambda p: fn(*eqx.combine(p, fixed)), axis_size=n)(part)


def _shared_or_per_case(fn, part, fixed, n):
    """``fn(loop, inputs)`` once (unbatched) if it does not depend on the batched leaves, else
    for every case (leading axis n)."""
    try:
        return jax.vmap(lambda p: fn(*eqx.combine(p, fixed)), axis_size=n, out_axes=None)(part)
    except ValueError:  # the result depends on batched leaves
        return _per_case(fn, part, fixed, n)


def union_jump_times(part, fixed, n, dtype) -> Array:
    """Sorted union of the cases' jump times (duplicates kept: a fixed shape per batch shape,
    so chunks never recompile; diffrax's ClipStepSizeController steps onto each distinct time
    once). Shared jump times are taken once."""
    jumps = _shared_or_per_case(lambda loop, inp: inp.scenario.jump_times(), part, fixed, n)
    return jnp.sort(jumps.reshape(-1)).astype(dtype)


def _field(part, fixed, n):
    """The ensemble vector field on (ClosedLoopState (n, ...), frozen time (n,)); args = held
    commands (leading axis n) or None."""

    def one_case(t, state, frozen_time, p, held):
        loop, inputs = eqx.combine(p, fixed)
        signals, dstate = loop.signals_and_derivative(t, state, inputs, held)
        bad = ~jnp.all(jnp.stack([jnp.all(jnp.isfinite(d)) for d in jax.tree.leaves(dstate)]))
        frozen = loop.diverged(state, signals.error[3], inputs) | bad | (frozen_time > 0)
        dstate = jax.tree.map(lambda d: jnp.where(frozen, jnp.zeros_like(d), d), dstate)
        return dstate, jnp.where(frozen, jnp.ones_like(frozen_time), jnp.zeros_like(frozen_time))

    def field(t, y, held):
        state, frozen_time = y
        held_axis = None if held is None else 0
        return jax.vmap(one_case, in_axes=(None, 0, 0, 0, held_axis), axis_size=n)(
            t, state, frozen_time, part, held
        )

    return field


def _anatomy(part, fixed, state, t_final, status):
    """(failure cause, final saturation) of every case (`ClosedLoop.anatomy`), from its end
    state (leaves with the case axis first)."""

    def one(p, y, t, st):
        loop, inputs = eqx.combine(p, fixed)
        return loop.anatomy(t, y, st, inputs)

    return jax.vmap(one)(part, state, t_final, status)


def _metrics(part, fixed, state, t_final, status, steps, rejected, peaks) -> BatchMetrics:
    n = t_final.shape[0]
    ones = jnp.ones((n,), jnp.int32)
    cause, final_saturation = _anatomy(part, fixed, state, t_final, status)
    nan = jnp.full((n,), jnp.nan, state.cost.dtype)
    return BatchMetrics(
        ise_attitude=state.cost[:, 0],
        ise_altitude=state.cost[:, 1],
        effort=state.cost[:, 2],
        saturation=state.cost[:, 3],
        status=status,
        t_final=t_final,
        num_steps=ones * steps,
        num_rejected_steps=ones * rejected,
        peak_attitude_error=peaks[:, 0],
        peak_altitude_error=peaks[:, 1],
        peak_saturation=peaks[:, 2],
        ise_position=state.cost[:, 4] if state.cost.shape[1] > 4 else nan,
        peak_position_error=peaks[:, 3],
        failure_cause=cause,
        final_saturation=final_saturation,
    )


def solve_group(
    part,
    fixed,
    n,
    solver,
    rtol,
    atol,
    dtype,
    max_steps,
    n_save,
    integrator="lean",
    group_size=None,
    lanes=None,
    dt0=None,
) -> BatchMetrics:
    """The n cases of ``part`` ((ClosedLoop, CaseInputs) leaves with leading axis n, sharing
    ``fixed``: leaves equal for every case, unbatched, evaluated once per group) in groups of
    ``group_size`` consecutive cases (None: one group), each one ensemble; ``integrator``:
    one of `INTEGRATORS` (module docstring); ``lanes`` (``"lean"``, continuous control): groups
    advanced at a time, a finished group's lane taking the next group (`lean_loop`'s work
    queue); None: all groups at once. ``dt0``: every group's first step [s] (None: diffrax's
    initial-step heuristic); with digital control the diffeqsolve integrator ignores it and
    starts every sample interval with the whole interval."""
    if integrator not in INTEGRATORS:
        raise ValueError(f"unknown integrator {integrator!r}; allowed: {', '.join(INTEGRATORS)}.")
    g = n if group_size is None else int(group_size)
    if n % g:
        raise ValueError(f"solve_group: {n} cases do not split into groups of {g}.")
    groups = Groups(n // g, g)
    loop = eqx.combine(part, fixed)[0]  # static structure (digital or not, buffer sizes)
    t0 = _shared_or_per_case(lambda lp, inp: inp.scenario.t0, part, fixed, n).reshape(-1)[0]
    t1 = _shared_or_per_case(lambda lp, inp: inp.scenario.t1, part, fixed, n).reshape(-1)[0]
    part_g = jax.tree.map(lambda x: x.reshape(groups.count, g, *x.shape[1:]), part)
    if integrator == "lean":
        jumps = jax.vmap(lambda p: union_jump_times(p, fixed, g, dtype))(part_g)
        controllers = eqx.filter_vmap(
            lambda j: step_size_controller(rtol, atol, j, norm=_last_axis_norm)
        )(jumps)
        args = (part, part_g, fixed, groups, controllers, solver, t0, t1, dtype, max_steps, n_save)
        if loop.digital:
            return _lean_digital(*args, dt0=dt0)
        return _lean_continuous(*args, lanes=lanes, dt0=dt0)

    def one_group(p):
        state0 = _per_case(lambda lp, inp: lp.initial_state(inp, dtype), p, fixed, g)
        # the frozen time is bookkeeping: the step is controlled on the closed-loop state only
        stepsize = step_size_controller(
            rtol,
            atol,
            union_jump_times(p, fixed, g, dtype),
            norm=lambda y: ensemble_rms_norm(y[0]),
        )
        y0 = (state0, jnp.zeros((g,), dtype))
        args = (p, fixed, g, _field(p, fixed, g), stepsize, solver, t0, t1, y0, dtype)
        if loop.digital:
            return _digital(*args, max_steps, n_save)
        return _continuous(*args, max_steps, n_save, dt0)

    out = jax.vmap(one_group)(part_g)
    return jax.tree.map(lambda x: x.reshape(n, *x.shape[2:]), out)


def _first_step(field, stepsize, solver, t0, t1, y0, dt0=None):
    """The first step: ``dt0`` where given, else diffrax's initial step-size heuristic
    (`diffrax.PIDController.init`; `diffeqsolve` itself starts with 0.01 s, as its heuristic
    does not apply to the direction-wrapped term it integrates), so that `diffeqsolve` starts
    with the step `lean_loop` starts with."""
    if dt0 is not None:
        return jnp.asarray(dt0, jnp.result_type(t0))
    term = diffrax.ODETerm(field)
    t_next, _ = stepsize.controller.init(
        term, t0, t1, y0, None, None, solver.func, solver.error_order(term)
    )
    return t_next - t0


def _continuous(
    part, fixed, n, field, stepsize, solver, t0, t1, y0, dtype, max_steps, n_save, dt0=None
):
    subs = [diffrax.SubSaveAt(t1=True)]
    if n_save:
        ts = t0 + (t1 - t0) * jnp.linspace(0.0, 1.0, n_save, dtype=dtype)

        def one_sample(t, state, p):
            lp, inputs = eqx.combine(p, fixed)
            sig = lp.signals_and_derivative(t, state, inputs)[0]
            return sample_peaks(
                sig.error, sig.u_command, inputs.vehicle, inputs.model, sig.position_error
            )

        def save_peaks(t, y, args):
            return jax.vmap(one_sample, in_axes=(None, 0, 0), axis_size=n)(t, y[0], part)

        subs.append(diffrax.SubSaveAt(ts=ts, fn=save_peaks))
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(field),
        solver,
        t0,
        t1,
        _first_step(field, stepsize, solver, t0, t1, y0, dt0),
        y0,
        args=None,
        saveat=diffrax.SaveAt(subs=subs),
        stepsize_controller=stepsize,
        max_steps=max_steps,
        throw=False,
    )
    state, frozen_time = jax.tree.map(lambda a: a[-1], sol.ys[0])
    t_stop = sol.ts[0][-1]
    status = status_from(sol.result, frozen_time > 0)
    t_final = t_stop - frozen_time
    if n_save:
        peaks = jax.vmap(peaks_over_samples, in_axes=(None, 1, 0))(sol.ts[1], sol.ys[1], t_final)
    else:
        peaks = jnp.full((n, N_PEAKS), jnp.nan, dtype)
    return _metrics(
        part,
        fixed,
        state,
        t_final,
        status,
        sol.stats["num_steps"],
        sol.stats["num_rejected_steps"],
        peaks,
    )


def _digital(part, fixed, n, field, stepsize, solver, t0, t1, y0, dtype, max_steps, n_save):
    term = diffrax.ODETerm(field)
    loop = eqx.combine(part, fixed)[0]
    max_samples = loop.sampling.max_samples
    # the group's one control rate (equal in every case: checked by simulate_batch)
    h = _shared_or_per_case(
        lambda lp, inp: 1.0 / lp.sampling.control_rate.astype(dtype), part, fixed, n
    ).reshape(-1)[0]
    buf0 = jax.vmap(lambda p, y: initial_buffer(eqx.combine(p, fixed)[0], y), axis_size=n)(
        part, y0[0]
    )

    def sample_instant_case(p, yi, bi, k, t_k):
        lp, inputs = eqx.combine(p, fixed)
        return sample_instant(lp, k, t_k, yi, bi, inputs)

    def step(carry, k):
        (y, frozen_time), buf, result, t_reached, steps = carry
        t_k = sample_time(t0, h, k)
        alive = (result == STATUS_OK) & (t_k < t1)
        start = jnp.minimum(t_k, t1)
        end = jnp.where(alive, jnp.minimum(sample_time(t0, h, k + 1), t1), start)
        y_in, buf_new, held, dctrl = jax.vmap(
            sample_instant_case, in_axes=(0, 0, 0, None, None), axis_size=n
        )(part, y, buf, k, t_k)
        sol = diffrax.diffeqsolve(
            term,
            solver,
            start,
            end,
            end - start,
            (y_in, frozen_time),
            args=held,
            saveat=diffrax.SaveAt(t1=True),
            stepsize_controller=stepsize,
            max_steps=max_steps,
            throw=False,
        )
        y_end, frozen_end = jax.tree.map(lambda a: a[-1], sol.ys)
        frozen = (frozen_end > 0)[:, None]
        controller = jnp.where(frozen, y_end.controller, y.controller + h * dctrl)
        y_end = eqx.tree_at(lambda s: s.controller, y_end, controller)
        # a failed interval solve stops the whole group where it stopped
        interval = jnp.where(
            sol.result == diffrax.RESULTS.successful, STATUS_OK, status_from(sol.result, False)
        )
        new = (
            jax.tree.map(
                lambda a, b: jnp.where(alive, a, b), (y_end, frozen_end), (y, frozen_time)
            ),
            jax.tree.map(lambda a, b: jnp.where(alive, a, b), buf_new, buf),
            jnp.where(alive, interval, result),
            jnp.where(alive, sol.ts[-1], t_reached),
            steps
            + jnp.where(
                alive, jnp.stack([sol.stats["num_steps"], sol.stats["num_rejected_steps"]]), 0
            ),
        )
        out = (peak_inputs(new[0][0]), held.u_command, new[3]) if n_save else None
        return new, out

    def peak_inputs(y):
        """`ClosedLoop.peak_inputs` of every case (leading axis n)."""
        return jax.vmap(lambda yy: loop.peak_inputs(yy.plant, yy.controller))(y)

    carry0 = (y0, buf0, jnp.asarray(STATUS_OK, jnp.int32), t0, jnp.zeros(2, jnp.int32))
    ((state, frozen_time), _, result, t_reached, steps), outs = jax.lax.scan(
        step, carry0, jnp.arange(max_samples, dtype=jnp.int32)
    )
    # not enough samples to reach t1: reported like a solver running out of steps
    result = jnp.where((result == STATUS_OK) & (t_reached < t1), STATUS_MAX_STEPS, result)
    status = jnp.where(frozen_time > 0, STATUS_DIVERGED, jnp.broadcast_to(result, (n,))).astype(
        jnp.int32
    )
    t_final = t_reached - frozen_time
    if n_save:
        q_ends, u_held, t_ends = outs  # (K, n, P), (K, n, 4), (K,)
        ts = t0 + (t1 - t0) * jnp.linspace(0.0, 1.0, n_save, dtype=dtype)
        q = jnp.concatenate([peak_inputs(y0[0])[None], q_ends])
        q_ts = interpolate(ts, jnp.concatenate([t0[None], t_ends]), q)  # (n_save, n, P)
        u_ts = u_held[held_index(ts, t0, h, max_samples)]  # (n_save, n, 4)

        def case_peaks(p, q_c, u_c, tf):
            lp, inputs = eqx.combine(p, fixed)
            samples = jax.vmap(lambda t, qq, u: lp.peak_sample(t, qq, u, inputs))(ts, q_c, u_c)
            return peaks_over_samples(ts, samples, tf)

        peaks = jax.vmap(case_peaks, in_axes=(0, 1, 1, 0), axis_size=n)(part, q_ts, u_ts, t_final)
    else:
        peaks = jnp.full((n, N_PEAKS), jnp.nan, dtype)
    return _metrics(part, fixed, state, t_final, status, steps[0], steps[1], peaks)


# --------------------------------------------------------------------------- lean integrator


def bridge_jumps(dtype) -> bool:
    """Whether the lean integrator advances the state over the two ulps of time that
    diffrax's jump-time clipping skips at every jump time (`lean_loop`'s ``bridge_jumps``):
    below float64. A float32 group's steps cross the union of its cases' jump times, and each
    skipped gap leaves the state behind the time-dependent inputs by its rate times the gap,
    an error the small altitude tracking errors of a well-tuned loop show in their ISE; in
    float64 the gaps are negligible and the plain steps are kept."""
    return jnp.finfo(dtype).bits < 64


def _save_times(t0, t1, n_save, dtype):
    return t0 + (t1 - t0) * jnp.linspace(0.0, 1.0, n_save, dtype=dtype)


def _to_last(tree):
    return jax.tree.map(lambda x: jnp.moveaxis(x, 0, -1), tree)


def _to_first(tree):
    return jax.tree.map(lambda x: jnp.moveaxis(x, -1, 0), tree)


def _at_group_values(fn, part_g, fixed, groups: Groups):
    """``run(group_args, *trees)``: ``fn(*group_args_i, loop, inputs, *case_values)`` for
    every case, with ``group_args`` a tuple of per-group arrays (G,) and ``trees`` per-case
    pytrees with the case axis last; outputs with the case axis first (n, ...). Values shared
    by a group's cases are computed once per group."""

    def one_group(gargs, p, *trees):
        def one_case(pp, *xs):
            return fn(*gargs, *eqx.combine(pp, fixed), *xs)

        return jax.vmap(one_case, in_axes=(0,) + (-1,) * len(trees))(p, *trees)

    def run(group_args, *trees):
        out = jax.vmap(one_group, in_axes=(0, 0) + (-2,) * len(trees))(
            tuple(group_args), part_g, *(groups.view(x) for x in trees)
        )
        return jax.tree.map(lambda x: x.reshape(groups.count * groups.size, *x.shape[2:]), out)

    return run


def _lean_group_field(fixed):
    """The vector field of one group for `lean_loop`: state leaves (..., g), args = (frozen
    (g,), held commands (leaves (..., g)) or None); frozen cases have zero derivatives."""

    def one_case(t, state, frozen, p, held):
        loop, inputs = eqx.combine(p, fixed)
        dstate = loop.signals_and_derivative(t, state, inputs, held, materialise=True)[1]
        return jax.tree.map(lambda d: jnp.where(frozen, jnp.zeros_like(d), d), dstate)

    def group_field(t, y, args, p):
        frozen, held = args
        held_axis = None if held is None else -1
        return jax.vmap(one_case, in_axes=(None, -1, -1, 0, held_axis), out_axes=-1)(
            t, y, frozen, p, held
        )

    return group_field


class EnsembleField(eqx.Module):
    """The vector field the lean ensemble integrator evaluates, on its own (profiling,
    checks): ``field(t, y)`` is d/dt of the closed-loop state of all n cases, leaves of y with
    the case axis last (``(..., n)``), at time t [s] (scalar, or per group (n // group_size,)),
    exactly as `solve_group` with ``integrator="lean"`` evaluates it (groups of
    ``group_size`` consecutive cases, case-invariant inputs evaluated once per group).

    Attributes:
        part: the inputs that differ between cases ((ClosedLoop, CaseInputs) leaves with
            leading axis n).
        fixed: the inputs shared by every case (unbatched).
        n, group_size: number of cases and cases per group (static).
    """

    part: Any
    fixed: Any
    n: int = eqx.field(static=True)
    group_size: int = eqx.field(static=True)

    def __check_init__(self):
        if self.group_size < 1 or self.n % self.group_size:
            raise ValueError(
                f"EnsembleField: {self.n} cases do not split into groups of {self.group_size}."
            )

    @property
    def groups(self) -> Groups:
        return Groups(self.n // self.group_size, self.group_size)

    def initial_state(self, dtype=None):
        """The cases' initial closed-loop states, leaves (..., n)."""
        dtype = jnp.result_type(float) if dtype is None else dtype
        return _to_last(
            _per_case(lambda lp, inp: lp.initial_state(inp, dtype), self.part, self.fixed, self.n)
        )

    def __call__(self, t, y, frozen=None):
        """dy/dt at time t [s]; ``frozen`` (n,) bool: cases with zero derivatives (default
        none)."""
        groups = self.groups
        part_g = jax.tree.map(
            lambda x: x.reshape(groups.count, groups.size, *x.shape[1:]), self.part
        )
        field = ensemble_field(_lean_group_field(self.fixed), part_g, groups)
        dtype = jax.tree.leaves(y)[0].dtype
        t_group = jnp.broadcast_to(jnp.asarray(t, dtype), (groups.count,))
        t_case = groups.per_case(t_group)
        frozen = jnp.zeros((self.n,), bool) if frozen is None else frozen
        return field(t_case, y, (frozen, None))


def _peak_sample(t, loop, inputs, sampled):
    """`sample_peaks` of one case at t from ``sampled`` = (plant state, controller state)
    (`_sampled`): the error r(t) - q and the controller's command (the signals `simulate`
    saves, without the plant)."""
    plant, controller = sampled
    measured = loop.plant.to_paper_layout(plant)
    u_cmd = loop.command(t, measured, controller, inputs)[0]
    return loop.peak_sample(t, loop.peak_inputs(plant, controller), u_cmd, inputs)


def _sampled(y: ClosedLoopState):
    """What a peak sample reads of the closed-loop state: (plant, controller)."""
    return y.plant, y.controller


class _Cases(eqx.Module):
    """Per-case bookkeeping of the lean ensemble: frozen (diverged) flags, the time a frozen
    case ended (the end of the step where it crossed the limits) and the running peaks (each
    group's next save-time index (G,), (n, 3) maxima; None without peaks)."""

    frozen: Array
    t_frozen: Array
    peaks: tuple | None

    def counts(self, t) -> Array:
        """Whether a sample at per-case times t (n,) counts (at or before the run's end)."""
        return ~self.frozen | (t <= self.t_frozen)

    def t_final(self, t_stop) -> Array:
        return jnp.where(self.frozen, self.t_frozen, t_stop)


def _freeze(cases: _Cases, t, y, diverged, groups: Groups) -> _Cases:
    """At the groups' accepted times t (G,) and state y: a case past the limits there is
    frozen from now on and ends at t, the end of the step where it crossed them (as
    `simulate`'s divergence event stops a run at the end of the step where it fires)."""
    new = ~cases.frozen & diverged((t,), y)
    t_frozen = jnp.where(new, groups.per_case(t), cases.t_frozen)
    return _Cases(cases.frozen | new, t_frozen, cases.peaks)


def _due_samples(taken, ts, t_hi, take):
    """Take every save time ts[j] <= t_hi[i] not yet taken by group i: ``taken`` = (next
    index per group (G,), accumulator); ``take(acc, j, t, due)`` adds the samples at the
    per-group indices j and times t (G,) of the groups where ``due`` (G,)."""
    last = ts.shape[0] - 1

    def pending(j):
        return (j <= last) & (ts[jnp.minimum(j, last)] <= t_hi)

    def body(c):
        j, acc = c
        due = pending(j)
        return j + due, take(acc, j, ts[jnp.minimum(j, last)], due)

    # one round unconditionally (a step rarely holds more than one save time; straight-line
    # code here kept XLA on one thread), further rounds while any group has one due
    return jax.lax.while_loop(lambda c: jnp.any(pending(c[0])), body, body(taken))


def _fold_samples(peaks, ts, t_hi, counts, sample_at, groups: Groups):
    """Fold every save time ts[j] <= t_hi[i] not yet taken by group i into the running peaks
    (``peaks`` = (next index per group (G,), maxima (n, 3))); ``sample_at(t)``: the (n, 3)
    samples at per-group times t (G,); ``counts(t_case)``: (n,) whether a sample counts."""

    def take(running, j, t, due):
        use = groups.per_case(due) & counts(groups.per_case(t))
        return fold_peaks(running, sample_at(t), use)

    return _due_samples(peaks, ts, t_hi, take)


def _lean_result(out, cases: _Cases, groups: Groups, dtype, peaks, part, fixed) -> BatchMetrics:
    """``peaks``: (n, 3) running maxima (`fold_peaks`), or None without peaks."""
    status = jnp.where(
        cases.frozen,
        STATUS_DIVERGED,
        groups.per_case(status_from(out.result, jnp.zeros_like(out.t, bool))),
    ).astype(jnp.int32)
    n = groups.count * groups.size
    peaks = jnp.full((n, N_PEAKS), jnp.nan, dtype) if peaks is None else finish_peaks(peaks)
    return _metrics(
        part,
        fixed,
        _to_first(out.y),
        cases.t_final(groups.per_case(out.t)),
        status,
        groups.per_case(out.num_steps),
        groups.per_case(out.num_rejected_steps),
        peaks,
    )


def _store_samples(stored, ts, t_hi, state_at, groups: Groups):
    """Store the state at every save time ts[j] <= t_hi[i] not yet taken by group i
    (``stored`` = (next index per group (G,), states: leaves (G, n_save, ..., group size),
    one contiguous block per group)); ``state_at(t)``: the state at per-group times t (G,),
    leaves with the case axis last. The peaks are computed from the stored states after the
    loop (`_stored_peaks`): one sample per save time instead of one per step."""
    index = jnp.arange(groups.count)
    dropped = ts.shape[0]  # an out-of-range row: the update is dropped

    def take(states, j, t, due):
        row = jnp.where(due, j, dropped)
        return jax.tree.map(
            lambda s, x: s.at[index, row].set(_blocks(x, groups), mode="drop"),
            states,
            state_at(t),
        )

    return _due_samples(stored, ts, t_hi, take)


def _blocks(x, groups: Groups):
    """(..., n) -> (G, ..., group size): each group's cases as one block."""
    return jnp.moveaxis(groups.view(x), -2, 0)


def _unblock(x, groups: Groups):
    """(G, ..., group size) -> (..., n), the inverse of `_blocks`."""
    return groups.flat(jnp.moveaxis(x, 0, -2))


def _stored_peaks(stored, ts, cases: _Cases, sample, groups: Groups):
    """Running peaks (n, 3) (`fold_peaks`) from the states `_store_samples` stored: the
    samples taken (j < the group's next index) that count (at or before the case's end)."""
    j_next, states = stored
    states = jax.tree.map(lambda x: _unblock(x, groups), states)
    samples = jax.vmap(lambda t, y: sample((jnp.full((groups.count,), t),), y), in_axes=(0, 0))(
        ts, states
    )  # (n_save, n, 3)
    taken = jnp.arange(ts.shape[0])[:, None] < groups.per_case(j_next)[None, :]
    counts = taken & cases.counts(ts[:, None])
    return jnp.max(fold_peaks(no_peaks(counts.shape, samples.dtype), samples, counts), axis=0)


def _stored_peaks_by_blocks(stored, ts, cases: _Cases, part_g, fixed, groups: Groups, L: int):
    """`_stored_peaks` of `_peak_sample` on consecutive blocks of L of the G groups (a work
    queue's pool, L its lanes; `jax.lax.map`): every block is evaluated at the shape of one
    chunk, so a group's peaks are bitwise those of its chunk solved alone (XLA fuses, and so
    rounds, a computation by its shape)."""
    G, g = groups.count, groups.size
    B = G // L
    j_next, states = stored

    def blocks(x):
        """(G, ...) -> (B, L, ...)."""
        return x.reshape(B, L, *x.shape[1:])

    def one(xs):
        j, st, frozen, t_frozen, p = xs
        grp = Groups(L, g)
        sample = _at_group_values(_peak_sample, p, fixed, grp)
        return _stored_peaks((j, st), ts, _Cases(frozen, t_frozen, None), sample, grp)

    out = jax.lax.map(
        one,
        (
            blocks(j_next),
            jax.tree.map(blocks, states),
            cases.frozen.reshape(B, L * g),
            cases.t_frozen.reshape(B, L * g),
            jax.tree.map(blocks, part_g),
        ),
    )
    return out.reshape(G * g, *out.shape[2:])


def _lean_start(part, fixed, n, dtype, n_save, G, store: bool = False):
    """Initial state and bookkeeping; ``store``: the peaks are kept as stored states
    (`_store_samples`), else as running maxima (`fold_peaks`)."""
    state0 = _to_last(_per_case(lambda lp, inp: lp.initial_state(inp, dtype), part, fixed, n))
    frozen = jnp.zeros((n,), bool)
    if not n_save:
        peaks = None
    elif store:
        g = n // G
        states = jax.tree.map(
            lambda x: jnp.zeros((G, n_save, *x.shape[:-1], g), x.dtype), _sampled(state0)
        )
        peaks = (jnp.zeros((G,), jnp.int32), states)
    else:
        peaks = (jnp.zeros((G,), jnp.int32), no_peaks((n,), dtype))
    return state0, _Cases(frozen, jnp.zeros((n,), dtype), peaks)


def _lean_continuous(
    part, part_g, fixed, groups, controllers, solver, t0, t1, dtype, max_steps, n_save, lanes, dt0
):
    """The ensemble on `lean_loop` (``lanes``: its work queue). After every accepted step: the
    divergence test (a diverged case is frozen from then on) and the states at the save times
    inside the step, from diffrax's dense interpolation (the peaks computed from them after
    the loop)."""
    n = groups.count * groups.size
    state0, cases0 = _lean_start(part, fixed, n, dtype, n_save, groups.count, store=True)
    ts = _save_times(t0, t1, n_save, dtype) if n_save else None
    sample = _at_group_values(_peak_sample, part_g, fixed, groups)

    def on_state(cases, t, y, args, inputs):
        grp = Groups(t.shape[0], groups.size)  # the groups advanced (the lanes)
        diverged = _at_group_values(
            lambda t, lp, inp, state: lp.diverged_at(t, state, inp), inputs, fixed, grp
        )
        cases = _freeze(cases, t, y, diverged, grp)
        return cases, (cases.frozen, None)

    def after_step(cases, step, args, keep, at_boundary, inputs):
        grp = Groups(keep.shape[0], groups.size)
        if n_save:
            peaks = _store_samples(
                cases.peaks,
                ts,
                jnp.where(keep, step.t1, -jnp.inf),
                lambda t: _sampled(step.evaluate_groups(t, grp)),
                grp,
            )
            cases = _Cases(cases.frozen, cases.t_frozen, peaks)
        false = jnp.zeros_like(keep)
        return cases, None, args, false, false

    out = lean_loop(
        _lean_group_field(fixed),
        part_g,
        solver,
        controllers,
        t0,
        t1,
        state0,
        (cases0.frozen, None),
        groups=groups,
        max_steps=max_steps,
        extra=cases0,
        after_step=after_step,
        on_state=on_state,
        lanes=lanes,
        bridge_jumps=bridge_jumps(dtype),
        dt0=dt0,
    )
    cases = out.extra
    if not n_save:
        peaks = None
    elif lanes is None or lanes >= groups.count:
        peaks = _stored_peaks(cases.peaks, ts, cases, sample, groups)
    else:
        peaks = _stored_peaks_by_blocks(cases.peaks, ts, cases, part_g, fixed, groups, lanes)
    return _lean_result(out, cases, groups, dtype, peaks, part, fixed)


def _held_sample(t, k, e_prev, e_end, h, t0, max_samples, loop, inputs, qa, qb, ua, ub):
    """`sample_peaks` of one case at a save time t in (e_prev, e_end]: the peak inputs
    (`ClosedLoop.peak_inputs`) linearly interpolated between the sample instants (qa, qb), the
    command held over t's sample interval (ua: interval k, ub: interval k + 1), as `simulate`
    samples digital control."""
    knots = jnp.stack([e_prev, e_end])
    q = jax.vmap(lambda a, b: jnp.interp(t, knots, jnp.stack([a, b])))(qa, qb)
    u = jnp.where(held_index(t, t0, h, max_samples) > k, ub, ua)
    return loop.peak_sample(t, q, u, inputs)


def _lean_digital(
    part, part_g, fixed, groups, controllers, solver, t0, t1, dtype, max_steps, n_save, dt0
):
    """Digital control on `lean_loop`: each group's steps land on its sample instants (its
    held command jumps there); a step ending on one runs the sample instant for the group's
    cases, as the interval solves of `simulate` do (the controller's Euler update, then
    `sample_instant`). Peaks from the states at the sample instants, linearly interpolated,
    and the held command (as `simulate`)."""
    n, G = groups.count * groups.size, groups.count
    loop = eqx.combine(part, fixed)[0]
    max_samples = loop.sampling.max_samples
    # each group's one control rate (equal in its cases: checked by simulate_batch)
    h_case = _per_case(lambda lp, inp: 1.0 / lp.sampling.control_rate.astype(dtype), part, fixed, n)
    h = h_case.reshape(G, groups.size)[:, 0]
    state0, cases0 = _lean_start(part, fixed, n, dtype, n_save, G)
    diverged = _at_group_values(
        lambda t, lp, inp, state: lp.diverged_at(t, state, inp), part_g, fixed, groups
    )
    ts = _save_times(t0, t1, n_save, dtype) if n_save else None

    def sample_instants(k, y, buf):
        def one(kk, hh, lp, inp, yy, bb):
            return sample_instant(lp, kk, sample_time(t0, hh, kk), yy, bb, inp)

        y1, buf1, held, dctrl = _at_group_values(one, part_g, fixed, groups)((k, h), y, buf)
        return _to_last(y1), _to_last(buf1), _to_last(held), _to_last(dctrl)

    def interval_end(k):
        return jnp.minimum(sample_time(t0, h, k + 1), t1)

    held_sample = _at_group_values(
        lambda t, k, ea, eb, hh, lp, inp, qa, qb, ua, ub: _held_sample(
            t, k, ea, eb, hh, t0, max_samples, lp, inp, qa, qb, ua, ub
        ),
        part_g,
        fixed,
        groups,
    )

    def after_step(extra, step, args, keep, at_boundary, inputs):
        del inputs  # every group at once: part_g
        cases, k, buf, dctrl, q_prev, e_prev = extra
        held = args[1]
        on = groups.per_case(at_boundary)
        y = step.y1
        update = on & ~cases.frozen
        y = eqx.tree_at(
            lambda s: s.controller,
            y,
            jnp.where(update, y.controller + groups.per_case(h) * dctrl, y.controller),
        )
        e_end = interval_end(k)
        _, buf_next, held_next, dctrl_next = sample_instants(k + 1, y, buf)
        q_end = loop.peak_inputs(y.plant, y.controller)
        peaks = cases.peaks
        if n_save:

            def sample_at(t):
                return held_sample(
                    (t, k, e_prev, e_end, h), q_prev, q_end, held.u_command, held_next.u_command
                )

            peaks = _fold_samples(
                peaks, ts, jnp.where(at_boundary, e_end, -jnp.inf), cases.counts, sample_at, groups
            )
        more = at_boundary & (e_end < t1) & (k + 1 < max_samples)
        more_case = groups.per_case(more)

        def choose(mask, a, b):
            return jax.tree.map(lambda x, z: jnp.where(mask, x, z), a, b)

        extra = (
            _Cases(cases.frozen, cases.t_frozen, peaks),
            jnp.where(more, k + 1, k),
            choose(more_case, buf_next, buf),
            choose(more_case, dctrl_next, dctrl),
            choose(on, q_end, q_prev),
            jnp.where(at_boundary, e_end, e_prev),
        )
        held = choose(more_case, held_next, held)
        # out of samples before t1: stop (reported as max_steps)
        stop = at_boundary & ~more & (e_end < t1)
        return extra, y, (cases.frozen, held), at_boundary, stop

    def on_state(extra, t, y, args, inputs):
        cases = _freeze(extra[0], t, y, diverged, groups)
        return (cases, *extra[1:]), (cases.frozen, args[1])

    k0 = jnp.zeros((G,), jnp.int32)
    buf0 = _to_last(
        jax.vmap(lambda p, y: initial_buffer(eqx.combine(p, fixed)[0], y), axis_size=n)(
            part, _to_first(state0)
        )
    )
    state0, buf0, held0, dctrl0 = sample_instants(k0, state0, buf0)
    q0 = loop.peak_inputs(state0.plant, state0.controller)  # leaves (..., n): case axis last
    extra0 = (cases0, k0, buf0, dctrl0, q0, jnp.full((G,), t0))
    out = lean_loop(
        _lean_group_field(fixed),
        part_g,
        solver,
        controllers,
        t0,
        t1,
        state0,
        (cases0.frozen, held0),
        groups=groups,
        max_steps=max_steps,
        extra=extra0,
        after_step=after_step,
        on_state=on_state,
        boundary=lambda extra, inputs: interval_end(extra[1]),
        bridge_jumps=bridge_jumps(dtype),
        dt0=dt0,
    )
    cases = out.extra[0]
    return _lean_result(out, cases, groups, dtype, cases.peaks[1] if n_save else None, part, fixed)
