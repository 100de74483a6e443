"""Shared test helpers (one tolerance-explicit comparison)."""

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
