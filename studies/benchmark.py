"""Batched-solving throughput benchmark (same as `afbl bench`).

    python studies/benchmark.py --out results/bench [--sizes 64,1024,4096,16384]

Measures simulations per second of the uncertain-step AFBL case for a scipy solve_ivp loop, a
loop of jitted diffrax solves, vmap, the ensemble and the float32 ensemble, with compile time,
memory and max relative ISE error vs a tight x64 reference; writes OUT/bench.json (a list of
rows) and OUT/bench.png (sims/s vs N).
"""

import sys

from afbl_jax.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", *sys.argv[1:]]))
