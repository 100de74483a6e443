"""Dask scaling: the default Monte-Carlo command as one process and on a LocalCluster.

    python studies/dask_scaling.py --cases 4096 --workers 2 --rounds 2

Runs `afbl montecarlo --cases N --seed 0 --no-report` alternately without and with
`--workers W`, writes the measurement with its provenance to docs/results/dask_scaling.json
(`--json`) and renders it into docs/scaling_out.md between its dask-scaling markers (`--page`;
`afbl_jax.studies.scaling`).
"""

import argparse
import json
import sys
import tempfile
from pathlib import Path

from afbl_jax.studies.scaling import measure_dask_scaling, render_dask_scaling

ROOT = Path(__file__).resolve().parents[1]
BEGIN, END = "<!-- dask-scaling:begin -->", "<!-- dask-scaling:end -->"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", type=int, default=4096)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--work", type=Path, default=None, help="folder for the runs (default: temp)")
    p.add_argument("--json", type=Path, default=ROOT / "docs" / "results" / "dask_scaling.json")
    p.add_argument("--page", type=Path, default=ROOT / "docs" / "scaling_out.md")
    args = p.parse_args()
    if args.cases < 1 or args.workers < 1 or args.rounds < 1:
        p.exit(2, "dask_scaling.py: error: --cases, --workers and --rounds must be >= 1\n")
    with tempfile.TemporaryDirectory(prefix="afbl-dask-scaling-") as tmp:
        doc = measure_dask_scaling(args.work or Path(tmp), args.cases, args.workers, args.rounds)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(doc, indent=2) + "\n")
    page = args.page.read_text()
    head, rest = page.split(BEGIN)
    _, tail = rest.split(END)
    args.page.write_text(f"{head}{BEGIN}\n{render_dask_scaling(doc)}{END}{tail}")
    print(f"wrote {args.json} and the measurement block of {args.page}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
