"""The Monte-Carlo study: run (or resume) the cases, then write meta.json, report.md/html,
summary.json and print the terminal summary (`run_study`); join the folders of a multi-host run
(`merge_study`).

Where the seconds go: `run_study` prints, and records in meta.json as ``phases_seconds``, the
wall time of each phase of the invocation (`PHASES`): ``startup`` (the process's start-up,
imports and argument checks before the study, when the caller gives it: the ``afbl`` command
does), ``compilation`` (JAX tracing, lowering and XLA compilation, or loading the compiled
program from the persistent cache, or loading a compiled executable without tracing
(`afbl_jax.sim.CachedJit`), in this process: the union of JAX's ``/jax/core/compile/*``
event spans and the executable loads), ``runs`` (sampling, solving and writing the chunks, less
their compilation) and ``report`` (summary, replays of the worst cases, report files, less
their compilation); ``total`` is their sum. With a Dask executor the workers compile, inside
``runs``.
"""

from __future__ import annotations

import contextlib
import importlib.metadata
import json
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import jax

from ...io import FileLock, atomic_write_text, controller_from_dict, run_metadata, table_columns
from ...model import AbstractController
from ...sim import LOAD_EVENT as EXECUTABLE_LOAD_EVENT
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
        n_cases, seed: the cases (case i from ``fold_in(PRNGKey(seed), i)``), drawn in
            float64 when ``jax_enable_x64`` is on (as the ``afbl`` command runs), else in
            float32 (other cases; meta.json records which).
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


PHASES = ("startup", "compilation", "runs", "report")
"""Phases of an invocation in ``phases_seconds`` (see the module docstring), then ``total``."""

_BACKEND_COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"
_COMPILE_EVENTS = (
    "/jax/core/compile/jaxpr_trace_duration",
    "/jax/core/compile/jaxpr_to_mlir_module_duration",
    _BACKEND_COMPILE_EVENT,
    EXECUTABLE_LOAD_EVENT,
)
"""JAX's events of tracing, lowering and XLA compilation (or loading from the cache), and the
loads of compiled executables (`afbl_jax.sim.CachedJit`)."""


class CompileClock:
    """Seconds JAX spends tracing, lowering and compiling (or loading compiled programs from the
    persistent cache) while `measure` is active: the union of the `_COMPILE_EVENTS` spans,
    so nested or overlapping events count once. ``programs``: XLA compilations or cache loads
    and executables loaded; ``cache_hits``: those loaded from the persistent compilation
    cache; ``executables_loaded``: those loaded from the executable cache (no tracing)."""

    def __init__(self) -> None:
        self._spans: list[tuple[float, float]] = []
        self._lock = threading.Lock()
        self.programs = 0
        self.cache_hits = 0
        self.executables_loaded = 0

    def record_span(self, event: str, start: float, end: float, **kwargs) -> None:
        """Listener of `jax.monitoring` time spans: keeps the span [start, end] [s] of a
        compilation event (other events are ignored)."""
        if event in _COMPILE_EVENTS:
            with self._lock:
                self._spans.append((start, end))
                loaded = event == EXECUTABLE_LOAD_EVENT
                self.programs += loaded or event == _BACKEND_COMPILE_EVENT
                self.executables_loaded += loaded

    def record_event(self, event: str, **kwargs) -> None:
        """Listener of `jax.monitoring` events: counts the persistent-cache hits."""
        if event == "/jax/compilation_cache/cache_hits":
            with self._lock:
                self.cache_hits += 1

    @contextlib.contextmanager
    def measure(self) -> Iterator[CompileClock]:
        jax.monitoring.register_event_time_span_listener(self.record_span)
        jax.monitoring.register_event_listener(self.record_event)
        try:
            yield self
        finally:
            jax.monitoring.unregister_event_time_span_listener(self.record_span)
            jax.monitoring.unregister_event_listener(self.record_event)

    @property
    def seconds(self) -> float:
        """Length of the union of the recorded spans [s]."""
        total, end = 0.0, float("-inf")
        with self._lock:
            spans = sorted(self._spans)
        for a, b in spans:
            if b > end:
                total += b - max(a, end)
                end = b
        return total


def phase_seconds(
    startup: float | None, compile_runs: float, runs: float, compile_report: float, report: float
) -> dict[str, float | None]:
    """``phases_seconds`` of meta.json from the wall time of the runs and of the report and the
    compilation inside each (``startup`` None: not measured, left out of ``total``)."""
    phases = {
        "startup": startup,
        "compilation": compile_runs + compile_report,
        "runs": max(0.0, runs - compile_runs),
        "report": max(0.0, report - compile_report),
    }
    phases["total"] = sum(v for v in phases.values() if v is not None)
    return phases


