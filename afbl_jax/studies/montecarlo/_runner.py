"""The Monte-Carlo runner: chunked, resumable, paired over controllers, optionally sharded.

For every chunk of ``chunk_size`` cases (the last one filled up with the following case
indices, results dropped, so every chunk has the same shape; a run of one chunk is simulated at
the smallest of a few fixed sizes that holds its cases, `simulated_size`) and every controller,
a *strategy*
maps ``(controller, chunk, settings, devices) -> per-case metrics`` (`METRIC_NAMES`). Built in
(`afbl_jax.simulate_batch` underneath, case axis split over ``devices``; every strategy runs
every closed loop, including the distribution's ``[unmodeled]`` section):

- ``"ensemble_f32"`` (the default; `DEFAULT_STRATEGY`): float32, groups of
  `ensemble_group_size` consecutive cases (16 with a continuous controller where the chunk is a
  multiple of devices x 16, else `GROUP_SIZE` = 4) each solved as one ODE system (shared steps,
  every case meeting its own tolerance), the groups vectorised, each device working through its
  cases `INNER_CHUNK` at a time; default tolerances rtol 3e-6, atol 3e-7 (float32 cannot honour
  1e-6 / 1e-8). The accuracy bound it is held to: max relative ISE error <= 1e-3 against a
  tight float64 reference (`afbl bench` reports it; the tests check it case by case). The
  tolerance is tighter than the benchmark's ``ensemble_f32`` rows (rtol 1e-5, atol 1e-6)
  because cases that drive the rotors into their limits, where the clipping kinks meet
  float32 round-off, need it to meet the bound. The lean integrator advances a float32 state
  over the two ulps of time skipped at each jump time (`afbl_jax.sim.lean_loop`,
  ``bridge_jumps``), without which small tracking errors (AFBL's altitude ISE) exceed the
  bound.
- ``"ensemble"``: the same in float64 (default tolerances rtol 1e-6, atol 1e-8).
- ``"vmap"``: ``jax.vmap`` over `afbl_jax.simulate` in float64 (every case its own step
  sequence; results independent of how cases are chunked).

Ensemble results depend (within the tolerance) on which cases share a group (fixed blocks of
`ensemble_group_size` case indices), not on the chunking among chunk sizes with the same group
size (with a continuous controller every multiple of devices x 16, which `run_montecarlo`
makes of a chunk size that is a multiple of 16; with a digital one every multiple of devices x
`GROUP_SIZE`): chunk sizes with the same groups give bitwise the same results (tested).
Resuming is exact (same chunks). With digital
control the cases of a group share their sample instants; the sampler draws one control rate
per group of `GROUP_SIZE` case indices (`afbl_jax.studies.montecarlo.sample_cases`).
Other strategies can be added with `register_strategy`. Metric definitions:
`afbl_jax.metrics`.
"""

from __future__ import annotations

import contextlib
import datetime
import json
import os
import socket
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import jax
import numpy as np

from ..._validation import check_seed
from ...io import (
    FileLock,
    atomic_write_bytes,
    atomic_write_table,
    atomic_write_text,
    gains_to_dict,
    git_revision,
    read_table,
)
from ...metrics import FAILURE_CAUSES, METRIC_NAMES, metric_columns
from ...model import AbstractController
from ...sim import STATUS_NAMES, STATUS_OUTSIDE_ENVELOPE, simulate_batch
from ..executors import Executor, LocalExecutor
from ._distribution import Distribution
from ._sampler import (
    GROUP_SIZE,
    INPUT_COLUMNS,
    MAX_CASE_INDEX,
    UNMODELED_COLUMNS,
    CaseBatch,
    sample_cases,
)

RESULTS_FILE = "results.parquet"


DEFAULT_STRATEGY = "ensemble_f32"
CONTINUOUS_GROUP_SIZE = 16
"""Cases per ensemble group with a continuous controller on CPU devices (a multiple of
`GROUP_SIZE`). Larger groups take more shared steps (the jump times of every case, the
strictest case's error) for less per-step work per case (the turbulence lines' cos/sin of
omega_k t are computed once per group). Accelerators keep `GROUP_SIZE`: there a solve's time
follows its slowest group's steps, not the work per step."""


def ensemble_group_size(
    digital: bool, n_cases: int | None = None, n_devices: int = 1, platform: str = "cpu"
) -> int:
    """Cases per ensemble group of the built-in ensemble strategies for ``n_cases`` cases
    split over ``n_devices`` devices of ``platform``: `CONTINUOUS_GROUP_SIZE` with a
    continuous controller on CPU devices where ``n_cases`` (None: any) is a multiple of
    devices x `CONTINUOUS_GROUP_SIZE`, else `GROUP_SIZE` (always with a digital controller: a
    group shares one sample clock, and the sampler draws one control rate per `GROUP_SIZE`
    cases)."""
    unit = CONTINUOUS_GROUP_SIZE * int(n_devices)
    whole = n_cases is None or int(n_cases) % unit == 0
    cpu = platform == "cpu"
    return CONTINUOUS_GROUP_SIZE if cpu and not digital and whole else GROUP_SIZE


