"""The tuner's comparison studies (same as `afbl tune-compare`), one command each:

    python studies/tune_compare.py --study optimizers --cases 16 --time-budget 300 \\
        --seeds 0 1 2 --out results/tune_optimizers
    python studies/tune_compare.py --study controllers --cases 16 --time-budget 300 \\
        --seeds 0 1 2 --heldout-cases 1024 --out results/tune_controllers
    python studies/tune_compare.py --study gradient-cost --cases 16 --out results/tune_grad

optimizers: objective against wall time of L-BFGS, Adam and CMA-ES on the same cases and
budget per seed (loss_vs_time.png). controllers: FBL+PID and AFBL tuned with the same
objective, method, budget and cases, paper and tuned gains on fresh held-out cases with noise.
gradient-cost: one gradient against one forward evaluation, float32 and float64.
"""

import sys

from afbl_jax.cli import main

if __name__ == "__main__":
    sys.exit(main(["tune-compare", *sys.argv[1:]]))
