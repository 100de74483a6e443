"""`afbl tune`: run the tuner and write gains.json, history.csv, meta.json, figures and the
held-out evaluation (paper gains vs tuned gains on a fresh case set, canonical ISE table)."""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import equinox as eqx
import jax
import numpy as np

from ...io import gains_to_dict, run_metadata, save_gains
from ...model import AbstractController, make_controller
from ...sim import STATUS_NAMES
from ..executors import Executor
from ..montecarlo import wilson_interval
from ..reproduce import SCENARIO_KEYS, ReproduceConfig, run_reproduction
from ._cases import nominal_vehicle, training_cases
from ._objective import ObjectiveConfig, case_costs, envelope_weights, limit_report
from ._optimize import CHECKPOINT_STATE, TuneConfig, Tuner, TuneResult, within_deadline

HELDOUT_CASES = 1024
"""Default number of fresh held-out cases."""
PERCENTILES = (50, 90, 99)
CVAR_LEVEL = 0.9
HELDOUT_SOLVER = {"dtype": "float32", "rtol": 3e-6, "atol": 3e-7}
"""Held-out solves: the Monte-Carlo study's default (float32 ensemble, rtol 3e-6, atol 3e-7)."""
HELDOUT_METRICS = ("ise", "ise_attitude", "ise_altitude", "effort", "saturation")


@dataclass
class TuningReport:
    """Everything `run_tuning` produced (also written to the output folder)."""

    result: TuneResult | None
    paper: AbstractController
    tuned: AbstractController
    heldout: dict | None
    canonical: dict | None
    text: str
    limits: dict | None = None


def cvar(values: np.ndarray, level: float = CVAR_LEVEL) -> float:
    """Mean of the worst ceil((1 - level) n) values (the upper tail; CVaR_level)."""
    v = np.sort(np.asarray(values, dtype=float))
    k = max(1, math.ceil((1.0 - level) * v.size))
    return float(np.mean(v[-k:]))


def distribution_stats(values: np.ndarray) -> dict:
    """P50/P90/P99, CVaR_0.9 and mean of ``values`` (finite ones)."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return {**{f"p{p}": math.nan for p in PERCENTILES}, "cvar90": math.nan, "mean": math.nan}
    out = {f"p{p}": float(np.percentile(v, p)) for p in PERCENTILES}
    out["cvar90"] = cvar(v)
    out["mean"] = float(np.mean(v))
    return out


@eqx.filter_jit
def _heldout_costs(config: ObjectiveConfig, controller, cases):
    return case_costs(controller, cases, config)


def evaluate_heldout(
    controllers: dict[str, AbstractController],
    cases,
    config: ObjectiveConfig,
    solver: dict | None = None,
) -> dict:
    """Per controller, on the ``cases`` inside the vehicle's flight envelope (sensor noise as
    sampled; a case outside it, decided before simulating, is no controller's failure and is
    left out and counted as ``outside_envelope``): P50/P90/P99, CVaR_0.9 and mean of
    ISE = ISE_att + ISE_alt [rad^2 s + m^2 s], each ISE, effort and saturation (a failed case
    counts with the costs accumulated until it failed), and the failure rate with its 95 %
    Wilson interval; ``n_cases`` is the number of cases inside the envelope. Solved as the
    Monte-Carlo study does (`HELDOUT_SOLVER`; ``solver`` overrides it)."""
    config = dataclasses.replace(config, **(HELDOUT_SOLVER if solver is None else solver))
    inside = np.asarray(envelope_weights(cases)) > 0
    out = {}
    for name, ctrl in controllers.items():
        c = jax.tree.map(np.asarray, _heldout_costs(config, ctrl, cases))
        n = int(np.sum(inside))
        k = int(np.sum(c.failed[inside]))
        values = {
            "ise": c.ise_attitude + c.ise_altitude,
            "ise_attitude": c.ise_attitude,
            "ise_altitude": c.ise_altitude,
            "effort": c.effort,
            "saturation": c.saturation,
        }
        entry = {
            "n_cases": n,
            "outside_envelope": int(inside.size - n),
            "failures": k,
            "failure_rate": k / n if n else math.nan,
        }
        entry["failure_wilson95"] = list(wilson_interval(k, n))
        for key in HELDOUT_METRICS:
            entry[key] = distribution_stats(values[key][inside])
        entry["saturated_fraction"] = float(np.mean(c.saturation[inside] > 0)) if n else math.nan
        out[name] = entry
    return out


def evaluate_canonical(controllers: dict[str, AbstractController], thrust_to_weight: float | None):
    """The four canonical scenarios (rtol 1e-8) with the tuning's rotor limit."""
    vehicle = nominal_vehicle(thrust_to_weight)
    rep = run_reproduction(
        ReproduceConfig(controllers, vehicle, rtol=1e-8, atol=1e-10, n_save=2001)
    )
    table = {}
    for key in SCENARIO_KEYS:
        table[key] = {}
        for name, r in rep.runs[key].items():
            table[key][name] = {
                "ise_attitude": float(r.ise_attitude),
                "ise_altitude": float(r.ise_altitude),
                "effort": float(r.effort),
                "saturation": float(r.saturation),
                "peak_rotor_speed": float(np.max(r.rotor_speeds)),
                "status": STATUS_NAMES[int(r.status)],
            }
    return rep, table, float(vehicle.omega_max)


