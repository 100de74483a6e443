"""Paper reproduction study (same as `afbl reproduce`).

    python studies/reproduce_paper.py --out results/paper

Runs {ideal, uncertain} x {step, sine} x {fbl, afbl, afbl_paper}, prints the ISE table beside
the paper's Tables 4/5 and writes OUT/ise.json and the figures OUT/fig08...fig21 (PNG).
"""

import sys

from afbl_jax.cli import main

if __name__ == "__main__":
    sys.exit(main(["reproduce", *sys.argv[1:]]))
