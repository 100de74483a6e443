"""Position hold in wind: trim, the trimmed start, the flight envelope, and the outer loop on
every solve path.

Physics checks: the trim against the closed form of linear drag; the closed loop, started at
rest in a steady wind, settles at the trim (position error to zero); the trimmed start is an
equilibrium of every closed loop (plant, actuators, aerodynamics, sampling, controller); the
envelope boundary against a brute-force search over wind speed with the closed loop itself.
"""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import afbl_jax as A
from afbl_jax.model import EnvelopeLimits, RotorDrag, envelope_margin, solve_trim
from afbl_jax.sim import CaseInputs, ClosedLoop, DivergenceLimits, sample_instant

TIGHT = {"solver": "dopri8", "rtol": 1e-10, "atol": 1e-12}
ROTOR = {
    "rotor_drag_horizontal": 3.0e-4,
    "rotor_drag_vertical": 6.0e-4,
    "parasitic_drag_horizontal": 8e-3,
    "parasitic_drag_vertical": 1.5e-2,
    "hub_height": 0.04,
    "cp_offset": 0.02,
}


def _wind(mean, gust=(0.0, 0.0, 0.0), turbulence=0.0, n=4):
    rng = np.random.default_rng(0)
    return A.Wind(
        np.array([2.0]),
        np.full((1, 3), 1.0),
        np.array([gust]),
        turbulence * rng.uniform(0.5, 1.0, (3, n)),
        np.geomspace(0.3, 6.0, n),
        rng.uniform(0, 2 * np.pi, (3, n)),
        mean=np.asarray(mean, float),
    )


def _scenario(mean, t1=10.0, **kw):
    return A.Scenario(
        A.make_reference(max_steps=1), A.no_disturbance(), t1=t1, wind=_wind(mean), **kw
    )


def test_trim_matches_linear_drag_closed_form():
    """Linear drag, centre of pressure at the CoM: tilt atan(c_d |w| / (m g)) into the wind,
    thrust sqrt((m g)^2 + (c_d |w|)^2), no torque; with a payload the true mass counts."""
    vehicle = A.QuadrotorParams(drag_coefficient=0.25)
    for wind, payload in (((6.0, 2.0, 0.0), 0.0), ((-3.0, 5.0, 0.0), 0.4), ((0.0, 0.0, 0.0), 0.2)):
        sc, sol = A.trim_scenario(
            _scenario(wind, payload_fraction=payload), vehicle, aerodynamics="linear"
        )
        mass, drag = 0.65 * (1 + payload), 0.25 * np.hypot(*wind[:2])
        assert bool(sol.converged) and float(sol.residual) < 1e-12
        np.testing.assert_allclose(float(sol.tilt), np.arctan2(drag, mass * 9.81), atol=1e-12)
        np.testing.assert_allclose(sol.trim.command[:3], 0.0, atol=1e-12)
        np.testing.assert_allclose(sol.trim.command[3], np.hypot(mass * 9.81, drag), rtol=1e-12)
        # the thrust leans into the wind
        direction = np.asarray(A.thrust_direction(*sc.initial_state[3:6]))
        np.testing.assert_allclose(direction[:2] * sol.trim.command[3], -0.25 * np.array(wind[:2]))
        np.testing.assert_allclose(sc.initial_state[6:12], 0.0)


def test_trim_converges_in_float32():
    """In float32 a trim inside the envelope still counts as converged (its residual bound
    follows the dtype) and matches the float64 trim to float32 accuracy."""
    vehicle = A.QuadrotorParams(**ROTOR).with_thrust_to_weight(2.5)

    @jax.jit  # one program per dtype, not one per operation
    def trim(v):
        wind = jnp.array([v, 0.5 * v, 0.0])
        return solve_trim(vehicle, vehicle, RotorDrag(), wind, jnp.zeros(3), 1.2 * vehicle.m)

    for v in (0.0, 4.0, 9.0):
        reference = trim(v)
        with jax.enable_x64(False):
            single = trim(v)
            assert single.trim.attitude.dtype == jnp.float32
        assert bool(reference.converged) and bool(single.converged)
        assert float(single.residual) < A.model.trim_residual_bound(np.float32)
        np.testing.assert_allclose(single.trim.attitude, reference.trim.attitude, atol=1e-5)
        np.testing.assert_allclose(
            single.trim.command, reference.trim.command, rtol=1e-5, atol=1e-6
        )


