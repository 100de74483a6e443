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


def as_float(x):
    """``x`` as a JAX array of JAX's default float dtype (the converter of every float field)."""
    import jax.numpy as jnp

    return jnp.asarray(x, dtype=jnp.result_type(float))
