"""The one closed loop: plant + actuators + aerodynamics + controller and its sampling.

Closed-loop ODE state (`ClosedLoopState`)
-----------------------------------------
- ``plant``: shape (12,), layout of the loop's plant (`afbl_jax.model.STATE_LAYOUT` or
  `afbl_jax.model.FULL_STATE_LAYOUT`);
- ``controller``: the controller's own state, shape (4,), channels (phi, theta, psi, z):
  PID integrators for `FBLPID`, adaptive estimates delta_hat for `AFBL`/`AFBLPaper`;
- ``cost``: running integrals, shape (4,): ``COST_LAYOUT`` = (ISE attitude eq. 42 [rad^2 s],
  ISE altitude eq. 43 [m^2 s], control effort integral of |u - u_hover|^2 [mixed units^2 s],
  u in (N, N, N m, N) and u_hover = (0, 0, 0, m_true g), saturation integral of
  sum_i (excess_i / W_hover)^2 [s] where excess_i is how far the commanded squared rotor speed
  W_i lies outside [omega_min^2, omega_max^2] and W_hover = m g / (4 b): zero while no rotor
  saturates, smooth (C^1) in the gains, so it can serve as a penalty);
- ``rotors``: rotor speeds Omega_1..4 [rad/s] with `FirstOrderRotors`, else None (no state).

With digital control the held command and the measurement ring buffer are discrete states of
the solve (`afbl_jax.sim` drives them), not ODE states; the controller's state then has zero
derivative between samples and is advanced at each sample.

One evaluation (`ClosedLoop.signals_and_derivative`): reference r(t) -> controller (on the
paper-layout measurement, or the held command) -> mixer (`afbl_jax.model.mix`: inversion with
the controller's model, clipping at the vehicle's rotor limits) -> actuators -> applied inputs
-> disturbance pulses + aerodynamic wrench of the wind -> plant derivative, plus the cost
integrands. Everything is a pure function of arrays (jit, vmap, grad).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .._typing import Array, Float, Scalar
from .._validation import check_positive
from ..model import (
    CHANNEL_INDEX,
    AbstractActuators,
    AbstractAerodynamics,
    AbstractController,
    AbstractPlant,
    AbstractSampling,
    ContinuousControl,
    InstantRotors,
    PaperPlant,
    QuadrotorParams,
    UnmodeledDynamics,
    diverged_from,
    hover_input,
    inputs_from_rotor_speeds_sq,
    make_aerodynamics,
    mix,
    omega_d,
    safe_sqrt,
    saturate_rotor_speeds_sq,
)
from ..scenario import Scenario

COST_LAYOUT: tuple[str, ...] = ("ise_attitude", "ise_altitude", "effort", "saturation")
"""Names of the running cost integrals (``ClosedLoopState.cost``), in order."""


class ClosedLoopState(eqx.Module):
    """The closed-loop ODE state; see the module docstring for the layout."""

    plant: Float[Array, 12]
    controller: Float[Array, 4]
    cost: Float[Array, 4]
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
    """

    controller: AbstractController
    plant: AbstractPlant = eqx.field(default_factory=PaperPlant)
    actuators: AbstractActuators = eqx.field(default_factory=InstantRotors)
    aerodynamics: AbstractAerodynamics = eqx.field(default_factory=make_aerodynamics)
    sampling: AbstractSampling = eqx.field(default_factory=ContinuousControl)

    @classmethod
    def make(
        cls,
        controller: AbstractController,
        unmodeled: UnmodeledDynamics | None = None,
        aerodynamics: AbstractAerodynamics | str | None = None,
    ) -> ClosedLoop:
        """The paper's loop (``unmodeled`` None) or the loop the settings name, with the
        aerodynamic model ``aerodynamics`` (a name of `afbl_jax.model.AERODYNAMICS`, an
        instance, or None: `LinearDrag`)."""
        aero = make_aerodynamics(aerodynamics)
        if unmodeled is None:
            return cls(controller, aerodynamics=aero)
        return cls(
            controller,
            unmodeled.plant_model(),
            unmodeled.actuator_model(),
            aero,
            unmodeled.sampling_model(),
        )

    @property
    def digital(self) -> bool:
        return self.sampling.digital

    def command(self, t, measured, controller_state, inputs: CaseInputs):
        """(u_cmd, W_cmd, W_sat, d controller state / dt) of the controller on a paper-layout
        ``measured`` state at time t [s]."""
        ref = inputs.scenario.reference(t)
        u_cmd, dctrl = self.controller(t, measured, controller_state, ref, inputs.model)
        w_cmd, w_sat = mix(inputs.model, inputs.vehicle, u_cmd)
        return u_cmd, w_cmd, w_sat, dctrl

    def initial_state(self, inputs: CaseInputs, dtype) -> ClosedLoopState:
        """State at t0: the scenario's initial plant state (converted to the plant's layout),
        zero controller state and costs, rotors at the first (noise-free) command."""
        sc = inputs.scenario
        plant0 = self.plant.from_paper_layout(sc.initial_state.astype(dtype))
        ctrl0 = self.controller.init_state().astype(dtype)
        rotors0 = None
        probe = self.actuators.init_state(jnp.zeros(4, dtype))
        if probe is not None:
            meas0 = self.plant.to_paper_layout(plant0)
            _, _, w_sat, _ = self.command(sc.t0, meas0, ctrl0, inputs)
            rotors0 = self.actuators.init_state(safe_sqrt(w_sat)).astype(dtype)
        return ClosedLoopState(plant0, ctrl0, jnp.zeros(len(COST_LAYOUT), dtype), rotors0)

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
        ref = sc.reference(t)
        if held is None:
            measured = self.plant.to_paper_layout(y.plant)
            u_cmd, dctrl = self.controller(t, measured, y.controller, ref, inputs.model)
            if materialise:
                u_cmd, dctrl = jax.lax.optimization_barrier((u_cmd, dctrl))
            w_cmd, w_sat = mix(inputs.model, vehicle, u_cmd)
        else:
            u_cmd, w_cmd = held.u_command, held.w_command
            w_sat = saturate_rotor_speeds_sq(vehicle, w_cmd)
            dctrl = jnp.zeros_like(y.controller)
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
        e = ref.r - y.plant[CHANNEL_INDEX]
        du = u - hover_input(vehicle, mass)
        excess = (w_cmd - w_sat) / w_hover  # zero unless a rotor is saturated
        dcost = jnp.stack([jnp.sum(e[:3] ** 2), e[3] ** 2, jnp.sum(du**2), jnp.sum(excess**2)])
        signals = Signals(ref.r, e, u_cmd, u, omega, force, torque, mass)
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
