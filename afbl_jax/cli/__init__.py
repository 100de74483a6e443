"""The ``afbl`` command: one module per subcommand over the public API.

`main` parses the arguments without importing JAX or the studies (``--help`` and argument
errors answer at once; each subcommand imports what it runs), then splits the CPU into one XLA
device per core (before JAX starts), keeps XLA's compiled programs between runs
(`afbl_jax.configure_compilation_cache`; ``AFBL_COMPILATION_CACHE=off`` for none), switches
JAX's 64-bit mode on once (before any gains or distribution file is read, so numbers keep full
precision) and runs the subcommand. Every user error
takes one path: a single line ``afbl <command>: error: <what was wrong and what is allowed>``
on stderr, exit status 2, no traceback. That includes argparse's own errors (unknown flag, a
value of the wrong type, a missing --out: the line ends with "(see afbl <command> --help)"
instead of argparse's usage block), validation errors of files and settings (ValueError),
operating-system errors (OSError: an unreadable file, a folder that cannot be written), a Dask
scheduler that does not answer and a Dask worker that cannot import the package
(``--scheduler``, ``--workers``). A cluster that loses a task for good (`ClusterError`) prints
one line and exits with status 1. Ctrl-C prints one line and exits with status 130 (a
Monte-Carlo run resumes when the same command is run again).
"""

from __future__ import annotations

import os
import sys

from ..studies.executors import ClusterError
from . import bench, falsify, montecarlo, reproduce, tune, tune_compare, unmodeled
from ._common import Parser, one_line

SUBCOMMANDS = (reproduce, montecarlo, falsify, unmodeled, tune, tune_compare, bench)


def build_parser() -> Parser:
    parser = Parser(prog="afbl", description="Quadrotor FBL+PID / adaptive FBL studies in JAX.")
    sub = parser.add_subparsers(dest="command", required=True)
    for module in SUBCOMMANDS:
        module.register(sub)
    return parser


def _configure_devices() -> None:
    """One XLA CPU device per core, when JAX has not started yet (`configure_cpu_devices`)."""
    from ..sim import configure_cpu_devices

    try:
        configure_cpu_devices()
    except RuntimeError:
        pass  # JAX already running (called from Python): keep its devices
    except ValueError as err:
        print(f"afbl: warning: {err}", file=sys.stderr)


def _configure_cache() -> None:
    """XLA's compiled programs kept between runs (`configure_compilation_cache`); a folder
    that cannot be created costs only the speed-up."""
    from ..sim import configure_compilation_cache

    try:
        configure_compilation_cache()
    except OSError as err:
        print(f"afbl: warning: no compilation cache ({one_line(str(err))})", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    """Run ``afbl`` with ``argv`` (default: the command line); returns the exit status."""
    parser = build_parser()
    try:
        args, extra = parser.parse_known_args(argv)
    except SystemExit as exc:  # --help, or an argparse error already printed as one line
        return exc.code if isinstance(exc.code, int) else 2
    if extra:
        _error(
            args.command,
            f"unrecognized arguments: {' '.join(extra)} (see afbl {args.command} --help)",
        )
        return 2
    _configure_devices()
    import jax

    _configure_cache()

    jax.config.update("jax_enable_x64", True)
    try:
        return _end(int(args.func(args) or 0))
    except ValueError as err:  # UsageError, and validation of files and settings in the library
        _error(args.command, str(err))
        return 2
    except OSError as err:  # a file that cannot be read or written
        what = f"{err.filename}: {err.strerror}" if err.strerror and err.filename else str(err)
        _error(args.command, f"{what}.")
        return 2
    except ClusterError as err:  # a Dask cluster lost a task for good (not the input's fault)
        _error(args.command, f"{err}; run the same command again to resume.")
        return 1
    except KeyboardInterrupt:
        print(f"afbl {args.command}: interrupted", file=sys.stderr)
        return 130


def _end(rc: int) -> int:
    """``rc``, or end the process with it at once when a command abandoned a computation at
    its time budget (still running in a thread: the interpreter's shutdown would abort)."""
    tuning = sys.modules.get("afbl_jax.studies.tuning")
    if tuning is not None and tuning.abandoned_work():
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(rc)
    return rc


def _error(command: str, message: str) -> None:
    print(f"afbl {command}: error: {one_line(message)}", file=sys.stderr)


if __name__ == "__main__":
    sys.exit(main())
