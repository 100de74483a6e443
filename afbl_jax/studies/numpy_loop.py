"""The Monte-Carlo closed loop in NumPy, solved with `scipy.integrate.solve_ivp`: the baseline a
user would otherwise write for the default distribution's cases (``afbl bench`` row
``scipy_rk45_montecarlo_cases``), written from the equations of `afbl_jax.model`,
`afbl_jax.scenario` and `afbl_jax.sim.ClosedLoop` (this module imports neither JAX nor the
rest of the package's numerics: only NumPy and scipy).

The loop (`NumpyCase.derivative`; continuous control, instantaneous rotors, the paper plant):

- reference r(t) of (phi, theta, psi, z): offset + minimum-jerk steps
  s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5 + a sinusoid, with exact rd, rdd
  (`afbl_jax.scenario.Reference`); position reference (x, y) likewise (or the initial
  position held);
- position loop (`afbl_jax.model.PositionHold`): a_cmd = a_ref + kp e_p + kd e_v + ki I,
  scaled onto a_max = g tan(tilt_max); (phi, theta)_cmd = (atan2(-b_y, sqrt(b_x^2 + g^2)),
  atan2(b_x, g)) with b = Rz(psi)^T a_sat; a critically damped command filter
  rdd = w_f^2 (cmd - r) - 2 w_f rd gives the roll and pitch references; dI/dt =
  e_p + (a_sat - a_cmd) / (ki T_w);
- inner controller on e = r - q, ed = rd - qd: AFBL v = rdd + lam ed - delta_hat + k s,
  s = ed + lam e, d delta_hat/dt = -s / gamma; AFBL as printed v = rdd - delta_hat + k ed,
  d delta_hat/dt = -ed / gamma; FBL+PID v = P e + I int(e) + D ed; then the inversion eq. (24)
  with the nominal model;
- mixer: exact inverse of eq. (16) with the model's (b, d), squared rotor speeds clipped to the
  vehicle's [omega_min^2, omega_max^2]; applied inputs from the vehicle's (b, d);
- wind: mean + 1-cosine gusts + sum of sinusoids (C cos(omega t) + S sin(omega t)) from the
  case's `afbl_jax.Wind` arrays; aerodynamics: `RotorDrag` (H-force at the hubs + quadratic
  parasitic drag) or `LinearDrag`;
- pulses of force and torque, payload mass from its attach time, plant eq. (15) corrected
  (`afbl_jax.model.plant_derivative`, gyroscopic term with the vehicle's sign);
- running ISE: attitude (against the position loop's commanded roll and pitch), altitude and,
  with a position loop, position.

The initial state is the case's (trimmed) initial plant state; the controller states at t0 are
those of `afbl_jax.sim.ClosedLoop.initial_controller_state` (position loop at rest at the trim
attitude, the inner controller holding the trim's command at zero error). `solve_ivp` (RK45 by
default) runs between the scenario's jump times (pulse edges, payload, gusts, blends), as the
JAX solve clips its steps onto them, and stops at the divergence limits.

Cases come from the package's case pytrees (`case_from_pytrees`, `cases_from_batch`): data
only (arrays read with ``numpy.asarray``), nothing of the dynamics is computed there.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

_CHANNEL_INDEX = (3, 4, 5, 2)
_CHANNEL_RATE_INDEX = (9, 10, 11, 8)


def _a(x) -> np.ndarray:
    return np.asarray(x, dtype=np.float64)


@dataclass(frozen=True)
class Steps:
    """Sum of minimum-jerk steps and a sinusoid per channel (`afbl_jax.scenario.Reference`,
    `PositionReference`): offset (C,), step_start/size/duration (C, S), sine (C,)."""

    offset: np.ndarray
    step_start: np.ndarray
    step_size: np.ndarray
    step_duration: np.ndarray
    sine_amplitude: np.ndarray
    sine_frequency: np.ndarray
    sine_phase: np.ndarray

    @classmethod
    def of(cls, ref) -> Steps:
        return cls(*(_a(getattr(ref, f)) for f in cls.__dataclass_fields__))

    def __call__(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(r, rd, rdd) at time t [s]."""
        tc = np.clip((t - self.step_start) * self._inverse_duration, 0.0, 1.0)
        inside = (tc > 0.0) & (tc < 1.0)
        s = tc**3 * (10.0 - 15.0 * tc + 6.0 * tc**2)
        ds = np.where(inside, 30.0 * tc**2 * (1.0 - tc) ** 2, 0.0)
        dds = np.where(inside, 60.0 * tc * (1.0 - tc) * (1.0 - 2.0 * tc), 0.0)
        scaled = self.step_size * self._inverse_duration
        r = self.offset + (self.step_size * s).sum(-1)
        rd = (scaled * ds).sum(-1)
        rdd = (scaled * self._inverse_duration * dds).sum(-1)
        if self._has_sine:
            wt = self.sine_frequency * t + self.sine_phase
            a, w = self.sine_amplitude, self.sine_frequency
            r = r + a * np.sin(wt)
            rd = rd + a * w * np.cos(wt)
            rdd = rdd - a * w**2 * np.sin(wt)
        return r, rd, rdd

    @functools.cached_property
    def _inverse_duration(self) -> np.ndarray:
        return 1.0 / self.step_duration

    @functools.cached_property
    def _has_sine(self) -> bool:
        return bool(np.any(self.sine_amplitude != 0.0))

    def kink_times(self) -> np.ndarray:
        starts = self.step_start.reshape(-1)
        return np.concatenate([starts, starts + self.step_duration.reshape(-1)])


