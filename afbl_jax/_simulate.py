"""Closed loop (plant + mixer + controller + cost integrals) solved by a diffrax adaptive solver.

Closed-loop ODE state (`ClosedLoopState`)
-----------------------------------------
- ``plant``: shape (12,), layout `afbl_jax._plant.STATE_LAYOUT`;
- ``controller``: the controller's own state, shape (4,), channels (phi, theta, psi, z):
  PID integrators for `FBLPID`, adaptive estimates delta_hat for `AFBL`/`AFBLPaper`;
- ``cost``: running integrals, shape (4,): ``COST_LAYOUT`` = (ISE attitude eq. 42 [rad^2 s],
  ISE altitude eq. 43 [m^2 s], control effort integral of |u - u_hover|^2 [mixed units^2 s],
  u in (N, N, N m, N) and u_hover = (0, 0, 0, m_true g), saturation integral of
  sum_i (excess_i / W_hover)^2 [s] where excess_i is how far the commanded squared rotor speed
  W_i lies outside [omega_min^2, omega_max^2] and W_hover = m g / (4 b): zero while no rotor
  saturates, smooth (C^1) in the gains, so it can serve as a penalty).

With ``simulate(..., unmodeled=UnmodeledDynamics(...))`` the closed-loop state is
`afbl_jax._unmodeled.UnmodeledState` (plant, rotors, controller, cost); the settings, the full
plant's state layout and the digital-control loop are documented in `afbl_jax._unmodeled`.

Everything here is a pure function of arrays: `simulate` works under `jax.jit`, `jax.vmap`
(over parameters, gains and scenario numbers) and `jax.grad` (of the ISE w.r.t. gains; the
adjoint is diffrax's `RecursiveCheckpointAdjoint`: discretise-then-optimise, the exact gradient
of the numerical solution, with checkpointed memory).
"""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp

from ._mixer import (
    inputs_from_rotor_speeds_sq,
    omega_d,
    rotor_speeds_sq_from_inputs,
    safe_sqrt,
    saturate_rotor_speeds_sq,
)
from ._params import QuadrotorParams
from ._plant import CHANNEL_INDEX, diverged_from, hover_input, plant_derivative
from ._scenarios import Scenario
from ._typing import Array, Float, Int, Scalar
from ._unmodeled import UnmodeledDynamics, simulate_unmodeled
from ._validation import check_positive
from ._wind import wind_wrench
from .controllers import AbstractController

COST_LAYOUT: tuple[str, ...] = ("ise_attitude", "ise_altitude", "effort", "saturation")

STATUS_OK = 0
STATUS_DIVERGED = 1
STATUS_MAX_STEPS = 2
STATUS_SOLVER_FAILED = 3
STATUS_NAMES = {
    STATUS_OK: "ok",
    STATUS_DIVERGED: "diverged",
    STATUS_MAX_STEPS: "solver_failed",
    STATUS_SOLVER_FAILED: "solver_failed",
}
STATUS_MESSAGES = {
    STATUS_OK: "ok",
    STATUS_DIVERGED: "diverged: attitude, altitude error or state exceeded the divergence limits",
    STATUS_MAX_STEPS: "solver_failed: max_steps reached before t1 (stiff or too tight tolerances)",
    STATUS_SOLVER_FAILED: "solver_failed: the solver stopped (step size collapsed or "
    "non-finite values)",
}


class ClosedLoopState(eqx.Module):
    """The closed-loop ODE state; see the module docstring for the layout."""

    plant: Float[Array, 12]
    controller: Float[Array, 4]
    cost: Float[Array, 3]


class DivergenceLimits(eqx.Module):
    """A run is stopped and flagged ``diverged`` past these limits (or on a non-finite state).

    Attributes:
        attitude: bound on |phi| and |theta| [rad].
        altitude_error: bound on |z_ref - z| [m].
    """

    attitude: Scalar = eqx.field(default=1.2, converter=jnp.asarray)
    altitude_error: Scalar = eqx.field(default=10.0, converter=jnp.asarray)

    def __check_init__(self):
        check_positive("DivergenceLimits", "attitude", self.attitude)
        check_positive("DivergenceLimits", "altitude_error", self.altitude_error)


class Signals(eqx.Module):
    """Closed-loop signals at one instant (all derived from the ODE state)."""

    reference: Float[Array, 4]
    error: Float[Array, 4]
    u_command: Float[Array, 4]
    u_applied: Float[Array, 4]
    rotor_speeds: Float[Array, 4]
    force: Float[Array, 3]
    torque: Float[Array, 3]
    mass: Scalar


class _Args(eqx.Module):
    controller: AbstractController
    scenario: Scenario
    vehicle: QuadrotorParams
    model: QuadrotorParams
    limits: DivergenceLimits


