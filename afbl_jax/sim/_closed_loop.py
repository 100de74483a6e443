"""The one closed loop: plant + actuators + aerodynamics + controller and its sampling.

Closed-loop ODE state (`ClosedLoopState`)
-----------------------------------------
- ``plant``: shape (12,), layout of the loop's plant (`afbl_jax.model.STATE_LAYOUT` or
  `afbl_jax.model.FULL_STATE_LAYOUT`);
- ``controller``: the flight controller's own state: the inner controller's, shape (4,),
  channels (phi, theta, psi, z): PID integrators for `FBLPID`, adaptive estimates delta_hat
  for `AFBL`/`AFBLPaper`; with a position loop followed by the outer loop's 6 entries
  (`afbl_jax.model.POSITION_LOOP_LAYOUT`), shape (10,);
- ``cost``: running integrals, shape (4,) (with a position loop (5,)): ``COST_LAYOUT`` =
  (ISE attitude eq. 42 [rad^2 s],
  ISE altitude eq. 43 [m^2 s], control effort integral of |u - u_hover|^2 [mixed units^2 s],
  u in (N, N, N m, N) and u_hover = (0, 0, 0, m_true g), saturation integral of
  sum_i (excess_i / W_hover)^2 [s] where excess_i is how far the commanded squared rotor speed
  W_i lies outside [omega_min^2, omega_max^2] and W_hover = m g / (4 b): zero while no rotor
  saturates, smooth (C^1) in the gains, so it can serve as a penalty);
- ``rotors``: rotor speeds Omega_1..4 [rad/s] with `FirstOrderRotors`, else None (no state).

With digital control the held command and the measurement ring buffer are discrete states of
the solve (`afbl_jax.sim` drives them), not ODE states; the controller's state then has zero
derivative between samples and is advanced at each sample.

With a position loop (`afbl_jax.model.PositionHold`) the roll and pitch references of the inner
controller are the outer loop's commanded attitude (its command filter's states), and the
attitude ISE and error are taken against them; yaw and altitude follow the scenario's
reference.

One evaluation (`ClosedLoop.signals_and_derivative`): reference r(t) (through the position
loop, if any) -> controller (on the paper-layout measurement, or the held command) -> mixer
(`afbl_jax.model.mix`: inversion with the controller's model, clipping at the vehicle's rotor
limits) -> actuators -> applied inputs
-> disturbance pulses + aerodynamic wrench of the wind -> plant derivative, plus the cost
integrands. Everything is a pure function of arrays (jit, vmap, grad).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp

from .._typing import Array, Float, Scalar
from .._validation import check_positive
from ..metrics import sample_peaks
from ..model import (
    CHANNEL_INDEX,
    AbstractActuators,
    AbstractAerodynamics,
    AbstractController,
    AbstractPlant,
    AbstractSampling,
    AnyController,
    ContinuousControl,
    InstantRotors,
    PaperPlant,
    PositionHold,
    QuadrotorParams,
    ReferenceSample,
    UnmodeledDynamics,
    diverged_from,
    hover_input,
    inputs_from_rotor_speeds_sq,
    make_aerodynamics,
    mix,
    omega_d,
    rotor_speeds_sq_from_inputs,
    safe_sqrt,
    saturate_rotor_speeds_sq,
    virtual_input_for,
)
from ..model.controllers import LAWS
from ..scenario import Scenario
from ._status import STATUS_DIVERGED, STATUS_OK

COST_LAYOUT: tuple[str, ...] = (
    "ise_attitude",
    "ise_altitude",
    "effort",
    "saturation",
    "ise_position",
)
"""Names of the running cost integrals (``ClosedLoopState.cost``), in order; the last one only
with a position loop."""
INNER_SIZE = 4
"""Entries of the inner controller's state (one per channel)."""


