"""Monte-Carlo statistics, terminal summary, figures and report.md / report.html.

Definitions (all computed from the results table alone, so they can be recomputed from the
file):

- flyable = the case lies inside the vehicle's flight envelope (status not "outside_envelope",
  decided before simulating); the fraction outside is reported with its 95 % Wilson interval
  and such cases are never counted as controller failures;
- failure = a flyable case whose run diverged or failed (status "diverged" or
  "solver_failed"); P(failure | flyable) with a 95 % Wilson score interval;
- ISE percentiles (P50/P90/P99/max) over the controller's ok runs only (position ISE where the
  cases fly with a position loop); the number of excluded runs (failed or outside the
  envelope) is reported beside them;
- paired win rate of a controller over the baseline (fbl when present) for a metric: over the
  flyable cases where at least one of the two is ok, the fraction where the challenger is ok
  and either the baseline failed or the challenger's value is strictly smaller; 95 % Wilson
  interval;
- failure anatomy: per controller and cause (`afbl_jax.metrics.FAILURE_CAUSES`: attitude or
  altitude limit, non-finite state, solver), the failed runs, their median failure time and the
  fraction whose rotors were commanded past their limit as they ended (final saturation >= 1).

A number that is undefined (percentiles of a controller without a successful run, a win rate
over no counted case) is None in the summary, ``null`` in summary.json (strict JSON: never
``NaN``) and written out in words in the tables ("no successful runs").
"""

from __future__ import annotations

import base64
import html
import io
import json
import math
from concurrent.futures import Future
from pathlib import Path

import numpy as np

from ...io import atomic_write_bytes, atomic_write_text
from ...metrics import FAILURE_CAUSES
from ...plotting.montecarlo import (
    controller_names,
    figure_ecdf,
    figure_failure_anatomy,
    figure_heatmaps,
    figure_ise_vs_payload,
    figure_worst,
)
from ...scenario import TURBULENCE_INTENSITIES
from ...sim import STATUS_LABELS
from .._stats import wilson_interval

ISE_METRICS = ("ise_attitude", "ise_altitude")
POSITION_METRIC = "ise_position"
FAILED = ("diverged", "solver_failed")
OUTSIDE = "outside_envelope"
PERCENTILES = (50, 90, 99)


NO_OK_RUNS = "no successful runs"


def _per_case(cols: dict, name: str, key: str) -> np.ndarray:
    """Values of ``key`` for controller ``name`` ordered by case index."""
    m = cols["controller"] == name
    order = np.argsort(cols["case"][m], kind="stable")
    return np.asarray(cols[key][m])[order]


def _ise_metrics(cols: dict) -> tuple[str, ...]:
    """The ISE columns the report shows: attitude, altitude, and position where any run has
    one (a position loop)."""
    pos = cols.get(POSITION_METRIC)
    has_position = pos is not None and bool(np.any(np.isfinite(np.asarray(pos, dtype=float))))
    return ISE_METRICS + ((POSITION_METRIC,) if has_position else ())


