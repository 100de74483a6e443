"""``afbl falsify``: worst cases within the distribution's bounds by projected multi-start
gradient ascent on the failure margin, against CMA-ES with the same budget; the most likely
failure (the ray's upper bound, then the design point by SLSQP); optionally the sensitivities
(DGSM, Sobol) of the margin and the attitude ISE."""

from __future__ import annotations

from pathlib import Path

from ._common import (
    Formatter,
    UsageError,
    add_controllers,
    add_out,
    add_tolerances,
    check_out,
    check_tolerances,
    controllers_from_args,
    seed,
)


def add_failure_limits(p) -> None:
    p.add_argument(
        "--attitude-limit",
        type=float,
        default=None,
        help="failure limit on the attitude error peak [rad] (default: the divergence "
        "limit 1.2, failure = the run diverged)",
    )
    p.add_argument(
        "--altitude-limit",
        type=float,
        default=None,
        help="failure limit on the altitude error peak [m] (default: the divergence limit 10)",
    )


def check_failure_limits(args) -> None:
    for flag, value in (
        ("--attitude-limit", args.attitude_limit),
        ("--altitude-limit", args.altitude_limit),
    ):
        if value is not None and not 0 < value < float("inf"):
            raise UsageError(f"{flag} must be a finite number > 0, got {value}.")


def distribution_from_args(args):
    from ..studies.montecarlo import default_distribution, load_distribution

    d = load_distribution(args.distribution) if args.distribution else default_distribution()
    if d.spec["unmodeled"]["enabled"]:
        raise UsageError(
            f"{args.distribution}: [unmodeled] enabled = true is not supported here (its inputs "
            "are not standard variates); set it to false."
        )
    return d


def register(sub) -> None:
    p = sub.add_parser(
        "falsify",
        formatter_class=Formatter,
        help="worst-case search: gradient ascent on the failure margin vs CMA-ES",
        description="For every controller and search seed, maximise the failure margin over "
        "the distribution's standard variates (within its bounds) by projected multi-start "
        "gradient ascent and by CMA-ES with the same budget from the same starts; write "
        "OUT/falsify.json, worst_cases.parquet, rare_report.md and figures (search progress, "
        "worst-case trajectories, sensitivities).",
    )
    add_controllers(p, "afbl")
    p.add_argument("--seed", type=seed, default=0, help="seed of the start cases")
    add_out(p)
    p.add_argument(
        "--distribution",
        type=Path,
        default=None,
        metavar="FILE",
        help="TOML/JSON overrides of the Monte-Carlo distribution (default: none, the "
        "Monte-Carlo default distribution)",
    )
    p.add_argument("--starts", type=int, default=8, help="starts = CMA-ES population size")
    p.add_argument(
        "--budget", type=int, default=64, help="simulations per search (each method and seed)"
    )
    p.add_argument("--seeds", type=int, default=1, help="search seeds (different starts)")
    p.add_argument(
        "--design-budget",
        type=int,
        default=16,
        help="gradient simulations of the design-point search (SLSQP on |z|^2 subject to "
        "failing, from the ray's most likely failure; 0: the ray's point only)",
    )
    p.add_argument(
        "--sensitivity-samples",
        type=int,
        default=0,
        help="DGSM points and Sobol base samples (power of 2; 0: no sensitivities)",
    )
    add_failure_limits(p)
    add_tolerances(p, 1e-6, 1e-8)
    p.set_defaults(func=run)


def run(args) -> int:
    from ..studies.rare import FalsifyConfig, run_falsify

    for flag, value, low in (
        ("--starts", args.starts, 2),
        ("--budget", args.budget, 1),
        ("--seeds", args.seeds, 1),
        ("--design-budget", args.design_budget, 0),
    ):
        if value < low:
            raise UsageError(f"{flag} must be >= {low}, got {value}.")
    if args.budget < args.starts:
        raise UsageError(
            f"--budget ({args.budget}) must be >= --starts ({args.starts}): one iteration "
            "simulates every start."
        )
    n = args.sensitivity_samples
    if n < 0 or (n and n & (n - 1)):
        raise UsageError(f"--sensitivity-samples must be 0 or a power of 2, got {n}.")
    check_failure_limits(args)
    check_tolerances(args)
    check_out(args.out)
    controllers = controllers_from_args(args)
    distribution = distribution_from_args(args)
    print(
        f"afbl falsify: {', '.join(controllers)}, {args.seeds} seed(s) x {args.starts} starts, "
        f"budget {args.budget} simulations per search -> {args.out}",
        flush=True,
    )
    run_falsify(
        FalsifyConfig(
            controllers,
            args.out,
            distribution,
            starts=args.starts,
            budget=args.budget,
            seeds=args.seeds,
            seed=args.seed,
            attitude_limit=args.attitude_limit,
            altitude_limit=args.altitude_limit,
            design_budget=args.design_budget,
            sensitivity_samples=n,
            rtol=args.rtol,
            atol=args.atol,
        )
    )
    print(f"wrote {args.out}/falsify.json, worst_cases.parquet, rare_report.md, figures/")
    return 0
