"""Throughput benchmark of batched solving (`afbl bench`).

Case: the canonical uncertain-step scenario with the AFBL paper gains, 20 s, rtol 1e-6,
atol 1e-8, Tsit5 (scipy: RK45). So that the accuracy check is meaningful, every case differs:
payload fraction p ~ U[0, 0.5], torque-pulse and force-pulse amplitudes scaled by U[0.5, 1.5]
each (`bench_cases`). Accuracy: max over ok cases and over (ise_attitude, ise_altitude) of
|ISE - ISE_ref| / ISE_ref, with ISE_ref from an x64 Dopri8 ensemble at rtol 1e-10, atol 1e-12
(itself cross-checked against per-case `simulate` on the first cases: ``reference_check``).

Strategies (rows of bench.json):

- ``scipy_rk45_loop``: `scipy.integrate.solve_ivp` (RK45, same rtol/atol) with a NumPy RHS,
  one case after the other: the baseline a user would otherwise write (measured on a subset of
  cases; sims/s does not depend on N).
- ``diffrax_loop``: a Python loop over one jitted `simulate` (n_save=0) per case (subset).
- ``vmap``, ``ensemble``: `simulate_batch` strategies, float64.
- ``ensemble_f32``: the ensemble in float32 at rtol 1e-5, atol 1e-6 (float32 cannot resolve
  1e-8 absolute / 1e-6 relative steps reliably; the measured error is in the row).
- ``ensemble_f32_chunked``: the same, each device solving its cases as consecutive chunks of
  128 inside one compiled call (``simulate_batch(chunk_size=128)``): the per-step working set
  then stays in cache (rows with N <= 128 per device are the unchunked ensemble).
- ``montecarlo_default``: exactly what ``afbl montecarlo`` runs by default per chunk (strategy
  ``ensemble_f32``: float32, groups of 16 cases (`ensemble_group_size`; 4 with digital
  control), 128 cases per CPU device at a time (all
  cases at once on a GPU), 401 saved samples for the peak metrics, rtol 3e-6, atol 3e-7);
  ``montecarlo_default_1dev``: the same on one device (one core), for a per-core comparison
  with the single-core scipy loop. With more than 128 cases per CPU device, a device's 128-case
  chunks are the lanes of the lean loop's work queue (``simulate_batch(work_queue=True)``);
  ``montecarlo_default_no_queue``: the same with the chunks one after the other, each waiting
  for its slowest group (the baseline of the work queue, measured in the same run).
- ``montecarlo_default_unmodeled``: the same Monte-Carlo default on a realistic vehicle: full
  rigid-body plant, first-order motor lag tau_m = 30 ms, digital control at 250 Hz with a
  one-sample measurement delay (noise off). Its accuracy is measured against an x64 Dopri8
  reference of the same loop; its ratio to the scipy loop (which simulates the paper's loop)
  says what a realistic vehicle costs, not a like-for-like speed-up.
- ``montecarlo_default_diffeqsolve``, ``montecarlo_default_unmodeled_diffeqsolve``: the same two
  rows with ``simulate_batch(integrator="diffeqsolve")`` (`diffrax.diffeqsolve` per group; with
  digital control a scan of one solve per sample interval) instead of the default lean loop:
  the baseline of the lean integrator, measured in the same run.
- ``montecarlo_cases``: the Monte-Carlo default distribution's own cases (wind, turbulence,
  gusts, rotor drag, payload, model errors, position hold, trimmed start), solved exactly as
  ``afbl montecarlo`` solves a chunk (`afbl_jax.studies.montecarlo.run_chunk`, default
  strategy); ``montecarlo_cases_no_position_loop``: the same cases, the same wind, flown
  without the position loop from rest, level (`without_position_loop`): what the position loop
  and the trimmed start cost per case, in the same run.
  Their accuracy is measured on the first cases against an x64 Dopri8 solve (rtol 1e-10) of
  the same closed loop.
- ``scipy_rk45_montecarlo_cases``: the baseline on those cases: `scipy.integrate.solve_ivp`
  (RK45, rtol 1e-6, atol 1e-8, as ``scipy_rk45_loop``) with a NumPy right-hand side of the same
  closed loop (`afbl_jax.studies.numpy_loop`: plant, mean wind + gusts + sum-of-sinusoids
  turbulence from each case's `afbl_jax.Wind` arrays, rotor drag, rotor-speed saturation, the
  position loop, AFBL, the ISE states; from the case's trimmed initial state, piecewise between
  the case's jump times, stopped at the divergence limits), one case after the other on one
  core, on the first ``scipy_montecarlo_cases`` cases (sims/s does not depend on N). Its
  accuracy is measured against the same x64 reference as ``montecarlo_cases``.
- ``tuning_gradient``: the gain-tuning objective (`afbl_jax.studies.tuning.TuneConfig`'s
  default: AFBL, robust, its training cases) on ``gradient_cases`` cases: one value-and-gradient
  (reverse mode) against one forward evaluation of the same cases, best of ``gradient_repeats``
  after compiling, one row per precision (float32 at rtol 3e-6, atol 3e-7; float64 at rtol
  1e-6, atol 1e-8; `afbl_jax.studies.tuning.gradient_cost`). sims/s: cases differentiated per
  second; ``forward_s``, ``gradient_s``; ``gradient_to_forward``: the row's gradient over its
  own forward pass; ``gradient_to_forward_float32``: over the float32 forward pass (the fast
  forward pass); ``gradient_rel_error``: the float32 gradient's largest deviation from the
  float64 one over the latter's largest entry (0 in the float64 row); no ISE error, no scipy
  ratio (``max_rel_ise_error``, ``ratio_to_scipy`` None). Both rows carry the peak-RSS growth
  of the whole measurement (both precisions).

Ratios (``ratio_to_scipy``, with the row it is taken against in ``ratio_baseline``): each row's
sims/s over its own kind of baseline measured in the same run: the canonical rows over
``scipy_rk45_loop``, the rows on the Monte-Carlo cases over ``scipy_rk45_montecarlo_cases``
(over ``scipy_rk45_loop`` when that row is not measured; ``montecarlo_cases_no_position_loop``
flies the same cases without the position loop, so its ratio says what the position loop
costs besides the speed-up).

Every batched row splits the cases over all local devices (``devices`` in the row) except
``montecarlo_default_1dev``; ``afbl bench`` starts with one XLA CPU device per core
(`afbl_jax.configure_cpu_devices`).

Memory: ``peak_rss_delta_mb`` is the growth of the process's peak resident set size
(``resource.getrusage`` max RSS, which includes compilation) during the row; it is 0 when the
row stays below an earlier peak, so it is a lower bound (rows run in increasing N).

bench.json is a list of rows; every row carries the same ``meta`` block (config, seed, versions,
git revision: `afbl_jax._meta.run_metadata`).
"""

