"""Unmodeled dynamics: full rigid-body plant, motor lag, digital control with noise and delay.

The controllers stay designed on the paper's eq. (15) model; these switches make the simulated
vehicle and the control loop differ from that model. All are off by default: ``simulate(...,
unmodeled=None)`` is the unchanged paper closed loop.

Per-case settings (`UnmodeledDynamics`, an `equinox.Module`)
------------------------------------------------------------
=================  =======  ===============================================================
field              kind     meaning
=================  =======  ===============================================================
plant              static   ``"paper"`` (eq. 15, `afbl_jax._plant.plant_derivative`) or
                            ``"full"`` (`full_plant_derivative`: body rates, Euler's equation)
motor_tau          dynamic  rotor time constant tau_m [s]; 0 = instantaneous rotors
max_samples        static   0 = continuous controller; > 0 = digital controller, number of
                            control samples the run may take (>= (t1 - t0) * control_rate,
                            else the run stops early with status 2 ``solver_failed``)
control_rate       dynamic  controller rate f_c [Hz] (used when max_samples > 0)
delay_samples      dynamic  transport delay of the measurements, in whole samples (int)
max_delay          static   capacity of the delay ring buffer (delay_samples <= max_delay)
noise_angle        dynamic  std of the measured phi, theta, psi [rad]
noise_rate         dynamic  std of the measured phid, thetad, psid [rad/s]
noise_altitude     dynamic  std of the measured z [m]
noise_vertical_    dynamic  std of the measured zd [m/s]
  speed
key                dynamic  jax PRNG key (uint32, shape (2,)); an int seed is converted
=================  =======  ===============================================================

Every dynamic field is a pytree leaf: a batch of settings is one `UnmodeledDynamics` whose
leaves have a leading batch axis (build it with `stack_unmodeled`), and ``jax.vmap(lambda u:
simulate(..., unmodeled=u))(batch)`` runs it. The static fields must agree within a batch (the
scan length and buffer size are static; cases with a lower f_c simply finish early and idle).

Full-plant state layout (``FULL_STATE_LAYOUT``)
-----------------------------------------------
Shape (12,), same as `afbl_jax._plant.STATE_LAYOUT` except that entries 9-11 are the body
rates (p, q, r) [rad/s] instead of the Euler-angle rates::

    index  0  1  2  3    4      5    6   7   8   9  10  11
    name   x  y  z  phi  theta  psi  xd  yd  zd  p  q   r

`Scenario.initial_state` stays in the paper layout (Euler rates); it is converted with
omega = T(eta)^-1 etad at t0. The controller always receives a paper-layout measurement:
an attitude estimator gives it etad = T(eta) omega (exact, before noise).

Closed-loop state with unmodeled dynamics (`UnmodeledState`)
------------------------------------------------------------
``plant`` (12,) in the layout of the chosen plant, ``rotors`` (4,) rotor speeds
Omega_1..4 [rad/s] (ODE states; they follow the saturated command with
dOmega/dt = (Omega_cmd - Omega) / tau_m; with tau_m = 0 they are unused and the applied speeds
are the command), ``controller`` (4,) and ``cost`` (4,) as in `afbl_jax._simulate`. The rotor
speeds start at the first command, so the motor lag adds no start-up transient.
`SimulationResult.final` keeps the `ClosedLoopState` type (plant, controller, cost).

Digital control (max_samples > 0)
---------------------------------
Sample k at t_k = t0 + k / f_c: the true plant state is measured (paper layout, plus Gaussian
noise keyed by ``fold_in(key, k)``; x, y, xd, yd are not used by the controllers and carry no
noise), pushed into a ring buffer, and the measurement from ``delay_samples`` samples earlier
(the initial noise-free measurement before that many samples exist) goes to the controller with
the reference r(t_k). Its command is held (zero-order hold) over [t_k, t_k+1); its own state is
advanced by a forward-Euler step (the usual digital PID / adaptive law). Implementation:
`jax.lax.scan` over samples, one adaptive diffrax solve per sample interval with the held command
(PID step control clipped at the scenario's jump times, divergence event as in `simulate`). The
cost integrals are ODE states of the inner solves, so ISE etc. keep their meaning (integrals of
the true continuous-time errors). With noise off the whole run is differentiable (reverse mode
through the scan and diffrax's checkpointed adjoint).

In digital mode ``simulate``'s ``max_steps`` is the step budget of each sample interval, and
``num_steps`` etc. are totals over the run. Measured cost (2 shared cores, float64): a 20 s
canonical run at 250 Hz takes 0.1-0.2 s after compilation (about 5000 inner solves of 1 step
each), the continuous loop 0.02 s; compiling the digital loop takes 3-30 s (machine load).
An alternative (one diffrax solve with the held command as a state updated at the sample
times) needs the solve stopped at each sample anyway, which is what the scan does.

Trajectory outputs in digital mode are linear interpolations of the states at the sample times
(exact at the sample times); ``u_command`` is the held command.
"""

