"""The ensemble: a group of cases solved as ONE ODE system with one shared step sequence.

The group's state leaves have a leading case axis; step-size control uses `ensemble_rms_norm`,
the maximum over cases of each case's RMS scaled error, so every case meets its own tolerance
on every step, and the vector field is evaluated for all cases at once.

- Divergence: a case crossing the `DivergenceLimits`, reaching a non-finite state or producing
  a non-finite derivative is *frozen*: its derivatives are zero from then on, so its cost
  integrals stop at the crossing, it cannot stall the shared step size, and its status is
  ``diverged``. The freeze is made persistent by an extra per-case state that grows at rate 1
  while frozen (``t_final = t_stop - frozen_time``).
- Jump times: the shared steps land on the union of the group's jump times.
- Digital control: the group's cases share their sample instants (one control rate per group):
  a scan over the samples, `afbl_jax.sim.sample_instant` for every case, then one ensemble
  solve per sample interval with the held commands; a frozen case keeps its state.
- Peaks: sampled at ``n_save`` equally spaced times (continuous: diffrax ``SubSaveAt(ts, fn)``
  keeping three numbers per case and sample; digital: the states at the sample instants,
  interpolated as `simulate` does), then `afbl_jax.metrics.peaks_over_samples`.
"""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._typing import Array
from ..metrics import (
    BatchMetrics,
    finish_peaks,
    fold_peaks,
    no_peaks,
    peaks_over_samples,
    sample_peaks,
)
from ..model import CHANNEL_INDEX
from ._digital import held_index, initial_buffer, interpolate, sample_instant, sample_time
from ._lean import lean_loop
from ._solve import step_size_controller
from ._status import STATUS_DIVERGED, STATUS_MAX_STEPS, STATUS_OK, status_from

INTEGRATORS = ("lean", "diffeqsolve")
"""How an ensemble is integrated: ``"lean"`` (`afbl_jax.sim.lean_loop` over diffrax's solver
step and step-size controller; fastest, not reverse-mode differentiable) or ``"diffeqsolve"``
(`diffrax.diffeqsolve`; differentiable with `jax.grad`)."""


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


def _metrics(state, t_final, status, steps, rejected, peaks) -> BatchMetrics:
    n = t_final.shape[0]
    ones = jnp.ones((n,), jnp.int32)
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
    )


def solve_group(
    part, fixed, n, solver, rtol, atol, dtype, max_steps, n_save, integrator="lean"
) -> BatchMetrics:
    """One ensemble of the n cases of ``part`` ((ClosedLoop, CaseInputs) leaves with leading
    axis n) sharing ``fixed`` (leaves equal for every case, unbatched: evaluated once).
    ``integrator``: one of `INTEGRATORS`. Both integrators control the step on the
    closed-loop state with `ensemble_rms_norm` and start from diffrax's initial-step
    heuristic, so they take the same steps until a case diverges."""
    if integrator not in INTEGRATORS:
        raise ValueError(f"unknown integrator {integrator!r}; allowed: {', '.join(INTEGRATORS)}.")
    loop = eqx.combine(part, fixed)[0]  # static structure (digital or not, buffer sizes)
    t0 = _shared_or_per_case(lambda lp, inp: inp.scenario.t0, part, fixed, n).reshape(-1)[0]
    t1 = _shared_or_per_case(lambda lp, inp: inp.scenario.t1, part, fixed, n).reshape(-1)[0]
    state0 = _per_case(lambda lp, inp: lp.initial_state(inp, dtype), part, fixed, n)
    jump_ts = union_jump_times(part, fixed, n, dtype)
    if integrator == "lean":
        stepsize = step_size_controller(rtol, atol, jump_ts, norm=ensemble_rms_norm)
        solve = _lean_digital if loop.digital else _lean_continuous
        return solve(part, fixed, n, stepsize, solver, t0, t1, state0, dtype, max_steps, n_save)
    # the frozen time is bookkeeping: the step is controlled on the closed-loop state only
    stepsize = step_size_controller(rtol, atol, jump_ts, norm=lambda y: ensemble_rms_norm(y[0]))
    y0 = (state0, jnp.zeros((n,), dtype))
    field = _field(part, fixed, n)
    solve = _digital if loop.digital else _continuous
    return solve(part, fixed, n, field, stepsize, solver, t0, t1, y0, dtype, max_steps, n_save)


