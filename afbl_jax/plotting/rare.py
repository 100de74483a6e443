"""Figures of the rare-failure studies: worst-case search progress, worst-case trajectories and
ranked sensitivities; pyplot is imported on first use."""

from __future__ import annotations

import numpy as np


def figure_search(histories: dict):
    """Best exact failure margin [-] against simulations used, per (controller, method) run;
    ``histories``: label -> list of (simulations, best margin); runs whose label ends in
    "seed N" share the colour and legend entry of their label's other words."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.6), layout="constrained")
    colours: dict[str, str] = {}
    for label, hist in histories.items():
        group = label.rsplit(" seed ", 1)[0]
        first = group not in colours
        colours.setdefault(group, f"C{len(colours)}")
        if len(hist):
            h = np.asarray(hist, dtype=float)
            ax.step(
                h[:, 0],
                h[:, 1],
                where="post",
                color=colours[group],
                alpha=0.8,
                label=group if first else None,
            )
    ax.axhline(0.0, color="k", lw=0.8, ls="--", label="failure (margin > 0)")
    ax.set_xlabel("simulations used [-]")
    ax.set_ylabel("best failure margin [-]")
    ax.legend(fontsize=7)
    ax.set_title("worst-case search: gradient ascent vs CMA-ES")
    return fig


def figure_trajectories(runs: dict):
    """Attitude errors [rad] and altitude error [m] of re-simulated worst cases up to each run's
    end; ``runs``: label -> `afbl_jax.simulate` result."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 3.4), layout="constrained", squeeze=False)
    for label, r in runs.items():
        valid = np.asarray(r.ts) <= float(r.t_final)
        t, e = np.asarray(r.ts)[valid], np.asarray(r.error)[valid]
        axes[0, 0].plot(t, e[:, 0], label=f"{label} e_phi")
        axes[0, 0].plot(t, e[:, 1], ls="--", label=f"{label} e_theta")
        axes[0, 1].plot(t, e[:, 3], label=label)
    axes[0, 0].set_ylabel("attitude error [rad]")
    axes[0, 1].set_ylabel("altitude error [m]")
    for ax in axes[0]:
        ax.set_xlabel("t [s]")
        ax.legend(fontsize=7)
    fig.suptitle("worst cases found, re-simulated (until the run's end)")
    return fig


def figure_sensitivity(rankings: dict, top: int = 12):
    """Ranked bars per panel; ``rankings``: title -> (names, values, label) or (names, values,
    label, half-widths of the values' intervals, drawn as error bars) (largest first; NaN
    values last, without a bar)."""
    import matplotlib.pyplot as plt

    n = max(len(rankings), 1)
    cols = min(n, 3)
    rows = -(-n // cols)
    fig, axes = plt.subplots(
        rows, cols, figsize=(4.6 * cols, 4.2 * rows), layout="constrained", squeeze=False
    )
    for ax in axes.flat[n:]:
        ax.set_visible(False)
    for ax, (title, entry) in zip(axes.flat, rankings.items(), strict=False):
        names, values, label = entry[:3]
        values = np.asarray(values, dtype=float)
        order = np.argsort(-np.nan_to_num(values, nan=-np.inf))[:top]
        err = None if len(entry) < 4 else np.asarray(entry[3], dtype=float)[order]
        ax.barh(np.arange(len(order))[::-1], values[order], xerr=err, capsize=2)
        ax.set_yticks(np.arange(len(order))[::-1], [str(names[i]) for i in order], fontsize=7)
        ax.set_xlabel(label)
        ax.set_title(title, fontsize=9)
    return fig
