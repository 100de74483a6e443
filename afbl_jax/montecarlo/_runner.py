"""The Monte-Carlo runner: chunked, resumable, paired over controllers, optionally sharded.

For every chunk of ``chunk_size`` cases (the last one padded with the following case indices,
so every chunk has the same shape and nothing recompiles) and every controller, a *strategy*
maps ``(controller, chunk, settings) -> per-case metrics`` (`METRIC_NAMES`). The default
strategy ``"vmap"`` is ``jax.jit(jax.vmap(simulate))``; others can be added with
`register_strategy` (e.g. a solver that integrates a whole chunk as one ODE system).

Per-case metrics (from `afbl_jax.simulate`, saved samples at ``n_save`` equally spaced times):

- ``ise_attitude`` [rad^2 s], ``ise_altitude`` [m^2 s]: the ODE's exact cost integrals (up to
  the stop time for a diverged run);
- ``peak_attitude_error`` [rad]: max over the saved samples of max(|e_phi|, |e_theta|, |e_psi|);
- ``peak_altitude_error`` [m]: max over the saved samples of |e_z|;
- ``peak_saturation`` [-]: max over the saved samples and the four rotors of
  commanded rotor speed / omega_max (the commanded speed is sqrt of the mixer's commanded
  Omega^2, clipped at 0); >= 1 means the command hit the rotor-speed limit;
- ``solver_steps``: diffrax steps; ``t_final`` [s]: end of the run;
- ``status``: 0 ok, 1 diverged (|phi| or |theta| > 1.2 rad, altitude error > 10 m, or a
  non-finite state), 2/3 solver_failed (`afbl_jax.STATUS_NAMES`).

Peaks are sampled at the save resolution (t1 / (n_save - 1), 0.05 s by default) and only
samples before the stop time count.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from .._gains_io import gains_to_dict
from .._mixer import rotor_speeds_sq_from_inputs
from .._simulate import STATUS_NAMES, DivergenceLimits, simulate
from ..controllers import AbstractController
from ._distribution import Distribution
from ._sampler import CaseBatch, sample_cases

METRIC_NAMES: tuple[str, ...] = (
    "ise_attitude", "ise_altitude", "peak_attitude_error", "peak_altitude_error",
    "peak_saturation", "solver_steps", "t_final", "status",
)
"""Per-case metrics returned by a strategy (see the module docstring)."""
RESULTS_FILE = "results.parquet"
STATUS_LABELS = ("ok", "diverged", "solver_failed")


@dataclass(frozen=True)
class SolverSettings:
    """Solver configuration of a Monte-Carlo run (static: changing it recompiles)."""

    solver: str = "tsit5"
    rtol: float = 1e-6
    atol: float = 1e-8
    n_save: int = 401
    max_steps: int = 16384

    def __post_init__(self):
        if not (self.rtol > 0 and self.atol > 0):
            raise ValueError(f"rtol and atol must be > 0, got {self.rtol}, {self.atol}.")
        if int(self.n_save) < 2 or int(self.max_steps) < 1:
            raise ValueError(f"n_save must be >= 2 and max_steps >= 1, got {self.n_save}, "
                             f"{self.max_steps}.")


def case_metrics(controller: AbstractController, scenario, vehicle, model,
                 settings: SolverSettings, unmodeled=None) -> dict[str, jax.Array]:
    """Metrics of one case (unbatched); see the module docstring. ``unmodeled``: the case's
    `afbl_jax.UnmodeledDynamics` (None = the paper's closed loop)."""
    r = simulate(controller, scenario, vehicle, model, solver=settings.solver,
                 rtol=settings.rtol, atol=settings.atol, n_save=settings.n_save,
                 max_steps=settings.max_steps, limits=DivergenceLimits(), unmodeled=unmodeled)
    valid = r.ts <= r.t_final

    def peak(x):
        x = jnp.where(valid & jnp.isfinite(x), x, 0.0)
        return jnp.max(x)

    err = jnp.abs(r.error)
    w_cmd = jax.vmap(lambda u: rotor_speeds_sq_from_inputs(model, u))(r.u_command)
    sat = jnp.sqrt(jnp.maximum(w_cmd, 0.0)) / vehicle.omega_max
    return {
        "ise_attitude": r.ise_attitude,
        "ise_altitude": r.ise_altitude,
        "peak_attitude_error": peak(jnp.max(err[:, :3], axis=1)),
        "peak_altitude_error": peak(err[:, 3]),
        "peak_saturation": peak(jnp.max(sat, axis=1)),
        "solver_steps": r.num_steps,
        "t_final": r.t_final,
        "status": r.status,
    }


@eqx.filter_jit
def _vmap_chunk(controller, chunk: CaseBatch, settings: SolverSettings):
    model_axis = 0 if chunk.model_batched else None
    if chunk.unmodeled is None:
        return jax.vmap(case_metrics, in_axes=(None, 0, 0, model_axis, None))(
            controller, chunk.scenario, chunk.vehicle, chunk.model, settings)
    return jax.vmap(case_metrics, in_axes=(None, 0, 0, model_axis, None, 0))(
        controller, chunk.scenario, chunk.vehicle, chunk.model, settings, chunk.unmodeled)


def vmap_strategy(controller: AbstractController, chunk: CaseBatch,
                  settings: SolverSettings) -> dict[str, jax.Array]:
    """``jax.jit(jax.vmap(case_metrics))`` over the chunk's cases."""
    return _vmap_chunk(controller, chunk, settings)


Strategy = Callable[[AbstractController, CaseBatch, SolverSettings], dict]
STRATEGIES: dict[str, Strategy] = {"vmap": vmap_strategy}
"""Chunk strategies by name: ``(controller, chunk, settings) -> metrics dict``."""
UNMODELED_STRATEGIES: set[str] = {"vmap"}
"""Strategies that simulate ``chunk.unmodeled`` (others reject chunks that carry it)."""


def register_strategy(name: str, fn: Strategy, *, unmodeled: bool = False) -> None:
    """Make ``fn`` available as ``strategy=name`` (and ``--strategy name``); ``unmodeled``:
    ``fn`` honours ``chunk.unmodeled`` (unmodeled-dynamics settings per case)."""
    STRATEGIES[name] = fn
    if unmodeled:
        UNMODELED_STRATEGIES.add(name)
    else:
        UNMODELED_STRATEGIES.discard(name)


def shard_chunk(chunk: CaseBatch, devices=None) -> CaseBatch:
    """Place the chunk's case axis across ``devices`` (default all) with `jax.sharding`.

    Unbatched leaves (the nominal model) are replicated. The chunk size must be a multiple of
    the device count.
    """
    devices = jax.devices() if devices is None else devices
    n = len(devices)
    if chunk.n_cases % n:
        raise ValueError(f"chunk of {chunk.n_cases} cases does not split over {n} devices.")
    mesh = jax.sharding.Mesh(np.asarray(devices), ("cases",))
    split = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("cases"))
    repl = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec())

    def place(x):
        if np.ndim(x) >= 1 and np.shape(x)[0] == chunk.n_cases:
            return jax.device_put(x, split)
        return jax.device_put(x, repl)

    return jax.tree.map(place, chunk)