def _signals_and_derivative(t, y: ClosedLoopState, args: _Args):
    ref = args.scenario.reference(t)
    u_cmd, dctrl = args.controller(t, y.plant, y.controller, ref, args.model)
    w_cmd = rotor_speeds_sq_from_inputs(args.model, u_cmd)
    w = saturate_rotor_speeds_sq(args.vehicle, w_cmd)
    u, omega = inputs_from_rotor_speeds_sq(args.vehicle, w), safe_sqrt(w)
    w_hover = args.vehicle.m * args.vehicle.g / (4.0 * args.vehicle.b)
    force, torque = args.scenario.disturbance(t)
    wind_force, wind_torque = wind_wrench(t, y.plant, args.scenario, args.vehicle)
    force, torque = force + wind_force, torque + wind_torque
    mass = args.vehicle.m * args.scenario.mass_factor(t)
    dplant = plant_derivative(args.vehicle, y.plant, u, omega_d(omega), mass, force, torque)
    e = ref.r - y.plant[CHANNEL_INDEX]
    du = u - hover_input(args.vehicle, mass)
    excess = (w_cmd - w) / w_hover  # zero unless a rotor is saturated
    dcost = jnp.stack([jnp.sum(e[:3] ** 2), e[3] ** 2, jnp.sum(du**2), jnp.sum(excess**2)])
    signals = Signals(ref.r, e, u_cmd, u, omega, force, torque, mass)
    return signals, ClosedLoopState(dplant, dctrl, dcost)


def closed_loop_vector_field(t, y: ClosedLoopState, args: _Args) -> ClosedLoopState:
    """d/dt of the closed-loop state (the diffrax vector field)."""
    return _signals_and_derivative(t, y, args)[1]


def _diverged(t, y: ClosedLoopState, args: _Args, **kwargs):
    del kwargs
    ref = args.scenario.reference(t)
    return diverged_from(y.plant, ref.r[3] - y.plant[2], args.limits, y.controller)


