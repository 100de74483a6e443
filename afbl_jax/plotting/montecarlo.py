"""Figures of a Monte-Carlo study (ISE vs payload, payload x gust heatmaps, ECDFs, worst cases),
from the results columns alone; pyplot is imported on first use.

Axes without anything to show (a controller without a successful run) say so in words instead
of showing empty dummy axes; the figures use matplotlib's constrained layout, so titles and
labels do not overlap.
"""

from __future__ import annotations

import numpy as np

ISE_METRICS = ("ise_attitude", "ise_altitude")
ISE_LABELS = {
    "ise_attitude": "ISE attitude [rad$^2$ s]",
    "ise_altitude": "ISE altitude [m$^2$ s]",
}
"""Axis labels (with units) of the ISE metrics."""
NO_OK_RUNS = "no successful runs"


def controller_names(cols: dict) -> list[str]:
    """Controllers of a results table, in first-appearance order."""
    names: list[str] = []
    for c in cols["controller"]:
        if c not in names:
            names.append(str(c))
    return names


def _binned(x, y, edges):
    med, p10, p90, centres = [], [], [], []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        m = (x >= lo) & (x <= hi)
        if np.sum(m) >= 3:
            med.append(np.median(y[m]))
            p10.append(np.percentile(y[m], 10))
            p90.append(np.percentile(y[m], 90))
            centres.append(0.5 * (lo + hi))
    return np.array(centres), np.array(med), np.array(p10), np.array(p90)


def _log_scale_if_positive(ax, axis: str, values) -> None:
    """Log scale when some plotted value is > 0 (tiny runs may have no bin or no ok run)."""
    if np.any(np.asarray(values) > 0):
        (ax.set_yscale if axis == "y" else ax.set_xscale)("log")


def _say_empty(ax, text: str = NO_OK_RUNS) -> None:
    """Write ``text`` across an axes that has nothing to show (no dummy ticks)."""
    ax.text(0.5, 0.5, text, transform=ax.transAxes, ha="center", va="center", color="0.3")
    ax.set_xticks([])
    ax.set_yticks([])


def _edges(x, n_bins: int) -> np.ndarray:
    """Bin edges over the values (numpy's: a constant sample gets a unit-wide range around it)."""
    return np.histogram_bin_edges(np.asarray(x, dtype=float), bins=n_bins)


def figure_ise_vs_payload(cols):
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), layout="constrained")
    p = cols["payload_fraction"]
    edges = _edges(p, 10)
    for ax, metric in zip(axes, ISE_METRICS, strict=True):
        plotted = [np.zeros(0)]
        for name in controller_names(cols):
            m = (cols["controller"] == name) & (cols["status"] == "ok")
            if not np.any(m):
                ax.plot([], [], label=f"{name}: {NO_OK_RUNS}")
                continue
            c, med, lo, hi = _binned(p[m], cols[metric][m], edges)
            (line,) = ax.plot(c, med, marker="o", label=f"{name} median")
            ax.fill_between(c, lo, hi, color=line.get_color(), alpha=0.2, label=f"{name} P10-P90")
            plotted.append(lo)
        if not np.any(cols["status"] == "ok"):
            _say_empty(ax)
            continue
        ax.set_xlabel("payload fraction p [-]")
        ax.set_ylabel(ISE_LABELS[metric])
        _log_scale_if_positive(ax, "y", np.concatenate(plotted))
        ax.legend(fontsize=7)
    fig.suptitle("ISE vs payload fraction (ok runs; binned median, P10-P90 band)")
    return fig


def figure_heatmaps(cols, n_bins: int = 6):
    """Per controller: failure probability of the flyable cases (top) and median ISE attitude
    of the ok runs (bottom) over payload x gust-speed bins. White cells hold no flyable case
    (top), or no ok run (bottom); the figure title says so."""
    import matplotlib.pyplot as plt

    names = controller_names(cols)
    fig, axes = plt.subplots(
        2, len(names), figsize=(4.5 * len(names) + 1, 7.4), squeeze=False, layout="constrained"
    )
    p, g = cols["payload_fraction"], cols["gust_speed"]
    pe, ge = _edges(p, n_bins), _edges(g, n_bins)
    for j, name in enumerate(names):
        m = cols["controller"] == name
        fail = np.full((n_bins, n_bins), np.nan)
        med = np.full((n_bins, n_bins), np.nan)
        ip = np.clip(np.digitize(p[m], pe) - 1, 0, n_bins - 1)
        ig = np.clip(np.digitize(g[m], ge) - 1, 0, n_bins - 1)
        st, ise = cols["status"][m], cols["ise_attitude"][m]
        for a in range(n_bins):
            for b in range(n_bins):
                sel = (ip == a) & (ig == b) & (st != "outside_envelope")
                if np.any(sel):
                    fail[b, a] = np.mean(np.isin(st[sel], ("diverged", "solver_failed")))
                    okv = ise[sel & (st == "ok")]
                    med[b, a] = np.median(okv) if len(okv) else np.nan
        for i, (data, title, unit) in enumerate(
            (
                (fail, "P(failure | flyable)", "failure probability [-]"),
                (med, "median ISE attitude (ok runs)", "median " + ISE_LABELS["ise_attitude"]),
            )
        ):
            ax = axes[i, j]
            ax.set_title(f"{name}: {title}", fontsize=9)
            if np.all(np.isnan(data)):
                _say_empty(ax)
                continue
            limits = {"vmin": 0.0, "vmax": 1.0} if i == 0 else {}
            im = ax.imshow(
                data,
                origin="lower",
                aspect="auto",
                extent=(pe[0], pe[-1], ge[0], ge[-1]),
                cmap="viridis",
                **limits,
            )
            fig.colorbar(im, ax=ax, label=unit)
            ax.set_xlabel("payload fraction p [-]")
            ax.set_ylabel("gust speed [m/s]")
    fig.suptitle(
        "payload x gust speed; white cells: no flyable case in the bin (top), no successful "
        "run in the bin (bottom)",
        fontsize=10,
    )
    return fig