class ClosedLoopState(eqx.Module):
    """The closed-loop ODE state; see the module docstring for the layout."""

    plant: Float[Array, 12]
    controller: Float[Array, " C"]
    cost: Float[Array, " K"]
    rotors: Float[Array, 4] | None = None


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
    """Closed-loop signals at one instant (all derived from the state)."""

    reference: Float[Array, 4]
    error: Float[Array, 4]
    u_command: Float[Array, 4]
    u_applied: Float[Array, 4]
    rotor_speeds: Float[Array, 4]
    force: Float[Array, 3]
    torque: Float[Array, 3]
    mass: Scalar
    position_error: Float[Array, 2] | None = None


class CaseInputs(eqx.Module):
    """The data of one case besides the loop itself: scenario, true vehicle, the controller's
    nominal model and the divergence limits."""

    scenario: Scenario
    vehicle: QuadrotorParams
    model: QuadrotorParams
    limits: DivergenceLimits


class Held(eqx.Module):
    """A digital controller's zero-order hold: commanded inputs u (4,) and the mixer's
    commanded squared rotor speeds W (4,) [rad^2/s^2]."""

    u_command: Float[Array, 4]
    w_command: Float[Array, 4]


class ClosedLoop(eqx.Module):
    """The closed loop composed from its parts (each a small interface of `afbl_jax.model`).

    Attributes:
        controller: `FBLPID`, `AFBL` or `AFBLPaper` (gains dynamic).
        plant: `PaperPlant` (default) or `RigidBodyPlant`.
        actuators: `InstantRotors` (default) or `FirstOrderRotors` (tau_m dynamic).
        aerodynamics: `LinearDrag` (default) or `RotorDrag` (coefficients in the vehicle).
        sampling: `ContinuousControl` (default) or `DigitalControl`.
        position_loop: `PositionHold` (the outer loop: roll and pitch references from the
            horizontal position error; gains dynamic) or None (default: the scenario's attitude
            references drive the inner loops, as in the paper).
    """

    controller: AbstractController
    plant: AbstractPlant = eqx.field(default_factory=PaperPlant)
    actuators: AbstractActuators = eqx.field(default_factory=InstantRotors)
    aerodynamics: AbstractAerodynamics = eqx.field(default_factory=make_aerodynamics)
    sampling: AbstractSampling = eqx.field(default_factory=ContinuousControl)
    position_loop: PositionHold | None = None

    @classmethod
    def make(
        cls,
        controller: AbstractController,
        unmodeled: UnmodeledDynamics | None = None,
        aerodynamics: AbstractAerodynamics | str | None = None,
        position_loop: PositionHold | None = None,
    ) -> ClosedLoop:
        """The paper's loop (``unmodeled`` None) or the loop the settings name, with the
        aerodynamic model ``aerodynamics`` (a name of `afbl_jax.model.AERODYNAMICS`, an
        instance, or None: `LinearDrag`) and the outer ``position_loop`` (None: none)."""
        aero = make_aerodynamics(aerodynamics)
        if unmodeled is None:
            return cls(controller, aerodynamics=aero, position_loop=position_loop)
        return cls(
            controller,
            unmodeled.plant_model(),
            unmodeled.actuator_model(),
            aero,
            unmodeled.sampling_model(),
            position_loop,
        )

    def shared_program(self) -> ClosedLoop:
        """This loop with its controller as an `AnyController` (the law's own operations), so
        that the loops of every controller law compile to one program; unchanged where the
        controller's gains are traced or batched (an enclosing program is the controller's own
        anyway) or the controller is no law of `afbl_jax.model.controllers.LAWS`."""
        ctrl = self.controller
        if type(ctrl) not in LAWS:
            return self
        gains = [getattr(ctrl, g) for g in ctrl.gain_names]
        if any(isinstance(g, jax.core.Tracer) or jnp.ndim(g) != 1 for g in gains):
            return self
        return dataclasses.replace(self, controller=AnyController.of(ctrl))

    @property
    def digital(self) -> bool:
        return self.sampling.digital

    @property
    def n_costs(self) -> int:
        """Entries of ``ClosedLoopState.cost`` (`COST_LAYOUT`; 5 with a position loop)."""
        return len(COST_LAYOUT) - (self.position_loop is None)

    def _inner(self, controller_state):
        if self.position_loop is None:
            return controller_state
        return controller_state[:INNER_SIZE]

    def reference(self, t, measured, controller_state, inputs: CaseInputs):
        """(the inner controller's `ReferenceSample`, d(outer-loop state)/dt or None) at time
        t [s] on a paper-layout ``measured`` state."""
        ref = inputs.scenario.reference(t)
        if self.position_loop is None:
            return ref, None
        att, douter = self.position_loop(
            measured,
            controller_state[INNER_SIZE:],
            inputs.scenario.position_at(t),
            inputs.model,
        )
        ref = ReferenceSample(
            jnp.concatenate([att.r, ref.r[2:]]),
            jnp.concatenate([att.rd, ref.rd[2:]]),
            jnp.concatenate([att.rdd, ref.rdd[2:]]),
        )
        return ref, douter

    def reference_values(self, t, controller_state, inputs: CaseInputs):
        """The reference values r (phi, theta, psi, z) the tracking errors are taken against at
        time t [s]: the scenario's, with a position loop's commanded roll and pitch (its
        command filter's states) in place of the scenario's."""
        r = inputs.scenario.reference(t).r
        if self.position_loop is None:
            return r
        return jnp.concatenate([controller_state[INNER_SIZE + 2 : INNER_SIZE + 4], r[2:]])

    def position_error(self, t, plant, inputs: CaseInputs):
        """p_ref - p (x, y) [m] at time t [s] with a position loop, else None."""
        if self.position_loop is None:
            return None
        return inputs.scenario.position_at(t).r - plant[0:2]

    def command(self, t, measured, controller_state, inputs: CaseInputs):
        """(u_cmd, W_cmd, W_sat, d controller state / dt) of the flight controller (position
        loop, if any, and inner controller) on a paper-layout ``measured`` state at time
        t [s]."""
        ref, douter = self.reference(t, measured, controller_state, inputs)
        u_cmd, dctrl = self.controller(
            t, measured, self._inner(controller_state), ref, inputs.model
        )
        if douter is not None:
            dctrl = jnp.concatenate([dctrl, douter])
        w_cmd, w_sat = mix(inputs.model, inputs.vehicle, u_cmd)
        return u_cmd, w_cmd, w_sat, dctrl

    def initial_controller_state(self, inputs: CaseInputs, plant_paper, dtype):
        """The flight controller's state at t0 from the paper-layout initial plant state:
        zeros (a position loop: at rest at the initial attitude), or with a trimmed start
        (``Scenario.trim``) the states that command the trim's inputs at zero error: the inner
        controller's `state_for` of the virtual input that gives them on the trim state, the
        position loop at rest at the trim attitude."""
        sc = inputs.scenario
        inner = self.controller.init_state().astype(dtype)
        outer = None
        if self.position_loop is not None:
            attitude = plant_paper[3:5] if sc.trim is None else sc.trim.attitude.astype(dtype)
            outer = self.position_loop.init_state(attitude, plant_paper[5], inputs.model)
            outer = outer.astype(dtype)
        if sc.trim is not None:
            trim_state = plant_paper.at[3:5].set(sc.trim.attitude.astype(dtype))
            trim_state = trim_state.at[9:12].set(0.0)
            full = inner if outer is None else jnp.concatenate([inner, outer])
            ref, _ = self.reference(sc.t0, trim_state, full, inputs)
            v = virtual_input_for(inputs.model, trim_state, sc.trim.command.astype(dtype))
            inner = self.controller.state_for(v, ref).astype(dtype)
        return inner if outer is None else jnp.concatenate([inner, outer])

    def initial_state(self, inputs: CaseInputs, dtype) -> ClosedLoopState:
        """State at t0: the scenario's initial plant state (converted to the plant's layout),
        the flight controller's initial state (`initial_controller_state`), zero costs, rotors
        at the first (noise-free) command."""
        sc = inputs.scenario
        plant0 = self.plant.from_paper_layout(sc.initial_state.astype(dtype))
        meas0 = self.plant.to_paper_layout(plant0)
        ctrl0 = self.initial_controller_state(inputs, meas0, dtype)
        rotors0 = None
        probe = self.actuators.init_state(jnp.zeros(4, dtype))
        if probe is not None:
            _, _, w_sat, _ = self.command(sc.t0, meas0, ctrl0, inputs)
            rotors0 = self.actuators.init_state(safe_sqrt(w_sat)).astype(dtype)
        return ClosedLoopState(plant0, ctrl0, jnp.zeros(self.n_costs, dtype), rotors0)

    def signals_and_derivative(
        self,
        t,
        y: ClosedLoopState,
        inputs: CaseInputs,
        held: Held | None = None,
        materialise: bool = False,
    ) -> tuple[Signals, ClosedLoopState]:
        """Signals at (t, y) and dy/dt; ``held``: the digital controller's held command
        (None: the controller acts on the state now). ``materialise`` (static; forward-only
        integrators): compute the controller's output once behind an XLA optimisation
        barrier, which XLA otherwise recomputes inside each of the mixer's consumers. Not for
        differentiated paths: reverse mode through the barrier does not give the derivative of
        the solve to the solver's accuracy (the primal values are unchanged)."""
        sc, vehicle = inputs.scenario, inputs.vehicle
        if held is None:
            measured = self.plant.to_paper_layout(y.plant)
            ref, douter = self.reference(t, measured, y.controller, inputs)
            u_cmd, dctrl = self.controller(
                t, measured, self._inner(y.controller), ref, inputs.model
            )
            if douter is not None:
                dctrl = jnp.concatenate([dctrl, douter])
            if materialise:
                u_cmd, dctrl = jax.lax.optimization_barrier((u_cmd, dctrl))
            w_cmd, w_sat = mix(inputs.model, vehicle, u_cmd)
            r = ref.r
        else:
            u_cmd, w_cmd = held.u_command, held.w_command
            w_sat = saturate_rotor_speeds_sq(vehicle, w_cmd)
            dctrl = jnp.zeros_like(y.controller)
            r = self.reference_values(t, y.controller, inputs)
        omega_cmd = safe_sqrt(w_sat)
        w, omega = self.actuators.applied(y.rotors, omega_cmd, w_sat)
        drotors = self.actuators.derivative(y.rotors, omega_cmd)
        u = inputs_from_rotor_speeds_sq(vehicle, w)
        w_hover = vehicle.m * vehicle.g / (4.0 * vehicle.b)
        force, torque = sc.disturbance(t)
        air_state = self.plant.to_paper_layout(y.plant)
        wind_force, wind_torque = self.aerodynamics.wrench(sc.wind(t), air_state, vehicle, omega)
        force, torque = force + wind_force, torque + wind_torque
        mass = vehicle.m * sc.mass_factor(t)
        dplant = self.plant.derivative(vehicle, y.plant, u, omega_d(omega), mass, force, torque)
        e = r - y.plant[CHANNEL_INDEX]
        du = u - hover_input(vehicle, mass)
        excess = (w_cmd - w_sat) / w_hover  # zero unless a rotor is saturated
        costs = [jnp.sum(e[:3] ** 2), e[3] ** 2, jnp.sum(du**2), jnp.sum(excess**2)]
        e_pos = self.position_error(t, y.plant, inputs)
        if e_pos is not None:
            costs.append(jnp.sum(e_pos**2))
        dcost = jnp.stack(costs)
        signals = Signals(r, e, u_cmd, u, omega, force, torque, mass, e_pos)
        return signals, ClosedLoopState(dplant, dctrl, dcost, drotors)

    def vector_field(self, t, y: ClosedLoopState, args) -> ClosedLoopState:
        """d/dt of the closed-loop state (the diffrax vector field; args = (inputs, held))."""
        inputs, held = args
        return self.signals_and_derivative(t, y, inputs, held)[1]

    def diverged(self, y: ClosedLoopState, altitude_error, inputs: CaseInputs) -> Array:
        """The divergence test (`afbl_jax.model.diverged_from`) on this loop's state."""
        return diverged_from(y.plant, altitude_error, inputs.limits, y.controller, y.rotors)

    def diverged_at(self, t, y: ClosedLoopState, inputs: CaseInputs) -> Array:
        """`diverged` with the altitude error from the reference at t."""
        return self.diverged(y, inputs.scenario.reference(t).r[3] - y.plant[2], inputs)

    def peak_inputs(self, plant, controller_state) -> Array:
        """What a peak sample reads of the state, as one vector (linearly interpolated between
        the control samples under digital control): q = (phi, theta, psi, z) and, with a
        position loop, the commanded roll and pitch [rad] and the position (x, y) [m]."""
        q = plant[CHANNEL_INDEX]
        if self.position_loop is None:
            return q
        return jnp.concatenate([q, controller_state[INNER_SIZE + 2 : INNER_SIZE + 4], plant[0:2]])

    def peak_sample(self, t, peak_inputs, u_command, inputs: CaseInputs) -> Array:
        """`afbl_jax.metrics.sample_peaks` at time t [s] from `peak_inputs` and the
        controller's command: the tracking errors against `reference_values` and, with a
        position loop, the position error."""
        r = inputs.scenario.reference(t).r
        q = peak_inputs[:4]
        if self.position_loop is None:
            err, e_pos = r - q, None
        else:
            err = jnp.concatenate([peak_inputs[4:6], r[2:]]) - q
            e_pos = inputs.scenario.position_at(t).r - peak_inputs[6:8]
        return sample_peaks(err, u_command, inputs.vehicle, inputs.model, e_pos)

    def anatomy(self, t, y: ClosedLoopState, status, inputs: CaseInputs) -> tuple[Array, Array]:
        """(failure cause, commanded saturation) of a run that ended at time t [s] in state y
        with ``status``: the cause indexes `afbl_jax.metrics.FAILURE_CAUSES` (0 none for a run
        that finished; for a diverged run non-finite, else the divergence limit crossed by the
        most, attitude or altitude; solver for a run the solver stopped); the saturation is
        max_i commanded rotor speed / Omega_max [-] of the controller's command on the end
        state (>= 1: the rotors were commanded past their limit as the run ended)."""
        measured = self.plant.to_paper_layout(y.plant)
        finite = jnp.all(jnp.isfinite(y.plant)) & jnp.all(jnp.isfinite(y.controller))
        limits = inputs.limits
        att = jnp.maximum(jnp.abs(y.plant[3]), jnp.abs(y.plant[4])) / limits.attitude
        alt = jnp.abs(inputs.scenario.reference(t).r[3] - y.plant[2]) / limits.altitude_error
        diverged_cause = jnp.where(~finite, 3, jnp.where(att >= alt, 1, 2))
        cause = jnp.where(
            status == STATUS_OK, 0, jnp.where(status == STATUS_DIVERGED, diverged_cause, 4)
        )
        u_cmd = self.command(t, measured, y.controller, inputs)[0]
        w = rotor_speeds_sq_from_inputs(inputs.model, u_cmd)
        sat = jnp.sqrt(jnp.maximum(jnp.max(w), 0.0)) / inputs.vehicle.omega_max
        return cause.astype(jnp.int32), jnp.where(finite, sat, jnp.nan)
