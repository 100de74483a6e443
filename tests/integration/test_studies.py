"""Every script in studies/ runs end to end at a small size, as a user would run it (a fresh
Python process, one XLA CPU device per core), and writes its outputs; bad input is one line on
stderr with exit status 2 and no traceback."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from ..helpers import subprocess_env

ROOT = Path(__file__).resolve().parents[2]
STUDIES = ROOT / "studies"


def _wilson_written_out(k: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """Wilson's (1927) score interval written out, independently of the package's:
    (p + z^2 / 2n -+ z sqrt(p (1 - p) / n + z^2 / 4n^2)) / (1 + z^2 / n)."""
    p = k / n
    centre = p + z**2 / (2 * n)
    half = z * math.sqrt(p * (1 - p) / n + z**2 / (4 * n**2))
    return ((centre - half) / (1 + z**2 / n), (centre + half) / (1 + z**2 / n))


def _check_importance_estimate(est: dict, results: Path) -> None:
    """The importance-sampling estimate and its 95 % interval (normal approximation of the
    weighted mean, clipped at 0) recomputed from the final stage's samples in results.parquet:
    w_i = 1[margin_i > 0] exp(log_weight_i)."""
    import numpy as np
    import pyarrow.parquet as pq

    t = pq.read_table(results).to_pydict()
    w = np.where(np.asarray(t["failure_margin"]) > 0, np.exp(t["log_weight"]), 0.0)
    p = w.mean()
    sd = w.std(ddof=1) / math.sqrt(len(w))
    assert len(w) == est["n_final"] and est["failures"] == int(np.sum(w > 0))
    assert est["probability"] == pytest.approx(p, rel=1e-12, abs=1e-300)
    assert est["ci95"] == pytest.approx([max(0.0, p - 1.96 * sd), p + 1.96 * sd], abs=1e-15)


def _run(script: str, *args: str, timeout: int = 900) -> subprocess.CompletedProcess:
    env = subprocess_env(PYTHONUNBUFFERED="1")
    return subprocess.run(
        [sys.executable, str(STUDIES / script), *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=ROOT,
        env=env,
    )


def test_every_study_script_is_tested():
    tested = {
        "reproduce_paper.py",
        "montecarlo_robustness.py",
        "tune_gains.py",
        "tune_compare.py",
        "unmodeled_dynamics.py",
        "benchmark.py",
        "rare_failures.py",
        "dask_scaling.py",  # tests/integration/test_dask.py
        "test_times.py",
        "turbulence_band.py",
    }
    assert {p.name for p in STUDIES.glob("*.py")} == tested


def test_turbulence_band_script_rejects_bad_input(tmp_path):
    r = _run("turbulence_band.py", "--cases", "0", "--out", str(tmp_path / "b"))
    assert r.returncode == 2 and "--cases must be >= 1" in r.stderr
    assert "Traceback" not in r.stderr and not (tmp_path / "b").exists()


@pytest.mark.slow
def test_turbulence_band_script(tmp_path):
    """Both runs on 8 cases (two fresh compilations, hence slow): the cutoff keeps fewer lines,
    most of the variance, and every case's status; the ISE differences are those of the two
    runs' results files, recomputed here."""
    import numpy as np
    import pyarrow.parquet as pq

    out = tmp_path / "b"
    r = _run("turbulence_band.py", "--cases", "8", "--out", str(out), "--no-progress")
    assert r.returncode == 0, r.stderr[-2000:]
    doc = json.loads((out / "turbulence_band.json").read_text())
    v = doc["variants"]
    assert v["cutoff"]["lines"] < v["all_lines"]["lines"] == 64
    assert v["cutoff"]["top_line_rad_s"] <= 100.0 < v["all_lines"]["top_line_rad_s"]
    assert all(0.99 < k["total"] <= 1.0 for k in doc["variance_kept"].values())
    cut, full = (pq.read_table(out / k / "results.parquet").to_pandas() for k in v)
    for c, e in doc["ise_relative_difference"].items():
        a = cut[cut.controller == c].sort_values("case")
        b = full[full.controller == c].sort_values("case")
        ok = (a.status.values == "ok") & (b.status.values == "ok")
        rel = np.abs(a.ise_attitude.values[ok] / b.ise_attitude.values[ok] - 1)
        assert e["ise_attitude"]["max"] == pytest.approx(rel.max(), rel=1e-12)
        assert e["status_changed"] == int(np.sum(a.status.values != b.status.values))


