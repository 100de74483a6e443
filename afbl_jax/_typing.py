"""jaxtyping aliases used across the package (one place)."""

from jaxtyping import Array, ArrayLike, Bool, Float, Int

Scalar = Float[Array, ""]
ScalarLike = float | Float[ArrayLike, ""]
Vec3 = Float[Array, "3"]
Vec4 = Float[Array, "4"]
PlantState = Float[Array, "12"]
"""Plant state, layout documented in `afbl_jax._plant` (``STATE_LAYOUT``)."""

__all__ = [
    "Array",
    "ArrayLike",
    "Bool",
    "Float",
    "Int",
    "PlantState",
    "Scalar",
    "ScalarLike",
    "Vec3",
    "Vec4",
]
