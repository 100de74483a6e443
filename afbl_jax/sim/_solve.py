"""One case: the closed loop solved by a diffrax adaptive solver (`simulate`).

Continuous control: one `diffrax.diffeqsolve` over [t0, t1] with PID step control clipped onto
every jump time of the scenario and a divergence event. Digital control: `jax.lax.scan` over
the sample instants (`afbl_jax.sim.sample_instant`), one adaptive solve per sample interval with
the held command. Both are pure functions of arrays: `simulate` works under `jax.jit`,
`jax.vmap` and `jax.grad` (the adjoint is diffrax's `RecursiveCheckpointAdjoint`:
discretise-then-optimise, the exact gradient of the numerical solution, with checkpointed
memory; with noise off the digital loop is differentiable too).
"""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp

from .._typing import Array, Float, Int, Scalar
from .._validation import check_positive
from ..model import (
    AbstractAerodynamics,
    AbstractController,
    PositionHold,
    QuadrotorParams,
    UnmodeledDynamics,
)
from ..scenario import Scenario
from ._closed_loop import (
    CaseInputs,
    ClosedLoop,
    ClosedLoopState,
    DivergenceLimits,
    Held,
    Signals,
)
from ._digital import held_index, initial_buffer, interpolate, sample_instant, sample_time
from ._executables import CachedJit
from ._status import STATUS_MAX_STEPS, STATUS_OK, status_from

SOLVERS = {"tsit5": diffrax.Tsit5, "dopri5": diffrax.Dopri5, "dopri8": diffrax.Dopri8}
"""Solvers selectable by name (Dopri5 is MATLAB's ode45 pair)."""


SAVINGS = ("saveat", "dense")
"""How `simulate` takes its samples (its ``saving`` argument)."""


def get_solver(solver: str | diffrax.AbstractSolver) -> diffrax.AbstractSolver:
    """A diffrax solver instance from a name in `SOLVERS` (or the instance itself)."""
    if isinstance(solver, diffrax.AbstractSolver):
        return solver
    try:
        return SOLVERS[solver]()
    except KeyError:
        raise ValueError(f"unknown solver {solver!r}; allowed: {', '.join(SOLVERS)}.") from None


class SimulationResult(eqx.Module):
    """Output of `simulate`.

    Trajectory arrays have a leading time axis of length ``n_save`` (empty when n_save = 0);
    samples after an early stop (divergence) are ``inf`` (states and signals; with continuous
    control the times too, as diffrax fills them). With digital
    control the samples are linear interpolations of the states at the control samples (exact
    there) and ``u_command`` is the held command.

    Attributes:
        ts: save times [s].
        plant: plant states, (n_save, 12), layout of the loop's plant (`afbl_jax.model`).
        controller_state: (n_save, 4).
        reference, error: r and e = r - q per channel (phi, theta, psi, z), (n_save, 4).
        u_command, u_applied: inputs (u1, u2, u3, u4) before / after rotor saturation (and
            motor lag).
        rotor_speeds: (n_save, 4) [rad/s].
        disturbance_force: (n_save, 3) [N]; disturbance_torque: (n_save, 3) [N m] (pulses plus
            aerodynamic wrench).
        position_error: p_ref - p (x, y) [m], (n_save, 2), with a position loop (else None).
        final: closed-loop state at the end of the run (t1, or where it stopped).
        t_final: time the run ended [s].
        ise_attitude, ise_altitude, effort, saturation: cost integrals at the end of the run
            (`COST_LAYOUT`); ise_position: with a position loop (else None).
        failure_cause: `afbl_jax.metrics.FAILURE_CAUSES` code of the end state; final_saturation:
            commanded rotor saturation on the end state [-] (`ClosedLoop.anatomy`).
        status: a `Status` code (0 ok, 1 diverged, 2 max_steps reached, 3 solver failure;
            `status_message` explains each).
        num_steps, num_accepted_steps, num_rejected_steps: solver statistics (totals over the
            sample intervals with digital control).
    """

    ts: Float[Array, " n"]
    plant: Float[Array, "n 12"]
    controller_state: Float[Array, "n 4"]
    reference: Float[Array, "n 4"]
    error: Float[Array, "n 4"]
    u_command: Float[Array, "n 4"]
    u_applied: Float[Array, "n 4"]
    rotor_speeds: Float[Array, "n 4"]
    disturbance_force: Float[Array, "n 3"]
    disturbance_torque: Float[Array, "n 3"]
    final: ClosedLoopState
    t_final: Scalar
    ise_attitude: Scalar
    ise_altitude: Scalar
    effort: Scalar
    saturation: Scalar
    status: Int[Array, ""]
    num_steps: Int[Array, ""]
    num_accepted_steps: Int[Array, ""]
    num_rejected_steps: Int[Array, ""]
    failure_cause: Int[Array, ""]
    final_saturation: Scalar
    position_error: Float[Array, "n 2"] | None = None
    ise_position: Scalar | None = None

    @property
    def ok(self) -> Array:
        return self.status == STATUS_OK