def distribution_is_digital(distribution: Distribution) -> bool:
    """Whether the distribution's cases have a digital controller (its ``[unmodeled]``
    section enabled, with unmodeled.control_rate > 0 Hz)."""
    unmodeled = distribution.spec["unmodeled"]
    return bool(unmodeled["enabled"]) and unmodeled["control_rate"][1] > 0


INNER_CHUNK = 128
"""Cases per CPU device solved at a time inside one compiled call (keeps the working set in
cache); accelerators solve all their cases at once (`device_chunk`)."""
ACCELERATOR_CHUNK_SIZE = 16384
"""Default cases per runner chunk on an accelerator (`default_chunk_size`)."""
CPU_CHUNK_SIZE = 1024
"""Default cases per runner chunk on CPU devices: several `INNER_CHUNK` per device, so that the
lean loop's work queue hands a finished group's lane to the next group (with one
`INNER_CHUNK` per device there is nothing to queue); the results do not depend on it."""


def _platform(devices=None) -> str:
    return (tuple(devices) if devices else tuple(jax.local_devices()))[0].platform


def device_chunk(chunk_size: int | None, devices=None) -> int | None:
    """Cases each device solves at a time for a strategy whose CPU setting is ``chunk_size``:
    that on CPU devices (a working set that stays in cache), None (all of the device's cases
    at once) on accelerators, where a step of a few hundred cases leaves the GPU idle (a GPU
    step costs about the same for a few hundred cases as for tens of thousands)."""
    return chunk_size if _platform(devices) == "cpu" else None


def default_chunk_size(devices=None) -> int:
    """Cases per runner chunk (and chunk file) when none is given: `CPU_CHUNK_SIZE` on CPU
    devices, `ACCELERATOR_CHUNK_SIZE` on accelerators (thousands of cases per compiled call
    keep a GPU busy)."""
    return CPU_CHUNK_SIZE if _platform(devices) == "cpu" else ACCELERATOR_CHUNK_SIZE


STRATEGY_TOLERANCES = {"ensemble_f32": (3e-6, 3e-7), "ensemble": (1e-6, 1e-8), "vmap": (1e-6, 1e-8)}
"""Default (rtol, atol) per strategy (used when `SolverSettings` leaves them None)."""


@dataclass(frozen=True)
class SolverSettings:
    """Solver configuration of a Monte-Carlo run (static: changing it recompiles).

    ``rtol``/``atol`` None: the strategy's defaults (`STRATEGY_TOLERANCES`, see
    `with_tolerances_for`)."""

    solver: str = "tsit5"
    rtol: float | None = None
    atol: float | None = None
    n_save: int = 401
    max_steps: int = 16384

    def with_tolerances_for(self, strategy: str) -> SolverSettings:
        """These settings with unset tolerances filled in from ``strategy``'s defaults."""
        rtol, atol = STRATEGY_TOLERANCES.get(strategy, STRATEGY_TOLERANCES["vmap"])
        return replace(
            self,
            rtol=rtol if self.rtol is None else self.rtol,
            atol=atol if self.atol is None else self.atol,
        )

    def __post_init__(self):
        for name in ("rtol", "atol"):
            value = getattr(self, name)
            if value is not None and not (0 < value < float("inf")):
                raise ValueError(
                    f"{name} must be a finite number > 0 (or None: the strategy's default), "
                    f"got {value}."
                )
        if int(self.n_save) < 2 or int(self.max_steps) < 1:
            raise ValueError(
                f"n_save must be >= 2 and max_steps >= 1, got {self.n_save}, {self.max_steps}."
            )


BATCH_SETTINGS = {
    "ensemble_f32": {
        "strategy": "ensemble",
        "dtype": "float32",
        "group_size": CONTINUOUS_GROUP_SIZE,
        "chunk_size": INNER_CHUNK,
    },
    "ensemble": {
        "strategy": "ensemble",
        "dtype": "float64",
        "group_size": CONTINUOUS_GROUP_SIZE,
        "chunk_size": INNER_CHUNK,
    },
    "vmap": {"strategy": "vmap", "dtype": None, "group_size": None, "chunk_size": INNER_CHUNK},
}
"""`afbl_jax.simulate_batch` settings of the built-in strategies (besides `SolverSettings`);
``dtype`` None: JAX's default float; ensembles with a digital controller run in groups of
`GROUP_SIZE` instead (`ensemble_group_size`)."""


