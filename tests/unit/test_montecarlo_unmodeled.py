"""Monte-Carlo sampling of unmodeled-dynamics settings (distribution section [unmodeled]).

Short runs (t1 = 3 s, few saved samples) and one chunk size keep the digital-loop compiles few.
"""

from __future__ import annotations

import jax
import numpy as np
import pytest

import afbl_jax as A
from afbl_jax.io import table_columns
from afbl_jax.studies import montecarlo as mc

T1 = 3.0
CHUNK = 4  # one ensemble group
SEED = 5
SETTINGS = mc.SolverSettings(n_save=31, max_steps=4096).with_tolerances_for("vmap")
QUIET = {  # no pulses / gust / turbulence: only the unmodeled dynamics and the initial state
    "time": {"t1": T1},
    "pulses": {"enabled": False, "start": [0.5, 2.0]},
    "gust": {"enabled": False, "start": [0.5, 2.0]},
    "turbulence": {"enabled": False},
    "payload": {"fraction": [0.0, 0.2]},
}


def _dist(**unmodeled):
    return mc.Distribution.from_dict({**QUIET, "unmodeled": {"enabled": True, **unmodeled}})


@pytest.fixture(scope="module")
def fbl():
    return A.make_controller("fbl")


@pytest.fixture(scope="module")
def digital():
    return _dist(
        plant="full",
        motor_tau=[0.02, 0.04],
        control_rate=[100.0, 200.0],
        delay_samples=[0, 2],
        noise_angle=[0.0, 1e-3],
        noise_rate=[0.0, 1e-2],
        noise_altitude=[0.0, 1e-2],
        noise_vertical_speed=[0.0, 1e-2],
    )


@pytest.mark.parametrize(
    "section, match",
    [
        ({"bogus": 1}, "not a known key"),
        ({"plant": "rigid"}, "one of paper, full"),
        ({"motor_tau": [-0.01, 0.02]}, "must be >= 0"),
        ({"motor_tau": [0.05, 0.02]}, "high < low"),
        ({"delay_samples": [0, 1.5], "control_rate": [100, 200]}, "whole numbers"),
        ({"control_rate": [0, 200]}, "either \\[0, 0\\]"),
        ({"noise_angle": [0.0, 0.01]}, "need a digital controller"),
        ({"enabled": "yes"}, "true or false"),
    ],
)
def test_invalid_unmodeled_sections_rejected(section, match):
    with pytest.raises(ValueError, match=match):
        mc.Distribution.from_dict({"unmodeled": section})


def test_default_has_no_unmodeled_settings():
    batch = mc.sample_cases(mc.default_distribution(), CHUNK, SEED)
    assert batch.unmodeled is None and batch.input_columns == mc.INPUT_COLUMNS
    assert not set(mc.UNMODELED_COLUMNS) & set(batch.inputs)


def test_sampling_deterministic_within_ranges_and_separate_stream(digital):
    a = mc.sample_cases(digital, 64, SEED)
    b = mc.sample_cases(digital, 64, SEED)
    assert jax.tree.all(
        jax.tree.map(lambda x, y: bool(np.array_equal(x, y)), a.unmodeled, b.unmodeled)
    )
    u = a.unmodeled
    assert (u.plant, u.max_samples, u.max_delay) == ("full", int(np.ceil(T1 * 200.0)), 2)
    spec = digital.spec["unmodeled"]
    for name in (
        "motor_tau",
        "control_rate",
        "noise_angle",
        "noise_rate",
        "noise_altitude",
        "noise_vertical_speed",
    ):
        x = np.asarray(getattr(u, name))
        lo, hi = spec[name]
        assert np.all((x >= lo) & (x <= hi)), name
        assert np.std(x) > 0.1 * (hi - lo) / np.sqrt(12), name  # actually spread over the range
        np.testing.assert_array_equal(x, np.asarray(a.inputs[name]))
    d = np.asarray(u.delay_samples)
    assert set(np.unique(d)) == {0, 1, 2}  # integers, both ends included
    # one control rate per ensemble group of GROUP_SIZE consecutive cases (shared sample
    # instants), drawn from the group's first case; the other settings per case
    rate = np.asarray(u.control_rate).reshape(-1, mc.GROUP_SIZE)
    assert np.all(rate == rate[:, :1]) and len(np.unique(rate[:, 0])) == rate.shape[0]
    assert len(np.unique(np.asarray(u.motor_tau))) == 64
    # the other inputs are drawn exactly as without the section
    plain = mc.sample_cases(mc.Distribution.from_dict(QUIET), 64, SEED)
    for name in mc.INPUT_COLUMNS:
        np.testing.assert_array_equal(np.asarray(a.inputs[name]), np.asarray(plain.inputs[name]))
    # case i is the same in any batch, noise keys differ between cases
    c = mc.sample_cases(digital, CHUNK, SEED, start=10)
    np.testing.assert_array_equal(np.asarray(c.unmodeled.key), np.asarray(u.key)[10 : 10 + CHUNK])
    assert len({tuple(k) for k in np.asarray(u.key).tolist()}) == 64