def test_test_times_script(tmp_path):
    """The per-file times of a small pytest run: every test of the file counted once, its
    seconds within the wall time, the run's counts parsed."""
    out = tmp_path / "times.json"
    r = _run("test_times.py", "--out", str(out), "--", "tests/unit/test_stats.py", "-n", "0")
    assert r.returncode == 0, r.stderr[-2000:]
    doc = json.loads(out.read_text())
    assert doc["exit_code"] == 0 and doc["failed"] == 0 and doc["passed"] > 0
    (row,) = doc["files"]
    assert row["file"] == "tests/unit/test_stats.py" and row["tests"] == doc["passed"]
    assert 0 < row["seconds"] <= doc["wall_s"]


def test_reproduce_paper_script(tmp_path):
    r = _run(
        "reproduce_paper.py",
        "--out",
        str(tmp_path),
        "--controllers",
        "fbl,afbl",
        "--n-save",
        "11",
        "--rtol",
        "1e-6",
        "--atol",
        "1e-8",
        "--no-figures",
    )
    assert r.returncode == 0, r.stderr[-2000:]
    assert "ISE reduction of afbl vs fbl" in r.stdout
    doc = json.loads((tmp_path / "ise.json").read_text())
    assert doc["meta"]["config"]["controllers"]["afbl"]["lambda"] == [4.0, 4.0, 4.0, 4.0]


def test_montecarlo_script(tmp_path):
    r = _run(
        "montecarlo_robustness.py",
        "--cases",
        "8",
        "--chunk-size",
        "8",
        "--out",
        str(tmp_path / "mc"),
        "--no-progress",
    )
    assert r.returncode == 0, r.stderr[-2000:]
    assert "paired win rate" in r.stdout
    for name in ("results.parquet", "meta.json", "summary.json", "report.md", "report.html"):
        assert (tmp_path / "mc" / name).exists(), name
    meta = json.loads((tmp_path / "mc" / "meta.json").read_text())
    assert meta["config"]["seed"] == 0 and meta["git_revision"]
    assert len(meta["jax_devices"]) == os.cpu_count()  # one device per core


def test_unmodeled_script(tmp_path):
    r = _run(
        "unmodeled_dynamics.py",
        "--out",
        str(tmp_path),
        "--controllers",
        "fbl",
        "--taus",
        "0.03",
        "--rates",
        "50",
        "--noise-levels",
        "0",
        "--no-figures",
    )
    assert r.returncode == 0, r.stderr[-2000:]
    doc = json.loads((tmp_path / "unmodeled_dynamics.json").read_text())
    assert doc["meta"]["config"]["rates_hz"] == [50.0]


def test_tune_script(tmp_path):
    r = _run(
        "tune_gains.py",
        "--controller",
        "afbl",
        "--objective",
        "nominal",
        "--steps",
        "1",
        "--method",
        "cmaes",
        "--population",
        "4",
        "--heldout-cases",
        "8",
        "--out",
        str(tmp_path),
        "--no-figures",
        "--no-progress",
        "--rtol",
        "1e-5",
        "--atol",
        "1e-7",
    )
    assert r.returncode == 0, r.stderr[-2000:]
    gains = json.loads((tmp_path / "gains.json").read_text())
    assert gains["controller"] == "afbl" and len(gains["lambda"]) == 4
    doc = json.loads((tmp_path / "evaluation.json").read_text())
    paper, tuned = doc["heldout"]["paper"], doc["heldout"]["tuned"]
    assert paper["n_cases"] + paper["outside_envelope"] == 8
    assert set(paper["ise"]) >= {"p50", "p90", "p99", "cvar90"}
    for entry in (paper, tuned):
        k, n = entry["failures"], entry["n_cases"]
        assert entry["failure_rate"] == k / n
        assert entry["failure_wilson95"] == pytest.approx(_wilson_written_out(k, n), abs=1e-12)