from __future__ import annotations

import math

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._mixer import (
    inputs_from_rotor_speeds_sq,
    omega_d,
    rotor_speeds_sq_from_inputs,
    safe_sqrt,
    saturate_rotor_speeds_sq,
)
from ._params import QuadrotorParams
from ._plant import (
    CHANNEL_INDEX,
    diverged_from,
    hover_input,
    plant_derivative,
    thrust_direction,
)
from ._typing import Array, Float, Int, PlantState, Scalar, Vec3, Vec4
from ._validation import check_nonnegative, concrete
from ._wind import wind_wrench

PLANT_MODELS: tuple[str, ...] = ("paper", "full")
FULL_STATE_LAYOUT: tuple[str, ...] = (
    "x", "y", "z", "phi", "theta", "psi", "xd", "yd", "zd", "p", "q", "r",
)
"""Names of the 12 full-plant state entries (body rates p, q, r at 9-11)."""
NOISE_FIELDS: tuple[str, ...] = (
    "noise_angle", "noise_rate", "noise_altitude", "noise_vertical_speed",
)


def _as_float(x) -> Array:
    return jnp.asarray(x, dtype=jnp.result_type(float))


def _as_int(x) -> Array:
    return jnp.asarray(x, dtype=jnp.int32)


def _as_key(x) -> Array:
    if isinstance(x, int | np.integer):
        return jax.random.PRNGKey(int(x))
    return jnp.asarray(x, dtype=jnp.uint32)


