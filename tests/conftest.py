import gc
import os

import jax
import pytest

jax.config.update("jax_enable_x64", True)
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
