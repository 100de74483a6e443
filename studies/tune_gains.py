"""Gain tuning study (same as `afbl tune`).

    python studies/tune_gains.py --controller afbl --objective robust --cases 64 --steps 100 \\
        --seed 0 --out results/tune_afbl

Optimises the controller's log-gains with optax (Adam + cosine schedule) by gradient descent
through the diffrax closed loop, with the rotor limit (thrust-to-weight 2.5), an effort term and
a saturation penalty; writes OUT/gains.json, history.csv, convergence.png, before_after.png,
meta.json and evaluation.{txt,json} (paper vs tuned gains on fresh held-out cases and on the
canonical scenarios). ``--resume`` continues from OUT's checkpoint.
"""

import sys

from afbl_jax.cli import main

if __name__ == "__main__":
    sys.exit(main(["tune", *sys.argv[1:]]))
