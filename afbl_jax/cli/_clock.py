"""When this process started, on `time.perf_counter`'s clock (imported first by `afbl_jax.cli`,
so the ``afbl`` command can say how long its start-up and imports took)."""

from __future__ import annotations

import os
import time

CLI_IMPORTED = time.perf_counter()
"""`time.perf_counter` when `afbl_jax.cli` started to import."""


def _process_age() -> float:
    """Seconds since this process started (Linux: /proc, 10 ms resolution); 0 elsewhere."""
    try:
        with open("/proc/self/stat") as f:
            fields = f.read().rpartition(")")[2].split()
        with open("/proc/uptime") as f:
            uptime = float(f.read().split()[0])
        return max(0.0, uptime - int(fields[19]) / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError):
        return 0.0


PROCESS_START = CLI_IMPORTED - _process_age()
"""`time.perf_counter` at the start of this process (the interpreter's start-up included)."""


def since_start() -> float:
    """Seconds since this process started (`PROCESS_START`)."""
    return time.perf_counter() - PROCESS_START