def format_report(
    heldout: dict,
    canonical: dict,
    omega_max: float,
    heldout_seed: int,
    config: TuneConfig,
    limits: dict | None = None,
    on_box: list[str] | None = None,
) -> str:
    first = next(iter(heldout.values()))
    outside = first.get("outside_envelope", 0)
    lines = [
        f"Held-out evaluation: {first['n_cases']} fresh cases inside the flight envelope "
        f"({outside} outside it left out; seed {heldout_seed}; training "
        f"seed {config.seed}; sensor noise on), rotor limit omega_max = {omega_max:.1f} rad/s",
        "ISE = ISE_att + ISE_alt [rad^2 s + m^2 s]; effort = int |u - u_hover|^2 dt; "
        "sat = saturation integral [s]; every case inside the envelope counted (failed: costs "
        "until failure); float32 solves (rtol 3e-6, atol 3e-7) as in the Monte-Carlo study",
        f"{'gains':<8}{'metric':<14}{'P50':>11}{'P90':>11}{'P99':>11}{'CVaR0.9':>11}{'mean':>11}",
    ]
    for name, e in heldout.items():
        for key in HELDOUT_METRICS:
            s = e[key]
            lines.append(
                f"{name:<8}{key:<14}{s['p50']:>11.4e}{s['p90']:>11.4e}{s['p99']:>11.4e}"
                f"{s['cvar90']:>11.4e}{s['mean']:>11.4e}"
            )
        lo, hi = e["failure_wilson95"]
        lines.append(
            f"{name:<8}{'failures':<14}{e['failures']:>6d} / {e['n_cases']} = "
            f"{100 * e['failure_rate']:.2f} % (95 % Wilson {100 * lo:.2f}-{100 * hi:.2f} %)"
        )
    if limits is not None:
        lines += [
            "",
            "Limits at the tuned gains (training cases): "
            f"effort {limits['effort_ratio']:.3f} x paper (limit {limits['effort_limit']:g}"
            f"{', ACTIVE' if limits['effort_active'] else ''}); saturation "
            f"{limits['saturation_ratio']:.3g} x scale (limit {limits['saturation_limit']:g}"
            f"{', ACTIVE' if limits['saturation_active'] else ''}); failures "
            f"{limits['failures']} (paper's gains: {limits['failures_reference']})",
        ]
    if on_box is not None:
        lines.append("Gains on the box: " + (", ".join(on_box) if on_box else "none"))
    lines += [
        "",
        "Canonical scenarios (rtol 1e-8, same rotor limit): ISE [rad^2 s, m^2 s], "
        "effort, peak rotor speed [rad/s]",
        f"{'scenario':<16}{'gains':<7}{'ISE att':>12}{'ISE alt':>12}{'effort':>9}"
        f"{'peak rotor':>12}  status",
    ]
    for key, per in canonical.items():
        for name, v in per.items():
            lines.append(
                f"{key:<16}{name:<7}{v['ise_attitude']:>12.4e}{v['ise_altitude']:>12.4e}"
                f"{v['effort']:>9.2f}{v['peak_rotor_speed']:>12.1f}  {v['status']}"
            )
    return "\n".join(lines)


def write_history_csv(history: list[dict], path: Path) -> None:
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(history[0]))
        writer.writeheader()
        writer.writerows(history)


def _out_of_time(config: TuneConfig, out: Path, started: float, resume: bool, log):
    """The outputs of a run whose budget ended before the objective was ready: the starting
    point (the paper's gains) in gains.json, no history, evaluation.txt saying so."""
    out.mkdir(parents=True, exist_ok=True)
    paper = make_controller(config.controller)
    if not resume:
        save_gains(paper, out / "gains.json")
    text = (
        f"Not tuned: the time budget of {config.time_budget:g} s ended before the objective "
        f"was compiled and evaluated ({time.perf_counter() - started:.1f} s); gains.json holds "
        "the starting point (the paper's gains)."
    )
    log(text)
    (out / "evaluation.txt").write_text(text + "\n")
    meta = run_metadata({**config.to_dict(), "resume": resume})
    (out / "meta.json").write_text(json.dumps(meta, indent=2) + "\n")
    return TuningReport(None, paper, paper, None, None, text, None)


