"""`afbl_jax.ensemble_vector_field`: the ensemble vector field (case axis last, groups,
case-invariant inputs hoisted) equals the single-case closed loop evaluated case by case."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import afbl_jax as A
from afbl_jax.studies import montecarlo as mc

N, GROUP = 8, 4


@pytest.fixture(scope="module")
def batch():
    return mc.sample_cases(mc.default_distribution(), N, 11)


def _perturbed_state(field, seed):
    """The initial states moved by random amounts (so every term of the field is active)."""
    y0 = field.initial_state(jnp.float64)
    keys = jax.random.split(jax.random.PRNGKey(seed), len(jax.tree.leaves(y0)))
    leaves, tree = jax.tree.flatten(y0)
    scale = 0.2
    moved = [x + scale * jax.random.normal(k, x.shape) for x, k in zip(leaves, keys, strict=True)]
    return jax.tree.unflatten(tree, moved)


@pytest.mark.parametrize("t", [0.0, 3.7, 11.2])
def test_ensemble_field_equals_single_case_loop(batch, t):
    controller = A.AFBL()
    field = A.ensemble_vector_field(
        controller,
        batch.scenario,
        batch.vehicle,
        batch.model,
        aerodynamics=batch.aerodynamics,
        group_size=GROUP,
        position_loop=batch.position_loop,
    )
    y = _perturbed_state(field, 1)
    dy = eqx.filter_jit(lambda f, tt, yy: f(tt, yy))(field, t, y)
    loop = A.ClosedLoop.make(
        controller, aerodynamics=batch.aerodynamics, position_loop=batch.position_loop
    )
    for i in range(N):
        scenario, vehicle, model = batch.case(i)
        inputs = A.sim.CaseInputs(scenario, vehicle, model, A.DivergenceLimits())
        yi = jax.tree.map(lambda x: x[..., i], y)
        ref = loop.vector_field(jnp.asarray(t), yi, (inputs, None))
        for a, b in zip(jax.tree.leaves(dy), jax.tree.leaves(ref), strict=True):
            np.testing.assert_allclose(a[..., i], b, rtol=1e-12, atol=1e-12)


def test_frozen_cases_have_zero_derivative(batch):
    field = A.ensemble_vector_field(
        A.AFBL(), batch.scenario, batch.vehicle, batch.model, group_size=GROUP
    )
    y = field.initial_state()
    frozen = jnp.arange(N) % 3 == 0
    dy = field(1.0, y, frozen)
    free = field(1.0, y)
    for a, b in zip(jax.tree.leaves(dy), jax.tree.leaves(free), strict=True):
        assert np.all(np.asarray(a)[..., np.asarray(frozen)] == 0.0)
        np.testing.assert_array_equal(a[..., ~frozen], b[..., ~frozen])
        assert np.any(np.asarray(b)[..., np.asarray(frozen)] != 0.0)


def test_digital_control_and_bad_groups_rejected(batch):
    digital = A.UnmodeledDynamics.make(control_rate=250.0, duration=20.0)
    with pytest.raises(ValueError, match="continuous control only"):
        A.ensemble_vector_field(A.AFBL(), batch.scenario, unmodeled=digital)
    with pytest.raises(ValueError, match="do not split into groups of 3"):
        A.ensemble_vector_field(A.AFBL(), batch.scenario, group_size=3)


def test_profiling_script_runs_at_a_small_size(capsys):
    """benchmarks/vector_field.py end to end on 8 cases: one timing per variant, and the
    variants that remove work report it (no Dryden lines: fewer sin/cos in the HLO)."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "benchmarks" / "vector_field.py"
    spec = importlib.util.spec_from_file_location("vector_field_script", path)
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    per = script.main(
        ["--cases", "8", "--evals", "2", "--repeats", "1", "--variants", "default,no_wind", "--hlo"]
    )
    assert set(per) == {("this", "default"), ("this", "no_wind")}
    assert all(np.isfinite(v) and v > 0 for v in per.values())
    out = capsys.readouterr().out
    rows = {line.split()[1]: line.split() for line in out.splitlines() if line.startswith("this ")}
    assert int(rows["no_wind"][2]) < int(rows["default"][2])  # sin/cos count
