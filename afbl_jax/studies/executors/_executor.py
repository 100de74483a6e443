"""Where a study's batches of simulations run: in this process (`LocalExecutor`, the default) or
as tasks of a Dask cluster (`DaskExecutor`).

An executor is a small configuration object; ``executor.session()`` opens it (a Dask client,
and the cluster too for a local one) as a context manager whose session runs tasks:
``session.imap(fn, items)`` yields ``(item, fn(item), info)`` as tasks finish, taking items
from ``items`` only as task slots free up (so a caller may hold a lock per item it hands
out), and ``session.map(fn, items)`` returns ``[fn(item) for item in items]`` in order.
``info`` says where and when a task ran (`TaskInfo`). The task functions are the ones a
one-process run calls, so a study's numbers do not depend on its executor. This module
imports no Dask: `DaskExecutor.session` imports it on first use (`afbl_jax.studies.executors`
with the ``cluster`` extra installed).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Protocol

from ._task import TaskInfo, run_task


class Session(Protocol):
    """An open executor (`LocalExecutor.session`, `DaskExecutor.session`)."""

    record: dict
    """Provenance: ``kind`` ("local" or "dask"), and for Dask the scheduler's address, whether
    the cluster was started for this run, and its workers at the start (address -> host, pid,
    JAX devices, threads, afbl-jax version and git revision)."""

    def imap(self, fn: Callable, items: Iterable) -> Iterator[tuple[Any, Any, TaskInfo]]: ...

    def map(self, fn: Callable, items: Sequence) -> list: ...

    def slots(self) -> int:
        """Tasks that can run at once now (1 in this process)."""
        ...

    def note(self) -> str:
        """A few words for a progress bar ("" in this process)."""
        ...


class LocalSession:
    """Runs every task in this process, one after the other, in order."""

    record = {"kind": "local"}

    def imap(self, fn, items):
        for item in items:
            result, info = run_task(fn, item)
            yield item, result, info

    def map(self, fn, items):
        return [fn(item) for item in items]

    def slots(self) -> int:
        return 1

    def note(self) -> str:
        return ""


@dataclass(frozen=True)
class LocalExecutor:
    """Every task in this process, one after the other (the default of every study)."""

    @contextmanager
    def session(self) -> Iterator[Session]:
        yield LocalSession()


@dataclass(frozen=True)
class DaskExecutor:
    """Tasks on a Dask cluster (``pip install afbl-jax[cluster]``).

    Attributes:
        address: the scheduler of a running cluster (``tcp://host:8786``; a
            ``dask_jobqueue.SLURMCluster``'s ``scheduler_address``); None: a
            ``distributed.LocalCluster`` on this machine, started for the session and closed
            after it.
        n_workers: worker processes of that LocalCluster (one thread each; None: one per core);
            only without ``address``.
        cpu_devices: XLA CPU devices per worker (`afbl_jax.configure_cpu_devices`); None: the
            cores over the workers for a LocalCluster, else each worker's
            ``$AFBL_CPU_DEVICES``, else 1.
        retries: times a task that raised is run again (``Client.submit(retries=...)``). A
            task whose worker died is rescheduled by the scheduler without counting here (up to
            ``distributed.scheduler.allowed-failures`` deaths, then `ClusterError`).
        timeout: seconds to wait for the scheduler (None: Dask's
            ``distributed.comm.timeouts.connect``, 30 s by default).

    Workers start without fork (``distributed.worker.multiprocessing-method`` "spawn": JAX is
    multithreaded) and set JAX up once, through a worker plugin, before their first task
    (workers that join later too): their CPU devices, the compilation cache
    (`afbl_jax.configure_compilation_cache`, each worker's own default) and the client's
    64-bit mode. Opening the session raises ValueError (before anything is written) when the
    scheduler does not answer or a worker cannot import this package.
    """

    address: str | None = None
    n_workers: int | None = None
    cpu_devices: int | None = None
    retries: int = 1
    timeout: float | None = None

    def __post_init__(self):
        if self.address is not None and not _is_address(self.address):
            raise ValueError(
                f"a Dask scheduler address is [protocol://]host:port (e.g. tcp://10.0.0.5:8786), "
                f"got {self.address!r}."
            )
        if self.address is not None and self.n_workers is not None:
            raise ValueError(
                "n_workers starts a LocalCluster; with the address of a running cluster leave "
                "it None (that cluster has its own workers)."
            )
        for name in ("n_workers", "cpu_devices"):
            value = getattr(self, name)
            if value is not None and (isinstance(value, bool) or int(value) < 1):
                raise ValueError(f"{name} must be an integer >= 1 (or None), got {value!r}.")
        if isinstance(self.retries, bool) or int(self.retries) < 0:
            raise ValueError(f"retries must be an integer >= 0, got {self.retries!r}.")
        if self.timeout is not None and not 0 < self.timeout < float("inf"):
            raise ValueError(f"timeout must be a number of seconds > 0, got {self.timeout!r}.")

    @contextmanager
    def session(self) -> Iterator[Session]:
        from ._dask import DaskSession

        s = DaskSession(self)
        try:
            yield s
        finally:
            s.close()


def _is_address(address) -> bool:
    """Whether ``address`` looks like ``[protocol://]host:port`` (a port number present)."""
    if not isinstance(address, str):
        return False
    rest = address.split("://", 1)[-1]
    host, _, port = rest.rpartition(":")
    return bool(host) and port.isdigit() and int(port) < 65536


Executor = LocalExecutor | DaskExecutor
"""The executors a study takes (``executor=``; None: `LocalExecutor`)."""


def map_batches(session: Session, fn: Callable, x, batch: int | None):
    """``fn`` over ``x`` (rows) in consecutive batches of at most ``batch`` rows (None: one),
    each batch one task, the results (1-D float64) concatenated in order."""
    import numpy as np

    n = x.shape[0]
    if batch is None or batch >= n:
        parts = [x]
    else:
        parts = [x[i : i + batch] for i in range(0, n, batch)]
    out = session.map(fn, parts)
    return np.concatenate([np.asarray(r, dtype=np.float64) for r in out])
