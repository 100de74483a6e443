"""ZYX Euler-angle kinematics, written once.

R = Rz(psi) Ry(theta) Rx(phi) maps body-frame vectors to the earth frame (z up); the body
rates omega = (p, q, r) and the Euler-angle rates etad = (phid, thetad, psid) are related by
etad = T(eta) omega (paper eq. 6-7). Angles in rad, rates in rad/s.
"""

from __future__ import annotations

import jax.numpy as jnp

from .._typing import Array, Scalar, Vec3


def rotation_matrix(phi: Scalar, theta: Scalar, psi: Scalar) -> Array:
    """ZYX rotation matrix R = Rz(psi) Ry(theta) Rx(phi) (body -> earth), shape (3, 3).

    (The paper's eq. 5 has two wrong entries in its first row; see docs/paper_notes.md.)
    """
    cphi, sphi = jnp.cos(phi), jnp.sin(phi)
    cth, sth = jnp.cos(theta), jnp.sin(theta)
    cpsi, spsi = jnp.cos(psi), jnp.sin(psi)
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


def thrust_direction(phi: Scalar, theta: Scalar, psi: Scalar) -> Vec3:
    """Third column of `rotation_matrix`: the body z axis (thrust direction) in the earth frame."""
    return rotation_matrix(phi, theta, psi)[:, 2]


def euler_rates_from_body_rates(phi: Scalar, theta: Scalar, omega: Vec3) -> Vec3:
    """etad = T(eta) omega for ZYX Euler angles (paper eq. 6-7) [rad/s]."""
    p, q, r = omega[0], omega[1], omega[2]
    sphi, cphi = jnp.sin(phi), jnp.cos(phi)
    tth, cth = jnp.tan(theta), jnp.cos(theta)
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
    sphi, cphi = jnp.sin(phi), jnp.cos(phi)
    sth, cth = jnp.sin(theta), jnp.cos(theta)
    return jnp.stack(
        [
            phid - sth * psid,
            cphi * thetad + sphi * cth * psid,
            -sphi * thetad + cphi * cth * psid,
        ]
    )
