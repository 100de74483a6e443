"""Reference signals with exact first and second derivatives.

A `Reference` is data (a pytree of arrays), so a batch of different references is one
`Reference` with a leading batch axis. Each of the four channels (phi [rad], theta [rad],
psi [rad], z [m]) is

    r(t) = offset + sum_k  size_k * blend((t - start_k) / duration_k)
                  + amplitude * sin(frequency * t + phase)

where blend(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5 for tau in [0, 1] (0 before, 1 after) is the
minimum-jerk step: continuous position, velocity and acceleration, so r, rd and rdd are all
continuous and only the jerk jumps at a blend's start and end.

A `PositionReference` is the same construction on the horizontal position (x, y) [m], the
reference of the position loop (`afbl_jax.model.PositionHold`).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._typing import Array, Float
from .._validation import as_float, check_finite, check_last_dim, check_positive
from ..model import PositionSample, ReferenceSample


def min_jerk_blend(tau):
    """(s, ds/dtau, d2s/dtau2) of the minimum-jerk blend, clipped to tau in [0, 1]."""
    inside = (tau > 0.0) & (tau < 1.0)
    tc = jnp.clip(tau, 0.0, 1.0)
    s = tc**3 * (10.0 - 15.0 * tc + 6.0 * tc**2)
    ds = jnp.where(inside, 30.0 * tc**2 * (1.0 - tc) ** 2, 0.0)
    dds = jnp.where(inside, 60.0 * tc * (1.0 - tc) * (1.0 - 2.0 * tc), 0.0)
    return s, ds, dds


def _slot_sum(x):
    """Sum over the last (slot) axis as elementwise additions: with per-case step sizes a
    reduction becomes one small XLA reduction per case, far slower on a CPU than the adds."""
    total = x[..., 0]
    for k in range(1, x.shape[-1]):
        total = total + x[..., k]
    return total


def _reduce_sum(x):
    return jnp.sum(x, axis=-1)


def _evaluate(ref, t, slot_sum=_reduce_sum):
    """(r, rd, rdd) of a sum of minimum-jerk steps and a sinusoid per channel at time t [s];
    ``slot_sum`` sums over the step slots."""
    tau = (t - ref.step_start) / ref.step_duration
    s, ds, dds = min_jerk_blend(tau)
    r = ref.offset + slot_sum(ref.step_size * s)
    rd = slot_sum(ref.step_size * ds / ref.step_duration)
    rdd = slot_sum(ref.step_size * dds / ref.step_duration**2)
    wt = ref.sine_frequency * t + ref.sine_phase
    a, w = ref.sine_amplitude, ref.sine_frequency
    r = r + a * jnp.sin(wt)
    rd = rd + a * w * jnp.cos(wt)
    rdd = rdd - a * w**2 * jnp.sin(wt)
    return r, rd, rdd


class Reference(eqx.Module):
    """Sum of minimum-jerk steps and a sinusoid per channel (order phi, theta, psi, z).

    Attributes:
        offset: constant value per channel, shape (4,) [rad, rad, rad, m].
        step_start: blend start times, shape (4, S) [s].
        step_size: step heights b - a, shape (4, S) [rad or m]; 0 disables a slot.
        step_duration: blend durations, shape (4, S) [s], > 0.
        sine_amplitude: shape (4,) [rad or m].
        sine_frequency: shape (4,) [rad/s].
        sine_phase: shape (4,) [rad].
    """

    offset: Float[Array, 4] = eqx.field(converter=as_float)
    step_start: Float[Array, "4 S"] = eqx.field(converter=as_float)
    step_size: Float[Array, "4 S"] = eqx.field(converter=as_float)
    step_duration: Float[Array, "4 S"] = eqx.field(converter=as_float)
    sine_amplitude: Float[Array, 4] = eqx.field(converter=as_float)
    sine_frequency: Float[Array, 4] = eqx.field(converter=as_float)
    sine_phase: Float[Array, 4] = eqx.field(converter=as_float)

    def __check_init__(self):
        owner = type(self).__name__
        for name in ("offset", "sine_amplitude", "sine_frequency", "sine_phase"):
            check_last_dim(owner, name, getattr(self, name), 4)
            check_finite(owner, name, getattr(self, name))
        shapes = {np.shape(getattr(self, n)) for n in ("step_start", "step_size", "step_duration")}
        if len(shapes) != 1 or len(next(iter(shapes))) < 2 or next(iter(shapes))[-2] != 4:
            raise ValueError(
                f"{owner}: step_start, step_size and step_duration must share one shape "
                f"(..., 4, S), got {sorted(shapes)}."
            )
        check_finite(owner, "step_start", self.step_start)
        check_finite(owner, "step_size", self.step_size)
        check_positive(owner, "step_duration", self.step_duration)

    def __call__(self, t) -> ReferenceSample:
        """Reference (r, rd, rdd) at time t [s]."""
        return ReferenceSample(*_evaluate(self, t))

    def kink_times(self) -> Array:
        """Start and end of every blend [s]: where the reference's jerk jumps."""
        starts = self.step_start.reshape(-1)
        return jnp.concatenate([starts, starts + self.step_duration.reshape(-1)])