def test_chunk_case_equals_single_unmodeled_simulation(digital, fbl):
    batch = mc.sample_cases(digital, CHUNK, SEED)
    out = mc.run_chunk(fbl, batch, strategy="vmap", settings=SETTINGS)
    assert np.all(out["status"] == 0)  # ok
    i = 1
    scenario, vehicle, model = batch.case(i)
    settings = batch.unmodeled_case(i)
    assert settings.digital and float(settings.noise_angle) > 0
    r = A.simulate(
        fbl,
        scenario,
        vehicle,
        model,
        rtol=SETTINGS.rtol,
        atol=SETTINGS.atol,
        n_save=SETTINGS.n_save,
        max_steps=SETTINGS.max_steps,
        unmodeled=settings,
        aerodynamics=batch.aerodynamics,
        position_loop=batch.position_loop,
    )
    assert np.isclose(out["ise_attitude"][i], float(r.ise_attitude), rtol=1e-9, atol=1e-14)
    assert np.isclose(out["ise_altitude"][i], float(r.ise_altitude), rtol=1e-9, atol=1e-14)
    assert out["solver_steps"][i] == int(r.num_steps)
    # the settings matter: the same case without them gives a different cost
    plain = A.simulate(
        fbl,
        scenario,
        vehicle,
        model,
        rtol=SETTINGS.rtol,
        atol=SETTINGS.atol,
        n_save=SETTINGS.n_save,
        max_steps=SETTINGS.max_steps,
        aerodynamics=batch.aerodynamics,
        position_loop=batch.position_loop,
    )
    assert not np.isclose(float(plain.ise_attitude), float(r.ise_attitude), rtol=1e-3)
    # results table carries the sampled numbers
    table = table_columns(mc._runner._chunk_table(batch, CHUNK, {"fbl": out}))
    np.testing.assert_allclose(table["control_rate"], np.asarray(batch.unmodeled.control_rate))
    assert table["delay_samples"].dtype == np.int64


def test_slow_delayed_controller_flagged_diverged(fbl):
    """A 2-3 Hz controller with a two-sample delay, started 0.05-0.1 rad off its trim."""
    slow = mc.Distribution.from_dict(
        {
            **QUIET,
            "initial": {"attitude": [0.05, 0.1]},
            "unmodeled": {
                "enabled": True,
                "control_rate": [2.0, 3.0],
                "delay_samples": [2, 2],
                "motor_tau": [0.03, 0.03],
            },
        }
    )
    batch = mc.sample_cases(slow, CHUNK, SEED)
    out = mc.run_chunk(fbl, batch, settings=SETTINGS)  # must not raise
    ref = mc.run_chunk(fbl, batch, strategy="vmap", settings=SETTINGS)
    np.testing.assert_array_equal(out["status"], ref["status"])
    # both stop a case at the end of the step in which it crossed the limit (their own steps):
    # within a step of each other
    np.testing.assert_allclose(out["t_final"], ref["t_final"], atol=0.1)
    labels = mc._runner.status_label(out["status"])
    assert np.all(labels == "diverged"), labels
    assert np.all(out["t_final"] < T1)


@pytest.mark.parametrize("strategy, bound", [("ensemble", 1e-6), ("ensemble_f32", 1e-3)])
def test_ensemble_with_unmodeled_agrees_with_single_simulation(digital, fbl, strategy, bound):
    """The ensemble path (the Monte-Carlo default with [unmodeled]) runs the full plant, motor
    lag and digital control with delay and noise; case by case it agrees with `simulate`:
    float64 within 1e-6 relative ISE, float32 within the documented 1e-3 bound."""
    assert mc.resolve_strategy("auto") == "ensemble_f32"
    batch = mc.sample_cases(digital, CHUNK, SEED)
    out = mc.run_chunk(
        fbl, batch, strategy=strategy, settings=mc.SolverSettings(n_save=31, max_steps=4096)
    )
    assert np.all(out["status"] == 0)
    assert np.all(out["solver_steps"] == out["solver_steps"][0])  # one group, shared steps
    for i in range(CHUNK):
        scenario, vehicle, model = batch.case(i)
        r = A.simulate(
            fbl,
            scenario,
            vehicle,
            model,
            rtol=1e-9,
            atol=1e-11,
            n_save=31,
            unmodeled=batch.unmodeled_case(i),
            aerodynamics=batch.aerodynamics,
            position_loop=batch.position_loop,
        )
        for k in ("ise_attitude", "ise_altitude"):
            np.testing.assert_allclose(out[k][i], float(getattr(r, k)), rtol=bound, err_msg=k)
        m = A.metrics_from_result(r, vehicle, model)
        np.testing.assert_allclose(
            out["peak_attitude_error"][i], float(m.peak_attitude_error), rtol=10 * bound
        )


def test_report_figures_survive_tiny_runs():
    """Two cases leave every payload bin with < 3 runs: the figures still render (linear axes)."""
    import matplotlib.pyplot as plt

    from afbl_jax.plotting.montecarlo import figure_ecdf, figure_ise_vs_payload

    cols = {
        "controller": np.array(["fbl", "fbl", "afbl", "afbl"]),
        "status": np.array(["ok", "diverged", "ok", "ok"]),
        "payload_fraction": np.array([0.1, 0.4, 0.1, 0.4]),
        "ise_attitude": np.array([1e-2, np.nan, 5e-3, 6e-3]),
        "ise_altitude": np.array([2e-2, np.nan, 1e-3, 2e-3]),
    }
    fig = figure_ise_vs_payload(cols)
    assert all(ax.get_yscale() == "linear" for ax in fig.axes)  # nothing to log-scale
    plt.close(fig)
    fig = figure_ecdf(cols)
    assert all(ax.get_xscale() == "log" for ax in fig.axes)
    plt.close(fig)
