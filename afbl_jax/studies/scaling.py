"""Dask scaling: the same Monte-Carlo command as one process and on a Dask LocalCluster.

`measure_dask_scaling` runs ``afbl montecarlo --cases N --seed 0 --no-report`` (both
controllers, the default distribution and chunking) alternately as one process (one XLA CPU
device per core) and with ``--workers W`` (a LocalCluster of W worker processes, one thread and
cores / W devices each), each a fresh ``python -m afbl_jax.cli`` process with the compilation
cache as the command keeps it. Per run it reads the run time the command records
(``meta.json``'s ``elapsed_seconds_this_invocation``: sampling, solving and writing the chunks,
for the cluster also starting it and setting JAX up on its workers) and, for the cluster, every
chunk task's start and duration on its worker (``invocations.jsonl``'s ``chunk_tasks``). From
those:

- throughput: simulations (cases x controllers) per second of run time;
- the ratio of the cluster's to the one process's throughput (medians over the rounds);
- the task window: first task start to last task end, and the cluster start-up before it
  (run time minus the window, which includes the first chunk's sampling in the client);
- scheduling overhead per task: the mean gap between the end of a worker's task and the start
  of its next one (sending the result, the client's turn, dispatching the next task);
- idle fraction: the worker time inside the window spent outside any task, 1 - (sum of task
  durations) / (workers x window): the gaps plus waiting at the end for the last chunk.

The tables of the two modes are compared byte for byte. `render_dask_scaling` turns the JSON
into the Markdown block of ``docs/scaling_out.md``.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

from ..io import git_revision, package_versions

CONTROLLERS = 2  # fbl, afbl: the command's default


def _load() -> list[float]:
    try:
        return [float(x) for x in Path("/proc/loadavg").read_text().split()[:3]]
    except OSError:
        return []


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def _one_run(folder: Path, n_cases: int, workers: int | None, echo) -> dict:
    argv = ["montecarlo", "--cases", str(n_cases), "--seed", "0", "--out", str(folder)]
    argv += ["--no-report", "--no-progress"]
    if workers:
        argv += ["--workers", str(workers)]
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    load_before = _load()
    t0 = time.perf_counter()
    r = subprocess.run(
        [sys.executable, "-m", "afbl_jax.cli", *argv], capture_output=True, text=True, env=env
    )
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        raise RuntimeError(f"afbl {' '.join(argv)} failed: {r.stderr[-2000:]}")
    meta = json.loads((folder / "meta.json").read_text())
    runs = float(meta["elapsed_seconds_this_invocation"])
    entry = {
        "mode": f"dask LocalCluster, {workers} workers" if workers else "one process",
        "command": "afbl " + " ".join(argv),
        "command_seconds": wall,
        "run_seconds": runs,
        "simulations_per_second": n_cases * CONTROLLERS / runs,
        "load_before": load_before,
        "load_after": _load(),
    }
    if workers:
        inv = meta["invocations"][-1]
        tasks = inv["chunk_tasks"]
        starts = [t[0] for t in tasks.values()]
        ends = [t[0] + t[1] for t in tasks.values()]
        busy = sum(t[1] for t in tasks.values())
        window = max(ends) - min(starts)
        gaps = []
        for chunks in inv["chunks_by_worker"].values():
            spans = sorted(tasks[str(c)] for c in chunks)
            gaps += [b[0] - (a[0] + a[1]) for a, b in zip(spans[:-1], spans[1:], strict=True)]
        entry.update(
            {
                "workers": inv["executor"]["workers"],
                "chunks_by_worker": inv["chunks_by_worker"],
                "tasks": len(tasks),
                "task_seconds": {c: tasks[c][1] for c in sorted(tasks, key=int)},
                "task_window_seconds": window,
                "startup_seconds": runs - window,
                "overhead_per_task_seconds": statistics.mean(gaps) if gaps else None,
                "idle_fraction": 1 - busy / (workers * window),
                "window_simulations_per_second": n_cases * CONTROLLERS / window,
            }
        )
    echo(
        f"{entry['mode']}: runs {runs:.1f} s ({entry['simulations_per_second']:.1f} sim/s), "
        f"command {wall:.1f} s, load {load_before}"
    )
    return entry


def measure_dask_scaling(
    out: str | Path, n_cases: int = 4096, workers: int = 2, rounds: int = 2, echo=print
) -> dict:
    """Run the comparison (module docstring) ``rounds`` times, alternating the modes, into
    folders under ``out``; returns the JSON document (provenance, every run, the summary)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    load_at_start = _load()
    runs = []
    identical = []
    for k in range(rounds):
        one = _one_run(out / f"one_process_{k}", n_cases, None, echo)
        dask = _one_run(out / f"dask_{k}", n_cases, workers, echo)
        same = (out / f"one_process_{k}" / "results.parquet").read_bytes() == (
            out / f"dask_{k}" / "results.parquet"
        ).read_bytes()
        identical.append(same)
        runs += [{**one, "round": k}, {**dask, "round": k}]
    # with several rounds the first fills the compilation cache: the summary takes the others
    warm = [r for r in runs if r["round"] > 0 or rounds == 1]
    one_tp = statistics.median(r["simulations_per_second"] for r in warm if "tasks" not in r)
    dask_runs = [r for r in warm if "tasks" in r]
    dask_tp = statistics.median(r["simulations_per_second"] for r in dask_runs)
    window_tp = statistics.median(r["window_simulations_per_second"] for r in dask_runs)
    loads = [x for r in runs for x in (r["load_before"][:1] + r["load_after"][:1])]
    return {
        "what": f"afbl montecarlo, {n_cases} cases x {CONTROLLERS} controllers: one process "
        f"(one XLA CPU device per core) against a Dask LocalCluster of {workers} worker "
        f"processes (one thread, cores / {workers} devices each)",
        "provenance": {
            "command": f"python studies/dask_scaling.py --cases {n_cases} --workers {workers} "
            f"--rounds {rounds}",
            "git_revision": git_revision(),
            "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            "machine": {
                "cpu": _cpu_model(),
                "cores": os.cpu_count(),
                "platform": platform.platform(),
            },
            "versions": {**package_versions(), **_dask_versions()},
            "load_average_at_start": load_at_start,
            "load_average_1min_range": [min(loads), max(loads)] if loads else None,
            "busy": bool(load_at_start) and load_at_start[0] > 0.5,
        },
        "runs": runs,
        "summary": {
            "one_process_simulations_per_second": one_tp,
            "dask_simulations_per_second": dask_tp,
            "ratio": dask_tp / one_tp,
            "ratio_task_window": window_tp / one_tp,
            "target_ratio": 0.85,
            "rounds_in_summary": sorted({r["round"] for r in warm}),
            "overhead_per_task_seconds": _median_or_none(
                r["overhead_per_task_seconds"] for r in dask_runs
            ),
            "idle_fraction": statistics.median(r["idle_fraction"] for r in dask_runs),
            "startup_seconds": statistics.median(r["startup_seconds"] for r in dask_runs),
            "tables_identical": identical,
        },
    }


