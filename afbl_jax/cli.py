"""`afbl` command line: thin subcommands over the public API."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ._unmodeled_cli import add_unmodeled_arguments, add_unmodeled_subcommand, unmodeled_from_args
from .tuning._study import add_tune_parser


def _enable_x64() -> None:
    import jax

    jax.config.update("jax_enable_x64", True)


def _add_reproduce(sub) -> None:
    p = sub.add_parser(
        "reproduce",
        help="run the paper's scenarios for fbl, afbl, afbl_paper; print ISE; write figures",
        description="Paper reproduction: {ideal, uncertain} x {step, sine} x controllers. Prints "
        "the ISE table beside the paper's Tables 4/5 and writes OUT/ise.json and OUT/fig*.png. "
        "Exits with status 1 if any run failed or diverged.",
    )
    p.add_argument("--out", required=True, type=Path, help="output folder (created)")
    p.add_argument("--gains", action="append", default=[], type=Path, metavar="FILE",
                   help="gains JSON replacing the paper gains of its controller (repeatable)")
    p.add_argument("--controllers", default="fbl,afbl,afbl_paper",
                   help="comma-separated subset of fbl,afbl,afbl_paper (default: all)")
    p.add_argument("--solver", default="tsit5", choices=["tsit5", "dopri5", "dopri8"])
    p.add_argument("--rtol", type=float, default=1e-8)
    p.add_argument("--atol", type=float, default=1e-10)
    p.add_argument("--n-save", type=int, default=2001, help="saved samples per run (>= 2)")
    p.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    add_unmodeled_arguments(p)
    p.set_defaults(func=_cmd_reproduce)


def _cmd_reproduce(args) -> int:
    from . import CONTROLLERS, make_controller
    from ._gains_io import load_gains
    from ._reproduce import format_ise_table, run_reproduction, write_ise_json

    names = [n.strip() for n in args.controllers.split(",") if n.strip()]
    bad = [n for n in names if n not in CONTROLLERS]
    if bad or not names:
        raise SystemExit(f"afbl reproduce: unknown controller(s) {bad or names}; allowed: "
                         f"{', '.join(CONTROLLERS)}.")
    if args.n_save < 2:
        raise SystemExit("afbl reproduce: --n-save must be >= 2.")
    if not (args.rtol > 0 and args.atol > 0):
        raise SystemExit("afbl reproduce: --rtol and --atol must be > 0.")
    controllers = {n: make_controller(n) for n in names}
    for path in args.gains:
        try:
            ctrl = load_gains(path)
        except ValueError as err:
            raise SystemExit(f"afbl reproduce: {err}") from None
        controllers[ctrl.name] = ctrl
    _enable_x64()
    print(f"running {len(controllers)} controllers x 4 scenarios ({args.solver}, rtol="
          f"{args.rtol:g}, atol={args.atol:g}) ...", flush=True)
    result = run_reproduction(controllers, solver=args.solver, rtol=args.rtol, atol=args.atol,
                              n_save=args.n_save, unmodeled=unmodeled_from_args(args))
    args.out.mkdir(parents=True, exist_ok=True)
    write_ise_json(result, args.out / "ise.json")
    print(format_ise_table(result))
    if not args.no_figures:
        from .plotting import plot_paper_figures

        paths = plot_paper_figures(result.runs, args.out)
        print(f"\nwrote {args.out / 'ise.json'} and {len(paths)} figures to {args.out}/")
    failures = result.failures()
    for key, name, why in failures:
        print(f"FAILED: {key} / {name}: {why}", file=sys.stderr)
    return 1 if failures else 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="afbl", description="Quadrotor FBL+PID / adaptive FBL studies in JAX.")
    sub = parser.add_subparsers(dest="command", required=True)
    _add_reproduce(sub)
    from .montecarlo._study import add_merge_subcommand
    from .montecarlo._study import add_subcommand as _add_montecarlo

    _add_montecarlo(sub)
    add_merge_subcommand(sub)
    add_unmodeled_subcommand(sub)
    add_tune_parser(sub)
    from ._bench import add_bench_parser

    add_bench_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """The ``afbl`` command. Run from the command line (``argv`` None), it first splits the CPU
    into one XLA device per core (`afbl_jax.configure_cpu_devices`; ``AFBL_CPU_DEVICES=1``
    keeps one); called with an explicit ``argv`` (tests, scripts) it leaves devices alone."""
    if argv is None:
        from ._devices import configure_cpu_devices

        try:
            configure_cpu_devices()
        except (RuntimeError, ValueError) as err:
            print(f"afbl: warning: {err}", file=sys.stderr)
    parser = build_parser()
    args = parser.parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