def format_phases(
    phases: dict, programs: int = 0, cache_hits: int = 0, executables_loaded: int = 0
) -> str:
    """One line: the seconds of each phase (`PHASES`) and the total."""
    words = {
        "startup": "start-up and imports",
        "compilation": "tracing and compilation",
        "runs": "runs",
        "report": "report",
    }
    parts = []
    for name in PHASES:
        if phases.get(name) is None:
            continue
        part = f"{words[name]} {phases[name]:.1f} s"
        if name == "compilation" and programs:
            loaded = f", {executables_loaded} loaded compiled" if executables_loaded else ""
            part += f" ({programs} programs, {cache_hits} from the compilation cache{loaded})"
        parts.append(part)
    return "time: " + ", ".join(parts) + f"; total {phases['total']:.1f} s"


def run_study(
    config: StudyConfig, echo=print, *, startup_seconds: float | None = None
) -> dict | None:
    """Run (or resume) the study into ``config.out`` and write every output; returns the
    summary. With ``host_count > 1`` this host's shard is run and written (results.parquet holds
    only its rows, meta.json its provenance) and None is returned: `merge_study` makes the
    report. ``startup_seconds``: the caller's start-up before this call, recorded as the
    ``startup`` phase (`PHASES`; None: not recorded)."""
    c = config
    out = Path(c.out)
    clock = CompileClock()
    t_start = time.perf_counter()
    with clock.measure():
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
    compile_runs = clock.seconds
    if c.host_count > 1:
        phases = phase_seconds(startup_seconds, compile_runs, elapsed, 0.0, 0.0)
        with FileLock(out / FOLDER_LOCK):
            _write_meta(out, elapsed, phases)
        if echo is not None:
            echo(
                f"host {c.host_index} of {c.host_count}: {table.num_rows} rows in {out} "
                f"({elapsed:.1f} s); when every host is done: afbl merge --out DIR "
                "<the hosts' folders>"
            )
            echo(format_phases(phases, clock.programs, clock.cache_hits, clock.executables_loaded))
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
        startup=startup_seconds,
        compile_runs=compile_runs,
        clock=clock,
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


def _write_meta(out: Path, elapsed: float, phases: dict | None = None) -> dict:
    config = json.loads((out / "run.json").read_text())
    meta = run_metadata(config)
    for extra in ("pyarrow", "tqdm"):
        try:
            meta["versions"][extra] = importlib.metadata.version(extra)
        except importlib.metadata.PackageNotFoundError:
            meta["versions"][extra] = "not installed"
    meta["elapsed_seconds_this_invocation"] = elapsed
    if phases is not None:
        meta["phases_seconds"] = phases
    meta["results_file"] = "results.parquet"
    meta["invocations"] = read_invocations(out)
    atomic_write_text(json.dumps(meta, indent=2) + "\n", out / "meta.json")
    return meta


def _finish(
    out: Path,
    table,
    controllers,
    distribution,
    seed,
    *,
    report,
    echo,
    elapsed,
    startup=None,
    compile_runs=0.0,
    clock=None,
) -> dict:
    clock = clock or CompileClock()
    compiled_before = clock.seconds
    t_report = time.perf_counter()
    with clock.measure():
        summary, meta = _summarize_and_report(
            out, table, controllers, distribution, seed, report, elapsed
        )
    report_seconds = time.perf_counter() - t_report
    phases = phase_seconds(
        startup, compile_runs, elapsed, clock.seconds - compiled_before, report_seconds
    )
    meta["phases_seconds"] = phases
    with FileLock(out / FOLDER_LOCK):
        # another run into the folder may have finished since the report read the log
        meta["invocations"] = read_invocations(out)
        atomic_write_text(json.dumps(meta, indent=2) + "\n", out / "meta.json")
    if echo is not None:
        echo(format_summary(summary))
        echo(
            f"\nwrote {out}/results.parquet, meta.json, summary.json"
            + (", report.md, report.html" if report else "")
        )
        echo(format_phases(phases, clock.programs, clock.cache_hits, clock.executables_loaded))
    return summary


def _summarize_and_report(out, table, controllers, distribution, seed, report, elapsed):
    cols = table_columns(table)
    summary = summarize(cols)
    # runs sharing the folder write their (equal) reports one after the other
    with FileLock(out / FOLDER_LOCK):
        meta = _write_meta(out, elapsed)
        settings = SolverSettings(**meta["config"]["settings"])
        n_cases = int(meta["config"]["n_cases"])
        if report:
            # the replays (compiled solves, which release the GIL) run while the other
            # figures are drawn
            with ThreadPoolExecutor(max_workers=1) as pool:
                replays = pool.submit(
                    replay_worst,
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
    return summary, meta
