"""A lean adaptive loop: one `jax.lax.while_loop` driving diffrax's own pieces.

`lean_loop` integrates ``dy/dt = field(t, y, args)`` with a diffrax solver's own ``step`` (the
Runge-Kutta stages, error estimate and dense-output information) and a diffrax step-size
controller's own ``init`` / ``adapt_step_size`` (PID control, clipping onto jump times), the
way `diffrax.diffeqsolve` does, but carries only what a batched Monte-Carlo solve needs: no
saving machinery, events, progress meter or adjoint bookkeeping. What a caller needs from the
trajectory it computes inside the loop from every accepted step (`Step`: both ends and
diffrax's dense interpolation over the step), with a hook:

- ``after_step(extra, step, args, keep, at_boundary) -> (extra, y1, args, jumped, stop)`` runs
  after every step (``keep``: the step was accepted; its outputs are used only then). Running
  reductions over the trajectory (peaks at sample times, integrals, soft maxima) update
  ``extra`` from ``step``; a hook may also change the state and ``args`` (digital control:
  the sample instant's discrete update), say so with ``jumped`` (the solver then re-evaluates
  its first stage, as after a jump time), or end the solve (``stop``).
- ``boundary(extra) -> t``: steps never cross t (the next sample instant; +inf: none).
  ``at_boundary`` tells the hook that the accepted step ended there, and the step budget
  ``max_steps`` counts the steps since the last boundary (with no boundary: all steps).

Per step the loop does what `diffrax.diffeqsolve` does (the same solver step, the same
controller call, non-finite error estimates rejected, the last step clipped onto ``t1`` within
100 ulps), so with the same solver, controller and field both take the same steps. The loop is
a ``while_loop``: forward-mode differentiable, not reverse-mode (`jax.grad` needs
`diffrax.diffeqsolve` and its checkpointed adjoint).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp

from .._typing import Array


class Step(NamedTuple):
    """One step of `lean_loop`: from (t0, y0) to (t1, y1), with diffrax's dense interpolation
    (``interpolation.evaluate(t)`` for t in [t0, t1])."""

    t0: Array
    t1: Array
    y0: Any
    y1: Any
    interpolation: diffrax.AbstractLocalInterpolation


class LoopOutcome(NamedTuple):
    """What `lean_loop` returns: end time and state, the hook's ``extra``, the diffrax result
    (`diffrax.RESULTS`), and the step counts (all steps, rejected steps)."""

    t: Array
    y: Any
    args: Any
    extra: Any
    result: Any
    num_steps: Array
    num_rejected_steps: Array


class _Carry(eqx.Module):
    t: Array
    t_next: Array
    y: Any
    args: Any
    solver_state: Any
    controller_state: Any
    made_jump: Array
    budget_used: Array
    num_steps: Array
    num_rejected: Array
    result: Any
    stop: Array
    extra: Any


def _no_hook(extra, step, args, keep, at_boundary):
    del step, keep, at_boundary
    return extra, None, args, jnp.asarray(False), jnp.asarray(False)


def _prevbefore(t, n: int):
    for _ in range(n):
        t = jnp.nextafter(t, jnp.asarray(-jnp.inf, t.dtype))
    return t


def lean_loop(
    field: Callable,
    solver: diffrax.AbstractSolver,
    controller: diffrax.AbstractStepSizeController,
    t0,
    t1,
    y0,
    args=None,
    *,
    max_steps: int,
    extra=None,
    after_step: Callable | None = None,
    boundary: Callable | None = None,
    dt0=None,
) -> LoopOutcome:
    """Integrate ``field`` from t0 to t1 (module docstring). ``after_step`` None: no hook; its
    ``y1`` output None: the state is unchanged."""
    term = diffrax.ODETerm(field)
    after_step = _no_hook if after_step is None else after_step
    t0 = jnp.asarray(t0)
    t1 = jnp.asarray(t1, t0.dtype)
    order = solver.error_order(term)
    t_next, controller_state = controller.init(term, t0, t1, y0, dt0, args, solver.func, order)
    t_next = jnp.minimum(t_next, t1)
    if boundary is not None:
        t_next = jnp.minimum(t_next, boundary(extra))
    solver_state = solver.init(term, t0, t_next, y0, args)
    # as diffeqsolve: a step ending within 100 ulps of t1 is extended onto t1
    t1_floor = _prevbefore(t1, 100)
    zero = jnp.asarray(0, jnp.int32)
    carry = _Carry(
        t0,
        t_next,
        y0,
        args,
        solver_state,
        controller_state,
        jnp.asarray(False),
        zero,
        zero,
        zero,
        diffrax.RESULTS.successful,
        jnp.asarray(False),
        extra,
    )

    def cond(c: _Carry):
        ok = c.result == diffrax.RESULTS.successful
        return (c.t < t1) & ok & ~c.stop & (c.budget_used < max_steps)

    def body(c: _Carry) -> _Carry:
        y1, y_error, dense, solver_state, solver_result = solver.step(
            term, c.t, c.t_next, c.y, c.args, c.solver_state, c.made_jump
        )
        y_error = jax.tree.map(lambda e: jnp.where(jnp.isnan(e), jnp.inf, e), y_error)
        keep, t_new, t_next, jump, controller_state, controller_result = controller.adapt_step_size(
            c.t, c.t_next, c.y, y1, c.args, y_error, order, c.controller_state
        )
        t_new = jnp.minimum(t_new, t1)
        clip = t_next > t1_floor
        t_next = jnp.where(clip, jnp.where(keep, t1, t_new + 0.5 * (t1 - t_new)), t_next)
        at_boundary = keep & (
            jnp.asarray(False) if boundary is None else t_new >= boundary(c.extra)
        )
        step = Step(c.t, c.t_next, c.y, y1, solver.interpolation_cls(t0=c.t, t1=c.t_next, **dense))
        extra, y_hook, args, jumped, stop = after_step(c.extra, step, c.args, keep, at_boundary)
        y1 = y1 if y_hook is None else y_hook
        if boundary is not None:
            t_next = jnp.maximum(jnp.minimum(t_next, boundary(extra)), jnp.nextafter(t_new, t1))

        def pick(a, b):
            return jax.tree.map(lambda x, z: jnp.where(keep, x, z), a, b)

        result = diffrax.RESULTS.where(keep, solver_result, diffrax.RESULTS.successful)
        result = diffrax.RESULTS.where(
            result == diffrax.RESULTS.successful, controller_result, result
        )
        return _Carry(
            t_new,
            t_next,
            pick(y1, c.y),
            pick(args, c.args),
            pick(solver_state, c.solver_state),
            controller_state,
            jnp.where(keep, jump | jumped, c.made_jump),
            jnp.where(at_boundary, 0, c.budget_used + 1),
            c.num_steps + 1,
            c.num_rejected + jnp.where(keep, 0, 1),
            result,
            keep & stop,
            pick(extra, c.extra),
        )

    c = jax.lax.while_loop(cond, body, carry)
    # stopped before t1 with no failure: a step budget (or the hook's) ran out
    result = diffrax.RESULTS.where(
        (c.result == diffrax.RESULTS.successful) & (c.t < t1),
        diffrax.RESULTS.max_steps_reached,
        c.result,
    )
    return LoopOutcome(c.t, c.y, c.args, c.extra, result, c.num_steps, c.num_rejected)
