import gc

import jax
import pytest

jax.config.update("jax_enable_x64", True)


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop JAX's compiled programs after each test module, so that one pytest process does
    not accumulate the executables of the whole suite (XLA's compiler crashed with a
    segmentation fault late in the suite when every module's programs were kept)."""
    yield
    jax.clear_caches()
    gc.collect()