def figure_ecdf(cols):
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), layout="constrained")
    for ax, metric in zip(axes, ISE_METRICS, strict=True):
        plotted = [np.zeros(0)]
        for name in controller_names(cols):
            m = (cols["controller"] == name) & (cols["status"] == "ok")
            if not np.any(m):
                ax.plot([], [], label=f"{name}: {NO_OK_RUNS}")
                continue
            x = np.sort(cols[metric][m])
            n_all = int(np.sum(cols["controller"] == name))
            ax.step(x, np.arange(1, len(x) + 1) / n_all, where="post", label=name)
            plotted.append(x)
        if not np.any(cols["status"] == "ok"):
            _say_empty(ax)
            continue
        _log_scale_if_positive(ax, "x", np.concatenate(plotted))
        ax.set_xlabel(ISE_LABELS[metric])
        ax.legend()
    axes[0].set_ylabel("fraction of all cases [-]")
    fig.suptitle("ECDF of ISE over all cases (failed runs count as never reaching the level)")
    return fig


def figure_worst(replays: dict):
    import matplotlib.pyplot as plt

    n = max(len(replays), 1)
    fig, axes = plt.subplots(n, 2, figsize=(11, 2.4 * n), squeeze=False, layout="constrained")
    for i, (case, runs) in enumerate(replays.items()):
        for name, r in runs.items():
            valid = np.asarray(r.ts) <= float(r.t_final)
            t = np.asarray(r.ts)[valid]
            e = np.asarray(r.error)[valid]
            axes[i, 0].plot(t, np.max(np.abs(e[:, :3]), axis=1), label=name)
            axes[i, 1].plot(t, np.asarray(r.plant)[valid, 2], label=f"{name} z")
        ref = next(iter(runs.values()))
        axes[i, 1].plot(
            np.asarray(ref.ts), np.asarray(ref.reference)[:, 3], "k--", lw=0.8, label="z ref"
        )
        axes[i, 0].set_ylabel(f"case {case}\nmax |e_att| [rad]", fontsize=8)
        axes[i, 1].set_ylabel("z [m]")
        axes[i, 0].legend(fontsize=7)
        axes[i, 1].legend(fontsize=7)
    axes[-1, 0].set_xlabel("t [s]")
    axes[-1, 1].set_xlabel("t [s]")
    fig.suptitle("five worst cases, re-simulated")
    return fig


FAILURE_MARKERS = {"attitude": "o", "altitude": "s", "non_finite": "X", "solver": "D"}


def figure_failure_anatomy(cols):
    """Failure time by cause: one row per controller, each failed flyable run at its failure
    time [s] on the line of its cause (attitude or altitude limit, non-finite state, solver),
    filled where its rotors were commanded past their limit as it ended (final saturation
    >= 1), hollow otherwise."""
    import matplotlib.pyplot as plt

    names = controller_names(cols)
    causes = list(FAILURE_MARKERS)
    fig, axes = plt.subplots(
        len(names), 1, figsize=(8, 1.2 + 1.1 * len(names)), squeeze=False, layout="constrained"
    )
    failed = np.isin(cols["status"], ("diverged", "solver_failed"))
    for ax, name in zip(axes[:, 0], names, strict=True):
        m = failed & (cols["controller"] == name)
        ax.set_title(f"{name}: {int(np.sum(m))} failed flyable runs", fontsize=9)
        if not np.any(m):
            _say_empty(ax, "no failed run")
            continue
        t = np.asarray(cols["t_final"], dtype=float)[m]
        cause = np.asarray(cols["failure_cause"])[m]
        sat = np.asarray(cols["final_saturation"], dtype=float)[m] >= 1.0
        for i, c in enumerate(causes):
            for filled in (True, False):
                sel = (cause == c) & (sat == filled)
                if not np.any(sel):
                    continue
                ax.scatter(
                    t[sel],
                    np.full(int(np.sum(sel)), i),
                    marker=FAILURE_MARKERS[c],
                    facecolors=f"C{i}" if filled else "none",
                    edgecolors=f"C{i}",
                    label=f"{c}, {'saturated' if filled else 'not saturated'}",
                )
        ax.set_yticks(range(len(causes)), causes, fontsize=8)
        ax.set_ylim(-0.5, len(causes) - 0.5)
        ax.set_xlabel("failure time [s]")
        ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))
    fig.suptitle("failure time by cause (filled: rotors commanded past their limit as it ended)")
    return fig
