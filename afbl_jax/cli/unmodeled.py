"""``afbl unmodeled`` (the unmodeled-dynamics study) and the unmodeled-dynamics flags of
``afbl reproduce``."""

from __future__ import annotations

import argparse

from ._common import (
    Formatter,
    UsageError,
    add_controllers,
    add_out,
    check_out,
    controllers_from_args,
    floats,
    seed,
)


def add_unmodeled_arguments(p: argparse.ArgumentParser) -> None:
    """Flags of `afbl reproduce` selecting unmodeled dynamics (defaults: the paper's model)."""
    g = p.add_argument_group("unmodeled dynamics (defaults: the paper's model, continuous control)")
    g.add_argument(
        "--plant",
        choices=["paper", "full"],
        default="paper",
        help="plant model: paper eq. 15 or the full rigid body",
    )
    g.add_argument(
        "--motor-tau",
        type=float,
        default=0.0,
        metavar="SECONDS",
        help="rotor time constant tau_m [s] (0: instantaneous rotors)",
    )
    g.add_argument(
        "--control-rate",
        type=float,
        default=None,
        metavar="HZ",
        help="digital controller rate f_c [Hz] with zero-order hold (default: "
        "continuous controller)",
    )
    g.add_argument(
        "--delay-samples",
        type=int,
        default=0,
        help="measurement delay in control samples (needs --control-rate)",
    )
    g.add_argument(
        "--noise",
        type=float,
        default=0.0,
        metavar="LEVEL",
        help="measurement noise as a multiple of the nominal standard deviations "
        "(angle 0.005 rad, rate 0.02 rad/s, z 0.02 m, zd 0.05 m/s; needs "
        "--control-rate)",
    )
    g.add_argument("--seed", type=seed, default=0, help="noise seed, in [0, 2^63 - 1]")


def unmodeled_from_args(args, duration: float = 20.0):
    """`UnmodeledDynamics` from the flags, or None when all are at their defaults."""
    from ..studies.unmodeled import NOMINAL_NOISE

    if not args.motor_tau >= 0:
        raise UsageError(f"--motor-tau must be >= 0 [s], got {args.motor_tau}.")
    if args.control_rate is not None and not args.control_rate > 0:
        raise UsageError(f"--control-rate must be > 0 [Hz], got {args.control_rate}.")
    if args.delay_samples < 0 or not args.noise >= 0:
        raise UsageError("--delay-samples and --noise must be >= 0.")
    if args.control_rate is None and (args.delay_samples or args.noise):
        raise UsageError("--delay-samples and --noise need --control-rate.")
    if args.plant == "paper" and args.motor_tau == 0 and args.control_rate is None:
        return None
    from ..model import UnmodeledDynamics

    noise = {k: args.noise * v for k, v in NOMINAL_NOISE.items()}
    return UnmodeledDynamics.make(
        plant=args.plant,
        motor_tau=args.motor_tau,
        control_rate=args.control_rate,
        duration=duration,
        delay_samples=args.delay_samples,
        seed=args.seed,
        **noise,
    )


def register(sub) -> None:
    p = sub.add_parser(
        "unmodeled",
        formatter_class=Formatter,
        help="FBL vs AFBL under unmodeled dynamics: ISE and failure rate over tau_m x f_c x noise",
        description="Runs the four canonical scenarios for every cell of a motor-time-constant x "
        "control-rate x noise-level grid (digital control with a measurement delay, full "
        "rigid-body plant by default) and writes OUT/unmodeled_dynamics.json, "
        "OUT/unmodeled_dynamics.txt and OUT/stability_boundary_<controller>.png.",
    )
    add_out(p)
    add_controllers(p, "fbl,afbl")
    p.add_argument(
        "--taus", type=floats, default="0,0.02,0.04,0.06,0.1", help="motor time constants [s]"
    )
    p.add_argument("--rates", type=floats, default="50,100,250,500", help="control rates [Hz]")
    p.add_argument(
        "--noise-levels",
        type=floats,
        default="0,1",
        help="noise levels, multiples of the nominal standard deviations",
    )
    p.add_argument("--seeds", type=int, default=2, help="noise seeds per scenario")
    p.add_argument(
        "--delay-samples", type=int, default=1, help="measurement delay in control samples"
    )
    p.add_argument(
        "--plant",
        choices=["paper", "full"],
        default="full",
        help="plant model: paper eq. 15 or the full rigid body",
    )
    p.add_argument(
        "--seed", type=seed, default=0, help="base noise seed (the runs use seed + 1000 s + j)"
    )
    p.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..studies.unmodeled import (
        UnmodeledStudyConfig,
        format_study_table,
        run_unmodeled_study,
        write_study,
    )

    check_out(args.out)
    controllers = controllers_from_args(args)
    if args.delay_samples < 0 or args.seeds < 1:
        raise UsageError("--delay-samples must be >= 0 and --seeds >= 1.")
    if not args.taus or not args.rates or not args.noise_levels:
        raise UsageError("--taus, --rates and --noise-levels need at least one value each.")
    if (
        any(t < 0 for t in args.taus)
        or any(r <= 0 for r in args.rates)
        or any(n < 0 for n in args.noise_levels)
    ):
        raise UsageError("motor taus must be >= 0 s, rates > 0 Hz, noise levels >= 0.")
    result = run_unmodeled_study(
        UnmodeledStudyConfig(
            controllers,
            taus=tuple(args.taus),
            rates=tuple(args.rates),
            noise_levels=tuple(args.noise_levels),
            n_seeds=args.seeds,
            plant=args.plant,
            delay_samples=args.delay_samples,
            seed=args.seed,
        )
    )
    path = write_study(result, args.out)
    print(format_study_table(result))
    if not args.no_figures:
        from ..plotting.unmodeled import plot_stability_boundary

        paths = plot_stability_boundary(result, args.out)
        print(f"wrote {path} and {len(paths)} figures to {args.out}/")
    return 0