def make_reference(
    steps: dict[str, list[tuple[float, float, float]]] | None = None,
    sines: dict[str, tuple[float, float, float]] | None = None,
    offset: dict[str, float] | None = None,
    step_duration: float = 1.0,
    max_steps: int | None = None,
) -> Reference:
    """Build a `Reference` from readable pieces.

    Args:
        steps: channel -> list of (t0 [s], a, b): minimum-jerk step from a to b starting at t0.
            The value before the first step is taken from ``offset`` (default 0), and each step
            adds b - a; consecutive steps must chain (each a equals the previous b).
        sines: channel -> (amplitude, frequency [rad/s], phase [rad]).
        offset: channel -> constant value before any step.
        step_duration: blend duration [s] (1 s in the canonical scenarios).
        max_steps: number of step slots S per channel (padding with zero-size steps keeps
            references of different step counts stackable); defaults to the largest count.
    Channels are "phi", "theta", "psi", "z".
    """
    names = ("phi", "theta", "psi", "z")
    steps, sines, offset = steps or {}, sines or {}, offset or {}
    for key in (*steps, *sines, *offset):
        if key not in names:
            raise ValueError(f"unknown reference channel {key!r}; allowed: {', '.join(names)}.")
    n = max([len(v) for v in steps.values()] + [0]) if max_steps is None else max_steps
    n = max(n, 1)
    start = np.zeros((4, n))
    size = np.zeros((4, n))
    base = np.array([float(offset.get(c, 0.0)) for c in names])
    for i, c in enumerate(names):
        chan = steps.get(c, [])
        if len(chan) > n:
            raise ValueError(f"channel {c!r} has {len(chan)} steps but max_steps is {n}.")
        level = base[i]
        for k, (t0, a, b) in enumerate(chan):
            if not np.isclose(a, level):
                raise ValueError(
                    f"step {k} of channel {c!r} starts from {a} but the reference is at {level} "
                    "there; steps must chain."
                )
            start[i, k], size[i, k], level = t0, b - a, b
    amp = np.array([sines.get(c, (0.0, 0.0, 0.0))[0] for c in names])
    freq = np.array([sines.get(c, (0.0, 0.0, 0.0))[1] for c in names])
    phase = np.array([sines.get(c, (0.0, 0.0, 0.0))[2] for c in names])
    return Reference(base, start, size, np.full((4, n), float(step_duration)), amp, freq, phase)