from __future__ import annotations

import json
import resource
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import jax
import numpy as np

from ..io import run_metadata
from ..metrics import BatchMetrics
from ..model import AFBL, UnmodeledDynamics
from ..scenario import PulseDisturbance, Scenario, paper_scenario
from ..sim import STATUS_OK, simulate, simulate_batch
from .bench_rows import (
    ALL_STRATEGIES,
    BATCH_ROWS,
    DEFAULT_SIZES,
    GRADIENT_ROW,
    LOOP_STRATEGIES,
    MONTECARLO_CASE_ROWS,
    MONTECARLO_SCIPY_ROW,
)

CHUNK = 128


REALISTIC_VEHICLE = {"plant": "full", "motor_tau": 0.03, "control_rate": 250.0, "delay_samples": 1}
"""The realistic-vehicle settings of the ``montecarlo_default_unmodeled`` row."""


def realistic_unmodeled(duration: float = 20.0) -> UnmodeledDynamics:
    """`UnmodeledDynamics` of the ``montecarlo_default_unmodeled`` row (`REALISTIC_VEHICLE`)."""
    return UnmodeledDynamics.make(duration=duration, **REALISTIC_VEHICLE)


def _mc_default(
    one_device: bool, unmodeled: bool = False, integrator: str = "lean", work_queue: bool = True
) -> dict:
    from .montecarlo import BATCH_SETTINGS, DEFAULT_STRATEGY, STRATEGY_TOLERANCES, SolverSettings

    rtol, atol = STRATEGY_TOLERANCES[DEFAULT_STRATEGY]
    return {
        **BATCH_SETTINGS[DEFAULT_STRATEGY],
        "rtol": rtol,
        "atol": atol,
        "n_save": SolverSettings().n_save,
        "one_device": one_device,
        "always": True,
        "unmodeled": unmodeled,
        "integrator": integrator,
        "work_queue": work_queue,
        "platform_chunk": True,  # chunked on CPU devices only (`device_chunk`)
    }


BATCH_STRATEGIES = {
    # name (`bench_rows.BATCH_ROWS`, same order): simulate_batch settings ("always": measure
    # even when chunking changes nothing)
    "vmap": {"strategy": "vmap", "dtype": "float64", "rtol": 1e-6, "atol": 1e-8},
    "ensemble": {"strategy": "ensemble", "dtype": "float64", "rtol": 1e-6, "atol": 1e-8},
    "ensemble_f32": {"strategy": "ensemble", "dtype": "float32", "rtol": 1e-5, "atol": 1e-6},
    "ensemble_f32_chunked": {
        "strategy": "ensemble",
        "dtype": "float32",
        "rtol": 1e-5,
        "atol": 1e-6,
        "chunk_size": CHUNK,
    },
    "montecarlo_default": _mc_default(False),
    "montecarlo_default_1dev": _mc_default(True),
    "montecarlo_default_no_queue": _mc_default(False, work_queue=False),
    "montecarlo_default_diffeqsolve": _mc_default(False, integrator="diffeqsolve"),
    "montecarlo_default_unmodeled": _mc_default(False, unmodeled=True),
    "montecarlo_default_unmodeled_diffeqsolve": _mc_default(
        False, unmodeled=True, integrator="diffeqsolve"
    ),
}
REFERENCE = {"solver": "dopri8", "rtol": 1e-10, "atol": 1e-12, "dtype": "float64"}