def test_tune_compare_script(tmp_path):
    r = _run(
        "tune_compare.py",
        "--study",
        "optimizers",
        "--methods",
        "cmaes",
        "--seeds",
        "0",
        "--objective",
        "nominal",
        "--population",
        "4",
        "--steps",
        "2",
        "--time-budget",
        "600",
        "--rtol",
        "1e-5",
        "--atol",
        "1e-7",
        "--no-progress",
        "--out",
        str(tmp_path),
    )
    assert r.returncode == 0, r.stderr[-2000:]
    doc = json.loads((tmp_path / "optimizers.json").read_text())
    hist = doc["runs"]["cmaes"]["0"]
    assert len(hist) == 3 and hist[-1]["loss"] <= hist[0]["loss"]
    assert (tmp_path / "loss_vs_time.png").exists()


def test_benchmark_script(tmp_path):
    r = _run(
        "benchmark.py",
        "--out",
        str(tmp_path),
        "--sizes",
        "8",
        "--strategies",
        "scipy_rk45_loop,montecarlo_default",
        "--scipy-cases",
        "1",
        "--ref-cases",
        "8",
    )
    assert r.returncode == 0, r.stderr[-2000:]
    rows = json.loads((tmp_path / "bench.json").read_text())
    assert [r_["strategy"] for r_ in rows] == ["scipy_rk45_loop", "montecarlo_default"]
    assert rows[1]["max_rel_ise_error"] < 1e-3


@pytest.mark.parametrize(
    "script, args, match",
    [
        ("montecarlo_robustness.py", ["--cases", "0"], "--cases must be >= 1"),
        ("reproduce_paper.py", ["--controllers", "lqr"], "unknown controller"),
    ],
)
def test_bad_input_is_one_line_exit_2(tmp_path, script, args, match):
    out = tmp_path / "never"
    r = _run(script, "--out", str(out), *args)
    assert r.returncode == 2
    assert match in r.stderr and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert not out.exists()


SHORT_TOML = """
[time]
t1 = 2.0
[pulses]
start = [0.5, 1.5]
[gust]
start = [0.5, 1.5]
[turbulence]
n_frequencies = 4
"""


def test_rare_failures_script_rejects_bad_input(tmp_path):
    r = _run("rare_failures.py", "--starts", "1", "--out", str(tmp_path / "bad"))
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip() == "afbl falsify: error: --starts must be >= 2, got 1."
    r = _run("rare_failures.py", "estimate", "--estimator", "x", "--out", str(tmp_path / "bad"))
    assert r.returncode == 2 and "unknown --estimator 'x'" in r.stderr
    assert not (tmp_path / "bad").exists()


