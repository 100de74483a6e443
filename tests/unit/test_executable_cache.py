"""The executable cache (`afbl_jax.sim.CachedJit`): a call made again, in this process or a new
one, loads the executable compiled before (no tracing) and gives bitwise the same results; the
key separates what changes the program; what cannot be kept is not kept."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from afbl_jax.sim import CachedJit, executable_cache_folder, set_executable_cache

from ..helpers import subprocess_env


@pytest.fixture
def folder(tmp_path):
    previous = executable_cache_folder()
    set_executable_cache(tmp_path / "exe")
    yield tmp_path / "exe"
    set_executable_cache(previous)


def _poly(x, power, scale):
    return {"y": scale * x**power + jnp.sum(x), "n": jnp.asarray(power)}


def _files(folder):
    return sorted(p.name for p in folder.glob("*.exe")) if folder.exists() else []


def test_second_instance_loads_the_kept_executable_bitwise(folder):
    x = np.linspace(0.0, 1.0, 7)
    first = CachedJit(_poly, "poly")(x, 3, 0.5)
    assert len(_files(folder)) == 1
    traces = []

    def listen(event, *args, **kwargs):
        if event == "/jax/core/compile/jaxpr_trace_duration":
            traces.append(kwargs.get("fun_name"))

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        again = CachedJit(_poly, "poly")(x, 3, 0.5)  # a new instance: loads the file
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    assert "poly_executable" not in traces
    assert np.array_equal(first["y"], again["y"]) and int(again["n"]) == 3
    assert np.array_equal(first["y"], 0.5 * x**3 + x.sum())


def test_key_separates_static_values_shapes_and_dtypes(folder):
    f = CachedJit(_poly, "poly")
    x = np.linspace(0.0, 1.0, 7)
    f(x, 3, 0.5)
    f(x, 3, 0.5)  # the same call: no new file
    assert len(_files(folder)) == 1
    f(x, 2, 0.5)
    f(x, 3, 0.25)
    f(np.linspace(0.0, 1.0, 8), 3, 0.5)
    f(x.astype(np.float32), 3, 0.5)
    assert len(_files(folder)) == 5
    out = CachedJit(_poly, "poly")(x, 2, 0.25)  # a combination never kept: compiled, right
    assert np.allclose(out["y"], 0.25 * x**2 + x.sum(), rtol=0, atol=1e-15)
    assert len(_files(folder)) == 6


def test_what_cannot_be_kept_runs_uncached(folder):
    x = np.arange(4.0)

    def with_callback(x):
        y = jax.pure_callback(np.cos, jax.ShapeDtypeStruct(x.shape, x.dtype), x)
        return y + 1.0

    assert np.allclose(CachedJit(with_callback, "callback")(x), np.cos(x) + 1.0)

    class Opaque:  # its repr carries an address: no stable key
        def __init__(self, k):
            self.k = k

        def __hash__(self):
            return hash(self.k)

        def __eq__(self, other):
            return isinstance(other, Opaque) and other.k == self.k

    def scaled(x, o):
        return x * o.k

    assert np.allclose(CachedJit(scaled, "opaque")(x, Opaque(3.0)), 3.0 * x)
    # under a trace: the plain filter_jit path, differentiable
    g = jax.grad(lambda s: CachedJit(_poly, "poly")(x, 2, s)["y"].sum())(2.0)
    assert np.isclose(g, np.sum(x**2))
    assert _files(folder) == []


def test_unreadable_file_is_compiled_again_and_replaced(folder):
    x = np.linspace(0.0, 1.0, 5)
    expected = CachedJit(_poly, "poly")(x, 3, 0.5)["y"]
    (path,) = folder.glob("*.exe")
    path.write_bytes(b"not an executable")
    out = CachedJit(_poly, "poly")(x, 3, 0.5)["y"]
    assert np.array_equal(out, expected)
    assert path.stat().st_size > 1000  # rewritten
    assert np.array_equal(CachedJit(_poly, "poly")(x, 3, 0.5)["y"], expected)


def test_cache_off_keeps_nothing(tmp_path):
    previous = executable_cache_folder()
    set_executable_cache(None)
    try:
        out = CachedJit(_poly, "poly")(np.ones(3), 2, 1.0)
    finally:
        set_executable_cache(previous)
    assert np.allclose(out["y"], 4.0) and not list(tmp_path.rglob("*.exe"))


_SCRIPT = textwrap.dedent(
    """
    import json, sys
    import jax, jax.numpy as jnp, numpy as np
    import afbl_jax as A
    from afbl_jax.sim import CachedJit, set_executable_cache

    set_executable_cache(sys.argv[1])
    traced = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda event, d, **kw: traced.append(kw.get("fun_name"))
        if event == "/jax/core/compile/jaxpr_trace_duration" else None
    )
    solve = CachedJit(lambda a, b: jnp.linalg.solve(a, b), "lapack_solve")
    a = np.array([[4.0, 1.0], [2.0, 3.0]])
    x = np.asarray(solve(a, np.array([1.0, 2.0])))
    r = A.simulate(A.AFBL(), A.paper_scenario("uncertain", "step"), n_save=21, saving="dense")
    print(json.dumps({
        "x": x.tolist(),
        "ise": float(r.ise_attitude),
        "phi": np.asarray(r.plant)[:, 0].tolist(),
        "traced": sorted(set(n for n in traced if n and n.endswith("_executable"))),
    }))
    """
)


def test_a_new_process_loads_instead_of_tracing(tmp_path):
    """Two processes: the first compiles and keeps `simulate` (dense saving) and a LAPACK
    solve, the second loads both (no tracing; a loaded LAPACK call runs) with bitwise the
    same numbers."""
    script = tmp_path / "run.py"
    script.write_text(_SCRIPT)
    runs = []
    for _ in range(2):
        proc = subprocess.run(
            [sys.executable, str(script), str(tmp_path / "exe")],
            capture_output=True,
            text=True,
            env=subprocess_env(),
            timeout=300,
        )
        assert proc.returncode == 0, proc.stderr[-2000:]
        runs.append(json.loads(proc.stdout.strip().splitlines()[-1]))
    first, second = runs
    assert first["traced"] == ["lapack_solve_executable", "simulate_executable"]
    assert second["traced"] == []
    assert first["x"] == second["x"] and np.allclose(first["x"], [0.1, 0.6])
    assert first["ise"] == second["ise"] and first["phi"] == second["phi"]


def test_threads_calling_at_once_compile_once(folder):
    """Several threads making the same first call share one compilation, one file and one
    result (bitwise)."""
    import threading

    f = CachedJit(_poly, "poly")
    x = np.linspace(0.0, 1.0, 9)
    traces = []

    def listen(event, *args, **kwargs):
        if event == "/jax/core/compile/jaxpr_trace_duration":
            traces.append(kwargs.get("fun_name"))

    start = threading.Barrier(4)
    results = [None] * 4

    def call(i):
        start.wait()
        results[i] = f(x, 2, 1.5)

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        threads = [threading.Thread(target=call, args=(i,)) for i in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    assert traces.count("poly_executable") == 1
    assert len(_files(folder)) == 1
    for r in results:
        assert np.array_equal(r["y"], 1.5 * x**2 + x.sum())


def test_keeping_a_program_out_of_jax_cache_leaves_other_threads_setting():
    """The compilation that `CachedJit` keeps out of JAX's persistent cache raises the cache's
    minimum compile time for its own thread only: a program another thread compiles meanwhile
    is written to JAX's cache as usual, and the setting is the same afterwards."""
    import threading

    from afbl_jax.sim import _executables

    if _executables._min_compile_time is None:
        pytest.skip("this jax has no per-thread setting (compilations are then serialised)")
    before = jax.config.jax_persistent_cache_min_compile_time_secs
    seen = {}

    class Lowered:
        def compile(self):
            seen["here"] = _executables._min_compile_time.value

            def other():
                seen["other"] = jax.config.jax_persistent_cache_min_compile_time_secs

            t = threading.Thread(target=other)
            t.start()
            t.join()
            return "compiled"

    compiled, serializable = _executables._compile_fresh(Lowered())
    assert compiled == "compiled" and serializable
    assert seen["here"] == float("inf")
    assert seen["other"] == before
    assert jax.config.jax_persistent_cache_min_compile_time_secs == before