# --------------------------------------------------------------------------- cases


def bench_cases(n: int, seed: int = 0) -> tuple[Scenario, np.ndarray]:
    """N uncertain-step cases (batched `Scenario`) and their numbers (n, 3): payload fraction,
    torque-pulse scale, force-pulse scale."""
    base = paper_scenario("uncertain", "step")
    rng = np.random.default_rng(seed)
    draws = np.stack(
        [rng.uniform(0.0, 0.5, n), rng.uniform(0.5, 1.5, n), rng.uniform(0.5, 1.5, n)], axis=1
    )

    def tile(x):
        x = np.asarray(x)
        return np.broadcast_to(x, (n, *x.shape)).copy()

    d = base.disturbance
    disturbance = PulseDisturbance(
        start=tile(d.start),
        duration=tile(d.duration),
        torque=tile(d.torque) * draws[:, 1, None, None],
        force=tile(d.force) * draws[:, 2, None, None],
    )
    reference = jax.tree.map(tile, base.reference)
    scenarios = Scenario(
        reference=reference,
        disturbance=disturbance,
        payload_fraction=draws[:, 0],
        payload_time=tile(base.payload_time),
        initial_state=tile(base.initial_state),
        t0=tile(base.t0),
        t1=tile(base.t1),
        wind=jax.tree.map(tile, base.wind),
    )
    return scenarios, draws


# --------------------------------------------------------------------------- numpy baseline
# Adapted from tests/numpy_reference.py (the independent NumPy closed loop), AFBL only, step
# profile, with per-case payload and pulse amplitudes.

_P = {
    "m": 0.650,
    "Ix": 7.5e-3,
    "Iy": 7.5e-3,
    "Iz": 1.3e-2,
    "b": 3.13e-5,
    "d": 7.5e-7,
    "Jr": 6e-5,
    "l": 0.23,
    "g": 9.81,
    "gyro_sign": -1.0,  # QuadrotorParams() default (PHYSICAL_GYRO_SIGN), as the cases use
}
_STEPS = (
    (3, 1.0, 1.0),
    (3, 16.0, -1.0),
    (0, 4.0, 0.1),
    (0, 8.0, -0.1),
    (1, 6.0, -0.1),
    (1, 10.0, 0.1),
    (2, 8.0, 0.2),
    (2, 12.0, -0.2),
)


def _numpy_rhs(t, y, mass_factor, torque, force_z, gamma, k, lam):
    p = _P
    r, rd, rdd = np.zeros(4), np.zeros(4), np.zeros(4)
    for ch, t0, delta in _STEPS:
        tau = t - t0
        if 0.0 < tau < 1.0:
            r[ch] += delta * tau**3 * (10.0 - 15.0 * tau + 6.0 * tau**2)
            rd[ch] += delta * 30.0 * tau**2 * (1.0 - tau) ** 2
            rdd[ch] += delta * 60.0 * tau * (1.0 - 3.0 * tau + 2.0 * tau**2)
        elif tau >= 1.0:
            r[ch] += delta
    plant, dhat = y[:12], y[12:16]
    q = plant[[3, 4, 5, 2]]
    qd = plant[[9, 10, 11, 8]]
    e, ed = r - q, rd - qd
    s = ed + lam * e
    v = rdd + lam * ed - dhat + k * s
    phi, theta, psi = plant[3:6]
    phid, thetad, psid = plant[9:12]
    ix, iy, iz, arm, b, d = p["Ix"], p["Iy"], p["Iz"], p["l"], p["b"], p["d"]
    u = np.array(
        [
            (ix / arm) * (v[0] - thetad * psid * (iy - iz) / ix),
            (iy / arm) * (v[1] - phid * psid * (iz - ix) / iy),
            iz * (v[2] - phid * thetad * (ix - iy) / iz),
            p["m"] * (p["g"] + v[3]) / (np.cos(phi) * np.cos(theta)),
        ]
    )
    w = np.maximum(
        np.array(
            [
                u[3] / (4 * b) - u[1] / (2 * b) - u[2] / (4 * d),
                u[3] / (4 * b) - u[0] / (2 * b) + u[2] / (4 * d),
                u[3] / (4 * b) + u[1] / (2 * b) - u[2] / (4 * d),
                u[3] / (4 * b) + u[0] / (2 * b) + u[2] / (4 * d),
            ]
        ),
        0.0,
    )
    U = np.array(
        [b * (w[3] - w[1]), b * (w[2] - w[0]), d * (w[1] + w[3] - w[0] - w[2]), b * w.sum()]
    )
    om = np.sqrt(w)
    od = -om[0] + om[1] - om[2] + om[3]
    tq = torque if 10.0 <= t < 11.0 else np.zeros(3)
    fz = force_z if 12.0 <= t < 13.0 else 0.0
    m = p["m"] * mass_factor
    cphi, sphi, cth, sth = np.cos(phi), np.sin(phi), np.cos(theta), np.sin(theta)
    cpsi, spsi = np.cos(psi), np.sin(psi)
    dy = np.empty(20)
    dy[0:6] = plant[6:12]
    dy[6] = (cphi * sth * cpsi + sphi * spsi) * U[3] / m
    dy[7] = (cphi * sth * spsi - sphi * cpsi) * U[3] / m
    dy[8] = -p["g"] + cphi * cth * U[3] / m + fz / m
    dy[9] = (
        thetad * psid * (iy - iz) / ix
        - (p["gyro_sign"] * p["Jr"] / ix) * thetad * od
        + arm * U[0] / ix
        + tq[0] / ix
    )
    dy[10] = (
        phid * psid * (iz - ix) / iy
        + (p["gyro_sign"] * p["Jr"] / iy) * phid * od
        + arm * U[1] / iy
        + tq[1] / iy
    )
    dy[11] = phid * thetad * (ix - iy) / iz + U[2] / iz + tq[2] / iz
    dy[12:16] = -s / gamma
    dy[16] = e[0] ** 2 + e[1] ** 2 + e[2] ** 2
    dy[17] = e[3] ** 2
    dy[18:20] = 0.0
    return dy


