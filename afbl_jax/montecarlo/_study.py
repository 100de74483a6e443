"""The Monte-Carlo study (`afbl montecarlo` and studies/montecarlo_robustness.py): run, then
write meta.json, report.md/html, summary.json and print the terminal summary."""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import sys
import time
from pathlib import Path

from .._meta import run_metadata
from ..controllers import AbstractController
from ._distribution import Distribution, default_distribution, load_distribution
from ._report import format_summary, replay_worst, summarize, write_report
from ._runner import (
    STRATEGIES,
    SolverSettings,
    merge_results,
    resolve_strategy,
    run_montecarlo,
    table_columns,
)


def run_study(controllers: dict[str, AbstractController], distribution: Distribution,
              n_cases: int, seed: int, out: str | Path, *, chunk_size: int = 256,
              strategy: str | None = None, settings: SolverSettings | None = None,
              report: bool = True, progress: bool = True, echo=print, host_index: int = 0,
              host_count: int = 1) -> dict | None:
    """Run (or resume) the study into ``out`` and write every output; returns the summary.

    With ``host_count > 1`` this host's shard is run and written (results.parquet holds only
    its rows, meta.json its provenance) and None is returned: `merge_study` makes the report.
    """
    out = Path(out)
    t_start = time.perf_counter()
    table = run_montecarlo(controllers, distribution, n_cases, seed, out, chunk_size=chunk_size,
                           strategy=strategy, settings=settings, progress=progress,
                           host_index=host_index, host_count=host_count)
    elapsed = time.perf_counter() - t_start
    if host_count > 1:
        _write_meta(out, elapsed)
        if echo is not None:
            echo(f"host {host_index} of {host_count}: {table.num_rows} rows in {out} "
                 f"({elapsed:.1f} s); when every host is done: afbl merge --out DIR "
                 "<the hosts' folders>")
        return None
    return _finish(out, table, controllers, distribution, seed, report=report, echo=echo,
                   elapsed=elapsed)


def merge_study(shards: list[str | Path], out: str | Path, *, report: bool = True,
                echo=print) -> dict:
    """Join a multi-host run's folders into ``out`` (`merge_results`) and write the report and
    summary as a one-host run would; returns the summary."""
    from .._gains_io import controller_from_dict

    t_start = time.perf_counter()
    table, config = merge_results(shards, out)
    controllers = {name: controller_from_dict(g, source=f"{shards[0]}/run.json")
                   for name, g in config["controllers"].items()}
    distribution = Distribution.from_dict(config["distribution"])
    return _finish(Path(out), table, controllers, distribution, int(config["seed"]),
                   report=report, echo=echo, elapsed=time.perf_counter() - t_start)


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
    meta["invocations"] = [json.loads(line) for line in
                           (out / "invocations.jsonl").read_text().splitlines() if line]
    (out / "meta.json").write_text(json.dumps(meta, indent=2) + "\n")
    return meta


