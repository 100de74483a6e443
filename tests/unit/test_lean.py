"""The lean ensemble integrator (`simulate_batch(integrator="lean")`, the default) agrees case
by case with the `diffrax.diffeqsolve` ensemble (same solver, tolerances and groups): on the
benchmark's canonical cases, on Monte-Carlo cases (rotor drag, Dryden turbulence, gusts) with
divergent members, and with unmodeled dynamics (full plant, motor lag, digital control with
delay and noise); chunks reuse one compiled program.

Agreement bounds: ISE within 10 rtol (relative), statuses equal, the divergence time within one
step (the lean loop ends a diverged case at the end of the step where it crossed the limits,
diffeqsolve where a stage first crossed them inside the step), peaks from the same save times
(diffrax's dense interpolation on both paths) within 10 rtol.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import afbl_jax as A
from afbl_jax.studies import montecarlo as mc
from afbl_jax.studies.bench import bench_cases

from ..helpers import count_compiles

RTOL, ATOL = 1e-6, 1e-8
T1 = 4.0
N, GROUP = 8, 4
PEAKS = ("peak_attitude_error", "peak_altitude_error", "peak_saturation")
SHORT = {  # Monte-Carlo defaults (rotor drag, mean wind, Dryden, gusts, pulses) over 4 s
    "time": {"t1": T1},
    "pulses": {"start": [0.5, 3.0]},
    "gust": {"start": [0.5, 3.0]},
    "payload": {"attach_time": [0.5, 3.0]},
}


def _both(controller, scenarios, vehicles=None, models=None, **kw):
    return tuple(
        A.simulate_batch(controller, scenarios, vehicles, models, integrator=i, **kw)
        for i in ("lean", "diffeqsolve")
    )


def _heavy(scenarios, cases):
    """Payload fraction 3 (4x the mass: more than the rotors can lift) attached at 0.5 s in
    ``cases``."""
    pf, pt = np.array(scenarios.payload_fraction), np.array(scenarios.payload_time)
    pf[list(cases)], pt[list(cases)] = 3.0, 0.5
    return eqx.tree_at(
        lambda s: (s.payload_fraction, s.payload_time),
        scenarios,
        (jnp.asarray(pf), jnp.asarray(pt)),
    )


def _assert_agree(lean, ref, t_step, n_save=True):
    """Case-by-case agreement (module docstring); ``t_step``: per-case bound on one step [s]."""
    status = np.asarray(lean.status)
    np.testing.assert_array_equal(status, np.asarray(ref.status))
    ok = status == A.sim.STATUS_OK
    assert ok.sum() >= 1
    for k in ("ise_attitude", "ise_altitude", "effort"):
        np.testing.assert_allclose(
            np.asarray(getattr(lean, k))[ok], np.asarray(getattr(ref, k))[ok], rtol=10 * RTOL
        )
    if n_save:
        for k in PEAKS:
            np.testing.assert_allclose(
                np.asarray(getattr(lean, k))[ok], np.asarray(getattr(ref, k))[ok], rtol=10 * RTOL
            )
    dt = np.asarray(lean.t_final) - np.asarray(ref.t_final)
    np.testing.assert_allclose(dt[ok], 0.0, atol=1e-12)
    bad = ~ok
    assert np.all(dt[bad] >= -1e-12) and np.all(dt[bad] <= np.asarray(t_step)[bad]), dt


def test_lean_agrees_with_diffeqsolve_on_canonical_cases():
    """Benchmark cases (the paper's uncertain step, payload and pulse amplitudes varied), groups
    of 2: no divergence, so both take the same steps."""
    scenarios, _ = bench_cases(4, seed=3)
    lean, ref = _both(
        A.AFBL(), scenarios, rtol=RTOL, atol=ATOL, n_save=81, group_size=2, dtype="float64"
    )
    assert np.all(np.asarray(lean.status) == A.sim.STATUS_OK)
    _assert_agree(lean, ref, np.zeros(4))
    np.testing.assert_allclose(lean.num_steps, ref.num_steps, rtol=0.01)
    # the cases differ, so equality is not trivial
    assert np.ptp(np.asarray(lean.ise_altitude)) > 1e-3 * np.max(np.asarray(lean.ise_altitude))


def _mc_run(mc_cases, controller="afbl", **kw):
    """`simulate_batch` on the Monte-Carlo cases (their vehicles, models and aerodynamics),
    41 saved samples, the test tolerances; ``kw``: the other settings."""
    batch, scenarios = mc_cases
    return A.simulate_batch(
        A.make_controller(controller),
        scenarios,
        batch.vehicle,
        batch.model,
        aerodynamics=batch.aerodynamics,
        position_loop=batch.position_loop,
        rtol=RTOL,
        atol=ATOL,
        n_save=41,
        **kw,
    )


@pytest.fixture(scope="module")
def mc_cases():
    batch = mc.sample_cases(mc.Distribution.from_dict(SHORT), N, 3)
    assert batch.aerodynamics.name == "rotor_drag"
    return batch, _heavy(batch.scenario, (1, 6))


@pytest.fixture(scope="module")
def mc_lean(mc_cases):
    return _mc_run(mc_cases, group_size=GROUP)


def test_lean_agrees_with_diffeqsolve_on_montecarlo_cases_with_divergence(mc_cases, mc_lean):
    ref = _mc_run(mc_cases, group_size=GROUP, integrator="diffeqsolve")
    lean = mc_lean
    status = np.asarray(lean.status)
    assert list(np.nonzero(status == A.sim.STATUS_DIVERGED)[0]) == [1, 6]
    # one step: bounded by twice the group's mean step (the steps are short and even here)
    t_step = 2 * T1 / np.asarray(lean.num_steps)
    _assert_agree(lean, ref, t_step)


def test_lean_chunks_reuse_one_program_and_equal_unchunked(mc_cases, mc_lean):
    batch, scenarios = mc_cases

    def run(sc):
        return _mc_run((batch, sc), group_size=GROUP, chunk_size=GROUP)

    chunked = run(scenarios)
    np.testing.assert_array_equal(chunked.status, mc_lean.status)
    # the chunked and unchunked programs fuse (and so round) differently; the diverged cases
    # (1 and 6), whose states run away before they are frozen, amplify that round-off
    ok = np.asarray(mc_lean.status) == A.sim.STATUS_OK
    for k in ("ise_attitude", "ise_altitude", "t_final", *PEAKS):
        a, b = np.asarray(getattr(chunked, k)), np.asarray(getattr(mc_lean, k))
        np.testing.assert_allclose(a[ok], b[ok], rtol=1e-9, atol=1e-14, err_msg=k)
        np.testing.assert_allclose(a[~ok], b[~ok], rtol=1e-5, atol=1e-12, err_msg=k)
    other = _heavy(batch.scenario, (0,))  # new values, same shapes
    with count_compiles() as compiles:
        run(other)
    assert compiles.count == 0


def test_lean_digital_control_agrees_with_diffeqsolve():
    """Full plant, motor lag, digital control at 200 Hz with delay and measurement noise: the
    lean loop lands its steps on the sample instants; a diverged case ends on one."""
    dist = mc.Distribution.from_dict(
        {
            **{**SHORT, "time": {"t1": 3.0}},
            "pulses": {"start": [0.5, 2.0]},
            "gust": {"start": [0.5, 2.0]},
            "payload": {"fraction": [0.0, 0.2], "attach_time": [0.5, 2.0]},
            "unmodeled": {
                "enabled": True,
                "plant": "full",
                "motor_tau": [0.02, 0.04],
                "control_rate": [200.0, 200.0],
                "delay_samples": [0, 2],
                "noise_angle": [0.0, 1e-3],
                "noise_rate": [0.0, 1e-2],
            },
        }
    )
    batch = mc.sample_cases(dist, N, 5)
    scenarios = _heavy(batch.scenario, (1,))
    lean, ref = _both(
        A.make_controller("fbl"),
        scenarios,
        batch.vehicle,
        batch.model,
        unmodeled=batch.unmodeled,
        aerodynamics=batch.aerodynamics,
        position_loop=batch.position_loop,
        rtol=RTOL,
        atol=ATOL,
        n_save=31,
        group_size=GROUP,
        max_steps=4096,
    )
    assert list(np.nonzero(np.asarray(lean.status) != A.sim.STATUS_OK)[0]) == [1]
    _assert_agree(lean, ref, np.full(N, 1.0 / 200.0))
    # the diverged case ends on a sample instant (k / 200 s)
    k = float(lean.t_final[1]) * 200.0
    assert abs(k - round(k)) < 1e-9


@pytest.mark.slow
def test_diffeqsolve_ensemble_is_reverse_differentiable_lean_is_not():
    """``integrator="diffeqsolve"``: `jax.grad` through the ensemble equals central differences
    of the lean ensemble; the lean loop refuses reverse mode (a while loop)."""
    scenarios, _ = bench_cases(2, seed=2)
    scenarios = eqx.tree_at(lambda s: s.t1, scenarios, jnp.full(2, 3.0))

    def loss(k, integrator):
        ctrl = eqx.tree_at(lambda c: c.k, A.AFBL(), k)
        m = A.simulate_batch(ctrl, scenarios, rtol=1e-8, atol=1e-10, integrator=integrator)
        return jnp.sum(m.ise_attitude + m.ise_altitude)

    k0 = A.AFBL().k
    grad = np.asarray(jax.grad(loss)(k0, "diffeqsolve"))
    h = 1e-4
    fd = [
        (loss(k0.at[i].add(h), "lean") - loss(k0.at[i].add(-h), "lean")) / (2 * h) for i in range(4)
    ]
    np.testing.assert_allclose(grad, fd, rtol=1e-5)
    assert np.all(np.abs(grad) > 0)
    with pytest.raises(ValueError, match="Reverse-mode"):
        jax.grad(loss)(k0, "lean")


def _decay_loop(lanes, extra=None):
    """`lean_loop` on dy/dt = -k y (cases with the rates ``K``, groups of 2: different step
    counts per group); extra: accepted steps per group, the running max of |y| per case, and
    the state at t = 0.5 s from the dense interpolation, stored per group as one block (G, 2)
    (`Step.evaluate_groups`) and per case (n,) (`Step.evaluate`)."""
    import diffrax

    groups = A.sim.Groups(4, 2)
    rates = jnp.array([[1.0, 2.0], [40.0, 50.0], [3.0, 1.0], [90.0, 5.0]])

    def field(t, y, args, k):
        return -k * y

    controllers = eqx.filter_vmap(
        lambda _: diffrax.PIDController(rtol=1e-8, atol=1e-10, norm=mc_norm)
    )(jnp.arange(4))
    if extra is None:
        extra = (jnp.zeros(4, jnp.int32), jnp.zeros(8), jnp.zeros((4, 2)), jnp.zeros(8))

    def after_step(extra, step, args, keep, at_boundary, inputs):
        count, peak, mid_block, mid_case = extra
        lanes = A.sim.Groups(keep.shape[0], 2)
        keep_case = lanes.per_case(keep)
        peak = jnp.where(keep_case, jnp.maximum(peak, jnp.abs(step.y1)), peak)
        inside = keep & (step.t0 < 0.5) & (step.t1 >= 0.5)
        half = jnp.full(keep.shape, 0.5)
        at_half = step.evaluate_groups(half, lanes).reshape(-1, 2)
        mid_block = jnp.where(inside[:, None], at_half, mid_block)
        at_half_case = step.evaluate(lanes.per_case(half))
        mid_case = jnp.where(lanes.per_case(inside), at_half_case, mid_case)
        extra = (count + keep, peak, mid_block, mid_case)
        return extra, None, args, jnp.zeros_like(keep), jnp.zeros_like(keep)

    return A.sim.lean_loop(
        field,
        rates,
        diffrax.Tsit5(),
        controllers,
        0.0,
        1.0,
        jnp.linspace(1.0, 2.0, 8),
        groups=groups,
        max_steps=4096,
        extra=extra,
        after_step=after_step,
        lanes=lanes,
    )


def mc_norm(y):
    return A.sim.ensemble_rms_norm(y, case_axis=-1)


def test_lean_loop_work_queue_gives_every_group_its_own_steps():
    """Lanes 1 and 2 (a finished group's lane takes the next group) against all 4 groups at
    once: every group takes the same steps (exactly), with the same end state and hook results
    (to round-off: other vector widths); the exact solution checks the state. Before a group's
    first step is accepted its first stage is evaluated afresh: a group whose first step was
    rejected while another's was accepted took extra, wrongly estimated steps from the solver's
    placeholder zero stage (group 3 here: 153 steps, 15 rejected, against 133 and 1 alone)."""
    ref = _decay_loop(None)
    steps = np.asarray(ref.num_steps)
    assert len(set(steps.tolist())) >= 3  # the groups differ, so the queue reorders work
    y_exact = np.linspace(1.0, 2.0, 8) * np.exp(-np.array([1, 2, 40, 50, 3, 1, 90, 5.0]))
    np.testing.assert_allclose(ref.y, y_exact, rtol=1e-6, atol=1e-9)
    # the interpolated state at t = 0.5 s: the exact solution, per group as per case
    y_half = np.linspace(1.0, 2.0, 8) * np.exp(-0.5 * np.array([1, 2, 40, 50, 3, 1, 90, 5.0]))
    np.testing.assert_allclose(ref.extra[2].reshape(-1), y_half, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(ref.extra[2].reshape(-1), ref.extra[3], rtol=1e-14, atol=1e-300)
    for lanes in (1, 2):
        out = _decay_loop(lanes)
        np.testing.assert_array_equal(out.num_steps, ref.num_steps)
        np.testing.assert_array_equal(out.extra[0], steps - np.asarray(ref.num_rejected_steps))
        np.testing.assert_allclose(out.y, ref.y, rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(out.extra[1], ref.extra[1], rtol=1e-9)
        # the per-group blocks move with their groups through the queue
        np.testing.assert_allclose(out.extra[2], ref.extra[2], rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(out.extra[3], ref.extra[3], rtol=1e-9, atol=1e-15)
        np.testing.assert_array_equal(out.t, np.ones(4))
    with pytest.raises(ValueError, match="lanes must be an integer >= 1"):
        _decay_loop(0)
    with pytest.raises(ValueError, match=r"lanes \(3\) must divide the number of groups \(4\)"):
        _decay_loop(3)
    bad = (jnp.zeros(4, jnp.int32), jnp.zeros(8), jnp.zeros((4, 2)), jnp.zeros((8, 3)))
    with pytest.raises(ValueError, match=r"per group \(leading axis of length 4\) or per case"):
        _decay_loop(2, extra=bad)


@pytest.mark.default_codegen
def test_lean_work_queue_equals_chunks_one_after_the_other(mc_cases):
    """Monte-Carlo cases with divergent members, groups of 2, chunks of 4 (two lanes over four
    groups): the work queue against the chunks one after the other, case by case and bitwise."""

    def run(work_queue):
        one_device = jax.local_devices()[:1]
        kw = {"group_size": 2, "chunk_size": 4, "devices": one_device, "work_queue": work_queue}
        return _mc_run(mc_cases, "fbl", **kw)

    queued, chunked = run(True), run(False)
    assert np.sum(np.asarray(queued.status) == A.sim.STATUS_DIVERGED) == 2
    # bitwise: a group's arithmetic does not depend on the groups beside it
    for k in ("status", "num_steps", "ise_attitude", "ise_altitude", "effort", "t_final", *PEAKS):
        np.testing.assert_array_equal(getattr(queued, k), getattr(chunked, k), err_msg=k)
