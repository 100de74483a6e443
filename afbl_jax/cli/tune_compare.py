"""``afbl tune-compare``: the tuner's comparison studies, one command each."""

from __future__ import annotations

import json

from ._common import Formatter, UsageError, add_out, check_out, seed
from .tune import add_tuning_args, check_tuning_args, config_from_args


def register(sub) -> None:
    p = sub.add_parser(
        "tune-compare",
        formatter_class=Formatter,
        help="compare optimisers, or tuned FBL+PID vs tuned AFBL, or measure gradient cost",
        description="optimizers: objective vs wall time of L-BFGS, Adam and CMA-ES (same cases "
        "and --time-budget per seed; OUT/loss_vs_time.png, optimizers.json). controllers: "
        "FBL+PID and AFBL tuned alike, evaluated on fresh held-out cases with noise "
        "(OUT/controllers.{txt,json}). gradient-cost: one gradient vs one forward evaluation "
        "of the training cases, float32 and float64 (OUT/gradient_cost.json).",
    )
    p.add_argument(
        "--study",
        required=True,
        choices=["optimizers", "controllers", "gradient-cost"],
        help="optimizers: L-BFGS / Adam / CMA-ES / hybrid on the same cases and budget; "
        "controllers: "
        "FBL+PID and AFBL each tuned, then evaluated on held-out cases; gradient-cost: "
        "value-and-gradient time against the forward evaluation",
    )
    add_tuning_args(p)
    p.add_argument("--seeds", type=seed, nargs="+", default=[0, 1, 2], help="training seeds")
    p.add_argument(
        "--methods",
        nargs="+",
        default=["lbfgs", "adam", "cmaes", "hybrid"],
        choices=["lbfgs", "adam", "cmaes", "hybrid"],
        help="optimizers study: methods to compare",
    )
    p.add_argument("--heldout-cases", type=int, default=1024, help="controllers: held-out cases")
    p.add_argument("--heldout-seed", type=seed, default=1000, help="controllers: held-out seed")
    p.add_argument("--repeats", type=int, default=3, help="gradient-cost: timing repeats")
    add_out(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from ..studies.tuning import (
        compare_controllers,
        compare_optimizers,
        format_controllers,
        gradient_cost,
    )

    check_tuning_args(args)
    if args.study == "controllers" and args.heldout_seed in args.seeds:
        raise UsageError(
            f"--heldout-seed {args.heldout_seed} is also a training seed; give another."
        )
    if args.study != "gradient-cost" and args.time_budget is None:
        raise UsageError(f"--study {args.study} compares at equal wall time: give --time-budget.")
    if args.heldout_cases < 1 or args.repeats < 1:
        raise UsageError("--heldout-cases and --repeats must be >= 1.")
    check_out(args.out)
    args.out.mkdir(parents=True, exist_ok=True)
    base = config_from_args(args, args.seeds[0])
    progress = not args.no_progress
    if args.study == "optimizers":
        compare_optimizers(base, tuple(args.methods), tuple(args.seeds), args.out, progress)
        print(f"wrote {args.out}/optimizers.json, loss_vs_time.png")
    elif args.study == "controllers":
        doc = compare_controllers(
            base, tuple(args.seeds), args.heldout_cases, args.heldout_seed, args.out, progress
        )
        print(format_controllers(doc["heldout"]))
        print(f"wrote {args.out}/controllers.json, controllers.txt")
    else:
        from ..io import run_metadata

        doc = gradient_cost(base, args.repeats)
        doc["meta"] = run_metadata(base.to_dict())
        (args.out / "gradient_cost.json").write_text(json.dumps(doc, indent=1) + "\n")
        print(f"wrote {args.out}/gradient_cost.json")
    return 0
