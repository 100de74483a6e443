"""CLI pieces for unmodeled dynamics: `afbl reproduce --plant/--motor-tau/--control-rate/...`
and the `afbl unmodeled` study subcommand."""

from __future__ import annotations

import argparse
from pathlib import Path


def _floats(text: str) -> list[float]:
    try:
        return [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        msg = f"expected comma-separated numbers, got {text!r}"
        raise argparse.ArgumentTypeError(msg) from None


def add_unmodeled_arguments(p: argparse.ArgumentParser) -> None:
    """Flags of `afbl reproduce` selecting unmodeled dynamics (defaults: the paper's model)."""
    g = p.add_argument_group("unmodeled dynamics (defaults: the paper's model, continuous "
                             "control)")
    g.add_argument("--plant", choices=["paper", "full"], default="paper",
                   help="plant model: paper eq. 15 (default) or the full rigid body")
    g.add_argument("--motor-tau", type=float, default=0.0, metavar="SECONDS",
                   help="rotor time constant tau_m [s] (default 0: instantaneous rotors)")
    g.add_argument("--control-rate", type=float, default=None, metavar="HZ",
                   help="digital controller rate f_c [Hz] with zero-order hold (default: "
                   "continuous controller)")
    g.add_argument("--delay-samples", type=int, default=0,
                   help="measurement delay in control samples (needs --control-rate)")
    g.add_argument("--noise", type=float, default=0.0, metavar="LEVEL",
                   help="measurement noise as a multiple of the nominal standard deviations "
                   "(angle 0.005 rad, rate 0.02 rad/s, z 0.02 m, zd 0.05 m/s; needs "
                   "--control-rate)")
    g.add_argument("--seed", type=int, default=0, help="noise seed")


def unmodeled_from_args(args, duration: float = 20.0):
    """`UnmodeledDynamics` from the flags, or None when all are at their defaults."""
    from ._unmodeled_study import NOMINAL_NOISE

    if args.motor_tau < 0:
        raise SystemExit("afbl: --motor-tau must be >= 0 [s].")
    if args.control_rate is not None and not args.control_rate > 0:
        raise SystemExit("afbl: --control-rate must be > 0 [Hz].")
    if args.delay_samples < 0 or args.noise < 0:
        raise SystemExit("afbl: --delay-samples and --noise must be >= 0.")
    if args.control_rate is None and (args.delay_samples or args.noise):
        raise SystemExit("afbl: --delay-samples and --noise need --control-rate.")
    if (args.plant == "paper" and args.motor_tau == 0 and args.control_rate is None):
        return None
    from ._unmodeled import UnmodeledDynamics

    noise = {k: args.noise * v for k, v in NOMINAL_NOISE.items()}
    return UnmodeledDynamics.make(
        plant=args.plant, motor_tau=args.motor_tau, control_rate=args.control_rate,
        duration=duration, delay_samples=args.delay_samples, seed=args.seed, **noise)


def add_unmodeled_subcommand(sub) -> None:
    p = sub.add_parser(
        "unmodeled",
        help="FBL vs AFBL under unmodeled dynamics: ISE and failure rate over tau_m x f_c x noise",
        description="Runs the four canonical scenarios for every cell of a motor-time-constant x "
        "control-rate x noise-level grid (digital control with a measurement delay, full "
        "rigid-body plant by default) and writes OUT/unmodeled_dynamics.json, "
        "OUT/unmodeled_dynamics.txt and OUT/stability_boundary_<controller>.png.",
    )
    p.add_argument("--out", required=True, type=Path, help="output folder (created)")
    p.add_argument("--gains", action="append", default=[], type=Path, metavar="FILE",
                   help="gains JSON replacing the paper gains of its controller (repeatable)")
    p.add_argument("--controllers", default="fbl,afbl",
                   help="comma-separated subset of fbl,afbl,afbl_paper (default: fbl,afbl)")
    p.add_argument("--taus", type=_floats, default="0,0.02,0.04,0.06,0.1",
                   help="motor time constants [s] (default 0,0.02,0.04,0.06,0.1)")
    p.add_argument("--rates", type=_floats, default="50,100,250,500",
                   help="control rates [Hz] (default 50,100,250,500)")
    p.add_argument("--noise-levels", type=_floats, default="0,1",
                   help="noise levels, multiples of the nominal standard deviations (default 0,1)")
    p.add_argument("--seeds", type=int, default=2, help="noise seeds per scenario (default 2)")
    p.add_argument("--delay-samples", type=int, default=1,
                   help="measurement delay in control samples (default 1)")
    p.add_argument("--plant", choices=["paper", "full"], default="full")
    p.add_argument("--seed", type=int, default=0, help="base noise seed")
    p.add_argument("--no-figures", action="store_true")
    p.set_defaults(func=_cmd_unmodeled)


def _cmd_unmodeled(args) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)
    from . import CONTROLLERS, make_controller
    from ._gains_io import load_gains
    from ._unmodeled_study import (
        format_study_table,
        plot_stability_boundary,
        run_unmodeled_study,
        write_study,
    )

    names = [n.strip() for n in args.controllers.split(",") if n.strip()]
    bad = [n for n in names if n not in CONTROLLERS]
    if bad or not names:
        raise SystemExit(f"afbl unmodeled: unknown controller(s) {bad or names}; allowed: "
                         f"{', '.join(CONTROLLERS)}.")
    controllers = {n: make_controller(n) for n in names}
    for path in args.gains:
        try:
            ctrl = load_gains(path)
        except ValueError as err:
            raise SystemExit(f"afbl unmodeled: {err}") from None
        controllers[ctrl.name] = ctrl
    if args.delay_samples < 0 or args.seeds < 1:
        raise SystemExit("afbl unmodeled: --delay-samples must be >= 0 and --seeds >= 1.")
    try:
        result = run_unmodeled_study(
            controllers, taus=args.taus, rates=args.rates, noise_levels=args.noise_levels,
            n_seeds=args.seeds, plant=args.plant, delay_samples=args.delay_samples,
            seed=args.seed)
    except ValueError as err:
        raise SystemExit(f"afbl unmodeled: {err}") from None
    path = write_study(result, args.out)
    print(format_study_table(result))
    if not args.no_figures:
        paths = plot_stability_boundary(result, args.out)
        print(f"wrote {path} and {len(paths)} figures to {args.out}/")
    return 0