class UnmodeledDynamics(eqx.Module):
    """Per-case unmodeled-dynamics settings; layout and meaning in the module docstring.

    The default instance is the paper's model with a continuous controller (equivalent to
    ``simulate(..., unmodeled=None)`` up to round-off).
    """

    plant: str = eqx.field(default="paper", static=True)
    motor_tau: Scalar = eqx.field(default=0.0, converter=_as_float)
    max_samples: int = eqx.field(default=0, static=True)
    control_rate: Scalar = eqx.field(default=1000.0, converter=_as_float)
    delay_samples: Int[Array, ""] = eqx.field(default=0, converter=_as_int)
    max_delay: int = eqx.field(default=8, static=True)
    noise_angle: Scalar = eqx.field(default=0.0, converter=_as_float)
    noise_rate: Scalar = eqx.field(default=0.0, converter=_as_float)
    noise_altitude: Scalar = eqx.field(default=0.0, converter=_as_float)
    noise_vertical_speed: Scalar = eqx.field(default=0.0, converter=_as_float)
    key: Array = eqx.field(default=0, converter=_as_key)

    def __check_init__(self):
        owner = type(self).__name__
        if self.plant not in PLANT_MODELS:
            raise ValueError(
                f"{owner}.plant must be one of {', '.join(PLANT_MODELS)}, got {self.plant!r}."
            )
        if not isinstance(self.max_samples, int) or self.max_samples < 0:
            raise ValueError(f"{owner}.max_samples must be an int >= 0, got {self.max_samples!r}.")
        if not isinstance(self.max_delay, int) or self.max_delay < 0:
            raise ValueError(f"{owner}.max_delay must be an int >= 0, got {self.max_delay!r}.")
        check_nonnegative(owner, "motor_tau", self.motor_tau)
        for name in NOISE_FIELDS:
            check_nonnegative(owner, name, getattr(self, name))
        tau = concrete(self.motor_tau)
        if tau is not None and not np.all(np.isfinite(tau)):
            raise ValueError(f"{owner}.motor_tau must be finite [s], got {tau!r}.")
        delay = concrete(self.delay_samples)
        if delay is not None and not (np.all(delay >= 0) and np.all(delay <= self.max_delay)):
            raise ValueError(
                f"{owner}.delay_samples must be in [0, max_delay = {self.max_delay}], got "
                f"{delay!r}."
            )
        rate = concrete(self.control_rate)
        if self.max_samples > 0:
            if rate is not None and not (np.all(np.isfinite(rate)) and np.all(rate > 0)):
                raise ValueError(f"{owner}.control_rate must be finite and > 0 [Hz], got "
                                 f"{rate!r}.")
        else:
            extra = [n for n in NOISE_FIELDS if (v := concrete(getattr(self, n))) is not None
                     and np.any(v != 0)]
            if delay is not None and np.any(delay != 0):
                extra.append("delay_samples")
            if extra:
                raise ValueError(
                    f"{owner}: {', '.join(extra)} need a digital controller (max_samples > 0; "
                    "use UnmodeledDynamics.make(control_rate=..., duration=...))."
                )

    @property
    def digital(self) -> bool:
        return self.max_samples > 0

    @classmethod
    def make(
        cls,
        plant: str = "paper",
        motor_tau: float = 0.0,
        control_rate: float | None = None,
        duration: float = 20.0,
        delay_samples: int = 0,
        noise_angle: float = 0.0,
        noise_rate: float = 0.0,
        noise_altitude: float = 0.0,
        noise_vertical_speed: float = 0.0,
        seed: int = 0,
        max_delay: int | None = None,
        max_samples: int | None = None,
    ) -> UnmodeledDynamics:
        """Convenience constructor: ``control_rate`` None = continuous controller, else a
        digital controller at that rate [Hz] with ``max_samples = ceil(duration * rate)``
        (``duration`` = t1 - t0 of the scenarios it will run [s]) unless given (a common
        ``max_samples`` lets settings with different rates share one batch / compilation)."""
        if control_rate is None:
            max_samples = 0
        elif max_samples is None:
            max_samples = int(math.ceil(duration * control_rate - 1e-9))
        return cls(
            plant=plant, motor_tau=motor_tau, max_samples=max_samples,
            control_rate=1000.0 if control_rate is None else control_rate,
            delay_samples=delay_samples,
            max_delay=max(8, delay_samples) if max_delay is None else max_delay,
            noise_angle=noise_angle, noise_rate=noise_rate, noise_altitude=noise_altitude,
            noise_vertical_speed=noise_vertical_speed, key=seed,
        )

    def noise_std(self) -> PlantState:
        """Per-entry measurement-noise standard deviation, paper state layout, shape (12,)."""
        z = jnp.zeros_like(self.noise_angle)
        a, r = self.noise_angle, self.noise_rate
        return jnp.stack([z, z, self.noise_altitude, a, a, a, z, z, self.noise_vertical_speed,
                          r, r, r])


def unmodeled_config(settings: UnmodeledDynamics) -> dict:
    """Plain-JSON description of (unbatched) settings, for result-file metadata."""
    out: dict = {"plant": settings.plant, "max_samples": settings.max_samples,
                 "max_delay": settings.max_delay}
    for name in ("motor_tau", "control_rate", "delay_samples", *NOISE_FIELDS):
        out[name] = np.asarray(getattr(settings, name)).tolist()
    out["key"] = np.asarray(settings.key).tolist()
    out["digital"] = settings.digital
    return out