def scipy_loop(draws: np.ndarray, rtol: float = 1e-6, atol: float = 1e-8) -> np.ndarray:
    """(n, 2) ISE (attitude, altitude) of each case by `solve_ivp` RK45 with a NumPy RHS."""
    from scipy.integrate import solve_ivp

    ctrl = AFBL()
    gamma, k, lam = (np.asarray(getattr(ctrl, g)) for g in ("gamma", "k", "lam"))
    y0 = np.zeros(20)
    y0[:12] = np.asarray(paper_scenario("uncertain", "step").initial_state)
    out = np.empty((len(draws), 2))
    for i, (p, ts, fs) in enumerate(draws):
        sol = solve_ivp(
            _numpy_rhs,
            (0.0, 20.0),
            y0,
            method="RK45",
            rtol=rtol,
            atol=atol,
            args=(1.0 + p, ts * np.array([0.01, 0.01, 0.01]), fs * -2.0, gamma, k, lam),
        )
        out[i] = sol.y[16:18, -1] if sol.success else np.nan
    return out


# --------------------------------------------------------------------------- measurement


def _index(tree, sl):
    return jax.tree.map(lambda x: x[sl], tree)


def _rel_error(ise: np.ndarray, ref: np.ndarray, ok: np.ndarray) -> float:
    """Max over ok cases of |ise - ref| / |ref| (ise, ref: (n, 2)); inf if no case is ok."""
    if not np.any(ok):
        return float("inf")
    return float(np.max(np.abs(ise[ok] - ref[ok]) / np.abs(ref[ok])))


def _ise(m: BatchMetrics) -> np.ndarray:
    return np.stack(
        [np.asarray(m.ise_attitude, np.float64), np.asarray(m.ise_altitude, np.float64)], axis=1
    )


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: kB


def reference_ise(scenarios: Scenario, chunk: int = 4096, unmodeled=None) -> np.ndarray:
    """(n, 2) tight-tolerance x64 reference ISE (Dopri8 ensemble, rtol 1e-10, atol 1e-12)."""
    n = scenarios.t0.shape[0]
    parts = []
    for a in range(0, n, chunk):
        m = simulate_batch(
            AFBL(),
            _index(scenarios, slice(a, a + chunk)),
            strategy="ensemble",
            solver=REFERENCE["solver"],
            rtol=REFERENCE["rtol"],
            atol=REFERENCE["atol"],
            dtype="float64",
            unmodeled=unmodeled,
        )
        if not np.all(np.asarray(m.status) == STATUS_OK):
            raise RuntimeError("bench reference solve failed for some cases")
        parts.append(_ise(m))
    return np.concatenate(parts)


def measure_batch(name: str, scenarios: Scenario, ref: np.ndarray) -> dict:
    """One row: run twice (compile + run, then run), time the second call."""
    cfg = BATCH_STRATEGIES[name]
    unmodeled = realistic_unmodeled() if cfg.get("unmodeled") else None
    n = scenarios.t0.shape[0]
    devices = jax.local_devices()[:1] if cfg.get("one_device") else jax.local_devices()
    rss0 = _rss_mb()

    chunk_size, group_size = cfg.get("chunk_size"), cfg.get("group_size")
    if cfg.get("platform_chunk"):  # the Monte-Carlo default: its chunking and groups
        from .montecarlo import device_chunk, ensemble_group_size

        chunk_size = device_chunk(chunk_size, devices)
        digital = unmodeled is not None and unmodeled.digital
        group_size = ensemble_group_size(digital, n, len(devices), devices[0].platform)

    def call():
        return jax.block_until_ready(
            simulate_batch(
                AFBL(),
                scenarios,
                strategy=cfg["strategy"],
                rtol=cfg["rtol"],
                atol=cfg["atol"],
                dtype=cfg["dtype"],
                chunk_size=chunk_size,
                group_size=group_size,
                n_save=cfg.get("n_save", 0),
                devices=devices,
                unmodeled=unmodeled,
                integrator=cfg.get("integrator", "lean"),
                work_queue=cfg.get("work_queue", True),
            )
        )

    t = time.perf_counter()
    call()
    first = time.perf_counter() - t
    t = time.perf_counter()
    m = call()
    run = time.perf_counter() - t
    k = min(n, len(ref))  # accuracy over the first k cases (those with a reference)
    ok = np.asarray(m.status)[:k] == STATUS_OK
    return {
        "strategy": name,
        "N": n,
        "dtype": cfg["dtype"],
        "rtol": cfg["rtol"],
        "atol": cfg["atol"],
        "chunk_size": chunk_size,
        "group_size": group_size,
        "n_save": cfg.get("n_save", 0),
        "devices": len(devices),
        "unmodeled": REALISTIC_VEHICLE if unmodeled else None,
        "integrator": cfg.get("integrator", "lean") if cfg["strategy"] == "ensemble" else None,
        "work_queue": cfg.get("work_queue", True),
        "sims_per_s": n / run,
        "seconds": run,
        "compile_s": max(first - run, 0.0),
        "peak_rss_delta_mb": max(_rss_mb() - rss0, 0.0),
        "max_rel_ise_error": _rel_error(_ise(m)[:k], ref[:k], ok),
        "error_cases": k,
        "n_ok": int(np.sum(np.asarray(m.status) == STATUS_OK)),
        "num_steps_max": int(np.max(np.asarray(m.num_steps))),
    }


