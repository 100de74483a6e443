"""The Dask side of `DaskExecutor`: the session (client, and a LocalCluster when no address is
given), the worker plugin that sets JAX up, and a worker's description. Imported only when a
Dask session opens."""

from __future__ import annotations

import itertools
import logging
import os
import uuid

import dask
from distributed import Client, LocalCluster, WorkerPlugin, as_completed
from distributed.client import FutureCancelledError
from distributed.scheduler import KilledWorker

from ._task import ClusterError, run_task

PLUGIN_NAME = "afbl-jax-setup"


class JaxSetup(WorkerPlugin):
    """Sets JAX up in a worker process before its first task: ``cpu_devices`` XLA CPU devices
    (None: ``$AFBL_CPU_DEVICES``, else 1; kept as they are when JAX already runs there), the
    compilation cache (`afbl_jax.configure_compilation_cache`) and 64-bit mode ``x64``."""

    name = PLUGIN_NAME

    def __init__(self, x64: bool, cpu_devices: int | None):
        self.x64 = bool(x64)
        self.cpu_devices = cpu_devices

    def setup(self, worker):
        from ...sim import (
            CPU_DEVICES_ENV_VAR,
            configure_compilation_cache,
            configure_cpu_devices,
        )

        n = self.cpu_devices
        if n is None and not os.environ.get(CPU_DEVICES_ENV_VAR):
            n = 1
        try:
            configure_cpu_devices(n)
        except RuntimeError:
            pass  # JAX already runs in this worker: its devices stay
        try:
            configure_compilation_cache()
        except OSError:
            pass  # no cache folder: every program is compiled
        import jax

        jax.config.update("jax_enable_x64", self.x64)


def worker_info(dask_worker=None) -> dict:
    """This worker's host, pid, JAX devices, threads, afbl-jax version and git revision."""
    import socket

    import jax

    from ... import __version__
    from ...io import git_revision

    return {
        "host": socket.gethostname(),
        "pid": os.getpid(),
        "devices": [str(d) for d in jax.local_devices()],
        "threads": None if dask_worker is None else dask_worker.state.nthreads,
        "afbl_jax": __version__,
        "git_revision": git_revision(),
    }


class DaskSession:
    """An open `DaskExecutor` ``config`` (see `afbl_jax.studies.executors.Session`)."""

    def __init__(self, config):
        import jax

        self.config = config
        self.cluster = None
        self.client = None
        self._tag = uuid.uuid4().hex[:8]
        self._count = itertools.count()
        timeout = config.timeout
        if timeout is None:
            timeout = dask.utils.parse_timedelta(
                dask.config.get("distributed.comm.timeouts.connect")
            )
        cpu_devices = config.cpu_devices
        try:
            with dask.config.set({"distributed.worker.multiprocessing-method": "spawn"}):
                if config.address is None:
                    n = config.n_workers or os.cpu_count() or 1
                    if cpu_devices is None:
                        cpu_devices = max(1, (os.cpu_count() or 1) // n)
                    self.cluster = LocalCluster(
                        n_workers=n,
                        threads_per_worker=1,
                        processes=True,
                        dashboard_address=":0",  # a free port: never a clash
                        silence_logs=logging.ERROR,
                    )
                    address = self.cluster.scheduler_address
                else:
                    address = config.address
                try:
                    self.client = Client(address, timeout=timeout, set_as_default=False)
                except Exception as err:  # OSError, TimeoutError, ValueError (bad address)
                    raise ValueError(
                        f"no Dask scheduler answered at {address} within {timeout:g} s "
                        f"({type(err).__name__}: {err}); start one (`dask scheduler`) or give its "
                        "address"
                    ) from None
            try:
                self.client.register_plugin(JaxSetup(jax.config.jax_enable_x64, cpu_devices))
            except Exception as err:
                raise ValueError(
                    f"a Dask worker of {address} could not set up afbl-jax "
                    f"({type(err).__name__}: {err}); every worker needs this package installed "
                    "(pip install afbl-jax[cluster], the same version as here)"
                ) from None
            try:
                workers = self.client.run(worker_info)
            except Exception as err:
                raise ValueError(
                    f"a Dask worker of {address} could not run afbl-jax "
                    f"({type(err).__name__}: {err}); every worker needs this package installed "
                    "(pip install afbl-jax[cluster], the same version as here)"
                ) from None
        except BaseException:
            self.close()
            raise
        self.address = address
        self.record = {
            "kind": "dask",
            "scheduler": address,
            "local_cluster": self.cluster is not None,
            "workers": workers,
        }

    def close(self) -> None:
        if self.client is not None:
            if self.cluster is None:
                try:  # a shared cluster's later workers need not take this client's setup
                    self.client.unregister_worker_plugin(PLUGIN_NAME)
                except Exception:
                    pass
            self.client.close()
            self.client = None
        if self.cluster is not None:
            self.cluster.close()
            self.cluster = None

    def slots(self) -> int:
        return max(1, sum(self.client.nthreads().values()))

    def note(self) -> str:
        n = len(self.client.nthreads())
        return f"{n} Dask worker{'s' if n != 1 else ''}"

    def _submit(self, fn, item):
        key = f"afbl-{self._tag}-{next(self._count)}"
        return self.client.submit(
            run_task, fn, item, key=key, pure=False, retries=self.config.retries
        )

    def imap(self, fn, items):
        """As tasks finish: (item, fn(item), info); at most twice the cluster's task slots in
        flight (refilled before each yield, so workers never wait for the caller)."""
        it = iter(items)
        pending: dict = {}
        done = as_completed(loop=self.client.loop)

        def fill():
            limit = 2 * self.slots()
            while len(pending) < limit:
                try:
                    item = next(it)
                except StopIteration:
                    return
                future = self._submit(fn, item)
                pending[future] = item
                done.add(future)

        try:
            fill()
            while pending:
                future = next(done)
                item = pending.pop(future)
                result, info = _result(future)
                fill()
                yield item, result, info
        finally:
            if pending:
                self.client.cancel(list(pending))

    def map(self, fn, items):
        futures = [self._submit(fn, item) for item in items]
        try:
            return [_result(f)[0] for f in futures]
        finally:
            self.client.cancel([f for f in futures if not f.done()])


def _result(future):
    try:
        return future.result()
    except KilledWorker as err:
        raise ClusterError(
            f"Dask workers died while running a task, more often than "
            f"distributed.scheduler.allowed-failures allows ({err})"
        ) from None
    except FutureCancelledError as err:
        raise ClusterError(f"a Dask task was cancelled ({err})") from None