@pytest.mark.slow
def test_rare_failures_script(tmp_path):
    """End to end (10 min on the busy 2-core machine: two fresh processes compile the gradient
    and the ensembles; the same functions run in the default suite through notebook 04 and
    tests/unit/test_rare.py)."""
    dist = tmp_path / "short.toml"
    dist.write_text(SHORT_TOML)
    r = _run(
        "rare_failures.py",
        "--controllers",
        "afbl",
        "--starts",
        "2",
        "--budget",
        "4",
        "--design-budget",
        "3",
        "--attitude-limit",
        "0.2",
        "--distribution",
        str(dist),
        "--out",
        str(tmp_path / "f"),
    )
    assert r.returncode == 0, r.stderr[-2000:]
    doc = json.loads((tmp_path / "f" / "falsify.json").read_text())
    assert doc["config"]["budget"] == 4 and doc["git_revision"]
    assert doc["config"]["design_budget"] == 3
    entry = doc["falsify"]["controllers"]["afbl"]
    searches = entry["searches"]
    assert searches[0]["gradient"]["simulations"] <= 4 and searches[0]["cmaes"]["simulations"] <= 4
    if "most_likely_failure" in entry:  # a failing case was found: the design point fails too
        dp = entry["design_point"]
        assert dp["margin"] > 0 and dp["gradient_simulations"] <= 3
        assert dp["distance"] <= dp["ray_distance"] + 1e-9
        assert dp["ray_distance"] == entry["most_likely_failure"]["normal_distance"]
    for name in ("worst_cases.parquet", "rare_report.md", "figures/falsify_search.png"):
        assert (tmp_path / "f" / name).exists(), name
    r = _run(
        "rare_failures.py",
        "estimate",
        "--estimator",
        "ce",
        "--controllers",
        "afbl",
        "--cases",
        "16",
        "--stage-cases",
        "16",
        "--search-budget",
        "0",
        "--attitude-limit",
        "0.2",
        "--distribution",
        str(dist),
        "--out",
        str(tmp_path / "r"),
        "--no-progress",
    )
    assert r.returncode == 0, r.stderr[-2000:]
    doc = json.loads((tmp_path / "r" / "rare_event.json").read_text())
    est = doc["rare_event"]["controllers"]["afbl"]
    _check_importance_estimate(est, tmp_path / "r" / "results.parquet")
    assert est["total_simulations"] >= 32
    r = _run(
        "rare_failures.py",
        "estimate",
        "--estimator",
        "ce-mixture",
        "--strategy",
        "ensemble_f32",
        "--controllers",
        "afbl",
        "--cases",
        "16",
        "--stage-cases",
        "16",
        "--attitude-limit",
        "0.2",
        "--distribution",
        str(dist),
        "--out",
        str(tmp_path / "m"),
        "--no-progress",
    )
    assert r.returncode == 0, r.stderr[-2000:]
    doc = json.loads((tmp_path / "m" / "rare_event.json").read_text())
    assert doc["config"]["dtype"] == "float32" and doc["config"]["rtol"] == 3e-6
    est = doc["rare_event"]["controllers"]["afbl"]
    _check_importance_estimate(est, tmp_path / "m" / "results.parquet")
    assert est["stages"][0]["selected_names"] and est["proposal"]["alpha"] == 0.1
    assert est["total_simulations"] == 16 * (len(est["stages"]) + 1)
    r = _run(
        "rare_failures.py",
        "estimate",
        "--estimator",
        "subset",
        "--strategy",
        "ensemble_f32",
        "--controllers",
        "afbl",
        "--stage-cases",
        "20",
        "--p0",
        "0.1",
        "--attitude-limit",
        "1.0",
        "--distribution",
        str(dist),
        "--out",
        str(tmp_path / "s"),
        "--no-progress",
    )
    assert r.returncode == 0, r.stderr[-2000:]
    doc = json.loads((tmp_path / "s" / "rare_event.json").read_text())
    assert doc["config"]["p0"] == 0.1 and doc["config"]["n_per_stage"] == 20
    est = doc["rare_event"]["controllers"]["afbl"]
    assert est["method"] == "subset"
    # the log-normal interval p exp(-+ z sqrt(log(1 + cv^2))), from the reported p and cv
    spread = 1.959963984540054 * math.sqrt(math.log1p(est["cv"] ** 2))
    p_hat = est["probability"]
    if p_hat > 0:
        assert est["ci95"] == pytest.approx([p_hat * math.exp(-spread), p_hat * math.exp(spread)])
    else:  # no failure at the last level: an upper bound from the level before
        assert est["ci95"][0] == 0.0 and est["ci95"][1] > 0
    levels = est["stages"]
    assert est["total_simulations"] == 20 + 18 * (len(levels) - 1)  # 2 chains of 10 states
    assert est["probability"] == pytest.approx(
        math.prod(s["conditional_probability"] for s in levels)
    )
    import pyarrow.parquet as pq

    t = pq.read_table(tmp_path / "s" / "results.parquet").to_pydict()
    assert len(t["failure_margin"]) == 20 and len(set(t["log_weight"])) == 1
    assert sum(m > 0 for m in t["failure_margin"]) == levels[-1]["failures"]
    assert "subset simulation levels" in (tmp_path / "s" / "rare_report.md").read_text()