@dataclass(frozen=True)
class NumpyWind:
    """`afbl_jax.Wind` in NumPy: mean (3,), gusts (G,), (G, 3), (G, 3), turbulence lines
    omega (K,) and quadrature coefficients C, S (3, K) [m/s]."""

    mean: np.ndarray
    gust_start: np.ndarray
    gust_buildup: np.ndarray
    gust_amplitude: np.ndarray
    frequency: np.ndarray
    cos: np.ndarray
    sin: np.ndarray

    @classmethod
    def of(cls, wind) -> NumpyWind:
        return cls(
            _a(wind.mean),
            _a(wind.gust_start),
            _a(wind.gust_buildup),
            _a(wind.gust_amplitude),
            _a(wind.turbulence_frequency),
            _a(wind.turbulence_cos),
            _a(wind.turbulence_sin),
        )

    def __call__(self, t: float) -> np.ndarray:
        """Wind velocity (x, y, z) [m/s], earth frame, at time t [s]."""
        tau = np.clip((t - self.gust_start[:, None]) / self.gust_buildup, 0.0, 1.0)
        gust = (self.gust_amplitude * 0.5 * (1.0 - np.cos(np.pi * tau))).sum(0)
        arg = self.frequency * t
        return self.mean + gust + self.cos @ np.cos(arg) + self.sin @ np.sin(arg)

    def jump_times(self) -> np.ndarray:
        ends = self.gust_start[:, None] + self.gust_buildup
        return np.concatenate([self.gust_start, ends.reshape(-1)])


