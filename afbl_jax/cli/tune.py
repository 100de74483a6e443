"""``afbl tune``: gains by gradient descent through the simulation."""

from __future__ import annotations

from .._validation import MAX_SEED
from ._common import Formatter, UsageError, add_out, check_out, check_tolerances, seed


def register(sub) -> None:
    p = sub.add_parser(
        "tune",
        formatter_class=Formatter,
        help="tune controller gains by gradient descent through the simulation",
        description="Optimise log-gains with optax through the diffrax closed loop. Writes "
        "OUT/gains.json, history.csv, convergence.png, before_after.png, meta.json, "
        "evaluation.{txt,json} (held-out cases, paper vs tuned) and a checkpoint.",
    )
    p.add_argument(
        "--controller", default="afbl", choices=["afbl", "fbl"], help="controller to tune"
    )
    p.add_argument(
        "--objective",
        default="robust",
        choices=["nominal", "robust"],
        help="nominal: the canonical scenarios; robust: sampled Monte-Carlo cases",
    )
    p.add_argument(
        "--risk",
        default="mean",
        choices=["mean", "cvar"],
        help="robust objective: mean or CVaR over the cases",
    )
    p.add_argument(
        "--cvar-level", type=float, default=0.9, help="CVaR level alpha (mean of the worst 1-alpha)"
    )
    p.add_argument("--cases", type=int, default=64, help="training cases (robust)")
    p.add_argument("--steps", type=int, default=100, help="optimiser steps")
    p.add_argument(
        "--seed", type=seed, default=0, help="seed of the training cases, in [0, 2^63 - 1]"
    )
    p.add_argument(
        "--heldout-cases", type=int, default=None, help="held-out cases; default: --cases"
    )
    p.add_argument(
        "--heldout-seed",
        type=seed,
        default=None,
        help="seed of the held-out cases; default: seed + 1",
    )
    add_out(p)
    p.add_argument("--optimizer", default="adam", choices=["adam", "sgd"], help="optax optimiser")
    p.add_argument("--lr", type=float, default=0.05, help="peak step in log-gain units")
    p.add_argument(
        "--schedule",
        default="cosine",
        choices=["cosine", "constant"],
        help="learning-rate schedule",
    )
    p.add_argument(
        "--clip-norm", type=float, default=1.0, help="global-norm gradient clipping threshold"
    )
    p.add_argument(
        "--w-altitude", type=float, default=1.0, help="weight of the altitude ISE in the objective"
    )
    p.add_argument("--w-effort", type=float, default=1e-4, help="weight of the control effort")
    p.add_argument(
        "--w-saturation", type=float, default=1.0, help="weight of the rotor-saturation penalty"
    )
    p.add_argument(
        "--w-divergence", type=float, default=1.0, help="weight of the divergence penalty"
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
    p.add_argument("--max-steps", type=int, default=8192, help="solver step limit per run")
    p.add_argument(
        "--checkpoint-every", type=int, default=10, help="steps between checkpoints in OUT"
    )
    p.add_argument("--resume", action="store_true", help="continue from OUT's checkpoint")
    p.add_argument(
        "--no-figures", action="store_true", help="skip convergence.png and before_after.png"
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def config_from_args(args):
    from ..studies.tuning import ObjectiveConfig, TuneConfig

    ocfg = ObjectiveConfig(
        objective=args.objective,
        risk=args.risk,
        cvar_level=args.cvar_level,
        w_altitude=args.w_altitude,
        w_effort=args.w_effort,
        w_saturation=args.w_saturation,
        w_divergence=args.w_divergence,
        rtol=args.rtol,
        atol=args.atol,
        max_steps=args.max_steps,
    )
    return TuneConfig(
        controller=args.controller,
        objective=ocfg,
        n_cases=args.cases,
        seed=args.seed,
        steps=args.steps,
        optimizer=args.optimizer,
        learning_rate=args.lr,
        schedule=args.schedule,
        clip_norm=args.clip_norm,
        lower=args.lower,
        upper=args.upper,
        thrust_to_weight=args.thrust_to_weight or None,
        checkpoint_every=args.checkpoint_every,
    )


def run(args) -> int:
    from ..studies.tuning import run_tuning

    check_tolerances(args)
    if args.heldout_seed is None and args.seed == MAX_SEED:
        raise UsageError(
            f"--seed {args.seed} leaves no default held-out seed (seed + 1 > 2^63 - 1); "
            "give --heldout-seed."
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
    )
    print(
        f"wrote {args.out}/gains.json, history.csv, evaluation.txt/json, meta.json"
        + ("" if args.no_figures else ", convergence.png, before_after.png")
    )
    return 0
