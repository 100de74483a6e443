"""The rare-failure studies behind ``afbl falsify`` and ``afbl montecarlo --estimator``.

`run_falsify`: per controller and per search seed, projected multi-start gradient ascent and the
CMA-ES baseline with the same budget from the same starts (`afbl_jax.studies.rare.falsify`),
the most likely failure along the ray to the worst failing case and from there the design point
(`design_point_search`: SLSQP on |z|^2 subject to failing), the worst cases re-simulated
(figures), and optionally the global sensitivities (DGSM from batched gradients, Sobol indices
from SALib) of the failure margin and of the attitude ISE, and the Sobol indices of the failure
indicator. Writes ``falsify.json`` (config, seed, versions, git revision:
`afbl_jax.io.run_metadata`), ``worst_cases.parquet`` (the worst case of every search, its
inputs and margin), ``sensitivity.json`` and figures.

`run_rare_event`: a failure probability per controller by ``"crude"``, ``"is"`` (importance
sampling centred on the most likely failure found by a short gradient search), ``"ce"``
(cross-entropy method) or ``"ce-mixture"`` (cross-entropy method on the variates its stages
find moved in the elite set, with a defensive normal mixture proposal) or ``"subset"`` (subset
simulation, `afbl_jax.studies.rare.subset_simulation`: every variate moved by batched MCMC) in
standard-normal space of the variates. Writes ``rare_event.json`` (estimate, cv, 95 % interval,
simulations, stages or levels; with `afbl_jax.io.run_metadata`) and ``results.parquet`` (the
estimating stage's samples: case inputs, margin, log weight; subset: the last level's samples,
whose log weight is the log of the product of the earlier levels' conditional probabilities,
the same for all of them).
"""

from __future__ import annotations

import functools
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ...io import (
    atomic_write_bytes,
    atomic_write_table,
    atomic_write_text,
    gains_to_dict,
    run_metadata,
)
from ...model import AbstractController
from ...sim import simulate
from ..executors import Executor, LocalExecutor, map_batches
from ..montecarlo import (
    Distribution,
    cases_from_variates,
    default_distribution,
    discrete_variates,
    draw_variates,
    fixed_variates,
    variate_groups,
)
from ._estimators import (
    Estimate,
    cross_entropy,
    cross_entropy_mixture,
    crude,
    importance_sampling,
    to_unit,
)
from ._falsify import (
    cmaes_search,
    design_point,
    design_point_search,
    gradient_ascent,
    most_likely_failure,
)
from ._problem import MarginProblem
from ._sensitivity import dgsm, sobol_indices_outputs
from ._subset import subset_simulation

ESTIMATORS = ("crude", "is", "ce", "ce-mixture", "subset")


@dataclass(frozen=True)
class FalsifyConfig:
    """A worst-case search (`run_falsify`).

    Attributes:
        controllers: name -> controller; out: output folder.
        distribution: case distribution (bounds of the search; ``[unmodeled]`` off).
        starts: starts of the gradient ascent = CMA-ES population size.
        budget: simulations per search (each method, controller and seed).
        seeds: search seeds 0..seeds-1 (seed s starts from cases s * starts ... of the
            distribution's ``seed``); seed: the case seed.
        learning_rate: Adam step on the variates; sigma: CMA-ES initial step.
        attitude_limit [rad], altitude_limit [m]: failure limits (None: divergence limits).
        design_budget: gradient simulations of the design-point search
            (`design_point_search`, from the ray's most likely failure; 0: the ray's point
            only).
        sensitivity_samples: points for DGSM (gradients) and base samples for Sobol (power of
            2); 0: no sensitivities.
        rtol, atol, n_save: solver settings.
    """

    controllers: dict[str, AbstractController]
    out: Path
    distribution: Distribution = field(default_factory=default_distribution)
    starts: int = 8
    budget: int = 64
    seeds: int = 1
    seed: int = 0
    learning_rate: float = 0.05
    sigma: float = 0.3
    attitude_limit: float | None = None
    altitude_limit: float | None = None
    design_budget: int = 16
    sensitivity_samples: int = 0
    rtol: float = 1e-6
    atol: float = 1e-8
    n_save: int = 401

    def to_dict(self) -> dict:
        return {
            "controllers": {n: gains_to_dict(c) for n, c in self.controllers.items()},
            "distribution": self.distribution.to_dict(),
            **{
                k: getattr(self, k)
                for k in (
                    "starts",
                    "budget",
                    "seeds",
                    "seed",
                    "learning_rate",
                    "sigma",
                    "attitude_limit",
                    "altitude_limit",
                    "design_budget",
                    "sensitivity_samples",
                    "rtol",
                    "atol",
                    "n_save",
                )
            },
        }