def run_chunk(controller: AbstractController, chunk: CaseBatch, *, strategy: str = "vmap",
              settings: SolverSettings | None = None, shard: bool = False) -> dict[str, np.ndarray]:
    """Metrics of every case of ``chunk`` for ``controller`` as NumPy arrays."""
    settings = settings or SolverSettings()
    try:
        fn = STRATEGIES[strategy]
    except KeyError:
        raise ValueError(f"unknown strategy {strategy!r}; allowed: "
                         f"{', '.join(STRATEGIES)}.") from None
    if chunk.unmodeled is not None and strategy not in UNMODELED_STRATEGIES:
        raise ValueError(f"strategy {strategy!r} does not simulate unmodeled dynamics; with "
                         "the distribution's [unmodeled] section enabled use one of "
                         f"{', '.join(sorted(UNMODELED_STRATEGIES))}.")
    if shard:
        chunk = shard_chunk(chunk)
    out = fn(controller, chunk, settings)
    return {k: np.asarray(v) for k, v in out.items()}


def status_label(code) -> np.ndarray:
    """Status codes -> "ok" / "diverged" / "solver_failed"."""
    return np.array([STATUS_NAMES[int(c)] for c in np.asarray(code).reshape(-1)], dtype=object)


def _chunk_table(chunk: CaseBatch, n_valid: int, per_controller: dict[str, dict]) -> pa.Table:
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

    def to_dict(self) -> dict:
        return asdict(self)


