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
# slower), in this process and, through the environment, in its subprocesses.
TEST_XLA_FLAGS = "--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true"
if TEST_XLA_FLAGS not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {TEST_XLA_FLAGS}".strip()

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
    seconds = _recorded_file_seconds()
    # stable: files stay whole, the unknown ones after the known ones
    items.sort(key=lambda item: -seconds.get(item.path.name, -1.0))
