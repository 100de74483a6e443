"""Cost of the closed-loop vector field on Monte-Carlo cases, attributed to its parts.

Builds N default Monte-Carlo cases with the public sampler (`afbl_jax.studies.montecarlo`),
and times the ensemble vector field exactly as the Monte-Carlo default evaluates it
(`afbl_jax.ensemble_vector_field`: float32, groups of 4 cases, case axis last) in a compiled
loop of ``--evals`` evaluations, per case and evaluation. Variants switch parts off or make
them shared by all cases (a leaf equal in every case is evaluated once per group), so the
difference to the default says what that part costs. The loop compiles with the XLA options of
the package's batched solves (`afbl_jax.sim.batch_compiler_options`), so it measures the field
as the solve runs it. Variants are timed interleaved, best of ``--repeats``, in one process;
run pinned to one core for stable numbers::

    XLA_FLAGS=--xla_force_host_platform_device_count=1 taskset -c 1 \\
        python benchmarks/vector_field.py --cases 1024 [--against ../other-checkout]

With ``--against DIR`` the same variants of another checkout's package are timed in the
same process, interleaved (on the loaded 2-core machine the absolute numbers of such a run
differed from runs alone: compare the ratio and repeat, or alternate separate runs with
``PYTHONPATH`` set to each checkout).

``--profile`` prints the time per XLA kernel (fusion) of the first variant from a JAX
profiler trace, with the JAX primitives each holds. ``--hlo`` prints op counts of each
variant's compiled evaluation (transcendental ops, gathers, selects, broadcasts, transposes,
dtype conversions, float64 ops).
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import re
import sys
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import afbl_jax

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


def load_package(source: str | None):
    """The afbl_jax package of this checkout (None) or of another checkout's directory
    ``source`` (imported under another name, so both can be timed in one process)."""
    if source is None:
        return afbl_jax
    root = Path(source) / "afbl_jax"
    name = "afbl_jax_against"
    spec = importlib.util.spec_from_file_location(
        name, root / "__init__.py", submodule_search_locations=[str(root)]
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def _shared(tree, n):
    """Case 0 of a batched pytree, repeated for all n cases (then hoisted as shared)."""
    return jax.tree.map(lambda x: jnp.broadcast_to(x[0], (n, *x.shape[1:])), tree)


def _batched(tree, n):
    return jax.tree.map(lambda x: jnp.broadcast_to(jnp.asarray(x), (n, *np.shape(x))), tree)


def variant_cases(A, batch, name: str):
    """(scenario, vehicle, model, aerodynamics) of the cases of variant ``name`` (variants
    joined with "+" apply one after the other); ``A``: the afbl_jax package."""
    sc, veh, model, aero = batch.scenario, batch.vehicle, batch.model, batch.aerodynamics
    for part in name.split("+"):
        sc, veh, model, aero = _apply(A, part, batch.n_cases, sc, veh, model, aero)
    return sc, veh, model, aero


def _apply(A, name, n, sc, veh, model, aero):
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
        sc = importlib.import_module(A.__name__ + ".studies.bench").bench_cases(n, 0)[0]
        return sc, A.QuadrotorParams(), A.QuadrotorParams(), None
    elif name != "default":
        raise ValueError(f"unknown variant {name!r}; allowed: {', '.join(VARIANTS)}.")
    return sc, veh, model, aero


def make_field(A, n: int, seed: int, name: str, dtype, group_size: int):
    """The `ensemble_vector_field` of package ``A`` on n Monte-Carlo cases of variant
    ``name`` (AFBL, default distribution)."""
    mc = importlib.import_module(A.__name__ + ".studies.montecarlo")
    batch = mc.sample_cases(mc.default_distribution(), n, seed)
    sc, veh, model, aero = variant_cases(A, batch, name)
    return A.ensemble_vector_field(
        A.AFBL(), sc, veh, model, aerodynamics=aero, dtype=dtype, group_size=group_size
    )


def _loop_fn(n_evals: int, dtype):
    h = jnp.asarray(1e-4, dtype)

    def run(field, y0):
        # every group at its own time, as in a solve (groups take their own steps)
        offsets = jnp.arange(field.groups.count, dtype=dtype) * jnp.asarray(1e-3, dtype)

        def body(i, y):
            t = (i * h).astype(dtype) + offsets
            dy = field(t, y)
            return jax.tree.map(lambda a, b: a + h * b, y, dy)

        return jax.lax.fori_loop(0, n_evals, body, y0)

    return run


def solve_options(package) -> dict:
    """The XLA options ``package``'s batched solves compile with (none for a checkout that
    has no `batch_compiler_options`), so the loop measures the field as the solve runs it."""
    options = getattr(package.sim, "batch_compiler_options", None)
    return options() if options is not None else {}


def compiled_loop(field, n_evals: int, dtype, options=None):
    """A compiled function running ``n_evals`` evaluations, each on the state the previous
    one moved (y <- y + h f(t, y)), so that no evaluation can be hoisted or merged; compiled
    with the XLA ``options`` (a dict, `solve_options`)."""
    run = eqx.filter_jit(_loop_fn(n_evals, dtype), compiler_options=options or None)
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


def hlo_counts(field, dtype, options=None) -> dict[str, int]:
    """Op counts in the compiled HLO of one evaluation of ``field``."""
    y0 = field.initial_state(dtype)
    params, static = eqx.partition(field, eqx.is_array)
    one = jax.jit(
        lambda p, y: eqx.combine(p, static)(jnp.asarray(0.5, dtype), y),
        compiler_options=options or None,
    )
    text = one.lower(params, y0).compile().as_text()
    return {k: len(re.findall(p, text)) for k, p in HLO_PATTERNS.items()}


def profile(field, n_evals: int, dtype, top: int = 15, options=None) -> None:
    """Time per compiled kernel (XLA fusion) of the evaluation loop from a JAX profiler
    trace, with the operations (JAX primitive names) each fusion holds."""
    import collections
    import glob
    import gzip
    import json
    import tempfile

    run = compiled_loop(field, n_evals, dtype, options)
    run()
    params, static = eqx.partition(field, eqx.is_array)
    loop = _loop_fn(n_evals, dtype)
    y0 = field.initial_state(dtype)
    text = (
        jax.jit(lambda p, y: loop(eqx.combine(p, static), y), compiler_options=options or None)
        .lower(params, y0)
        .compile()
        .as_text()
    )
    with tempfile.TemporaryDirectory() as d:
        jax.profiler.start_trace(d, create_perfetto_trace=True)
        for _ in range(3):
            run()
        jax.profiler.stop_trace()
        trace = json.load(gzip.open(glob.glob(f"{d}/**/*.trace.json.gz", recursive=True)[0]))
    total = collections.Counter()
    for e in trace["traceEvents"]:
        name = e.get("name", "")
        if name.startswith("while"):  # the loop itself: it holds all the others
            continue
        if e.get("ph") == "X" and re.search(rf"\n\s*(ROOT )?%{re.escape(name)} = ", text):
            total[name] += e.get("dur", 0)
    whole = sum(total.values())
    print(f"\nkernels of the evaluation loop (share of {whole / 3e3:.2f} ms per run):")
    for name, dur in total.most_common(top):
        m = re.search(rf"%{re.escape(name)} = (\S+) .*?(calls=%(\S+?),|$)", text, re.M)
        shape, ops = m.group(1) if m else "?", ""
        if m and m.group(3):
            body = re.search(rf"\n%{re.escape(m.group(3))} .*?\n(.*?)\n}}", text, re.S)
            prims = collections.Counter(
                re.findall(r'op_name="[^"]*/([^"/]+)"', body.group(1) if body else "")
            )
            ops = " ".join(f"{k}:{v}" for k, v in prims.most_common(8))
        print(f"{dur / whole:6.1%} {name[:32]:32s} {shape[:24]:24s} {ops}")


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
    ap.add_argument(
        "--profile", action="store_true", help="time per XLA kernel of the first variant"
    )
    ap.add_argument(
        "--against",
        default=None,
        help="directory of another checkout: time its vector field too, in this process",
    )
    args = ap.parse_args(argv)
    names = [v for v in args.variants.split(",") if v]
    for v in names:
        if not set(v.split("+")) <= set(VARIANTS):
            ap.error(f"unknown variant {v!r}; allowed: {', '.join(VARIANTS)}")
    dtype = jnp.dtype(args.dtype)
    packages = {"this": load_package(None)}
    if args.against:
        packages["against"] = load_package(args.against)
    keys = [(p, v) for v in names for p in packages]
    fields = {
        (p, v): make_field(packages[p], args.cases, args.seed, v, dtype, args.group_size)
        for p, v in keys
    }
    options = {p: solve_options(pkg) for p, pkg in packages.items()}
    runs = {k: compiled_loop(f, args.evals, dtype, options[k[0]]) for k, f in fields.items()}
    for r in runs.values():
        r()  # compile and warm up
    best = {k: np.inf for k in keys}
    for _ in range(args.repeats):  # interleaved repetitions, best of k
        for k, r in runs.items():
            t0 = time.perf_counter()
            r()
            best[k] = min(best[k], time.perf_counter() - t0)
    per = {k: 1e9 * best[k] / (args.cases * args.evals) for k in keys}
    print(
        f"vector field, {args.cases} cases, {args.evals} evaluations, {dtype.name}, groups of "
        f"{args.group_size}, best of {args.repeats} (wall time)"
    )
    for p in packages:
        label = "this checkout" if p == "this" else f"--against {args.against}"
        print(f"\n{label}:")
        base = per.get((p, "default"), per[(p, names[0])])
        print(f"{'variant':18s} {'ns/case/eval':>12s} {'saved vs default':>17s}  what")
        for v in names:
            saved = base - per[(p, v)]
            what = " + ".join(VARIANTS[q] for q in v.split("+"))
            print(f"{v:18s} {per[(p, v)]:12.1f} {saved:10.1f} ({saved / base:5.1%})  {what}")
    if args.against:
        print("\nratio against / this (> 1: this checkout is faster)")
        for v in names:
            print(f"{v:18s} {per[('against', v)] / per[('this', v)]:12.2f}")
    if args.profile:
        profile(fields[("this", names[0])], args.evals, dtype, options=options["this"])
    if args.hlo:
        print()
        cols = list(HLO_PATTERNS)
        print(f"{'package':8s} {'variant':18s} " + " ".join(f"{c[:12]:>12s}" for c in cols))
        for p, v in keys:
            counts = hlo_counts(fields[(p, v)], dtype, options[p])
            print(f"{p:8s} {v:18s} " + " ".join(f"{counts[c]:12d}" for c in cols))
    return per


if __name__ == "__main__":
    main()