def stack_unmodeled(settings: list[UnmodeledDynamics]) -> UnmodeledDynamics:
    """Stack settings with equal static fields along a new leading axis (for `jax.vmap`)."""
    if not settings:
        raise ValueError("stack_unmodeled needs at least one UnmodeledDynamics.")
    return jax.tree.map(lambda *xs: jnp.stack(xs), *settings)


# ------------------------------------------------------------------------------------------
# full rigid-body plant


def euler_rates_from_body_rates(phi: Scalar, theta: Scalar, omega: Vec3) -> Vec3:
    """etad = T(eta) omega for ZYX Euler angles (paper eq. 6-7) [rad/s]."""
    p, q, r = omega[0], omega[1], omega[2]
    sphi, cphi = jnp.sin(phi), jnp.cos(phi)
    tth, cth = jnp.tan(theta), jnp.cos(theta)
    return jnp.stack([
        p + sphi * tth * q + cphi * tth * r,
        cphi * q - sphi * r,
        (sphi * q + cphi * r) / cth,
    ])


def body_rates_from_euler_rates(phi: Scalar, theta: Scalar, etad: Vec3) -> Vec3:
    """omega = T(eta)^-1 etad (inverse of `euler_rates_from_body_rates`) [rad/s]."""
    phid, thetad, psid = etad[0], etad[1], etad[2]
    sphi, cphi = jnp.sin(phi), jnp.cos(phi)
    sth, cth = jnp.sin(theta), jnp.cos(theta)
    return jnp.stack([
        phid - sth * psid,
        cphi * thetad + sphi * cth * psid,
        -sphi * thetad + cphi * cth * psid,
    ])


def full_plant_derivative(
    params: QuadrotorParams,
    state: PlantState,
    u: Vec4,
    omega_d_: Scalar,
    mass: Scalar,
    force: Vec3,
    torque: Vec3,
) -> PlantState:
    """Time derivative of the full rigid-body state (`FULL_STATE_LAYOUT`).

    Translation eq. (8) with the full rotation matrix; attitude kinematics etad = T(eta) omega
    (eq. 6-7); Euler's equation I omegad = -omega x I omega - omega x (0, 0, Jr Omega_d) + tau
    (eq. 10-11; gyroscopic sign as in `plant_derivative`, times ``gyro_sign``), with body
    torque tau = (l u1, l u2, u3) + external torque (taken in the body frame). Same arguments
    as `afbl_jax._plant.plant_derivative`; its eq. (15) is the small-angle form of this.
    """
    phi, theta, psi = state[3], state[4], state[5]
    p, q, r = state[9], state[10], state[11]
    Ix, Iy, Iz, Jr, arm = params.Ix, params.Iy, params.Iz, params.Jr, params.arm_length
    acc_lin = thrust_direction(phi, theta, psi) * u[3] / mass + force / mass
    acc_lin = acc_lin.at[2].add(-params.g)
    gyro = params.gyro_sign * Jr * omega_d_
    pd = ((Iy - Iz) * q * r - gyro * q + arm * u[0] + torque[0]) / Ix
    qd = ((Iz - Ix) * p * r + gyro * p + arm * u[1] + torque[1]) / Iy
    rd = ((Ix - Iy) * p * q + u[2] + torque[2]) / Iz
    etad = euler_rates_from_body_rates(phi, theta, state[9:12])
    return jnp.concatenate([state[6:9], etad, acc_lin, jnp.stack([pd, qd, rd])])


def to_paper_layout(plant: str, state: PlantState) -> PlantState:
    """The paper-layout (Euler-rate) view of a plant state of model ``plant``."""
    if plant == "paper":
        return state
    etad = euler_rates_from_body_rates(state[3], state[4], state[9:12])
    return jnp.concatenate([state[:9], etad])


def from_paper_layout(plant: str, state: PlantState) -> PlantState:
    """Inverse of `to_paper_layout` (initial states are given in the paper layout)."""
    if plant == "paper":
        return state
    omega = body_rates_from_euler_rates(state[3], state[4], state[9:12])
    return jnp.concatenate([state[:9], omega])


def _plant_fn(plant: str):
    return plant_derivative if plant == "paper" else full_plant_derivative


