"""The Monte-Carlo runner: chunked, resumable, paired over controllers, optionally sharded.

For every chunk of ``chunk_size`` cases (the last one filled with the following case indices,
so every chunk has the same shape and nothing recompiles) and every controller, a *strategy*
maps ``(controller, chunk, settings, devices) -> per-case metrics`` (`METRIC_NAMES`). Built in
(`afbl_jax.simulate_batch` underneath, case axis split over ``devices``; every strategy runs
every closed loop, including the distribution's ``[unmodeled]`` section):

- ``"ensemble_f32"`` (the default; `DEFAULT_STRATEGY`): float32, groups of `GROUP_SIZE`
  consecutive cases each solved as one ODE system (shared steps, every case meeting its own
  tolerance), the groups vectorised, each device working through its cases `INNER_CHUNK` at a
  time; default tolerances rtol 3e-6, atol 3e-7 (float32 cannot honour 1e-6 / 1e-8). The
  fastest path that meets the accuracy bound (max relative ISE error <= 1e-3 against a tight
  float64 reference; measured by `afbl bench` and checked by the tests). At rtol 1e-5,
  atol 1e-6 (the benchmark's ``ensemble_f32`` rows, 1.2-1.4x faster) 3 of 8190 runs of the
  default 4096-case study missed the bound (up to 1.5e-3, FBL cases driving the rotors into
  their limit, where the clipping kinks meet float32 round-off); at 3e-6 / 3e-7 none did
  (max 6.7e-4).
- ``"ensemble"``: the same in float64 (default tolerances rtol 1e-6, atol 1e-8).
- ``"vmap"``: ``jax.vmap`` over `afbl_jax.simulate` in float64 (every case its own step
  sequence; results independent of how cases are chunked).

Ensemble results depend (within the tolerance) on which cases share a group: the same case in a
different chunking or group can differ by ~rtol. Resuming is exact (same chunks). With digital
control the cases of a group share their sample instants; the sampler draws one control rate
per group of `GROUP_SIZE` case indices (`afbl_jax.studies.montecarlo.sample_cases`).
Other strategies can be added with `register_strategy`. Metric definitions:
`afbl_jax.metrics`.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import jax
import numpy as np

from ...io import atomic_write_table, gains_to_dict, read_table
from ...metrics import METRIC_NAMES, metric_columns
from ...model import AbstractController
from ...sim import STATUS_NAMES, simulate_batch
from ._distribution import Distribution
from ._sampler import GROUP_SIZE, CaseBatch, sample_cases

RESULTS_FILE = "results.parquet"


DEFAULT_STRATEGY = "ensemble_f32"
INNER_CHUNK = 128
"""Cases per device solved at a time inside one compiled call (keeps the working set in cache)."""
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
        if not ((self.rtol is None or self.rtol > 0) and (self.atol is None or self.atol > 0)):
            raise ValueError(f"rtol and atol must be > 0, got {self.rtol}, {self.atol}.")
        if int(self.n_save) < 2 or int(self.max_steps) < 1:
            raise ValueError(
                f"n_save must be >= 2 and max_steps >= 1, got {self.n_save}, {self.max_steps}."
            )


BATCH_SETTINGS = {
    "ensemble_f32": {
        "strategy": "ensemble",
        "dtype": "float32",
        "group_size": GROUP_SIZE,
        "chunk_size": INNER_CHUNK,
    },
    "ensemble": {
        "strategy": "ensemble",
        "dtype": "float64",
        "group_size": GROUP_SIZE,
        "chunk_size": INNER_CHUNK,
    },
    "vmap": {"strategy": "vmap", "dtype": None, "group_size": None, "chunk_size": INNER_CHUNK},
}
"""`afbl_jax.simulate_batch` settings of the built-in strategies (besides `SolverSettings`);
``dtype`` None: JAX's default float."""


