"""The one status enumeration of every solve path, with its messages.

``status`` arrays hold the integer codes; `Status` names them and carries the messages, and
`status_from` is the one conversion from a solve's outcome to a code:

- a run whose state crossed the divergence limits or became non-finite is ``diverged``
  (whatever the solver said: its step control typically fails right after);
- otherwise a solver that ran out of steps is ``max_steps_reached`` and one that stopped for
  another reason (step size collapsed) is ``solver_failed``;
- else ``ok``.

``outside_envelope`` is decided before simulating (`afbl_jax.model.envelope_margin`): the case
asks more than the vehicle can fly (no trim in its mean wind, or a trim beyond the tilt limit
or the rotors' reserve). No solver sets it; a study sets it on such cases, so that they are
never counted as controller failures.

Results tables use the labels ("ok", "diverged", "solver_failed": both solver outcomes are
"solver_failed" there; "outside_envelope").
"""

from __future__ import annotations

import enum

import diffrax
import jax.numpy as jnp

from .._typing import Array


class Status(enum.IntEnum):
    """Outcome of one simulated case (the integer is the ``status`` code)."""

    ok = 0
    diverged = 1
    max_steps_reached = 2
    solver_failed = 3
    outside_envelope = 4

    @property
    def label(self) -> str:
        """Results-table label: "ok", "diverged", "solver_failed" or "outside_envelope"."""
        if self in (Status.max_steps_reached, Status.solver_failed):
            return "solver_failed"
        return self.name

    @property
    def message(self) -> str:
        return _MESSAGES[self]


_MESSAGES = {
    Status.ok: "ok",
    Status.diverged: "diverged: attitude, altitude error or state exceeded the divergence "
    "limits (or became non-finite)",
    Status.max_steps_reached: "solver_failed: max_steps reached before t1 (stiff or too tight "
    "tolerances)",
    Status.solver_failed: "solver_failed: the solver stopped (step size collapsed)",
    Status.outside_envelope: "outside_envelope: the case is outside the vehicle's flight "
    "envelope (no trim in its wind, or a trim past the tilt limit or the rotors' reserve); "
    "not a controller failure",
}

STATUS_OK = int(Status.ok)
STATUS_DIVERGED = int(Status.diverged)
STATUS_MAX_STEPS = int(Status.max_steps_reached)
STATUS_SOLVER_FAILED = int(Status.solver_failed)
STATUS_OUTSIDE_ENVELOPE = int(Status.outside_envelope)
STATUS_NAMES: dict[int, str] = {int(s): s.label for s in Status}
"""Status code -> results-table label."""
STATUS_MESSAGES: dict[int, str] = {int(s): s.message for s in Status}
"""Status code -> human-readable message."""
STATUS_LABELS: tuple[str, ...] = ("ok", "diverged", "solver_failed", "outside_envelope")
"""The labels a results table uses, in report order."""


def status_message(status) -> str:
    """Human-readable meaning of a status code."""
    code = int(status)
    return STATUS_MESSAGES.get(code, f"unknown status {code}")


def status_from(result, diverged) -> Array:
    """Status code from a diffrax ``result`` (`diffrax.RESULTS`; ``event_occurred`` is the
    divergence event of a single solve) and whether the run diverged (crossed the limits or
    became non-finite: the freeze flag of an ensemble case). Broadcasts over cases."""
    solver = jnp.where(
        result == diffrax.RESULTS.successful,
        STATUS_OK,
        jnp.where(
            result == diffrax.RESULTS.max_steps_reached, STATUS_MAX_STEPS, STATUS_SOLVER_FAILED
        ),
    )
    ok_event = result == diffrax.RESULTS.event_occurred
    return jnp.where(diverged | ok_event, STATUS_DIVERGED, solver).astype(jnp.int32)