def measurement_noise(settings: UnmodeledDynamics, k) -> PlantState:
    """The measurement noise added at control sample k (paper layout, shape (12,)).

    Gaussian, zero mean, standard deviations `UnmodeledDynamics.noise_std`, drawn from
    ``jax.random.fold_in(settings.key, k)``: the same key and k always give the same noise.
    """
    sub = jax.random.fold_in(settings.key, k)
    std = settings.noise_std()
    return std * jax.random.normal(sub, (12,), dtype=std.dtype)


def measure(settings: UnmodeledDynamics, state: PlantState, k) -> PlantState:
    """What the digital controller measures at sample k: paper-layout state plus noise."""
    return to_paper_layout(settings.plant, state) + measurement_noise(settings, k)


# ------------------------------------------------------------------------------------------
# closed loop


class UnmodeledState(eqx.Module):
    """Closed-loop ODE state with rotor speeds (layout in the module docstring)."""

    plant: Float[Array, 12]
    rotors: Float[Array, 4]
    controller: Float[Array, 4]
    cost: Float[Array, 4]


class _UArgs(eqx.Module):
    controller: object
    scenario: object
    vehicle: QuadrotorParams
    model: QuadrotorParams
    limits: object
    settings: UnmodeledDynamics
    held: tuple | None  # (u_cmd, w_cmd) held by the digital controller, None = continuous


def _with_held(args: _UArgs, u_cmd, w_cmd) -> _UArgs:
    return _UArgs(args.controller, args.scenario, args.vehicle, args.model, args.limits,
                  args.settings, (u_cmd, w_cmd))


def _command(args: _UArgs, t, measured: PlantState, ctrl_state):
    ref = args.scenario.reference(t)
    u_cmd, dctrl = args.controller(t, measured, ctrl_state, ref, args.model)
    return u_cmd, rotor_speeds_sq_from_inputs(args.model, u_cmd), dctrl


def _signals_and_derivative(t, y: UnmodeledState, args: _UArgs):
    from ._simulate import Signals

    s = args.settings
    ref = args.scenario.reference(t)
    if args.held is None:
        meas = to_paper_layout(s.plant, y.plant)
        u_cmd, w_cmd, dctrl = _command(args, t, meas, y.controller)
    else:
        (u_cmd, w_cmd), dctrl = args.held, jnp.zeros_like(y.controller)
    w_sat = saturate_rotor_speeds_sq(args.vehicle, w_cmd)
    omega_cmd = safe_sqrt(w_sat)
    lag = s.motor_tau > 0
    tau = jnp.where(lag, s.motor_tau, 1.0)
    omega = jnp.where(lag, y.rotors, omega_cmd)
    drotors = jnp.where(lag, (omega_cmd - y.rotors) / tau, 0.0)
    u = inputs_from_rotor_speeds_sq(args.vehicle, omega**2)
    force, torque = args.scenario.disturbance(t)
    wind_force, wind_torque = wind_wrench(t, y.plant, args.scenario, args.vehicle)
    force, torque = force + wind_force, torque + wind_torque
    mass = args.vehicle.m * args.scenario.mass_factor(t)
    dplant = _plant_fn(s.plant)(args.vehicle, y.plant, u, omega_d(omega), mass, force, torque)
    e = ref.r - y.plant[CHANNEL_INDEX]
    du = u - hover_input(args.vehicle, mass)
    w_hover = args.vehicle.m * args.vehicle.g / (4.0 * args.vehicle.b)
    excess = (w_cmd - w_sat) / w_hover
    dcost = jnp.stack([jnp.sum(e[:3] ** 2), e[3] ** 2, jnp.sum(du**2), jnp.sum(excess**2)])
    signals = Signals(ref.r, e, u_cmd, u, omega, force, torque, mass)
    return signals, UnmodeledState(dplant, drotors, dctrl, dcost)


def _vector_field(t, y, args):
    return _signals_and_derivative(t, y, args)[1]


