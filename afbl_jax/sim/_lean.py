"""A lean adaptive loop: one `jax.lax.while_loop` driving diffrax's own pieces over groups of
cases.

`lean_loop` integrates an ensemble of n cases split into G groups of g = n / G consecutive
cases. Each group is one ODE system with its own step sequence (its own time, step size and
step-size controller state), but all groups are advanced together: one call of a diffrax
solver's own ``step`` (its Runge-Kutta stages, error estimate and dense-output information)
on the whole ensemble, with each case's step running over its group's interval, and one call
of a diffrax step-size controller's own ``adapt_step_size`` per group (`equinox.filter_vmap`:
PID control, clipping onto the group's jump times). Nothing else is carried: no saving
machinery, events, progress meter or adjoint bookkeeping.

Layout: every leaf of the state and of ``args`` has the case axis LAST (``(..., n)``; a
per-case scalar is ``(n,)``), so that the solver's stage arithmetic runs over long contiguous
case rows (rather than short per-case vectors, as with a case axis first or a ``vmap`` over
groups). Times are
per group, shape (G,); the solver sees them per case (repeated over each group's cases).
``group_field(t, y, args, inputs)`` is the vector field of ONE group: t a scalar, the leaves
of y and args of shape ``(..., g)``, ``inputs`` that group's slice of ``inputs`` (a pytree
with leading axis G).

What a caller needs from the trajectory it computes inside the loop from every step
(`Step`: the groups' intervals, both ends and diffrax's dense interpolation), with a hook:

- ``after_step(extra, step, args, keep, at_boundary, inputs) -> (extra, y1, args, jumped,
  stop)`` runs after every step; ``keep`` (G,): the group accepted its step (its outputs are
  used only then: the hook must leave a group's part of ``extra`` unchanged where keep is
  False).
  Running reductions over the trajectory (peaks at sample times, integrals, soft maxima)
  update ``extra``; a hook may change the state and ``args`` (digital control: a sample
  instant's discrete update) and say so with ``jumped`` (G,) (the solver then re-evaluates
  its first stage, as after a jump time), or end a group's solve (``stop`` (G,)).
- ``on_state(extra, t, y, args, inputs) -> (extra, args)`` runs on the groups' accepted
  times (G,) and state: once on the initial state, then after every step on the new state
  (that of the next step): per-case decisions the vector field reads from ``args`` (e.g.
  freezing the cases that crossed a limit). It runs last in the step, on the selected
  state, so that XLA keeps the step one sequence of work (computed beside the solver's
  stages, XLA may schedule it on a second thread, and the hand-overs cost CPU time).
- ``boundary(extra, inputs) -> t`` (G,): a group's steps never cross its t (the next sample
  instant; +inf: none). ``at_boundary`` tells the hook which groups' accepted steps ended there, and
  the step budget ``max_steps`` counts each group's steps since its last boundary (with no
  boundary: all its steps).

Every hook also gets ``inputs``: the leaves of ``inputs`` of the groups it is called on
(leading axis G).

Work queue (``lanes``, dividing G): the loop advances ``lanes`` groups at a time (its working
set). When a group is done, its lane takes the next group not yet started, so no lane waits
for the slowest group of a fixed set. The hooks see the lanes' groups (G = ``lanes`` in the
shapes above). A newly loaded group's first stage is evaluated afresh (as after a jump time),
and the initial-step heuristic runs on blocks of ``lanes`` groups, so a group's arithmetic is
the same as without the queue (bitwise; tested). The leaves of ``extra`` must be per group
(leading axis G: shape (G,), or one block per group (G, ...)) or per case with the case axis
last (``(..., n)``); `lean_loop` checks this. A group's slice of a per-group leaf is
contiguous, of a per-case leaf strided: large per-case records are cheaper as blocks.

Per group the loop does what `diffrax.diffeqsolve` does for one system (the same solver step,
the same controller call, non-finite error estimates rejected, the last step clipped onto t1
within 100 ulps), so both take the same steps. The first stage is evaluated afresh per group:
until its first step is accepted and after a jump (diffrax's solver step takes one flag for the
whole state, so the loop evaluates the vector field itself where any group needs it and hands
the solver each group's own first stage): a group's steps do not depend on the groups that
share the loop with it. The loop is a ``while_loop``: forward-mode
differentiable, not reverse-mode (`jax.grad` needs `diffrax.diffeqsolve` and its
checkpointed adjoint).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp

from .._typing import Array


class Groups(NamedTuple):
    """How the n cases (last axis) split into G groups of g consecutive cases."""

    count: int
    size: int

    def per_case(self, a) -> Array:
        """A per-group array (G,) repeated over each group's cases, shape (n,)."""
        a = jnp.asarray(a)  # a broadcast, not jnp.repeat (a scatter and a gather on CPU)
        return jnp.broadcast_to(a[..., None], (*a.shape, self.size)).reshape(*a.shape[:-1], -1)

    def view(self, tree):
        """Leaves (..., n) -> (..., G, g)."""
        return jax.tree.map(lambda x: x.reshape(*x.shape[:-1], self.count, self.size), tree)

    def flat(self, tree):
        """Leaves (..., G, g) -> (..., n)."""
        return jax.tree.map(lambda x: x.reshape(*x.shape[:-2], self.count * self.size), tree)


