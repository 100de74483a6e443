"""Figures of a tuning run: convergence and before/after on the canonical scenarios."""

from __future__ import annotations

from pathlib import Path

import numpy as np

CHANNELS = ("phi", "theta", "psi", "z")
_ERR_LABELS = (r"$e_\phi$ [rad]", r"$e_\theta$ [rad]", r"$e_\psi$ [rad]", r"$e_z$ [m]")


def plot_convergence(history: list[dict], config, path: str | Path) -> Path:
    """Loss, gradient norm and gains / paper gains against the optimiser step."""
    import matplotlib.pyplot as plt

    steps = np.array([h["step"] for h in history])
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    axes[0].plot(steps, [h["loss"] for h in history], color="k")
    axes[0].set_yscale("log")
    axes[0].set_title(
        f"{config.objective.objective} objective ({config.controller}, {config.method})"
    )
    axes[0].set_ylabel("objective [-]")
    axes[0].set_xlabel("iteration")
    axes[1].plot(steps, [h["grad_norm"] for h in history], color="tab:purple")
    axes[1].set_yscale("log")
    axes[1].set_title("gradient norm (z)")
    axes[1].set_xlabel("step")
    space = config.space()
    for name in space.names:
        for j, ch in enumerate(CHANNELS):
            ratio = np.array([h[f"{name}_{ch}"] for h in history]) / space.base[name][j]
            axes[2].plot(steps, ratio, label=f"{name} {ch}")
    axes[2].set_yscale("log")
    axes[2].axhline(config.lower, color="grey", ls=":")
    axes[2].axhline(config.upper, color="grey", ls=":")
    axes[2].set_title("gain / paper gain")
    axes[2].set_xlabel("step")
    axes[2].legend(fontsize=6, ncol=3)
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_before_after(runs: dict, omega_max: float, path: str | Path) -> Path:
    """Errors and peak rotor speed of paper vs tuned gains on the four canonical scenarios."""
    import matplotlib.pyplot as plt

    keys = list(runs)
    fig, axes = plt.subplots(
        5, len(keys), figsize=(3.6 * len(keys), 10), sharex=True, squeeze=False
    )
    style = {"paper": dict(color="tab:red", ls="--"), "tuned": dict(color="tab:blue")}
    for col, key in enumerate(keys):
        for name, r in runs[key].items():
            for row in range(4):
                axes[row, col].plot(r.ts, r.error[:, row], label=name, **style.get(name, {}))
            axes[4, col].plot(
                r.ts, np.max(r.rotor_speeds, axis=1), label=name, **style.get(name, {})
            )
        if np.isfinite(omega_max):
            axes[4, col].axhline(omega_max, color="k", lw=0.8, ls=":", label="limit")
        axes[0, col].set_title(key)
        axes[4, col].set_xlabel("time [s]")
    for row in range(4):
        axes[row, 0].set_ylabel(_ERR_LABELS[row])
    axes[4, 0].set_ylabel("max rotor speed [rad/s]")
    axes[0, 0].legend(fontsize=8)
    axes[4, 0].legend(fontsize=8)
    for ax in axes.ravel():
        ax.grid(alpha=0.3)
    fig.suptitle("Paper gains vs tuned gains (canonical scenarios, rotor limit on)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path)


def plot_loss_vs_time(runs: dict, path: str | Path, title: str = "tuning") -> Path:
    """Objective (normalised: 1 per term at the paper's gains) against wall time [s] for each
    method (colour) and seed (line style); ``runs``: {method: {seed: history rows}}."""
    import matplotlib.pyplot as plt

    colours = {"lbfgs": "tab:blue", "adam": "tab:orange", "cmaes": "tab:green", "hybrid": "tab:red"}
    styles = ("-", "--", ":", "-.")
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for method, per_seed in runs.items():
        for i, (seed, hist) in enumerate(sorted(per_seed.items())):
            t = [h["time_s"] for h in hist]
            best = np.minimum.accumulate([h["loss"] for h in hist])
            ax.plot(
                t,
                best,
                color=colours.get(method),
                ls=styles[i % len(styles)],
                drawstyle="steps-post",
                label=f"{method} seed {seed}",
            )
    ax.set_xlabel("wall time after compilation [s]")
    ax.set_ylabel("training objective, best so far [-]")
    ax.set_yscale("log")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)