@dataclass(frozen=True)
class NumpyCase:
    """One closed-loop case in NumPy (see the module docstring); build it with
    `case_from_pytrees` or `cases_from_batch`.

    Attributes:
        controller: "afbl", "afbl_paper" or "fbl"; gains: its gains by name, each (4,).
        vehicle, model: the true vehicle's and the controller's model parameters by the
            `afbl_jax.QuadrotorParams` field names.
        aerodynamics: "rotor_drag" or "linear".
        position_loop: `afbl_jax.PositionHold` fields by name (kp, kd, ki (2,), tilt_max,
            filter_frequency, windup_time), or None (no position loop).
        reference, position: attitude/altitude and position references (position None:
            hold the initial position).
        pulses: (start (P,), duration (P,), torque (P, 3), force (P, 3)).
        wind: the case's wind.
        payload_fraction, payload_time: payload p and its attach time [s].
        initial_plant: plant state at t0 (12,), paper layout; t0, t1 [s].
        trim: (attitude (2,), command (4,)) of a trimmed start, or None.
        limits: divergence limits (attitude [rad], altitude error [m]).
    """

    controller: str
    gains: dict
    vehicle: dict
    model: dict
    aerodynamics: str
    position_loop: dict | None
    reference: Steps
    position: Steps | None
    pulses: tuple
    wind: NumpyWind
    payload_fraction: float
    payload_time: float
    initial_plant: np.ndarray
    t0: float
    t1: float
    trim: tuple | None
    limits: tuple = (1.2, 10.0)

    # ------------------------------------------------------------------ layout
    @property
    def n_controller(self) -> int:
        return 4 + (6 if self.position_loop is not None else 0)

    @property
    def ise_index(self) -> int:
        """Index of the first ISE state (attitude, altitude, then position with a position
        loop) in the ODE state."""
        return 12 + self.n_controller

    # ------------------------------------------------------------------ pieces
    def _position_reference(self, t):
        if self.position is None:
            r = self.initial_plant[0:2]
            return r, np.zeros(2), np.zeros(2)
        return self.position(t)

    def _outer(self, position, plant, outer):
        """Position loop on the position reference ``position`` = (r, rd, rdd): (attitude
        reference r, rd, rdd (2,) each, d outer / dt (6,))."""
        pl, g = self.position_loop, self.model["g"]
        pr, prd, prdd = position
        e_p = pr - plant[0:2]
        a_cmd = prdd + pl["kp"] * e_p + pl["kd"] * (prd - plant[6:8]) + pl["ki"] * outer[0:2]
        a_max = g * math.tan(pl["tilt_max"])
        n2 = a_cmd[0] ** 2 + a_cmd[1] ** 2
        a_sat = a_cmd * (a_max / math.sqrt(n2)) if n2 > a_max**2 else a_cmd
        c, s = math.cos(plant[5]), math.sin(plant[5])
        bx = c * a_sat[0] + s * a_sat[1]
        by = -s * a_sat[0] + c * a_sat[1]
        cmd = np.array([math.atan2(-by, math.sqrt(bx**2 + g**2)), math.atan2(bx, g)])
        wf = pl["filter_frequency"]
        r, rd = outer[2:4], outer[4:6]
        rdd = wf**2 * (cmd - r) - 2.0 * wf * rd
        dintegral = e_p + (a_sat - a_cmd) / (pl["ki"] * pl["windup_time"])
        return r, rd, rdd, np.concatenate([dintegral, rd, rdd])

    def _reference(self, t, plant, controller_state, position=None):
        """Inner controller's (r, rd, rdd) and d outer / dt (None without a position loop);
        ``position``: the position reference at t (None: evaluated here)."""
        r, rd, rdd = self.reference(t)
        if self.position_loop is None:
            return r, rd, rdd, None
        if position is None:
            position = self._position_reference(t)
        ar, ard, ardd, douter = self._outer(position, plant, controller_state[4:])
        r = np.concatenate([ar, r[2:]])
        rd = np.concatenate([ard, rd[2:]])
        rdd = np.concatenate([ardd, rdd[2:]])
        return r, rd, rdd, douter

    def _virtual_input(self, e, ed, rdd, state):
        g = self.gains
        if self.controller == "afbl":
            s = ed + g["lam"] * e
            return rdd + g["lam"] * ed - state + g["k"] * s, -s / g["gamma"]
        if self.controller == "afbl_paper":
            return rdd - state + g["k"] * ed, -ed / g["gamma"]
        return g["P"] * e + g["I"] * state + g["D"] * ed, e

    def _state_for(self, v, rdd):
        if self.controller == "fbl":
            return v / self.gains["I"]
        return rdd - v

    def _feedback_linearize(self, plant, v):
        """Eq. (24) with the nominal model."""
        p = self.model
        ix, iy, iz, arm = p["Ix"], p["Iy"], p["Iz"], p["arm_length"]
        phid, thetad, psid = plant[9], plant[10], plant[11]
        return np.array(
            [
                ix / arm * (v[0] - thetad * psid * (iy - iz) / ix),
                iy / arm * (v[1] - phid * psid * (iz - ix) / iy),
                iz * (v[2] - phid * thetad * (ix - iy) / iz),
                p["m"] * (p["g"] + v[3]) / (math.cos(plant[3]) * math.cos(plant[4])),
            ]
        )

    def _virtual_input_for(self, plant, u):
        """Inverse of `_feedback_linearize` (the trimmed start)."""
        p = self.model
        ix, iy, iz, arm = p["Ix"], p["Iy"], p["Iz"], p["arm_length"]
        phid, thetad, psid = plant[9], plant[10], plant[11]
        return np.array(
            [
                arm * u[0] / ix + thetad * psid * (iy - iz) / ix,
                arm * u[1] / iy + phid * psid * (iz - ix) / iy,
                u[2] / iz + phid * thetad * (ix - iy) / iz,
                u[3] * math.cos(plant[3]) * math.cos(plant[4]) / p["m"] - p["g"],
            ]
        )

    def _aero(self, wind, plant, omega):
        """(force [N] earth frame, torque [N m] body) of the aerodynamic model."""
        veh = self.vehicle
        phi, theta, psi = plant[3], plant[4], plant[5]
        cphi, sphi = math.cos(phi), math.sin(phi)
        cth, sth = math.cos(theta), math.sin(theta)
        cpsi, spsi = math.cos(psi), math.sin(psi)
        rot = np.array(
            [
                [cpsi * cth, cpsi * sth * sphi - spsi * cphi, cphi * sth * cpsi + sphi * spsi],
                [spsi * cth, spsi * sth * sphi + cpsi * cphi, cphi * sth * spsi - sphi * cpsi],
                [-sth, cth * sphi, cphi * cth],
            ]
        )
        h_cp = veh["cp_offset"]
        if self.aerodynamics == "linear":
            force = veh["drag_coefficient"] * (wind - plant[6:9])
            f_body = rot.T @ force
            return force, np.array([-h_cp * f_body[1], h_cp * f_body[0], 0.0])
        phid, thetad, psid = plant[9], plant[10], plant[11]
        rates = np.array(
            [
                phid - sth * psid,
                cphi * thetad + sphi * cth * psid,
                -sphi * thetad + cphi * cth * psid,
            ]
        )
        v_air = rot.T @ (plant[6:9] - wind)
        # v_hub = v_air + rates x r_i, r_i the hub positions (rows of `_hubs`)
        hubs = self._hubs
        hx, hy, hz = hubs[:, 0], hubs[:, 1], hubs[:, 2]
        p, q, r = rates
        v_hub = np.stack(
            [v_air[0] + q * hz - r * hy, v_air[1] + r * hx - p * hz, v_air[2] + p * hy - q * hx],
            axis=1,
        )
        h_force = -omega[:, None] * self._rotor_k * v_hub
        fx, fy, fz = h_force[:, 0], h_force[:, 1], h_force[:, 2]
        speed = math.sqrt(v_air @ v_air)
        parasitic = -speed * self._parasitic_k * v_air
        f_body = h_force.sum(0) + parasitic
        torque = np.array(  # sum_i r_i x H_i + r_cp x D, r_cp = (0, 0, h_cp)
            [
                (hy * fz - hz * fy).sum() - h_cp * parasitic[1],
                (hz * fx - hx * fz).sum() + h_cp * parasitic[0],
                (hx * fy - hy * fx).sum(),
            ]
        )
        return rot @ f_body, torque

    @functools.cached_property
    def _hubs(self) -> np.ndarray:
        arm, h = self.vehicle["arm_length"], self.vehicle["hub_height"]
        return np.array([[arm, 0.0, h], [0.0, -arm, h], [-arm, 0.0, h], [0.0, arm, h]])

    @functools.cached_property
    def _rotor_k(self) -> np.ndarray:
        kd, kz = self.vehicle["rotor_drag_horizontal"], self.vehicle["rotor_drag_vertical"]
        return np.array([kd, kd, kz])

    @functools.cached_property
    def _parasitic_k(self) -> np.ndarray:
        c_xy = self.vehicle["parasitic_drag_horizontal"]
        return np.array([c_xy, c_xy, self.vehicle["parasitic_drag_vertical"]])

    # ------------------------------------------------------------------ the loop
    def initial_state(self) -> np.ndarray:
        """ODE state at t0: plant, controller states (trimmed start: holding the trim), ISE 0."""
        plant = np.array(self.initial_plant, dtype=np.float64)
        inner = np.zeros(4)
        parts = [inner]
        if self.position_loop is not None:
            att = plant[3:5] if self.trim is None else self.trim[0]
            g, psi = self.model["g"], plant[5]
            bx = g * math.tan(att[1])
            by = -math.tan(att[0]) * math.sqrt(bx**2 + g**2)
            c, s = math.cos(psi), math.sin(psi)
            accel = np.array([c * bx - s * by, s * bx + c * by])
            parts.append(np.concatenate([accel / self.position_loop["ki"], att, np.zeros(2)]))
        ctrl = np.concatenate(parts)
        if self.trim is not None:
            trim_state = plant.copy()
            trim_state[3:5] = self.trim[0]
            trim_state[9:12] = 0.0
            _, _, rdd, _ = self._reference(self.t0, trim_state, ctrl)
            v = self._virtual_input_for(trim_state, self.trim[1])
            ctrl[:4] = self._state_for(v, rdd)
        n_ise = 2 + (self.position_loop is not None)
        return np.concatenate([plant, ctrl, np.zeros(n_ise)])

    def derivative(self, t: float, y: np.ndarray) -> np.ndarray:
        """dy/dt of the closed loop at (t, y) (the `solve_ivp` right-hand side)."""
        veh = self.vehicle
        plant, ctrl = y[:12], y[12 : 12 + self.n_controller]
        position = None if self.position_loop is None else self._position_reference(t)
        r, rd, rdd, douter = self._reference(t, plant, ctrl, position)
        q = plant[list(_CHANNEL_INDEX)]
        qd = plant[list(_CHANNEL_RATE_INDEX)]
        e = r - q
        v, dinner = self._virtual_input(e, rd - qd, rdd, ctrl[:4])
        u_cmd = self._feedback_linearize(plant, v)
        # mixer: model's (b, d) inverted, clipped to the vehicle's rotor speeds
        b, d = self.model["b"], self.model["d"]
        tt, rr = u_cmd[3] / (4.0 * b), u_cmd[0] / (2.0 * b)
        pp, yy = u_cmd[1] / (2.0 * b), u_cmd[2] / (4.0 * d)
        w_cmd = np.array([tt - pp - yy, tt - rr + yy, tt + pp - yy, tt + rr + yy])
        w = np.clip(w_cmd, veh["omega_min"] ** 2, veh["omega_max"] ** 2)
        omega = np.sqrt(np.maximum(w, 0.0))
        vb, vd = veh["b"], veh["d"]
        u = np.array(
            [
                vb * (w[3] - w[1]),
                vb * (w[2] - w[0]),
                vd * (w[1] + w[3] - w[0] - w[2]),
                vb * (w[0] + w[1] + w[2] + w[3]),
            ]
        )
        start, duration, pulse_torque, pulse_force = self.pulses
        on = ((t >= start) & (t < start + duration)).astype(np.float64)
        wind_force, wind_torque = self._aero(self.wind(t), plant, omega)
        force = on @ pulse_force + wind_force
        torque = on @ pulse_torque + wind_torque
        mass = veh["m"] * (1.0 + (self.payload_fraction if t >= self.payload_time else 0.0))
        # plant, eq. (15) corrected
        phi, theta, psi = plant[3], plant[4], plant[5]
        phid, thetad, psid = plant[9], plant[10], plant[11]
        ix, iy, iz, arm = veh["Ix"], veh["Iy"], veh["Iz"], veh["arm_length"]
        cphi, sphi = math.cos(phi), math.sin(phi)
        cth, sth = math.cos(theta), math.sin(theta)
        cpsi, spsi = math.cos(psi), math.sin(psi)
        thrust = np.array(
            [cphi * sth * cpsi + sphi * spsi, cphi * sth * spsi - sphi * cpsi, cphi * cth]
        )
        acc = thrust * u[3] / mass + force / mass
        acc[2] -= veh["g"]
        gyro = veh["gyro_sign"] * veh["Jr"] * (-omega[0] + omega[1] - omega[2] + omega[3])
        phidd = thetad * psid * (iy - iz) / ix - gyro / ix * thetad + (arm * u[0] + torque[0]) / ix
        thetadd = phid * psid * (iz - ix) / iy + gyro / iy * phid + (arm * u[1] + torque[1]) / iy
        psidd = phid * thetad * (ix - iy) / iz + (u[2] + torque[2]) / iz
        ise = [e[0] ** 2 + e[1] ** 2 + e[2] ** 2, e[3] ** 2]
        parts = [plant[6:12], acc, (phidd, thetadd, psidd), dinner]
        if douter is not None:
            e_pos = position[0] - plant[0:2]
            ise.append(e_pos @ e_pos)
            parts.append(douter)
        parts.append(ise)
        return np.concatenate(parts)

    def jump_times(self) -> np.ndarray:
        """Times in (t0, t1) where the vector field jumps or kinks (as `Scenario.jump_times`)."""
        start, duration = self.pulses[0], self.pulses[1]
        parts = [start, start + duration, self.reference.kink_times(), [self.payload_time]]
        parts.append(self.wind.jump_times())
        if self.position is not None:
            parts.append(self.position.kink_times())
        times = np.unique(np.concatenate([np.ravel(p) for p in parts]))
        return times[(times > self.t0) & (times < self.t1)]

    def solve(self, rtol: float = 1e-6, atol: float = 1e-8, method: str = "RK45") -> NumpyResult:
        """`solve_ivp` from t0 to t1 (piecewise between `jump_times`), stopped at the
        divergence limits; the ISE at the end."""
        from scipy.integrate import solve_ivp

        att_limit, alt_limit = self.limits

        def attitude(t, y):
            return att_limit - max(abs(y[3]), abs(y[4]))

        def altitude(t, y):
            return alt_limit - abs(self.reference(t)[0][3] - y[2])

        for event in (attitude, altitude):
            event.terminal = True
        y = self.initial_state()
        edges = [self.t0, *self.jump_times(), self.t1]
        t, steps, evals = self.t0, 0, 0
        for a, b in zip(edges[:-1], edges[1:], strict=True):
            sol = solve_ivp(
                self.derivative,
                (a, b),
                y,
                method=method,
                rtol=rtol,
                atol=atol,
                events=(attitude, altitude),
            )
            steps += len(sol.t) - 1
            evals += sol.nfev
            y, t = sol.y[:, -1], sol.t[-1]
            if sol.status != 0:
                status = "diverged" if sol.status == 1 else "solver_failed"
                return NumpyResult(self._ise(y), status, t, steps, evals)
        return NumpyResult(self._ise(y), "ok", t, steps, evals)

    def _ise(self, y) -> np.ndarray:
        return np.array(y[self.ise_index :])