def _batch_strategy(name: str) -> Strategy:
    def run(controller, chunk: CaseBatch, settings: SolverSettings, devices=None):
        kwargs = dict(BATCH_SETTINGS[name])
        kwargs["chunk_size"] = device_chunk(kwargs["chunk_size"], devices)
        if kwargs["group_size"] is not None:
            n_dev = len(devices) if devices else len(jax.local_devices())
            digital = chunk.unmodeled is not None and chunk.unmodeled.digital
            platform = _platform(devices)
            kwargs["group_size"] = ensemble_group_size(digital, chunk.n_cases, n_dev, platform)
        m = simulate_batch(
            controller,
            chunk.scenario,
            chunk.vehicle,
            chunk.model,
            unmodeled=chunk.unmodeled,
            aerodynamics=chunk.aerodynamics,
            position_loop=chunk.position_loop,
            solver=settings.solver,
            rtol=settings.rtol,
            atol=settings.atol,
            max_steps=settings.max_steps,
            n_save=settings.n_save,
            devices=devices,
            **kwargs,
        )
        return metric_columns(m)

    return run


Strategy = Callable[..., dict]
"""``(controller, chunk, settings, devices) -> metrics dict`` (devices: tuple or None)."""
STRATEGIES: dict[str, Strategy] = {name: _batch_strategy(name) for name in BATCH_SETTINGS}
"""Chunk strategies by name (see the module docstring)."""


def register_strategy(name: str, fn: Strategy) -> None:
    """Make ``fn`` available as ``strategy=name`` (and ``--strategy name``); ``fn(controller,
    chunk, settings, devices)`` returns the `METRIC_NAMES` arrays for every case of the chunk,
    including its ``chunk.unmodeled`` settings when they are set."""
    STRATEGIES[name] = fn


def resolve_strategy(strategy: str | None, distribution: Distribution | None = None) -> str:
    """``None``/``"auto"``: `DEFAULT_STRATEGY`; otherwise a name of `STRATEGIES` (checked)."""
    del distribution
    if strategy in (None, "auto"):
        return DEFAULT_STRATEGY
    if strategy not in STRATEGIES:
        raise ValueError(f"unknown strategy {strategy!r}; allowed: auto, {', '.join(STRATEGIES)}.")
    return strategy


def local_devices(shard: bool) -> tuple:
    """All local devices, or only the first one."""
    return tuple(jax.local_devices()) if shard else (jax.local_devices()[0],)


def run_chunk(
    controller: AbstractController,
    chunk: CaseBatch,
    *,
    strategy: str | None = None,
    settings: SolverSettings | None = None,
    shard: bool = False,
) -> dict[str, np.ndarray]:
    """Metrics of every case of ``chunk`` for ``controller`` as NumPy arrays; ``strategy``
    None/"auto": `DEFAULT_STRATEGY`; ``shard``: split the case axis over all local devices (else
    the default device only)."""
    strategy = resolve_strategy(strategy)
    settings = (settings or SolverSettings()).with_tolerances_for(strategy)
    out = STRATEGIES[strategy](controller, chunk, settings, local_devices(shard))
    out = {k: np.asarray(v) for k, v in out.items()}
    return mark_outside_envelope(out, chunk)


def mark_outside_envelope(metrics: dict[str, np.ndarray], chunk: CaseBatch) -> dict:
    """``metrics`` with the status of every case outside the flight envelope (its
    ``envelope_cause`` not 0, decided before simulating) set to ``outside_envelope``, so that
    it is never counted as a controller failure; its simulated metrics stay as they are."""
    cause = chunk.inputs.get("envelope_cause")
    if cause is None:
        return metrics
    outside = np.asarray(cause).reshape(-1) != 0
    status = np.where(outside, STATUS_OUTSIDE_ENVELOPE, np.asarray(metrics["status"]))
    return {**metrics, "status": status.astype(np.asarray(metrics["status"]).dtype)}


def status_label(code) -> np.ndarray:
    """Status codes -> "ok" / "diverged" / "solver_failed"."""
    return np.array([STATUS_NAMES[int(c)] for c in np.asarray(code).reshape(-1)], dtype=object)


def _chunk_table(chunk: CaseBatch, n_valid: int, per_controller: dict[str, dict]):
    import pyarrow as pa

    cols: dict[str, list] = {}
    names = list(per_controller)
    case = np.asarray(chunk.index)[:n_valid]
    rows = len(names) * n_valid
    cols["case"] = np.repeat(case, len(names)).astype(np.int64)
    cols["controller"] = np.tile(np.array(names, dtype=object), n_valid)

    def interleave(arrays):
        return np.stack([a[:n_valid] for a in arrays], axis=1).reshape(rows)

    for name in chunk.input_columns:
        x = np.asarray(chunk.inputs[name])
        cols[name] = interleave([x] * len(names))
    for m in METRIC_NAMES:
        cols[m] = interleave([per_controller[c][m] for c in names])
        if np.issubdtype(cols[m].dtype, np.floating):
            cols[m] = cols[m].astype(np.float64)  # one schema whatever the strategy's dtype
    cols["status"] = status_label(cols["status"])
    for k in ("solver_steps", "turbulence_level", "profile", "delay_samples", "envelope_cause"):
        if k in cols:
            cols[k] = cols[k].astype(np.int64)
    if "failure_cause" in cols:
        cols["failure_cause"] = np.array(
            [FAILURE_CAUSES[int(c)] for c in cols["failure_cause"]], dtype=object
        )
    return pa.table(cols)


