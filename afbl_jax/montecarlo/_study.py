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
    run_montecarlo,
    table_columns,
)


def run_study(controllers: dict[str, AbstractController], distribution: Distribution,
              n_cases: int, seed: int, out: str | Path, *, chunk_size: int = 256,
              strategy: str = "vmap", settings: SolverSettings | None = None,
              report: bool = True, progress: bool = True, echo=print) -> dict:
    """Run (or resume) the study into ``out`` and write every output; returns the summary."""
    settings = settings or SolverSettings()
    out = Path(out)
    t_start = time.perf_counter()
    table = run_montecarlo(controllers, distribution, n_cases, seed, out, chunk_size=chunk_size,
                           strategy=strategy, settings=settings, progress=progress)
    elapsed = time.perf_counter() - t_start
    cols = table_columns(table)
    summary = summarize(cols)
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
    p.add_argument("--chunk-size", type=int, default=256, help="cases per compiled chunk")
    p.add_argument("--strategy", default="vmap", help="chunk strategy (default vmap)")
    p.add_argument("--rtol", type=float, default=1e-6)
    p.add_argument("--atol", type=float, default=1e-8)
    p.add_argument("--no-report", action="store_true", help="skip report.md/html and figures")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


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
    if args.strategy not in STRATEGIES:
        fail(f"unknown --strategy {args.strategy!r}; allowed: {', '.join(STRATEGIES)}.")
    try:
        settings = SolverSettings(rtol=args.rtol, atol=args.atol)
        distribution = (load_distribution(args.distribution) if args.distribution
                        else default_distribution())
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

    jax.config.update("jax_enable_x64", True)
    print(f"{prog}: {args.cases} cases x {', '.join(names)} (seed {args.seed}, chunk "
          f"{args.chunk_size}, strategy {args.strategy}) -> {args.out}", flush=True)
    try:
        summary = run_study(controllers, distribution, args.cases, args.seed, args.out,
                            chunk_size=args.chunk_size, strategy=args.strategy,
                            settings=settings, report=not args.no_report,
                            progress=not args.no_progress)
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="montecarlo_robustness",
                                     description="Monte-Carlo robustness study (afbl-jax).")
    add_arguments(parser)
    return main_from_args(parser.parse_args(argv), prog="montecarlo_robustness")


if __name__ == "__main__":
    sys.exit(main())