def without_position_loop(batch):
    """A Monte-Carlo case batch flown without its position loop, from rest: level, zero
    velocity and controller states, the attitude references of its missions (level flight;
    altitude and yaw steps as they are), the same vehicles and wind."""
    import equinox as eqx
    import jax.numpy as jnp

    scenario = eqx.tree_at(
        lambda s: (s.trim, s.position, s.initial_state),
        batch.scenario,
        (None, None, jnp.zeros_like(batch.scenario.initial_state)),
        is_leaf=lambda x: x is None,
    )
    return eqx.tree_at(
        lambda b: (b.scenario, b.position_loop),
        batch,
        (scenario, None),
        is_leaf=lambda x: x is None,
    )


def montecarlo_case_batch(name: str, n: int, seed: int):
    """The first ``n`` cases of the Monte-Carlo default distribution for the row ``name``
    (`MONTECARLO_CASE_ROWS`)."""
    from .montecarlo import default_distribution, sample_cases

    batch = sample_cases(default_distribution(), n, seed)
    return batch if name == "montecarlo_cases" else without_position_loop(batch)


def montecarlo_reference(batch) -> np.ndarray:
    """(n, 2) tight x64 reference ISE of a Monte-Carlo case batch (Dopri8 ensemble, rtol 1e-10,
    atol 1e-12, the batch's closed loop)."""
    m = simulate_batch(
        AFBL(),
        batch.scenario,
        batch.vehicle,
        batch.model,
        aerodynamics=batch.aerodynamics,
        position_loop=batch.position_loop,
        strategy="ensemble",
        solver=REFERENCE["solver"],
        rtol=REFERENCE["rtol"],
        atol=REFERENCE["atol"],
        dtype="float64",
        group_size=4,
        max_steps=200_000,
    )
    ise = _ise(m)
    ise[np.asarray(m.status) != STATUS_OK] = np.nan
    return ise


def measure_montecarlo_cases(name: str, batch, ref: np.ndarray) -> dict:
    """One row on Monte-Carlo cases: `run_chunk` with the default strategy, run twice
    (compile + run, then run), the second call timed."""
    from .montecarlo import DEFAULT_STRATEGY, STRATEGY_TOLERANCES, run_chunk

    n, rss0 = batch.n_cases, _rss_mb()
    shard = len(jax.local_devices()) > 1
    t = time.perf_counter()
    run_chunk(AFBL(), batch, shard=shard)
    first = time.perf_counter() - t
    t = time.perf_counter()
    m = run_chunk(AFBL(), batch, shard=shard)
    run = time.perf_counter() - t
    ise = np.stack([m["ise_attitude"], m["ise_altitude"]], axis=1).astype(np.float64)
    k = min(n, len(ref))
    ok = (np.asarray(m["status"])[:k] == STATUS_OK) & np.all(np.isfinite(ref[:k]), axis=1)
    rtol, atol = STRATEGY_TOLERANCES[DEFAULT_STRATEGY]
    return {
        "strategy": name,
        "N": n,
        "dtype": "float32",
        "rtol": rtol,
        "atol": atol,
        "devices": len(jax.local_devices()) if shard else 1,
        "position_loop": batch.position_loop is not None,
        "sims_per_s": n / run,
        "seconds": run,
        "compile_s": max(first - run, 0.0),
        "peak_rss_delta_mb": max(_rss_mb() - rss0, 0.0),
        "max_rel_ise_error": _rel_error(ise[:k], ref[:k], ok),
        "error_cases": k,
        "n_ok": int(np.sum(np.asarray(m["status"]) == STATUS_OK)),
        "num_steps_max": int(np.max(m["solver_steps"])),
        "num_steps_mean": float(np.mean(m["solver_steps"])),
    }


