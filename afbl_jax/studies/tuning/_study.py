"""`afbl tune`: run the tuner and write gains.json, history.csv, meta.json, figures and the
held-out evaluation (paper gains vs tuned gains on a fresh case set, canonical ISE table)."""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path

import jax
import numpy as np

from ...io import gains_to_dict, run_metadata, save_gains
from ...model import AbstractController, make_controller
from ...sim import STATUS_NAMES
from ..reproduce import SCENARIO_KEYS, ReproduceConfig, run_reproduction
from ._cases import nominal_vehicle, training_cases
from ._objective import ObjectiveConfig, case_costs
from ._optimize import TuneConfig, Tuner, TuneResult

PERCENTILES = (50, 90, 99)


@dataclass
class TuningReport:
    """Everything `run_tuning` produced (also written to the output folder)."""

    result: TuneResult
    paper: AbstractController
    tuned: AbstractController
    heldout: dict
    canonical: dict
    text: str


def evaluate_heldout(
    controllers: dict[str, AbstractController], cases, config: ObjectiveConfig
) -> dict:
    """Per controller: ISE percentiles, mean effort, failure rate on ``cases``."""
    fn = jax.jit(lambda c, cs: case_costs(c, cs, config))
    out = {}
    for name, ctrl in controllers.items():
        c = jax.tree.map(np.asarray, fn(ctrl, cases))
        ok = ~c.failed
        ise = c.ise_attitude + config.w_altitude * c.ise_altitude
        entry = {
            "n_cases": int(c.loss.shape[0]),
            "failure_rate": float(np.mean(c.failed)),
            "loss_mean": float(np.mean(c.loss)),
        }
        for key, vals in (
            ("ise", ise),
            ("ise_attitude", c.ise_attitude),
            ("ise_altitude", c.ise_altitude),
        ):
            v = vals[ok] if ok.any() else np.array([np.nan])
            entry[key] = {f"p{p}": float(np.percentile(v, p)) for p in PERCENTILES}
            entry[key]["mean"] = float(np.mean(v))
        entry["effort_mean"] = float(np.mean(c.effort[ok])) if ok.any() else float("nan")
        entry["saturation_mean"] = float(np.mean(c.saturation))
        entry["saturation_max"] = float(np.max(c.saturation))
        entry["saturated_fraction"] = float(np.mean(c.saturation > 0))
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
    heldout: dict, canonical: dict, omega_max: float, heldout_seed: int, config: TuneConfig
) -> str:
    w = config.objective.w_altitude
    lines = [
        f"Held-out evaluation: {next(iter(heldout.values()))['n_cases']} fresh cases "
        f"(seed {heldout_seed}; training seed {config.seed}), rotor limit omega_max = "
        f"{omega_max:.1f} rad/s",
        f"ISE = ISE_att + {w:g} ISE_alt over ok runs; effort = mean int |u - u_hover|^2 dt; "
        "sat = saturation integral [s] (mean, max, share of cases > 0); objective = mean J",
        f"{'gains':<8}{'ISE p50':>11}{'ISE p90':>11}{'ISE p99':>11}{'att p50':>11}"
        f"{'alt p50':>11}{'effort':>9}{'sat mean':>10}{'sat max':>9}{'sat>0':>7}"
        f"{'objective':>11}{'failed':>8}",
    ]
    for name, e in heldout.items():
        lines.append(
            f"{name:<8}{e['ise']['p50']:>11.4e}{e['ise']['p90']:>11.4e}"
            f"{e['ise']['p99']:>11.4e}{e['ise_attitude']['p50']:>11.4e}"
            f"{e['ise_altitude']['p50']:>11.4e}{e['effort_mean']:>9.2f}"
            f"{e['saturation_mean']:>10.2e}{e['saturation_max']:>9.2e}"
            f"{100 * e['saturated_fraction']:>6.0f}%{e['loss_mean']:>11.4e}"
            f"{100 * e['failure_rate']:>7.1f}%"
        )
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
) -> TuningReport:
    """Tune, then evaluate paper vs tuned gains and write every output file to ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    heldout_seed = config.seed + 1 if heldout_seed is None else int(heldout_seed)
    if heldout_seed == config.seed and config.objective.objective == "robust":
        raise ValueError("the held-out seed must differ from the training seed.")
    n_heldout = config.n_cases if heldout_cases is None else int(heldout_cases)
    tuner = Tuner(config)
    result = tuner.run(out, resume=resume, progress=progress, log=log)
    paper, tuned = make_controller(config.controller), result.controller
    save_gains(tuned, out / "gains.json")
    write_history_csv(result.history, out / "history.csv")
    log(
        f"loss {result.initial_loss:.5e} (paper gains) -> {result.final_loss:.5e} (tuned), "
        f"{config.steps} steps"
    )
    cases = training_cases(n_heldout, heldout_seed, thrust_to_weight=config.thrust_to_weight)
    controllers = {"paper": paper, "tuned": tuned}
    heldout = evaluate_heldout(controllers, cases, config.objective)
    rep, canonical, omega_max = evaluate_canonical(controllers, config.thrust_to_weight)
    text = format_report(heldout, canonical, omega_max, heldout_seed, config)
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
    doc = {
        "paper_gains": gains_to_dict(paper),
        "tuned_gains": gains_to_dict(tuned),
        "initial_loss": result.initial_loss,
        "final_loss": result.final_loss,
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
        plot_before_after(rep.runs, omega_max, out / "before_after.png")
    return TuningReport(result, paper, tuned, heldout, canonical, text)
