import gc
import os

import jax
import pytest

jax.config.update("jax_enable_x64", True)
# JAX's default devices (one on a CPU) in every test process, whichever test runs first: an
# in-process `afbl` command that happened to start JAX would give each core its own device
# (`configure_cpu_devices`) for every later test of that worker; several devices are tested in
# subprocesses
jax.devices()
# the compilation counts of the tests need real compilations, not loads from a cache
os.environ["AFBL_COMPILATION_CACHE"] = "off"


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop JAX's compiled programs after each test module, so that one pytest process does
    not accumulate the executables of the whole suite (XLA's compiler crashed with a
    segmentation fault late in the suite when every module's programs were kept)."""
    yield
    jax.clear_caches()
    gc.collect()


# The slowest test files first (measured per-file times on a 2-core machine, slowest first), so
# that pytest-xdist's two workers, which take whole files in this order (`--dist loadfile
# --no-loadscope-reorder` in pyproject.toml), finish together instead of one waiting for a long
# file handed out last; the other files follow in collection order.
SLOWEST_FILES = (
    "test_notebooks.py",
    "test_montecarlo.py",
    "test_studies.py",
    "test_tuning.py",
    "test_lean.py",
    "test_simulate.py",
    "test_reliability_cli.py",
    "test_batch.py",
    "test_montecarlo_unmodeled.py",
    "test_unmodeled.py",
    "test_rare.py",
    "test_reliability.py",
    "test_cli.py",
)


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(SLOWEST_FILES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: files stay whole