def summarize(cols: dict) -> dict:
    """All report numbers (JSON-serialisable) from the results columns."""
    names = controller_names(cols)
    metrics = _ise_metrics(cols)
    n_cases = int(len(np.unique(cols["case"])))
    out: dict = {"n_cases": n_cases, "controllers": {}, "paired": {}}
    first = _per_case(cols, names[0], "status")
    outside = int(np.sum(first == OUTSIDE))
    out["envelope"] = {
        "outside": outside,
        "flyable": n_cases - outside,
        "outside_fraction": outside / n_cases if n_cases else None,
        "outside_fraction_ci95": list(wilson_interval(outside, n_cases)),
    }
    for name in names:
        status = _per_case(cols, name, "status")
        ok = status == "ok"
        flyable = status != OUTSIDE
        failed = np.isin(status, FAILED)
        n, n_fly, fails = len(status), int(np.sum(flyable)), int(np.sum(failed))
        entry = {
            "n": n,
            "flyable": n_fly,
            "status_counts": {s: int(np.sum(status == s)) for s in STATUS_LABELS},
            "failures": fails,
            "failure_rate": fails / n_fly if n_fly else None,
            "failure_rate_ci95": list(wilson_interval(fails, n_fly)),
            "excluded_from_ise": int(np.sum(~ok)),
            "anatomy": _anatomy(cols, name, failed),
        }
        for metric in metrics:
            x = _per_case(cols, name, metric)[ok]
            stats = {f"p{q}": float(np.percentile(x, q)) if len(x) else None for q in PERCENTILES}
            stats["max"] = float(np.max(x)) if len(x) else None
            entry[metric] = stats
        out["controllers"][name] = entry
    baseline = "fbl" if "fbl" in names else names[0]
    for name in names:
        if name == baseline:
            continue
        pair = {}
        ok_b = _per_case(cols, baseline, "status") == "ok"
        ok_c = _per_case(cols, name, "status") == "ok"
        for metric in metrics:
            xb, xc = _per_case(cols, baseline, metric), _per_case(cols, name, metric)
            counted = ok_b | ok_c
            win = ok_c & (~ok_b | (xc < xb))
            k, n = int(np.sum(win & counted)), int(np.sum(counted))
            pair[metric] = {
                "wins": k,
                "n": n,
                "win_rate": k / n if n else None,
                "ci95": list(wilson_interval(k, n)) if n else None,
            }
        out["paired"][f"{name}_over_{baseline}"] = pair
    return out


def _anatomy(cols: dict, name: str, failed: np.ndarray) -> dict:
    """Per failure cause of ``name``'s failed runs: count, median failure time [s] and the
    fraction saturated as they ended (final saturation >= 1)."""
    if "failure_cause" not in cols:
        return {}
    cause = _per_case(cols, name, "failure_cause")
    t_final = np.asarray(_per_case(cols, name, "t_final"), dtype=float)
    sat = np.asarray(_per_case(cols, name, "final_saturation"), dtype=float)
    out = {}
    for c in FAILURE_CAUSES[1:]:
        m = failed & (cause == c)
        k = int(np.sum(m))
        out[c] = {
            "failures": k,
            "median_time": float(np.median(t_final[m])) if k else None,
            "saturated_fraction": float(np.mean(sat[m] >= 1.0)) if k else None,
        }
    return out