def _result(
    loop: ClosedLoop,
    inputs: CaseInputs,
    ts,
    traj: ClosedLoopState,
    signals: Signals,
    final: ClosedLoopState,
    t_final,
    status,
    steps,
) -> SimulationResult:
    cause, final_sat = loop.anatomy(t_final, final, status, inputs)
    return SimulationResult(
        ts=ts,
        plant=traj.plant,
        controller_state=traj.controller,
        reference=signals.reference,
        error=signals.error,
        u_command=signals.u_command,
        u_applied=signals.u_applied,
        rotor_speeds=signals.rotor_speeds,
        disturbance_force=signals.force,
        disturbance_torque=signals.torque,
        final=final,
        t_final=t_final,
        ise_attitude=final.cost[0],
        ise_altitude=final.cost[1],
        effort=final.cost[2],
        saturation=final.cost[3],
        status=status,
        num_steps=steps[0],
        num_accepted_steps=steps[1],
        num_rejected_steps=steps[2],
        failure_cause=cause,
        final_saturation=final_sat,
        position_error=signals.position_error,
        ise_position=None if loop.position_loop is None else final.cost[4],
    )


def _stats(sol) -> Array:
    return jnp.stack(
        [
            jnp.asarray(sol.stats[k])
            for k in ("num_steps", "num_accepted_steps", "num_rejected_steps")
        ]
    )


def _finite(y: ClosedLoopState) -> Array:
    return jnp.all(jnp.isfinite(y.cost)) & jnp.all(jnp.isfinite(y.plant))


def save_times(scenario: Scenario, n_save: int, dtype) -> Array:
    """``n_save`` equally spaced times [s] over the interval from t0 to t1."""
    return scenario.t0 + (scenario.t1 - scenario.t0) * jnp.linspace(0.0, 1.0, n_save, dtype=dtype)


def step_size_controller(rtol, atol, jump_ts, norm=None) -> diffrax.AbstractStepSizeController:
    """PID step control (optionally with an ensemble ``norm``) clipped onto ``jump_ts``."""
    kwargs = {} if norm is None else {"norm": norm}
    return diffrax.ClipStepSizeController(
        diffrax.PIDController(rtol=rtol, atol=atol, **kwargs), jump_ts=jump_ts
    )


def _empty(tree, dtype=None):
    return jax.tree.map(lambda a: jnp.zeros((0, *a.shape), dtype or a.dtype), tree)


def _pad_after(ts, t_final, tree):
    """``tree`` (leading time axis) with the samples after ``t_final`` set to ``inf``."""
    dead = ts > t_final
    return jax.tree.map(
        lambda a: jnp.where(dead.reshape(-1, *([1] * (a.ndim - 1))), jnp.inf, a), tree
    )


