"""What every subcommand shares: the usage-error type, the parser (one-line errors), shared
flags (defined once), the output-folder check and the controllers-with-gains-files logic."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from .._validation import MAX_SEED


class UsageError(ValueError):
    """A user error: printed as one line ``afbl <command>: error: ...``, exit status 2."""


def one_line(text: str, limit: int = 2000) -> str:
    """``text`` on one line (line breaks shown as spaces), at most ``limit`` characters."""
    flat = " ".join(str(text).split("\n")).replace("\r", " ")
    return flat if len(flat) <= limit else flat[: limit - 5] + " ..."


class Parser(argparse.ArgumentParser):
    """argparse with every error on ONE line, ``<prog>: error: <message> (see <prog> --help)``,
    exit status 2, like the errors the subcommands raise (argparse's own would print the usage
    block first)."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {one_line(message)} (see {self.prog} --help)\n")


class Formatter(argparse.ArgumentDefaultsHelpFormatter):
    """Help text with each flag's default ("(default: ...)"), unless the help text already says
    it or there is none to show (None, an off switch, an empty list)."""

    def _get_help_string(self, action):
        text = action.help or ""
        if "default" in text or action.default in (None, False, []):
            return text
        return super()._get_help_string(action)


def add_out(p: argparse.ArgumentParser, help: str = "output folder (created)") -> None:
    p.add_argument("--out", required=True, type=Path, help=help)


def check_out(path: Path) -> None:
    """Refuse an --out that cannot become a writable folder, creating nothing: an existing
    file, a path below a file, a read-only file system or a folder without write permission."""
    path = Path(path)
    if path.exists():
        if not path.is_dir():
            raise UsageError(
                f"--out {path} is an existing file; give a folder (created if missing)."
            )
        where = path
    else:
        where = path.absolute().parent
        while not where.exists():
            where = where.parent
        if not where.is_dir():
            raise UsageError(
                f"--out {path} lies below {where}, which is a file, not a folder; give a "
                "folder path."
            )
    read_only = hasattr(os, "statvfs") and bool(os.statvfs(where).f_flag & os.ST_RDONLY)
    if read_only or not os.access(where, os.W_OK | os.X_OK):
        why = "is on a read-only file system" if read_only else "is not writable for this user"
        what = "" if where == path else f" cannot be created: {where}"
        raise UsageError(f"--out {path}{what} {why}; give a writable folder.")


def seed(text: str) -> int:
    """argparse type: a seed, an integer in [0, 2^63 - 1]."""
    try:
        value = int(text)
    except ValueError:
        value = None
    if value is None or not 0 <= value <= MAX_SEED:
        raise argparse.ArgumentTypeError(
            f"expected an integer in [0, 2^63 - 1] = [0, {MAX_SEED}], got {text!r}"
        )
    return value


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
        if value is not None and not 0 < value < float("inf"):
            raise UsageError(f"--{name} must be a finite number > 0, got {value}.")


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


def add_cluster(p: argparse.ArgumentParser, what: str) -> None:
    """``--scheduler ADDRESS`` / ``--workers N``: run ``what`` as tasks of a Dask cluster."""
    g = p.add_argument_group(
        "Dask cluster (needs the cluster extra: pip install afbl-jax[cluster])",
        f"run {what} as tasks of a Dask cluster: every worker sets JAX up once (CPU devices, "
        "compilation cache, 64-bit mode) and the numbers are those of a one-process run",
    )
    g.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="address of a running Dask scheduler (e.g. tcp://host:8786; from `dask scheduler` "
        "or dask-jobqueue's SLURMCluster/PBSCluster) (default: none, this process computes)",
    )
    g.add_argument(
        "--workers",
        type=int,
        default=None,
        metavar="N",
        help="start a Dask LocalCluster of N worker processes on this machine (one thread and "
        "cores / N CPU devices each) for this command (default: none, this process computes)",
    )


def executor_from_args(args):
    """The executor of ``--scheduler`` / ``--workers`` (None: this process); refuses both at
    once, N < 1 and a missing Dask installation."""
    import importlib.util

    if args.scheduler is None and args.workers is None:
        return None
    if args.scheduler is not None and args.workers is not None:
        raise UsageError(
            "give --scheduler (a running cluster) or --workers (a LocalCluster here), not both."
        )
    if args.workers is not None and args.workers < 1:
        raise UsageError(f"--workers must be >= 1, got {args.workers}.")
    if importlib.util.find_spec("distributed") is None:
        raise UsageError(
            "--scheduler/--workers need Dask: pip install afbl-jax[cluster] (dask[distributed], "
            "dask-jobqueue)."
        )
    from ..studies.executors import DaskExecutor

    return DaskExecutor(address=args.scheduler, n_workers=args.workers)


def executor_words(executor) -> str:
    """How the command's header line names where it runs ("" in this process)."""
    if executor is None:
        return ""
    if executor.address is None:
        return f", Dask LocalCluster of {executor.n_workers} worker processes"
    return f", Dask scheduler {executor.address}"
