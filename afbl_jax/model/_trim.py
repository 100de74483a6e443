"""Trim and flight envelope: the equilibrium a vehicle needs in a steady wind, and whether it
can fly it.

Trim (`solve_trim`): at a given velocity v (earth frame; 0 for position hold, the mean wind for
a vehicle drifting with the air), yaw psi and mass, find the attitude (phi, theta) and the
commanded inputs u = (u1, u2, u3, u4) [N, N, N m, N] for which every acceleration of the plant
vanishes with the body at rest in rotation:

    (xdd, ydd, zdd, phidd, thetadd, psidd) = 0

where the applied inputs are those of the squared rotor speeds the mixer commands with the
controller's ``model`` (W = M_model^-1 u, not clipped: the trim says what the vehicle would
need), produced by the true ``vehicle`` (u_applied = M_vehicle W), and the aerodynamic wrench
of the steady wind w at the rotor speeds sqrt(W) (`afbl_jax.model.AbstractAerodynamics`).
Six equations in six unknowns, solved by Newton's method (`optimistix.Newton`) from level
hover, on the imbalance written as force / weight and torque / (weight x arm length) (the
accelerations times mass or inertia), so that the tolerance means the same for any vehicle;
at zero body rates the paper plant (eq. 15) and the rigid body share this equilibrium.
With `LinearDrag` and no centre-of-pressure offset the tilt is atan(c_d |w - v| / (m g)).

Flight envelope (`envelope_margin`): a trim is flyable when it exists (Newton converged to an
imbalance below `trim_residual_bound`), its tilt acos(cos phi cos theta) is within the tilt
limit and every rotor keeps a reserve: W_i <= (1 - reserve) Omega_max^2 (thrust left for
control torque) and W_i >= Omega_min^2. The margin is the smallest of 1 - tilt / tilt_limit and
1 - max_i W_i / ((1 - reserve) Omega_max^2) (and of (min_i W_i - Omega_min^2) / W_hover); it is
>= 0 exactly inside the envelope (`ENVELOPE_CAUSES` names the binding limit).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._typing import Array, Float, Int, Scalar, Vec3
from .._validation import as_float, check_nonnegative, concrete
from ._aero import AbstractAerodynamics
from ._mixer import inputs_from_rotor_speeds_sq, omega_d, rotor_speeds_sq_from_inputs, safe_sqrt
from ._params import QuadrotorParams
from ._plant import plant_derivative

TRIM_RESIDUAL = 1e-8
"""Largest force / weight or torque / (weight x arm length) imbalance [-] a converged trim may
leave in float64; below float64 the bound is `trim_residual_bound` of the dtype."""
ENVELOPE_CAUSES: tuple[str, ...] = ("inside", "no_trim", "tilt", "rotor_max", "rotor_min")
"""Envelope status codes: 0 inside; else the limit that binds (no equilibrium found, tilt
limit, rotor reserve at the top speed, rotor minimum speed)."""


class Trim(eqx.Module):
    """An equilibrium: attitude (phi, theta) [rad], shape (2,), and the commanded inputs u
    (u1, u2, u3, u4) [N, N, N m, N], shape (4,), that hold it."""

    attitude: Float[Array, 2] = eqx.field(converter=as_float)
    command: Float[Array, 4] = eqx.field(converter=as_float)


class TrimSolution(eqx.Module):
    """`solve_trim`'s result.

    Attributes:
        trim: the equilibrium (`Trim`).
        rotor_speeds_sq: squared rotor speeds W the trim needs (the model's mixer, not clipped)
            [rad^2/s^2], shape (4,).
        residual: largest remaining imbalance, force / weight or torque / (weight x arm
            length) [-].
        converged: Newton converged and the residual is below `trim_residual_bound` of the
            dtype (`TRIM_RESIDUAL` in float64).
    """

    trim: Trim
    rotor_speeds_sq: Float[Array, 4]
    residual: Scalar
    converged: Array

    @property
    def tilt(self) -> Scalar:
        """acos(cos phi cos theta) [rad]: the angle between thrust axis and vertical (written
        as atan2 of the thrust axis' horizontal and vertical parts, differentiable at 0)."""
        return tilt_angle(self.trim.attitude[..., 0], self.trim.attitude[..., 1])


def tilt_angle(phi, theta) -> Array:
    """acos(cos phi cos theta) [rad], the tilt of the thrust axis from the vertical, as
    atan2(|horizontal part|, vertical part) of the body z axis (zero gradient at level)."""
    h2 = jnp.sin(phi) ** 2 + (jnp.cos(phi) * jnp.sin(theta)) ** 2
    positive = h2 > 0
    horizontal = jnp.where(positive, jnp.sqrt(jnp.where(positive, h2, 1.0)), 0.0)
    return jnp.arctan2(horizontal, jnp.cos(phi) * jnp.cos(theta))


def trim_residual_bound(dtype) -> float:
    """Largest imbalance [-] a converged trim may leave in ``dtype``: `TRIM_RESIDUAL`, or
    32 machine epsilons where that is larger (3.8e-6 in float32, whose rounding alone leaves
    imbalances of about 1e-7)."""
    return max(TRIM_RESIDUAL, 32.0 * float(jnp.finfo(dtype).eps))


def _imbalance(x, args):
    vehicle, model, aerodynamics, wind, velocity, mass, psi = args
    attitude, u_cmd = x[:2], x[2:]
    state = jnp.concatenate(
        [jnp.zeros(3, x.dtype), attitude, psi[None], velocity, jnp.zeros(3, x.dtype)]
    )
    w = rotor_speeds_sq_from_inputs(model, u_cmd)
    u = inputs_from_rotor_speeds_sq(vehicle, w)
    omega = safe_sqrt(w)
    force, torque = aerodynamics.wrench(wind, state, vehicle, omega)
    acc = plant_derivative(vehicle, state, u, omega_d(omega), mass, force, torque)[6:12]
    weight = mass * vehicle.g
    inertia = jnp.stack([vehicle.Ix, vehicle.Iy, vehicle.Iz])
    return jnp.concatenate(
        [acc[:3] * mass / weight, acc[3:] * inertia / (weight * vehicle.arm_length)]
    )


def solve_trim(
    vehicle: QuadrotorParams,
    model: QuadrotorParams,
    aerodynamics: AbstractAerodynamics,
    wind_velocity: Vec3,
    velocity: Vec3,
    mass: Scalar,
    psi: Scalar = 0.0,
    *,
    max_steps: int = 32,
) -> TrimSolution:
    """The equilibrium (module docstring) of ``vehicle`` flown by a controller with nominal
    ``model`` at earth-frame ``velocity`` [m/s] in the steady wind ``wind_velocity`` [m/s],
    with true mass ``mass`` [kg] and yaw ``psi`` [rad]. Pure and jittable (vmap over cases);
    never raises: check ``converged``."""
    dtype = jnp.result_type(float)
    wind = jnp.asarray(wind_velocity, dtype)
    velocity = jnp.asarray(velocity, dtype)
    mass = jnp.asarray(mass, dtype)
    psi = jnp.asarray(psi, dtype)
    x0 = jnp.zeros(6, dtype).at[5].set(mass * vehicle.g)
    args = (vehicle, model, aerodynamics, wind, velocity, mass, psi)
    tol = 1e-12 if dtype == jnp.float64 else 1e-6
    sol = optx.root_find(
        _imbalance,
        optx.Newton(rtol=tol, atol=tol),
        jax.lax.stop_gradient(x0),
        jax.lax.stop_gradient(args),
        max_steps=max_steps,
        throw=False,
    )
    x = jax.lax.stop_gradient(sol.value)
    residual = jnp.max(jnp.abs(_imbalance(x, args)))
    ok = (sol.result == optx.RESULTS.successful) & (residual < trim_residual_bound(dtype))
    ok = ok & jnp.all(jnp.isfinite(x))
    # one Newton step from the root, differentiable in the inputs: its value is the root (the
    # imbalance vanishes there) and its derivative that of the implicit function theorem,
    # -J^-1 df/d(inputs); where no root was found, a step from level hover (finite, the case
    # is outside the envelope)
    x = jnp.where(ok, x, jax.lax.stop_gradient(x0))
    jac = jax.jacfwd(_imbalance)(x, args)
    x = x - jnp.linalg.solve(jac, _imbalance(x, args))
    return TrimSolution(Trim(x[:2], x[2:]), rotor_speeds_sq_from_inputs(model, x[2:]), residual, ok)


class EnvelopeLimits(eqx.Module):
    """What a trim must leave for control to count as flyable.

    Attributes:
        tilt: largest trim tilt [rad] (below the position loop's command limit, so that some
            tilt is left to reject disturbances).
        rotor_reserve: fraction of each rotor's top thrust b Omega_max^2 kept for control
            torque at trim, in [0, 1).
    """

    tilt: Scalar = eqx.field(default=0.6, converter=as_float)
    rotor_reserve: Scalar = eqx.field(default=0.2, converter=as_float)

    def __check_init__(self):
        owner = type(self).__name__
        tilt = concrete(self.tilt)
        if tilt is not None and not np.all((tilt > 0) & (tilt < np.pi / 2)):
            raise ValueError(f"{owner}.tilt must lie in (0, pi/2) [rad], got {tilt!r}.")
        check_nonnegative(owner, "rotor_reserve", self.rotor_reserve)
        reserve = concrete(self.rotor_reserve)
        if reserve is not None and not np.all(reserve < 1):
            raise ValueError(f"{owner}.rotor_reserve must be < 1, got {reserve!r}.")


def envelope_margin(
    solution: TrimSolution, vehicle: QuadrotorParams, limits: EnvelopeLimits
) -> tuple[Scalar, Int[Array, ""]]:
    """(margin, cause) of a trim (module docstring): margin >= 0 and cause 0 inside the
    envelope; otherwise cause indexes `ENVELOPE_CAUSES` (the limit with the smallest margin;
    1 where no trim exists, margin -inf)."""
    w = solution.rotor_speeds_sq
    w_top = (1.0 - limits.rotor_reserve) * vehicle.omega_max**2
    w_hover = vehicle.m * vehicle.g / (4.0 * vehicle.b)
    # minima and maxima of a few entries as elementwise ones: the gradient of a reduction is
    # taken through an equality with its result, which a fused compilation can round apart
    w_max = jnp.maximum(jnp.maximum(w[0], w[1]), jnp.maximum(w[2], w[3]))
    w_min = jnp.minimum(jnp.minimum(w[0], w[1]), jnp.minimum(w[2], w[3]))
    margins = (
        1.0 - solution.tilt / limits.tilt,
        1.0 - w_max / w_top,
        (w_min - vehicle.omega_min**2) / w_hover,
    )
    margin = jnp.minimum(jnp.minimum(margins[0], margins[1]), margins[2])
    cause = jnp.where(margin >= 0, 0, 2 + jnp.argmin(jax.lax.stop_gradient(jnp.stack(margins))))
    margin = jnp.where(solution.converged, margin, -jnp.inf)
    cause = jnp.where(solution.converged, cause, 1)
    return margin, cause.astype(jnp.int32)


def combine_margins(*pairs) -> tuple[Scalar, Int[Array, ""]]:
    """The binding (smallest) of several (margin, cause) pairs (e.g. the mean wind and the
    wind after a gust)."""
    margin, cause = pairs[0]
    for m, c in pairs[1:]:
        cause = jnp.where(m < margin, c, cause)
        margin = jnp.minimum(margin, m)
    return margin, cause
