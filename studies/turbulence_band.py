"""What the default turbulence cutoff keeps and saves: the default Monte-Carlo study with the
lines up to the cutoff and with every line of the grid, compared case by case.

    python studies/turbulence_band.py --cases 4096 --seed 0 --out results/band

Prints the comparison (`afbl_jax.studies.turbulence_band`) and writes it to
OUT/turbulence_band.json; the two runs' folders are OUT/cutoff and OUT/all_lines. Runs as
`afbl montecarlo` does: one XLA CPU device per core, the persistent compilation cache, x64
enabled (float64 sampling; the solves are float32 as there).
"""

import argparse
import json
import sys
from pathlib import Path


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", type=int, default=4096)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args()
    if args.cases < 1 or args.seed < 0:
        p.exit(2, "turbulence_band.py: error: --cases must be >= 1 and --seed >= 0\n")
    if args.out.exists() and any(args.out.iterdir()):
        p.exit(2, f"turbulence_band.py: error: --out {args.out} is not empty\n")
    print(f"turbulence band: {args.cases} cases, seed {args.seed} -> {args.out}", flush=True)
    from afbl_jax.sim import configure_compilation_cache, configure_cpu_devices

    configure_cpu_devices()  # one XLA CPU device per core, as `afbl montecarlo` runs
    configure_compilation_cache()
    import jax

    jax.config.update("jax_enable_x64", True)  # the cases drawn as the afbl command draws them
    from afbl_jax.studies.turbulence_band import compare_turbulence_bands, format_turbulence_bands

    doc = compare_turbulence_bands(
        args.out,
        args.cases,
        args.seed,
        echo=lambda s: print(s, flush=True),
        progress=not args.no_progress,
    )
    (args.out / "turbulence_band.json").write_text(json.dumps(doc, indent=1) + "\n")
    print(format_turbulence_bands(doc))
    return 0


if __name__ == "__main__":
    sys.exit(main())