def _continuous(
    loop: ClosedLoop,
    inputs: CaseInputs,
    solver,
    rtol,
    atol,
    n_save,
    max_steps,
    adjoint,
    dense: bool,
) -> SimulationResult:
    dtype = jnp.result_type(float)
    sc = inputs.scenario
    y0 = loop.initial_state(inputs, dtype)
    ts = save_times(sc, n_save, dtype) if n_save else None
    dense = bool(dense and n_save)  # static: without samples there is nothing to evaluate
    if dense:
        saveat = diffrax.SaveAt(t1=True, dense=True)
    else:
        saves = [diffrax.SubSaveAt(t1=True)] + ([diffrax.SubSaveAt(ts=ts)] if n_save else [])
        saveat = diffrax.SaveAt(subs=saves)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(loop.vector_field),
        solver,
        sc.t0,
        sc.t1,
        None,
        y0,
        args=(inputs, None),
        saveat=saveat,
        stepsize_controller=step_size_controller(rtol, atol, sc.jump_times()),
        max_steps=max_steps,
        event=diffrax.Event(lambda t, y, args, **kw: loop.diverged_at(t, y, args[0])),
        adjoint=adjoint,
        throw=False,
    )
    end_ts, end_ys = (sol.ts, sol.ys) if dense else (sol.ts[0], sol.ys[0])
    final = jax.tree.map(lambda a: a[-1], end_ys)
    t_final = end_ts[-1]

    def signals_at(save_ts, traj):
        return jax.vmap(lambda t, y: loop.signals_and_derivative(t, y, inputs)[0])(save_ts, traj)

    if dense:
        # the step's own interpolant (as SaveAt(ts) uses), evaluated after the solve
        traj = jax.vmap(sol.evaluate)(jnp.minimum(ts, t_final))
        save_ts, traj, signals = _pad_after(ts, t_final, (ts, traj, signals_at(ts, traj)))
    elif n_save:
        # diffrax pads the times and states after an early stop with inf; the signals too
        save_ts, traj = sol.ts[1], sol.ys[1]
        signals = _pad_after(save_ts, t_final, signals_at(save_ts, traj))
    else:
        save_ts, traj = jnp.zeros((0,), dtype), _empty(y0)
        signals = _empty(loop.signals_and_derivative(sc.t0, y0, inputs)[0])
    status = status_from(sol.result, ~_finite(final))
    return _result(loop, inputs, save_ts, traj, signals, final, t_final, status, _stats(sol))


