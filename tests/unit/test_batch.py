"""Batched solving (`simulate_batch`): ensemble = vmap = per-case `simulate`, divergence
isolation, no recompiles across chunks, float32 accuracy, and the `afbl bench` CLI.

Shapes and tolerances are shared with the bench smoke test (N = 4, the bench reference settings)
so that compiled programs are reused within the test session.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import afbl_jax as A
from afbl_jax.studies.bench import REFERENCE, bench_cases

from ..helpers import count_compiles

N = 4
TIGHT = {"solver": REFERENCE["solver"], "rtol": REFERENCE["rtol"], "atol": REFERENCE["atol"]}


def _case(tree, i):
    return jax.tree.map(lambda x: x[i], tree)


def _ise(m):
    return np.stack([np.asarray(m.ise_attitude, float), np.asarray(m.ise_altitude, float)], 1)


@pytest.fixture(scope="module")
def cases():
    scenarios, draws = bench_cases(N, seed=1)
    return scenarios, draws


@pytest.fixture(scope="module")
def tight_ensemble(cases):
    return A.simulate_batch(A.AFBL(), cases[0], strategy="ensemble", **TIGHT)


@pytest.fixture(scope="module")
def diverging_batch(cases):
    """Case 2 gets a 10 N m torque pulse (1000x): the attitude loop cannot hold it."""
    scenarios = cases[0]
    torque = np.array(scenarios.disturbance.torque)
    torque[2] *= 1000.0
    return eqx.tree_at(lambda s: s.disturbance.torque, scenarios, jnp.asarray(torque))


def test_bench_cases_differ(cases):
    scenarios, draws = cases
    assert scenarios.payload_fraction.shape == (N,)
    np.testing.assert_allclose(scenarios.payload_fraction, draws[:, 0])
    assert np.all((draws[:, 0] >= 0) & (draws[:, 0] <= 0.5))
    assert len(np.unique(draws[:, 1])) == N  # pulse amplitudes vary


def test_ensemble_equals_vmap_equals_simulate(cases, tight_ensemble):
    scenarios, _ = cases
    ctrl = A.AFBL()
    vm = A.simulate_batch(ctrl, scenarios, strategy="vmap", **TIGHT)
    singles = [A.simulate(ctrl, _case(scenarios, i), n_save=0, **TIGHT) for i in range(N)]
    single_ise = np.array([[float(r.ise_attitude), float(r.ise_altitude)] for r in singles])
    ens = tight_ensemble
    assert np.all(np.asarray(ens.status) == A.sim.STATUS_OK)
    assert np.all(np.asarray(vm.status) == 0)
    np.testing.assert_allclose(_ise(ens), single_ise, rtol=1e-7)
    np.testing.assert_allclose(_ise(vm), single_ise, rtol=1e-9)
    np.testing.assert_allclose(ens.effort, [float(r.effort) for r in singles], rtol=1e-7)
    # same per-case step control (counts differ by a few steps: batched arithmetic rounds
    # differently)
    np.testing.assert_allclose(vm.num_steps, [int(r.num_steps) for r in singles], rtol=0.02)
    # the cases really differ (payload, pulses), so equality above is not trivial
    assert np.ptp(single_ise[:, 1]) > 1e-3 * single_ise[:, 1].max()
    # one shared step sequence, at least as fine as the finest single case
    assert len(set(np.asarray(ens.num_steps).tolist())) == 1
    np.testing.assert_allclose(ens.t_final, 20.0)


def test_ensemble_norm_is_max_over_cases():
    rng = np.random.default_rng(0)
    tree = (rng.normal(size=(5, 3)), rng.normal(size=(5, 2, 2)))
    per_case = np.sqrt((np.sum(tree[0] ** 2, 1) + np.sum(tree[1] ** 2, (1, 2))) / 7)
    np.testing.assert_allclose(
        A.ensemble_rms_norm(jax.tree.map(jnp.asarray, tree)), per_case.max(), rtol=1e-12
    )


def test_ensemble_meets_tolerance_and_isolates_divergence(cases, diverging_batch, tight_ensemble):
    ctrl, scenarios = A.AFBL(), cases[0]
    clean = A.simulate_batch(ctrl, scenarios, strategy="ensemble")
    with count_compiles() as compiles:
        bad = A.simulate_batch(ctrl, diverging_batch, strategy="ensemble")
    # same shapes, different data: no retrace / recompile for the second chunk
    assert compiles.count == 0
    status = np.asarray(bad.status)
    assert status[2] == A.sim.STATUS_DIVERGED
    assert np.all(np.delete(status, 2) == 0) and np.all(np.asarray(clean.status) == 0)
    # at rtol 1e-6 every case is within ~1e-6 of the tight reference ...
    ref = _ise(tight_ensemble)
    assert np.max(np.abs(_ise(clean) - ref) / ref) < 2e-5
    # ... and the diverged case did not stall or corrupt the others
    keep = [0, 1, 3]
    assert np.max(np.abs(_ise(bad)[keep] - ref[keep]) / ref[keep]) < 2e-5
    assert int(bad.num_steps[0]) < 4 * int(clean.num_steps[0])
    # the diverged case stopped where a single simulate stops it (10 N m pulse from t = 10 s)
    single = A.simulate(ctrl, _case(diverging_batch, 2), n_save=0)
    assert int(single.status) == A.sim.STATUS_DIVERGED
    assert 10.0 < float(bad.t_final[2]) < 11.0
    np.testing.assert_allclose(float(bad.t_final[2]), float(single.t_final), atol=0.05)
    np.testing.assert_allclose(float(bad.ise_attitude[2]), float(single.ise_attitude), rtol=0.05)


def test_float32_ensemble_within_bound(cases, tight_ensemble):
    m = A.simulate_batch(
        A.AFBL(), cases[0], strategy="ensemble", dtype="float32", rtol=1e-5, atol=1e-6
    )
    assert m.ise_attitude.dtype == jnp.float32
    assert np.all(np.asarray(m.status) == 0)
    err = np.max(np.abs(_ise(m) - _ise(tight_ensemble)) / _ise(tight_ensemble))
    assert err < 1e-3  # the bound the benchmark reports for ensemble_f32 (measured ~5e-5)


def test_simulate_batch_rejects_bad_input(cases):
    scenarios, ctrl = cases[0], A.AFBL()
    with pytest.raises(ValueError, match="unknown strategy"):
        A.simulate_batch(ctrl, scenarios, strategy="pmap")
    with pytest.raises(ValueError, match="default float dtype"):
        A.simulate_batch(ctrl, scenarios, strategy="vmap", dtype="float32")
    with pytest.raises(ValueError, match="must be batched"):
        A.simulate_batch(ctrl, _case(scenarios, 0))
    vehicles = jax.tree.map(lambda x: jnp.stack([x] * (N + 1)), A.QuadrotorParams())
    with pytest.raises(ValueError, match="leading axis 4"):
        A.simulate_batch(ctrl, scenarios, vehicles)
    t1 = eqx.tree_at(lambda s: s.t1, scenarios, jnp.array([20.0, 20.0, 20.0, 19.0]))
    with pytest.raises(ValueError, match="one t1"):
        A.simulate_batch(ctrl, t1, strategy="ensemble")
    with pytest.raises(ValueError, match="rtol"):
        A.simulate_batch(ctrl, scenarios, rtol=0.0)
    with pytest.raises(ValueError, match="dt0 must be a step > 0"):
        A.simulate_batch(ctrl, scenarios, dt0=0.0)


def test_first_step_is_adapted_from_in_a_few_steps(cases, tight_ensemble):
    """The ensemble starts with ``dt0``: a first step 1000x smaller than `FIRST_STEP` costs a
    handful of steps (the controller grows it by up to 10x per step) and changes the solution
    only within the tolerance."""
    small = A.simulate_batch(A.AFBL(), cases[0], strategy="ensemble", dt0=1e-6, **TIGHT)
    assert A.sim.FIRST_STEP == 1e-3
    assert np.all(np.asarray(small.status) == A.sim.STATUS_OK)
    extra = np.asarray(small.num_steps) - np.asarray(tight_ensemble.num_steps)
    assert np.all((extra >= 1) & (extra <= 8)), extra
    np.testing.assert_allclose(_ise(small), _ise(tight_ensemble), rtol=1e-6)


def test_chunked_ensemble_equals_unchunked(cases, tight_ensemble):
    # 4 cases in chunks of 3: the last chunk is padded and the padding dropped
    m = A.simulate_batch(A.AFBL(), cases[0], strategy="ensemble", chunk_size=3, **TIGHT)
    assert m.ise_attitude.shape == (N,) and np.all(np.asarray(m.status) == 0)
    np.testing.assert_allclose(_ise(m), _ise(tight_ensemble), rtol=1e-7)
    with pytest.raises(ValueError, match="chunk_size"):
        A.simulate_batch(A.AFBL(), cases[0], chunk_size=0)


def test_groups_are_independent_ensembles(cases):
    """group_size=2: each pair of cases is its own ensemble, exactly as if solved alone."""
    scenarios, ctrl = cases[0], A.AFBL()
    grouped = A.simulate_batch(ctrl, scenarios, strategy="ensemble", group_size=2)
    for lo in (0, 2):
        alone = A.simulate_batch(
            ctrl, jax.tree.map(lambda x, lo=lo: x[lo : lo + 2], scenarios), strategy="ensemble"
        )
        np.testing.assert_allclose(_ise(grouped)[lo : lo + 2], _ise(alone), rtol=1e-12)
        assert np.all(np.asarray(grouped.num_steps[lo : lo + 2]) == int(alone.num_steps[0]))
    with pytest.raises(ValueError, match="group_size"):
        A.simulate_batch(ctrl, scenarios, strategy="vmap", group_size=2)


def test_peaks_match_single_simulation_samples(cases):
    """n_save: the ensemble's saved peaks (SubSaveAt fn) are the maxima of the signals of a
    single `simulate` sampled at the same times (tight tolerances on both)."""
    scenarios, ctrl = cases[0], A.AFBL()
    m = A.simulate_batch(ctrl, scenarios, strategy="ensemble", n_save=101, group_size=2, **TIGHT)
    vm = A.simulate_batch(ctrl, scenarios, strategy="vmap", n_save=101, **TIGHT)
    v = A.QuadrotorParams()
    for i in range(N):
        r = A.simulate(ctrl, _case(scenarios, i), n_save=101, **TIGHT)
        w = np.asarray(jax.vmap(lambda u: A.rotor_speeds_sq_from_inputs(v, u))(r.u_command))
        expect = [
            np.max(np.abs(r.error[:, :3])),
            np.max(np.abs(r.error[:, 3])),
            np.max(np.sqrt(np.maximum(w, 0.0))) / float(v.omega_max),
        ]
        for got in (m, vm):
            peaks = [got.peak_attitude_error[i], got.peak_altitude_error[i], got.peak_saturation[i]]
            np.testing.assert_allclose(peaks, expect, rtol=1e-7)
    assert np.all(np.isnan(np.asarray(A.simulate_batch(ctrl, scenarios).peak_saturation)))


def test_realistic_vehicle_ensemble_agrees_with_simulate(cases):
    """Full plant, 30 ms motor lag, 250 Hz digital control with a one-sample delay on 20 s
    runs: the ensemble agrees with single `simulate` case by case (float64 to 1e-6 relative
    ISE, float32 within the 1e-3 bound; 5000 sample intervals, whose ends must tile the run
    exactly for float32 to hold)."""
    from afbl_jax.studies.bench import realistic_unmodeled

    scenarios, u, ctrl = cases[0], realistic_unmodeled(), A.AFBL()
    singles = [A.simulate(ctrl, _case(scenarios, i), n_save=0, unmodeled=u) for i in range(N)]
    ref = np.array([[float(r.ise_attitude), float(r.ise_altitude)] for r in singles])
    assert all(int(r.status) == 0 for r in singles)
    for dtype, rtol, atol, bound in (("float64", 1e-6, 1e-8, 1e-6), ("float32", 3e-6, 3e-7, 1e-3)):
        m = A.simulate_batch(
            ctrl,
            scenarios,
            unmodeled=u,
            strategy="ensemble",
            dtype=dtype,
            rtol=rtol,
            atol=atol,
            group_size=2,
        )
        assert np.all(np.asarray(m.status) == 0)
        np.testing.assert_allclose(_ise(m), ref, rtol=bound, err_msg=dtype)
    bad = A.stack_unmodeled(
        [
            u,
            u,
            A.UnmodeledDynamics.make(plant="full", control_rate=200.0, max_samples=u.max_samples),
            u,
        ]
    )
    with pytest.raises(ValueError, match="share their control sample instants"):
        A.simulate_batch(ctrl, scenarios, unmodeled=bad, strategy="ensemble", group_size=2)


def test_compiler_options_are_used_and_change_no_status(cases, monkeypatch):
    """The batched solves compile with `CPU_COMPILER_OPTIONS` where XLA knows them (the
    versions this project is tested with do). Copy insertion by region analysis alone gives
    every metric bitwise as XLA's default compilation; with XLA's own reductions instead of
    YNNPACK's, sums round differently, so the solves agree to the solver's tolerance; keeping
    the optimization barriers changes no metric. Other platforms compile with none."""
    from afbl_jax.sim import _batch

    assert A.sim.batch_compiler_options() == A.sim.CPU_COMPILER_OPTIONS
    kw = {"strategy": "ensemble", "dtype": "float32", "rtol": 1e-5, "atol": 1e-6, "n_save": 41}
    tuned = A.simulate_batch(A.AFBL(), cases[0], **kw)
    copies = {"xla_cpu_copy_insertion_use_region_analysis": True}
    copies_only = eqx.filter_jit(_batch._run, compiler_options=copies)
    monkeypatch.setattr(_batch, "_compiled_run", lambda *platform: copies_only)
    copy_run = A.simulate_batch(A.AFBL(), cases[0], **kw)
    monkeypatch.setattr(_batch, "_compiled_run", lambda *platform: _batch._plain_run)
    plain = A.simulate_batch(A.AFBL(), cases[0], **kw)
    for a, b in zip(jax.tree.leaves(copy_run), jax.tree.leaves(plain)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_array_equal(np.asarray(tuned.status), np.asarray(plain.status))
    for name in ("ise_attitude", "ise_altitude"):
        a, b = np.asarray(getattr(tuned, name)), np.asarray(getattr(plain, name))
        np.testing.assert_allclose(a, b, rtol=10 * kw["rtol"])
    # optimization barriers kept until code generation change where values are stored, not
    # the arithmetic: every metric bitwise as without that option
    expanded = {
        k: v for k, v in A.sim.CPU_COMPILER_OPTIONS.items() if k != "xla_disable_hlo_passes"
    }
    assert len(expanded) == len(A.sim.CPU_COMPILER_OPTIONS) - 1
    run_expanded = eqx.filter_jit(_batch._run, compiler_options=expanded)
    monkeypatch.setattr(_batch, "_compiled_run", lambda *platform: run_expanded)
    without_barriers = A.simulate_batch(A.AFBL(), cases[0], **kw)
    for a, b in zip(jax.tree.leaves(tuned), jax.tree.leaves(without_barriers)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert A.sim.batch_compiler_options("gpu") == {}
