"""Shared test helpers (one tolerance-explicit comparison)."""

import os

import jax
import numpy as np


def tree_allclose(x, y, *, rtol: float, atol: float) -> bool:
    """True when two pytrees have equal structure and all leaves are close."""
    lx, tx = jax.tree.flatten(x)
    ly, ty = jax.tree.flatten(y)
    if tx != ty:
        return False
    return all(
        np.shape(a) == np.shape(b) and np.allclose(a, b, rtol=rtol, atol=atol, equal_nan=True)
        for a, b in zip(lx, ly, strict=True)
    )


class count_compiles:
    """Context manager counting XLA compilations inside it (``.count``), through JAX's public
    monitoring events: a second call with the same shapes must add none (no retracing)."""

    def __enter__(self):
        import jax.monitoring

        self.count = 0

        def listener(event, duration, **kwargs):
            if event == "/jax/core/compile/backend_compile_duration":
                self.count += 1

        self._listener = listener
        jax.monitoring.register_event_duration_secs_listener(listener)
        return self

    def __exit__(self, *exc):
        import jax.monitoring

        jax.monitoring.unregister_event_duration_listener(self._listener)
        return False


def subprocess_env(**overrides: str) -> dict[str, str]:
    """This process's environment for a subprocess, without a host device count in
    ``XLA_FLAGS`` (the subprocess chooses its own; the test session's other XLA flags stay, so
    that it shares the session's compiled programs), with ``overrides`` set."""
    flags = [
        f
        for f in os.environ.get("XLA_FLAGS", "").split()
        if not f.startswith("--xla_force_host_platform_device_count")
    ]
    return {**os.environ, "XLA_FLAGS": " ".join(flags), **overrides}
