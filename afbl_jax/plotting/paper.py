"""Figures of the paper reproduction (one PNG per paper figure, Figs. 8-21; pyplot is imported on
first use, and the backend is left to matplotlib)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..model import CHANNEL_INDEX

_LABELS = {
    0: (r"$\phi$ [rad]", r"$e_\phi$ [rad]"),
    1: (r"$\theta$ [rad]", r"$e_\theta$ [rad]"),
    2: (r"$\psi$ [rad]", r"$e_\psi$ [rad]"),
    3: (r"$z$ [m]", r"$e_z$ [m]"),
}
_STYLE = {
    "fbl": dict(color="tab:red", ls="--", label="FBL + PID"),
    "afbl": dict(color="tab:blue", ls="-", label="AFBL"),
    "afbl_paper": dict(color="tab:green", ls=":", label="AFBL (paper eq. 33)"),
}


def _style(name: str) -> dict:
    return _STYLE.get(name, dict(label=name))


def _channels_figure(runs, controllers, channels, what, title):
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(
        len(channels), 1, figsize=(7.5, 2.3 * len(channels) + 0.6), sharex=True, squeeze=False
    )
    first = next(iter(runs.values()))
    for ax, ch in zip(axes[:, 0], channels, strict=True):
        if what == "value":
            ax.plot(first.ts, first.reference[:, ch], color="k", lw=1.0, label="reference")
        for name in controllers:
            r = runs[name]
            y = r.plant[:, CHANNEL_INDEX[ch]] if what == "value" else r.error[:, ch]
            ax.plot(r.ts, y, **_style(name))
        ax.set_ylabel(_LABELS[ch][0 if what == "value" else 1])
        ax.grid(alpha=0.3)
    axes[0, 0].legend(loc="best", fontsize=8)
    axes[-1, 0].set_xlabel("time [s]")
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def _disturbance_figure(run, which):
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 3.0))
    if which == "torque":
        for i, n in enumerate((r"$\tau_\phi$", r"$\tau_\theta$", r"$\tau_\psi$")):
            ax.plot(run.ts, run.disturbance_torque[:, i], lw=1.5 - 0.4 * i, label=n)
        ax.set_ylabel("disturbance torque [N m]")
        ax.set_title("Pulse disturbance on the attitude (uncertain scenario)")
    else:
        ax.plot(run.ts, run.disturbance_force[:, 2], label=r"$F_z$")
        ax.set_ylabel("disturbance force [N]")
        ax.set_title("Pulse disturbance on the altitude (uncertain scenario)")
    ax.set_xlabel("time [s]")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    return fig


# file name -> (scenario key, channels, "value" | "error" | disturbance, paper figure title)
PAPER_FIGURES: dict[str, tuple[str, tuple[int, ...], str, str]] = {
    "fig08_takeoff_landing_ideal.png": (
        "ideal_step",
        (3,),
        "value",
        "Fig. 8: take-off and landing (ideal)",
    ),
    "fig09_attitude_ideal.png": ("ideal_step", (0, 1, 2), "value", "Fig. 9: attitude (ideal)"),
    "fig10_altitude_error_ideal.png": (
        "ideal_step",
        (3,),
        "error",
        "Fig. 10: altitude error (ideal)",
    ),
    "fig11_attitude_error_ideal.png": (
        "ideal_step",
        (0, 1, 2),
        "error",
        "Fig. 11: attitude errors (ideal)",
    ),
    "fig12_sine_attitude_ideal.png": (
        "ideal_sine",
        (0, 1, 2),
        "value",
        "Fig. 12: smooth attitude tracking (ideal)",
    ),
    "fig13_sine_attitude_error_ideal.png": (
        "ideal_sine",
        (0, 1, 2),
        "error",
        "Fig. 13: attitude errors, smooth tracking (ideal)",
    ),
    "fig14_disturbance_attitude.png": ("uncertain_step", (), "torque", ""),
    "fig15_disturbance_altitude.png": ("uncertain_step", (), "force", ""),
    "fig16_takeoff_landing_uncertain.png": (
        "uncertain_step",
        (3,),
        "value",
        "Fig. 16: take-off and landing (50 % payload + pulses)",
    ),
    "fig17_attitude_uncertain.png": (
        "uncertain_step",
        (0, 1, 2),
        "value",
        "Fig. 17: attitude (50 % payload + pulses)",
    ),
    "fig18_altitude_error_uncertain.png": (
        "uncertain_step",
        (3,),
        "error",
        "Fig. 18: altitude error (50 % payload + pulses)",
    ),
    "fig19_attitude_error_uncertain.png": (
        "uncertain_step",
        (0, 1, 2),
        "error",
        "Fig. 19: attitude errors (50 % payload + pulses)",
    ),
    "fig20_sine_attitude_uncertain.png": (
        "uncertain_sine",
        (0, 1, 2),
        "value",
        "Fig. 20: smooth attitude tracking (50 % payload + pulses)",
    ),
    "fig21_sine_attitude_error_uncertain.png": (
        "uncertain_sine",
        (0, 1, 2),
        "error",
        "Fig. 21: attitude errors, smooth tracking (50 % payload + pulses)",
    ),
}


def plot_paper_figures(
    runs: dict, out_dir: str | Path, controllers: tuple[str, ...] = ("fbl", "afbl")
) -> list[Path]:
    """Write Figs. 8-21 (FBL vs AFBL) and an overview of all controllers; returns the paths.

    ``runs[scenario_key][controller]`` are `SimulationResult`s (NumPy or JAX arrays).
    """
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for fname, (key, channels, what, title) in PAPER_FIGURES.items():
        available = tuple(c for c in controllers if c in runs[key])
        if what in ("torque", "force"):
            fig = _disturbance_figure(next(iter(runs[key].values())), what)
        else:
            fig = _channels_figure(runs[key], available, channels, what, title)
        fig.savefig(out / fname, dpi=110)
        plt.close(fig)
        paths.append(out / fname)
    paths.append(plot_overview(runs, out / "overview_all_controllers.png"))
    return paths


def plot_overview(runs: dict, path: str | Path) -> Path:
    """Grid: rows = scenarios, columns = (z, phi, attitude ISE growth), every controller."""
    import matplotlib.pyplot as plt

    keys = list(runs)
    fig, axes = plt.subplots(len(keys), 3, figsize=(13, 2.6 * len(keys)), squeeze=False)
    for row, key in enumerate(keys):
        first = next(iter(runs[key].values()))
        axes[row, 0].plot(first.ts, first.reference[:, 3], "k", lw=1, label="reference")
        axes[row, 1].plot(first.ts, first.reference[:, 0], "k", lw=1, label="reference")
        for name, r in runs[key].items():
            axes[row, 0].plot(r.ts, r.plant[:, 2], **_style(name))
            axes[row, 1].plot(r.ts, r.plant[:, 3], **_style(name))
            e2 = np.sum(np.asarray(r.error)[:, :3] ** 2, axis=1)
            dt = np.diff(np.asarray(r.ts), prepend=r.ts[0])
            axes[row, 2].semilogy(r.ts, np.maximum(np.cumsum(e2 * dt), 1e-6), **_style(name))
        axes[row, 0].set_ylabel(f"{key}\nz [m]")
        axes[row, 1].set_ylabel(r"$\phi$ [rad]")
        axes[row, 2].set_ylabel("attitude ISE so far (approx.)")
        for ax in axes[row]:
            ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    for ax in axes[-1]:
        ax.set_xlabel("time [s]")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path)
