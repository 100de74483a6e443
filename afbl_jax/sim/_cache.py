"""A persistent cache of XLA's compiled programs: a command run again loads its programs
instead of compiling them."""

from __future__ import annotations

import os
from pathlib import Path

CACHE_ENV_VAR = "AFBL_COMPILATION_CACHE"
"""Environment variable: the cache folder `configure_compilation_cache` uses, or ``off`` (also
``0``, ``none``, ``false``, ``no``) for no cache."""

_OFF = frozenset({"off", "0", "none", "false", "no", ""})


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/afbl-jax/xla`` (``~/.cache/afbl-jax/xla`` when it is unset)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "afbl-jax" / "xla"


def configure_compilation_cache(path: str | os.PathLike | None = None) -> Path | None:
    """Keep XLA's compiled programs in ``path`` (JAX's persistent compilation cache), so that a
    later process with the same programs (same code, shapes, tolerances, devices, JAX version)
    loads them instead of compiling them again.

    ``path`` None: ``$AFBL_COMPILATION_CACHE``, else `default_cache_dir`. The ``afbl`` command
    calls this at start-up. Every program is written, however fast it compiled (a study
    compiles over a hundred programs, most of them in well under JAX's default threshold of
    1 s, which together take longer to compile than to load), unless
    ``JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS`` sets a threshold; entries are a few
    hundred kB at most, nothing is evicted, so delete the folder to clear it. Programs that
    call back into Python are never cached, by JAX's rule: `simulate`'s are not (diffrax
    checks its save times with a host callback). A cached program is the same executable, so
    the numbers are bitwise the same as after compiling.

    Does nothing and returns None when ``$AFBL_COMPILATION_CACHE`` is ``off`` (or ``0``,
    ``none``, ``false``, ``no``) and ``path`` is None, or when JAX already has a cache folder
    (``JAX_COMPILATION_CACHE_DIR`` or ``jax.config``); returns the folder in use otherwise.

    Also keeps the compiled executables of the large programs (`CachedJit`: the batched
    solves, `simulate`, the Monte-Carlo sampler) in the folder's `EXECUTABLES_SUBFOLDER`, so
    that a later process loads them without tracing (`set_executable_cache`).

    Raises:
        OSError: the folder cannot be created.
    """
    import jax

    from ._executables import EXECUTABLES_SUBFOLDER, set_executable_cache

    if jax.config.jax_compilation_cache_dir:
        return None
    if path is None:
        env = os.environ.get(CACHE_ENV_VAR)
        if env is not None and env.strip().lower() in _OFF:
            return None
        path = env if env is not None else default_cache_dir()
    folder = Path(path).expanduser()
    folder.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(folder))
    set_executable_cache(folder / EXECUTABLES_SUBFOLDER)
    if "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS" not in os.environ:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    return folder