def _problem(c, controller) -> MarginProblem:
    return MarginProblem(
        controller,
        c.distribution,
        c.attitude_limit,
        c.altitude_limit,
        rtol=c.rtol,
        atol=c.atol,
        n_save=c.n_save,
        dtype=getattr(c, "dtype", None),
    )


def _replay(problem: MarginProblem, u):
    batch = cases_from_variates(problem.distribution, np.asarray(u)[None])
    scenario, vehicle, model = batch.case(0)
    return simulate(
        problem.controller,
        scenario,
        vehicle,
        model,
        rtol=problem.rtol,
        atol=problem.atol,
        n_save=problem.n_save,
        aerodynamics=batch.aerodynamics,
        position_loop=batch.position_loop,
        saving="dense",  # no host callback: the compiled replay is cached
    )


def _inputs_row(problem: MarginProblem, u) -> dict:
    batch = cases_from_variates(problem.distribution, np.asarray(u)[None])
    return {k: float(np.asarray(v)[0]) for k, v in batch.inputs.items()}


def run_falsify(config: FalsifyConfig, echo=print) -> dict:
    """Run the searches (module docstring); returns the summary written to falsify.json."""
    from ...plotting.rare import figure_search, figure_sensitivity, figure_trajectories

    c = config
    out = Path(c.out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    summary: dict = {"controllers": {}}
    histories, replays, rows = {}, {}, []
    for name, controller in c.controllers.items():
        problem = _problem(c, controller)
        runs = []
        for s in range(c.seeds):
            starts = np.asarray(draw_variates(c.distribution, c.starts, c.seed, start=s * c.starts))
            g = gradient_ascent(problem, starts, c.budget, c.learning_rate)
            b = cmaes_search(problem, starts, c.budget, c.sigma, seed=s)
            runs.append({"seed": s, "gradient": g.to_dict(), "cmaes": b.to_dict()})
            for r in (g, b):
                rows.append(
                    {
                        "controller": name,
                        "method": r.method,
                        "search_seed": s,
                        "margin": r.best_margin,
                        "first_failure_simulations": -1
                        if r.first_failure is None
                        else r.first_failure,
                        **_inputs_row(problem, r.best_u),
                    }
                )
            histories[f"{name} gradient seed {s}"] = g.history
            histories[f"{name} CMA-ES seed {s}"] = b.history
            if echo is not None:
                echo(
                    f"{name} seed {s}: gradient best margin {g.best_margin:+.4f}, first failure "
                    f"after {g.first_failure} sims ({g.seconds:.1f} s); CMA-ES "
                    f"{b.best_margin:+.4f}, {b.first_failure} sims ({b.seconds:.1f} s)"
                )
            if s == 0:
                worst = g if g.best_margin >= b.best_margin else b
                replays[name] = (worst, _replay(problem, worst.best_u))
        entry = {"searches": runs, **_first_failure_table(runs)}
        failing = [r for r in rows if r["controller"] == name and r["margin"] > 0]
        if failing:
            worst_u = replays[name][0].best_u
            u_ml, dist, used = most_likely_failure(problem, worst_u)
            entry["most_likely_failure"] = {
                "normal_distance": dist,
                "simulations": used,
                "inputs": _inputs_row(problem, u_ml),
            }
            if c.design_budget:
                dp = design_point_search(problem, u_ml, c.design_budget)
                entry["design_point"] = {
                    "ray_distance": dist,
                    **dp.to_dict(problem.names),
                    "inputs": _inputs_row(problem, dp.u),
                }
                u_ml = dp.u
                if echo is not None:
                    echo(
                        f"{name}: design point at standard-normal distance {dp.distance:.2f} "
                        f"(ray {dist:.2f}), margin {dp.margin:+.2e}, "
                        f"{dp.gradient_simulations} gradient + {dp.simulations} simulations"
                    )
            replays[f"{name} most likely"] = (None, _replay(problem, u_ml))
        if c.sensitivity_samples:
            entry["sensitivity"] = _sensitivity(problem, c.sensitivity_samples, c.seed)
        summary["controllers"][name] = entry
    summary["seconds"] = time.perf_counter() - t_start
    import pyarrow as pa

    atomic_write_table(pa.Table.from_pylist(rows), out / "worst_cases.parquet")
    meta = run_metadata(c.to_dict())
    meta["falsify"] = summary
    atomic_write_text(json.dumps(meta, indent=2, default=_json) + "\n", out / "falsify.json")
    fig_dir = out / "figures"
    fig_dir.mkdir(exist_ok=True)
    _save(figure_search(histories), fig_dir / "falsify_search.png")
    _save(
        figure_trajectories({k: r for k, (_, r) in replays.items()}),
        fig_dir / "falsify_worst_cases.png",
    )
    rankings = sensitivity_rankings(summary["controllers"])
    if rankings:
        _save(figure_sensitivity(rankings), fig_dir / "sensitivity.png")
        atomic_write_text(
            json.dumps(
                {n: e.get("sensitivity") for n, e in summary["controllers"].items()},
                indent=2,
                default=_json,
            )
            + "\n",
            out / "sensitivity.json",
        )
    write_rare_report(out)
    return summary


def sensitivity_rankings(controllers: dict) -> dict:
    """The panels of the sensitivity figure (`afbl_jax.plotting.rare.figure_sensitivity`) from
    the per-controller summaries (``falsify.json``'s ``falsify.controllers``, or
    ``sensitivity.json``'s entries under a ``sensitivity`` key)."""
    rankings = {}
    for name, entry in controllers.items():
        sens = entry.get("sensitivity")
        if sens:
            for key, label in (("margin", "failure margin"), ("ise_attitude", "ISE attitude")):
                d = sens[key]
                rankings[f"{name}: {label}, DGSM bound"] = (
                    d["dgsm"]["names"],
                    d["dgsm"]["bound"],
                    "nu / (pi^2 V) [-] (not for event times, discrete)",
                )
                rankings[f"{name}: {label}, Sobol S_T"] = (
                    d["sobol"]["names"],
                    d["sobol"]["ST"],
                    "total Sobol index [-] (95 % bootstrap interval)",
                    d["sobol"]["ST_conf"],
                )
            d = sens.get("failure")
            if d:
                rankings[f"{name}: failure indicator, Sobol S_T"] = (
                    d["sobol"]["names"],
                    d["sobol"]["ST"],
                    "total Sobol index [-] (95 % bootstrap interval)",
                    d["sobol"]["ST_conf"],
                )
    return rankings


def _first_failure_table(runs) -> dict:
    out = {}
    for method in ("gradient", "cmaes"):
        firsts = [r[method]["first_failure_simulations"] for r in runs]
        found = [f for f in firsts if f is not None]
        out[method] = {
            "found": len(found),
            "searches": len(firsts),
            # a search that found none counts as worse than any that did (inf)
            "median_first_failure": float(np.median([np.inf if f is None else f for f in firsts]))
            if firsts
            else None,
            "best_margin": max(r[method]["best_margin"] for r in runs),
        }
    return out


EVENT_TIME_GROUPS = ("payload_time", "pulse_start", "pulse_duration", "gust_start", "gust_buildup")
"""Variate groups that set when a forcing switches (payload attachment, pulse edges, the gust's
start and build-up): the vector field jumps at those times, so the simulation's derivative with
respect to them (0 from the switch, plus the solver's stepping to the jump) is not the
derivative of the outcome; their DGSM is reported as NaN (their Sobol indices stand)."""


def _sensitivity(problem: MarginProblem, n: int, seed: int, batch: int = 512) -> dict:
    """DGSM (n gradient simulations per output; NaN for `EVENT_TIME_GROUPS` and for discrete
    variates, whose category does not move with a gradient) of the smooth
    failure margin and the attitude ISE, and Sobol indices (n (G + 2) forward simulations,
    shared by all outputs) of the exact failure margin, the attitude ISE and the failure
    indicator (margin > 0; no DGSM: its gradient is 0 almost everywhere), in batches of
    ``batch`` cases under a progress bar."""
    from tqdm.auto import tqdm

    groups = variate_groups(problem.distribution)
    discrete = discrete_variates(problem.distribution)
    no_gradient = {*EVENT_TIME_GROUPS, *(g for g, k in zip(groups, discrete, strict=True) if k)}
    rng = np.random.default_rng(seed)
    u = rng.random((n, problem.dimension))
    out = {}
    for key in ("margin", "ise_attitude"):
        t0 = time.perf_counter()
        values, grads = [], []
        for k in tqdm(range(0, n, batch), desc=f"DGSM {key}", unit="batch"):
            value, grad, _ = problem.value_and_grad(u[k : k + batch], output=key)
            values.append(value)
            grads.append(grad)
        d = dgsm(np.concatenate(grads), np.concatenate(values), groups)
        skip = np.array([g in no_gradient for g in d["names"]])
        d["nu"] = np.where(skip, np.nan, d["nu"])
        d["bound"] = np.where(skip, np.nan, d["bound"])
        d["not_differentiable"] = [n for n in d["names"] if n in no_gradient]
        out[key] = {"dgsm": d, "dgsm_seconds": time.perf_counter() - t0}

    def f(x):
        margins, ises = [], []
        for k in tqdm(range(0, len(x), batch), desc="Sobol", unit="batch"):
            m, envelope = problem.evaluate(x[k : k + batch])
            margins.append(problem.margin_of(m, envelope))
            ises.append(np.asarray(m.ise_attitude))
        margin = np.concatenate(margins)
        return {
            "margin": _finite(margin),
            "ise_attitude": _finite(np.concatenate(ises)),
            "failure": (margin > 0).astype(np.float64),
        }

    t0 = time.perf_counter()
    sob = sobol_indices_outputs(f, problem.dimension, n, seed=seed, groups=groups)
    seconds = time.perf_counter() - t0
    out["failure"] = {
        "failures": int(round(sob["failure"]["mean"] * sob["failure"]["evaluations"]))
    }
    for key in out:
        out[key]["sobol"] = sob[key]
        out[key]["sobol_seconds"] = seconds
    return out


def _finite(y):
    """Non-finite values (a solve that failed before its first sample) replaced by the largest
    finite one."""
    y = np.asarray(y, dtype=np.float64)
    ok = np.isfinite(y)
    return np.where(ok, y, np.max(y[ok]) if ok.any() else 0.0)


@dataclass(frozen=True)
class RareEventConfig:
    """A failure-probability estimate (`run_rare_event`).

    Attributes:
        controllers, out, distribution, seed: as for the Monte-Carlo study.
        estimator: "crude", "is", "ce", "ce-mixture" or "subset".
        n_cases: crude: the cases; is, ce, ce-mixture: samples of the final
            importance-sampling stage; subset: unused.
        n_per_stage, rho, max_stages, adapt_scale: cross-entropy settings; subset: n_per_stage
            is the samples per level (n_per_stage * p0 chains) and max_stages the most levels
            after level 0.
        p0: subset: conditional probability of the intermediate levels, in (0, 0.5].
        components, alpha, max_selected: ce-mixture: components of the normal mixture, weight
            of the nominal (defensive) component, most variates adapted (chosen among all
            non-fixed variates by the stages' selection tests).
        search_budget: gradient simulations (HL-RF iterations, `design_point`) of the search
            for the most likely failure that centres "is" and starts "ce" (0: none; the
            nominal point); "ce-mixture" starts from the nominal distribution (no search).
        attitude_limit [rad], altitude_limit [m]: failure limits (None: divergence limits).
        rtol, atol, n_save: solver settings; dtype: of the margin solves (None: float64;
            "float32": the crude study's ``ensemble_f32`` path, with rtol 3e-6, atol 3e-7);
            batch: simulations per call (and per task on a cluster).
        executor: where the estimators' batches of simulations run (None: this process; a
            `DaskExecutor`: every batch of ``batch`` samples of a crude sample, a
            cross-entropy stage or a subset-simulation level (its seeds, then each MCMC step
            of its chains) is one task of a Dask cluster; the same batches, seeds and numbers
            as in one process). The gradient search of "is"/"ce" runs in this process.
    """

    controllers: dict[str, AbstractController]
    out: Path
    estimator: str = "ce"
    distribution: Distribution = field(default_factory=default_distribution)
    seed: int = 0
    n_cases: int = 1024
    n_per_stage: int = 512
    rho: float = 0.1
    max_stages: int = 10
    adapt_scale: bool = False
    p0: float = 0.1
    components: int = 2
    alpha: float = 0.1
    max_selected: int = 8
    search_budget: int = 8
    attitude_limit: float | None = None
    altitude_limit: float | None = None
    rtol: float = 1e-6
    atol: float = 1e-8
    n_save: int = 401
    dtype: str | None = None
    batch: int = 256
    executor: Executor | None = None

    def to_dict(self) -> dict:
        d = {k: getattr(self, k) for k in self.__dataclass_fields__ if k != "executor"}
        d["controllers"] = {n: gains_to_dict(c) for n, c in self.controllers.items()}
        d["distribution"] = self.distribution.to_dict()
        d["out"] = str(self.out)
        return d


def run_rare_event(config: RareEventConfig, echo=print) -> dict:
    """Estimate each controller's failure probability (module docstring); returns the summary
    written to rare_event.json."""
    import pyarrow as pa

    c = config
    if c.estimator not in ESTIMATORS:
        raise ValueError(f"unknown estimator {c.estimator!r}; allowed: {', '.join(ESTIMATORS)}.")
    if c.estimator == "subset" and not 0 < c.p0 <= 0.5:
        raise ValueError(f"p0 must lie in (0, 0.5], got {c.p0}.")
    if c.estimator == "subset" and round(c.n_per_stage * c.p0) < 2:
        raise ValueError(
            f"subset simulation needs n_per_stage * p0 >= 2 chains, got {c.n_per_stage} * {c.p0}."
        )
    out = Path(c.out)
    if (out / "run.json").exists():
        raise ValueError(
            f"{out} holds a crude Monte-Carlo study (run.json), whose results.parquet a "
            "rare-event run would replace; give another --out folder."
        )
    with (c.executor or LocalExecutor()).session() as session:  # before anything is written
        out.mkdir(parents=True, exist_ok=True)
        summary = _estimate(c, session, echo)
    tables = []
    for name, est in summary.pop("estimates").items():
        batch = cases_from_variates(c.distribution, to_unit(est.z))
        cols = {"controller": np.array([name] * est.n_final, dtype=object)}
        cols.update({kk: np.asarray(v, dtype=np.float64) for kk, v in batch.inputs.items()})
        cols["failure_margin"] = est.margin
        cols["log_weight"] = est.log_weight
        tables.append(pa.table(cols))
    atomic_write_table(pa.concat_tables(tables), out / "results.parquet")
    meta = run_metadata(c.to_dict())
    meta["rare_event"] = summary
    atomic_write_text(json.dumps(meta, indent=2, default=_json) + "\n", out / "rare_event.json")
    write_rare_report(out)
    return summary


def _normal_margin(problem: MarginProblem, z) -> np.ndarray:
    """Failure margins of standard-normal points z (n, D) (a task of `run_rare_event`)."""
    return problem.margin(to_unit(z))


def _estimate(c: RareEventConfig, session, echo) -> dict:
    """Every controller's estimate with ``session``'s batches (`run_rare_event`); the summary,
    with the `Estimate` objects under "estimates"."""
    summary: dict = {"estimator": c.estimator, "controllers": {}, "estimates": {}}
    if session.record["kind"] != "local":
        summary["executor"] = session.record
    for k, (name, controller) in enumerate(c.controllers.items()):
        t0 = time.perf_counter()
        problem = _problem(c, controller)
        rng = np.random.default_rng([c.seed, k])
        dim = problem.dimension

        margin = functools.partial(_normal_margin, problem)

        def g(z, margin=margin):
            # each batch of c.batch samples one task of the session (so the estimators get
            # batch=None): the batches of a one-process run, computed side by side
            return map_batches(session, margin, z, c.batch)

        adapt = adapted_variates(c.distribution)
        mean = None
        design = None
        if c.estimator in ("is", "ce") and c.search_budget:
            mean, history = design_point(problem, adapt, iterations=c.search_budget)
            design = {"iterations": history}
        before = problem.simulations + problem.gradient_simulations
        if c.estimator == "crude":
            est = crude(g, dim, c.n_cases, rng, batch=None)
        elif c.estimator == "ce-mixture":
            est = cross_entropy_mixture(
                g,
                dim,
                c.n_per_stage,
                c.n_cases,
                rng,
                rho=c.rho,
                max_stages=c.max_stages,
                candidates=~fixed_variates(c.distribution),
                max_selected=c.max_selected,
                components=c.components,
                alpha=c.alpha,
                batch=None,
            )
            names = problem.names
            for stage in est.stages:
                stage["selected_names"] = [names[j] for j in stage["selected"]]
        elif c.estimator == "subset":
            est = subset_simulation(
                g,
                dim,
                c.n_per_stage,
                rng,
                p0=c.p0,
                max_levels=c.max_stages,
                batch=None,
                echo=echo,
            )
        elif c.estimator == "is":
            est = importance_sampling(
                g, np.zeros(dim) if mean is None else mean, c.n_cases, rng, batch=None
            )
        else:
            est = cross_entropy(
                g,
                dim,
                c.n_per_stage,
                c.n_cases,
                rng,
                rho=c.rho,
                max_stages=c.max_stages,
                mean=mean,
                adapt_scale=c.adapt_scale,
                batch=None,
                adapt=adapt,
            )
        entry = est.to_dict()
        entry["design_point"] = design
        entry["search_simulations"] = before
        entry["total_simulations"] = before + est.simulations
        entry["seconds"] = time.perf_counter() - t0
        summary["controllers"][name] = entry
        if echo is not None:
            lo, hi = est.ci95
            echo(
                f"{name}: P(failure) = {est.probability:.3e} (cv {est.cv:.3f}, 95 % "
                f"[{lo:.3e}, {hi:.3e}]), {entry['total_simulations']} simulations "
                f"({entry['seconds']:.1f} s)"
            )
        summary["estimates"][name] = est
    return summary


def adapted_variates(distribution: Distribution) -> np.ndarray:
    """The variates whose importance-sampling proposal is fitted: every one but the
    turbulence phases (3 x n_frequencies of them, each changing little alone) and the fixed
    ones."""
    groups = np.array(variate_groups(distribution))
    return (groups != "turbulence_phase") & ~fixed_variates(distribution)


def _json(x):
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, Estimate):
        return x.to_dict()
    raise TypeError(type(x).__name__)


def _save(fig, path: Path) -> None:
    import io

    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    atomic_write_bytes(buf.getvalue(), path)


def write_rare_report(out) -> None:
    """Write ``rare_report.md`` in ``out`` from the rare-failure files found there."""
    from ..montecarlo import rare_sections

    atomic_write_text(
        "\n".join(["# Rare failures", "", *rare_sections(out)]) + "\n", Path(out) / "rare_report.md"
    )