def measure_scipy_montecarlo_cases(batch, ref: np.ndarray) -> dict:
    """The ``scipy_rk45_montecarlo_cases`` row: `solve_ivp` (RK45, rtol 1e-6, atol 1e-8) with
    the NumPy closed loop (`afbl_jax.studies.numpy_loop`) of each case of ``batch`` (AFBL), one
    after the other on one core; accuracy against ``ref`` (the x64 reference of the same
    cases)."""
    from .numpy_loop import cases_from_batch

    rss0 = _rss_mb()
    cases = cases_from_batch(batch, AFBL())  # reading the case data is not timed
    t = time.perf_counter()
    results = [c.solve(rtol=1e-6, atol=1e-8) for c in cases]
    run = time.perf_counter() - t
    n = len(cases)
    ise = np.array([r.ise[:2] for r in results])
    ok = np.array([r.status == "ok" for r in results]) & np.all(np.isfinite(ref[:n]), axis=1)
    return {
        "strategy": MONTECARLO_SCIPY_ROW,
        "N": n,
        "dtype": "float64",
        "rtol": 1e-6,
        "atol": 1e-8,
        "devices": 1,
        "position_loop": batch.position_loop is not None,
        "sims_per_s": n / run,
        "seconds": run,
        "compile_s": 0.0,
        "peak_rss_delta_mb": max(_rss_mb() - rss0, 0.0),
        "max_rel_ise_error": _rel_error(ise, ref[:n], ok),
        "error_cases": n,
        "n_ok": int(sum(r.status == "ok" for r in results)),
        "num_steps_max": max(r.steps for r in results),
        "num_steps_mean": float(np.mean([r.steps for r in results])),
    }


def measure_diffrax_loop(scenarios: Scenario, ref: np.ndarray) -> dict:
    n = scenarios.t0.shape[0]
    ctrl, rss0 = AFBL(), _rss_mb()

    def one(i):
        r = simulate(ctrl, _index(scenarios, i), rtol=1e-6, atol=1e-8, n_save=0)
        return jax.block_until_ready(r)

    t = time.perf_counter()
    one(0)
    first = time.perf_counter() - t
    t = time.perf_counter()
    results = [one(i) for i in range(n)]
    run = time.perf_counter() - t
    ise = np.array([[float(r.ise_attitude), float(r.ise_altitude)] for r in results])
    ok = np.array([int(r.status) == STATUS_OK for r in results])
    return {
        "strategy": "diffrax_loop",
        "N": n,
        "dtype": "float64",
        "rtol": 1e-6,
        "atol": 1e-8,
        "sims_per_s": n / run,
        "seconds": run,
        "compile_s": max(first - run / n, 0.0),
        "peak_rss_delta_mb": max(_rss_mb() - rss0, 0.0),
        "max_rel_ise_error": _rel_error(ise, ref, ok),
        "n_ok": int(ok.sum()),
        "num_steps_max": int(max(int(r.num_steps) for r in results)),
        "devices": 1,
    }


def measure_scipy(draws: np.ndarray, ref: np.ndarray) -> dict:
    rss0 = _rss_mb()
    t = time.perf_counter()
    ise = scipy_loop(draws)
    run = time.perf_counter() - t
    ok = np.all(np.isfinite(ise), axis=1)
    return {
        "strategy": "scipy_rk45_loop",
        "N": len(draws),
        "dtype": "float64",
        "rtol": 1e-6,
        "atol": 1e-8,
        "sims_per_s": len(draws) / run,
        "seconds": run,
        "compile_s": 0.0,
        "peak_rss_delta_mb": max(_rss_mb() - rss0, 0.0),
        "max_rel_ise_error": _rel_error(ise, ref, ok),
        "n_ok": int(ok.sum()),
        "num_steps_max": None,
        "devices": 1,
    }


def measure_tuning_gradient(n_cases: int, seed: int, repeats: int = 3, log=print) -> list[dict]:
    """The ``tuning_gradient`` rows (module docstring): float32, then float64."""
    from .tuning import TuneConfig, gradient_cost

    rss0 = _rss_mb()
    cost = gradient_cost(TuneConfig(n_cases=int(n_cases), seed=seed), repeats=repeats, log=log)
    rows = []
    for dtype in ("float32", "float64"):
        d = cost[dtype]
        rows.append(
            {
                "strategy": GRADIENT_ROW,
                "N": cost["n_cases"],
                "dtype": dtype,
                "rtol": d["rtol"],
                "atol": d["atol"],
                "sims_per_s": cost["n_cases"] / d["gradient_s"],
                "seconds": d["gradient_s"],
                "compile_s": d["gradient_compile_s"],
                "peak_rss_delta_mb": max(_rss_mb() - rss0, 0.0),
                "max_rel_ise_error": None,
                "n_ok": None,
                "num_steps_max": None,
                "devices": 1,
                "forward_s": d["forward_s"],
                "gradient_s": d["gradient_s"],
                "gradient_to_forward": d["gradient_s"] / d["forward_s"],
                "gradient_to_forward_float32": d["gradient_s"] / cost["float32"]["forward_s"],
                "gradient_rel_error": (
                    cost["float32_gradient_rel_error"] if dtype == "float32" else 0.0
                ),
            }
        )
    return rows