def _first_step(field, stepsize, solver, t0, t1, y0, args=None):
    """diffrax's initial step-size heuristic (`diffrax.PIDController.init`; `diffeqsolve`
    itself starts with 0.01 s, as its heuristic does not apply to the direction-wrapped term
    it integrates), so that `diffeqsolve` starts with the step `lean_loop` starts with."""
    term = diffrax.ODETerm(field)
    t_next, _ = stepsize.controller.init(
        term, t0, t1, y0, None, args, solver.func, solver.error_order(term)
    )
    return t_next - t0


def _continuous(part, fixed, n, field, stepsize, solver, t0, t1, y0, dtype, max_steps, n_save):
    subs = [diffrax.SubSaveAt(t1=True)]
    if n_save:
        ts = t0 + (t1 - t0) * jnp.linspace(0.0, 1.0, n_save, dtype=dtype)

        def one_sample(t, state, p):
            lp, inputs = eqx.combine(p, fixed)
            sig = lp.signals_and_derivative(t, state, inputs)[0]
            return sample_peaks(sig.error, sig.u_command, inputs.vehicle, inputs.model)

        def save_peaks(t, y, args):
            return jax.vmap(one_sample, in_axes=(None, 0, 0), axis_size=n)(t, y[0], part)

        subs.append(diffrax.SubSaveAt(ts=ts, fn=save_peaks))
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(field),
        solver,
        t0,
        t1,
        _first_step(field, stepsize, solver, t0, t1, y0),
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
        peaks = jnp.full((n, 3), jnp.nan, dtype)
    return _metrics(
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
        out = (new[0][0].plant[:, CHANNEL_INDEX], held.u_command, new[3]) if n_save else None
        return new, out

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
        q_ends, u_held, t_ends = outs  # (K, n, 4), (K, n, 4), (K,)
        ts = t0 + (t1 - t0) * jnp.linspace(0.0, 1.0, n_save, dtype=dtype)
        q = jnp.concatenate([y0[0].plant[None][:, :, CHANNEL_INDEX], q_ends])
        q_ts = interpolate(ts, jnp.concatenate([t0[None], t_ends]), q)  # (n_save, n, 4)
        u_ts = u_held[held_index(ts, t0, h, max_samples)]  # (n_save, n, 4)

        def case_peaks(p, q_c, u_c, tf):
            lp, inputs = eqx.combine(p, fixed)
            err = jax.vmap(lambda t, qq: inputs.scenario.reference(t).r - qq)(ts, q_c)
            samples = jax.vmap(lambda e, u: sample_peaks(e, u, inputs.vehicle, inputs.model))(
                err, u_c
            )
            return peaks_over_samples(ts, samples, tf)

        peaks = jax.vmap(case_peaks, in_axes=(0, 1, 1, 0), axis_size=n)(part, q_ts, u_ts, t_final)
    else:
        peaks = jnp.full((n, 3), jnp.nan, dtype)
    return _metrics(state, t_final, status, steps[0], steps[1], peaks)


# --------------------------------------------------------------------------- lean integrator


def _save_times(t0, t1, n_save, dtype):
    return t0 + (t1 - t0) * jnp.linspace(0.0, 1.0, n_save, dtype=dtype)


def _lean_field(part, fixed, n):
    """The ensemble vector field of the lean integrator on ClosedLoopState (n, ...); args =
    (frozen (n,) bool, held commands (leading axis n) or None). Frozen cases have zero
    derivatives."""

    def one_case(t, state, frozen, p, held):
        loop, inputs = eqx.combine(p, fixed)
        dstate = loop.signals_and_derivative(t, state, inputs, held)[1]
        return jax.tree.map(lambda d: jnp.where(frozen, jnp.zeros_like(d), d), dstate)

    def field(t, y, args):
        frozen, held = args
        held_axis = None if held is None else 0
        return jax.vmap(one_case, in_axes=(None, 0, 0, 0, held_axis), axis_size=n)(
            t, y, frozen, part, held
        )

    return field


def _diverged_fn(part, fixed, n):
    """(t, ClosedLoopState (n, ...)) -> (n,) bool: the divergence test of every case."""

    def one(t, state, p):
        lp, inputs = eqx.combine(p, fixed)
        return lp.diverged_at(t, state, inputs)

    return lambda t, y: jax.vmap(one, in_axes=(None, 0, 0), axis_size=n)(t, y, part)


def _sample_fn(part, fixed, n):
    """Peak samples (n, 3) of every case at (t, state): `sample_peaks` of the error r(t) - q
    and the controller's command (the signals `simulate` saves, without the plant)."""

    def one(t, state, p):
        lp, inputs = eqx.combine(p, fixed)
        measured = lp.plant.to_paper_layout(state.plant)
        u_cmd = lp.command(t, measured, state.controller, inputs)[0]
        err = inputs.scenario.reference(t).r - state.plant[CHANNEL_INDEX]
        return sample_peaks(err, u_cmd, inputs.vehicle, inputs.model)

    return lambda t, y: jax.vmap(one, in_axes=(None, 0, 0), axis_size=n)(t, y, part)


def _fold_samples(carry, ts, t_hi, counts, sample_at):
    """Fold every save time ts[j] <= t_hi not yet taken (carry = (next index, running peaks
    (n, 3))) into the running peaks; ``counts(t)``: (n,) whether a sample at t counts."""

    def cond(c):
        j, _ = c
        return (j < ts.shape[0]) & (ts[jnp.minimum(j, ts.shape[0] - 1)] <= t_hi)

    def body(c):
        j, peaks = c
        t = ts[j]
        return j + 1, fold_peaks(peaks, sample_at(t), counts(t))

    return jax.lax.while_loop(cond, body, carry)


class _Cases(eqx.Module):
    """Per-case bookkeeping of the lean ensemble: frozen (diverged) flags, the time a frozen
    case ended (the end of the step where it crossed the limits) and the running peaks (next
    save-time index, (n, 3) maxima; None without peaks)."""

    frozen: Array
    t_frozen: Array
    peaks: tuple | None

    def counts(self, t) -> Array:
        """Whether a sample at t counts for each case (t at or before its run's end)."""
        return ~self.frozen | (t <= self.t_frozen)

    def t_final(self, t_stop) -> Array:
        return jnp.where(self.frozen, self.t_frozen, t_stop)


def _end_of_step(cases: _Cases, t1, y1, diverged, keep) -> _Cases:
    """After an accepted step ending at t1: a case crossing the limits there is frozen from
    now on and ends at t1 (as `simulate`'s divergence event stops a run at the end of the
    step where it fires)."""
    new = keep & ~cases.frozen & diverged(t1, y1)
    return _Cases(cases.frozen | new, jnp.where(new, t1, cases.t_frozen), cases.peaks)


def _lean_continuous(part, fixed, n, stepsize, solver, t0, t1, state0, dtype, max_steps, n_save):
    """The ensemble on `lean_loop`. After every accepted step: the divergence test (per case;
    a diverged case is frozen from then on), and the peak samples at the save times inside the
    step from diffrax's dense interpolation (the running form of `peaks_over_samples`)."""
    ts = _save_times(t0, t1, n_save, dtype) if n_save else None
    sample = _sample_fn(part, fixed, n)
    diverged = _diverged_fn(part, fixed, n)

    def after_step(cases, step, args, keep, at_boundary):
        del at_boundary
        cases = _end_of_step(cases, step.t1, step.y1, diverged, keep)
        if n_save:
            peaks = _fold_samples(
                cases.peaks,
                ts,
                jnp.where(keep, step.t1, -jnp.inf),
                cases.counts,
                lambda t: sample(t, step.interpolation.evaluate(t)),
            )
            cases = _Cases(cases.frozen, cases.t_frozen, peaks)
        return cases, None, (cases.frozen, None), jnp.asarray(False), jnp.asarray(False)

    frozen0 = jnp.zeros((n,), bool)
    peaks0 = (jnp.asarray(0, jnp.int32), no_peaks((n,), dtype)) if n_save else None
    out = lean_loop(
        _lean_field(part, fixed, n),
        solver,
        stepsize,
        t0,
        t1,
        state0,
        (frozen0, None),
        max_steps=max_steps,
        extra=_Cases(frozen0, jnp.full((n,), t0, dtype), peaks0),
        after_step=after_step,
    )
    cases = out.extra
    status = status_from(out.result, cases.frozen)
    peaks = finish_peaks(cases.peaks[1]) if n_save else jnp.full((n, 3), jnp.nan, dtype)
    return _metrics(
        out.y, cases.t_final(out.t), status, out.num_steps, out.num_rejected_steps, peaks
    )


def _lean_digital(part, fixed, n, stepsize, solver, t0, t1, state0, dtype, max_steps, n_save):
    """Digital control on `lean_loop`: steps land on the sample instants (the held command
    jumps there); a step ending on one runs the sample instant for every case (as the
    interval solves of `simulate` do: the controller's Euler update, then `sample_instant`);
    peaks from the states at the sample instants, linearly interpolated (as `simulate`)."""
    loop = eqx.combine(part, fixed)[0]
    max_samples = loop.sampling.max_samples
    h = _shared_or_per_case(
        lambda lp, inp: 1.0 / lp.sampling.control_rate.astype(dtype), part, fixed, n
    ).reshape(-1)[0]
    diverged = _diverged_fn(part, fixed, n)

    def instant(k, y, buf):
        def one(p, yi, bi):
            lp, inputs = eqx.combine(p, fixed)
            return sample_instant(lp, k, sample_time(t0, h, k), yi, bi, inputs)

        return jax.vmap(one, axis_size=n)(part, y, buf)

    buf0 = jax.vmap(lambda p, y: initial_buffer(eqx.combine(p, fixed)[0], y), axis_size=n)(
        part, state0
    )
    k0 = jnp.asarray(0, jnp.int32)
    state0, buf0, held0, dctrl0 = instant(k0, state0, buf0)
    ts = _save_times(t0, t1, n_save, dtype) if n_save else None

    def interval_end(k):
        return jnp.minimum(sample_time(t0, h, k + 1), t1)

    def held_sampler(k, q_prev, e_prev, q_end, e_end, u_now, u_next):
        """Peak samples (n, 3) at a save time t in (e_prev, e_end]: q linearly interpolated
        between the sample instants, the command held over t's sample interval."""

        def one(t, p, qa, qb, ua, ub):
            inputs = eqx.combine(p, fixed)[1]
            knots = jnp.stack([e_prev, e_end])
            q = jax.vmap(lambda a, b: jnp.interp(t, knots, jnp.stack([a, b])))(qa, qb)
            u = jnp.where(held_index(t, t0, h, max_samples) > k, ub, ua)
            err = inputs.scenario.reference(t).r - q
            return sample_peaks(err, u, inputs.vehicle, inputs.model)

        return lambda t: jax.vmap(one, in_axes=(None, 0, 0, 0, 0, 0), axis_size=n)(
            t, part, q_prev, q_end, u_now, u_next
        )

    def after_step(extra, step, args, keep, at_boundary):
        cases, k, buf, dctrl, q_prev, e_prev = extra
        held = args[1]
        cases = _end_of_step(cases, step.t1, step.y1, diverged, keep)

        def at_instant():
            y = step.y1
            live = ~cases.frozen[:, None]
            y = eqx.tree_at(
                lambda s: s.controller, y, jnp.where(live, y.controller + h * dctrl, y.controller)
            )
            e_end = interval_end(k)
            y_next, buf_next, held_next, dctrl_next = instant(k + 1, y, buf)
            q_end = y.plant[:, CHANNEL_INDEX]
            peaks = cases.peaks
            if n_save:
                sample_at = held_sampler(
                    k, q_prev, e_prev, q_end, e_end, held.u_command, held_next.u_command
                )
                peaks = _fold_samples(peaks, ts, e_end, cases.counts, sample_at)
            done = _Cases(cases.frozen, cases.t_frozen, peaks)
            more = (e_end < t1) & (k + 1 < max_samples)

            def choose(a, b):
                return jax.tree.map(lambda x, z: jnp.where(more, x, z), a, b)

            extra_out = (
                done,
                *choose((k + 1, buf_next, dctrl_next), (k, buf, dctrl)),
                q_end,
                e_end,
            )
            held_out = choose(held_next, held)
            # out of samples before t1: stop (reported as max_steps)
            return extra_out, choose(y_next, y), held_out, jnp.asarray(True), ~more & (e_end < t1)

        def inside():
            return (
                (cases, k, buf, dctrl, q_prev, e_prev),
                step.y1,
                held,
                jnp.asarray(False),
                (jnp.asarray(False)),
            )

        extra, y1, held, jumped, stop = jax.lax.cond(at_boundary, at_instant, inside)
        return extra, y1, (extra[0].frozen, held), jumped, stop

    frozen0 = jnp.zeros((n,), bool)
    peaks0 = (jnp.asarray(0, jnp.int32), no_peaks((n,), dtype)) if n_save else None
    cases0 = _Cases(frozen0, jnp.full((n,), t0, dtype), peaks0)
    extra0 = (cases0, k0, buf0, dctrl0, state0.plant[:, CHANNEL_INDEX], t0)
    out = lean_loop(
        _lean_field(part, fixed, n),
        solver,
        stepsize,
        t0,
        t1,
        state0,
        (frozen0, held0),
        max_steps=max_steps,
        extra=extra0,
        after_step=after_step,
        boundary=lambda extra: interval_end(extra[1]),
    )
    cases = out.extra[0]
    status = status_from(out.result, cases.frozen)
    peaks = finish_peaks(cases.peaks[1]) if n_save else jnp.full((n, 3), jnp.nan, dtype)
    return _metrics(
        out.y, cases.t_final(out.t), status, out.num_steps, out.num_rejected_steps, peaks
    )
