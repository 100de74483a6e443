"""Comparison studies of the tuner, each one function (and one `afbl tune-compare` command):

- `compare_optimizers`: objective against wall time for L-BFGS, Adam, CMA-ES and the hybrid
  (CMA-ES, then L-BFGS) on the same training cases with the same time budget, for several
  seeds (each seed: its own training cases and CMA-ES sampling);
- `compare_controllers`: FBL+PID and AFBL tuned with the same objective, method, budget and
  cases, then paper and tuned gains of both on the same fresh held-out cases (noise on);
- `gradient_cost`: seconds of one objective gradient against one forward evaluation of the
  same cases (float32 and float64, measured in one run), and the float32 gradient's relative
  deviation from the float64 one.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ...io import gains_to_dict, run_metadata
from ...model import make_controller
from ._cases import training_cases
from ._optimize import TuneConfig, Tuner
from ._study import evaluate_heldout, write_history_csv


def compare_optimizers(
    base: TuneConfig,
    methods=("lbfgs", "adam", "cmaes", "hybrid"),
    seeds=(0, 1, 2),
    out: str | Path | None = None,
    progress: bool = False,
    log=print,
) -> dict:
    """Run every method for every seed on the same cases with ``base``'s budget and steps;
    returns {"runs": {method: {seed: history}}, "final": {method: {seed: objective}}}."""
    runs, final, compile_s = {}, {}, {}
    for seed in seeds:
        cases = None
        for method in methods:
            cfg = dataclasses.replace(base, method=method, seed=int(seed))
            tuner = Tuner(cfg, cases=cases)
            cases = tuner.cases
            res = tuner.run(progress=progress, log=log)
            runs.setdefault(method, {})[int(seed)] = res.history
            final.setdefault(method, {})[int(seed)] = res.final_loss
            compile_s.setdefault(method, {})[int(seed)] = res.compile_s
            log(
                f"seed {seed} {method:<6}: objective {res.initial_loss:.4f} -> "
                f"{res.final_loss:.4f} in {res.history[-1]['time_s']:.1f} s "
                f"({len(res.history) - 1} iterations; warm-up {res.compile_s:.1f} s: compile "
                "and one discarded iteration)"
            )
            if out is not None:
                d = Path(out) / f"{method}_seed{seed}"
                d.mkdir(parents=True, exist_ok=True)
                write_history_csv(res.history, d / "history.csv")
    doc = {"runs": runs, "final": final, "compile_s": compile_s, "time_to_reach": {}}
    # wall time each method needs to reach CMA-ES's final objective (per seed)
    if "cmaes" in methods:
        for method in methods:
            for seed in seeds:
                target = final["cmaes"][int(seed)]
                hist = runs[method][int(seed)]
                t = next((h["time_s"] for h in hist if h["loss"] <= target), None)
                doc["time_to_reach"].setdefault(method, {})[int(seed)] = t
    if out is not None:
        out = Path(out)
        meta = run_metadata({**base.to_dict(), "methods": list(methods), "seeds": list(seeds)})
        (out / "optimizers.json").write_text(json.dumps({**doc, "meta": meta}, indent=1) + "\n")
        from ...plotting.tuning import plot_loss_vs_time

        plot_loss_vs_time(runs, out / "loss_vs_time.png", title=f"{base.controller} tuning")
    return doc


def compare_controllers(
    base: TuneConfig,
    seeds=(0, 1, 2),
    n_heldout: int = 1024,
    heldout_seed: int = 1000,
    out: str | Path | None = None,
    progress: bool = False,
    log=print,
) -> dict:
    """Tune FBL+PID and AFBL with ``base``'s method/budget on the same cases per seed; evaluate
    the paper's and the tuned gains of both on ``n_heldout`` fresh cases (noise on)."""
    held = training_cases(n_heldout, heldout_seed, thrust_to_weight=base.thrust_to_weight)
    controllers = {"afbl_paper": make_controller("afbl"), "fbl_paper": make_controller("fbl")}
    tuned_gains = {}
    cases = None
    for seed in seeds:
        if int(seed) == int(heldout_seed):
            raise ValueError("the held-out seed must differ from the training seeds.")
        for ctrl in ("afbl", "fbl"):
            cfg = dataclasses.replace(base, controller=ctrl, seed=int(seed))
            tuner = Tuner(cfg, cases=cases if ctrl == "fbl" else None)
            cases = tuner.cases
            res = tuner.run(progress=progress, log=log)
            log(
                f"seed {seed} {ctrl}: objective {res.initial_loss:.4f} -> {res.final_loss:.4f} "
                f"({len(res.history) - 1} iterations, {res.history[-1]['time_s']:.1f} s)"
            )
            controllers[f"{ctrl}_tuned_seed{seed}"] = res.controller
            tuned_gains[f"{ctrl}_tuned_seed{seed}"] = gains_to_dict(res.controller)
    heldout = evaluate_heldout(controllers, held, base.objective)
    doc = {"heldout": heldout, "gains": tuned_gains}
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        meta = run_metadata(
            {
                **base.to_dict(),
                "seeds": list(seeds),
                "heldout_cases": n_heldout,
                "heldout_seed": heldout_seed,
            }
        )
        (out / "controllers.json").write_text(json.dumps({**doc, "meta": meta}, indent=1) + "\n")
        (out / "controllers.txt").write_text(format_controllers(heldout) + "\n")
    return doc


