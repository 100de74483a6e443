"""Unmodeled-dynamics study (same as `afbl unmodeled`).

    python studies/unmodeled_dynamics.py --out results/unmodeled [--gains tuned_fbl.json ...]

FBL and AFBL on the full rigid-body plant with motor lag tau_m and a digital controller at f_c
(one-sample measurement delay, optional noise): ISE and failure rate over tau_m x f_c x noise
level, written to OUT/unmodeled_dynamics.json / .txt, and a stability-boundary figure per
controller (OUT/stability_boundary_<controller>.png).
"""

import sys

from afbl_jax.cli import main

if __name__ == "__main__":
    sys.exit(main(["unmodeled", *sys.argv[1:]]))