@pytest.mark.parametrize("aero", ["linear", "rotor_drag"])
@pytest.mark.parametrize("controller", ["fbl", "afbl"])
def test_position_hold_from_rest_settles_at_the_trim(aero, controller):
    """Started level and at rest in a steady 7 m/s wind, the position loop brings the vehicle
    back to its position, tilted as the trim says (1e-6 rad after 600 s): the trim is the
    loop's own equilibrium, found here without it. FBL+PID settles to 1e-6 m; AFBL's adaptive
    estimates converge on time scales of minutes with the paper's gains (its slowest modes,
    about 150 s horizontally and 1600 s in altitude), so its position error is still shrinking
    at 600 s."""
    vehicle = A.QuadrotorParams(drag_coefficient=0.25, **ROTOR).with_thrust_to_weight(2.5)
    sc = _scenario((5.0, -5.0, 0.0), t1=600.0)
    _, sol = A.trim_scenario(sc, vehicle, aerodynamics=aero)
    r = A.simulate(
        A.make_controller(controller),
        sc,
        vehicle,
        aerodynamics=aero,
        position_loop=A.PositionHold(),
        n_save=7,
        max_steps=100_000,
        **TIGHT,
    )
    assert int(r.status) == 0
    final = np.asarray(r.final.plant)
    np.testing.assert_allclose(final[3:5], sol.trim.attitude, atol=1e-6)
    np.testing.assert_allclose(final[9:12], 0.0, atol=1e-6)
    assert float(sol.tilt) > 0.15  # a real tilt, not a hover
    assert float(r.ise_position) > 1e-3  # the wind did push it away first
    if controller == "fbl":
        np.testing.assert_allclose(final[0:3], 0.0, atol=1e-6)  # back at the start position
        np.testing.assert_allclose(final[6:9], 0.0, atol=1e-6)
    else:
        distance = np.linalg.norm(np.asarray(r.plant)[2:, 0:3], axis=1)  # from 200 s on
        assert np.all(np.diff(distance) < 0) and distance[-1] < 5e-3


LOOPS = list(
    itertools.product(
        ["fbl", "afbl"],
        ["linear", "rotor_drag"],
        [None, "full+lag", "full+lag+digital"],
        [True, False],
    )
)


@pytest.mark.parametrize("controller, aero, unmodeled, hold", LOOPS)
def test_trimmed_start_is_an_equilibrium(controller, aero, unmodeled, hold):
    """With gusts and turbulence off, the trimmed start of every closed loop (controllers,
    aerodynamics, paper or rigid-body plant, motor lag, digital control; position hold or
    drifting with the air) has plant, controller and rotor derivatives below 1e-9 (drifting:
    all but the position, which moves with the air)."""
    vehicle = A.QuadrotorParams(drag_coefficient=0.25, b=3.3e-5, **ROTOR).with_thrust_to_weight(2.5)
    model = A.QuadrotorParams()
    settings = {
        None: None,
        "full+lag": A.UnmodeledDynamics(plant="full", motor_tau=0.03),
        "full+lag+digital": A.UnmodeledDynamics(
            plant="full", motor_tau=0.03, max_samples=100, control_rate=200.0
        ),
    }[unmodeled]
    sc = _scenario((4.0, 3.0, 0.0), payload_fraction=0.3)
    sc, sol = A.trim_scenario(sc, vehicle, model, aerodynamics=aero, position_hold=hold)
    assert bool(sol.converged)
    loop = ClosedLoop.make(
        A.make_controller(controller),
        settings,
        aerodynamics=aero,
        position_loop=A.PositionHold() if hold else None,
    )
    inputs = CaseInputs(sc, vehicle, model, DivergenceLimits())
    y0 = loop.initial_state(inputs, jnp.float64)
    held = None
    if loop.digital:
        meas0 = loop.plant.to_paper_layout(y0.plant)
        buffer = jnp.broadcast_to(meas0, (loop.sampling.max_delay + 1, 12))
        y0, _, held, dctrl = sample_instant(loop, jnp.int32(0), sc.t0, y0, buffer, inputs)
        assert float(jnp.max(jnp.abs(dctrl))) < 1e-9
    d = loop.vector_field(sc.t0, y0, (inputs, held))
    # drifting, the position moves with the air (the equilibrium is the relative motion's)
    plant = d.plant if hold else d.plant[3:]
    for leaf in (plant, d.controller, d.rotors):
        if leaf is not None:
            assert float(jnp.max(jnp.abs(leaf))) < 1e-9
    if not hold:  # drifting: moving with the air, level
        np.testing.assert_allclose(d.plant[0:3], sc.wind.mean, rtol=1e-12)
        np.testing.assert_allclose(sc.initial_state[6:9], sc.wind.mean)
        np.testing.assert_allclose(sol.trim.attitude, 0.0, atol=1e-12)


def _steady(speed, payload, t1=40.0):
    """A calm scenario with a steady wind of ``speed`` [m/s] along x (traceable)."""
    z = 0.0 * speed
    return A.Scenario(
        A.make_reference(max_steps=1),
        A.no_disturbance(),
        payload_fraction=payload,
        t1=t1,
        wind=A.Wind(
            jnp.zeros(1),
            jnp.ones((1, 3)),
            jnp.zeros((1, 3)),
            jnp.zeros((3, 1)),
            jnp.zeros(1),
            jnp.zeros((3, 1)),
            mean=jnp.stack([speed, z, z]),
        ),
    )


