"""Cost of the closed-loop vector field on Monte-Carlo cases, attributed to its parts.

Builds N default Monte-Carlo cases with the public sampler (`afbl_jax.studies.montecarlo`),
and times the ensemble vector field exactly as the Monte-Carlo default evaluates it
(`afbl_jax.ensemble_vector_field`: float32, groups of 4 cases, case axis last) in a compiled
loop of ``--evals`` evaluations, per case and evaluation. Variants switch parts off or make
them shared by all cases (a leaf equal in every case is evaluated once per group), so the
difference to the default says what that part costs. Variants are timed interleaved, best of
``--repeats``, in one process; run pinned to one core for stable numbers::

    XLA_FLAGS=--xla_force_host_platform_device_count=1 taskset -c 1 \\
        python benchmarks/vector_field.py --cases 1024

``--hlo`` also prints op counts of each variant's compiled evaluation (transcendental ops,
gathers, selects, broadcasts, transposes, dtype conversions, float64 ops).
"""

from __future__ import annotations

import argparse
import re
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import afbl_jax as A
from afbl_jax.studies.bench import bench_cases
from afbl_jax.studies.montecarlo import default_distribution, sample_cases

VARIANTS = {
    "default": "the Monte-Carlo cases as sampled",
    "no_turbulence": "no Dryden lines (K = 0); mean wind and gust kept",
    "no_wind": "no wind at all (no mean wind, gust or turbulence)",
    "linear_drag": "LinearDrag instead of RotorDrag",
    "shared_reference": "case 0's reference for every case (evaluated once per group)",
    "no_pulses": "zero pulses, shared (evaluated once per group)",
    "no_payload": "no payload change, shared",
    "shared_vehicle": "case 0's vehicle for every case",
    "all_shared": "every input of case 0 (no per-case inputs at all)",
    "bench_cases": "the benchmark's cases (afbl bench: step reference, payload, pulses)",
}
"""Variant name -> what it changes."""


def _shared(tree, n):
    """Case 0 of a batched pytree, repeated for all n cases (then hoisted as shared)."""
    return jax.tree.map(lambda x: jnp.broadcast_to(x[0], (n, *x.shape[1:])), tree)


def _batched(tree, n):
    return jax.tree.map(lambda x: jnp.broadcast_to(jnp.asarray(x), (n, *np.shape(x))), tree)


def variant_cases(batch, name: str):
    """(scenario, vehicle, model, aerodynamics) of the cases of variant ``name`` (variants
    joined with "+" apply one after the other)."""
    sc, veh, model, aero = batch.scenario, batch.vehicle, batch.model, batch.aerodynamics
    for part in name.split("+"):
        sc, veh, model, aero = _apply(part, batch.n_cases, sc, veh, model, aero)
    return sc, veh, model, aero


def _apply(name, n, sc, veh, model, aero):
    if name == "no_turbulence":
        w = sc.wind
        k0 = jnp.zeros((n, 3, 0))
        wind = eqx.tree_at(
            lambda w: (w.turbulence_frequency, w.turbulence_cos, w.turbulence_sin),
            w,
            (jnp.zeros((n, 0)), k0, k0),
        )
        sc = eqx.tree_at(lambda s: s.wind, sc, wind)
    elif name == "no_wind":
        sc = eqx.tree_at(lambda s: s.wind, sc, _batched(A.no_wind(0, 0), n))
    elif name == "linear_drag":
        aero = "linear"
    elif name == "shared_reference":
        sc = eqx.tree_at(lambda s: s.reference, sc, _shared(sc.reference, n))
    elif name == "no_pulses":
        zero = jax.tree.map(jnp.zeros_like, sc.disturbance)
        sc = eqx.tree_at(lambda s: s.disturbance, sc, zero)
    elif name == "no_payload":
        sc = eqx.tree_at(
            lambda s: (s.payload_fraction, s.payload_time),
            sc,
            (jnp.zeros(n), jnp.zeros(n)),
        )
    elif name == "shared_vehicle":
        veh = _shared(veh, n)
    elif name == "all_shared":
        sc, veh = _shared(sc, n), _shared(veh, n)
    elif name == "bench_cases":
        sc = bench_cases(n, 0)[0]
        return sc, A.QuadrotorParams(), A.QuadrotorParams(), None
    elif name != "default":
        raise ValueError(f"unknown variant {name!r}; allowed: {', '.join(VARIANTS)}.")
    return sc, veh, model, aero