class Step(NamedTuple):
    """One step of `lean_loop`: group i from (t0[i], y0) to (t1[i], y1) (state leaves with the
    case axis last), with diffrax's dense interpolation (`evaluate`)."""

    t0: Array
    t1: Array
    y0: Any
    y1: Any
    interpolation: diffrax.AbstractLocalInterpolation

    def evaluate(self, t_case):
        """The state at per-case times ``t_case`` (n,), each within its group's step."""
        return jax.vmap(lambda it, t: it.evaluate(t), in_axes=(-1, -1), out_axes=-1)(
            self.interpolation, t_case
        )

    def evaluate_groups(self, t_group, groups: Groups):
        """The state at per-group times ``t_group`` (G,), each within its group's step; the
        interpolation evaluated once per group (its coefficients shared by the group's
        cases), leaves with the case axis last."""
        viewed = groups.view(self.interpolation)

        def one(it, t):
            it = eqx.tree_at(lambda i: (i.t0, i.t1), it, (it.t0[0], it.t1[0]))
            return it.evaluate(t)

        return groups.flat(jax.vmap(one, in_axes=(-2, 0), out_axes=-2)(viewed, t_group))


class LoopOutcome(NamedTuple):
    """What `lean_loop` returns, per group where shaped (G,): end times, the state and
    ``args`` at the end, the hook's ``extra``, the diffrax results (`diffrax.RESULTS`), the
    step counts (all steps, rejected steps)."""

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


def _no_hook(extra, step, args, keep, at_boundary, inputs):
    del step, at_boundary, inputs
    false = jnp.zeros_like(keep)
    return extra, None, args, false, false


def _results(result, G: int):
    """A diffrax result for each of G groups (shape (G,))."""
    return jax.tree.map(lambda v: jnp.broadcast_to(v, (G,)), result)


def _where(pred, a, b):
    """`diffrax.RESULTS.where` per group."""
    return jax.vmap(diffrax.RESULTS.where)(pred, a, b)


def _no_check(extra, t, y, args, inputs):
    del t, y, inputs
    return extra, args


def _prevbefore(t, n: int):
    for _ in range(n):
        t = jnp.nextafter(t, jnp.asarray(-jnp.inf, t.dtype))
    return t


def ensemble_field(group_field: Callable, inputs, groups: Groups) -> Callable:
    """The vector field `lean_loop` integrates: ``field(t_case, y, args)`` on the whole
    ensemble (leaves of y and args with the case axis last, ``t_case`` (n,) per-case times,
    equal within a group), each group through ``group_field(t, y_g, args_g, inputs_g)``."""

    def field(t_case, y, a):
        t_group = t_case.reshape(groups.count, groups.size)[:, 0]
        out = jax.vmap(group_field, in_axes=(0, -2, -2, 0), out_axes=-2)(
            t_group, groups.view(y), groups.view(a), inputs
        )
        return groups.flat(out)

    return field


