"""Monte-Carlo robustness study (thin script; `afbl montecarlo` runs the same code).

    python studies/montecarlo_robustness.py --cases 4096 --controllers fbl,afbl --seed 0 \
        --out results/mc
"""

import sys

from afbl_jax.montecarlo._study import main

if __name__ == "__main__":
    from afbl_jax import configure_cpu_devices

    configure_cpu_devices()  # one XLA device per core (AFBL_CPU_DEVICES=1 keeps one)
    sys.exit(main())
