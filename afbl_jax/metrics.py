"""Per-case metrics: one definition for every solve path (single, vmap, ensemble).

- ``ise_attitude`` [rad^2 s], ``ise_altitude`` [m^2 s], ``effort``, ``saturation``: the cost
  integrals of the closed-loop state (`afbl_jax.sim.COST_LAYOUT`), up to the stop time;
- ``peak_attitude_error`` [rad]: max over the samples of max(|e_phi|, |e_theta|, |e_psi|);
- ``peak_altitude_error`` [m]: max over the samples of |e_z|;
- ``peak_saturation`` [-]: max over the samples and the four rotors of commanded rotor speed /
  omega_max (commanded speed = sqrt of the mixer's commanded Omega^2 through the controller's
  model, clipped at 0); >= 1 means the command hit the rotor-speed limit;
- ``ise_position`` [m^2 s], ``peak_position_error`` [m]: with a position loop, the integral of
  |p_ref - p|^2 and the largest |p_ref - p| over the samples (horizontal position x, y); NaN
  without one (the attitude errors are then taken against the position loop's commanded roll
  and pitch, `afbl_jax.sim.ClosedLoop.reference_values`);
- ``failure_cause``: what ended a run that failed (`FAILURE_CAUSES`: none, attitude, altitude,
  non_finite, solver), from its end state; ``final_saturation`` [-]: the commanded rotor
  saturation (as ``peak_saturation``) on the end state, >= 1 when the rotors were commanded past
  their limit as the run ended.

Peaks are taken at ``n_save`` equally spaced times over [t0, t1] (with digital control: the
states linearly interpolated between control samples, the held command), counting only the
samples at or before the run's end (`peaks_over_samples`); a run with no such sample has NaN
peaks. `BatchMetrics` holds them per case; `metrics_from_result` converts a single
`afbl_jax.simulate` result, and the ensemble computes the same samples inside its solve.

Failure margin (`failure_margin`, column ``failure_margin`` [-]): an STL-style robustness value
of "the attitude and altitude errors stay within the failure limits", from the same in-solve
peaks: ``max(peak_attitude_error / attitude_limit, peak_altitude_error / altitude_limit) - 1``
(`peak_margin`), > 0 when a peak crossed its limit. The failure limits default to the
divergence limits of `afbl_jax.sim.DivergenceLimits` (1.2 rad, 10 m: `FAILURE_ATTITUDE`,
`FAILURE_ALTITUDE`), so the Monte-Carlo failure (status not ok) and the sign agree exactly:
a failed run (diverged, stopped by the solver) gets ``max(peak_margin, FAILED_MARGIN)`` (its
peaks stop where it stopped; the limit may be crossed between two samples) and a run that
finished ok ``min(peak_margin, 0)`` (the attitude peak also counts |e_psi| and the reference,
the divergence test only |phi|, |theta|). Failed <=> margin > 0. `smooth_margin` is the
differentiable variant for optimisation: a log-sum-exp over the channels at a temperature,
an upper bound of `peak_margin` by at most ``temperature log 2``; the peaks themselves are
maxima over the samples (differentiable almost everywhere: through the sample that attains
them).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ._typing import Array, Float, Int
from .model import QuadrotorParams, rotor_speeds_sq_from_inputs

METRIC_NAMES: tuple[str, ...] = (
    "ise_attitude",
    "ise_altitude",
    "ise_position",
    "peak_attitude_error",
    "peak_altitude_error",
    "peak_position_error",
    "peak_saturation",
    "failure_margin",
    "failure_cause",
    "final_saturation",
    "solver_steps",
    "t_final",
    "status",
)
"""Per-case metric columns of a results table (see the module docstring)."""


class BatchMetrics(eqx.Module):
    """Per-case results (every field has leading axis N; unbatched for one case).

    Attributes:
        ise_attitude, ise_altitude, effort, saturation: cost integrals at the end of each run
            (a diverged run's integrals stop where it diverged).
        status: `afbl_jax.sim.Status` codes (0 ok, 1 diverged, 2 max_steps, 3 solver failure).
        t_final: time each run ended [s] (t1, or where it stopped).
        num_steps: solver steps (accepted + rejected); for an ensemble the shared count.
        num_rejected_steps: rejected steps (shared count for an ensemble).
        peak_attitude_error [rad], peak_altitude_error [m], peak_saturation [-]: maxima over
            the samples before the run's end (module docstring); NaN without samples.
        ise_position [m^2 s], peak_position_error [m]: with a position loop (else NaN).
        failure_cause: `FAILURE_CAUSES` codes; final_saturation [-] (module docstring).
    """

    ise_attitude: Float[Array, " N"]
    ise_altitude: Float[Array, " N"]
    effort: Float[Array, " N"]
    saturation: Float[Array, " N"]
    status: Int[Array, " N"]
    t_final: Float[Array, " N"]
    num_steps: Int[Array, " N"]
    num_rejected_steps: Int[Array, " N"]
    peak_attitude_error: Float[Array, " N"]
    peak_altitude_error: Float[Array, " N"]
    peak_saturation: Float[Array, " N"]
    ise_position: Float[Array, " N"]
    peak_position_error: Float[Array, " N"]
    failure_cause: Int[Array, " N"]
    final_saturation: Float[Array, " N"]

    @property
    def ok(self) -> Array:
        return self.status == 0

    @property
    def failure_margin(self) -> Array:
        """`failure_margin` at the default failure limits: > 0 exactly when the run failed."""
        return failure_margin(self)


FAILURE_CAUSES: tuple[str, ...] = ("none", "attitude", "altitude", "non_finite", "solver")
"""What ended a failed run (``failure_cause`` codes 0-4): none (it finished), the attitude or
the altitude divergence limit (the one crossed by the most), a non-finite state, or the solver
(out of steps, step size collapsed)."""
PEAK_LAYOUT: tuple[str, ...] = ("attitude_error", "altitude_error", "saturation", "position_error")
"""The quantities of one peak sample (`sample_peaks`), in order."""
N_PEAKS = len(PEAK_LAYOUT)

FAILURE_ATTITUDE = 1.2
"""Default failure limit on the attitude error peak [rad] (= the divergence limit)."""
FAILURE_ALTITUDE = 10.0
"""Default failure limit on the altitude error peak [m] (= the divergence limit)."""
FAILED_MARGIN = 1e-6
"""Smallest margin given to a failed run (the peaks of a run stopped between two samples can
lie below the limits)."""


def _ratios(m: BatchMetrics, attitude_limit, altitude_limit) -> Array:
    """Peaks over limits, channel axis last; NaN peaks (no sample before the run's end) +inf."""
    r = jnp.stack(
        [m.peak_attitude_error / attitude_limit, m.peak_altitude_error / altitude_limit], axis=-1
    )
    return jnp.where(jnp.isnan(r), jnp.inf, r)


def peak_margin(
    m: BatchMetrics, attitude_limit=FAILURE_ATTITUDE, altitude_limit=FAILURE_ALTITUDE
) -> Array:
    """``max(peak_attitude_error / attitude_limit [rad/rad], peak_altitude_error /
    altitude_limit [m/m]) - 1`` per case: > 0 when a sampled peak crossed its limit."""
    return jnp.max(_ratios(m, attitude_limit, altitude_limit), axis=-1) - 1.0


def failure_margin(m: BatchMetrics, attitude_limit=None, altitude_limit=None) -> Array:
    """The failure margin per case (module docstring): > 0 exactly when the run failed
    (status not ok) or, with limits given, a peak crossed them.

    Limits None (the default limits, = the divergence limits): a run that finished ok has margin
    ``min(peak_margin, 0)`` <= 0, a failed one ``max(peak_margin, FAILED_MARGIN)``. With limits
    [rad], [m] given (e.g. tighter ones): failed runs ``max(peak_margin, FAILED_MARGIN)``, the
    others `peak_margin`."""
    default = attitude_limit is None and altitude_limit is None
    attitude_limit = FAILURE_ATTITUDE if attitude_limit is None else attitude_limit
    altitude_limit = FAILURE_ALTITUDE if altitude_limit is None else altitude_limit
    pm = peak_margin(m, attitude_limit, altitude_limit)
    failed = m.status != 0
    finished = jnp.minimum(pm, 0.0) if default else pm
    return jnp.where(failed, jnp.maximum(pm, FAILED_MARGIN), finished)


def smooth_margin(
    m: BatchMetrics,
    attitude_limit=FAILURE_ATTITUDE,
    altitude_limit=FAILURE_ALTITUDE,
    temperature=0.05,
) -> Array:
    """Differentiable failure margin: ``temperature * logsumexp(ratios / temperature) - 1``
    over the two channels' peak / limit ratios. An upper bound of `peak_margin`, above it by
    at most ``temperature * log 2``; the status does not enter (use `failure_margin` for the
    failed / not failed decision)."""
    r = _ratios(m, attitude_limit, altitude_limit)
    return temperature * jax.nn.logsumexp(r / temperature, axis=-1) - 1.0


def sample_peaks(
    error: Float[Array, 4],
    u_command: Float[Array, 4],
    vehicle: QuadrotorParams,
    model: QuadrotorParams,
    position_error: Float[Array, 2] | None = None,
) -> Array:
    """The quantities whose maxima over the samples are a run's peaks, shape (4,)
    (`PEAK_LAYOUT`): max(|e_phi|, |e_theta|, |e_psi|) [rad], |e_z| [m], max over the rotors of
    commanded rotor speed / omega_max [-], and |p_ref - p| [m] (NaN without
    ``position_error``: no position loop)."""
    err = jnp.abs(error)
    w_cmd = rotor_speeds_sq_from_inputs(model, u_command)
    w_max = jnp.maximum(jnp.maximum(w_cmd[0], w_cmd[1]), jnp.maximum(w_cmd[2], w_cmd[3]))
    sat = jnp.sqrt(jnp.maximum(w_max, 0.0)) / vehicle.omega_max
    if position_error is None:
        pos = jnp.full_like(sat, jnp.nan)
    else:  # |p_ref - p| with a zero (not NaN) gradient where it is 0 (a trimmed start)
        n2 = position_error[0] ** 2 + position_error[1] ** 2
        positive = n2 > 0
        pos = jnp.where(positive, jnp.sqrt(jnp.where(positive, n2, 1.0)), 0.0)
    # maxima over 3 and 4 entries as elementwise maxima: no reduction, which XLA's CPU backend
    # otherwise emits as one small reduction per case and sample
    return jnp.stack([jnp.maximum(jnp.maximum(err[0], err[1]), err[2]), err[3], sat, pos])


def peaks_over_samples(ts, samples, t_final) -> Array:
    """Max over the samples at ``ts`` (shape (n,)) with ts <= t_final of ``samples`` (n, P);
    non-finite samples are skipped; NaN where no sample counts. Returns shape (P,)."""
    valid = (ts <= t_final)[:, None] & jnp.isfinite(samples)
    peak = jnp.max(jnp.where(valid, samples, -jnp.inf), axis=0)
    return jnp.where(jnp.any(valid, axis=0), peak, jnp.nan)


def fold_peaks(peaks, samples, counts) -> Array:
    """One sample folded into running peaks (`peaks_over_samples` one sample at a time, for
    solvers that sample inside their loop): ``peaks`` and ``samples`` (..., P), ``counts``
    (...,) whether the sample is at or before the run's end. Start from -inf (`no_peaks`);
    non-finite samples are skipped; `finish_peaks` gives NaN where no sample counted."""
    use = counts[..., None] & jnp.isfinite(samples)
    return jnp.maximum(peaks, jnp.where(use, samples, -jnp.inf))


def no_peaks(shape, dtype) -> Array:
    """Running peaks before any sample: -inf, shape (*shape, `N_PEAKS`) (`fold_peaks`)."""
    return jnp.full((*shape, N_PEAKS), -jnp.inf, dtype)


def finish_peaks(peaks) -> Array:
    """Running peaks (`fold_peaks`) -> peaks: NaN where no sample counted (samples are >= 0)."""
    return jnp.where(jnp.isneginf(peaks), jnp.nan, peaks)


def metrics_from_result(result, vehicle: QuadrotorParams, model: QuadrotorParams) -> BatchMetrics:
    """`BatchMetrics` (unbatched) of one `afbl_jax.simulate` result; peaks from its saved
    samples (NaN when it saved none)."""
    nan = jnp.full((), jnp.nan, result.t_final.dtype)
    if result.ts.shape[0]:
        pos = result.position_error
        samples = jax.vmap(
            lambda e, u, p: sample_peaks(e, u, vehicle, model, p),
            in_axes=(0, 0, None if pos is None else 0),
        )(result.error, result.u_command, pos)
        peaks = peaks_over_samples(result.ts, samples, result.t_final)
    else:
        peaks = jnp.full((N_PEAKS,), jnp.nan, result.t_final.dtype)
    return BatchMetrics(
        result.ise_attitude,
        result.ise_altitude,
        result.effort,
        result.saturation,
        result.status,
        result.t_final,
        result.num_steps,
        result.num_rejected_steps,
        peaks[0],
        peaks[1],
        peaks[2],
        nan if result.ise_position is None else result.ise_position,
        peaks[3],
        result.failure_cause,
        result.final_saturation,
    )


def metric_columns(m: BatchMetrics) -> dict[str, Array]:
    """The `METRIC_NAMES` columns of a results table from `BatchMetrics`."""
    return {
        "ise_attitude": m.ise_attitude,
        "ise_altitude": m.ise_altitude,
        "ise_position": m.ise_position,
        "peak_attitude_error": m.peak_attitude_error,
        "peak_altitude_error": m.peak_altitude_error,
        "peak_position_error": m.peak_position_error,
        "peak_saturation": m.peak_saturation,
        "failure_margin": m.failure_margin,
        "failure_cause": m.failure_cause,
        "final_saturation": m.final_saturation,
        "solver_steps": m.num_steps,
        "t_final": m.t_final,
        "status": m.status,
    }