@dataclass(frozen=True)
class BenchConfig:
    """What `run_benchmark` measures (see the module docstring).

    Attributes:
        out: output folder (bench.json, bench.png).
        sizes: batch sizes N of the batched rows.
        strategies: rows to measure (`ALL_STRATEGIES`).
        scipy_cases, loop_cases: cases of the per-case loops (sims/s does not depend on N).
        ref_cases: cases with a tight x64 reference (accuracy on the first min(N, ref_cases)).
        seed: seed of the cases.
        montecarlo_ref_cases: cases of the Monte-Carlo rows with a tight x64 reference.
        scipy_montecarlo_cases: cases of the ``scipy_rk45_montecarlo_cases`` loop (at most
            ``montecarlo_ref_cases``; sims/s does not depend on N).
        gradient_cases, gradient_repeats: training cases and timing repeats of the
            ``tuning_gradient`` rows.
    """

    out: Path
    sizes: tuple = DEFAULT_SIZES
    strategies: tuple = ALL_STRATEGIES
    scipy_cases: int = 16
    loop_cases: int = 64
    ref_cases: int = 4096
    seed: int = 0
    montecarlo_ref_cases: int = 64
    scipy_montecarlo_cases: int = 4
    gradient_cases: int = 16
    gradient_repeats: int = 3


def run_benchmark(config: BenchConfig, log: Callable[[str], None] = print) -> list[dict]:
    """Measure every strategy; write OUT/bench.json and OUT/bench.png; return the rows."""
    out, sizes, strategies = config.out, config.sizes, config.strategies
    scipy_cases, loop_cases, ref_cases = config.scipy_cases, config.loop_cases, config.ref_cases
    seed = config.seed
    unknown = set(strategies) - set(ALL_STRATEGIES)
    if unknown:
        raise ValueError(
            f"unknown strategies {sorted(unknown)}; allowed: {', '.join(ALL_STRATEGIES)}."
        )
    if not sizes or any(int(s) <= 0 for s in sizes):
        raise ValueError(f"sizes must be positive integers, got {list(sizes)}.")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    n_max = max(max(sizes), scipy_cases, loop_cases)
    scenarios, draws = bench_cases(n_max, seed)
    n_ref = max(min(n_max, ref_cases), scipy_cases, loop_cases)
    ref, reference_check = None, None
    if any(s in strategies for s in (*LOOP_STRATEGIES, *BATCH_ROWS)):
        log(f"reference: {n_ref} cases, x64 Dopri8 rtol 1e-10 ...")
        ref = reference_ise(_index(scenarios, slice(0, n_ref)))
        # independent check of the reference: per-case simulate, Dopri8 tight
        k = min(4, n_max)
        direct = np.array(
            [
                [float(r.ise_attitude), float(r.ise_altitude)]
                for r in (
                    simulate(
                        AFBL(),
                        _index(scenarios, i),
                        solver="dopri8",
                        rtol=1e-10,
                        atol=1e-12,
                        n_save=0,
                    )
                    for i in range(k)
                )
            ]
        )
        reference_check = _rel_error(direct, ref[:k], np.ones(k, bool))
    ref_unmodeled = None
    if any(BATCH_STRATEGIES[s].get("unmodeled") for s in strategies if s in BATCH_STRATEGIES):
        log(f"reference of the realistic vehicle: {n_ref} cases, x64 Dopri8 rtol 1e-10 ...")
        ref_unmodeled = reference_ise(
            _index(scenarios, slice(0, n_ref)), unmodeled=realistic_unmodeled()
        )
    rows: list[dict] = []
    if "scipy_rk45_loop" in strategies:
        log(f"scipy_rk45_loop on {scipy_cases} cases ...")
        rows.append(measure_scipy(draws[:scipy_cases], ref[:scipy_cases]))
    if "diffrax_loop" in strategies:
        log(f"diffrax_loop on {loop_cases} cases ...")
        rows.append(measure_diffrax_loop(_index(scenarios, slice(0, loop_cases)), ref[:loop_cases]))
    for n in sorted(int(s) for s in sizes):
        for name, cfg in BATCH_STRATEGIES.items():
            chunk = cfg.get("chunk_size")
            if (
                chunk is not None
                and not cfg.get("always")
                and n <= chunk * len(jax.local_devices())
            ):
                continue  # identical to the unchunked row
            if name in strategies:
                log(f"{name} N={n} ...")
                row_ref = ref_unmodeled if cfg.get("unmodeled") else ref
                rows.append(measure_batch(name, _index(scenarios, slice(0, n)), row_ref))
                log(
                    f"  {rows[-1]['sims_per_s']:.1f} sims/s, err "
                    f"{rows[-1]['max_rel_ise_error']:.2e}"
                )
    mc_rows = [name for name in MONTECARLO_CASE_ROWS if name in strategies]
    mc_scipy = MONTECARLO_SCIPY_ROW in strategies
    if mc_rows or mc_scipy:
        n_mc_ref = min(n_max, config.montecarlo_ref_cases)
        refs: dict[str, np.ndarray] = {}

        def case_batch(name):
            log(f"{name}: sampling {n_max} cases, x64 Dopri8 reference of {n_mc_ref} ...")
            batch = montecarlo_case_batch(name, n_max, seed)
            refs[name] = montecarlo_reference(batch.take(np.arange(n_mc_ref)))
            return batch

        sampled = {}
        if mc_scipy:
            batch = sampled["montecarlo_cases"] = case_batch("montecarlo_cases")
            k = max(1, min(config.scipy_montecarlo_cases, n_mc_ref))
            log(f"{MONTECARLO_SCIPY_ROW} on {k} cases ...")
            rows.append(
                measure_scipy_montecarlo_cases(batch.take(np.arange(k)), refs["montecarlo_cases"])
            )
            log(f"  {rows[-1]['sims_per_s']:.2f} sims/s, err {rows[-1]['max_rel_ise_error']:.2e}")
        for name in mc_rows:
            batch = sampled[name] if name in sampled else case_batch(name)
            for n in sorted(int(s) for s in sizes):
                log(f"{name} N={n} ...")
                rows.append(measure_montecarlo_cases(name, batch.take(np.arange(n)), refs[name]))
                log(
                    f"  {rows[-1]['sims_per_s']:.1f} sims/s, err "
                    f"{rows[-1]['max_rel_ise_error']:.2e}"
                )
    if GRADIENT_ROW in strategies:
        log(f"{GRADIENT_ROW} on {config.gradient_cases} training cases ...")
        rows += measure_tuning_gradient(
            config.gradient_cases, seed, config.gradient_repeats, log=lambda s: log("  " + s)
        )
    # each row's ratio is to the scipy loop on its own kind of cases, measured in this run: the
    # canonical rows to scipy_rk45_loop, the Monte-Carlo case rows to scipy_rk45_montecarlo_cases
    # (to scipy_rk45_loop when that row is not measured)
    speed = {r["strategy"]: r["sims_per_s"] for r in rows if r["strategy"].startswith("scipy_")}
    for r in rows:
        baseline = "scipy_rk45_loop"
        if r["strategy"] in (MONTECARLO_SCIPY_ROW, *MONTECARLO_CASE_ROWS) and mc_scipy:
            baseline = MONTECARLO_SCIPY_ROW
        if r["strategy"] == GRADIENT_ROW:
            baseline = None  # not a simulation of the benchmark's cases
        r["ratio_baseline"] = baseline if baseline in speed else None
        r["ratio_to_scipy"] = r["sims_per_s"] / speed[baseline] if baseline in speed else None
    meta = run_metadata(
        {
            "sizes": sorted(int(s) for s in sizes),
            "strategies": list(strategies),
            "scipy_cases": scipy_cases,
            "loop_cases": loop_cases,
            "ref_cases": n_ref,
            "seed": seed,
            "case": "paper_scenario('uncertain','step'), AFBL paper gains, 20 s; payload fraction "
            "U[0,0.5], torque/force pulse scales U[0.5,1.5]",
            "montecarlo_cases": "the default Monte-Carlo distribution's cases 0..N-1 of the seed, "
            "AFBL paper gains",
            "montecarlo_ref_cases": config.montecarlo_ref_cases,
            "scipy_montecarlo_cases": config.scipy_montecarlo_cases,
            "reference": REFERENCE,
            "reference_check_max_rel_error": reference_check,
            "gradient_cases": config.gradient_cases,
            "gradient_repeats": config.gradient_repeats,
        }
    )
    for r in rows:
        r["meta"] = meta
    (out / "bench.json").write_text(json.dumps(rows, indent=2))
    from ..plotting.bench import plot_benchmark

    plot_benchmark(rows, out / "bench.png", (*BATCH_STRATEGIES, *MONTECARLO_CASE_ROWS))
    return rows


