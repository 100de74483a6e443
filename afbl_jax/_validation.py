"""Construction-time checks that skip traced values (so vmap/jit/grad still work). JAX is imported
only by the checks that need it, so the CLI's argument parsing (`MAX_SEED`) starts without it."""

from __future__ import annotations

import numpy as np

MAX_SEED = 2**63 - 1
"""Largest seed: `jax.random.PRNGKey` takes a signed 64-bit integer (seeds here are >= 0)."""


def check_seed(seed, name: str = "seed") -> int:
    """``seed`` as an int in [0, `MAX_SEED`]; ValueError (saying the range) otherwise."""
    if (
        isinstance(seed, bool)
        or not isinstance(seed, int | np.integer)
        or not (0 <= int(seed) <= MAX_SEED)
    ):
        raise ValueError(f"{name} must be an integer in [0, 2^63 - 1], got {seed!r}.")
    return int(seed)


def concrete(x) -> np.ndarray | None:
    """`x` as a NumPy array, or ``None`` when it is a JAX tracer (inside jit/vmap/grad)."""
    import jax

    if isinstance(x, jax.core.Tracer):
        return None
    try:
        return np.asarray(x)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        return None


def check_finite(owner: str, name: str, x) -> None:
    v = concrete(x)
    if v is not None and not np.all(np.isfinite(v)):
        raise ValueError(f"{owner}.{name} must be finite, got {v!r}.")


def check_positive(owner: str, name: str, x, *, allow_inf: bool = False) -> None:
    v = concrete(x)
    if v is None:
        return
    if np.any(np.isnan(v)):
        raise ValueError(f"{owner}.{name} must be a number > 0, got NaN ({v!r}).")
    if not allow_inf and not np.all(np.isfinite(v)):
        raise ValueError(f"{owner}.{name} must be finite and > 0, got {v!r}.")
    if not np.all(v > 0):
        raise ValueError(f"{owner}.{name} must be > 0, got {v!r}.")


def check_nonnegative(owner: str, name: str, x) -> None:
    v = concrete(x)
    if v is None:
        return
    if np.any(np.isnan(v)) or not np.all(v >= 0):
        raise ValueError(f"{owner}.{name} must be >= 0 (and not NaN), got {v!r}.")


def check_last_dim(owner: str, name: str, x, size: int) -> None:
    shape = np.shape(x)
    if len(shape) == 0 or shape[-1] != size:
        raise ValueError(
            f"{owner}.{name} must have a last dimension of {size} (channel order phi, theta, "
            f"psi, z), got shape {shape}."
        )


def _on_host(x, device_types) -> bool:
    """Whether ``x`` (a number, array or nested sequence) holds no JAX array or tracer."""
    if isinstance(x, list | tuple):
        return all(_on_host(v, device_types) for v in x)
    return not isinstance(x, device_types)


def as_float(x, broadcast: int | None = None):
    """``x`` as a JAX array of JAX's default float dtype (the converter of every float field);
    with ``broadcast`` = n, a scalar becomes n equal entries. Host values (numbers, sequences,
    NumPy arrays) are converted by NumPy and put on the default device, which runs no device
    program; JAX arrays and tracers are converted by `jax.numpy`."""
    import jax
    import jax.numpy as jnp

    dtype = jnp.result_type(float)
    host = _on_host(x, jax.Array | jax.core.Tracer)
    xp = np if host else jnp
    x = xp.asarray(x, dtype=dtype)
    if broadcast is not None and x.ndim == 0:
        x = xp.broadcast_to(x, (broadcast,))
    return jax.device_put(x) if host else x