@dataclass
class MonteCarloConfig:
    """Everything that determines the results (recorded in meta.json; resume checks it)."""

    n_cases: int
    seed: int
    controllers: dict  # name -> gains dict
    distribution: dict
    chunk_size: int
    strategy: str
    settings: dict
    hosts: list = field(default_factory=lambda: [0, 1])  # [host index, host count]

    def to_dict(self) -> dict:
        return asdict(self)


def config_differences(a: dict, b: dict, prefix: str = "") -> list[str]:
    """Dotted names of the entries in which two configurations (nested dicts) differ."""
    out = []
    for key in sorted(set(a) | set(b), key=str):
        va, vb = a.get(key, _MISSING), b.get(key, _MISSING)
        if isinstance(va, dict) and isinstance(vb, dict):
            out += config_differences(va, vb, f"{prefix}{key}.")
        elif va != vb:
            out.append(f"{prefix}{key}")
    return out


_MISSING = object()


def chunk_file(chunk_dir: Path, c: int) -> Path:
    """Path of chunk ``c``'s results (global chunk numbering, the same on every host)."""
    return chunk_dir / f"chunk_{c:06d}.parquet"


def _chunk_lock(chunk_dir: Path, c: int) -> FileLock:
    """Lock of chunk ``c``: held by the run computing it (so runs sharing a folder split the
    chunks between them); removed once the chunk file exists."""
    return FileLock(chunk_dir / f".chunk_{c:06d}.lock")


FOLDER_LOCK = ".lock"
"""Lock file in a results folder, held while run.json, the invocation log or the report is
written."""


def host_chunks(n_chunks: int, host_index: int, host_count: int) -> range:
    """The chunks host ``host_index`` of ``host_count`` runs: c = host_index (mod host_count)."""
    return range(int(host_index), int(n_chunks), int(host_count))


def chunk_ladder(chunk_size: int, unit: int) -> tuple[int, ...]:
    """The sizes a chunk may be simulated at: ``unit``, 2 ``unit``, 4 ``unit``, ... (below
    ``chunk_size``) and ``chunk_size``. A few fixed sizes, so runs of any length reuse the same
    compiled programs; ``unit`` (devices x `ensemble_group_size`) keeps the ensemble groups
    of the default runs whole."""
    sizes, s = [], int(unit)
    while s < chunk_size:
        sizes.append(s)
        s *= 2
    return (*sizes, int(chunk_size))


def simulated_size(n_valid: int, chunk_size: int, unit: int, n_chunks: int) -> int:
    """Cases simulated for a chunk holding ``n_valid`` cases (its cases first, then the
    following case indices as padding, dropped).

    A run of one chunk (``n_chunks`` 1) takes the smallest size of `chunk_ladder` that holds
    its cases (``--cases 1`` simulates one group per device, not a whole chunk). In a longer run
    every chunk, the last one too, is simulated at ``chunk_size``: compiling a second size per
    controller costs about as much as simulating a whole chunk, more than the padding.
    Depends on the configuration only, so resumed and multi-host runs simulate the same
    chunks."""
    if n_chunks > 1:
        return int(chunk_size)
    return next(s for s in chunk_ladder(chunk_size, unit) if s >= n_valid)


def results_bytes_per_case(n_controllers: int, distribution: Distribution) -> int:
    """A lower bound of the memory one case's rows take in the results table [bytes]: 8 per
    number (case index, inputs, metrics) and per row the two labels' offsets and characters."""
    inputs = len(INPUT_COLUMNS) + (
        len(UNMODELED_COLUMNS) if distribution.spec["unmodeled"]["enabled"] else 0
    )
    numbers = 1 + inputs + len(METRIC_NAMES) - 1  # case + inputs + metrics but status
    labels = 2 * 4 + len("fbl") + len("ok")  # controller and status: offsets + shortest text
    return n_controllers * (8 * numbers + labels)