def _extra_kinds(extra, G: int, n: int):
    """Per leaf of ``extra``: True per group (shape (G,), or (G, ...) with a last axis other
    than n: one block per group), False per case (last axis n)."""

    def kind(x):
        shape = jnp.shape(x)
        if len(shape) == 1 and shape[0] == G:
            return True
        if len(shape) >= 1 and shape[-1] == n:
            return False
        if len(shape) >= 1 and shape[0] == G:
            return True
        raise ValueError(
            f"lean_loop: with lanes, every leaf of extra must be per group (leading axis of "
            f"length {G}) or per case (case axis last, length {n}); got a leaf of shape "
            f"{shape}."
        )

    return jax.tree.map(kind, extra)


def _take(tree, kinds, i, g: int):
    """Group i's slice: leaves per group (``kinds`` True: leading axis) -> x[i]; per case
    (False: case axis last) -> (..., g)."""

    def one(x, per_group):
        if per_group:
            return jax.lax.dynamic_index_in_dim(x, i, 0, keepdims=False)
        return jax.lax.dynamic_slice_in_dim(x, i * g, g, axis=x.ndim - 1)

    return jax.tree.map(one, tree, kinds)


def _put(tree, kinds, i, value, g: int):
    """``tree`` with group i's slice (`_take`) set to ``value``."""

    def one(x, per_group, v):
        if per_group:
            return jax.lax.dynamic_update_index_in_dim(x, v, i, 0)
        return jax.lax.dynamic_update_slice_in_dim(x, v, i * g, axis=x.ndim - 1)

    return jax.tree.map(one, tree, kinds, value)


def _first(tree, kinds, count: int, g: int):
    """The slices of the first ``count`` groups."""
    return jax.tree.map(lambda x, k: x[:count] if k else x[..., : count * g], tree, kinds)


def _all(tree, value: bool):
    return jax.tree.map(lambda _: value, tree)


def _fsal(solver, solver_state) -> bool:
    """Whether ``solver_state`` is an explicit Runge-Kutta method's FSAL state: (first-step
    flag, the vector field at the step's start)."""
    return isinstance(solver, diffrax.AbstractERK) and isinstance(solver_state, tuple)


def _by_blocks(fn, controllers, y0, args, inputs, G: int, L: int, g: int):
    """``fn(controllers, y (..., L, g), args (..., L, g), inputs)`` on consecutive blocks of L
    of the G groups (`jax.lax.map`), outputs per group (leading axis G)."""
    B = G // L
    ctrl_arr, ctrl_static = eqx.partition(controllers, eqx.is_array)

    def per_group(x):
        return x.reshape(B, L, *x.shape[1:])

    def per_case(x):
        return jnp.moveaxis(x.reshape(*x.shape[:-1], B, L, g), -3, 0)

    def one(xs):
        c, y, a, inp = xs
        return fn(eqx.combine(c, ctrl_static), y, a, inp)

    out = jax.lax.map(
        one,
        (
            jax.tree.map(per_group, ctrl_arr),
            jax.tree.map(per_case, y0),
            jax.tree.map(per_case, args),
            jax.tree.map(per_group, inputs),
        ),
    )
    # a per-block constant (a Python constant in the controller's state) -> per group
    return jax.tree.map(
        lambda x: x.reshape(G, *x.shape[2:]) if x.ndim >= 2 else jnp.repeat(x, L), out
    )


def _no_solver_state(c: _Carry) -> _Carry:
    return dataclasses.replace(c, solver_state=None)


class _Queue(eqx.Module):
    """The work queue: the lanes' carry, inputs and step-size controllers (array leaves), the
    pool group each lane holds, which lanes still hold a group, the next group to start, and
    the pool's carries (each group's initial carry until it starts, its final one once
    done)."""

    lanes: _Carry
    inputs: Any
    controllers: Any
    group: Array
    active: Array
    next: Array
    pool: _Carry


