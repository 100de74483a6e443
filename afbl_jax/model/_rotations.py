"""ZYX Euler-angle kinematics, written once.

R = Rz(psi) Ry(theta) Rx(phi) maps body-frame vectors to the earth frame (z up); the body
rates omega = (p, q, r) and the Euler-angle rates etad = (phid, thetad, psid) are related by
etad = T(eta) omega (paper eq. 6-7). Angles in rad, rates in rad/s.

Every function takes the sines and cosines of the angles as an optional `AttitudeTrig`
(``trig``; None: computed from the angles), so that a caller evaluating several of them on one
attitude computes the six values once (`attitude_trig`).
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp

from .._typing import Array, Scalar, Vec3


class AttitudeTrig(NamedTuple):
    """Sines and cosines of the ZYX Euler angles (phi, theta, psi)."""

    sphi: Scalar
    cphi: Scalar
    sth: Scalar
    cth: Scalar
    spsi: Scalar
    cpsi: Scalar


def attitude_trig(phi: Scalar, theta: Scalar, psi: Scalar = 0.0) -> AttitudeTrig:
    """sin and cos of phi, theta, psi [rad] (psi 0 where only phi and theta matter)."""
    return AttitudeTrig(
        jnp.sin(phi), jnp.cos(phi), jnp.sin(theta), jnp.cos(theta), jnp.sin(psi), jnp.cos(psi)
    )


def rotation_matrix(
    phi: Scalar, theta: Scalar, psi: Scalar, trig: AttitudeTrig | None = None
) -> Array:
    """ZYX rotation matrix R = Rz(psi) Ry(theta) Rx(phi) (body -> earth), shape (3, 3).

    (The paper's eq. 5 has two wrong entries in its first row; see docs/paper_notes.md.)
    """
    sphi, cphi, sth, cth, spsi, cpsi = attitude_trig(phi, theta, psi) if trig is None else trig
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


def thrust_direction(
    phi: Scalar, theta: Scalar, psi: Scalar, trig: AttitudeTrig | None = None
) -> Vec3:
    """Third column of `rotation_matrix`: the body z axis (thrust direction) in the earth frame."""
    sphi, cphi, sth, cth, spsi, cpsi = attitude_trig(phi, theta, psi) if trig is None else trig
    return jnp.stack([cphi * sth * cpsi + sphi * spsi, cphi * sth * spsi - sphi * cpsi, cphi * cth])


def euler_rates_from_body_rates(
    phi: Scalar, theta: Scalar, omega: Vec3, trig: AttitudeTrig | None = None
) -> Vec3:
    """etad = T(eta) omega for ZYX Euler angles (paper eq. 6-7) [rad/s]."""
    p, q, r = omega[0], omega[1], omega[2]
    if trig is None:
        sphi, cphi = jnp.sin(phi), jnp.cos(phi)
        tth, cth = jnp.tan(theta), jnp.cos(theta)
    else:
        sphi, cphi, cth = trig.sphi, trig.cphi, trig.cth
        tth = trig.sth / trig.cth
    return jnp.stack(
        [
            p + sphi * tth * q + cphi * tth * r,
            cphi * q - sphi * r,
            (sphi * q + cphi * r) / cth,
        ]
    )


def body_rates_from_euler_rates(
    phi: Scalar, theta: Scalar, etad: Vec3, trig: AttitudeTrig | None = None
) -> Vec3:
    """omega = T(eta)^-1 etad (inverse of `euler_rates_from_body_rates`) [rad/s]."""
    phid, thetad, psid = etad[0], etad[1], etad[2]
    if trig is None:
        sphi, cphi = jnp.sin(phi), jnp.cos(phi)
        sth, cth = jnp.sin(theta), jnp.cos(theta)
    else:
        sphi, cphi, sth, cth = trig.sphi, trig.cphi, trig.sth, trig.cth
    return jnp.stack(
        [
            phid - sth * psid,
            cphi * thetad + sphi * cth * psid,
            -sphi * thetad + cphi * cth * psid,
        ]
    )
