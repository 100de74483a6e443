"""The ``afbl`` command: one module per subcommand over the public API.

`main` splits the CPU into one XLA device per core (before JAX starts), switches JAX's 64-bit
mode on once (before any gains or distribution file is read, so numbers keep full precision),
parses the arguments and runs the subcommand. Every user error takes one path: a single line
``afbl <command>: error: <what was wrong and what is allowed>`` on stderr, exit status 2.
"""

from __future__ import annotations

import argparse
import sys

from . import bench, montecarlo, reproduce, tune, unmodeled
from ._common import UsageError

SUBCOMMANDS = (reproduce, montecarlo, unmodeled, tune, bench)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="afbl", description="Quadrotor FBL+PID / adaptive FBL studies in JAX."
    )
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


def main(argv: list[str] | None = None) -> int:
    """Run ``afbl`` with ``argv`` (default: the command line); returns the exit status."""
    _configure_devices()
    import jax

    jax.config.update("jax_enable_x64", True)
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except UsageError as err:
        print(f"afbl {args.command}: error: {err}", file=sys.stderr)
        return 2
    except ValueError as err:  # validation of files and settings in the library
        print(f"afbl {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
