"""One controller type for every law, so that one compiled program serves them all.

A compiled closed loop is specific to its controller's class: FBL+PID and AFBL solves of the same
cases are two programs, each compiled on its own. `AnyController` holds one instance of every
law (`FBLPID`, `AFBL`, `AFBLPaper`) and a dynamic index of the one that acts; each law computes
its output and the index selects it (`jax.lax.select_n`), so the closed loop of any law has the
same structure and array shapes, and a study of both controllers compiles its programs once.

The acting law's outputs are its own operations, selected, so results are those of the law's own
class up to the rounding that XLA's code generation may change between two programs (a
multiply-add contracted into one instruction or not); the other laws add a few operations per
evaluation on (4,)-vectors, and their gains get zero gradient.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import equinox as eqx
import jax
import numpy as np

from ..._typing import Array, Vec4
from ._base import AbstractController, ReferenceSample
from .afbl import AFBL, AFBLPaper
from .fbl_pid import FBLPID

LAWS: tuple[type[AbstractController], ...] = (FBLPID, AFBL, AFBLPaper)
"""The laws an `AnyController` holds, in the order of its index."""


def _paper_gains(law: type[AbstractController]) -> dict[str, np.ndarray]:
    """The default gains of ``law`` as NumPy arrays (no JAX array is made, so this works inside
    a trace too)."""
    return {
        f.name: np.asarray(f.default) for f in dataclasses.fields(law) if f.name in law.gain_names
    }


class AnyController(AbstractController):
    """Every law side by side; ``law`` (int32 scalar, dynamic) is the index in `LAWS` of the one
    that acts. Build it with `AnyController.of`; `acting` gives the acting law back.

    Attributes:
        law: index of the acting law in `LAWS`, an int32 array of shape ().
        laws: one instance of each class of `LAWS`, in that order; the others hold the paper's
            gains (broadcast to the acting law's gain shape and dtype).
    """

    name: ClassVar[str] = "any"
    gain_names: ClassVar[tuple[str, ...]] = ()

    law: Array
    laws: tuple[FBLPID, AFBL, AFBLPaper]

    def __check_init__(self):
        if tuple(type(c) for c in self.laws) != LAWS:
            raise TypeError(
                f"AnyController: laws must be instances of {', '.join(c.__name__ for c in LAWS)} "
                f"in that order, got {', '.join(type(c).__name__ for c in self.laws)}."
            )

    @classmethod
    def of(cls, controller: AbstractController) -> AnyController:
        """``controller`` (an instance of a class of `LAWS`, or an `AnyController`) as an
        `AnyController` acting with it."""
        if isinstance(controller, AnyController):
            return controller
        if type(controller) not in LAWS:
            raise TypeError(
                f"AnyController.of: controller must be one of "
                f"{', '.join(c.__name__ for c in LAWS)}, got {type(controller).__name__}."
            )
        # as the acting gains: shape, dtype, device and whether committed to it (a jit's cache
        # tells committed and uncommitted arguments apart)
        like = getattr(controller, controller.gain_names[0])
        committed = isinstance(like, jax.Array) and like.committed

        def alike(x, shape=like.shape, dtype=like.dtype):
            x = np.broadcast_to(np.asarray(x, dtype), shape)
            return jax.device_put(x, like.sharding if committed else None)

        # the other laws: the paper's gains, validated by the class, then set to exactly those
        # arrays (the class's converter would give them the default float dtype)
        def paper(law):
            gains = {g: alike(x) for g, x in _paper_gains(law).items()}
            return eqx.tree_at(
                lambda c: [getattr(c, g) for g in gains], law(**gains), [*gains.values()]
            )

        laws = tuple(controller if law is type(controller) else paper(law) for law in LAWS)
        return cls(alike(LAWS.index(type(controller)), (), np.int32), laws)

    def acting(self) -> AbstractController:
        """The acting law's own controller (``law`` must be concrete)."""
        return self.laws[int(self.law)]

    def init_state(self) -> Vec4:
        return self._select([c.init_state() for c in self.laws])

    def state_for(self, v: Vec4, ref: ReferenceSample) -> Vec4:
        return self._select([c.state_for(v, ref) for c in self.laws])

    def virtual_input(
        self, e: Vec4, ed: Vec4, ref: ReferenceSample, state: Vec4
    ) -> tuple[Vec4, Vec4]:
        outs = [c.virtual_input(e, ed, ref, state) for c in self.laws]
        return self._select([v for v, _ in outs]), self._select([d for _, d in outs])

    def _select(self, values):
        return jax.lax.select_n(self.law, *values)
