"""ZYX Euler-angle kinematics, written once.

R = Rz(psi) Ry(theta) Rx(phi) maps body-frame vectors to the earth frame (z up); the body
rates omega = (p, q, r) and the Euler-angle rates etad = (phid, thetad, psid) are related by
etad = T(eta) omega (paper eq. 6-7). Angles in rad, rates in rad/s.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .._typing import Array, Scalar, Vec3


def cos_sin(angle: Scalar) -> tuple[Array, Array]:
    """(cos, sin) of an angle [rad], computed once per evaluation: behind an XLA optimization
    barrier, so that a compiler that keeps barriers materialises them instead of recomputing
    them inside every fused consumer (XLA's CPU backend fuses transcendental functions into
    each consumer; `afbl_jax.sim.CPU_COMPILER_OPTIONS` keeps the barriers in the batched
    solves). The values are those of `jnp.cos` and `jnp.sin`; under XLA's default options
    the barrier is removed before fusion."""
    return jax.lax.optimization_barrier((jnp.cos(angle), jnp.sin(angle)))


def rotation_matrix(phi: Scalar, theta: Scalar, psi: Scalar) -> Array:
    """ZYX rotation matrix R = Rz(psi) Ry(theta) Rx(phi) (body -> earth), shape (3, 3).

    (The paper's eq. 5 has two wrong entries in its first row; see docs/paper_notes.md.)
    """
    cphi, sphi = cos_sin(phi)
    cth, sth = cos_sin(theta)
    cpsi, spsi = cos_sin(psi)
    return jnp.stack(
        [
            jnp.stack(
                [cpsi * cth, cpsi * sth * sphi - spsi * cphi, cphi * sth * cpsi + sphi * spsi]
            ),
            jnp.stack(
                [spsi * cth, spsi * sth * sphi + cpsi * cphi, cphi * sth * spsi - sphi * cpsi]
            ),
            jnp.stack([-sth, cth * sphi, cphi * cth]),
        ]
    )


def rotate(m: Array, v: Vec3) -> Vec3:
    """m @ v for a (3, 3) matrix m, as explicit sums of products: on an ensemble XLA fuses
    them with their neighbours, where a batched ``m @ v`` would be a library call per case
    group and a transpose of m."""
    return jnp.stack([m[i, 0] * v[0] + m[i, 1] * v[1] + m[i, 2] * v[2] for i in range(3)])


def rotate_transposed(m: Array, v: Vec3) -> Vec3:
    """m^T @ v for a (3, 3) matrix m (as `rotate`)."""
    return jnp.stack([m[0, i] * v[0] + m[1, i] * v[1] + m[2, i] * v[2] for i in range(3)])


def thrust_direction(phi: Scalar, theta: Scalar, psi: Scalar) -> Vec3:
    """Third column of `rotation_matrix`: the body z axis (thrust direction) in the earth frame."""
    return rotation_matrix(phi, theta, psi)[:, 2]


def euler_rates_from_body_rates(phi: Scalar, theta: Scalar, omega: Vec3) -> Vec3:
    """etad = T(eta) omega for ZYX Euler angles (paper eq. 6-7) [rad/s]."""
    p, q, r = omega[0], omega[1], omega[2]
    cphi, sphi = cos_sin(phi)
    tth, cth = jnp.tan(theta), cos_sin(theta)[0]
    return jnp.stack(
        [
            p + sphi * tth * q + cphi * tth * r,
            cphi * q - sphi * r,
            (sphi * q + cphi * r) / cth,
        ]
    )


def body_rates_from_euler_rates(phi: Scalar, theta: Scalar, etad: Vec3) -> Vec3:
    """omega = T(eta)^-1 etad (inverse of `euler_rates_from_body_rates`) [rad/s]."""
    phid, thetad, psid = etad[0], etad[1], etad[2]
    cphi, sphi = cos_sin(phi)
    cth, sth = cos_sin(theta)
    return jnp.stack(
        [
            phid - sth * psid,
            cphi * thetad + sphi * cth * psid,
            -sphi * thetad + cphi * cth * psid,
        ]
    )
