"""Rare failures: worst cases by gradient vs CMA-ES (same as `afbl falsify`), or a rare-event
failure probability (`afbl montecarlo --estimator ce-mixture|ce|is|subset`) with ``estimate``
as first argument.

    python studies/rare_failures.py --controllers afbl --seeds 10 --starts 4 --budget 32 \\
        --distribution studies/distributions/light_turbulence_4s.toml --out results/falsify
    python studies/rare_failures.py estimate --estimator ce-mixture --strategy ensemble_f32 \\
        --controllers afbl --stage-cases 400 --cases 1700 \\
        --distribution studies/distributions/light_turbulence.toml --out results/rare

Writes OUT/falsify.json, worst_cases.parquet, rare_report.md and figures (or rare_event.json,
results.parquet, rare_report.md).
"""

import sys

from afbl_jax.cli import main

if __name__ == "__main__":
    args = sys.argv[1:]
    if args[:1] == ["estimate"]:
        sys.exit(main(["montecarlo", *args[1:]]))
    sys.exit(main(["falsify", *args]))
