"""``afbl montecarlo`` (the Monte-Carlo robustness study) and ``afbl merge`` (join the folders
of a multi-host run)."""

from __future__ import annotations

import importlib
import threading
from pathlib import Path

from ._clock import since_start
from ._common import (
    Formatter,
    UsageError,
    add_cluster,
    add_controllers,
    add_out,
    add_progress,
    add_tolerances,
    check_out,
    check_tolerances,
    controllers_from_args,
    executor_from_args,
    executor_words,
    seed,
)
from .falsify import add_failure_limits, check_failure_limits, distribution_from_args


def register(sub) -> None:
    p = sub.add_parser(
        "montecarlo",
        formatter_class=Formatter,
        help="Monte-Carlo robustness study: payload, model error, wind; paired controllers",
        description="Sample --cases cases from the distribution, simulate each with every "
        "controller (paired), write OUT/results.parquet, meta.json, summary.json, report.md, "
        "report.html and print a summary. Re-running the same command resumes; several runs "
        "of the same command into one OUT share the chunks between them.",
    )
    p.add_argument("--cases", type=int, default=4096, help="number of cases")
    add_controllers(p, "fbl,afbl")
    p.add_argument("--seed", type=seed, default=0, help="seed of the cases, in [0, 2^63 - 1]")
    add_out(p, "output folder (created; re-running the same command there resumes)")
    p.add_argument(
        "--distribution",
        type=Path,
        default=None,
        metavar="FILE",
        help="TOML or JSON file overriding the default distribution",
    )
    p.add_argument(
        "--chunk-size",
        type=int,
        default=None,
        help="cases per compiled chunk and per chunk file (default: 1024 on CPU devices, 16384 "
        "on a GPU)",
    )
    p.add_argument(
        "--strategy",
        default="auto",
        help="how a chunk is solved: ensemble_f32 (float32 grouped ensembles, the "
        "fastest within the 1e-3 accuracy bound), ensemble (float64), vmap (float64, "
        "one step sequence per case); auto: ensemble_f32",
    )
    add_tolerances(p, note=" (default: 3e-6 / 3e-7 for ensemble_f32, else 1e-6 / 1e-8)")
    p.add_argument("--no-report", action="store_true", help="skip report.md/html and figures")
    add_progress(p)
    rare = p.add_argument_group(
        "rare-event estimators",
        "--estimator is|ce|ce-mixture estimates the failure probability by importance "
        "sampling, --estimator subset by subset simulation, in the standard-normal space of "
        "the case variates (float64 ensembles at --rtol/--atol, default 1e-6 / 1e-8; with "
        "--strategy ensemble_f32 the crude study's float32 path, default 3e-6 / 3e-7) and "
        "writes OUT/rare_event.json, results.parquet (the estimating samples with their log "
        "weights; subset: the last level's samples) and rare_report.md; --cases is then the "
        "size of the final importance-sampling stage (unused by subset)",
    )
    rare.add_argument(
        "--estimator",
        default="crude",
        help="crude (the Monte-Carlo study above), is (importance sampling centred on the most "
        "likely failure a gradient search finds), ce (cross-entropy method) or ce-mixture "
        "(cross-entropy method on the few variates its stages find to drive failure, with a "
        "defensive normal mixture proposal; the one that works on several failure modes) or "
        "subset (subset simulation: levels of conditional probability --p0, every variate "
        "moved by batched adaptive MCMC; for the rarest failures)",
    )
    rare.add_argument(
        "--stage-cases",
        type=int,
        default=512,
        help="ce, ce-mixture: samples per cross-entropy stage; subset: samples per level",
    )
    rare.add_argument(
        "--p0",
        type=float,
        default=0.1,
        help="subset: conditional probability of each intermediate level, in (0, 0.5]",
    )
    rare.add_argument(
        "--search-budget",
        type=int,
        default=8,
        help="is/ce: gradient simulations (HL-RF iterations) of the search for the most likely "
        "failure that centres is and starts ce (0: none, the nominal point)",
    )
    add_failure_limits(rare)
    add_cluster(p, "the chunks (and --estimator's batches of simulations)")
    hosts = p.add_argument_group(
        "several hosts",
        "run the same command on every host, each with its own --out, then join the "
        "folders with `afbl merge` (hosts sharing a file system with working file locks can "
        "instead run the same command without these flags into one --out)",
    )
    hosts.add_argument(
        "--host-index",
        type=int,
        default=None,
        help="this host's index i (runs chunks i, i+P, ...); default: one host",
    )
    hosts.add_argument(
        "--host-count", type=int, default=None, help="number of hosts P; default: one host"
    )
    hosts.add_argument(
        "--distributed",
        action="store_true",
        help="call jax.distributed.initialize() (coordinator from the cluster "
        "environment or JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES, "
        "JAX_PROCESS_ID) and take i, P from jax.process_index/process_count",
    )
    p.set_defaults(func=run)

    m = sub.add_parser(
        "merge",
        formatter_class=Formatter,
        help="join the result folders of a multi-host Monte-Carlo run and write its report",
        description="Check that the folders hold hosts 0..P-1 of one configuration with every "
        "chunk finished, then write OUT/results.parquet (equal to a one-host run's), run.json, "
        "meta.json, summary.json, report.md/html and print the summary.",
    )
    m.add_argument(
        "shards", nargs="+", type=Path, metavar="FOLDER", help="the hosts' --out folders"
    )
    add_out(m, "merged output folder")
    m.add_argument("--no-report", action="store_true", help="skip report.md/html and figures")
    m.set_defaults(func=run_merge)


