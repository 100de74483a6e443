"""CPU devices for the case axis: XLA exposes one CPU device unless told otherwise."""

from __future__ import annotations

import os

_FLAG = "--xla_force_host_platform_device_count"
ENV_VAR = "AFBL_CPU_DEVICES"
"""Environment variable overriding the number of CPU devices `configure_cpu_devices` sets."""
CPU_DEVICES_ENV_VAR = ENV_VAR


def configure_cpu_devices(n: int | None = None) -> int | None:
    """Let XLA split the CPU into ``n`` devices (default: ``$AFBL_CPU_DEVICES``, else the number
    of cores), so `afbl_jax.simulate_batch` and the Monte-Carlo runner can give each core its
    own share of the cases (`jax.shard_map`; with a single CPU device XLA keeps a batched solve
    on about one core).

    Sets ``XLA_FLAGS=--xla_force_host_platform_device_count=n``; it must run before JAX's first
    computation (the ``afbl`` command and the study scripts call it at start-up). Accelerators
    are unaffected (the flag only concerns the host platform). Does nothing and returns None
    when ``XLA_FLAGS`` already sets the count; returns the count set otherwise.

    Raises:
        RuntimeError: JAX's backends are already initialised (the flag would be ignored).
        ValueError: ``n`` (or ``$AFBL_CPU_DEVICES``) is not an integer >= 1.
    """
    flags = os.environ.get("XLA_FLAGS", "")
    if _FLAG in flags:
        return None
    if n is None:
        env = os.environ.get(ENV_VAR)
        try:
            n = int(env) if env is not None else (os.cpu_count() or 1)
        except ValueError:
            raise ValueError(f"${ENV_VAR} must be an integer >= 1, got {env!r}.") from None
    if isinstance(n, bool) or int(n) < 1:
        raise ValueError(f"configure_cpu_devices: n must be an integer >= 1, got {n!r}.")
    from jax._src import xla_bridge

    if xla_bridge.backends_are_initialized():
        raise RuntimeError(
            "configure_cpu_devices must run before JAX's first computation "
            "(its backends are already initialised)."
        )
    os.environ["XLA_FLAGS"] = f"{flags} {_FLAG}={int(n)}".strip()
    return int(n)
