"""``afbl tune``: gains by gradient descent through the simulation."""

from __future__ import annotations

from ._common import Formatter, add_out


def register(sub) -> None:
    p = sub.add_parser(
        "tune",
        formatter_class=Formatter,
        help="tune controller gains by gradient descent through the simulation",
        description="Optimise log-gains with optax through the diffrax closed loop. Writes "
        "OUT/gains.json, history.csv, convergence.png, before_after.png, meta.json, "
        "evaluation.{txt,json} (held-out cases, paper vs tuned) and a checkpoint.",
    )
    p.add_argument("--controller", default="afbl", choices=["afbl", "fbl"])
    p.add_argument("--objective", default="robust", choices=["nominal", "robust"])
    p.add_argument(
        "--risk",
        default="mean",
        choices=["mean", "cvar"],
        help="robust objective: mean or CVaR over the cases",
    )
    p.add_argument("--cvar-level", type=float, default=0.9)
    p.add_argument("--cases", type=int, default=64, help="training cases (robust)")
    p.add_argument("--steps", type=int, default=100)
    p.add_argument("--seed", type=int, default=0, help="seed of the training cases")
    p.add_argument("--heldout-cases", type=int, default=None, help="default: --cases")
    p.add_argument("--heldout-seed", type=int, default=None, help="default: seed + 1")
    add_out(p)
    p.add_argument("--optimizer", default="adam", choices=["adam", "sgd"])
    p.add_argument("--lr", type=float, default=0.05, help="peak step in log-gain units")
    p.add_argument("--schedule", default="cosine", choices=["cosine", "constant"])
    p.add_argument("--clip-norm", type=float, default=1.0)
    p.add_argument("--w-altitude", type=float, default=1.0)
    p.add_argument("--w-effort", type=float, default=1e-4)
    p.add_argument("--w-saturation", type=float, default=1.0)
    p.add_argument("--w-divergence", type=float, default=1.0)
    p.add_argument("--lower", type=float, default=0.1, help="gain box: lower x paper gains")
    p.add_argument("--upper", type=float, default=10.0, help="gain box: upper x paper gains")
    p.add_argument(
        "--thrust-to-weight",
        type=float,
        default=2.5,
        help="rotor limit at nominal mass; 0 = unlimited",
    )
    p.add_argument("--rtol", type=float, default=1e-6)
    p.add_argument("--atol", type=float, default=1e-8)
    p.add_argument("--max-steps", type=int, default=8192)
    p.add_argument("--checkpoint-every", type=int, default=10)
    p.add_argument("--resume", action="store_true", help="continue from OUT's checkpoint")
    p.add_argument("--no-figures", action="store_true")
    p.add_argument("--no-progress", action="store_true")
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
