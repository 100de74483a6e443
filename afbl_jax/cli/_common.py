"""What every subcommand shares: the usage-error type, shared flags (defined once) and the
controllers-with-gains-files logic."""

from __future__ import annotations

import argparse
from pathlib import Path


class UsageError(ValueError):
    """A user error: printed as one line ``afbl <command>: error: ...``, exit status 2."""


class Formatter(argparse.ArgumentDefaultsHelpFormatter):
    """Help text with each flag's default."""


def add_out(p: argparse.ArgumentParser, help: str = "output folder (created)") -> None:
    p.add_argument("--out", required=True, type=Path, help=help)


def add_controllers(p: argparse.ArgumentParser, default: str) -> None:
    p.add_argument(
        "--controllers", default=default, help="comma-separated subset of fbl, afbl, afbl_paper"
    )
    p.add_argument(
        "--gains",
        action="append",
        default=[],
        type=Path,
        metavar="FILE",
        help="gains JSON replacing the paper gains of its controller (repeatable)",
    )


def add_tolerances(p: argparse.ArgumentParser, rtol=None, atol=None, note: str = "") -> None:
    p.add_argument("--rtol", type=float, default=rtol, help="relative tolerance" + note)
    p.add_argument("--atol", type=float, default=atol, help="absolute tolerance" + note)


def add_progress(p: argparse.ArgumentParser) -> None:
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def floats(text: str) -> list[float]:
    """argparse type: comma-separated numbers."""
    try:
        return [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated numbers, got {text!r}"
        ) from None


def check_tolerances(args) -> None:
    for name in ("rtol", "atol"):
        value = getattr(args, name)
        if value is not None and not value > 0:
            raise UsageError(f"--{name} must be a number > 0, got {value}.")


def controllers_from_args(args) -> dict:
    """name -> controller from ``--controllers`` (paper gains) and ``--gains`` files."""
    from ..io import load_gains
    from ..model import CONTROLLERS, make_controller

    names = [n.strip() for n in args.controllers.split(",") if n.strip()]
    bad = [n for n in names if n not in CONTROLLERS]
    if bad or not names:
        raise UsageError(
            f"unknown controller(s) {', '.join(bad) or repr(args.controllers)}; "
            f"allowed: {', '.join(CONTROLLERS)}."
        )
    if len(set(names)) != len(names):
        raise UsageError(f"controller listed twice in --controllers {args.controllers!r}.")
    controllers = {n: make_controller(n) for n in names}
    for path in args.gains:
        ctrl = load_gains(path)
        if ctrl.name not in controllers:
            raise UsageError(
                f"gains file {path} is for {ctrl.name!r}, which is not in "
                f"--controllers ({', '.join(names)})."
            )
        controllers[ctrl.name] = ctrl
    return controllers