def physical_memory() -> int | None:
    """This machine's physical memory [bytes] (None where the OS does not say)."""
    try:
        return int(os.sysconf("SC_PHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (AttributeError, ValueError, OSError):
        return None


def _human(n_bytes: float) -> str:
    for unit in ("B", "kB", "MB", "GB", "TB", "PB"):
        if n_bytes < 1000 or unit == "PB":
            return f"{n_bytes:.3g} {unit}"
        n_bytes /= 1000
    raise AssertionError  # unreachable


def check_results_fit(
    n_cases: int,
    n_controllers: int,
    distribution: Distribution,
    host_count: int = 1,
    memory: int | None = None,
) -> None:
    """Raise ValueError when the results table of ``n_cases`` (this host's share of
    ``host_count``) cannot fit in ``memory`` (default: this machine's physical memory): the run
    holds its table in memory at the end, so a run that cannot fit is refused before it starts
    instead of failing after hours."""
    memory = physical_memory() if memory is None else int(memory)
    if memory is None:
        return
    per_case = results_bytes_per_case(n_controllers, distribution)
    share = -(-int(n_cases) // int(host_count))
    if share * per_case > memory:
        fit = memory // per_case * int(host_count)
        hosts = f" on each of {host_count} hosts" if host_count > 1 else ""
        raise ValueError(
            f"{n_cases} cases x {n_controllers} controller(s) need at least "
            f"{_human(share * per_case)} of memory for the results table{hosts}, more than this "
            f"machine's {_human(memory)}; at most {fit} cases fit."
        )


def read_invocations(out: str | Path) -> list[dict]:
    """The invocations of a results folder (``invocations.jsonl``), one dict per invocation:
    its start record with its finish record merged in (``chunks_computed``: chunks this
    invocation simulated; absent if it was interrupted)."""
    log = Path(out) / "invocations.jsonl"
    if not log.exists():
        return []
    entries: list[dict] = []
    by_id: dict = {}
    for line in log.read_text().splitlines():
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            continue  # a line cut short by a crash: provenance only, skip it
        key = record.get("invocation")
        if key is not None and key in by_id and "finished_utc" in record:
            by_id[key].update(record)
        elif "finished_utc" not in record:
            entries.append(record)
            if key is not None:
                by_id[key] = record
    return entries


def _log_invocation(out: Path, record: dict) -> None:
    with open(out / "invocations.jsonl", "a") as fh:
        fh.write(json.dumps(record) + "\n")


def _damaged(path: Path, why: str, fix: str) -> ValueError:
    return ValueError(
        f"{path} is damaged ({why}); it was probably cut short or overwritten: delete it and {fix}."
    )


def _check_chunk(path: Path, rows: int, fix: str) -> None:
    """Refuse a chunk file that is not complete parquet or has the wrong number of rows."""
    import pyarrow.parquet as pq

    try:
        found = pq.read_metadata(path).num_rows
    except Exception as err:  # pyarrow raises ArrowInvalid or a bare OSError for bad footers
        if isinstance(err, OSError) and err.errno is not None:
            raise
        raise _damaged(path, f"not a complete parquet file: {err}", fix) from None
    if found != rows:
        raise _damaged(path, f"{found} rows instead of {rows}", fix)


def _read_chunk(path: Path, rows: int, fix: str):
    """A finished chunk file, refused (saying what to do) when it is not complete parquet or
    does not hold ``rows`` rows."""
    _check_chunk(path, rows, fix)
    try:
        return read_table(path)
    except ValueError as err:
        raise _damaged(path, str(err), fix) from None


RERUN = "re-run the same command (that chunk is recomputed)"


def run_montecarlo(
    controllers: dict[str, AbstractController],
    distribution: Distribution,
    n_cases: int,
    seed: int,
    out: str | Path | None = None,
    *,
    chunk_size: int | None = None,
    strategy: str | None = None,
    settings: SolverSettings | None = None,
    shard: bool | None = None,
    progress: bool = True,
    host_index: int = 0,
    host_count: int = 1,
    executor: Executor | None = None,
):
    """Simulate ``n_cases`` cases for every controller (paired) and return the results table.

    One row per (case, controller): the case's sampled inputs (`INPUT_COLUMNS`) and metrics
    (`METRIC_NAMES`, status as "ok"/"diverged"/"solver_failed"). With ``out``, each finished
    chunk is written to ``out/chunks/`` at once; running the same call again skips finished
    chunks (resume) and the final ``out/results.parquet`` equals an uninterrupted run's. A
    different configuration in an existing ``out`` raises (naming the differing entries)
    instead of mixing runs; so do chunk files that were cut short (with what to do).

    Several processes may run the same call into one ``out`` at once: each chunk is computed by
    the first process that locks it (`FileLock`), the others take its file, and every process
    ends with the same ``results.parquet``. Every invocation is logged in
    ``out/invocations.jsonl`` (`read_invocations`), with the chunks it computed.

    ``strategy``: a name of `STRATEGIES`, or None/"auto" (`resolve_strategy`). Ensemble
    groups are consecutive blocks of `ensemble_group_size` case indices (16 with a continuous
    controller and a chunk size that is a multiple of 16, else 4), so the numbers do not
    depend on the chunk size among chunk sizes that are multiples of 16. With another chunk
    size a run shorter than one chunk may be simulated at a size that takes groups of 16. A
    run of a single chunk is simulated at the smallest size of `chunk_ladder` that holds its cases
    (`simulated_size`); the progress bar counts the run's own cases, never the padding.

    ``chunk_size``: cases per chunk (None: `default_chunk_size`, 1024 on CPU devices, 16384 on
    an accelerator). ``shard``: split each chunk's case axis over all local JAX devices
    (default: when there are several); ``chunk_size`` is then rounded up to a multiple of
    devices x the group size (16 with a continuous controller and a chunk size that is a
    multiple of 16, else `GROUP_SIZE`).

    Several hosts: ``host_index`` i of ``host_count`` P runs only the chunks c = i (mod P)
    (`host_chunks`) and returns / writes only their rows; `merge_results` joins the hosts'
    ``out`` folders into the table of a one-host run.

    ``executor``: where the chunks are computed (None: `LocalExecutor`, this process, chunk
    after chunk). With a `DaskExecutor` each chunk is one task on a worker (the same
    `sample_cases`, `run_chunk` and chunk table, on the worker's own devices), at most twice
    the cluster's task slots in flight; this process writes each finished chunk file (once,
    atomically, with the chunk's lock held meanwhile, as above), so a worker that dies leaves
    no partial chunk and the scheduler gives its chunk to another worker; workers that join
    during the run take chunks too. The invocation log records the cluster (``executor``: the
    scheduler and its workers), which chunks each worker computed (``chunks_by_worker``) and
    each chunk task's start (Unix time) and duration on its worker [s] (``chunk_tasks``).

    Refused before anything is written (ValueError): a results table that cannot fit in this
    machine's memory (`check_results_fit`), seeds outside [0, 2^63 - 1], a Dask scheduler that
    does not answer or a worker that cannot import this package.
    """
    if not controllers:
        raise ValueError("run_montecarlo needs at least one controller.")
    if isinstance(n_cases, bool) or int(n_cases) < 1:
        raise ValueError(f"n_cases must be >= 1, got {n_cases!r}.")
    if chunk_size is None:
        chunk_size = default_chunk_size()
    if isinstance(chunk_size, bool) or int(chunk_size) < 1:
        raise ValueError(f"chunk_size must be >= 1, got {chunk_size!r}.")
    if not (int(host_count) >= 1 and 0 <= int(host_index) < int(host_count)):
        raise ValueError(
            f"need 0 <= host_index < host_count, got host_index {host_index}, "
            f"host_count {host_count}."
        )
    if int(n_cases) - 1 > MAX_CASE_INDEX:
        raise ValueError(f"n_cases must be <= 2^63, got {n_cases}.")
    seed = check_seed(seed)
    check_results_fit(int(n_cases), len(controllers), distribution, int(host_count))
    strategy = resolve_strategy(strategy, distribution)
    settings = (settings or SolverSettings()).with_tolerances_for(strategy)
    n_dev = len(jax.local_devices())
    shard = n_dev > 1 if shard is None else bool(shard)
    chunk_size = int(chunk_size)
    # groups of 16 (continuous control) where the chunk size allows them; every size a chunk
    # is simulated at (`chunk_ladder`) keeps those groups whole on every device
    digital = distribution_is_digital(distribution)
    group = ensemble_group_size(digital, chunk_size, platform=_platform())
    unit = group * (n_dev if shard else 1)
    if shard:
        # every device gets whole groups of consecutive cases: the ensemble groups (and so the
        # numbers) are the same as on one device
        chunk_size = -(-chunk_size // unit) * unit
    config = MonteCarloConfig(
        int(n_cases),
        seed,
        {n: gains_to_dict(c) for n, c in controllers.items()},
        distribution.to_dict(),
        chunk_size,
        strategy,
        asdict(settings),
        [int(host_index), int(host_count)],
    )
    n_chunks = -(-int(n_cases) // chunk_size)
    mine = host_chunks(n_chunks, host_index, host_count)

    def valid(c: int) -> int:
        return min(chunk_size, int(n_cases) - c * chunk_size)

    n_mine = len(mine) * chunk_size  # this host's real cases (the last chunk may be short)
    if len(mine) and mine[-1] == n_chunks - 1:
        n_mine -= chunk_size - valid(n_chunks - 1)
    chunk_dir = None
    invocation = None
    with contextlib.ExitStack() as stack:
        if out is not None:
            out = Path(out)
            chunk_dir = out / "chunks"
            text = json.dumps(config.to_dict(), indent=2, sort_keys=True)
            _check_same_config(out, json.loads(text))  # before writing anything
        # a cluster that cannot be reached or set up raises here, before anything is written
        session = stack.enter_context((executor or LocalExecutor()).session())
        local = session.record["kind"] == "local"
        if out is not None:
            chunk_dir.mkdir(parents=True, exist_ok=True)
            # which of this host's chunks are done: one directory listing, not one look-up per
            # chunk (they are read, and checked, in the loop below, under the progress bar)
            done = [c for c in _listed_chunks(chunk_dir) if c in mine]
            now = _now()
            invocation = f"{socket.gethostname()}:{os.getpid()}:{now}"
            with FileLock(out / FOLDER_LOCK):
                _check_same_config(out, json.loads(text))  # again, now that no one else writes
                if not (out / "run.json").exists():
                    atomic_write_text(text, out / "run.json")
                # provenance of every invocation (a resumed run may span several code revisions)
                _log_invocation(
                    out,
                    {
                        "invocation": invocation,
                        "started_utc": now,
                        "git_revision": git_revision(),
                        "chunks_already_done": len(done),
                        "n_chunks": len(mine),
                        "host": [int(host_index), int(host_count)],
                        "devices": [str(d) for d in local_devices(shard)],
                        **({} if local else {"executor": session.record}),
                    },
                )
        bar = None
        if progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=n_mine, unit="case", desc="monte carlo")
            if session.note():
                bar.set_postfix_str(session.note())
        job = _ChunkJob(
            controllers,
            distribution,
            seed,
            int(n_cases),
            chunk_size,
            unit,
            n_chunks,
            strategy,
            settings,
            shard if local else None,
            bool(jax.config.jax_enable_x64),
            n_dev if shard else 1,
            _platform(),
        )
        tables: dict[int, object] = {}
        locks: dict[int, FileLock] = {}
        by_worker: dict[str, list[int]] = {}
        timings: dict[str, list[float]] = {}  # chunk -> [start (Unix time), seconds] of its task
        pending: list[int] = []

        def finished(c: int, table) -> None:
            tables[c] = table
            if bar is not None:
                bar.update(valid(c))

        def read(c: int) -> None:
            path = chunk_file(chunk_dir, c)
            finished(c, _read_chunk(path, valid(c) * len(controllers), RERUN))

        def claim(chunks, wait: bool):
            """The chunks of ``chunks`` this run computes, each yielded with its lock held
            (taken only when the executor asks for the next chunk); the others are read
            (finished by another run in this folder) or, without ``wait``, left in ``pending``
            (another run holds their lock)."""
            for c in chunks:
                if chunk_dir is None:
                    yield c
                    continue
                if chunk_file(chunk_dir, c).exists():
                    read(c)
                    continue
                lock = _chunk_lock(chunk_dir, c)
                if wait:
                    if bar is not None:
                        bar.set_postfix_str(f"waiting for chunk {c} (another run in this folder)")
                    lock.acquire()
                elif not lock.acquire(blocking=False):
                    pending.append(c)  # another run in this folder is computing it
                    continue
                if chunk_file(chunk_dir, c).exists():  # finished while this run waited
                    lock.release(unlink=True)
                    read(c)
                    continue
                locks[c] = lock
                yield c

        def compute(chunks) -> None:
            # each chunk is written here, by this process, once, atomically: a worker that
            # dies mid-chunk leaves nothing, and its chunk is computed again elsewhere
            for c, table, info in session.imap(job, chunks):
                if chunk_dir is not None:
                    atomic_write_table(table, chunk_file(chunk_dir, c))
                    locks.pop(c).release(unlink=True)
                by_worker.setdefault(info["worker"], []).append(c)
                timings[str(c)] = [info["start_utc"], info["seconds"]]
                finished(c, table)
                if bar is not None and session.note():
                    bar.set_postfix_str(session.note())

        try:
            compute(claim(mine, wait=False))
            compute(claim(list(pending), wait=True))
        finally:
            for c, lock in locks.items():  # interrupted: the chunks in flight stay undone
                lock.release(unlink=chunk_file(chunk_dir, c).exists())
    if bar is not None:
        bar.set_postfix_str("")
        bar.close()
    computed = sum(len(v) for v in by_worker.values())
    result = _concat([tables[c] for c in mine])
    if out is not None:
        atomic_write_table(result, out / RESULTS_FILE)
        with FileLock(out / FOLDER_LOCK):
            _log_invocation(
                out,
                {
                    "invocation": invocation,
                    "finished_utc": _now(),
                    "chunks_computed": computed,
                    **({} if local else {"chunks_by_worker": by_worker, "chunk_tasks": timings}),
                },
            )
    return result


@dataclass(frozen=True)
class _ChunkJob:
    """One chunk of a run as a picklable task: ``job(c)`` samples chunk ``c``'s cases
    (`sample_cases`), solves them with every controller (`run_chunk`) and returns the chunk's
    table (the rows of its own cases). ``shard`` None (a task on a Dask worker): split the case
    axis over the worker's devices where that keeps the run's ensemble groups
    (`ensemble_group_size` with the run's ``devices``, whole groups on every device), else
    solve on one device."""

    controllers: dict
    distribution: Distribution
    seed: int
    n_cases: int
    chunk_size: int
    unit: int
    n_chunks: int
    strategy: str
    settings: SolverSettings
    shard: bool | None
    x64: bool
    devices: int = 1
    platform: str = "cpu"

    def valid(self, c: int) -> int:
        return min(self.chunk_size, self.n_cases - c * self.chunk_size)

    def worker_shard(self, size: int) -> bool:
        """Whether a chunk simulated at ``size`` cases is split over this process's devices
        (``shard`` None)."""
        n = len(jax.local_devices())
        if n == 1:
            return False
        digital = distribution_is_digital(self.distribution)
        group = ensemble_group_size(digital, size, self.devices, self.platform)
        here = _platform()
        whole = size % (n * group) == 0
        return whole and ensemble_group_size(digital, size, n, here) == group

    def __call__(self, c: int):
        if bool(jax.config.jax_enable_x64) != self.x64:
            jax.config.update("jax_enable_x64", self.x64)
        size = simulated_size(self.valid(c), self.chunk_size, self.unit, self.n_chunks)
        chunk = sample_cases(self.distribution, size, self.seed, start=c * self.chunk_size)
        shard = self.worker_shard(size) if self.shard is None else self.shard
        per = {
            name: run_chunk(
                ctrl, chunk, strategy=self.strategy, settings=self.settings, shard=shard
            )
            for name, ctrl in self.controllers.items()
        }
        return _chunk_table(chunk, self.valid(c), per)


def _now() -> str:
    return datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")


def _listed_chunks(chunk_dir: Path) -> list[int]:
    """Chunk numbers of the finished chunk files in ``chunk_dir``."""
    found = []
    for name in os.listdir(chunk_dir):
        if name.startswith("chunk_") and name.endswith(".parquet"):
            try:
                found.append(int(name[len("chunk_") : -len(".parquet")]))
            except ValueError:
                continue
    return sorted(found)


def _check_same_config(out: Path, config: dict) -> None:
    """Refuse a folder holding results of another configuration (naming what differs)."""
    run_file = out / "run.json"
    if out.exists() and not out.is_dir():
        raise ValueError(f"{out} is a file, not a folder; give a folder for the results.")
    if not run_file.exists():
        return
    try:
        found = json.loads(run_file.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError):
        raise _damaged(run_file, "not JSON", "the chunks beside it, or use another folder")
    diff = config_differences(found, config) if isinstance(found, dict) else ["run.json"]
    if diff:
        raise ValueError(
            f"{out} holds results of a different configuration (differs in: "
            f"{', '.join(diff)}; see {run_file}); use another --out folder or delete it."
        )


def _concat(tables):
    import pyarrow as pa

    return pa.concat_tables(tables)


def merge_results(shards: list[str | Path], out: str | Path) -> tuple:
    """Join the ``out`` folders of a multi-host run (one per host, same configuration, hosts
    0..P-1) into ``out/results.parquet`` (rows in case order, equal to a one-host run's) and
    ``out/run.json``; returns (table, config). Raises ValueError, naming the folder, when a
    configuration differs (naming the differing entries), a host is missing or twice, or a
    chunk file is missing or damaged."""
    if not shards:
        raise ValueError("merge needs at least one results folder.")
    configs = {}
    for d in map(Path, shards):
        run_file = d / "run.json"
        if not run_file.exists():
            raise ValueError(f"{d} is not a Monte-Carlo results folder (no run.json).")
        try:
            configs[d] = json.loads(run_file.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError):
            raise ValueError(f"{run_file} is damaged (not JSON).") from None
    first_dir, first = next(iter(configs.items()))
    count = int(first["hosts"][1])
    base = {k: v for k, v in first.items() if k != "hosts"}
    seen: dict[int, Path] = {}
    for d, cfg in configs.items():
        diff = config_differences({k: v for k, v in cfg.items() if k != "hosts"}, base)
        if diff:
            raise ValueError(
                f"{d} was run with a different configuration than {first_dir} "
                f"(differs in: {', '.join(diff)})."
            )
        index, n = (int(x) for x in cfg["hosts"])
        if n != count:
            raise ValueError(f"{d} is host {index} of {n}, {first_dir} of {count} hosts.")
        if index in seen:
            raise ValueError(f"{d} and {seen[index]} are both host {index}.")
        seen[index] = d
    missing = sorted(set(range(count)) - set(seen))
    if missing:
        raise ValueError(f"results of host(s) {missing} of {count} are missing.")
    n_cases, chunk_size = int(base["n_cases"]), int(base["chunk_size"])
    n_chunks = -(-n_cases // chunk_size)
    paths = [chunk_file(seen[c % count] / "chunks", c) for c in range(n_chunks)]
    n_controllers = len(base["controllers"])
    for c, path in enumerate(paths):
        fix = f"re-run host {c % count}'s command (that chunk is recomputed), then merge again"
        if not path.exists():
            raise ValueError(
                f"{path} is missing: host {c % count} has not finished (re-run "
                "its command to resume it)."
            )
        _check_chunk(path, min(chunk_size, n_cases - c * chunk_size) * n_controllers, fix)
    out = Path(out)
    (out / "chunks").mkdir(parents=True, exist_ok=True)
    tables = []
    with FileLock(out / FOLDER_LOCK):
        for c, path in enumerate(paths):
            # the merged folder is a complete one-host run folder (resumable like any other)
            target = chunk_file(out / "chunks", c)
            if path.resolve() != target.resolve():
                atomic_write_bytes(path.read_bytes(), target)
            tables.append(read_table(path))
        table = _concat(tables)
        config = {**base, "hosts": [0, 1]}
        atomic_write_text(json.dumps(config, indent=2, sort_keys=True), out / "run.json")
        lines = []
        for index in sorted(seen):
            log = seen[index] / "invocations.jsonl"
            if log.exists():
                lines.append(log.read_text())
        atomic_write_text("".join(lines), out / "invocations.jsonl")
        atomic_write_table(table, out / RESULTS_FILE)
    return table, config
