"""Figures of the unmodeled-dynamics study: failure rate over (f_c, tau_m) per controller."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def plot_stability_boundary(result, out: Path) -> list[Path]:
    """One PNG per controller: failure rate over (f_c, tau_m), one panel per noise level, with
    the 50 % failure contour as the stability boundary and the mean attitude ISE in each cell."""
    import matplotlib.pyplot as plt

    paths = []
    rates, taus = np.array(result.rates), np.array(result.taus)
    for name, fail in result.failure_rate.items():
        n = len(result.noise_levels)
        fig, axes = plt.subplots(1, n, figsize=(5.0 * n, 4.2), squeeze=False)
        for i_n, ax in enumerate(axes[0]):
            im = ax.imshow(
                fail[i_n],
                origin="lower",
                cmap="RdYlGn_r",
                vmin=0.0,
                vmax=1.0,
                aspect="auto",
                extent=(-0.5, len(rates) - 0.5, -0.5, len(taus) - 0.5),
            )
            if len(rates) > 1 and len(taus) > 1 and fail[i_n].min() < 0.5 < fail[i_n].max():
                ax.contour(
                    np.arange(len(rates)),
                    np.arange(len(taus)),
                    fail[i_n],
                    levels=[0.5],
                    colors="k",
                    linewidths=2,
                )
            for i_t in range(len(taus)):
                for i_r in range(len(rates)):
                    a = result.ise_attitude[name][i_n, i_t, i_r]
                    txt = f"{fail[i_n, i_t, i_r]:.0%}\n" + (f"{a:.1e}" if np.isfinite(a) else "-")
                    ax.text(i_r, i_t, txt, ha="center", va="center", fontsize=7)
            ax.set_xticks(range(len(rates)), [f"{r:g}" for r in rates])
            ax.set_yticks(range(len(taus)), [f"{t * 1e3:g}" for t in taus])
            ax.set_xlabel("control rate f_c [Hz]")
            ax.set_ylabel("motor time constant tau_m [ms]")
            ax.set_title(f"{name}: noise level {result.noise_levels[i_n]:g}")
        fig.colorbar(im, ax=axes[0].tolist(), label="failure rate (cell text: rate, mean ISE att)")
        fig.suptitle(
            f"{name}: stability boundary (black: 50 % failures), "
            f"{result.config.get('plant', '')} plant, delay "
            f"{result.config.get('delay_samples', '')} sample(s)",
            fontsize=10,
        )
        path = Path(out) / f"stability_boundary_{name}.png"
        fig.savefig(path, dpi=120)
        plt.close(fig)
        paths.append(path)
    return paths
