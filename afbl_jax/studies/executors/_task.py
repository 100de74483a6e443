"""What every executor runs for a task, and the error of a cluster that cannot finish one."""

from __future__ import annotations

import os
import socket
import sys
import time
from collections.abc import Callable
from typing import Any


class ClusterError(RuntimeError):
    """A cluster could not finish a task (e.g. every worker that took it died, more often than
    ``distributed.scheduler.allowed-failures``)."""


class TaskInfo(dict):
    """Where and when a task ran: ``worker`` (its address; "local" in this process), ``host``,
    ``pid``, ``devices`` (its JAX devices), ``start_utc`` (Unix time [s]) and ``seconds`` (wall
    time of the task function on the worker)."""


def run_task(fn: Callable, item) -> tuple[Any, TaskInfo]:
    """``fn(item)`` with a `TaskInfo`; what every executor runs for every task."""
    import jax

    start = time.time()
    t0 = time.perf_counter()
    result = fn(item)
    seconds = time.perf_counter() - t0
    worker = "local"
    if "distributed" in sys.modules:  # never imported by a one-process run
        from distributed import get_worker

        try:
            worker = get_worker().address
        except ValueError:  # not in a worker
            pass
    info = TaskInfo(
        worker=worker,
        host=socket.gethostname(),
        pid=os.getpid(),
        devices=len(jax.local_devices()),
        start_utc=start,
        seconds=seconds,
    )
    return result, info
