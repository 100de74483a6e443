"""Feedback linearization + PID (paper eqs. 24, 28, 29; gains Table 2)."""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx

from ..._typing import Array, Vec4
from ._base import AbstractController, ReferenceSample, as_gain

PAPER_FBL_GAINS = {
    "P": (30.0, 30.0, 30.0, 80.0),
    "I": (8.0, 8.0, 8.0, 10.0),
    "D": (8.0, 8.0, 8.0, 10.0),
}
"""Table 2, channel order (phi, theta, psi, z)."""


class FBLPID(AbstractController):
    """v = P e + I integral(e) + D ed on each channel, then the nominal-model inversion.

    e = r - q, ed = rd - qd (q in phi, theta, psi [rad], z [m]). The controller state is the
    integral of e per channel [rad s or m s].

    Attributes:
        P: proportional gains [1/s^2], shape (4,).
        I: integral gains [1/s^3], shape (4,).
        D: derivative gains [1/s], shape (4,).
    """

    name: ClassVar[str] = "fbl"
    gain_names: ClassVar[tuple[str, ...]] = ("P", "I", "D")

    P: Array = eqx.field(default=PAPER_FBL_GAINS["P"], converter=as_gain)
    I: Array = eqx.field(default=PAPER_FBL_GAINS["I"], converter=as_gain)  # noqa: E741
    D: Array = eqx.field(default=PAPER_FBL_GAINS["D"], converter=as_gain)

    def virtual_input(
        self, e: Vec4, ed: Vec4, ref: ReferenceSample, state: Vec4
    ) -> tuple[Vec4, Vec4]:
        del ref
        return self.P * e + self.I * state + self.D * ed, e

    def state_for(self, v: Vec4, ref: ReferenceSample) -> Vec4:
        del ref
        return v / self.I
