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
from ..metrics import BatchMetrics, peaks_over_samples, sample_peaks
from ..model import CHANNEL_INDEX
from ._digital import held_index, initial_buffer, interpolate, sample_instant, sample_time
from ._solve import step_size_controller
from ._status import STATUS_DIVERGED, STATUS_MAX_STEPS, STATUS_OK, status_from


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


def _metrics(state, frozen_time, t_stop, status, steps, rejected, peaks) -> BatchMetrics:
    n = frozen_time.shape[0]
    ones = jnp.ones((n,), jnp.int32)
    t_final = (t_stop - frozen_time).astype(frozen_time.dtype)
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


def solve_group(part, fixed, n, solver, rtol, atol, dtype, max_steps, n_save) -> BatchMetrics:
    """One ensemble of the n cases of ``part`` ((ClosedLoop, CaseInputs) leaves with leading
    axis n) sharing ``fixed`` (leaves equal for every case, unbatched: evaluated once)."""
    loop = eqx.combine(part, fixed)[0]  # static structure (digital or not, buffer sizes)
    t0 = _shared_or_per_case(lambda lp, inp: inp.scenario.t0, part, fixed, n).reshape(-1)[0]
    t1 = _shared_or_per_case(lambda lp, inp: inp.scenario.t1, part, fixed, n).reshape(-1)[0]
    y0 = (
        _per_case(lambda lp, inp: lp.initial_state(inp, dtype), part, fixed, n),
        jnp.zeros((n,), dtype),
    )
    stepsize = step_size_controller(
        rtol, atol, union_jump_times(part, fixed, n, dtype), norm=ensemble_rms_norm
    )
    term = diffrax.ODETerm(_field(part, fixed, n))
    solve = _digital if loop.digital else _continuous
    return solve(part, fixed, n, term, stepsize, solver, t0, t1, y0, dtype, max_steps, n_save)


def _continuous(part, fixed, n, term, stepsize, solver, t0, t1, y0, dtype, max_steps, n_save):
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
        term,
        solver,
        t0,
        t1,
        None,
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
        frozen_time,
        t_stop,
        status,
        sol.stats["num_steps"],
        sol.stats["num_rejected_steps"],
        peaks,
    )


def _digital(part, fixed, n, term, stepsize, solver, t0, t1, y0, dtype, max_steps, n_save):
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
    return _metrics(state, frozen_time, t_reached, status, steps[0], steps[1], peaks)
