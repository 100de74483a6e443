"""``afbl tune``: gains by L-BFGS / Adam / CMA-ES through the batched simulation."""

from __future__ import annotations

import math
import time

from .._validation import MAX_SEED
from ._common import (
    Formatter,
    UsageError,
    add_cluster,
    add_out,
    check_out,
    check_tolerances,
    executor_from_args,
    seed,
)


def add_tuning_args(p) -> None:
    """Flags shared by `afbl tune` and `afbl tune-compare` (objective, limits, method)."""
    p.add_argument(
        "--controller", default="afbl", choices=["afbl", "fbl"], help="controller to tune"
    )
    p.add_argument(
        "--objective",
        default="robust",
        choices=["nominal", "robust"],
        help="nominal: the canonical scenarios; robust: sampled cases with unmodeled dynamics",
    )
    p.add_argument(
        "--risk",
        default="mean",
        choices=["mean", "cvar"],
        help="robust objective: mean or (smoothed) CVaR over the cases",
    )
    p.add_argument(
        "--cvar-level", type=float, default=0.9, help="CVaR level alpha (mean of the worst 1-alpha)"
    )
    p.add_argument("--cases", type=int, default=64, help="training cases (robust)")
    p.add_argument("--steps", type=int, default=100, help="iterations, or CMA-ES generations")
    p.add_argument(
        "--method",
        "--optimizer",
        dest="method",
        default="lbfgs",
        choices=["lbfgs", "adam", "cmaes", "hybrid"],
        help="optimiser: L-BFGS with a backtracking line search, Adam, CMA-ES (gradient-free), "
        "or hybrid (CMA-ES generations, then L-BFGS from the best candidate)",
    )
    p.add_argument(
        "--cmaes-generations",
        type=int,
        default=5,
        help="hybrid: CMA-ES generations before L-BFGS takes over",
    )
    p.add_argument(
        "--linesearch-steps",
        type=int,
        default=4,
        help="L-BFGS: most trial steps (forward evaluations) per iteration",
    )
    p.add_argument(
        "--time-budget",
        type=float,
        default=None,
        help="wall-time budget [s]: afbl tune: of the whole command (compilation and "
        "evaluation included); tune-compare: of each run's iterations; default: none",
    )
    p.add_argument("--lr", type=float, default=0.05, help="Adam: peak step, in z units")
    p.add_argument(
        "--schedule",
        default="cosine",
        choices=["cosine", "constant"],
        help="Adam: learning-rate schedule",
    )
    p.add_argument("--clip-norm", type=float, default=1.0, help="Adam: gradient clipping norm")
    p.add_argument("--sigma", type=float, default=0.2, help="CMA-ES: initial step (z units)")
    p.add_argument(
        "--population", type=int, default=None, help="CMA-ES population; default: 4 + 3 ln 12"
    )
    p.add_argument(
        "--w-attitude", type=float, default=1.0, help="weight of ISE_att / paper's ISE_att"
    )
    p.add_argument(
        "--w-altitude", type=float, default=1.0, help="weight of ISE_alt / paper's ISE_alt"
    )
    p.add_argument("--w-effort", type=float, default=0.0, help="weight of effort / paper's")
    p.add_argument("--w-saturation", type=float, default=0.0, help="weight of saturation / paper's")
    p.add_argument(
        "--w-divergence",
        type=float,
        default=10.0,
        help="weight of the failure hinge (margin) or added per failed case (step)",
    )
    p.add_argument(
        "--effort-limit",
        type=float,
        default=1.0,
        help="limit: mean effort <= this x the paper's gains' (inf: none)",
    )
    p.add_argument(
        "--saturation-limit",
        type=float,
        default=1.0,
        help="limit: mean saturation <= this x the paper's gains' (floored at 1e-4 s)",
    )
    p.add_argument("--penalty", type=float, default=100.0, help="weight of limit violations")
    p.add_argument(
        "--failure",
        default="margin",
        choices=["margin", "step"],
        help="failure term: margin (saturated softplus hinge on the smooth failure margin, "
        "continuous in the gains) or step (a constant per failed case)",
    )
    p.add_argument(
        "--reserve", type=float, default=0.3, help="margin reserve where the hinge starts"
    )
    p.add_argument(
        "--margin-temperature",
        type=float,
        default=0.025,
        help="temperature of the smooth margin and the hinge",
    )
    p.add_argument(
        "--loss-cap",
        type=float,
        default=50.0,
        help="cap of a case's performance term (a failed case costs cap + w_divergence)",
    )
    p.add_argument(
        "--cvar-temperature",
        type=float,
        default=0.05,
        help="beta of the smoothed CVaR (0: exact mean of the worst cases)",
    )
    p.add_argument(
        "--dtype",
        default="float64",
        choices=["float64", "float32"],
        help="precision of the training solves",
    )
    p.add_argument("--lower", type=float, default=0.1, help="gain box: lower x paper gains")
    p.add_argument("--upper", type=float, default=10.0, help="gain box: upper x paper gains")
    p.add_argument(
        "--thrust-to-weight",
        type=float,
        default=2.5,
        help="rotor limit at nominal mass; 0 = unlimited",
    )
    p.add_argument("--rtol", type=float, default=1e-6, help="relative tolerance")
    p.add_argument("--atol", type=float, default=1e-8, help="absolute tolerance")
    p.add_argument(
        "--max-steps", type=int, default=4096, help="solver steps per run with continuous control"
    )
    p.add_argument(
        "--max-steps-interval",
        type=int,
        default=64,
        help="solver steps per sample interval (digital control; gradient memory grows with it)",
    )
    p.add_argument(
        "--gradient-chunk",
        type=int,
        default=32,
        help="most cases one reverse pass differentiates at a time (a multiple of 4): the "
        "gradient's memory is bounded by one chunk per device, not the training set; "
        "with several devices, every device gets a chunk",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress lines")


def register(sub) -> None:
    p = sub.add_parser(
        "tune",
        formatter_class=Formatter,
        help="tune controller gains (L-BFGS, Adam or CMA-ES through the simulation)",
        description="Optimise the gains on realistic training cases (full plant, motor lag, "
        "digital control; noise off) with a normalised objective and limits. Writes "
        "OUT/gains.json, history.csv, convergence.png, before_after.png, meta.json, "
        "evaluation.{txt,json} (held-out cases with noise: paper vs tuned) and a checkpoint.",
    )
    add_tuning_args(p)
    p.add_argument(
        "--seed", type=seed, default=0, help="seed of the training cases, in [0, 2^63 - 1]"
    )
    p.add_argument("--heldout-cases", type=int, default=1024, help="fresh held-out cases")
    p.add_argument(
        "--heldout-seed",
        type=seed,
        default=None,
        help="seed of the held-out cases; default: seed + 1",
    )
    add_out(p)
    p.add_argument(
        "--checkpoint-every", type=int, default=10, help="iterations between checkpoints in OUT"
    )
    p.add_argument("--resume", action="store_true", help="continue from OUT's checkpoint")
    p.add_argument(
        "--no-figures", action="store_true", help="skip convergence.png and before_after.png"
    )
    add_cluster(p, "the CMA-ES populations (--method cmaes or hybrid)")
    p.set_defaults(func=run)


def check_tuning_args(args) -> None:
    check_tolerances(args)
    if args.time_budget is not None and not (
        math.isfinite(args.time_budget) and args.time_budget > 0
    ):
        raise UsageError(f"--time-budget must be a number of seconds > 0, got {args.time_budget}.")
    from ..studies.tuning import ObjectiveConfig

    try:
        ObjectiveConfig(
            cvar_temperature=args.cvar_temperature,
            reserve=args.reserve,
            loss_cap=args.loss_cap,
            margin_temperature=args.margin_temperature,
            gradient_chunk=args.gradient_chunk,
        )
    except ValueError as e:
        raise UsageError(str(e)) from None
    if args.linesearch_steps < 1:
        raise UsageError(f"--linesearch-steps must be >= 1, got {args.linesearch_steps}.")
    if args.cmaes_generations < 1:
        raise UsageError(f"--cmaes-generations must be >= 1, got {args.cmaes_generations}.")
    if args.cases < 1 or args.steps < 0:
        raise UsageError(f"need --cases >= 1 and --steps >= 0, got {args.cases}, {args.steps}.")


def config_from_args(args, seed_value: int = 0):
    from ..studies.tuning import ObjectiveConfig, TuneConfig

    ocfg = ObjectiveConfig(
        objective=args.objective,
        risk=args.risk,
        cvar_level=args.cvar_level,
        cvar_temperature=args.cvar_temperature,
        failure=args.failure,
        reserve=args.reserve,
        loss_cap=args.loss_cap,
        margin_temperature=args.margin_temperature,
        w_attitude=args.w_attitude,
        w_altitude=args.w_altitude,
        w_effort=args.w_effort,
        w_saturation=args.w_saturation,
        w_divergence=args.w_divergence,
        effort_limit=args.effort_limit,
        saturation_limit=args.saturation_limit,
        penalty=args.penalty,
        dtype=args.dtype,
        rtol=args.rtol,
        atol=args.atol,
        max_steps=args.max_steps,
        max_steps_interval=args.max_steps_interval,
        gradient_chunk=args.gradient_chunk,
    )
    return TuneConfig(
        controller=args.controller,
        objective=ocfg,
        n_cases=args.cases,
        seed=getattr(args, "seed", seed_value),
        steps=args.steps,
        method=args.method,
        linesearch_steps=args.linesearch_steps,
        time_budget=args.time_budget,
        learning_rate=args.lr,
        schedule=args.schedule,
        clip_norm=args.clip_norm,
        sigma=args.sigma,
        population=args.population,
        lower=args.lower,
        upper=args.upper,
        thrust_to_weight=args.thrust_to_weight or None,
        checkpoint_every=getattr(args, "checkpoint_every", 0),
        cmaes_generations=args.cmaes_generations,
    )


def run(args) -> int:
    started = time.perf_counter()
    from ..studies.tuning import run_tuning

    check_tuning_args(args)
    if args.heldout_cases < 1:
        raise UsageError(f"--heldout-cases must be >= 1, got {args.heldout_cases}.")
    if args.heldout_seed is None and args.seed == MAX_SEED:
        raise UsageError(
            f"--seed {args.seed} leaves no default held-out seed (seed + 1 > 2^63 - 1); "
            "give --heldout-seed."
        )
    executor = executor_from_args(args)
    if executor is not None and args.method not in ("cmaes", "hybrid"):
        raise UsageError(
            f"--scheduler/--workers evaluate CMA-ES populations on a cluster; --method "
            f"{args.method} takes one gradient step at a time in this process: use --method "
            "cmaes or hybrid, or leave them out."
        )
    check_out(args.out)
    config = config_from_args(args)
    run_tuning(
        config,
        args.out,
        resume=args.resume,
        heldout_cases=args.heldout_cases,
        heldout_seed=args.heldout_seed,
        figures=not args.no_figures,
        progress=not args.no_progress,
        executor=executor,
        started=started,
    )
    print(
        f"wrote {args.out}/gains.json, history.csv, evaluation.txt/json, meta.json"
        + ("" if args.no_figures else ", convergence.png, before_after.png")
    )
    return 0