def lean_loop(
    group_field: Callable,
    inputs,
    solver: diffrax.AbstractSolver,
    controllers: diffrax.AbstractStepSizeController,
    t0,
    t1,
    y0,
    args=None,
    *,
    groups: Groups,
    max_steps: int,
    extra=None,
    after_step: Callable | None = None,
    on_state: Callable | None = None,
    boundary: Callable | None = None,
    lanes: int | None = None,
    bridge_jumps: bool = False,
    dt0: float | None = None,
) -> LoopOutcome:
    """Integrate the ensemble from t0 to t1 (module docstring). ``controllers``: one diffrax
    step-size controller per group (array leaves with leading axis G, e.g. built with
    `equinox.filter_vmap`); the first step of each group comes from its controller's
    ``init`` with ``dt0`` [s] (as `diffrax.diffeqsolve` passes its ``dt0``; None: diffrax's
    initial-step heuristic for a PID controller, two more evaluations of the vector field, a
    further copy of it in the compiled program). ``after_step`` None: no
    hook; its ``y1`` output None: the state is unchanged. ``lanes``: groups advanced at a time
    (a work queue, module docstring); None or >= G: all groups at once. ``bridge_jumps``
    (a first-same-as-last ``solver``, e.g. Tsit5): a step clipped onto a jump time ends one
    ulp before it and the next one starts one ulp after it (diffrax's
    `ClipStepSizeController`), so the state is not advanced over those two ulps of time; with
    ``bridge_jumps`` it is, by the derivative at the step's end (one Euler step over the
    gap). In float32 the two ulps are ~4e-6 s at t ~ 20 s, and a group with many jump times
    (the union of its cases') would otherwise run its states behind the time-dependent
    inputs (references, wind); in float64 the gap is negligible."""
    after_step = _no_hook if after_step is None else after_step
    on_state = _no_check if on_state is None else on_state
    G, g = groups.count, groups.size
    if lanes is not None and (isinstance(lanes, bool) or int(lanes) < 1):
        raise ValueError(f"lean_loop: lanes must be an integer >= 1 or None, got {lanes!r}.")
    L = G if lanes is None else min(int(lanes), G)
    if G % L:
        raise ValueError(f"lean_loop: lanes ({L}) must divide the number of groups ({G}).")
    t0 = jnp.asarray(t0)
    t1 = jnp.asarray(t1, t0.dtype)
    order = solver.error_order(diffrax.ODETerm(ensemble_field(group_field, inputs, groups)))

    first = None if dt0 is None else jnp.asarray(dt0, t0.dtype)

    def init_group(controller, y, a, inp):
        term_g = diffrax.ODETerm(lambda t, yy, aa: group_field(t, yy, aa, inp))
        return controller.init(term_g, t0, t1, y, first, a, solver.func, order)

    init_all = eqx.filter_vmap(init_group, in_axes=(eqx.if_array(0), -2, -2, 0))
    if L == G or dt0 is not None:  # a given first step does not depend on the pool
        t_next, controller_state = init_all(controllers, groups.view(y0), groups.view(args), inputs)
    else:
        # L groups at a time, as the loop steps them: XLA's rounding of the initial-step
        # heuristic depends on the array size, and a group's result must not depend on the pool
        t_next, controller_state = _by_blocks(init_all, controllers, y0, args, inputs, G, L, g)
    t_next = jnp.minimum(t_next, t1)
    # every leaf per group (a Python constant in the controller's state, e.g. a flag, too)
    controller_state = jax.tree.map(
        lambda x: x if eqx.is_array(x) else jnp.full((G,), x), controller_state
    )
    if boundary is not None:
        t_next = jnp.minimum(t_next, boundary(extra, inputs))
    # as diffeqsolve: a step ending within 100 ulps of t1 is extended onto t1
    t1_floor = _prevbefore(t1, 100)
    zeros = jnp.zeros((G,), jnp.int32)
    false = jnp.zeros((G,), bool)
    extra, args = on_state(extra, jnp.full((G,), t0), y0, args, inputs)
    pool = _Carry(
        jnp.full((G,), t0),
        t_next,
        y0,
        args,
        None,
        controller_state,
        # a group's first stage is evaluated afresh until it accepts its first step
        jnp.ones((G,), bool),
        zeros,
        zeros,
        zeros,
        _results(diffrax.RESULTS.successful, G),
        false,
        extra,
    )

    def running(c: _Carry) -> Array:
        ok = c.result == diffrax.RESULTS.successful
        return (c.t < t1) & ok & ~c.stop & (c.budget_used < max_steps)

    def adapt(controller, ta, tb, y, y1, err, state):
        return controller.adapt_step_size(ta, tb, y, y1, None, err, order, state)

    def solver_init(c: _Carry, inp, grp: Groups) -> _Carry:
        term = diffrax.ODETerm(ensemble_field(group_field, inp, grp))
        state = solver.init(term, grp.per_case(c.t), grp.per_case(c.t_next), c.y, c.args)
        return dataclasses.replace(c, solver_state=state)

    def advance(c: _Carry, inp, ctrl, grp: Groups) -> _Carry:
        """One step of the groups ``grp`` (inputs ``inp``, step-size controllers ``ctrl``)."""
        term = diffrax.ODETerm(ensemble_field(group_field, inp, grp))
        live = running(c)
        no = jnp.zeros_like(live)
        extra, args = c.extra, c.args
        t_case, t_next_case = grp.per_case(c.t), grp.per_case(c.t_next)
        solver_state, made_jump = c.solver_state, jnp.any(c.made_jump & live)
        if _fsal(solver, solver_state):
            # the first stage afresh for the groups that need it only (the solver's flag is one
            # for all): a group's steps do not depend on which groups share the loop with it
            first_step, f0 = solver_state
            fresh = grp.per_case(c.made_jump & live)

            def first_stage(f0):
                f = term.vf(t_case, c.y, args)
                return jax.tree.map(lambda a, b: jnp.where(fresh, a, b), f, f0)

            f0 = jax.lax.cond(made_jump, first_stage, lambda f0: f0, f0)
            solver_state, made_jump = (jnp.zeros_like(first_step), f0), False
        y1, y_error, dense, solver_state, solver_result = solver.step(
            term, t_case, t_next_case, c.y, args, solver_state, made_jump
        )
        y_error = jax.tree.map(lambda e: jnp.where(jnp.isnan(e), jnp.inf, e), y_error)
        keep, t_new, t_next, jump, controller_state, controller_result = eqx.filter_vmap(
            adapt, in_axes=(eqx.if_array(0), 0, 0, -2, -2, -2, 0)
        )(
            ctrl,
            c.t,
            c.t_next,
            grp.view(c.y),
            grp.view(y1),
            grp.view(y_error),
            c.controller_state,
        )
        keep = keep & live
        t_new = jnp.where(live, jnp.minimum(t_new, t1), c.t)
        if bridge_jumps and _fsal(solver, solver_state):
            # the ulps skipped past a jump time, crossed with the derivative at the step's end
            gap = grp.per_case(jnp.where(keep, t_new - c.t_next, 0.0))
            y1 = jax.tree.map(lambda y, f: jnp.where(gap > 0, y + gap * f, y), y1, solver_state[1])
        clip = t_next > t1_floor
        t_next = jnp.where(clip, jnp.where(keep, t1, t_new + 0.5 * (t1 - t_new)), t_next)
        at_boundary = keep & (no if boundary is None else t_new >= boundary(c.extra, inp))
        step = Step(
            c.t, c.t_next, c.y, y1, solver.interpolation_cls(t0=t_case, t1=t_next_case, **dense)
        )
        extra, y_hook, args_out, jumped, stop = after_step(
            extra, step, args, keep, at_boundary, inp
        )
        y1 = y1 if y_hook is None else y_hook
        if boundary is not None:
            t_next = jnp.maximum(
                jnp.minimum(t_next, boundary(extra, inp)), jnp.nextafter(t_new, t1)
            )
        t_next = jnp.where(live, t_next, c.t_next)
        keep_case = grp.per_case(keep)

        def pick(a, b):
            def one(x, z):
                return jnp.where(keep_case if jnp.ndim(x) else jnp.any(keep), x, z)

            return jax.tree.map(one, a, b)

        ok = _results(diffrax.RESULTS.successful, grp.count)
        result = _where(keep, _results(solver_result, grp.count), ok)
        result = _where(result == diffrax.RESULTS.successful, controller_result, result)
        result = _where(live, result, c.result)
        y_new = pick(y1, c.y)
        extra, args_new = on_state(extra, t_new, y_new, pick(args_out, args), inp)
        return _Carry(
            t_new,
            t_next,
            y_new,
            args_new,
            pick(solver_state, c.solver_state),
            # a finished group's controller state is not used again: not selected (a select
            # here would copy its jump times every step)
            controller_state,
            jnp.where(keep, jump | jumped, c.made_jump),
            jnp.where(at_boundary, 0, c.budget_used + live),
            c.num_steps + live,
            c.num_rejected + (live & ~keep),
            result,
            c.stop | (keep & stop),
            extra,
        )

    if L == G:
        c = jax.lax.while_loop(
            lambda c: jnp.any(running(c)),
            lambda c: advance(c, inputs, controllers, groups),
            solver_init(pool, inputs, groups),
        )
    else:
        c = _run_queue(pool, inputs, controllers, G, L, g, running, solver_init, advance)
    # stopped before t1 with no failure: a step budget (or the hook's) ran out
    result = _where(
        (c.result == diffrax.RESULTS.successful) & (c.t < t1),
        _results(diffrax.RESULTS.max_steps_reached, G),
        c.result,
    )
    return LoopOutcome(c.t, c.y, c.args, c.extra, result, c.num_steps, c.num_rejected)


