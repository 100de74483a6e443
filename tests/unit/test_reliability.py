"""What a new user hits first, in-process: solver failures on every strategy, gains at full
precision, runs sharing a folder, case keys beyond 2^32, results that cannot fit, reports of
degenerate runs, figure labels and layout, progress and padding, messages of damaged or foreign
folders, --help defaults, and a seeded fuzz of bad distribution and gains files.

The same things through the real ``afbl`` command: tests/integration/test_reliability_cli.py.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

import afbl_jax as A
from afbl_jax.cli import build_parser, main
from afbl_jax.io import FileLock, atomic_write_table, controller_from_dict, table_columns
from afbl_jax.model import CHANNEL_INDEX
from afbl_jax.sim import Status
from afbl_jax.studies import montecarlo as mc
from afbl_jax.studies.montecarlo import _runner

from ..fuzz_inputs import bad_files

CHUNK = 4  # the chunk size of tests/unit/test_montecarlo.py: its compiled programs are reused
SEED = 11
ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def fbl():
    return {"fbl": A.make_controller("fbl")}


@pytest.fixture(scope="module")
def dist():
    return mc.default_distribution()


def _strict_json(text: str):
    def refuse(constant):
        raise ValueError(f"non-standard JSON constant {constant}")

    return json.loads(text, parse_constant=refuse)


# ------------------------------------------------------------ solver failures, every strategy
def test_solver_failure_reports_where_it_stopped_on_every_strategy(fbl):
    """Inertia scaled by 1e-9 makes the attitude loop so stiff that every solve runs out of
    steps within microseconds: the strategies say so (max_steps_reached), stop there (not at
    t1), and take the peaks over the samples before the stop (the t = 0 sample), never over the
    unsimulated rest of the run. vmap is `simulate` per case; the ensemble computes its peaks in
    its own solve. (The default ensemble_f32 runs the same ensemble code in float32: the real
    command's test covers it, tests/integration/test_reliability_cli.py.)"""
    import equinox as eqx

    # started 0.05-0.1 rad off the trim attitude, so that the t = 0 sample has an error
    start = mc.Distribution.from_dict({"initial": {"attitude": [0.05, 0.1]}})
    chunk = mc.sample_cases(start, CHUNK, 0)
    v = chunk.vehicle  # [model_error] inertia_scale = [1e-9, 1e-9]
    chunk = eqx.tree_at(
        lambda c: (c.vehicle.Ix, c.vehicle.Iy, c.vehicle.Iz),
        chunk,
        (v.Ix * 1e-9, v.Iy * 1e-9, v.Iz * 1e-9),
    )
    settings = mc.SolverSettings(max_steps=256)
    runs = {s: mc.run_chunk(fbl["fbl"], chunk, strategy=s, settings=settings) for s in
            ("vmap", "ensemble")}  # fmt: skip
    # the t = 0 sample, computed here from the initial state and the loop's reference (the
    # position loop commands the trim attitude)
    scenario, vehicle, model = chunk.case(0)
    loop = A.ClosedLoop.make(
        fbl["fbl"], aerodynamics=chunk.aerodynamics, position_loop=chunk.position_loop
    )
    inputs = A.sim.CaseInputs(scenario, vehicle, model, A.DivergenceLimits())
    y0 = loop.initial_state(inputs, np.float64)
    q0 = np.asarray(scenario.initial_state)[np.asarray(CHANNEL_INDEX)]  # phi, theta, psi, z
    e0 = np.asarray(loop.reference_values(0.0, y0.controller, inputs)) - q0
    assert np.max(np.abs(e0[:3])) >= 0.05
    for strategy, got in runs.items():
        assert list(got["status"]) == [Status.max_steps_reached] * CHUNK, strategy
        assert list(mc._runner.status_label(got["status"])) == ["solver_failed"] * CHUNK
        assert np.all((got["t_final"] > 0) & (got["t_final"] < 1e-4)), strategy
        assert np.isclose(got["peak_attitude_error"][0], np.max(np.abs(e0[:3])), rtol=1e-9)
        assert np.isclose(got["peak_altitude_error"][0], abs(e0[3]), rtol=1e-9, atol=1e-15)
    # 256 steps of about 3e-10 s each: the ensemble's shared steps are its stiffest case's
    np.testing.assert_allclose(runs["ensemble"]["t_final"], runs["vmap"]["t_final"], rtol=0.5)
    for k in ("peak_attitude_error", "peak_altitude_error", "peak_saturation"):
        np.testing.assert_allclose(runs["ensemble"][k], runs["vmap"][k], rtol=1e-9, atol=1e-15)


# ------------------------------------------------------------ gains precision
def test_gains_keep_full_precision(tmp_path):
    data = json.loads((ROOT / "docs" / "tuned_gains_afbl.json").read_text())
    data["k"][3] = 80.123456789012345
    ctrl = controller_from_dict(data)
    assert float(ctrl.k[3]) == 80.123456789012345 and float(ctrl.k[3]) != 80.12345886230469
    huge = controller_from_dict({**data, "k": [1e300, 1.0, 1.0, 1.0]})
    assert float(huge.k[0]) == 1e300


# ------------------------------------------------------------ runs sharing a folder
def _recording(monkeypatch, on_call=None):
    sizes = []
    real = _runner.run_chunk

    def record(controller, chunk, **kwargs):
        sizes.append(chunk.n_cases)
        if on_call is not None:
            on_call()
        return real(controller, chunk, **kwargs)

    monkeypatch.setattr(_runner, "run_chunk", record)
    return sizes


# exactly two chunks on any device count: with several devices a sharded run rounds the chunk
# size up to devices x group size (one chunk of 8 here), and these tests would wait forever on
# a lock that only the second chunk's start releases
TWO_CHUNKS = dict(chunk_size=CHUNK, shard=False, progress=False)


def test_run_waits_for_a_chunk_another_run_holds(tmp_path, monkeypatch, fbl, dist):
    """Chunk 0 is locked by "another run": this run computes chunk 1 first, then waits for chunk
    0's lock and computes it itself (the other run stopped without writing it)."""
    out = tmp_path / "shared"
    (out / "chunks").mkdir(parents=True)
    other = _runner._chunk_lock(out / "chunks", 0)
    assert other.acquire(blocking=False)
    sizes = _recording(monkeypatch, on_call=other.release)  # released once chunk 1 starts
    table = mc.run_montecarlo(fbl, dist, 2 * CHUNK, SEED, out, **TWO_CHUNKS)
    assert sizes == [CHUNK, CHUNK]
    assert table_columns(table)["case"].tolist() == list(range(2 * CHUNK))
    (entry,) = mc.read_invocations(out)
    assert entry["chunks_computed"] == 2 and entry["chunks_already_done"] == 0
    assert not list((out / "chunks").glob(".chunk_*.lock"))  # lock files removed when done


def test_run_takes_a_chunk_another_run_finished(tmp_path, monkeypatch, fbl, dist):
    """While this run waits for chunk 0, "the other run" writes it: it is read, not computed,
    and the final table equals a run that computed everything."""
    alone = mc.run_montecarlo(fbl, dist, 2 * CHUNK, SEED, **TWO_CHUNKS)
    out = tmp_path / "shared"
    (out / "chunks").mkdir(parents=True)
    other = _runner._chunk_lock(out / "chunks", 0)
    assert other.acquire(blocking=False)
    first = alone.slice(0, CHUNK)

    def finish_chunk_0():
        atomic_write_table(first, _runner.chunk_file(out / "chunks", 0))
        other.release()

    sizes = _recording(monkeypatch, on_call=finish_chunk_0)
    table = mc.run_montecarlo(fbl, dist, 2 * CHUNK, SEED, out, **TWO_CHUNKS)
    assert sizes == [CHUNK]  # chunk 1 only
    assert table.equals(alone)
    assert mc.read_invocations(out)[0]["chunks_computed"] == 1


def test_file_lock_excludes_other_holders(tmp_path):
    a, b = FileLock(tmp_path / "x.lock"), FileLock(tmp_path / "x.lock")
    assert a.acquire(blocking=False)
    assert not b.acquire(blocking=False)
    a.release()
    assert b.acquire(blocking=False)
    b.release(unlink=True)
    assert not (tmp_path / "x.lock").exists()


# ------------------------------------------------------------ sizes and case keys
def test_case_keys_stay_distinct_beyond_2_32(dist):
    low = mc.sample_cases(dist, 4, 0, start=0)
    high = mc.sample_cases(dist, 4, 0, start=2**32)
    assert not np.allclose(low.inputs["payload_fraction"], high.inputs["payload_fraction"])
    # indices below 2^32 keep their keys fold_in(PRNGKey(seed), i)
    import jax

    want = jax.random.fold_in(jax.random.PRNGKey(3), 2**32 - 1)
    np.testing.assert_array_equal(mc.case_keys(3, [2**32 - 1])[0], want)
    keys = np.asarray(mc.case_keys(3, [0, 2**32, 2**33, 2**40 + 5, 5, mc.MAX_CASE_INDEX]))
    assert len({tuple(k) for k in keys}) == len(keys)
    # a case is the same in every batch, on both sides of 2^32
    across = mc.sample_cases(dist, 4, 0, start=2**32 - 2)
    assert across.index.tolist() == [2**32 - 2, 2**32 - 1, 2**32, 2**32 + 1]
    np.testing.assert_array_equal(
        across.inputs["payload_fraction"][2:], high.inputs["payload_fraction"][:2]
    )
    with pytest.raises(ValueError, match=r"2\^63 - 1"):
        mc.sample_cases(dist, 2, 0, start=mc.MAX_CASE_INDEX)
    with pytest.raises(ValueError, match=r"seed must be an integer in \[0, 2\^63 - 1\]"):
        mc.sample_cases(dist, 1, 2**64)


def test_results_that_cannot_fit_are_refused(dist, tmp_path):
    per_case = _runner.results_bytes_per_case(2, dist)
    table = mc.run_montecarlo(
        {"fbl": A.make_controller("fbl"), "afbl": A.make_controller("afbl")},
        dist,
        1,
        SEED,
        chunk_size=CHUNK,
        progress=False,
    )
    assert per_case <= table.nbytes  # a lower bound of the real table's memory
    mc.check_results_fit(1000, 2, dist, memory=1000 * per_case)
    with pytest.raises(ValueError, match="at most 999 cases fit"):
        mc.check_results_fit(1000, 2, dist, memory=1000 * per_case - 1)
    with pytest.raises(ValueError, match="need at least .* TB of memory"):
        mc.run_montecarlo({"fbl": A.make_controller("fbl")}, dist, 10**12, 0, tmp_path / "x")
    assert not (tmp_path / "x").exists()


# ------------------------------------------------------------ progress and padding
def test_ensemble_group_size_follows_control_and_chunk():
    """Groups of 16 with a continuous controller where every device holds whole groups of 16,
    else (and always with digital control: one sample clock per group) groups of 4."""
    assert mc.ensemble_group_size(False, 1024, 2) == mc.CONTINUOUS_GROUP_SIZE == 16
    assert mc.ensemble_group_size(False, 16, 1) == 16
    assert mc.ensemble_group_size(False, 16, 2) == mc.GROUP_SIZE == 4  # 8 cases per device
    assert mc.ensemble_group_size(False, 24, 1) == 4
    assert mc.ensemble_group_size(True, 1024, 2) == 4
    assert mc.ensemble_group_size(False, 16384, 1, "gpu") == 4  # accelerators: not measured
    assert mc.BATCH_SETTINGS["ensemble_f32"]["group_size"] == 16
    assert not mc.distribution_is_digital(mc.default_distribution())
    digital = mc.Distribution.from_dict(
        {"unmodeled": {"enabled": True, "control_rate": [200, 400]}}
    )
    assert mc.distribution_is_digital(digital)
    # a rate in a disabled section samples no unmodeled dynamics: the cases stay continuous
    off = mc.Distribution.from_dict({"unmodeled": {"enabled": False, "control_rate": [200, 400]}})
    assert not mc.distribution_is_digital(off)
    assert mc.sample_cases(off, 4, 0).unmodeled is None


def test_progress_counts_cases_and_one_chunk_runs_are_small(monkeypatch, capsys, fbl, dist):
    assert mc.chunk_ladder(256, 8) == (8, 16, 32, 64, 128, 256)
    assert mc.simulated_size(1, 256, 8, n_chunks=1) == 8
    assert mc.simulated_size(40, 256, 8, n_chunks=1) == 64
    assert mc.simulated_size(1, 256, 8, n_chunks=3) == 256  # reuse the chunks' program
    sizes = _recording(monkeypatch)
    one = mc.run_montecarlo(fbl, dist, 1, SEED, chunk_size=256, progress=True)
    err = capsys.readouterr().err
    assert sizes == [mc.CONTINUOUS_GROUP_SIZE]  # one group of 16 cases, not 256
    assert "1/1" in err and "/256" not in err
    assert table_columns(one)["case"].tolist() == [0]
    sizes.clear()
    mc.run_montecarlo(fbl, dist, 6, SEED, chunk_size=CHUNK, progress=True)
    assert sizes == [CHUNK, CHUNK] and "6/6" in capsys.readouterr().err


# ------------------------------------------------------------ degenerate reports
def _cols(status, payload, n=4):
    names = np.array(["fbl", "afbl"] * n)
    rng = np.random.default_rng(0)
    return {
        "case": np.repeat(np.arange(n), 2),
        "controller": names,
        "status": np.array(status * (2 * n // len(status))),
        "payload_fraction": np.repeat(np.asarray(payload, float), 2),
        "gust_speed": np.repeat(rng.uniform(0, 6, n), 2),
        "ise_attitude": rng.uniform(1e-3, 1e-2, 2 * n),
        "ise_altitude": rng.uniform(1e-3, 1e-2, 2 * n),
    }


def test_report_of_a_run_where_every_run_failed(tmp_path, dist):
    import matplotlib.pyplot as plt

    from afbl_jax.plotting.montecarlo import figure_ecdf, figure_heatmaps, figure_ise_vs_payload

    cols = _cols(["solver_failed", "diverged"], [0.3] * 4)  # one payload value
    summary = mc.summarize(cols)
    text = mc.format_summary(summary)
    assert "no successful runs" in text and "nan" not in text.lower()
    assert "0/0" in text and "no case with a successful run" in text
    meta = {"config": {"seed": 0}, "git_revision": "x"}
    mc.write_report(tmp_path, cols, summary, dist, meta)
    saved = _strict_json((tmp_path / "summary.json").read_text())
    assert saved["controllers"]["fbl"]["ise_attitude"]["p50"] is None
    assert saved["paired"]["afbl_over_fbl"]["ise_altitude"]["win_rate"] is None
    md = (tmp_path / "report.md").read_text()
    assert "no successful runs" in md and "nan" not in md.lower()
    assert [p.name for p in (tmp_path / "figures").iterdir()] == ["heatmap_payload_gust.png"]
    fig = figure_heatmaps(cols)
    fig.canvas.draw()
    for ax in fig.axes:
        if ax.get_title().endswith("(ok runs)"):
            assert [t.get_text() for t in ax.texts] == ["no successful runs"]
        elif ax.get_title():
            lo, hi = ax.get_xlim()  # a constant payload gets a readable range, no 1e-12 offset
            assert hi - lo >= 0.5 and ax.xaxis.get_major_formatter().get_offset() == ""
    plt.close(fig)
    for make in (figure_ise_vs_payload, figure_ecdf):
        fig = make(cols)
        assert all([t.get_text() for t in ax.texts] == ["no successful runs"] for ax in fig.axes)
        assert all(not ax.get_xticks().size for ax in fig.axes)
        plt.close(fig)


def _suptitle(fig) -> list:
    from matplotlib.text import Text

    title = fig.get_suptitle()
    return [t for t in fig.findobj(Text) if title and t.get_text() == title and t.figure is fig]


def _overlaps(fig) -> list[str]:
    """Pairs of figure elements (axes with their labels, suptitle) whose boxes overlap."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    boxes = [(f"axes {i}", ax.get_tightbbox(renderer)) for i, ax in enumerate(fig.axes)]
    boxes += [("suptitle", t.get_window_extent(renderer)) for t in _suptitle(fig)]
    bad = []
    for i, (na, a) in enumerate(boxes):
        for nb, b in boxes[i + 1 :]:
            w = min(a.x1, b.x1) - max(a.x0, b.x0)
            h = min(a.y1, b.y1) - max(a.y0, b.y0)
            if w > 1 and h > 1:  # more than a pixel each way
                bad.append(f"{na} / {nb}")
    return bad


def test_report_figures_have_units_and_no_overlaps():
    import matplotlib.pyplot as plt

    from afbl_jax.plotting.montecarlo import figure_ecdf, figure_heatmaps, figure_ise_vs_payload

    cols = _cols(["ok", "ok", "diverged", "ok"], np.linspace(0, 0.5, 40), n=40)
    for make in (figure_ise_vs_payload, figure_ecdf, figure_heatmaps):
        fig = make(cols)
        assert _overlaps(fig) == [], make.__name__
        labels = [ax.get_xlabel() for ax in fig.axes] + [ax.get_ylabel() for ax in fig.axes]
        for label in filter(None, labels):
            assert re.search(r"\[.+\]", label), (make.__name__, label)  # a unit in brackets
        assert any("ISE" in x for x in labels)
        if make is figure_heatmaps:
            assert "white cells" in fig.get_suptitle()
        plt.close(fig)


# ------------------------------------------------------------ small gaps
def test_damaged_chunk_and_foreign_folder_say_what_to_do(tmp_path, fbl, dist, capsys):
    out = tmp_path / "run"
    mc.run_montecarlo(fbl, dist, 2 * CHUNK, SEED, out, chunk_size=CHUNK, progress=False)
    path = _runner.chunk_file(out / "chunks", 1)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])  # cut short
    with pytest.raises(ValueError, match="damaged .* delete it and re-run the same command"):
        mc.run_montecarlo(fbl, dist, 2 * CHUNK, SEED, out, chunk_size=CHUNK, progress=False)
    other = mc.Distribution.from_dict({"payload": {"fraction": [0.0, 0.4]}})
    with pytest.raises(ValueError, match=r"differs in: distribution\.payload\.fraction, seed;"):
        mc.run_montecarlo(fbl, other, 2 * CHUNK, SEED + 1, out, chunk_size=CHUNK, progress=False)
    assert mc.config_differences({"a": {"b": 1, "c": 2}}, {"a": {"b": 1, "c": 3}, "d": 0}) == [
        "a.c",
        "d",
    ]
    argv = ["montecarlo", "--out", str(out), "--cases", str(2 * CHUNK), "--controllers", "fbl"]
    assert main([*argv, "--seed", str(SEED), "--chunk-size", str(CHUNK), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "delete it and re-run the same command" in err
    path.unlink()  # what the message says: the chunk is recomputed
    mc.run_montecarlo(fbl, dist, 2 * CHUNK, SEED, out, chunk_size=CHUNK, progress=False)
    assert len(pq.read_table(out / "results.parquet")) == 2 * CHUNK


def test_every_flag_shows_its_default_in_help(capsys):
    parser = build_parser()
    sub = next(a for a in parser._actions if a.choices and "tune" in a.choices)
    for name, p in sub.choices.items():
        for action in p._actions:
            if action.option_strings and action.dest != "help":
                flag = f"afbl {name} {action.option_strings[0]}"
                assert action.help, f"{flag} has no help text"
                if action.default is None and not action.required:  # what "unset" means
                    assert "default" in action.help, f"{flag} does not say its default"
    assert main(["tune", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    for flag, default in (("--steps", "100"), ("--lr", "0.05"), ("--max-steps", "4096")):
        pattern = re.escape(flag) + r" [A-Z_]+ [^()]*\(default: " + re.escape(default) + r"\)"
        assert re.search(pattern, text), flag


def test_tolerance_and_argparse_errors_are_one_line(tmp_path, capsys):
    out = tmp_path / "never"
    for argv, match in (
        (["--rtol", "-1"], "--rtol must be a finite number > 0, got -1.0."),
        (["--atol", "nan"], "--atol must be a finite number > 0, got nan."),
        (["--cases", "x"], "argument --cases: invalid int value: 'x'"),
        (["--seed", str(2**64)], "argument --seed: expected an integer in [0, 2^63 - 1]"),
        (["--frobnicate"], "unrecognized arguments: --frobnicate"),
    ):
        assert main(["montecarlo", "--out", str(out), *argv]) == 2
        err = capsys.readouterr().err
        assert err.startswith("afbl montecarlo: error: ") and err.count("\n") == 1, err
        assert match in err and "None" not in err
    assert main(["montecarlo"]) == 2
    assert "required: --out (see afbl montecarlo --help)" in capsys.readouterr().err
    assert not out.exists()


def test_docs_read_results_with_core_dependencies(tmp_path, dist):
    """The getting-started page's snippet for reading results runs as written (pyarrow and
    NumPy are core dependencies; pandas is only needed for its to_pandas() line)."""
    readme = (ROOT / "docs" / "getting_started.md").read_text()
    snippet = readme.split("<!-- read-results -->")[1].split("```python")[1].split("```")[0]
    both = {"fbl": A.make_controller("fbl"), "afbl": A.make_controller("afbl")}
    mc.run_montecarlo(both, dist, CHUNK, SEED, tmp_path / "results" / "mc", chunk_size=CHUNK,
                      progress=False)  # fmt: skip
    namespace: dict = {}
    import os

    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:
        exec(snippet, namespace)
    finally:
        os.chdir(cwd)
    assert sorted(namespace["cols"]["case"].tolist()) == sorted(list(range(CHUNK)) * 2)
    assert np.isfinite(namespace["cols"]["ise_attitude"][namespace["ok"]].mean())
    assert "pandas" in readme.split("<!-- read-results -->")[1].split("```")[2]


# ------------------------------------------------------------ fuzz
def test_fuzzed_bad_files_are_refused_cleanly(tmp_path, capsys):
    """60 generated bad files through `afbl montecarlo` (the CLI's main, in this process):
    exit status 2, one line naming the file, nothing written, no exception escapes."""
    cases = bad_files(tmp_path / "bad", seed=2024, n_distribution=40, n_gains=20)
    assert len({what for _, _, what in cases}) >= 20  # many different mutations
    out = tmp_path / "never"
    for kind, path, what in cases:
        flag = ["--distribution", str(path)] if kind == "distribution" else ["--gains", str(path)]
        argv = ["montecarlo", "--out", str(out), "--controllers", "fbl,afbl,afbl_paper", *flag]
        rc = main(argv)
        captured = capsys.readouterr()
        err = captured.err
        assert rc == 2, (what, path.read_bytes()[:200], err)
        assert err.startswith("afbl montecarlo: error: ") and err.count("\n") == 1, (what, err)
        assert str(path) in err, (what, err)
        assert not captured.out and not out.exists(), what


def test_bad_file_sources_are_reported_by_name(tmp_path):
    with pytest.raises(ValueError, match="is a directory"):
        mc.load_distribution(tmp_path)
    path = tmp_path / "d.json"
    path.write_text('{"payload": {"fraction": [0, 1e999]}}')
    with pytest.raises(ValueError, match=r"d\.json: payload\.fraction must be a range"):
        mc.load_distribution(path)