def make_field(batch, name: str, controller, dtype, group_size: int):
    sc, veh, model, aero = variant_cases(batch, name)
    return A.ensemble_vector_field(
        controller, sc, veh, model, aerodynamics=aero, dtype=dtype, group_size=group_size
    )


def compiled_loop(field, n_evals: int, dtype):
    """A compiled function running ``n_evals`` evaluations, each on the state the previous
    one moved (y <- y + h f(t, y)), so that no evaluation can be hoisted or merged."""
    h = jnp.asarray(1e-4, dtype)

    @eqx.filter_jit
    def run(field, y0):
        def body(i, y):
            t = (i * h).astype(dtype)
            dy = field(t, y)
            return jax.tree.map(lambda a, b: a + h * b, y, dy)

        return jax.lax.fori_loop(0, n_evals, body, y0)

    y0 = field.initial_state(dtype)
    return lambda: jax.block_until_ready(run(field, y0))


HLO_PATTERNS = {
    "sin/cos": r"= f\d+\[[^\]]*\]\{?[^ ]*\}? (sine|cosine)\(",
    "tan/atan/exp/log/sqrt": r" (tan|atan2|exponential|log|sqrt|rsqrt|power)\(",
    "divide": r" divide\(",
    "gather/dyn-slice": r" (gather|dynamic-slice)\(",
    "select": r" select\(",
    "broadcast": r" broadcast\(",
    "transpose/copy": r" (transpose|copy)\(",
    "convert": r" convert\(",
    "f64 values": r"= f64\[",
    "fusions": r" fusion\(",
}


def hlo_counts(field, dtype) -> dict[str, int]:
    """Op counts in the compiled HLO of one evaluation of ``field``."""
    y0 = field.initial_state(dtype)
    params, static = eqx.partition(field, eqx.is_array)
    one = jax.jit(lambda p, y: eqx.combine(p, static)(jnp.asarray(0.5, dtype), y))
    text = one.lower(params, y0).compile().as_text()
    return {k: len(re.findall(p, text)) for k, p in HLO_PATTERNS.items()}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", type=int, default=1024)
    ap.add_argument("--evals", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--group-size", type=int, default=4)
    ap.add_argument("--dtype", default="float32")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--hlo", action="store_true")
    args = ap.parse_args(argv)
    names = [v for v in args.variants.split(",") if v]
    for v in names:
        if not set(v.split("+")) <= set(VARIANTS):
            ap.error(f"unknown variant {v!r}; allowed: {', '.join(VARIANTS)}")
    dtype = jnp.dtype(args.dtype)
    batch = sample_cases(default_distribution(), args.cases, args.seed)
    controller = A.AFBL()
    fields = {v: make_field(batch, v, controller, dtype, args.group_size) for v in names}
    runs = {v: compiled_loop(f, args.evals, dtype) for v, f in fields.items()}
    for r in runs.values():
        r()  # compile and warm up
    best = {v: np.inf for v in names}
    for _ in range(args.repeats):  # interleaved repetitions, best of k
        for v, r in runs.items():
            t0 = time.perf_counter()
            r()
            best[v] = min(best[v], time.perf_counter() - t0)
    per = {v: 1e9 * best[v] / (args.cases * args.evals) for v in names}
    base = per.get("default", next(iter(per.values())))
    print(
        f"vector field, {args.cases} cases, {args.evals} evaluations, {dtype.name}, groups of "
        f"{args.group_size}, best of {args.repeats} (wall time)"
    )
    print(f"{'variant':18s} {'ns/case/eval':>12s} {'saved vs default':>17s}  what")
    for v in names:
        saved = base - per[v]
        print(f"{v:18s} {per[v]:12.1f} {saved:10.1f} ({saved / base:5.1%})  {' + '.join(VARIANTS[p] for p in v.split('+'))}")
    if args.hlo:
        print()
        counts = {v: hlo_counts(f, dtype) for v, f in fields.items()}
        keys = list(HLO_PATTERNS)
        print(f"{'variant':18s} " + " ".join(f"{k[:12]:>12s}" for k in keys))
        for v in names:
            print(f"{v:18s} " + " ".join(f"{counts[v][k]:12d}" for k in keys))
    return per


if __name__ == "__main__":
    main()
