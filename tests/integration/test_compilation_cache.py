"""The persistent compilation cache: a second process loads the programs the first one
compiled, with bitwise the same numbers; it can be switched off; an unusable folder costs only
a warning."""

import json
import os
import subprocess
import sys
from pathlib import Path

import afbl_jax as A

ROOT = Path(__file__).resolve().parents[2]

# one small ensemble solve; prints the cache loads, the compilations and the metrics
SCRIPT = """
import json, sys
import jax
import jax.monitoring as mon
jax.config.update("jax_enable_x64", True)
import afbl_jax as A
counts = {"hits": 0, "compiles": 0, "loaded": 0}
def on_event(name, **kw):
    if name == "/jax/compilation_cache/cache_hits":
        counts["hits"] += 1
def on_duration(name, d, **kw):
    if name == "/jax/core/compile/backend_compile_duration":
        counts["compiles"] += 1
def on_span(name, start, end, **kw):
    if name == A.sim.LOAD_EVENT:
        counts["loaded"] += 1
mon.register_event_listener(on_event)
mon.register_event_duration_secs_listener(on_duration)
mon.register_event_time_span_listener(on_span)
folder = A.configure_compilation_cache()
scenarios = A.stack_scenarios([A.paper_scenario("uncertain", "step")] * 4)
m = A.simulate_batch(A.AFBL(), scenarios, A.QuadrotorParams(), strategy="ensemble",
                     dtype="float32", rtol=1e-5, atol=1e-6, n_save=0, devices=jax.devices()[:1])
print(json.dumps({"folder": str(folder), **counts,
                  "ise": [float(x) for x in m.ise_attitude],
                  "steps": [int(x) for x in m.num_steps]}))
"""


def _env(env_extra: dict) -> dict:
    """The subprocess's environment: this one with ``env_extra``, without a cache folder set by
    JAX's own variables (they win over `configure_compilation_cache`, which is under test)."""
    env = {k: v for k, v in os.environ.items() if k != "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"}
    env = {**env, **env_extra, "PYTHONPATH": str(ROOT)}
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    return env


def _run(env_extra: dict) -> dict:
    out = subprocess.run(
        [sys.executable, "-c", SCRIPT],
        env=_env(env_extra),
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_second_process_loads_the_programs_with_the_same_numbers(tmp_path):
    # every program is cached, however fast it compiled (no threshold set in the environment)
    env = {"AFBL_COMPILATION_CACHE": str(tmp_path / "xla")}
    first = _run(env)
    assert first["folder"] == str(tmp_path / "xla")
    assert first["compiles"] > 0
    entries = sorted(p.relative_to(tmp_path) for p in (tmp_path / "xla").rglob("*"))
    assert entries  # the programs were written
    kept = list((tmp_path / "xla" / A.sim.EXECUTABLES_SUBFOLDER).glob("*.exe"))
    assert len(kept) == 1  # the ensemble solve's executable
    second = _run(env)
    # every program of the second process is loaded: the solve's executable without tracing
    # it (so also without the small programs its tracing evaluates), the others from JAX's
    # cache (JAX's compile event fires for loads too; a program compiled twice in one process
    # is loaded the second time: hits in the first)
    assert second["loaded"] == 1 and first["loaded"] == 0
    assert second["hits"] == second["compiles"] < first["compiles"]
    assert second["ise"] == first["ise"] and second["steps"] == first["steps"]
    # nothing new to write: the same programs
    assert sorted(p.relative_to(tmp_path) for p in (tmp_path / "xla").rglob("*")) == entries


def test_cache_off_and_unusable_folder(tmp_path, monkeypatch):
    off = _run({"AFBL_COMPILATION_CACHE": "off"})
    assert off["folder"] == "None" and off["hits"] == 0
    monkeypatch.setenv("AFBL_COMPILATION_CACHE", "off")
    assert A.configure_compilation_cache() is None  # in-process: nothing changed
    # a folder that cannot be created: one warning line, then the command runs (here to its
    # one-line usage error: --help answers before the cache is set up)
    blocker = tmp_path / "file"
    blocker.write_text("")
    code = "import sys; from afbl_jax.cli import main; sys.exit(main(sys.argv[1:]))"
    done = subprocess.run(
        [sys.executable, "-c", code, "bench", "--out", str(tmp_path / "b"), "--sizes", "0"],
        env=_env({"AFBL_COMPILATION_CACHE": str(blocker / "xla")}),
        capture_output=True,
        text=True,
    )
    assert done.returncode == 2, done.stderr
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(lines) == 2, done.stderr
    assert lines[0].startswith("afbl: warning: no compilation cache")
    assert lines[1].startswith("afbl bench: error:")
    assert not (tmp_path / "b").exists()
