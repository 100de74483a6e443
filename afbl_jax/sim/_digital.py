"""Digital control: what happens at a sample instant, and the trajectory samples between them.

At sample k (t_k = t0 + k h, h = 1 / f_c) `sample_instant` measures the true state (paper
layout plus the sampling's noise for k), pushes it into the delay ring buffer, hands the
measurement from ``delay_samples`` samples earlier to the controller with r(t_k), and returns
the command to hold over [t_k, t_k+1) and the controller-state derivative (applied as one
forward-Euler step of length h). At k = 0 rotor states start at the first command. Every solve
path (one case, vmap, ensemble) calls this one function, so they agree case by case.

Trajectory outputs in digital mode (`interpolate`, `held_index`) are linear interpolations of
the states at the sample times (exact at the sample times) and the held command.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ..model import safe_sqrt
from ._closed_loop import CaseInputs, ClosedLoop, ClosedLoopState, Held


def initial_buffer(loop: ClosedLoop, y0: ClosedLoopState):
    """The delay ring buffer at t0: the noise-free initial measurement in every slot,
    shape (max_delay + 1, 12)."""
    meas0 = loop.plant.to_paper_layout(y0.plant)
    return jnp.broadcast_to(meas0, (loop.sampling.max_delay + 1, meas0.shape[0]))


def sample_instant(loop: ClosedLoop, k, t_k, y: ClosedLoopState, buffer, inputs: CaseInputs):
    """Sample k at t_k: returns (y with rotors set at k = 0, new buffer, `Held` command,
    controller-state derivative)."""
    s = loop.sampling
    nbuf = s.max_delay + 1
    delay = jnp.clip(s.delay_samples, 0, s.max_delay)
    measured = loop.plant.to_paper_layout(y.plant) + s.noise(k).astype(y.plant.dtype)
    buffer = buffer.at[k % nbuf].set(measured)
    u_cmd, w_cmd, w_sat, dctrl = loop.command(t_k, buffer[(k - delay) % nbuf], y.controller, inputs)
    if y.rotors is not None:
        y = eqx.tree_at(lambda s_: s_.rotors, y, jnp.where(k == 0, safe_sqrt(w_sat), y.rotors))
    return y, buffer, Held(u_cmd, w_cmd), dctrl


def sample_time(t0, h, k):
    """t_k = t0 + k h [s]: the one formula for sample instants, so consecutive sample intervals
    [t_k, t_k+1) tile the run exactly in every precision (t_k + h would not: rounded at t ~ 20 s,
    float32 intervals would overlap or leave gaps of ~1e-6 s each)."""
    return t0 + k.astype(h.dtype) * h


def interpolate(ts, sample_ts, values):
    """Linear interpolation of ``values`` (leading axis = sample_ts) at ``ts``, leaf-wise."""

    def one(a):
        flat = a.reshape(a.shape[0], -1)
        cols = jax.vmap(lambda c: jnp.interp(ts, sample_ts, c), in_axes=1, out_axes=1)(flat)
        return cols.reshape(ts.shape[0], *a.shape[1:])

    return jax.tree.map(one, values)


def held_index(ts, t0, h, max_samples):
    """Index of the sample interval holding the command at each of ``ts``."""
    return jnp.clip(jnp.floor((ts - t0) / h).astype(jnp.int32), 0, max_samples - 1)
