"""The Monte-Carlo study: run (or resume) the cases, then write meta.json, report.md/html,
summary.json and print the terminal summary (`run_study`); join the folders of a multi-host run
(`merge_study`)."""

from __future__ import annotations

import importlib.metadata
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

from ...io import FileLock, atomic_write_text, controller_from_dict, run_metadata, table_columns
from ...model import AbstractController
from ..executors import Executor
from ._distribution import Distribution, default_distribution
from ._report import format_summary, replay_worst, summarize, summary_json, write_report
from ._runner import FOLDER_LOCK, SolverSettings, merge_results, read_invocations, run_montecarlo


@dataclass(frozen=True)
class StudyConfig:
    """A Monte-Carlo study (`run_study`).

    Attributes:
        controllers: name -> controller (paired: every controller flies the same cases).
        out: output folder (created; running the same study there again resumes).
        n_cases, seed: the cases (case i from ``fold_in(PRNGKey(seed), i)``).
        distribution: the case distribution (default `DEFAULT_DISTRIBUTION`).
        chunk_size: cases per compiled chunk and per chunk file (None: 1024 on CPU devices,
            16384 on an accelerator).
        strategy: how a chunk is solved (None/"auto": `DEFAULT_STRATEGY`).
        settings: solver settings (None: the strategy's defaults).
        report: write report.md/html and figures; progress: show a progress bar.
        host_index, host_count: this host's share of a multi-host run.
        executor: where the chunks are computed (None: this process; a `DaskExecutor`: tasks
            of a Dask cluster, see `run_montecarlo`).
    """

    controllers: dict[str, AbstractController]
    out: Path
    n_cases: int = 4096
    seed: int = 0
    distribution: Distribution = field(default_factory=default_distribution)
    chunk_size: int | None = None
    strategy: str | None = None
    settings: SolverSettings | None = None
    report: bool = True
    progress: bool = True
    host_index: int = 0
    host_count: int = 1
    executor: Executor | None = None


def run_study(config: StudyConfig, echo=print) -> dict | None:
    """Run (or resume) the study into ``config.out`` and write every output; returns the
    summary. With ``host_count > 1`` this host's shard is run and written (results.parquet holds
    only its rows, meta.json its provenance) and None is returned: `merge_study` makes the
    report."""
    c = config
    out = Path(c.out)
    t_start = time.perf_counter()
    table = run_montecarlo(
        c.controllers,
        c.distribution,
        c.n_cases,
        c.seed,
        out,
        chunk_size=c.chunk_size,
        strategy=c.strategy,
        settings=c.settings,
        progress=c.progress,
        host_index=c.host_index,
        host_count=c.host_count,
        executor=c.executor,
    )
    elapsed = time.perf_counter() - t_start
    if c.host_count > 1:
        with FileLock(out / FOLDER_LOCK):
            _write_meta(out, elapsed)
        if echo is not None:
            echo(
                f"host {c.host_index} of {c.host_count}: {table.num_rows} rows in {out} "
                f"({elapsed:.1f} s); when every host is done: afbl merge --out DIR "
                "<the hosts' folders>"
            )
        return None
    return _finish(
        out,
        table,
        c.controllers,
        c.distribution,
        c.seed,
        report=c.report,
        echo=echo,
        elapsed=elapsed,
    )


def merge_study(
    shards: list[str | Path], out: str | Path, *, report: bool = True, echo=print
) -> dict:
    """Join a multi-host run's folders into ``out`` (`merge_results`) and write the report and
    summary as a one-host run would; returns the summary."""
    t_start = time.perf_counter()
    table, config = merge_results(shards, out)
    controllers = {
        name: controller_from_dict(g, source=f"{shards[0]}/run.json")
        for name, g in config["controllers"].items()
    }
    distribution = Distribution.from_dict(config["distribution"])
    return _finish(
        Path(out),
        table,
        controllers,
        distribution,
        int(config["seed"]),
        report=report,
        echo=echo,
        elapsed=time.perf_counter() - t_start,
    )


def _write_meta(out: Path, elapsed: float) -> dict:
    config = json.loads((out / "run.json").read_text())
    meta = run_metadata(config)
    for extra in ("pyarrow", "tqdm"):
        try:
            meta["versions"][extra] = importlib.metadata.version(extra)
        except importlib.metadata.PackageNotFoundError:
            meta["versions"][extra] = "not installed"
    meta["elapsed_seconds_this_invocation"] = elapsed
    meta["results_file"] = "results.parquet"
    meta["invocations"] = read_invocations(out)
    atomic_write_text(json.dumps(meta, indent=2) + "\n", out / "meta.json")
    return meta


def _finish(out: Path, table, controllers, distribution, seed, *, report, echo, elapsed) -> dict:
    t_report = time.perf_counter()
    cols = table_columns(table)
    summary = summarize(cols)
    # runs sharing the folder write their (equal) reports one after the other
    with FileLock(out / FOLDER_LOCK):
        meta = _write_meta(out, elapsed)
        settings = SolverSettings(**meta["config"]["settings"])
        n_cases = int(meta["config"]["n_cases"])
        if report:
            replays = replay_worst(
                cols,
                controllers,
                distribution,
                seed,
                k=min(5, n_cases),
                settings=settings,
                chunk_size=int(meta["config"]["chunk_size"]),
            )
            write_report(out, cols, summary, distribution, meta, replays)
        else:
            atomic_write_text(summary_json(summary), out / "summary.json")
    if echo is not None:
        echo(format_summary(summary))
        echo(
            f"\nwrote {out}/results.parquet, meta.json, summary.json"
            + (", report.md, report.html" if report else "")
            + f" (runs {elapsed:.1f} s, "
            + ("report" if report else "summary")
            + f" {time.perf_counter() - t_report:.1f} s)"
        )
    return summary