def _batch_strategy(name: str) -> Strategy:
    kwargs = BATCH_SETTINGS[name]

    def run(controller, chunk: CaseBatch, settings: SolverSettings, devices=None):
        m = simulate_batch(
            controller,
            chunk.scenario,
            chunk.vehicle,
            chunk.model,
            unmodeled=chunk.unmodeled,
            aerodynamics=chunk.aerodynamics,
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
    return {k: np.asarray(v) for k, v in out.items()}


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
    for k in ("solver_steps", "turbulence_level", "profile", "delay_samples"):
        if k in cols:
            cols[k] = cols[k].astype(np.int64)
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


def chunk_file(chunk_dir: Path, c: int) -> Path:
    """Path of chunk ``c``'s results (global chunk numbering, the same on every host)."""
    return chunk_dir / f"chunk_{c:06d}.parquet"


def host_chunks(n_chunks: int, host_index: int, host_count: int) -> range:
    """The chunks host ``host_index`` of ``host_count`` runs: c = host_index (mod host_count)."""
    return range(int(host_index), int(n_chunks), int(host_count))


def run_montecarlo(
    controllers: dict[str, AbstractController],
    distribution: Distribution,
    n_cases: int,
    seed: int,
    out: str | Path | None = None,
    *,
    chunk_size: int = 256,
    strategy: str | None = None,
    settings: SolverSettings | None = None,
    shard: bool | None = None,
    progress: bool = True,
    host_index: int = 0,
    host_count: int = 1,
):
    """Simulate ``n_cases`` cases for every controller (paired) and return the results table.

    One row per (case, controller): the case's sampled inputs (`INPUT_COLUMNS`) and metrics
    (`METRIC_NAMES`, status as "ok"/"diverged"/"solver_failed"). With ``out``, each finished
    chunk is written to ``out/chunks/`` at once; running the same call again skips finished
    chunks (resume) and the final ``out/results.parquet`` equals an uninterrupted run's. A
    different configuration in an existing ``out`` raises instead of mixing runs.

    ``strategy``: a name of `STRATEGIES`, or None/"auto" (`resolve_strategy`). Ensemble
    groups are consecutive blocks of `GROUP_SIZE` case indices, so with chunk sizes that are
    multiples of `GROUP_SIZE` the numbers do not depend on the chunk size.

    ``shard``: split each chunk's case axis over all local JAX devices (default: when there are
    several); ``chunk_size`` is then rounded up to a multiple of devices x `GROUP_SIZE`.

    Several hosts: ``host_index`` i of ``host_count`` P runs only the chunks c = i (mod P)
    (`host_chunks`) and returns / writes only their rows; `merge_results` joins the hosts'
    ``out`` folders into the table of a one-host run.
    """
    if not controllers:
        raise ValueError("run_montecarlo needs at least one controller.")
    if isinstance(n_cases, bool) or int(n_cases) < 1:
        raise ValueError(f"n_cases must be >= 1, got {n_cases!r}.")
    if isinstance(chunk_size, bool) or int(chunk_size) < 1:
        raise ValueError(f"chunk_size must be >= 1, got {chunk_size!r}.")
    if not (int(host_count) >= 1 and 0 <= int(host_index) < int(host_count)):
        raise ValueError(
            f"need 0 <= host_index < host_count, got host_index {host_index}, "
            f"host_count {host_count}."
        )
    strategy = resolve_strategy(strategy, distribution)
    settings = (settings or SolverSettings()).with_tolerances_for(strategy)
    n_dev = len(jax.local_devices())
    shard = n_dev > 1 if shard is None else bool(shard)
    chunk_size = int(chunk_size)
    if shard:
        # every device gets whole groups of consecutive cases: the ensemble groups (and so the
        # numbers) are the same as on one device
        unit = n_dev * GROUP_SIZE
        chunk_size = -(-chunk_size // unit) * unit
    config = MonteCarloConfig(
        int(n_cases),
        int(seed),
        {n: gains_to_dict(c) for n, c in controllers.items()},
        distribution.to_dict(),
        chunk_size,
        strategy,
        asdict(settings),
        [int(host_index), int(host_count)],
    )
    chunk_dir = None
    if out is not None:
        out = Path(out)
        chunk_dir = out / "chunks"
        run_file = out / "run.json"
        text = json.dumps(config.to_dict(), indent=2, sort_keys=True)
        if run_file.exists():
            if run_file.read_text() != text:
                raise ValueError(
                    f"{out} holds results of a different configuration ({run_file}); use "
                    "another --out folder or delete it."
                )
        chunk_dir.mkdir(parents=True, exist_ok=True)
        run_file.write_text(text)
    n_chunks = -(-int(n_cases) // chunk_size)
    mine = host_chunks(n_chunks, host_index, host_count)
    if out is not None:
        # provenance of every invocation (a resumed run may span several code revisions)
        import datetime as _dt

        from ...io import git_revision

        done = sum(chunk_file(chunk_dir, c).exists() for c in mine)
        entry = {
            "started_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            "git_revision": git_revision(),
            "chunks_already_done": int(done),
            "n_chunks": len(mine),
            "host": [int(host_index), int(host_count)],
            "devices": [str(d) for d in local_devices(shard)],
        }
        with open(out / "invocations.jsonl", "a") as fh:
            fh.write(json.dumps(entry) + "\n")
    tables = []
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(mine) * chunk_size, unit="case", desc="monte carlo")
    for c in mine:
        start = c * chunk_size
        n_valid = min(chunk_size, int(n_cases) - start)
        path = chunk_file(chunk_dir, c) if chunk_dir is not None else None
        if path is not None and path.exists():
            tables.append(read_table(path))
        else:
            chunk = sample_cases(distribution, chunk_size, seed, start=start)
            per = {
                name: run_chunk(ctrl, chunk, strategy=strategy, settings=settings, shard=shard)
                for name, ctrl in controllers.items()
            }
            table = _chunk_table(chunk, n_valid, per)
            if path is not None:
                atomic_write_table(table, path)
            tables.append(table)
        if bar is not None:
            bar.update(chunk_size)
    if bar is not None:
        bar.close()
    result = _concat(tables)
    if out is not None:
        atomic_write_table(result, out / RESULTS_FILE)
    return result


def _concat(tables):
    import pyarrow as pa

    return pa.concat_tables(tables)


def merge_results(shards: list[str | Path], out: str | Path) -> tuple:
    """Join the ``out`` folders of a multi-host run (one per host, same configuration, hosts
    0..P-1) into ``out/results.parquet`` (rows in case order, equal to a one-host run's) and
    ``out/run.json``; returns (table, config). Raises ValueError, naming the folder, when a
    configuration differs, a host is missing or twice, or a chunk file is missing."""
    if not shards:
        raise ValueError("merge needs at least one results folder.")
    configs = {}
    for d in map(Path, shards):
        run_file = d / "run.json"
        if not run_file.exists():
            raise ValueError(f"{d} is not a Monte-Carlo results folder (no run.json).")
        configs[d] = json.loads(run_file.read_text())
    first_dir, first = next(iter(configs.items()))
    count = int(first["hosts"][1])
    base = {k: v for k, v in first.items() if k != "hosts"}
    seen: dict[int, Path] = {}
    for d, cfg in configs.items():
        if {k: v for k, v in cfg.items() if k != "hosts"} != base:
            diff = sorted(
                k for k in set(cfg) | set(base) if k != "hosts" and cfg.get(k) != base.get(k)
            )
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
    n_chunks = -(-int(base["n_cases"]) // int(base["chunk_size"]))
    paths = [chunk_file(seen[c % count] / "chunks", c) for c in range(n_chunks)]
    for c, path in enumerate(paths):
        if not path.exists():
            raise ValueError(
                f"{path} is missing: host {c % count} has not finished (re-run "
                "its command to resume it)."
            )
    out = Path(out)
    (out / "chunks").mkdir(parents=True, exist_ok=True)
    tables = []
    for c, path in enumerate(paths):
        # the merged folder is a complete one-host run folder (resumable like any other)
        if path.resolve() != chunk_file(out / "chunks", c).resolve():
            shutil.copy2(path, chunk_file(out / "chunks", c))
        tables.append(read_table(path))
    table = _concat(tables)
    config = {**base, "hosts": [0, 1]}
    (out / "run.json").write_text(json.dumps(config, indent=2, sort_keys=True))
    with open(out / "invocations.jsonl", "w") as fh:
        for index in sorted(seen):
            log = seen[index] / "invocations.jsonl"
            if log.exists():
                fh.write(log.read_text())
    atomic_write_table(table, out / RESULTS_FILE)
    return table, config
