"""Gain tuning study (same as `afbl tune`).

    python studies/tune_gains.py --controller afbl --cases 64 --time-budget 1200 \\
        --seed 0 --out results/tune_afbl

Tunes the controller's gains (default: L-BFGS with a backtracking Armijo line search;
``--method adam``, ``cmaes`` or ``hybrid``) on realistic training cases (rigid-body plant,
motor lag, digital control, delay; noise off) with an objective normalised by the paper's gains
and limits on effort and rotor saturation; writes OUT/gains.json, history.csv, convergence.png,
before_after.png, meta.json and evaluation.{txt,json} (paper vs tuned gains on 1024 fresh
held-out cases with sensor noise: P50/P90/P99, CVaR_0.9, failures with Wilson intervals;
canonical scenarios). ``--resume`` continues from OUT's checkpoint.
"""

import sys

from afbl_jax.cli import main

if __name__ == "__main__":
    sys.exit(main(["tune", *sys.argv[1:]]))
