"""The Dask executor: Monte-Carlo chunks, rare-event batches and CMA-ES populations as tasks of a
LocalCluster of 2 worker processes give the tables and numbers of a one-process run, a worker
killed mid-run costs no chunk and writes none twice, bad cluster input is one line with exit
status 2 and nothing written, and the one-process path never imports Dask."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

import afbl_jax as A
from afbl_jax.cli import main as cli_main
from afbl_jax.studies import montecarlo as mc
from afbl_jax.studies.executors import DaskExecutor, LocalExecutor, map_batches

distributed = pytest.importorskip("distributed")

N = 48  # twelve chunks of 4 cases (the chunk programs of tests/unit/test_montecarlo.py)
CHUNK = 4
SEED = 5
DIST = mc.default_distribution()
SHORT = mc.Distribution.from_dict(
    {"time": {"t1": 3.0}, "pulses": {"start": [0.5, 2.0]}, "gust": {"start": [0.5, 2.0]}},
    "3 s test distribution",
)


@pytest.fixture(scope="module")
def cluster():
    """A LocalCluster of 2 worker processes (spawned, one thread each), shared by the tests,
    and a client of the test's own to watch and kill its workers."""
    with distributed.LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=True,
        dashboard_address=":0",
        silence_logs=50,
    ) as c:
        with distributed.Client(c, set_as_default=False) as client:
            yield c, client


@pytest.fixture(scope="module")
def controllers():
    return {"fbl": A.make_controller("fbl"), "afbl": A.make_controller("afbl")}


@pytest.fixture(scope="module")
def reference(tmp_path_factory, controllers):
    """The one-process run every cluster run is compared with."""
    out = tmp_path_factory.mktemp("dask") / "one_process"
    mc.run_montecarlo(controllers, DIST, N, SEED, out, chunk_size=CHUNK, progress=False)
    return out


def _bytes(folder: Path) -> bytes:
    return (folder / "results.parquet").read_bytes()