@pytest.mark.parametrize(
    "coefficients, payload",
    [
        (ROTOR, 0.0),  # the tilt limit binds
        ({**ROTOR, "rotor_drag_horizontal": 4.3e-4}, 0.5),  # the rotor reserve binds
    ],
)
def test_envelope_boundary_agrees_with_brute_force(coefficients, payload):
    """The envelope boundary in wind speed (bisection on `envelope_margin` of the trim)
    against a brute-force search with the closed loop itself (FBL+PID, position hold, started
    at rest, 150 s, at a grid of speeds): the boundary lies in the grid cell where the settled
    tilt or rotor speeds first leave the limits, and where the loop holds it settles at the
    trim."""
    vehicle = A.QuadrotorParams(**coefficients).with_thrust_to_weight(2.5)
    limits = EnvelopeLimits()
    mass = vehicle.m * (1 + payload)

    @jax.jit
    def trim(v):
        return solve_trim(
            vehicle, vehicle, RotorDrag(), jnp.array([v, 0.0, 0.0]), jnp.zeros(3), mass
        )

    def margin(v):
        return float(envelope_margin(trim(v), vehicle, limits)[0])

    lo, hi = 0.0, 20.0
    assert margin(lo) > 0 > margin(hi)
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if margin(mid) >= 0 else (lo, mid)
    boundary = lo
    speeds = np.arange(np.floor(boundary) - 1.5, np.floor(boundary) + 2.01, 0.5)
    loop = ClosedLoop.make(A.FBLPID(), aerodynamics="rotor_drag", position_loop=A.PositionHold())

    @jax.jit
    @jax.vmap
    def fly(v):
        sc = _steady(v, payload, t1=150.0)
        r = A.simulate(loop, sc, vehicle, n_save=0, rtol=1e-8, atol=1e-10, max_steps=100_000)
        inputs = CaseInputs(sc, vehicle, vehicle, DivergenceLimits())
        rotors = loop.signals_and_derivative(sc.t1, r.final, inputs)[0].rotor_speeds
        phi, theta = r.final.plant[3], r.final.plant[4]
        return jnp.arccos(jnp.cos(phi) * jnp.cos(theta)), jnp.max(rotors**2), r.status

    tilt, w_max, status = (np.asarray(x) for x in fly(jnp.asarray(speeds)))
    w_top = (1 - float(limits.rotor_reserve)) * float(vehicle.omega_max) ** 2
    inside = (status == 0) & (tilt <= float(limits.tilt)) & (w_max <= w_top)
    assert inside[0] and not inside[-1]
    first_out = int(np.argmin(inside))
    assert np.all(inside[:first_out]) and not np.any(inside[first_out:])
    assert speeds[first_out - 1] <= boundary < speeds[first_out]
    for k in np.nonzero(inside)[0]:
        np.testing.assert_allclose(tilt[k], float(trim(speeds[k]).tilt), atol=1e-5)