def run(args) -> int:
    """Validate everything before any simulation (errors: exit 2, nothing written)."""
    from ..studies.montecarlo import (
        STRATEGIES,
        SolverSettings,
        StudyConfig,
        check_results_fit,
        default_chunk_size,
        default_distribution,
        load_distribution,
        resolve_strategy,
        run_study,
    )

    if args.cases < 1:
        raise UsageError(f"--cases must be >= 1, got {args.cases}.")
    if args.chunk_size is not None and args.chunk_size < 1:
        raise UsageError(f"--chunk-size must be >= 1, got {args.chunk_size}.")
    if args.seed < 0:
        raise UsageError(f"--seed must be >= 0, got {args.seed}.")
    if args.strategy != "auto" and args.strategy not in STRATEGIES:
        raise UsageError(
            f"unknown --strategy {args.strategy!r}; allowed: auto, {', '.join(STRATEGIES)}."
        )
    if args.distributed and (args.host_index is not None or args.host_count is not None):
        raise UsageError(
            "--distributed takes the host index and count from JAX; do not also "
            "give --host-index/--host-count."
        )
    if (args.host_index is None) != (args.host_count is None):
        raise UsageError("give both --host-index and --host-count (or neither).")
    executor = executor_from_args(args)
    if executor is not None and (args.host_index is not None or args.distributed):
        raise UsageError(
            "--scheduler/--workers put every chunk on one Dask cluster; --host-index/"
            "--host-count/--distributed split the chunks between hosts without one: give one "
            "or the other."
        )
    if args.host_count is not None and not (0 <= args.host_index < args.host_count):
        raise UsageError(
            f"need 0 <= --host-index < --host-count, got {args.host_index}, {args.host_count}."
        )
    check_tolerances(args)
    if args.estimator not in ("crude", "is", "ce", "ce-mixture", "subset"):
        raise UsageError(
            f"unknown --estimator {args.estimator!r}; allowed: crude, is, ce, ce-mixture, subset."
        )
    if args.estimator != "crude":
        return run_rare(args, executor)
    if args.attitude_limit is not None or args.altitude_limit is not None:
        raise UsageError(
            "--attitude-limit/--altitude-limit apply to --estimator is|ce|ce-mixture|subset; "
            "the crude study counts status failures (the divergence limits)."
        )
    check_out(args.out)
    controllers = controllers_from_args(args)
    distribution = (
        load_distribution(args.distribution) if args.distribution else default_distribution()
    )
    strategy = resolve_strategy(args.strategy)
    settings = SolverSettings(rtol=args.rtol, atol=args.atol).with_tolerances_for(strategy)
    import jax

    host_index, host_count = (args.host_index or 0), (args.host_count or 1)
    if args.distributed:
        jax.distributed.initialize()
        host_index, host_count = jax.process_index(), jax.process_count()
    check_results_fit(args.cases, len(controllers), distribution, host_count)
    chunk_size = default_chunk_size() if args.chunk_size is None else args.chunk_size
    hosts = f", host {host_index} of {host_count}" if host_count > 1 else ""
    print(
        f"afbl montecarlo: {args.cases} cases x {', '.join(controllers)} (seed {args.seed}, "
        f"chunk {chunk_size}, strategy {strategy}, rtol {settings.rtol:g}, atol "
        f"{settings.atol:g}, {len(jax.local_devices())} device(s){hosts}"
        f"{executor_words(executor)}) -> {args.out}",
        flush=True,
    )
    # the summary's and the report's imports, on the idle core while the first chunk's
    # programs load or compile (single-threaded work)
    preload = ["scipy.stats"] + ([] if args.no_report else ["matplotlib.pyplot"])
    threading.Thread(target=_import_quietly, args=(preload,), daemon=True).start()
    run_study(
        StudyConfig(
            controllers,
            args.out,
            n_cases=args.cases,
            seed=args.seed,
            distribution=distribution,
            chunk_size=chunk_size,
            strategy=strategy,
            settings=settings,
            report=not args.no_report,
            progress=not args.no_progress,
            host_index=host_index,
            host_count=host_count,
            executor=executor,
        ),
        startup_seconds=since_start(),
    )
    return 0


