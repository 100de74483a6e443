"""Monte-Carlo robustness study (same as `afbl montecarlo`).

    python studies/montecarlo_robustness.py --cases 4096 --controllers fbl,afbl --seed 0 \\
        --out results/mc

Samples the cases (payload, model errors, pulses, gusts, Dryden turbulence, initial offsets,
step/sine references; a TOML/JSON --distribution overrides any of it), simulates every case
with every controller and writes OUT/results.parquet, meta.json, summary.json, report.md and
report.html. Re-running the same command resumes.
"""

import sys

from afbl_jax.cli import main

if __name__ == "__main__":
    sys.exit(main(["montecarlo", *sys.argv[1:]]))
