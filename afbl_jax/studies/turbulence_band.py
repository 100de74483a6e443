"""What the turbulence cutoff keeps and what it saves: the default Monte-Carlo study run with the
distribution's lines up to ``omega_cutoff`` and with every line of its grid (up to
``omega_max``), same cases and seed, compared case by case.

The cutoff leaves each case's lines below it untouched (same frequencies, phases and
amplitudes, `afbl_jax.studies.montecarlo.turbulence_lines`), so the two runs differ only by the
turbulence power above the cutoff. `compare_turbulence_bands` reports, per variant, the lines
realised, the run time and the median solver steps per case; per axis u, v, w, the realised
turbulence variance the cutoff keeps (summed over the cases, and the case that keeps least);
per controller and ISE metric, the relative difference of each case's ISE between the two runs
(over the runs ok in both) and the runs whose status differs.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..io import read_results
from ..model import make_controller
from .montecarlo import Distribution, StudyConfig, run_study, turbulence_lines

ISE_COLUMNS = ("ise_attitude", "ise_altitude", "ise_position")
"""Per-case ISE columns compared [rad^2 s, m^2 s, m^2 s]."""


def _variant(distribution: Distribution, all_lines: bool) -> Distribution:
    spec = distribution.to_dict()
    if all_lines:
        spec["turbulence"]["omega_cutoff"] = float(spec["turbulence"]["omega_max"])
    return Distribution(spec, distribution.source + (" (every line)" if all_lines else ""))


def compare_turbulence_bands(
    work: str | Path,
    n_cases: int = 4096,
    seed: int = 0,
    controllers: tuple[str, ...] = ("fbl", "afbl"),
    distribution: Distribution | None = None,
    echo=print,
    progress: bool = True,
) -> dict:
    """Run the study (paper gains of ``controllers``, ``distribution`` default the default
    distribution) into ``work``/cutoff and ``work``/all_lines and compare them (module
    docstring); ``progress``: the study's progress bar. Returns a JSON-ready dict."""
    base = distribution or Distribution()
    work = Path(work)
    ctrls = {name: make_controller(name) for name in controllers}
    runs = {}
    for key, all_lines in (("cutoff", False), ("all_lines", True)):
        dist = _variant(base, all_lines)
        omega, _ = turbulence_lines(dist.spec["turbulence"])
        echo(f"turbulence band: {key}, {len(omega)} lines up to {omega[-1]:.4g} rad/s")
        out = work / key
        run_study(
            StudyConfig(ctrls, out, n_cases, seed, dist, report=False, progress=progress),
            echo=lambda *_: None,
        )
        meta = json.loads((out / "meta.json").read_text())
        runs[key] = {
            "cols": read_results(out),
            "lines": len(omega),
            "top_line_rad_s": float(omega[-1]),
            "runs_s": meta["phases_seconds"]["runs"],
        }
    cut, full = runs["cutoff"]["cols"], runs["all_lines"]["cols"]
    order_c = np.lexsort((cut["case"], cut["controller"]))
    order_f = np.lexsort((full["case"], full["controller"]))
    cut = {k: v[order_c] for k, v in cut.items()}
    full = {k: v[order_f] for k, v in full.items()}
    if not np.array_equal(cut["case"], full["case"]):
        raise RuntimeError("the two runs did not simulate the same cases")
    doc = {
        "config": {
            "n_cases": n_cases,
            "seed": seed,
            "controllers": list(controllers),
            "turbulence": base.spec["turbulence"],
        },
        "variants": {},
        "variance_kept": {},
        "ise_relative_difference": {},
    }
    for key, r in runs.items():
        cols = r["cols"]
        doc["variants"][key] = {
            "lines": r["lines"],
            "top_line_rad_s": r["top_line_rad_s"],
            "runs_s": r["runs_s"],
            "median_solver_steps": {
                c: float(np.median(cols["solver_steps"][cols["controller"] == c]))
                for c in controllers
            },
        }
    first = cut["controller"] == controllers[0]
    for ax in "uvw":
        kept = cut[f"turbulence_rms_{ax}"][first] ** 2
        whole = full[f"turbulence_rms_{ax}"][first] ** 2
        m = whole > 0
        doc["variance_kept"][ax] = {
            "total": float(np.sum(kept[m]) / np.sum(whole[m])),
            "least": float(np.min(kept[m] / whole[m])) if np.any(m) else None,
        }
    for c in controllers:
        sel = cut["controller"] == c
        ok = sel & (cut["status"] == "ok") & (full["status"] == "ok")
        entry = {"runs_ok_in_both": int(np.sum(ok))}
        entry["status_changed"] = int(np.sum(sel & (cut["status"] != full["status"])))
        for metric in ISE_COLUMNS:
            rel = np.abs(cut[metric][ok] / full[metric][ok] - 1.0)
            entry[metric] = {
                "median": float(np.median(rel)),
                "p99": float(np.quantile(rel, 0.99)),
                "max": float(np.max(rel)),
                "above_1e-3": int(np.sum(rel > 1e-3)),
            }
        doc["ise_relative_difference"][c] = entry
    return doc


def format_turbulence_bands(doc: dict) -> str:
    """The comparison as plain-text tables."""
    lines = ["variant    lines  top line [rad/s]  runs [s]  median solver steps per case"]
    for key, v in doc["variants"].items():
        steps = ", ".join(f"{c} {s:.0f}" for c, s in v["median_solver_steps"].items())
        lines.append(
            f"{key:<10} {v['lines']:<6} {v['top_line_rad_s']:<17.4g} {v['runs_s']:<9.1f} {steps}"
        )
    lines += ["", "axis  variance kept (all cases)  least kept (one case)"]
    for ax, v in doc["variance_kept"].items():
        lines.append(f"{ax:<5} {100 * v['total']:<26.3f} {100 * v['least']:.3f}")
    lines += ["", "controller  metric        median     P99        max        cases > 1e-3"]
    for c, e in doc["ise_relative_difference"].items():
        for metric in ISE_COLUMNS:
            d = e[metric]
            lines.append(
                f"{c:<11} {metric:<13} {d['median']:<10.2e} {d['p99']:<10.2e} "
                f"{d['max']:<10.2e} {d['above_1e-3']}/{e['runs_ok_in_both']}"
            )
        lines.append(f"{c:<11} runs whose status differs: {e['status_changed']}")
    return "\n".join(lines)
