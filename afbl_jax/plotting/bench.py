"""Figure of the throughput benchmark: simulations per second against batch size."""

from __future__ import annotations

from pathlib import Path


def plot_benchmark(rows: list[dict], path: Path, batch_rows=()) -> Path:
    """sims/s against N per batched row (``batch_rows``: their names, in legend order) and the
    per-case loops as horizontal lines."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for name in batch_rows or sorted({r["strategy"] for r in rows if r.get("N", 0) > 1}):
        pts = sorted((r["N"], r["sims_per_s"]) for r in rows if r["strategy"] == name)
        if pts:
            dashed = name.startswith("montecarlo_cases")  # the Monte-Carlo distribution's cases
            ax.plot(*zip(*pts, strict=True), "s--" if dashed else "o-", label=name)
    loops = (
        ("scipy_rk45_loop", "k--"),
        ("diffrax_loop", "k:"),
        ("scipy_rk45_montecarlo_cases", "k-."),
    )
    for name, style in loops:
        for r in rows:
            if r["strategy"] == name:
                ax.axhline(r["sims_per_s"], ls=style[1:], color="k", label=f"{name} (per case)")
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xlabel("batch size N [cases]")
    ax.set_ylabel("throughput [simulations / s]")
    ax.set_title("AFBL, 20 s: uncertain step (solid), Monte-Carlo cases (dashed)")
    ax.grid(True, which="both", alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return Path(path)