def test_cluster_run_is_bit_identical_and_recorded(cluster, controllers, reference, tmp_path):
    c, client = cluster
    out = tmp_path / "cluster"
    mc.run_study(
        mc.StudyConfig(
            controllers,
            out,
            N,
            SEED,
            DIST,
            chunk_size=CHUNK,
            report=False,
            progress=False,
            executor=DaskExecutor(c.scheduler_address),
        ),
        echo=None,
    )
    assert _bytes(out) == _bytes(reference)
    meta = json.loads((out / "meta.json").read_text())
    (entry,) = meta["invocations"]
    assert entry["executor"]["kind"] == "dask"
    assert entry["executor"]["scheduler"] == c.scheduler_address
    workers = entry["executor"]["workers"]
    assert set(workers) == set(client.nthreads())
    assert {w["pid"] for w in workers.values()} == set(client.run(os.getpid).values())
    assert all(len(w["devices"]) == 1 for w in workers.values())  # one core each
    chunks = sorted(k for v in entry["chunks_by_worker"].values() for k in v)
    assert chunks == list(range(N // CHUNK)) and entry["chunks_computed"] == N // CHUNK
    assert set(entry["chunks_by_worker"]) <= set(workers)
    # a second run into the folder resumes: nothing left to compute, the same table
    again = mc.run_montecarlo(
        controllers,
        DIST,
        N,
        SEED,
        out,
        chunk_size=CHUNK,
        progress=False,
        executor=DaskExecutor(c.scheduler_address),
    )
    assert again.equals(pq.read_table(reference / "results.parquet"))
    assert mc.read_invocations(out)[-1]["chunks_computed"] == 0


def test_killed_worker_costs_no_chunk(cluster, controllers, reference, tmp_path, monkeypatch):
    """A worker process killed (SIGKILL, by pid) while it computes a chunk: the scheduler gives
    the chunk to another worker, the nanny starts a new worker, every chunk file is written
    once and whole, and the table is the one-process run's."""
    c, client = cluster
    from afbl_jax.studies.montecarlo import _runner

    writes: list[Path] = []
    killed: list[int] = []
    real = _runner.atomic_write_table

    def write(table, path):
        path = Path(path)
        if path.parent.name == "chunks" and not killed:
            busy = [w for w, keys in client.processing().items() if keys]
            if busy:
                pid = client.run(os.getpid, workers=busy[:1])[busy[0]]
                os.kill(pid, signal.SIGKILL)
                killed.append(pid)
        writes.append(path)
        real(table, path)

    monkeypatch.setattr(_runner, "atomic_write_table", write)
    out = tmp_path / "killed"
    table = mc.run_montecarlo(
        controllers,
        DIST,
        N,
        SEED,
        out,
        chunk_size=CHUNK,
        progress=False,
        executor=DaskExecutor(c.scheduler_address),
    )
    assert killed, "no worker was busy when the first chunk came back"
    assert table.equals(pq.read_table(reference / "results.parquet"))
    assert _bytes(out) == _bytes(reference)
    chunk_writes = [p.name for p in writes if p.parent.name == "chunks"]
    assert sorted(chunk_writes) == sorted(set(chunk_writes))  # none twice
    assert len(chunk_writes) == N // CHUNK
    assert sorted(p.name for p in (out / "chunks").iterdir()) == sorted(chunk_writes)  # no temp
    (entry,) = mc.read_invocations(out)
    assert sum(len(v) for v in entry["chunks_by_worker"].values()) == N // CHUNK
    client.wait_for_workers(2, timeout=60)  # the nanny's new worker, for the tests after this
    assert killed[0] not in client.run(os.getpid).values()


@pytest.mark.slow
@pytest.mark.parametrize("estimator", ["subset", "ce"])
def test_rare_event_batches_equal_one_process(cluster, controllers, tmp_path, estimator):
    """Subset-simulation levels (their samples, then each MCMC step of the chains) and
    cross-entropy stages in batches of 4 samples, one task each: the numbers of the same
    batches in one process."""
    from afbl_jax.studies.rare import RareEventConfig, run_rare_event

    c, _ = cluster
    afbl = {"afbl": controllers["afbl"]}
    config = RareEventConfig(
        afbl,
        tmp_path / f"{estimator}_local",
        estimator,
        SHORT,
        seed=3,
        n_cases=8,
        n_per_stage=16,
        p0=0.25,
        max_stages=1,
        search_budget=0,
        batch=4,
    )
    local = run_rare_event(config, echo=None)
    dask = run_rare_event(
        dataclasses.replace(
            config,
            out=tmp_path / f"{estimator}_dask",
            executor=DaskExecutor(c.scheduler_address),
        ),
        echo=None,
    )
    assert dask.pop("executor")["kind"] == "dask"
    if estimator == "subset":  # level 0, then one level of MCMC steps (tasks of 4 chains)
        assert [st["level"] for st in local["controllers"]["afbl"]["stages"]] == [0, 1]
    for entry in (local, dask):
        for e in entry["controllers"].values():
            e.pop("seconds")
    assert dask == local
    assert _bytes(config.out) == _bytes(tmp_path / f"{estimator}_dask")


@pytest.mark.slow
def test_cmaes_population_groups_equal_one_call(cluster):
    """A CMA-ES generation whose population is split into groups of candidates, one task
    each, gives the one call's objective values and so the same run."""
    from afbl_jax.studies.tuning import ObjectiveConfig, TuneConfig, Tuner

    c, _ = cluster
    config = TuneConfig(
        controller="fbl",
        objective=ObjectiveConfig(objective="nominal", rtol=1e-5, atol=1e-7),
        method="cmaes",
        population=4,
        steps=1,
        checkpoint_every=0,
    )
    local = Tuner(config).run(progress=False, log=lambda *a: None)
    tuner = Tuner(config, executor=DaskExecutor(c.scheduler_address))
    dask = tuner.run(progress=False, log=lambda *a: None)
    assert tuner.executor_record["kind"] == "dask"
    for a, b in zip(local.history, dask.history, strict=True):
        a, b = dict(a), dict(b)
        a.pop("time_s"), b.pop("time_s")
        assert a == b


def test_population_groups_keep_ensemble_groups_whole():
    from afbl_jax.studies.tuning._optimize import population_groups

    assert population_groups(11, 64, 2) == [(0, 5), (5, 11)]
    assert population_groups(11, 64, 1) == [(0, 11)]
    assert population_groups(3, 64, 8) == [(0, 1), (1, 2), (2, 3)]
    # 2 cases per candidate: boundaries at even candidates (4 cases per ensemble group)
    assert population_groups(7, 2, 3) == [(0, 2), (2, 4), (4, 7)]
    assert population_groups(11, 3, 2) == [(0, 4), (4, 11)]  # 3 cases: every 4th candidate
    for p, n, s in ((11, 64, 2), (7, 2, 3), (11, 3, 2), (9, 6, 4)):
        groups = population_groups(p, n, s)
        assert groups[0][0] == 0 and groups[-1][1] == p and len(groups) <= s
        assert all(a * n % 4 == 0 for a, _ in groups)


def test_map_batches_keeps_order_and_batches(cluster):
    c, _ = cluster
    x = np.arange(10.0).reshape(10, 1)
    with LocalExecutor().session() as s:
        assert map_batches(s, np.ravel, x, 3).tolist() == list(range(10))
    with DaskExecutor(c.scheduler_address).session() as s:
        assert map_batches(s, np.ravel, x, 3).tolist() == list(range(10))
        assert s.map(len, [x[:3], x[3:]]) == [3, 7]


def test_unanswered_scheduler_is_one_line_exit_2(tmp_path, capsys):
    import dask

    out = tmp_path / "never"
    with dask.config.set({"distributed.comm.timeouts.connect": "1s"}):
        rc = cli_main(
            ["montecarlo", "--cases", "8", "--scheduler", "tcp://127.0.0.1:9", "--out", str(out)]
        )
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no Dask scheduler answered at tcp://127.0.0.1:9" in err[0]
    assert not out.exists()


def test_worker_without_the_package_is_one_line_exit_2(tmp_path, capsys):
    """A worker started in an environment whose afbl_jax cannot be imported."""
    fake = tmp_path / "site" / "afbl_jax"
    fake.mkdir(parents=True)
    (fake / "__init__.py").write_text("raise ImportError('afbl_jax is not installed here')\n")
    with distributed.LocalCluster(
        n_workers=0, processes=False, protocol="tcp", dashboard_address=":0", silence_logs=50
    ) as c:
        env = {**os.environ, "PYTHONPATH": str(fake.parent)}
        worker = subprocess.Popen(
            [sys.executable, "-m", "distributed.cli.dask_worker", c.scheduler_address]
            + ["--nthreads", "1", "--no-dashboard", "--no-nanny"],
            env=env,
            cwd=tmp_path,  # not the source tree, whose afbl_jax `python -m` would find first
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        try:
            with distributed.Client(c, set_as_default=False) as client:
                client.wait_for_workers(1, timeout=60)
            out = tmp_path / "never"
            argv = ["montecarlo", "--cases", "8", "--scheduler", c.scheduler_address]
            rc = cli_main([*argv, "--out", str(out)])
        finally:
            worker.kill()
            worker.wait()
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "could not set up afbl-jax" in err[0] and "afbl_jax is not installed here" in err[0]
    assert not out.exists()


@pytest.mark.parametrize(
    "argv, match",
    [
        (["montecarlo", "--workers", "2", "--scheduler", "tcp://h:1"], "not both"),
        (["montecarlo", "--workers", "0"], "--workers must be >= 1"),
        (["montecarlo", "--scheduler", "nowhere"], r"\[protocol://\]host:port"),
        (
            ["montecarlo", "--workers", "2", "--host-index", "0", "--host-count", "2"],
            "give one or the other",
        ),
        (["tune", "--method", "lbfgs", "--workers", "2"], "use --method cmaes"),
    ],
)
def test_cluster_flags_bad_input(tmp_path, capsys, argv, match):
    import re

    out = tmp_path / "never"
    assert cli_main([*argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and re.search(match, err[0]), err
    assert not out.exists()


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"address": "tcp://h:1", "n_workers": 2}, "leave it None"),
        ({"n_workers": 0}, "n_workers must be an integer >= 1"),
        ({"cpu_devices": 0}, "cpu_devices must be an integer >= 1"),
        ({"retries": -1}, "retries must be an integer >= 0"),
        ({"timeout": 0}, "timeout must be a number of seconds > 0"),
        ({"address": "h"}, "host:port"),
    ],
)
def test_dask_executor_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        DaskExecutor(**kwargs)


def test_one_process_path_never_imports_dask(tmp_path):
    """``import afbl_jax``, the command's parser, the executors' configuration and a whole
    one-process Monte-Carlo run (a stand-in strategy: no solves) leave Dask unimported."""
    code = textwrap.dedent(
        f"""
        import sys
        import numpy as np
        import afbl_jax
        from afbl_jax.cli import build_parser
        from afbl_jax.metrics import METRIC_NAMES
        from afbl_jax.studies import montecarlo as mc
        from afbl_jax.studies.executors import DaskExecutor, LocalExecutor

        build_parser()
        DaskExecutor(n_workers=2)

        def zeros(controller, chunk, settings, devices):
            n = chunk.n_cases
            return {{m: np.zeros(n, int if m in ("status", "solver_steps") else float)
                    for m in METRIC_NAMES}}

        mc.register_strategy("zeros", zeros)
        ctrl = {{"fbl": afbl_jax.make_controller("fbl")}}
        mc.run_montecarlo(ctrl, mc.default_distribution(), 8, 0, {str(tmp_path / "mc")!r},
                          chunk_size=4, strategy="zeros", progress=False,
                          executor=LocalExecutor())
        print([m for m in sys.modules if m.split(".")[0] in ("dask", "distributed",
                                                              "dask_jobqueue")])
        """
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.strip().splitlines()[-1] == "[]"
    assert len(pq.read_table(tmp_path / "mc" / "results.parquet")) == 8


ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / "docs" / "scaling_out.md"


def _snippet(marker: str) -> str:
    return PAGE.read_text().split(f"<!-- {marker} -->")[1].split("```python")[1].split("```")[0]


def test_scaling_out_page_slurm_example_builds_its_job_script(capsys):
    """The page's SLURMCluster block is valid dask-jobqueue (it writes the job script; nothing
    is submitted): one single-threaded worker process per core."""
    pytest.importorskip("dask_jobqueue")
    namespace: dict = {}
    exec(compile(_snippet("slurm-cluster-example"), "scaling_out.md", "exec"), namespace)
    try:
        script = capsys.readouterr().out
        assert "--nthreads 1" in script and "--nworkers 32" in script and "#SBATCH" in script
        assert namespace["cluster"].scheduler_address.startswith("tcp://")
    finally:
        namespace["cluster"].close()


def test_scaling_out_page_shows_the_recorded_measurement():
    """The measurement block of docs/scaling_out.md is the rendering of
    docs/results/dask_scaling.json (never edited by hand)."""
    from afbl_jax.studies.scaling import render_dask_scaling

    doc = json.loads((ROOT / "docs" / "results" / "dask_scaling.json").read_text())
    block = PAGE.read_text().split("<!-- dask-scaling:begin -->\n")[1]
    block = block.split("<!-- dask-scaling:end -->")[0]
    assert block == render_dask_scaling(doc)
    s = doc["summary"]
    assert s["ratio"] == pytest.approx(
        s["dask_simulations_per_second"] / s["one_process_simulations_per_second"]
    )
    assert doc["provenance"]["git_revision"] and doc["provenance"]["machine"]["cores"]


@pytest.mark.slow
def test_dask_scaling_script(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("before\n<!-- dask-scaling:begin -->\nold\n<!-- dask-scaling:end -->\nafter\n")
    out = tmp_path / "scaling.json"
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    r = subprocess.run(
        [sys.executable, str(ROOT / "studies" / "dask_scaling.py"), "--cases", "32"]
        + ["--rounds", "1", "--json", str(out), "--page", str(page)],
        capture_output=True,
        text=True,
        timeout=900,
        env=env,
        cwd=ROOT,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    doc = json.loads(out.read_text())
    assert doc["summary"]["tables_identical"] == [True]
    assert [r["mode"] for r in doc["runs"]] == ["one process", "dask LocalCluster, 2 workers"]
    text = page.read_text()
    assert text.startswith("before\n") and text.endswith("after\n") and "old" not in text


@pytest.mark.slow
def test_scaling_out_page_example_runs(tmp_path, monkeypatch):
    """The LocalCluster example of docs/scaling_out.md runs as written (smaller)."""
    snippet = _snippet("local-cluster-example")
    snippet = snippet.replace("n_cases=4096", "n_cases=32").replace(
        "chunk_size=1024", "chunk_size=16"
    )
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "__main__"}
    exec(compile(snippet, "scaling_out.md", "exec"), namespace)
    meta = json.loads((tmp_path / "results" / "mc_dask" / "meta.json").read_text())
    assert meta["invocations"][0]["executor"]["local_cluster"] is True