def format_controllers(heldout: dict) -> str:
    first = next(iter(heldout.values()))
    lines = [
        f"held-out: {first['n_cases']} cases inside the flight envelope "
        f"({first.get('outside_envelope', 0)} outside it left out)",
        f"{'gains':<20}{'att P50':>11}{'alt P50':>11}{'ISE P90':>11}{'ISE CVaR.9':>11}"
        f"{'effort P50':>11}{'failed':>8}",
    ]
    for name, e in heldout.items():
        lines.append(
            f"{name:<20}{e['ise_attitude']['p50']:>11.4e}{e['ise_altitude']['p50']:>11.4e}"
            f"{e['ise']['p90']:>11.4e}{e['ise']['cvar90']:>11.4e}{e['effort']['p50']:>11.4e}"
            f"{e['failures']:>8d}"
        )
    return "\n".join(lines)


def _best_of(fn, repeats: int) -> tuple[float, object]:
    """(best seconds of ``repeats`` calls of ``fn``, the last call's output)."""
    best, value = float("inf"), None
    for _ in range(repeats):
        t = time.perf_counter()
        value = jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - t)
    return best, value


def gradient_cost(base: TuneConfig, repeats: int = 3, log=print) -> dict:
    """Seconds (best of ``repeats``, after compiling) of one forward evaluation and one
    value-and-gradient of the objective on ``base``'s training cases, in float32 and float64,
    the seconds of the first value-and-gradient beyond a compiled one (its tracing and
    compilation: ``gradient_compile_s``), and the float32 gradient's largest deviation from the
    float64 one relative to the float64 gradient's largest entry."""
    out, grads = {}, {}
    cases = None
    for dtype, rtol, atol in (("float32", 3e-6, 3e-7), ("float64", 1e-6, 1e-8)):
        obj = dataclasses.replace(base.objective, dtype=dtype, rtol=rtol, atol=atol)
        tuner = Tuner(dataclasses.replace(base, objective=obj), cases=cases)
        cases = tuner.cases
        z = tuner.space.init_z()
        _best_of(lambda: tuner.loss_and_costs(z)[0], 1)  # compiled (or loaded)
        t_fwd, _ = _best_of(lambda: tuner.loss_and_costs(z)[0], repeats)
        first_grad, _ = _best_of(lambda: tuner.value_and_grad(z)[1], 1)
        t_grad, grad = _best_of(lambda: tuner.value_and_grad(z)[1], repeats)
        grads[dtype] = np.concatenate([np.asarray(v) for v in jax.tree.leaves(grad)])
        out[dtype] = {
            "forward_s": t_fwd,
            "gradient_s": t_grad,
            "rtol": rtol,
            "atol": atol,
            "gradient_compile_s": max(first_grad - t_grad, 0.0),
        }
        log(f"{dtype}: forward {t_fwd:.3f} s, value-and-gradient {t_grad:.3f} s")
    g32, g64 = grads["float32"], grads["float64"]
    out["n_cases"] = int(cases.n_cases)
    out["ratio_gradient64_to_forward32"] = (
        out["float64"]["gradient_s"] / out["float32"]["forward_s"]
    )
    out["ratio_gradient32_to_forward32"] = (
        out["float32"]["gradient_s"] / out["float32"]["forward_s"]
    )
    out["ratio_gradient64_to_forward64"] = (
        out["float64"]["gradient_s"] / out["float64"]["forward_s"]
    )
    out["float32_gradient_rel_error"] = float(jnp.max(jnp.abs(g32 - g64)) / jnp.max(jnp.abs(g64)))
    return out