def _strict(x):
    """``x`` with every non-finite float replaced by None (JSON ``null``)."""
    if isinstance(x, dict):
        return {k: _strict(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_strict(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def summary_json(summary: dict) -> str:
    """summary.json text: strict JSON (undefined numbers are ``null``, never ``NaN``)."""
    return json.dumps(_strict(summary), indent=2, allow_nan=False) + "\n"


def _fmt(x: float | None) -> str:
    return "-" if x is None or not math.isfinite(x) else f"{x:.4g}"


def summary_tables(summary: dict) -> list[tuple[str, list[str], list[list[str]]]]:
    """(title, header, rows) tables shared by the terminal, markdown and HTML outputs."""
    tables = []
    units = {"ise_attitude": "rad^2 s", "ise_altitude": "m^2 s", "ise_position": "m^2 s"}
    first = next(iter(summary["controllers"].values()), {})
    for metric, unit in units.items():
        if metric not in first:
            continue
        rows = []
        for name, e in summary["controllers"].items():
            s = e[metric]
            if s["max"] is None:
                stats = [NO_OK_RUNS] + ["-"] * len(PERCENTILES)
            else:
                stats = [*(_fmt(s[f"p{q}"]) for q in PERCENTILES), _fmt(s["max"])]
            rows.append([name, *stats, str(e["excluded_from_ise"])])
        tables.append(
            (
                f"{metric} [{unit}] over ok runs",
                ["controller", "P50", "P90", "P99", "max", "excluded (failed or not flyable)"],
                rows,
            )
        )
    env = summary.get("envelope")
    if env is not None:
        lo, hi = env["outside_fraction_ci95"]
        frac = env["outside_fraction"]
        tables.append(
            (
                "flight envelope (decided before simulating)",
                ["cases", "flyable", "outside the envelope", "fraction outside", "95 % Wilson"],
                [
                    [
                        str(summary["n_cases"]),
                        str(env["flyable"]),
                        str(env["outside"]),
                        "-" if frac is None else f"{100 * frac:.2f} %",
                        f"[{100 * lo:.2f}, {100 * hi:.2f}] %",
                    ]
                ],
            )
        )
    rows = []
    for name, e in summary["controllers"].items():
        lo, hi = e["failure_rate_ci95"]
        c = e["status_counts"]
        rate = e["failure_rate"]
        rows.append(
            [
                name,
                str(e.get("flyable", e["n"])),
                str(c["ok"]),
                str(c["diverged"]),
                str(c["solver_failed"]),
                "-" if rate is None else f"{100 * rate:.2f} %",
                f"[{100 * lo:.2f}, {100 * hi:.2f}] %",
            ]
        )
    tables.append(
        (
            "failures of flyable cases",
            [
                "controller",
                "flyable runs",
                "ok",
                "diverged",
                "solver_failed",
                "P(failure | flyable)",
                "95 % Wilson",
            ],
            rows,
        )
    )
    rows = []
    for name, e in summary["controllers"].items():
        for cause, a in e.get("anatomy", {}).items():
            if not a["failures"]:
                continue
            rows.append(
                [
                    name,
                    cause,
                    str(a["failures"]),
                    f"{a['median_time']:.2f}",
                    f"{100 * a['saturated_fraction']:.0f} %",
                ]
            )
    if rows:
        tables.append(
            (
                "failure anatomy",
                ["controller", "cause", "failures", "median time [s]", "saturated as it ended"],
                rows,
            )
        )
    rows = []
    for pair, per in summary["paired"].items():
        for metric, w in per.items():
            if not w["n"]:
                rows.append([pair, metric, "0/0", "no case with a successful run", "-"])
                continue
            lo, hi = w["ci95"]
            rows.append(
                [
                    pair,
                    metric,
                    f"{w['wins']}/{w['n']}",
                    f"{100 * w['win_rate']:.1f} %",
                    f"[{100 * lo:.1f}, {100 * hi:.1f}] %",
                ]
            )
    if rows:
        tables.append(
            (
                "paired win rate (same cases)",
                ["pair", "metric", "wins/cases", "win rate", "95 % Wilson"],
                rows,
            )
        )
    return tables


def _no_ok_runs(summary: dict) -> list[str]:
    return [n for n, e in summary["controllers"].items() if e["status_counts"]["ok"] == 0]


def format_summary(summary: dict) -> str:
    """Plain-text summary for the terminal."""
    lines = [
        f"Monte-Carlo summary: {summary['n_cases']} cases x "
        f"{len(summary['controllers'])} controllers"
    ]
    failed = _no_ok_runs(summary)
    if failed:
        lines.append(f"{', '.join(failed)}: {NO_OK_RUNS} (every run diverged or failed)")
    for title, header, rows in summary_tables(summary):
        widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
        lines += ["", title]
        lines.append("  ".join(h.ljust(w) for h, w in zip(header, widths, strict=True)))
        lines += ["  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)) for r in rows]
    return "\n".join(lines)


def worst_cases(cols, k: int = 5) -> list[int]:
    """Case indices of the k worst flyable cases: failed runs first, then by the largest ISE
    attitude relative to the controller's median (max over controllers)."""
    names = controller_names(cols)
    cases = np.sort(np.unique(cols["case"]))
    score = np.zeros(len(cases))
    for name in names:
        ise = _per_case(cols, name, "ise_attitude")
        status = _per_case(cols, name, "status")
        ok = status == "ok"
        med = np.median(ise[ok]) if np.any(ok) else 1.0
        part = np.where(ok, ise / med, np.inf)
        score = np.maximum(score, np.where(status == OUTSIDE, -np.inf, part))
    order = np.argsort(-score, kind="stable")
    return [int(c) for c in cases[order[:k]]]


def replay_worst(
    cols,
    controllers: dict,
    distribution,
    seed: int,
    k: int = 5,
    settings=None,
    *,
    chunk_size: int | None = None,
) -> dict[int, dict]:
    """Re-simulate the k worst cases with every controller (trajectories kept).

    ``chunk_size``: the run's chunk size; the cases are drawn in a batch of that size
    (`sample_cases_at`), with the sampler the run compiled and bitwise the inputs the run
    simulated. The replays run on the CPU whatever the default device (a handful of
    sequential float64 solves, each a chain of small steps, run faster there than on an
    accelerator); the cases are drawn on the default device, as the run drew them."""
    import jax

    from ...sim import simulate
    from ._runner import SolverSettings
    from ._sampler import sample_cases_at

    settings = (settings or SolverSettings()).with_tolerances_for("vmap")
    cases = worst_cases(cols, k)
    if not cases:
        return {}
    size = chunk_size if chunk_size is not None and chunk_size >= len(cases) else None
    # one transfer to the host; the rows are then numpy slices, not small device programs
    batch = jax.device_get(sample_cases_at(distribution, cases, seed, size=size))
    cpu = jax.devices("cpu")[0]
    arrays = jax.Array | np.ndarray | np.generic
    out = {}
    for i, case in enumerate(cases):
        scenario, vehicle, model, unmodeled, aerodynamics, position_loop, ctrls = jax.tree.map(
            lambda x: jax.device_put(x, cpu) if isinstance(x, arrays) else x,
            (
                *batch.case(i),
                batch.unmodeled_case(i),
                batch.aerodynamics,
                batch.position_loop,
                controllers,
            ),
        )
        with jax.default_device(cpu):
            out[case] = {
                name: simulate(
                    ctrl,
                    scenario,
                    vehicle,
                    model,
                    solver=settings.solver,
                    rtol=settings.rtol,
                    atol=settings.atol,
                    n_save=801,
                    max_steps=settings.max_steps,
                    unmodeled=unmodeled,
                    aerodynamics=aerodynamics,
                    position_loop=position_loop,
                    saving="dense",  # no host callback: the compiled replay is cached
                )
                for name, ctrl in ctrls.items()
            }
    return out


# ---------------------------------------------------------------- documents
def _png(fig) -> bytes:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    return buf.getvalue()


def _md_table(header, rows) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def _html_table(header, rows) -> str:
    h = "".join(f"<th>{html.escape(c)}</th>" for c in header)
    body = "".join(
        "<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in r) + "</tr>" for r in rows
    )
    return f"<table><tr>{h}</tr>{body}</table>"


def rare_sections(out: str | Path) -> list[str]:
    """Markdown sections for the rare-failure results found in ``out`` (``falsify.json``,
    ``rare_event.json``; sensitivities inside falsify.json), with their figures; empty when
    none were computed there."""
    out = Path(out)
    md: list[str] = []
    f = out / "falsify.json"
    if f.exists():
        data = json.loads(f.read_text())["falsify"]
        md += ["## Worst cases (falsification)", ""]
        rows = []
        for name, e in data["controllers"].items():
            for method, label in (("gradient", "gradient ascent"), ("cmaes", "CMA-ES")):
                m = e[method]
                rows.append(
                    [
                        name,
                        label,
                        f"{m['found']}/{m['searches']}",
                        f"{m['median_first_failure']:g}",
                        f"{m['best_margin']:+.4f}",
                    ]
                )
        md += [
            _md_table(
                [
                    "controller",
                    "method",
                    "searches finding a failure",
                    "median simulations to first failure",
                    "best margin",
                ],
                rows,
            ),
            "",
        ]
        for name, e in data["controllers"].items():
            ml = e.get("most_likely_failure")
            if ml:
                md.append(
                    f"{name}: most likely failure along the ray to the worst case at "
                    f"standard-normal distance {ml['normal_distance']:.2f} "
                    f"({ml['simulations']} simulations)."
                )
            dp = e.get("design_point")
            if dp:
                top = ", ".join(f"{v['name']} {v['z']:+.2f}" for v in dp["top_variates"][:6])
                md += [
                    "",
                    f"{name}: design point (SLSQP on |z|^2 subject to failing) at "
                    f"standard-normal distance {dp['distance']:.2f} (ray: "
                    f"{dp['ray_distance']:.2f}), exact margin there {dp['margin']:+.3e} "
                    f"(forward re-solve), {dp['gradient_simulations']} gradient + "
                    f"{dp['simulations']} forward simulations ({dp['message']}); largest |z|: "
                    f"{top}.",
                ]
        md += ["", "![search](figures/falsify_search.png)", ""]
        md += ["![worst cases](figures/falsify_worst_cases.png)", ""]
        if any(e.get("sensitivity") for e in data["controllers"].values()):
            md += ["## Sensitivities", "", "![sensitivities](figures/sensitivity.png)", ""]
            for name, e in data["controllers"].items():
                sens = e.get("sensitivity")
                if not sens:
                    continue
                for key, sd in sens.items():
                    st = np.asarray(sd["sobol"]["ST"], dtype=float)
                    conf = np.asarray(sd["sobol"]["ST_conf"], dtype=float)
                    order = np.argsort(-np.nan_to_num(st, nan=-np.inf))[:5]
                    top = ", ".join(
                        f"{sd['sobol']['names'][i]} {st[i]:.2f} +- {conf[i]:.2f}" for i in order
                    )
                    line = (
                        f"- {name}, {key}: largest total Sobol indices (+- 95 % bootstrap "
                        f"half-width): {top}"
                    )
                    if sd.get("dgsm"):
                        nu = np.asarray(sd["dgsm"]["bound"], dtype=float)
                        order = np.argsort(-np.nan_to_num(nu, nan=-np.inf))[:5]
                        line += "; largest DGSM bounds nu / (pi^2 V): " + ", ".join(
                            f"{sd['dgsm']['names'][i]} {nu[i]:.2g}" for i in order
                        )
                    if "failures" in sd:
                        line += f" ({sd['failures']} failures among the Sobol samples)"
                    md.append(line)
            md.append("")
    f = out / "rare_event.json"
    if f.exists():
        data = json.loads(f.read_text())["rare_event"]
        md += [f"## Rare-event estimate ({data['estimator']})", ""]
        rows = [
            [
                name,
                f"{e['probability']:.3e}",
                f"{e['cv']:.3f}",
                f"[{e['ci95'][0]:.3e}, {e['ci95'][1]:.3e}]",
                str(e["total_simulations"]),
                f"{e['seconds']:.1f}",
            ]
            for name, e in data["controllers"].items()
        ]
        md += [
            _md_table(
                ["controller", "P(failure)", "cv", "95 % interval", "simulations", "time [s]"],
                rows,
            ),
            "",
        ]
        for name, e in data["controllers"].items():
            if e.get("method") != "subset":
                continue
            md += [
                f"{name}: subset simulation levels (threshold: the failure-margin level the "
                "next level is conditioned on, 0 at the last; gamma: the chains' correlation "
                "factor; cv of the estimate assuming uncorrelated levels, "
                f"{e['cv']:.3f}; fully correlated, {e.get('cv_correlated', float('nan')):.3f}).",
                "",
                _md_table(
                    [
                        "level",
                        "threshold",
                        "samples",
                        "failures",
                        "acceptance rate",
                        "gamma",
                        "conditional probability",
                    ],
                    [
                        [
                            str(s["level"]),
                            f"{s['threshold']:+.4f}",
                            str(s["samples"]),
                            str(s["failures"]),
                            "-" if s["acceptance_rate"] is None else f"{s['acceptance_rate']:.3f}",
                            f"{s['gamma']:.2f}",
                            f"{s['conditional_probability']:.4g}",
                        ]
                        for s in e["stages"]
                    ],
                ),
                "",
            ]
            last = e["stages"][-1]
            if "p_above_threshold" in last:
                md += [
                    f"The levels did not reach the failure margin 0: P(margin > "
                    f"{last['threshold']:+.4f}) = {last['p_above_threshold']:.3e} (95 % upper "
                    f"end {last['p_above_threshold_high']:.3e}) bounds P(failure) from above.",
                    "",
                ]
    return md


def write_report(
    out: str | Path,
    cols: dict,
    summary: dict,
    distribution,
    meta: dict,
    replays: dict | Future | None = None,
    figures: bool = True,
) -> dict[str, Path]:
    """Write summary.json, report.md (+ figures/*.png) and a self-contained report.html.

    ``replays``: `replay_worst`'s result, or a `concurrent.futures.Future` of it (the other
    figures are drawn while it computes; its result is awaited for the worst-case figure)."""
    out = Path(out)
    atomic_write_text(summary_json(summary), out / "summary.json")
    figs: list[tuple[str, str, bytes]] = []
    any_ok = bool(np.any(np.asarray(cols["status"]) == "ok"))
    if figures:
        fig_dir = out / "figures"
        fig_dir.mkdir(exist_ok=True)
        makers = [
            ("heatmap_payload_gust", "payload x gust amplitude", lambda: figure_heatmaps(cols)),
        ]
        if any_ok:  # the ISE figures show ok runs only
            makers[:0] = [
                ("ise_vs_payload", "ISE vs payload fraction", lambda: figure_ise_vs_payload(cols))
            ]
            makers.append(("ecdf_ise", "ECDF of ISE", lambda: figure_ecdf(cols)))
        if np.any(np.isin(np.asarray(cols["status"]), FAILED)) and "failure_cause" in cols:
            makers.append(
                ("failure_anatomy", "failure time by cause", lambda: figure_failure_anatomy(cols))
            )

        def draw(stem: str, title: str, make) -> None:
            data = _png(make())
            atomic_write_bytes(data, fig_dir / f"{stem}.png")
            figs.append((stem, title, data))

        for maker in makers:
            draw(*maker)
        if isinstance(replays, Future):  # the figures above were drawn while it computed
            replays = replays.result()
        if replays:
            draw("worst_cases", "five worst cases", lambda: figure_worst(replays))
    cfg = meta.get("config", {})
    failed = _no_ok_runs(summary)
    intro = (
        f"{summary['n_cases']} cases, controllers {', '.join(summary['controllers'])}, "
        f"seed {cfg.get('seed')}, git {meta.get('git_revision')}. Turbulence levels: "
        f"{', '.join(f'{i} = {n}' for i, n in enumerate(TURBULENCE_INTENSITIES))}."
        + (
            f" {', '.join(failed)}: {NO_OK_RUNS} (every run diverged or failed)"
            + ("; no ISE figures." if not any_ok else ".")
            if failed
            else ""
        )
    )
    md = ["# Monte-Carlo robustness report", "", intro, ""]
    hp = [
        "<!doctype html><html><head><meta charset='utf-8'><title>Monte-Carlo robustness"
        "</title><style>body{font-family:sans-serif;max-width:1100px;margin:auto}"
        "table{border-collapse:collapse;margin:8px 0}td,th{border:1px solid #bbb;"
        "padding:2px 6px;font-size:13px}</style></head><body>",
        "<h1>Monte-Carlo robustness report</h1>",
        f"<p>{html.escape(intro)}</p>",
    ]
    for title, header, rows in summary_tables(summary):
        md += [f"## {title}", "", _md_table(header, rows), ""]
        hp += [f"<h2>{html.escape(title)}</h2>", _html_table(header, rows)]
    for stem, title, data in figs:
        md += [f"## {title}", "", f"![{title}](figures/{stem}.png)", ""]
        b64 = base64.b64encode(data).decode()
        hp += [
            f"<h2>{html.escape(title)}</h2>",
            f"<img alt='{html.escape(title)}' src='data:image/png;base64,{b64}'>",
        ]
    rare = rare_sections(out)
    if rare:
        md += rare
        hp += [f"<pre>{html.escape(chr(10).join(rare))}</pre>"]
    dist_rows = [
        [s, k, json.dumps(v)] for s, body in distribution.spec.items() for k, v in body.items()
    ]
    md += ["## Distribution", "", _md_table(["section", "key", "value"], dist_rows), ""]
    hp += ["<h2>Distribution</h2>", _html_table(["section", "key", "value"], dist_rows)]
    hp += [
        "<h2>Metadata</h2>",
        f"<pre>{html.escape(json.dumps(meta, indent=2))}</pre>",
        "</body></html>",
    ]
    atomic_write_text("\n".join(md), out / "report.md")
    atomic_write_text("\n".join(hp), out / "report.html")
    return {"md": out / "report.md", "html": out / "report.html", "summary": out / "summary.json"}
