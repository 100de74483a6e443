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
