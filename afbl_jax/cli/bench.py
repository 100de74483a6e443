"""``afbl bench``: throughput of the batched-solving strategies against a scipy loop."""

from __future__ import annotations

from ._common import Formatter, UsageError, add_out, check_out, seed


def register(sub) -> None:
    from ..studies.bench_rows import ALL_STRATEGIES, DEFAULT_SIZES

    p = sub.add_parser(
        "bench",
        formatter_class=Formatter,
        help="throughput of batched-solving strategies vs a scipy loop; writes bench.json",
        description="Simulations per second of the uncertain-step AFBL case for a scipy "
        "solve_ivp loop, a loop of jitted diffrax solves, vmap, the ensemble and float32 "
        "ensemble, the Monte-Carlo default (also on a realistic vehicle: full plant, 30 ms motor "
        "lag, 250 Hz digital control), and of the Monte-Carlo default distribution's own cases "
        "for afbl montecarlo's solve and a scipy solve_ivp loop of the same closed loop, with "
        "compile time, memory and max relative ISE error vs an x64 reference; and the gain-"
        "tuning objective's value-and-gradient against its forward pass (tuning_gradient). "
        "Writes OUT/bench.json and OUT/bench.png.",
    )
    add_out(p)
    p.add_argument(
        "--sizes", default=",".join(map(str, DEFAULT_SIZES)), help="comma-separated batch sizes"
    )
    p.add_argument(
        "--strategies", default=",".join(ALL_STRATEGIES), help="comma-separated rows to measure"
    )
    p.add_argument("--scipy-cases", type=int, default=16, help="cases for the scipy loop")
    p.add_argument(
        "--scipy-montecarlo-cases",
        type=int,
        default=4,
        help="cases for the scipy loop on the Monte-Carlo cases (scipy_rk45_montecarlo_cases)",
    )
    p.add_argument("--loop-cases", type=int, default=64, help="cases for the diffrax loop")
    p.add_argument(
        "--ref-cases",
        type=int,
        default=4096,
        help="cases with a tight x64 reference (accuracy is measured on the first "
        "min(N, ref-cases) cases of each row)",
    )
    p.add_argument(
        "--gradient-cases",
        type=int,
        default=16,
        help="training cases of the tuning_gradient rows",
    )
    p.add_argument("--seed", type=seed, default=0, help="seed of the cases, in [0, 2^63 - 1]")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..studies.bench_rows import ALL_STRATEGIES

    try:
        sizes = tuple(int(s) for s in args.sizes.split(",") if s.strip())
    except ValueError:
        raise UsageError(f"--sizes must be comma-separated integers, got {args.sizes!r}.") from None
    strategies = tuple(s.strip() for s in args.strategies.split(",") if s.strip())
    unknown = sorted(set(strategies) - set(ALL_STRATEGIES))
    if unknown:
        raise UsageError(f"unknown strategies {unknown}; allowed: {', '.join(ALL_STRATEGIES)}.")
    if not sizes or min(sizes) <= 0:
        raise UsageError(f"--sizes must be positive integers, got {args.sizes!r}.")
    counts = (args.scipy_cases, args.scipy_montecarlo_cases, args.loop_cases, args.ref_cases)
    if min(*counts, args.gradient_cases) <= 0:
        raise UsageError(
            "--scipy-cases, --scipy-montecarlo-cases, --loop-cases, --ref-cases, "
            "--gradient-cases must be > 0."
        )
    check_out(args.out)
    from ..studies.bench import BenchConfig, format_rows, run_benchmark

    rows = run_benchmark(
        BenchConfig(
            args.out,
            sizes,
            strategies,
            args.scipy_cases,
            args.loop_cases,
            args.ref_cases,
            args.seed,
            scipy_montecarlo_cases=args.scipy_montecarlo_cases,
            gradient_cases=args.gradient_cases,
        ),
        log=lambda s: print(s, flush=True),
    )
    print(format_rows(rows))
    print(f"wrote {args.out / 'bench.json'} and {args.out / 'bench.png'}")
    return 0
