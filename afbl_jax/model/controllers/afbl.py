"""Adaptive feedback linearization (paper eqs. 31-40; gains Table 3).

Both variants estimate a lumped disturbance delta per channel (qdd = v + delta on the
linearized model) and use v = rdd - delta_hat + K * error, d(delta_hat)/dt = -error / gamma.

- `AFBL` (default, ``"afbl"``) uses the composite error s = ed + lambda e: with
  V = s^2/2 + gamma (delta_hat - delta)^2 / 2 one gets dV/dt = -K s^2 for constant delta, and
  s -> 0 drives e -> 0 with time constant 1/lambda. lambda is our addition (default 4 1/s).
- `AFBLPaper` (``"afbl_paper"``) is eqs. (33), (37), (40) verbatim: the error is the rate error
  e = rd - qd. Integrating (37) shows it is a PD law with P = 1/gamma and D = K and no integral
  action, so position errors are corrected slowly and a constant disturbance (payload) leaves a
  growing altitude error. See docs/paper_notes.md.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx

from ..._typing import Array, Vec4
from ._base import AbstractController, ReferenceSample, as_gain

PAPER_AFBL_GAINS = {
    "gamma": (8.0, 15.0, 8.0, 20.0),
    "k": (8.0, 15.0, 8.0, 80.0),
}
"""Table 3, channel order (phi, theta, psi, z)."""
DEFAULT_LAMBDA = (4.0, 4.0, 4.0, 4.0)
"""Composite-error slope lambda [1/s] of `AFBL` (not in the paper)."""


class AFBL(AbstractController):
    """AFBL on the composite error s = ed + lam * e.

    v = rdd + lam ed - delta_hat + k s,  d(delta_hat)/dt = -s / gamma.
    The controller state is delta_hat per channel [rad/s^2 or m/s^2].

    Attributes:
        gamma: adaptation gains (the estimate moves at 1/gamma per unit error), shape (4,).
        k: error-feedback gains [1/s], shape (4,).
        lam: composite-error slopes [1/s], shape (4,).
    """

    name: ClassVar[str] = "afbl"
    gain_names: ClassVar[tuple[str, ...]] = ("gamma", "k", "lam")

    gamma: Array = eqx.field(default=PAPER_AFBL_GAINS["gamma"], converter=as_gain)
    k: Array = eqx.field(default=PAPER_AFBL_GAINS["k"], converter=as_gain)
    lam: Array = eqx.field(default=DEFAULT_LAMBDA, converter=as_gain)

    def virtual_input(
        self, e: Vec4, ed: Vec4, ref: ReferenceSample, state: Vec4
    ) -> tuple[Vec4, Vec4]:
        s = ed + self.lam * e
        return ref.rdd + self.lam * ed - state + self.k * s, -s / self.gamma

    def state_for(self, v: Vec4, ref: ReferenceSample) -> Vec4:
        return ref.rdd - v


class AFBLPaper(AbstractController):
    """AFBL exactly as printed: rate error e = rd - qd (eq. 33).

    v = rdd - delta_hat + k e,  d(delta_hat)/dt = -e / gamma.

    Attributes:
        gamma: adaptation gains, shape (4,).
        k: error-feedback gains [1/s], shape (4,).
    """

    name: ClassVar[str] = "afbl_paper"
    gain_names: ClassVar[tuple[str, ...]] = ("gamma", "k")

    gamma: Array = eqx.field(default=PAPER_AFBL_GAINS["gamma"], converter=as_gain)
    k: Array = eqx.field(default=PAPER_AFBL_GAINS["k"], converter=as_gain)

    def virtual_input(
        self, e: Vec4, ed: Vec4, ref: ReferenceSample, state: Vec4
    ) -> tuple[Vec4, Vec4]:
        del e
        return ref.rdd - state + self.k * ed, -ed / self.gamma

    def state_for(self, v: Vec4, ref: ReferenceSample) -> Vec4:
        return ref.rdd - v