def _finish(out: Path, table, controllers, distribution, seed, *, report, echo,
            elapsed) -> dict:
    cols = table_columns(table)
    summary = summarize(cols)
    meta = _write_meta(out, elapsed)
    settings = SolverSettings(**meta["config"]["settings"])
    n_cases = int(meta["config"]["n_cases"])
    if report:
        replays = replay_worst(cols, controllers, distribution, seed, k=min(5, n_cases),
                               settings=settings)
        write_report(out, cols, summary, distribution, meta, replays)
    else:
        (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    if echo is not None:
        echo(format_summary(summary))
        echo(f"\nwrote {out}/results.parquet, meta.json, summary.json"
             + (", report.md, report.html" if report else "") + f" ({elapsed:.1f} s)")
    return summary


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--cases", type=int, default=4096, help="number of cases (default 4096)")
    p.add_argument("--controllers", default="fbl,afbl",
                   help="comma-separated controllers, e.g. fbl,afbl (default)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True, type=Path, help="output folder (created; re-running "
                   "the same command there resumes)")
    p.add_argument("--distribution", type=Path, default=None, metavar="FILE",
                   help="TOML or JSON file overriding the default distribution")
    p.add_argument("--gains", action="append", default=[], type=Path, metavar="FILE",
                   help="gains JSON replacing the paper gains of its controller (repeatable)")
    p.add_argument("--chunk-size", type=int, default=256,
                   help="cases per compiled chunk and per chunk file (default 256)")
    p.add_argument("--strategy", default="auto",
                   help="how a chunk is solved: ensemble_f32 (float32 grouped ensembles, the "
                   "fastest within the 1e-3 accuracy bound), ensemble (float64), vmap (float64, "
                   "one step sequence per case; needed for [unmodeled]); auto (default): "
                   "ensemble_f32, or vmap when the distribution enables [unmodeled]")
    p.add_argument("--rtol", type=float, default=None,
                   help="relative tolerance (default: 3e-6 for ensemble_f32, else 1e-6)")
    p.add_argument("--atol", type=float, default=None,
                   help="absolute tolerance (default: 3e-7 for ensemble_f32, else 1e-8)")
    p.add_argument("--no-report", action="store_true", help="skip report.md/html and figures")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    hosts = p.add_argument_group(
        "several hosts", "run the same command on every host (each with its own --out, or one "
        "shared folder), then join the folders with `afbl merge`")
    hosts.add_argument("--host-index", type=int, default=None,
                       help="this host's index i (runs chunks i, i+P, ...)")
    hosts.add_argument("--host-count", type=int, default=None, help="number of hosts P")
    hosts.add_argument("--distributed", action="store_true",
                       help="call jax.distributed.initialize() (coordinator from the cluster "
                       "environment or JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES, "
                       "JAX_PROCESS_ID) and take i, P from jax.process_index/process_count")


def main_from_args(args, prog: str = "afbl montecarlo") -> int:
    """Validate everything before any simulation (errors exit non-zero, nothing written)."""
    from ..controllers import CONTROLLERS, make_controller

    def fail(msg: str):
        raise SystemExit(f"{prog}: error: {msg}")

    names = [n.strip() for n in args.controllers.split(",") if n.strip()]
    bad = [n for n in names if n not in CONTROLLERS]
    if bad or not names:
        fail(f"unknown controller(s) {bad or names}; allowed: {', '.join(CONTROLLERS)}.")
    if len(set(names)) != len(names):
        fail(f"controller listed twice in {args.controllers!r}.")
    if args.cases < 1:
        fail(f"--cases must be >= 1, got {args.cases}.")
    if args.chunk_size < 1:
        fail(f"--chunk-size must be >= 1, got {args.chunk_size}.")
    if args.seed < 0:
        fail(f"--seed must be >= 0, got {args.seed}.")
    if args.strategy != "auto" and args.strategy not in STRATEGIES:
        fail(f"unknown --strategy {args.strategy!r}; allowed: auto, {', '.join(STRATEGIES)}.")
    if args.distributed and (args.host_index is not None or args.host_count is not None):
        fail("--distributed takes the host index and count from JAX; do not also give "
             "--host-index/--host-count.")
    if (args.host_index is None) != (args.host_count is None):
        fail("give both --host-index and --host-count (or neither).")
    if args.host_count is not None and not (0 <= args.host_index < args.host_count):
        fail(f"need 0 <= --host-index < --host-count, got {args.host_index}, "
             f"{args.host_count}.")
    try:
        settings = SolverSettings(rtol=args.rtol, atol=args.atol)
        distribution = (load_distribution(args.distribution) if args.distribution
                        else default_distribution())
        strategy = resolve_strategy(args.strategy, distribution)
        controllers = {n: make_controller(n) for n in names}
        from .._gains_io import load_gains

        for path in args.gains:
            ctrl = load_gains(path)
            if ctrl.name not in controllers:
                fail(f"gains file {path} is for {ctrl.name!r}, which is not in --controllers.")
            controllers[ctrl.name] = ctrl
    except ValueError as err:
        fail(str(err))
    import jax

    host_index, host_count = (args.host_index or 0), (args.host_count or 1)
    if args.distributed:
        jax.distributed.initialize()
        host_index, host_count = jax.process_index(), jax.process_count()
    jax.config.update("jax_enable_x64", True)
    settings = settings.with_tolerances_for(strategy)
    hosts = f", host {host_index} of {host_count}" if host_count > 1 else ""
    print(f"{prog}: {args.cases} cases x {', '.join(names)} (seed {args.seed}, chunk "
          f"{args.chunk_size}, strategy {strategy}, rtol {settings.rtol:g}, atol "
          f"{settings.atol:g}, {len(jax.local_devices())} device(s){hosts}) -> {args.out}",
          flush=True)
    try:
        summary = run_study(controllers, distribution, args.cases, args.seed, args.out,
                            chunk_size=args.chunk_size, strategy=strategy,
                            settings=settings, report=not args.no_report,
                            progress=not args.no_progress, host_index=host_index,
                            host_count=host_count)
    except ValueError as err:
        fail(str(err))
    del summary
    return 0


def add_subcommand(sub) -> None:
    """Register ``afbl montecarlo`` on the CLI's subparsers."""
    p = sub.add_parser(
        "montecarlo",
        help="Monte-Carlo robustness study: payload, model error, wind; paired controllers",
        description="Sample --cases cases from the distribution, simulate each with every "
        "controller (paired), write OUT/results.parquet, meta.json, summary.json, report.md, "
        "report.html and print a summary. Re-running the same command resumes.",
    )
    add_arguments(p)
    p.set_defaults(func=lambda a: main_from_args(a))


def add_merge_subcommand(sub) -> None:
    """Register ``afbl merge`` (join the folders of a multi-host Monte-Carlo run)."""
    p = sub.add_parser(
        "merge",
        help="join the result folders of a multi-host Monte-Carlo run and write its report",
        description="Check that the folders hold hosts 0..P-1 of one configuration with every "
        "chunk finished, then write OUT/results.parquet (equal to a one-host run's), run.json, "
        "meta.json, summary.json, report.md/html and print the summary.",
    )
    p.add_argument("shards", nargs="+", type=Path, metavar="FOLDER",
                   help="the hosts' --out folders")
    p.add_argument("--out", required=True, type=Path, help="merged output folder")
    p.add_argument("--no-report", action="store_true", help="skip report.md/html and figures")

    def run(args) -> int:
        import jax

        jax.config.update("jax_enable_x64", True)
        try:
            merge_study(args.shards, args.out, report=not args.no_report)
        except ValueError as err:
            raise SystemExit(f"afbl merge: error: {err}") from None
        return 0

    p.set_defaults(func=run)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="montecarlo_robustness",
                                     description="Monte-Carlo robustness study (afbl-jax).")
    add_arguments(parser)
    return main_from_args(parser.parse_args(argv), prog="montecarlo_robustness")


if __name__ == "__main__":
    sys.exit(main())