def _diverged(t, y: UnmodeledState, args: _UArgs, **kwargs):
    del kwargs
    ref = args.scenario.reference(t)
    return diverged_from(y.plant, ref.r[3] - y.plant[2], args.limits, y.controller, y.rotors)


def _initial_state(controller, scenario, settings, args, dtype):
    plant0 = from_paper_layout(settings.plant, scenario.initial_state.astype(dtype))
    ctrl0 = controller.init_state().astype(dtype)
    meas0 = to_paper_layout(settings.plant, plant0)
    _, w_cmd0, _ = _command(args, scenario.t0, meas0, ctrl0)
    rotors0 = safe_sqrt(saturate_rotor_speeds_sq(args.vehicle, w_cmd0))
    from ._simulate import COST_LAYOUT

    return UnmodeledState(plant0, rotors0, ctrl0, jnp.zeros(len(COST_LAYOUT), dtype)), meas0


def _solver_status(result, finite):
    from ._simulate import solver_status  # (_simulate imports this module)

    return solver_status(result, finite)


def _result(ts, traj, signals, final: UnmodeledState, t_final, status, steps):
    from ._simulate import ClosedLoopState, make_result

    closed = ClosedLoopState(final.plant, final.controller, final.cost)
    return make_result(ts, traj.plant, traj.controller, signals, closed, t_final, status, steps)


@eqx.filter_jit
def simulate_unmodeled(controller, scenario, vehicle, model, limits, settings, solver, rtol,
                       atol, n_save, max_steps, adjoint):
    """`simulate` with unmodeled dynamics (called by `afbl_jax.simulate(unmodeled=...)`)."""
    if settings.digital:
        return _simulate_digital(controller, scenario, vehicle, model, limits, settings, solver,
                                 rtol, atol, n_save, max_steps, adjoint)
    return _simulate_continuous(controller, scenario, vehicle, model, limits, settings, solver,
                                rtol, atol, n_save, max_steps, adjoint)


def _empty_like_signals(args, t0, y0):
    sig = _signals_and_derivative(t0, y0, args)[0]
    return jax.tree.map(lambda a: jnp.zeros((0, *a.shape), a.dtype), sig)


def _simulate_continuous(controller, scenario, vehicle, model, limits, settings, solver, rtol,
                         atol, n_save, max_steps, adjoint):
    args = _UArgs(controller, scenario, vehicle, model, limits, settings, None)
    dtype = jnp.result_type(float)
    y0, _ = _initial_state(controller, scenario, settings, args, dtype)
    from ._simulate import ClosedLoopState, solve_closed_loop

    return solve_closed_loop(
        _vector_field, _diverged, lambda t, y: _signals_and_derivative(t, y, args)[0], solver,
        scenario, y0, args, rtol, atol, n_save, max_steps, adjoint,
        lambda y: ClosedLoopState(y.plant, y.controller, y.cost))