def test_position_loop_commands_the_trim_attitude_and_its_limit():
    """The outer loop's attitude command points the thrust along (a, g) (tilt atan(|a| / g) at
    any yaw), is inverted by `acceleration_for_attitude`, and the tilt limit caps it."""
    from afbl_jax.model import acceleration_for_attitude, attitude_for_acceleration

    rng = np.random.default_rng(1)
    for _ in range(10):
        a, psi = rng.uniform(-5, 5, 2), rng.uniform(-np.pi, np.pi)
        att = attitude_for_acceleration(jnp.asarray(a), psi, 9.81)
        d = np.asarray(A.thrust_direction(att[0], att[1], psi))
        np.testing.assert_allclose(d[:2] / d[2] * 9.81, a, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(acceleration_for_attitude(att, psi, 9.81), a, rtol=1e-12)
    loop = A.PositionHold(tilt_max=0.3)
    far = jnp.zeros(12).at[0].set(-100.0)  # 100 m behind: a saturated command
    ref = A.model.PositionSample(jnp.zeros(2), jnp.zeros(2), jnp.zeros(2))
    state = jnp.zeros(6)
    for _ in range(2000):  # the command filter settles on the limited command
        att, d = loop(far, state, ref, A.QuadrotorParams())
        state = state + 0.005 * d
    np.testing.assert_allclose(np.arccos(np.cos(att.r[0]) * np.cos(att.r[1])), 0.3, atol=1e-6)
    with pytest.raises(ValueError, match="tilt_max must lie in"):
        A.PositionHold(tilt_max=2.0)
    with pytest.raises(ValueError, match="kp must have a last dimension of 2"):
        A.PositionHold(kp=np.ones(3))
    with pytest.raises(TypeError, match="position_loop must be a PositionHold"):
        A.simulate(A.AFBL(), _scenario((0, 0, 0)), position_loop="hold")


# ------------------------------------------------------------------ every solve path
def _cases(n=4):
    vehicle = A.QuadrotorParams(**ROTOR).with_thrust_to_weight(2.5)
    model = A.QuadrotorParams()
    out = []
    for i in range(n):
        rng = np.random.default_rng(i)
        wind = _wind(
            (rng.uniform(-5, 5), rng.uniform(-5, 5), 0.0),
            gust=tuple(rng.normal(0, 1.0, 3)),
            turbulence=0.3,
        )
        pos = A.make_position_reference(
            steps={"x": [(2.0, 0.0, 1.0)], "y": [(3.0, 0.0, -1.0)]}, step_duration=2.0
        )
        sc = A.Scenario(
            A.make_reference(steps={"z": [(1.0, 0.0, 0.5)], "psi": [(4.0, 0.0, 0.2)]}),
            A.paper_disturbance("uncertain"),
            payload_fraction=0.15 * i,
            t1=6.0,
            wind=wind,
            position=pos,
        )
        out.append(A.trim_scenario(sc, vehicle, model, aerodynamics="rotor_drag")[0])
    return A.stack_scenarios(out), out, vehicle, model


@pytest.fixture(scope="module")
def cases():
    return _cases()


def _metrics(m):
    return np.stack(
        [
            np.asarray(getattr(m, k), float)
            for k in ("ise_attitude", "ise_altitude", "ise_position", "peak_position_error")
        ],
        1,
    )


@pytest.mark.parametrize("digital", [False, True])
def test_every_solve_path_agrees_with_simulate(cases, digital):
    """Position loop on (rotor drag, gust, turbulence, payload, position steps, trimmed
    start): vmap and both ensemble integrators agree with single `simulate` case by case in
    float64 (1e-6 relative ISE, tight tolerances; digital control: 1e-6 at the default), the
    float32 ensemble within the 1e-3 bound."""
    batch, scenarios, vehicle, model = cases
    ctrl, pl = A.AFBL(), A.PositionHold()
    unmodeled = (
        A.UnmodeledDynamics(plant="full", motor_tau=0.03, max_samples=1200, control_rate=200.0)
        if digital
        else None
    )
    tol = {} if digital else TIGHT
    common = dict(aerodynamics="rotor_drag", position_loop=pl, unmodeled=unmodeled, n_save=61)
    singles = [
        A.metrics_from_result(A.simulate(ctrl, s, vehicle, model, **common, **tol), vehicle, model)
        for s in scenarios
    ]
    ref = _metrics(jax.tree.map(lambda *x: jnp.stack(x), *singles))
    assert np.all(ref[:, 2] > 1e-4)  # the position steps and wind move it
    paths = [
        dict(strategy="ensemble", integrator="lean", group_size=2),
        dict(strategy="ensemble", integrator="diffeqsolve", group_size=2),
    ]
    if not digital:
        paths.insert(0, dict(strategy="vmap"))
    for kw in paths:
        m = A.simulate_batch(ctrl, batch, vehicle, model, **common, **tol, **kw)
        assert np.all(np.asarray(m.status) == 0), kw
        np.testing.assert_allclose(_metrics(m), ref, rtol=1e-6, err_msg=str(kw))
    f32 = A.simulate_batch(
        ctrl,
        batch,
        vehicle,
        model,
        **common,
        strategy="ensemble",
        group_size=2,
        dtype="float32",
        rtol=3e-6,
        atol=3e-7,
    )
    np.testing.assert_allclose(_metrics(f32), ref, rtol=1e-3)


def test_position_gains_gradient_matches_finite_differences(cases):
    """d ISE_position / d(kp, kd) through `simulate` (diffrax's checkpointed adjoint) against
    central differences (float64, 1e-3 relative)."""
    _, scenarios, vehicle, model = cases
    sc = scenarios[1]

    def ise(gains):
        pl = A.PositionHold(kp=gains[0], kd=gains[1])
        r = A.simulate(
            A.AFBL(),
            sc,
            vehicle,
            model,
            aerodynamics="rotor_drag",
            position_loop=pl,
            n_save=0,
            rtol=1e-10,
            atol=1e-12,
        )
        return r.ise_position

    g0 = jnp.array([1.92, 2.4])
    grad = np.asarray(jax.jit(jax.grad(ise))(g0))
    f = jax.jit(ise)
    h = 1e-4
    fd = [(float(f(g0.at[i].add(h))) - float(f(g0.at[i].add(-h)))) / (2 * h) for i in range(2)]
    np.testing.assert_allclose(grad, fd, rtol=1e-3)
    assert np.all(np.abs(grad) > 1e-4)