def _import_quietly(modules: list[str]) -> None:
    """Import ``modules`` ahead of their first use (a failure shows where they are used)."""
    for name in modules:
        try:
            importlib.import_module(name)
        except Exception:  # the later import reports it
            pass


def run_rare(args, executor=None) -> int:
    from ..studies.rare import RareEventConfig, run_rare_event

    if args.stage_cases < 2:
        raise UsageError(f"--stage-cases must be >= 2, got {args.stage_cases}.")
    if not 0 < args.p0 <= 0.5:
        raise UsageError(f"--p0 must lie in (0, 0.5], got {args.p0}.")
    if args.estimator == "subset" and round(args.stage_cases * args.p0) < 2:
        raise UsageError(
            f"--estimator subset needs --stage-cases x --p0 >= 2 chains, got "
            f"{args.stage_cases} x {args.p0}."
        )
    if args.search_budget < 0:
        raise UsageError(f"--search-budget must be >= 0, got {args.search_budget}.")
    if args.host_index is not None or args.distributed:
        raise UsageError(
            "--estimator is|ce|ce-mixture|subset runs on one host (no --host-index/--distributed)."
        )
    if args.strategy not in ("auto", "ensemble", "ensemble_f32"):
        raise UsageError(
            f"--estimator {args.estimator} solves ensembles: --strategy must be auto or "
            f"ensemble (float64) or ensemble_f32 (float32), got {args.strategy!r}."
        )
    f32 = args.strategy == "ensemble_f32"
    check_failure_limits(args)
    check_out(args.out)
    controllers = controllers_from_args(args)
    distribution = distribution_from_args(args)
    size = (
        f"{args.stage_cases} samples per level, p0 {args.p0:g}"
        if args.estimator == "subset"
        else f"{args.cases} final samples"
    )
    print(
        f"afbl montecarlo: --estimator {args.estimator}, {', '.join(controllers)} (seed "
        f"{args.seed}, {size}{executor_words(executor)}) -> {args.out}",
        flush=True,
    )
    run_rare_event(
        RareEventConfig(
            controllers,
            args.out,
            args.estimator,
            distribution,
            seed=args.seed,
            n_cases=args.cases,
            n_per_stage=args.stage_cases,
            p0=args.p0,
            search_budget=args.search_budget,
            attitude_limit=args.attitude_limit,
            altitude_limit=args.altitude_limit,
            rtol=args.rtol or (3e-6 if f32 else 1e-6),
            atol=args.atol or (3e-7 if f32 else 1e-8),
            dtype="float32" if f32 else None,
            executor=executor,
        )
    )
    print(f"wrote {args.out}/rare_event.json, results.parquet, rare_report.md")
    return 0


def run_merge(args) -> int:
    from ..studies.montecarlo import merge_study

    check_out(args.out)
    merge_study(args.shards, args.out, report=not args.no_report)
    return 0