def _run_queue(pool: _Carry, inputs, controllers, G, L, g, running, solver_init, advance):
    """`lean_loop`'s work queue: L lanes over the G groups of ``pool``; returns the pool with
    every group's final carry."""
    n = G * g
    kinds = _Carry(
        True,
        True,
        _all(pool.y, False),
        _all(pool.args, False),
        None,
        _all(pool.controller_state, True),
        True,
        True,
        True,
        True,
        _all(pool.result, True),
        True,
        _extra_kinds(pool.extra, G, n),
    )
    inputs_arr, inputs_static = eqx.partition(inputs, eqx.is_array)
    ctrl_arr, ctrl_static = eqx.partition(controllers, eqx.is_array)
    in_kinds, ctrl_kinds = _all(inputs_arr, True), _all(ctrl_arr, True)
    lane_groups = Groups(L, g)

    def refill(q: _Queue) -> _Queue:
        """Every lane whose group is done: its carry to the pool, the next group into it."""

        def need(q):
            return q.active & ~running(q.lanes)

        def one(q: _Queue) -> _Queue:
            lane = jnp.argmax(need(q))
            done = _take(_no_solver_state(q.lanes), kinds, lane, g)
            pool = _put(q.pool, kinds, q.group[lane], done, g)
            nxt = q.next
            more = nxt < G
            nxt = jnp.minimum(nxt, G - 1)

            def load(tree, pool_tree, k):
                new = _take(pool_tree, k, nxt, g)
                old = _take(tree, k, lane, g)
                chosen = jax.tree.map(lambda a, b: jnp.where(more, a, b), new, old)
                return _put(tree, k, lane, chosen, g)

            lanes = load(_no_solver_state(q.lanes), pool, kinds)
            # a new group's first stage is evaluated afresh; a lane left empty never asks
            lanes = dataclasses.replace(
                lanes,
                solver_state=q.lanes.solver_state,
                made_jump=lanes.made_jump.at[lane].set(more),
            )
            return _Queue(
                lanes,
                load(q.inputs, inputs_arr, in_kinds),
                load(q.controllers, ctrl_arr, ctrl_kinds),
                q.group.at[lane].set(jnp.where(more, nxt, q.group[lane])),
                q.active.at[lane].set(more),
                q.next + more.astype(q.next.dtype),
                pool,
            )

        def all_lanes(q):
            return jax.lax.while_loop(lambda q: jnp.any(need(q)), one, q)

        return jax.lax.cond(jnp.any(need(q)), all_lanes, lambda q: q, q)

    def step(q: _Queue) -> _Queue:
        lanes = advance(
            q.lanes,
            eqx.combine(q.inputs, inputs_static),
            eqx.combine(q.controllers, ctrl_static),
            lane_groups,
        )
        return refill(dataclasses.replace(q, lanes=lanes))

    first_inputs = _first(inputs_arr, in_kinds, L, g)
    lanes0 = solver_init(
        _first(pool, kinds, L, g), eqx.combine(first_inputs, inputs_static), lane_groups
    )
    q = _Queue(
        lanes0,
        first_inputs,
        _first(ctrl_arr, ctrl_kinds, L, g),
        jnp.arange(L, dtype=jnp.int32),
        jnp.ones((L,), bool),
        jnp.asarray(L, jnp.int32),
        pool,
    )
    q = jax.lax.while_loop(lambda q: jnp.any(q.active), step, refill(q))
    return q.pool