def _digital(
    loop: ClosedLoop, inputs: CaseInputs, solver, rtol, atol, n_save, max_steps, adjoint
) -> SimulationResult:
    dtype = jnp.result_type(float)
    sc = inputs.scenario
    y0 = loop.initial_state(inputs, dtype)
    t0, t1 = sc.t0.astype(dtype), sc.t1.astype(dtype)
    h = 1.0 / loop.sampling.control_rate.astype(dtype)
    stepsize = step_size_controller(rtol, atol, sc.jump_times())
    term = diffrax.ODETerm(loop.vector_field)
    event = diffrax.Event(lambda t, y, args, **kw: loop.diverged_at(t, y, args[0]))

    def step(carry, k):
        y, buf, status, t_final, nsteps = carry
        t_k = sample_time(t0, h, k)
        alive = (status == STATUS_OK) & (t_k < t1)
        start = jnp.minimum(t_k, t1)
        end = jnp.where(alive, jnp.minimum(sample_time(t0, h, k + 1), t1), start)
        y_in, buf, held, dctrl = sample_instant(loop, k, t_k, y, buf, inputs)
        sol = diffrax.diffeqsolve(
            term,
            solver,
            start,
            end,
            end - start,
            y_in,
            args=(inputs, held),
            saveat=diffrax.SaveAt(t1=True),
            stepsize_controller=stepsize,
            max_steps=max_steps,
            event=event,
            adjoint=adjoint,
            throw=False,
        )
        y_end = jax.tree.map(lambda a: a[-1], sol.ys)
        y_end = eqx.tree_at(lambda s: s.controller, y_end, y.controller + h * dctrl)
        new_status = jnp.where(alive, status_from(sol.result, ~_finite(y_end)), status)
        y_new = jax.tree.map(lambda a, b: jnp.where(alive, a, b), y_end, y)
        t_final = jnp.where(alive, sol.ts[-1], t_final)
        nsteps = nsteps + jnp.where(alive, _stats(sol), 0)
        out = (y_new, held, t_final) if n_save else None
        return (y_new, buf, new_status, t_final, nsteps), out

    carry0 = (
        y0,
        initial_buffer(loop, y0),
        jnp.asarray(STATUS_OK, jnp.int32),
        t0,
        jnp.zeros(3, jnp.int32),
    )
    (final, _, status, t_final, nsteps), outs = jax.lax.scan(
        step, carry0, jnp.arange(loop.sampling.max_samples, dtype=jnp.int32)
    )
    # not enough samples to reach t1: reported like a solver running out of steps
    status = jnp.where((status == STATUS_OK) & (t_final < t1), STATUS_MAX_STEPS, status)
    status = status.astype(jnp.int32)
    if n_save:
        ys, helds, t_ends = outs
        ts = save_times(sc, n_save, dtype)
        states = jax.tree.map(lambda a0, a: jnp.concatenate([a0[None], a]), y0, ys)
        traj = interpolate(ts, jnp.concatenate([t0[None], t_ends]), states)
        held = jax.tree.map(lambda a: a[held_index(ts, t0, h, loop.sampling.max_samples)], helds)
        signals = jax.vmap(lambda t, y, hd: loop.signals_and_derivative(t, y, inputs, hd)[0])(
            ts, traj, held
        )
        # after an early stop the trajectory is padded with inf, as in the continuous loop
        traj, signals = _pad_after(ts, t_final, (traj, signals))
    else:
        ts, traj = jnp.zeros((0,), dtype), _empty(y0)
        signals = _empty(
            loop.signals_and_derivative(
                t0, y0, inputs, Held(jnp.zeros(4, dtype), jnp.zeros(4, dtype))
            )[0]
        )
    return _result(loop, inputs, ts, traj, signals, final, t_final, status, tuple(nsteps))


def _simulate_case(loop, inputs, solver, rtol, atol, n_save, max_steps, adjoint, dense):
    if loop.digital:
        return _digital(loop, inputs, solver, rtol, atol, n_save, max_steps, adjoint)
    return _continuous(loop, inputs, solver, rtol, atol, n_save, max_steps, adjoint, dense)


_simulate = CachedJit(_simulate_case, "simulate")