def run_tuning(
    config: TuneConfig,
    out: str | Path,
    *,
    resume: bool = False,
    heldout_cases: int | None = None,
    heldout_seed: int | None = None,
    figures: bool = True,
    progress: bool = True,
    log=print,
    distribution=None,
    executor: Executor | None = None,
    started: float | None = None,
) -> TuningReport:
    """Tune, then evaluate paper vs tuned gains and write every output file to ``out``.
    ``executor``: where CMA-ES populations are evaluated (`Tuner`; None: this process).

    ``config.time_budget`` bounds the whole call, from ``started`` (`time.perf_counter`; None:
    the call's start): sampling, compilation, iterations (`Tuner.run` with ``started``) and the
    evaluation. The iterations stop early enough to leave an estimate of the evaluation's time
    (twice the first objective evaluation's, compilation included); the gains and history are
    written when they stop; an evaluation still running at the deadline is abandoned and
    evaluation.txt says so."""
    t_call = time.perf_counter()
    started = t_call if started is None else started
    budget = config.time_budget
    out = Path(out)
    if resume and not (out / CHECKPOINT_STATE).exists():
        raise ValueError(f"no checkpoint in {out} ({CHECKPOINT_STATE} missing).")
    heldout_seed = config.seed + 1 if heldout_seed is None else int(heldout_seed)
    if heldout_seed == config.seed and config.objective.objective == "robust":
        raise ValueError("the held-out seed must differ from the training seed.")
    n_heldout = HELDOUT_CASES if heldout_cases is None else int(heldout_cases)
    if progress:
        log(
            f"sampling the training cases and compiling the objective (first call) ... "
            f"[{time.perf_counter() - started:.1f} s]"
        )
    t_init = time.perf_counter()

    def make_tuner():
        return Tuner(config, distribution=distribution, executor=executor)

    tuner = make_tuner() if budget is None else within_deadline(make_tuner, started + budget)
    t_init = time.perf_counter() - t_init
    if tuner is None:
        return _out_of_time(config, out, started, resume, log)
    if progress:
        log(f"objective at the paper's gains ready in {t_init:.1f} s")
    # a Dask scheduler that does not answer raises here, before anything is written
    result = tuner.run(
        out,
        resume=resume,
        progress=progress,
        log=log,
        started=started if budget is not None else None,
        reserve=2.0 * t_init,
    )
    out.mkdir(parents=True, exist_ok=True)
    paper, tuned = make_controller(config.controller), result.controller
    save_gains(tuned, out / "gains.json")
    write_history_csv(result.history, out / "history.csv")
    log(
        f"objective {result.initial_loss:.5e} (paper gains) -> {result.final_loss:.5e} "
        f"(tuned), {len(result.history) - 1} iterations of {config.method}, "
        f"{result.history[-1]['time_s']:.1f} s"
        + (f"; stopped early: {result.stopped}" if result.stopped else "")
    )
    limits = limit_report(
        result.costs,
        result.reference,
        config.objective,
        int(
            np.sum(
                np.asarray(tuner.reference_costs.failed)
                & (np.asarray(tuner.reference_costs.weights()) > 0)
            )
        ),
    )
    on_box = tuner.space.on_box(result.params)
    cases = training_cases(
        n_heldout, heldout_seed, thrust_to_weight=config.thrust_to_weight, distribution=distribution
    )
    controllers = {"paper": paper, "tuned": tuned}

    def evaluate():
        heldout = evaluate_heldout(controllers, cases, config.objective)
        return heldout, *evaluate_canonical(controllers, config.thrust_to_weight)

    if progress:
        log(f"evaluating paper and tuned gains on {n_heldout} held-out cases ...")
    if budget is None:
        evaluated = evaluate()
    else:
        evaluated = within_deadline(evaluate, started + budget)
    if evaluated is None:
        heldout, rep, canonical, omega_max = None, None, None, None
        text = (
            f"Held-out evaluation not done: the time budget of {budget:g} s was spent before it "
            f"finished (gains.json and history.csv hold the tuned gains)."
        )
    else:
        heldout, rep, canonical, omega_max = evaluated
        text = format_report(heldout, canonical, omega_max, heldout_seed, config, limits, on_box)
    log(text)
    (out / "evaluation.txt").write_text(text + "\n")
    meta = run_metadata(
        {
            **config.to_dict(),
            "heldout_cases": n_heldout,
            "heldout_seed": heldout_seed,
            "resume": resume,
        }
    )
    if tuner.executor_record is not None:
        meta["executor"] = tuner.executor_record
    doc = {
        "paper_gains": gains_to_dict(paper),
        "tuned_gains": gains_to_dict(tuned),
        "initial_loss": result.initial_loss,
        "final_loss": result.final_loss,
        "stopped": result.stopped,
        "limits": limits,
        "gains_on_box": on_box,
        "heldout": heldout,
        "canonical": canonical,
        "omega_max": omega_max,
        "meta": meta,
    }
    (out / "evaluation.json").write_text(json.dumps(doc, indent=2) + "\n")
    (out / "meta.json").write_text(json.dumps(meta, indent=2) + "\n")
    if figures:
        from ...plotting.tuning import plot_before_after, plot_convergence

        plot_convergence(result.history, config, out / "convergence.png")
        if rep is not None:
            plot_before_after(rep.runs, omega_max, out / "before_after.png")
    return TuningReport(result, paper, tuned, heldout, canonical, text, limits)
