"""Unmodeled-dynamics study: ISE and failure rate of FBL and AFBL over tau_m x f_c x noise.

For every controller, every grid cell (motor time constant tau_m, control rate f_c, noise
level) runs the four canonical scenarios ({ideal, uncertain} x {step, sine}) on the chosen
plant (default: full rigid body) with a digital controller (delay ``delay_samples`` samples);
with noise on, each scenario runs with ``n_seeds`` noise seeds. A cell's failure rate is the
fraction of its runs that did not finish ``ok`` (diverged or solver failure); its ISE values are
means over the runs that finished. All cells with the same f_c form one `jax.vmap` batch (f_c
sets the static scan length).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from .._validation import MAX_SEED
from ..io import gains_to_dict, run_metadata
from ..model import UnmodeledDynamics, make_controller, stack_unmodeled
from ..scenario import PROFILES, SCENARIO_KINDS, paper_scenario, stack_scenarios
from ..sim import simulate

NOMINAL_NOISE = {
    "noise_angle": 0.005,
    "noise_rate": 0.02,
    "noise_altitude": 0.02,
    "noise_vertical_speed": 0.05,
}
"""Noise level 1: standard deviations [rad, rad/s, m, m/s] (typical small-UAV estimates)."""
DEFAULT_TAUS = (0.0, 0.02, 0.04, 0.06, 0.1)
DEFAULT_RATES = (50.0, 100.0, 250.0, 500.0)
DEFAULT_NOISE_LEVELS = (0.0, 1.0)


@dataclass
class UnmodeledStudyResult:
    """Per controller, arrays indexed ``(noise, tau, rate)`` over the grid."""

    taus: list[float]
    rates: list[float]
    noise_levels: list[float]
    failure_rate: dict[str, np.ndarray]
    ise_attitude: dict[str, np.ndarray]
    ise_altitude: dict[str, np.ndarray]
    baseline: dict[str, dict[str, float]]
    config: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        def arr(a):
            return [
                [[None if not math.isfinite(v) else float(v) for v in row] for row in plane]
                for plane in np.asarray(a)
            ]

        return {
            "axes": {
                "noise_level": self.noise_levels,
                "motor_tau_s": self.taus,
                "control_rate_hz": self.rates,
            },
            "layout": "[noise_level][motor_tau][control_rate]",
            "failure_rate": {k: arr(v) for k, v in self.failure_rate.items()},
            "ise_attitude_mean_ok": {k: arr(v) for k, v in self.ise_attitude.items()},
            "ise_altitude_mean_ok": {k: arr(v) for k, v in self.ise_altitude.items()},
            "baseline_paper_model_continuous": self.baseline,
            "meta": run_metadata(self.config),
        }


def _cases(taus, rate, noise_levels, n_seeds, plant, delay, duration, seed):
    """Flat lists (settings, scenario index, (noise, tau) index) for one control rate."""
    settings, scen_idx, cell = [], [], []
    max_delay = max(8, delay)
    for i_n, level in enumerate(noise_levels):
        seeds = range(n_seeds) if level > 0 else range(1)
        for i_t, tau in enumerate(taus):
            for s in seeds:
                for j in range(len(SCENARIO_KINDS) * len(PROFILES)):
                    noise = {k: level * v for k, v in NOMINAL_NOISE.items()}
                    settings.append(
                        UnmodeledDynamics.make(
                            plant=plant,
                            motor_tau=tau,
                            control_rate=rate,
                            duration=duration,
                            delay_samples=delay,
                            seed=seed + 1000 * s + j,
                            max_delay=max_delay,
                            **noise,
                        )
                    )
                    scen_idx.append(j)
                    cell.append((i_n, i_t))
    return settings, np.array(scen_idx), cell


@dataclass(frozen=True)
class UnmodeledStudyConfig:
    """The grid of `run_unmodeled_study` (units: taus [s], rates [Hz], noise levels as multiples
    of `NOMINAL_NOISE`); ``controllers`` default: fbl and afbl with the paper's gains."""

    controllers: dict | None = None
    taus: tuple = DEFAULT_TAUS
    rates: tuple = DEFAULT_RATES
    noise_levels: tuple = DEFAULT_NOISE_LEVELS
    n_seeds: int = 2
    plant: str = "full"
    delay_samples: int = 1
    seed: int = 0
    rtol: float = 1e-6
    atol: float = 1e-8
    progress: bool = True