def _simulate_digital(controller, scenario, vehicle, model, limits, settings, solver, rtol, atol,
                      n_save, max_steps, adjoint):
    from ._simulate import STATUS_MAX_STEPS, STATUS_OK

    args = _UArgs(controller, scenario, vehicle, model, limits, settings, None)
    dtype = jnp.result_type(float)
    y0, meas0 = _initial_state(controller, scenario, settings, args, dtype)
    t0, t1 = scenario.t0.astype(dtype), scenario.t1.astype(dtype)
    h = 1.0 / settings.control_rate.astype(dtype)
    nbuf = settings.max_delay + 1
    delay = jnp.clip(settings.delay_samples, 0, settings.max_delay)
    buf0 = jnp.broadcast_to(meas0, (nbuf, 12))
    stepsize = diffrax.ClipStepSizeController(
        diffrax.PIDController(rtol=rtol, atol=atol), jump_ts=scenario.jump_times()
    )
    term = diffrax.ODETerm(_vector_field)
    zero_i = jnp.zeros((), jnp.int32)

    def step(carry, k):
        y, buf, status, t_final, nsteps = carry
        t_k = t0 + k.astype(dtype) * h
        alive = (status == STATUS_OK) & (t_k < t1)
        start = jnp.minimum(t_k, t1)
        end = jnp.where(alive, jnp.minimum(t_k + h, t1), start)
        buf = buf.at[k % nbuf].set(measure(settings, y.plant, k))
        meas = buf[(k - delay) % nbuf]
        u_cmd, w_cmd, dctrl = _command(args, t_k, meas, y.controller)
        omega_cmd = safe_sqrt(saturate_rotor_speeds_sq(vehicle, w_cmd))
        y_in = eqx.tree_at(lambda s: s.rotors, y, jnp.where(k == 0, omega_cmd, y.rotors))
        sol = diffrax.diffeqsolve(
            term, solver, start, end, end - start, y_in,
            args=_with_held(args, u_cmd, w_cmd),
            saveat=diffrax.SaveAt(t1=True), stepsize_controller=stepsize, max_steps=max_steps,
            event=diffrax.Event(_diverged), adjoint=adjoint, throw=False,
        )
        y_end = jax.tree.map(lambda a: a[-1], sol.ys)
        y_end = eqx.tree_at(lambda s: s.controller, y_end, y.controller + h * dctrl)
        finite = jnp.all(jnp.isfinite(y_end.cost)) & jnp.all(jnp.isfinite(y_end.plant))
        new_status = jnp.where(alive, _solver_status(sol.result, finite), status)
        y_new = jax.tree.map(lambda a, b: jnp.where(alive, a, b), y_end, y)
        t_final = jnp.where(alive, sol.ts[-1], t_final)
        stats = jnp.stack([jnp.asarray(sol.stats[n]) for n in
                           ("num_steps", "num_accepted_steps", "num_rejected_steps")])
        nsteps = nsteps + jnp.where(alive, stats, 0)
        out = (y_new, u_cmd, w_cmd, t_final) if n_save else None
        return (y_new, buf, new_status, t_final, nsteps), out

    carry0 = (y0, buf0, zero_i + STATUS_OK, t0, jnp.zeros(3, jnp.int32))
    (final, _, status, t_final, nsteps), outs = jax.lax.scan(
        step, carry0, jnp.arange(settings.max_samples, dtype=jnp.int32)
    )
    # not enough samples to reach t1: report like a solver running out of steps
    status = jnp.where((status == STATUS_OK) & (t_final < t1), STATUS_MAX_STEPS, status)
    status = status.astype(jnp.int32)
    if n_save:
        ys, u_cmds, w_cmds, t_ends = outs
        ts = t0 + (t1 - t0) * jnp.linspace(0.0, 1.0, n_save, dtype=dtype)
        sample_ts = jnp.concatenate([t0[None], t_ends])
        states = jax.tree.map(lambda a0, a: jnp.concatenate([a0[None], a]), y0, ys)

        def interp(a):
            flat = a.reshape(a.shape[0], -1)
            cols = jax.vmap(lambda c: jnp.interp(ts, sample_ts, c), in_axes=1, out_axes=1)(flat)
            return cols.reshape(ts.shape[0], *a.shape[1:])

        traj = jax.tree.map(interp, states)
        idx = jnp.clip(jnp.floor((ts - t0) / h).astype(jnp.int32), 0, settings.max_samples - 1)
        held_u, held_w = u_cmds[idx], w_cmds[idx]

        def sig(t, y, u, w):
            return _signals_and_derivative(t, y, _with_held(args, u, w))[0]

        signals = jax.vmap(sig)(ts, traj, held_u, held_w)
        # after an early stop the trajectory is padded with inf, as in `simulate`
        dead = ts > t_final
        traj, signals = jax.tree.map(
            lambda a: jnp.where(dead.reshape(-1, *([1] * (a.ndim - 1))), jnp.inf, a),
            (traj, signals),
        )
    else:
        ts = jnp.zeros((0,), dtype)
        traj = jax.tree.map(lambda a: jnp.zeros((0, *a.shape), a.dtype), y0)
        signals = _empty_like_signals(args, t0, y0)
    return _result(ts, traj, signals, final, t_final, status, tuple(nsteps))
