"""``afbl reproduce``: the paper reproduction (ISE table, ise.json, Figs. 8-21)."""

from __future__ import annotations

import sys

from ._common import (
    Formatter,
    UsageError,
    add_controllers,
    add_out,
    check_out,
    check_tolerances,
    controllers_from_args,
)
from .unmodeled import add_unmodeled_arguments, unmodeled_from_args


def register(sub) -> None:
    p = sub.add_parser(
        "reproduce",
        formatter_class=Formatter,
        help="run the paper's scenarios for fbl, afbl, afbl_paper; print ISE; write figures",
        description="Paper reproduction: {ideal, uncertain} x {step, sine} x controllers. Prints "
        "the ISE table beside the paper's Tables 4/5 and writes OUT/ise.json and OUT/fig*.png. "
        "Exits with status 1 if any run failed or diverged.",
    )
    add_out(p)
    add_controllers(p, "fbl,afbl,afbl_paper")
    p.add_argument(
        "--solver",
        default="tsit5",
        choices=["tsit5", "dopri5", "dopri8"],
        help="diffrax Runge-Kutta solver",
    )
    p.add_argument("--rtol", type=float, default=1e-8, help="relative tolerance")
    p.add_argument("--atol", type=float, default=1e-10, help="absolute tolerance")
    p.add_argument("--n-save", type=int, default=2001, help="saved samples per run (>= 2)")
    p.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    p.add_argument(
        "--gyro-sign",
        choices=["eq14", "physical"],
        default="eq14",
        help="rotor gyroscopic sign: eq14 = eq. (14) as printed (the faithful reproduction); "
        "physical = the sign that matches the rotor spin directions of eq. (16), the default "
        "of every other study (docs/paper_notes.md section 5)",
    )
    add_unmodeled_arguments(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from ..studies.reproduce import (
        ReproduceConfig,
        format_ise_table,
        run_reproduction,
        write_ise_json,
    )

    if args.n_save < 2:
        raise UsageError(f"--n-save must be >= 2, got {args.n_save}.")
    check_tolerances(args)
    check_out(args.out)
    from ..model import EQ14_GYRO_SIGN, PHYSICAL_GYRO_SIGN

    gyro_sign = EQ14_GYRO_SIGN if args.gyro_sign == "eq14" else PHYSICAL_GYRO_SIGN
    controllers = controllers_from_args(args)
    settings = unmodeled_from_args(args)
    print(
        f"running {len(controllers)} controllers x 4 scenarios ({args.solver}, rtol="
        f"{args.rtol:g}, atol={args.atol:g}, gyroscopic sign {args.gyro_sign}) ...",
        flush=True,
    )
    result = run_reproduction(
        ReproduceConfig(
            controllers,
            solver=args.solver,
            rtol=args.rtol,
            atol=args.atol,
            n_save=args.n_save,
            unmodeled=settings,
            gyro_sign=gyro_sign,
        )
    )
    args.out.mkdir(parents=True, exist_ok=True)
    write_ise_json(result, args.out / "ise.json")
    print(format_ise_table(result))
    if not args.no_figures:
        from ..plotting.paper import plot_paper_figures

        paths = plot_paper_figures(result.runs, args.out)
        print(f"\nwrote {args.out / 'ise.json'} and {len(paths)} figures to {args.out}/")
    failures = result.failures()
    for key, name, why in failures:
        print(f"FAILED: {key} / {name}: {why}", file=sys.stderr)
    return 1 if failures else 0
