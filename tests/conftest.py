import gc
import json
import os
import shutil
import tempfile
from pathlib import Path

# One persistent compilation cache for the whole test session, made by the first pytest
# process (xdist's controller) before JAX is imported and inherited through the environment by
# its workers, the `afbl` subprocesses and the notebook kernels, so that a program compiled by
# one of them is loaded by the others; every program is kept, however fast it compiled. Removed
# when that process ends. JAX's compile event fires for cache loads too, so the compilation
# counts of the tests (no recompilation in a loop) mean the same with it.
_SESSION_CACHE = "AFBL_TEST_SESSION_CACHE"
_OWNS_SESSION_CACHE = _SESSION_CACHE not in os.environ
if _OWNS_SESSION_CACHE:
    os.environ[_SESSION_CACHE] = tempfile.mkdtemp(prefix="afbl-test-xla-")
os.environ["JAX_COMPILATION_CACHE_DIR"] = os.environ[_SESSION_CACHE]
os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
os.environ["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"] = "0"
# The tests compile far more than they run: XLA's CPU backend compiles without LLVM's
# optimisation passes (the same HLO programs and IEEE arithmetic, generated faster and run
# slower) and with its classic code generator instead of its fusion emitters (the default),
# in this process and, through the environment, in its subprocesses. The classic generator
# compiles faster, but it does not keep the rounding of an operation the same between
# programs of different shapes: the tests that assert two different programs agree bit for
# bit are marked `default_codegen`, left out here and run in one subprocess with XLA's
# default code generator by tests/integration/test_default_codegen.py
# (`AFBL_TEST_CODEGEN=default` runs every test with it).
TEST_XLA_FLAGS = ("--xla_backend_optimization_level=0", "--xla_llvm_disable_expensive_passes=true")
CODEGEN_ENV = "AFBL_TEST_CODEGEN"
CLASSIC_CODEGEN_FLAG = "--xla_cpu_use_fusion_emitters=false"
DEFAULT_CODEGEN = os.environ.get(CODEGEN_ENV) == "default"
_flags = [f for f in os.environ.get("XLA_FLAGS", "").split() if f != CLASSIC_CODEGEN_FLAG]
_flags += [f for f in TEST_XLA_FLAGS if f not in _flags]
if not DEFAULT_CODEGEN:
    _flags.append(CLASSIC_CODEGEN_FLAG)
os.environ["XLA_FLAGS"] = " ".join(_flags)

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)
# JAX's default devices (one on a CPU) in every test process, whichever test runs first: an
# in-process `afbl` command that happened to start JAX would give each core its own device
# (`configure_cpu_devices`) for every later test of that worker; several devices are tested in
# subprocesses
jax.devices()
# the commands' own cache folder (`AFBL_COMPILATION_CACHE`) stays off: the session cache above
# is the only one, and nothing is written to the user's cache folder
os.environ["AFBL_COMPILATION_CACHE"] = "off"


# With AFBL_TEST_COMPILE_LOG naming a folder (`studies/test_times.py` sets it), each test
# process appends one JSON line per test to WORKER.jsonl there: the seconds JAX spent tracing
# and lowering, the XLA programs compiled (backend compilations less persistent-cache loads) and
# the seconds of those compilations and loads (``compiled_1s``: the spans of 1 s or more, the
# large programs), in this process (not in the subprocesses a test
# starts: `afbl` commands, notebook kernels).
_COMPILE_LOG = os.environ.get("AFBL_TEST_COMPILE_LOG")
_JAX_SPANS = {
    "/jax/core/compile/jaxpr_trace_duration": "trace_lower_s",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "trace_lower_s",
    "/jax/core/compile/backend_compile_duration": "xla_s",
}
_test_compiles: dict[str, float] = {}


def _on_jax_span(event: str, seconds: float, **kwargs) -> None:
    key = _JAX_SPANS.get(event)
    if key is not None:
        _test_compiles[key] = _test_compiles.get(key, 0.0) + seconds
        if key == "xla_s":
            _test_compiles["compiled"] = _test_compiles.get("compiled", 0) + 1
            if seconds >= 1.0:
                _test_compiles["compiled_1s"] = _test_compiles.get("compiled_1s", 0) + 1


def _on_jax_event(event: str, **kwargs) -> None:
    if event == "/jax/compilation_cache/cache_hits":  # a load, not a compilation
        _test_compiles["compiled"] = _test_compiles.get("compiled", 0) - 1


if _COMPILE_LOG:
    jax.monitoring.register_event_duration_secs_listener(_on_jax_span)
    jax.monitoring.register_event_listener(_on_jax_event)

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_protocol(item, nextitem):
        _test_compiles.clear()
        yield
        row = {"id": item.nodeid, **_test_compiles}
        worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        with open(Path(_COMPILE_LOG) / f"{worker}.jsonl", "a") as f:
            f.write(json.dumps(row) + "\n")


def pytest_unconfigure(config):
    if _OWNS_SESSION_CACHE:
        shutil.rmtree(os.environ[_SESSION_CACHE], ignore_errors=True)


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop JAX's compiled programs after each test module, so that one pytest process does
    not accumulate the executables of the whole suite (XLA's compiler crashed with a
    segmentation fault late in the suite when every module's programs were kept)."""
    yield
    jax.clear_caches()
    gc.collect()


# The slowest test files first (the per-file times recorded on a 2-core machine by
# `studies/test_times.py` in docs/results/test_times.json), so that pytest-xdist's two workers,
# which take whole files in this order (`--dist loadfile --no-loadscope-reorder` in
# pyproject.toml), finish together instead of one waiting for a long file handed out last; files
# the record does not know follow in collection order.
def _recorded_file_seconds() -> dict[str, float]:
    record = Path(__file__).resolve().parents[1] / "docs" / "results" / "test_times.json"
    try:
        doc = json.loads(record.read_text())
        (run,) = doc["files"].values()
        return {Path(f["file"]).name: float(f["seconds"]) for f in run["files"]}
    except (OSError, ValueError, KeyError, TypeError):
        return {}


def pytest_collection_modifyitems(config, items):
    if not DEFAULT_CODEGEN:  # run by tests/integration/test_default_codegen.py
        left_out = [item for item in items if item.get_closest_marker("default_codegen")]
        if left_out:
            config.hook.pytest_deselected(items=left_out)
            items[:] = [item for item in items if item not in left_out]
    seconds = _recorded_file_seconds()
    # stable: files stay whole, the unknown ones after the known ones
    items.sort(key=lambda item: -seconds.get(item.path.name, -1.0))