def format_rows(rows: list[dict]) -> str:
    head = (
        f"{'strategy':<34}{'N':>7}{'dev':>4}{'dtype':>9}{'sims/s':>11}{'x scipy':>9}"
        f"{'compile s':>11}{'rss MB':>8}{'max rel err':>13}"
    )
    lines = [head]
    for r in rows:
        ratio = "-" if r["ratio_to_scipy"] is None else f"{r['ratio_to_scipy']:.1f}"
        error = "-" if r["max_rel_ise_error"] is None else f"{r['max_rel_ise_error']:.2e}"
        lines.append(
            f"{r['strategy']:<34}{r['N']:>7}{r['devices']:>4}{r['dtype']:>9}"
            f"{r['sims_per_s']:>11.1f}"
            f"{ratio:>9}{r['compile_s']:>11.1f}{r['peak_rss_delta_mb']:>8.0f}"
            f"{error:>13}"
        )
    for r in rows:
        if r["strategy"] == GRADIENT_ROW:
            lines.append(
                f"{GRADIENT_ROW} {r['dtype']}: value-and-gradient {r['gradient_s']:.2f} s = "
                f"{r['gradient_to_forward']:.1f}x its forward pass ({r['forward_s']:.2f} s), "
                f"{r['gradient_to_forward_float32']:.1f}x the float32 forward pass "
                f"({r['N']} cases)"
            )
    return "\n".join(lines)