def simulate(
    controller: AbstractController | ClosedLoop,
    scenario: Scenario,
    vehicle: QuadrotorParams | None = None,
    model: QuadrotorParams | None = None,
    *,
    solver: str | diffrax.AbstractSolver = "tsit5",
    rtol: float = 1e-6,
    atol: float = 1e-8,
    n_save: int = 401,
    max_steps: int = 16384,
    limits: DivergenceLimits | None = None,
    adjoint: diffrax.AbstractAdjoint | None = None,
    unmodeled: UnmodeledDynamics | None = None,
    aerodynamics: AbstractAerodynamics | str | None = None,
    position_loop: PositionHold | None = None,
    saving: str = "saveat",
) -> SimulationResult:
    """Simulate one closed-loop case.

    Args:
        controller: `FBLPID`, `AFBL` or `AFBLPaper` (gains are dynamic: vmap/grad over them), or
            a whole `ClosedLoop` (then ``unmodeled`` must be None).
        scenario: reference, disturbances, payload, wind, initial state, time span.
        vehicle: true vehicle parameters (default: Table 1, no rotor limits).
        model: the controller's nominal model (default: ``vehicle``).
        solver: diffrax solver or name ("tsit5" default, "dopri5" ode45-like, "dopri8").
        rtol, atol: tolerances of the PID step-size controller.
        n_save: number of equally spaced save times over [t0, t1] (0: only the end state).
        max_steps: solver step budget (per sample interval with digital control); exceeding it
            gives status ``max_steps_reached``, never an exception.
        limits: divergence limits (default `DivergenceLimits()`): crossing them stops the run
            with status ``diverged``.
        adjoint: diffrax adjoint for gradients (default `RecursiveCheckpointAdjoint`).
        unmodeled: unmodeled dynamics (full rigid-body plant, motor lag, digital control with
            noise and delay; `afbl_jax.model.UnmodeledDynamics`). None (default): the paper's
            model with a continuous controller.
        aerodynamics: aerodynamic model, a name ("linear", "rotor_drag") or an
            `AbstractAerodynamics`; None (default): `LinearDrag` (coefficients in ``vehicle``).
        position_loop: the outer position loop (`afbl_jax.model.PositionHold`): roll and pitch
            references from the scenario's position reference (``Scenario.position``); None
            (default): the scenario's attitude references (the paper's loop).
        saving: how the ``n_save`` samples of a continuous-control run are taken (`SAVINGS`).
            "saveat" (default): diffrax's ``SaveAt(ts=...)`` inside the solve; lean in memory,
            for batches and gradients. Under ``jax.jit`` diffrax checks those times with a
            host callback, and JAX's persistent compilation cache never stores a program
            that has one, so every new process compiles it again. "dense": diffrax's dense
            output, evaluated at the same times after the solve with the same interpolant
            of each step (the same samples to round-off); no host callback, so the compiled
            program is cached like the ensemble programs; it holds the dense output of
            ``max_steps`` steps (about 9 x the state size per step), for single solves such
            as replays and figures. Digital control samples its own way (no callback) and
            ignores the choice.

    Never raises for a failed or diverged run (diffrax ``throw=False``); check ``status``.
    """
    loop = closed_loop_of(controller, unmodeled, aerodynamics, position_loop)
    vehicle = QuadrotorParams() if vehicle is None else vehicle
    model = vehicle if model is None else model
    limits = DivergenceLimits() if limits is None else limits
    check_positive("simulate", "rtol", rtol)
    check_positive("simulate", "atol", atol)
    if int(n_save) < 0 or int(max_steps) <= 0:
        raise ValueError(f"n_save must be >= 0 and max_steps > 0, got {n_save}, {max_steps}.")
    if saving not in SAVINGS:
        raise ValueError(f"saving must be one of {', '.join(SAVINGS)}, got {saving!r}.")
    return _simulate(
        loop.shared_program(),
        CaseInputs(scenario, vehicle, model, limits),
        get_solver(solver),
        float(rtol),
        float(atol),
        int(n_save),
        int(max_steps),
        adjoint or diffrax.RecursiveCheckpointAdjoint(),
        saving == "dense",
    )


def closed_loop_of(controller, unmodeled=None, aerodynamics=None, position_loop=None) -> ClosedLoop:
    """The `ClosedLoop` a `simulate` call describes (a controller plus optional settings)."""
    if isinstance(controller, ClosedLoop):
        if unmodeled is not None or aerodynamics is not None or position_loop is not None:
            raise ValueError(
                "give either a ClosedLoop or unmodeled/aerodynamics/position_loop settings, "
                "not both."
            )
        return controller
    if not isinstance(controller, AbstractController):
        raise TypeError(
            f"controller must be an AbstractController or a ClosedLoop, got "
            f"{type(controller).__name__}."
        )
    if position_loop is not None and not isinstance(position_loop, PositionHold):
        raise TypeError(
            f"position_loop must be a PositionHold or None, got {type(position_loop).__name__}."
        )
    return ClosedLoop.make(controller, unmodeled, aerodynamics, position_loop)