class PositionReference(eqx.Module):
    """Horizontal position reference (x, y) [m] for the position loop
    (`afbl_jax.model.PositionHold`): minimum-jerk steps and a sinusoid per channel, as
    `Reference` (fields shaped (2,) and (2, S), channel order x, y; units m, s, rad/s)."""

    offset: Float[Array, 2] = eqx.field(converter=as_float)
    step_start: Float[Array, "2 S"] = eqx.field(converter=as_float)
    step_size: Float[Array, "2 S"] = eqx.field(converter=as_float)
    step_duration: Float[Array, "2 S"] = eqx.field(converter=as_float)
    sine_amplitude: Float[Array, 2] = eqx.field(converter=as_float)
    sine_frequency: Float[Array, 2] = eqx.field(converter=as_float)
    sine_phase: Float[Array, 2] = eqx.field(converter=as_float)

    def __check_init__(self):
        owner = type(self).__name__
        for name in ("offset", "sine_amplitude", "sine_frequency", "sine_phase"):
            if np.shape(getattr(self, name))[-1:] != (2,):
                raise ValueError(
                    f"{owner}.{name} must have a last dimension of 2 (x, y), got shape "
                    f"{np.shape(getattr(self, name))}."
                )
            check_finite(owner, name, getattr(self, name))
        shapes = {np.shape(getattr(self, n)) for n in ("step_start", "step_size", "step_duration")}
        if len(shapes) != 1 or len(next(iter(shapes))) < 2 or next(iter(shapes))[-2] != 2:
            raise ValueError(
                f"{owner}: step_start, step_size and step_duration must share one shape "
                f"(..., 2, S), got {sorted(shapes)}."
            )
        check_finite(owner, "step_start", self.step_start)
        check_finite(owner, "step_size", self.step_size)
        check_positive(owner, "step_duration", self.step_duration)

    def __call__(self, t) -> PositionSample:
        """Position reference (r [m], rd [m/s], rdd [m/s^2]) at time t [s] (its step sizes
        differ between cases: the slots are summed elementwise, `_slot_sum`)."""
        return PositionSample(*_evaluate(self, t, _slot_sum))

    def kink_times(self) -> Array:
        """Start and end of every blend [s]: where the reference's jerk jumps."""
        starts = self.step_start.reshape(-1)
        return jnp.concatenate([starts, starts + self.step_duration.reshape(-1)])


def make_position_reference(
    steps: dict[str, list[tuple[float, float, float]]] | None = None,
    sines: dict[str, tuple[float, float, float]] | None = None,
    offset: dict[str, float] | None = None,
    step_duration: float = 1.0,
    max_steps: int | None = None,
) -> PositionReference:
    """Build a `PositionReference` from readable pieces, as `make_reference` (channels "x",
    "y"; steps (t0 [s], a [m], b [m]), sines (amplitude [m], frequency [rad/s], phase [rad]),
    offsets [m], blend duration [s])."""
    names = ("x", "y")
    steps, sines, offset = steps or {}, sines or {}, offset or {}
    for key in (*steps, *sines, *offset):
        if key not in names:
            raise ValueError(f"unknown position channel {key!r}; allowed: {', '.join(names)}.")
    n = max([len(v) for v in steps.values()] + [0]) if max_steps is None else max_steps
    n = max(n, 1)
    start = np.zeros((2, n))
    size = np.zeros((2, n))
    base = np.array([float(offset.get(c, 0.0)) for c in names])
    for i, c in enumerate(names):
        chan = steps.get(c, [])
        if len(chan) > n:
            raise ValueError(f"channel {c!r} has {len(chan)} steps but max_steps is {n}.")
        level = base[i]
        for k, (t0, a, b) in enumerate(chan):
            if not np.isclose(a, level):
                raise ValueError(
                    f"step {k} of channel {c!r} starts from {a} but the reference is at {level} "
                    "there; steps must chain."
                )
            start[i, k], size[i, k], level = t0, b - a, b
    amp = np.array([sines.get(c, (0.0, 0.0, 0.0))[0] for c in names])
    freq = np.array([sines.get(c, (0.0, 0.0, 0.0))[1] for c in names])
    phase = np.array([sines.get(c, (0.0, 0.0, 0.0))[2] for c in names])
    return PositionReference(
        base, start, size, np.full((2, n), float(step_duration)), amp, freq, phase
    )