def run_unmodeled_study(config: UnmodeledStudyConfig | None = None) -> UnmodeledStudyResult:
    cfg = UnmodeledStudyConfig() if config is None else config
    controllers, taus, rates, noise_levels = cfg.controllers, cfg.taus, cfg.rates, cfg.noise_levels
    n_seeds, plant, delay_samples, seed = cfg.n_seeds, cfg.plant, cfg.delay_samples, cfg.seed
    rtol, atol, progress = cfg.rtol, cfg.atol, cfg.progress
    """Run the grid (see module docstring); ``controllers`` default: fbl and afbl, paper gains."""
    if controllers is None:
        controllers = {n: make_controller(n) for n in ("fbl", "afbl")}
    if not taus or not rates or not noise_levels or n_seeds < 1:
        raise ValueError("taus, rates and noise_levels must be non-empty and n_seeds >= 1.")
    if not 0 <= seed <= MAX_SEED - 1000 * n_seeds:
        raise ValueError(
            f"seed must lie in [0, 2^63 - 1 - 1000 x {n_seeds} seeds] (the runs use the noise "
            f"seeds seed + 1000 s + j), got {seed}."
        )
    if any(t < 0 for t in taus) or any(r <= 0 for r in rates) or any(n < 0 for n in noise_levels):
        raise ValueError("motor taus must be >= 0 s, rates > 0 Hz, noise levels >= 0.")
    scenarios = [paper_scenario(k, p) for k in SCENARIO_KINDS for p in PROFILES]
    duration = float(scenarios[0].t1 - scenarios[0].t0)
    batch_all = stack_scenarios(scenarios)
    shape = (len(noise_levels), len(taus), len(rates))
    fail = {n: np.zeros(shape) for n in controllers}
    ise_a = {n: np.full(shape, np.nan) for n in controllers}
    ise_z = {n: np.full(shape, np.nan) for n in controllers}
    baseline = {}
    start = time.time()
    for name, ctrl in controllers.items():
        base = jax.vmap(lambda sc, c=ctrl: simulate(c, sc, n_save=0, rtol=rtol, atol=atol))(
            batch_all
        )
        baseline[name] = {
            "ise_attitude_mean": float(jnp.mean(base.ise_attitude)),
            "ise_altitude_mean": float(jnp.mean(base.ise_altitude)),
            "failures": int(jnp.sum(base.status != 0)),
        }
        for i_r, rate in enumerate(rates):
            settings, scen_idx, cell = _cases(
                taus, rate, noise_levels, n_seeds, plant, delay_samples, duration, seed
            )
            batch_u = stack_unmodeled(settings)
            batch_s = jax.tree.map(lambda a, idx=scen_idx: a[idx], batch_all)

            @jax.jit
            def run(sc, u, c=ctrl):
                return jax.vmap(
                    lambda s, uu: simulate(c, s, n_save=0, rtol=rtol, atol=atol, unmodeled=uu)
                )(sc, u)

            r = run(batch_s, batch_u)
            status = np.asarray(r.status)
            ia, iz = np.asarray(r.ise_attitude), np.asarray(r.ise_altitude)
            for i_n in range(len(noise_levels)):
                for i_t in range(len(taus)):
                    sel = np.array([c == (i_n, i_t) for c in cell])
                    ok = sel & (status == 0)
                    fail[name][i_n, i_t, i_r] = 1.0 - ok.sum() / sel.sum()
                    if ok.any():
                        ise_a[name][i_n, i_t, i_r] = ia[ok].mean()
                        ise_z[name][i_n, i_t, i_r] = iz[ok].mean()
            if progress:
                print(
                    f"  {name}: f_c = {rate:g} Hz done ({len(settings)} runs, "
                    f"{time.time() - start:.0f} s elapsed)",
                    flush=True,
                )
    config = {
        "controllers": {n: gains_to_dict(c) for n, c in controllers.items()},
        "taus_s": list(taus),
        "rates_hz": list(rates),
        "noise_levels": list(noise_levels),
        "nominal_noise_std": NOMINAL_NOISE,
        "n_seeds": n_seeds,
        "plant": plant,
        "delay_samples": delay_samples,
        "seed": seed,
        "rtol": rtol,
        "atol": atol,
        "scenarios": [f"{k}_{p}" for k in SCENARIO_KINDS for p in PROFILES],
        "elapsed_s": round(time.time() - start, 1),
    }
    return UnmodeledStudyResult(
        list(taus), list(rates), list(noise_levels), fail, ise_a, ise_z, baseline, config
    )


def format_study_table(result: UnmodeledStudyResult) -> str:
    """Failure rate / mean ISE per grid cell, one block per controller and noise level."""
    lines = []
    for name in result.failure_rate:
        b = result.baseline[name]
        lines.append(
            f"{name}: paper model, continuous control: mean ISE att "
            f"{b['ise_attitude_mean']:.3e}, alt {b['ise_altitude_mean']:.3e}"
        )
        for i_n, level in enumerate(result.noise_levels):
            lines.append(f"  noise level {level:g}: failure rate / mean ISE att / mean ISE alt")
            lines.append("  tau_m [s] \\ f_c [Hz]" + "".join(f"{r:>28g}" for r in result.rates))
            for i_t, tau in enumerate(result.taus):
                cells = []
                for i_r in range(len(result.rates)):
                    f = result.failure_rate[name][i_n, i_t, i_r]
                    a = result.ise_attitude[name][i_n, i_t, i_r]
                    z = result.ise_altitude[name][i_n, i_t, i_r]
                    cells.append(f"{f:>5.2f} / {a:8.2e} / {z:8.2e}")
                lines.append(f"  {tau:<20g}" + "".join(f"{c:>28}" for c in cells))
        lines.append("")
    return "\n".join(lines)


def write_study(result: UnmodeledStudyResult, out: Path) -> Path:
    """Write OUT/unmodeled_dynamics.json and .txt; returns the JSON path."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "unmodeled_dynamics.json"
    path.write_text(json.dumps(result.to_json(), indent=2) + "\n")
    (out / "unmodeled_dynamics.txt").write_text(format_study_table(result) + "\n")
    return path