def _median_or_none(values):
    values = [v for v in values if v is not None]
    return statistics.median(values) if values else None


def _dask_versions() -> dict:
    import importlib.metadata

    out = {}
    for name in ("dask", "distributed"):
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out


def render_dask_scaling(doc: dict) -> str:
    """The Markdown block of ``docs/scaling_out.md`` for a `measure_dask_scaling` document."""
    s, p = doc["summary"], doc["provenance"]
    lo, hi = p["load_average_1min_range"] or (float("nan"), float("nan"))
    start = p["load_average_at_start"][0] if p["load_average_at_start"] else float("nan")
    busy = (
        f"the machine was busy (other jobs: load average {start:.2f} before the first run), so "
        "these numbers are provisional"
        if p["busy"]
        else f"the machine was quiet before the first run (load average {start:.2f})"
    )
    lines = [
        f"Measured with `{p['command']}` at git revision `{p['git_revision'][:12]}` on "
        f"{p['date'][:10]} ({p['machine']['cpu']}, {p['machine']['cores']} cores; 1-minute "
        f"load average {lo:.2f}-{hi:.2f} during the runs; {busy}): {doc['what']}.",
        "",
        "| round | mode | run time [s] | simulations / s | tasks | task window [s] | "
        "gap between tasks [s] | idle |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in doc["runs"]:
        dask = "tasks" in r
        lines.append(
            f"| {r['round']} | {r['mode']} | {r['run_seconds']:.1f} | "
            f"{r['simulations_per_second']:.1f} | {r['tasks'] if dask else '-'} | "
            + (
                f"{r['task_window_seconds']:.1f} | {_num(r['overhead_per_task_seconds'])} | "
                f"{100 * r['idle_fraction']:.0f} % |"
                if dask
                else "- | - | - |"
            )
        )
    met = "met" if s["ratio"] >= s["target_ratio"] else "missed"
    same = "byte-identical" if all(s["tables_identical"]) else "not byte-identical"
    rounds = ", ".join(str(k) for k in s["rounds_in_summary"])
    lines += [
        "",
        f"Median throughput (round{'s' if len(s['rounds_in_summary']) > 1 else ''} {rounds}; "
        "a first round fills the compilation cache): "
        f"{s['dask_simulations_per_second']:.1f} simulations/s on the cluster "
        f"against {s['one_process_simulations_per_second']:.1f} in one process, a ratio of "
        f"**{s['ratio']:.2f}** (target {s['target_ratio']:.2f}: {met}); "
        f"{s['ratio_task_window']:.2f} counting only the window in which the workers ran tasks "
        f"(the cluster's start-up took {s['startup_seconds']:.1f} s of each run). Scheduling "
        f"overhead: {_num(s['overhead_per_task_seconds'])} s between a worker's tasks; the "
        f"workers were idle {100 * s['idle_fraction']:.0f} % of the task window (the gaps and "
        f"the wait for the last chunk). The two modes' `results.parquet` were {same}.",
    ]
    return "\n".join(lines) + "\n"


def _num(x) -> str:
    return "-" if x is None else f"{x:.2f}"