class SimulationResult(eqx.Module):
    """Output of `simulate`.

    Trajectory arrays have a leading time axis of length ``n_save`` (empty when n_save = 0);
    samples after an early stop (divergence) are ``inf``, as diffrax fills them.

    Attributes:
        ts: save times [s].
        plant: plant states, (n_save, 12), layout `afbl_jax._plant.STATE_LAYOUT`.
        controller_state: (n_save, 4).
        reference, error: r and e = r - q per channel (phi, theta, psi, z), (n_save, 4).
        u_command, u_applied: inputs (u1, u2, u3, u4) before / after rotor saturation.
        rotor_speeds: (n_save, 4) [rad/s].
        disturbance_force: (n_save, 3) [N]; disturbance_torque: (n_save, 3) [N m].
        final: closed-loop state at the end of the run (t1, or where it stopped).
        t_final: time the run ended [s].
        ise_attitude, ise_altitude, effort, saturation: cost integrals at the end of the run
            (`COST_LAYOUT`).
        status: 0 ok, 1 diverged, 2 max_steps reached, 3 other solver failure
            (`STATUS_MESSAGES` explains each).
        num_steps, num_accepted_steps, num_rejected_steps: solver statistics.
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

    @property
    def ok(self) -> Array:
        return self.status == STATUS_OK


def status_message(status) -> str:
    """Human-readable meaning of a `SimulationResult.status` code."""
    return STATUS_MESSAGES.get(int(status), f"unknown status {int(status)}")


SOLVERS = {"tsit5": diffrax.Tsit5, "dopri5": diffrax.Dopri5, "dopri8": diffrax.Dopri8}
"""Solvers selectable by name (Dopri5 is MATLAB's ode45 pair)."""


def get_solver(solver: str | diffrax.AbstractSolver) -> diffrax.AbstractSolver:
    if isinstance(solver, diffrax.AbstractSolver):
        return solver
    try:
        return SOLVERS[solver]()
    except KeyError:
        raise ValueError(f"unknown solver {solver!r}; allowed: {', '.join(SOLVERS)}.") from None


def simulate(
    controller: AbstractController,
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
) -> SimulationResult:
    """Simulate one closed-loop case.

    Args:
        controller: `FBLPID`, `AFBL` or `AFBLPaper` (gains are dynamic: vmap/grad over them).
        scenario: reference, disturbances, payload, initial state, time span.
        vehicle: true vehicle parameters (default: Table 1, no rotor limits).
        model: the controller's nominal model (default: ``vehicle``).
        solver: diffrax solver or name ("tsit5" default, "dopri5" ode45-like, "dopri8").
        rtol, atol: tolerances of the PID step-size controller.
        n_save: number of equally spaced save times over [t0, t1] (0: only the end state).
        max_steps: solver step budget; exceeding it gives status 2, never an exception.
        limits: divergence limits (default `DivergenceLimits()`): crossing them stops the run
            with status 1.
        adjoint: diffrax adjoint for gradients (default `RecursiveCheckpointAdjoint`).
        unmodeled: unmodeled dynamics (full rigid-body plant, motor lag, digital control with
            noise and delay; `afbl_jax._unmodeled` documents the settings and state layouts).
            None (default): the paper's model with a continuous controller, as always.

    Never raises for a failed or diverged run (diffrax ``throw=False``); check ``status``.
    """
    vehicle = QuadrotorParams() if vehicle is None else vehicle
    model = vehicle if model is None else model
    limits = DivergenceLimits() if limits is None else limits
    check_positive("simulate", "rtol", rtol)
    check_positive("simulate", "atol", atol)
    if int(n_save) < 0 or int(max_steps) <= 0:
        raise ValueError(f"n_save must be >= 0 and max_steps > 0, got {n_save}, {max_steps}.")
    if unmodeled is not None:
        return simulate_unmodeled(
            controller, scenario, vehicle, model, limits, unmodeled, get_solver(solver),
            float(rtol), float(atol), int(n_save), int(max_steps),
            adjoint or diffrax.RecursiveCheckpointAdjoint(),
        )
    return _simulate(
        controller,
        scenario,
        vehicle,
        model,
        limits,
        get_solver(solver),
        float(rtol),
        float(atol),
        int(n_save),
        int(max_steps),
        adjoint or diffrax.RecursiveCheckpointAdjoint(),
    )


@eqx.filter_jit
def _simulate(controller, scenario, vehicle, model, limits, solver, rtol, atol, n_save, max_steps,
              adjoint) -> SimulationResult:
    args = _Args(controller, scenario, vehicle, model, limits)
    dtype = jnp.result_type(float)
    y0 = ClosedLoopState(
        scenario.initial_state.astype(dtype),
        controller.init_state().astype(dtype),
        jnp.zeros(len(COST_LAYOUT), dtype),
    )
    return solve_closed_loop(closed_loop_vector_field, _diverged,
                             lambda t, y: _signals_and_derivative(t, y, args)[0], solver,
                             scenario, y0, args, rtol, atol, n_save, max_steps, adjoint,
                             lambda y: y)



def solver_status(result, finite) -> Int[Array, ""]:
    """Our status code from a diffrax result and whether the final state is finite."""
    return jnp.where(
        result == diffrax.RESULTS.successful,
        jnp.where(finite, STATUS_OK, STATUS_SOLVER_FAILED),
        jnp.where(
            result == diffrax.RESULTS.event_occurred,
            STATUS_DIVERGED,
            jnp.where(result == diffrax.RESULTS.max_steps_reached, STATUS_MAX_STEPS,
                      STATUS_SOLVER_FAILED),
        ),
    ).astype(jnp.int32)


def make_result(ts, plant, controller_state, signals: Signals, final: ClosedLoopState, t_final,
                status, steps) -> SimulationResult:
    """Assemble a `SimulationResult` (shared by the continuous and the unmodeled loops);
    ``steps`` = (num_steps, num_accepted_steps, num_rejected_steps)."""
    return SimulationResult(
        ts=ts,
        plant=plant,
        controller_state=controller_state,
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
    )


def solve_closed_loop(vector_field, diverged, signals_fn, solver, scenario: Scenario, y0, args,
                      rtol, atol, n_save, max_steps, adjoint, to_closed_loop) -> SimulationResult:
    """The adaptive solve shared by the continuous closed loops (`simulate` and the unmodeled
    loop): PID step control clipped onto every jump time, the divergence event, a final-state
    buffer separate from the ``n_save`` trajectory samples (padded with inf after an early
    stop), the signals at the samples (``signals_fn(t, y)``) and the status.
    ``to_closed_loop`` maps the final ODE state to a `ClosedLoopState`."""
    dtype = jnp.result_type(float)
    t0, t1 = scenario.t0, scenario.t1
    ts = t0 + (t1 - t0) * jnp.linspace(0.0, 1.0, n_save, dtype=dtype) if n_save else None
    saves = [diffrax.SubSaveAt(t1=True)] + ([diffrax.SubSaveAt(ts=ts)] if n_save else [])
    stepsize = diffrax.ClipStepSizeController(
        diffrax.PIDController(rtol=rtol, atol=atol), jump_ts=scenario.jump_times()
    )
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(vector_field), solver, t0, t1, None, y0, args=args,
        saveat=diffrax.SaveAt(subs=saves), stepsize_controller=stepsize, max_steps=max_steps,
        event=diffrax.Event(diverged), adjoint=adjoint, throw=False,
    )
    final = jax.tree.map(lambda a: a[-1], sol.ys[0])
    if n_save:
        save_ts, traj = sol.ts[1], sol.ys[1]
        signals = jax.vmap(signals_fn)(save_ts, traj)
    else:
        save_ts = jnp.zeros((0,), dtype)
        traj = jax.tree.map(lambda a: jnp.zeros((0, *a.shape), a.dtype), y0)
        signals = jax.tree.map(lambda a: jnp.zeros((0, *a.shape), a.dtype),
                               signals_fn(t0, y0))
    finite = jnp.all(jnp.isfinite(final.cost)) & jnp.all(jnp.isfinite(final.plant))
    steps = tuple(jnp.asarray(sol.stats[k]) for k in
                  ("num_steps", "num_accepted_steps", "num_rejected_steps"))
    return make_result(save_ts, traj.plant, traj.controller, signals, to_closed_loop(final),
                       sol.ts[0][-1], solver_status(sol.result, finite), steps)