@dataclass(frozen=True)
class NumpyResult:
    """ISE (attitude [rad^2 s], altitude [m^2 s], position [m^2 s] with a position loop),
    status ("ok", "diverged", "solver_failed"), end time [s], accepted steps and right-hand
    side evaluations of one `NumpyCase.solve`."""

    ise: np.ndarray
    status: str
    t_final: float
    steps: int
    evaluations: int


_PARAMS = (
    "m",
    "Ix",
    "Iy",
    "Iz",
    "b",
    "d",
    "Jr",
    "arm_length",
    "g",
    "omega_min",
    "omega_max",
    "gyro_sign",
    "drag_coefficient",
    "cp_offset",
    "rotor_drag_horizontal",
    "rotor_drag_vertical",
    "parasitic_drag_horizontal",
    "parasitic_drag_vertical",
    "hub_height",
)
_POSITION_LOOP = ("kp", "kd", "ki", "tilt_max", "filter_frequency", "windup_time")


def _params(p) -> dict:
    return {n: float(np.asarray(getattr(p, n))) for n in _PARAMS}


def case_from_pytrees(
    controller,
    scenario,
    vehicle,
    model=None,
    aerodynamics: str = "linear",
    position_loop=None,
    limits: tuple[float, float] = (1.2, 10.0),
) -> NumpyCase:
    """A `NumpyCase` from one (unbatched) case of the package: a controller (`afbl_jax.AFBL`,
    `AFBLPaper`, `FBLPID`), `afbl_jax.Scenario`, true vehicle and nominal model
    (`afbl_jax.QuadrotorParams`; model None: the vehicle), the aerodynamic model's name,
    the `afbl_jax.PositionHold` (or None) and the divergence limits (attitude [rad], altitude
    error [m])."""
    model = vehicle if model is None else model
    if controller.name not in ("afbl", "afbl_paper", "fbl"):
        raise ValueError(f"unknown controller {controller.name!r}.")
    if aerodynamics not in ("linear", "rotor_drag"):
        raise ValueError(f"unknown aerodynamic model {aerodynamics!r}.")
    sc = scenario
    loop = None
    if position_loop is not None:
        loop = {n: _a(getattr(position_loop, n)) for n in _POSITION_LOOP}
        for n in ("tilt_max", "filter_frequency", "windup_time"):
            loop[n] = float(loop[n])
    d = sc.disturbance
    trim = None if sc.trim is None else (_a(sc.trim.attitude), _a(sc.trim.command))
    return NumpyCase(
        controller=controller.name,
        gains={n: _a(getattr(controller, n)) for n in controller.gain_names},
        vehicle=_params(vehicle),
        model=_params(model),
        aerodynamics=aerodynamics,
        position_loop=loop,
        reference=Steps.of(sc.reference),
        position=None if sc.position is None else Steps.of(sc.position),
        pulses=(_a(d.start), _a(d.duration), _a(d.torque), _a(d.force)),
        wind=NumpyWind.of(sc.wind),
        payload_fraction=float(np.asarray(sc.payload_fraction)),
        payload_time=float(np.asarray(sc.payload_time)),
        initial_plant=_a(sc.initial_state),
        t0=float(np.asarray(sc.t0)),
        t1=float(np.asarray(sc.t1)),
        trim=trim,
        limits=(float(limits[0]), float(limits[1])),
    )


def cases_from_batch(batch, controller, indices=None) -> list[NumpyCase]:
    """`NumpyCase` of rows ``indices`` (default all) of a Monte-Carlo `CaseBatch` (the paper's
    loop only: ``batch.unmodeled`` must be None)."""
    if batch.unmodeled is not None:
        raise ValueError("the NumPy loop has no unmodeled dynamics (full plant, lag, sampling).")
    indices = range(batch.n_cases) if indices is None else indices
    out = []
    for i in indices:
        scenario, vehicle, model = batch.case(int(i))
        out.append(
            case_from_pytrees(
                controller,
                scenario,
                vehicle,
                model,
                batch.aerodynamics.name,
                batch.position_loop,
            )
        )
    return out