def _atomic_write_table(table: pa.Table, path: Path) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    pq.write_table(table, tmp)
    os.replace(tmp, path)


def run_montecarlo(
    controllers: dict[str, AbstractController],
    distribution: Distribution,
    n_cases: int,
    seed: int,
    out: str | Path | None = None,
    *,
    chunk_size: int = 256,
    strategy: str = "vmap",
    settings: SolverSettings | None = None,
    shard: bool | None = None,
    progress: bool = True,
) -> pa.Table:
    """Simulate ``n_cases`` cases for every controller (paired) and return the results table.

    One row per (case, controller): the case's sampled inputs (`INPUT_COLUMNS`) and metrics
    (`METRIC_NAMES`, status as "ok"/"diverged"/"solver_failed"). With ``out``, each finished
    chunk is written to ``out/chunks/`` at once; running the same call again skips finished
    chunks (resume) and the final ``out/results.parquet`` equals an uninterrupted run's. A
    different configuration in an existing ``out`` raises instead of mixing runs.

    ``shard``: split each chunk's case axis over all JAX devices (default: when there are
    several); ``chunk_size`` is then rounded up to a multiple of the device count.
    """
    settings = settings or SolverSettings()
    if not controllers:
        raise ValueError("run_montecarlo needs at least one controller.")
    if isinstance(n_cases, bool) or int(n_cases) < 1:
        raise ValueError(f"n_cases must be >= 1, got {n_cases!r}.")
    if isinstance(chunk_size, bool) or int(chunk_size) < 1:
        raise ValueError(f"chunk_size must be >= 1, got {chunk_size!r}.")
    if strategy not in STRATEGIES:
        raise ValueError(f"unknown strategy {strategy!r}; allowed: {', '.join(STRATEGIES)}.")
    n_dev = len(jax.devices())
    shard = n_dev > 1 if shard is None else bool(shard)
    chunk_size = int(chunk_size)
    if shard and chunk_size % n_dev:
        chunk_size += n_dev - chunk_size % n_dev
    config = MonteCarloConfig(
        int(n_cases), int(seed), {n: gains_to_dict(c) for n, c in controllers.items()},
        distribution.to_dict(), chunk_size, strategy, asdict(settings),
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
                    "another --out folder or delete it.")
        chunk_dir.mkdir(parents=True, exist_ok=True)
        run_file.write_text(text)
    n_chunks = -(-int(n_cases) // chunk_size)
    if out is not None:
        # provenance of every invocation (a resumed run may span several code revisions)
        import datetime as _dt

        from .._meta import git_revision

        done = sum((chunk_dir / f"chunk_{c:06d}.parquet").exists() for c in range(n_chunks))
        entry = {"started_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
                 "git_revision": git_revision(), "chunks_already_done": int(done),
                 "n_chunks": n_chunks}
        with open(out / "invocations.jsonl", "a") as fh:
            fh.write(json.dumps(entry) + "\n")
    tables = []
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=n_chunks * chunk_size, unit="case", desc="monte carlo")
    for c in range(n_chunks):
        start = c * chunk_size
        n_valid = min(chunk_size, int(n_cases) - start)
        path = chunk_dir / f"chunk_{c:06d}.parquet" if chunk_dir is not None else None
        if path is not None and path.exists():
            tables.append(pq.read_table(path))
        else:
            chunk = sample_cases(distribution, chunk_size, seed, start=start)
            per = {name: run_chunk(ctrl, chunk, strategy=strategy, settings=settings,
                                   shard=shard) for name, ctrl in controllers.items()}
            table = _chunk_table(chunk, n_valid, per)
            if path is not None:
                _atomic_write_table(table, path)
            tables.append(table)
        if bar is not None:
            bar.update(chunk_size)
    if bar is not None:
        bar.close()
    result = pa.concat_tables(tables)
    if out is not None:
        _atomic_write_table(result, out / RESULTS_FILE)
    return result


def read_results(path: str | Path) -> dict[str, np.ndarray]:
    """Columns of a results file (or of an ``out`` folder's results.parquet) as NumPy arrays."""
    path = Path(path)
    if path.is_dir():
        path = path / RESULTS_FILE
    return table_columns(pq.read_table(path))


def table_columns(table: pa.Table) -> dict[str, np.ndarray]:
    return {name: table.column(name).to_numpy(zero_copy_only=False)
            for name in table.column_names}
