"""A folder of compiled executables keyed by the call's signature (JAX's
`jax.experimental.serialize_executable`), so that a process that makes the same call again
loads the executable instead of tracing, lowering and compiling its function.

JAX's persistent compilation cache (`configure_compilation_cache`) is keyed by the lowered
program, so a later process still traces and lowers every function before it finds the
program: for the ensemble solves that is most of a warm command's start. This cache is keyed
by what determines the traced program without tracing it:

- the source of the ``afbl_jax`` package and the versions of jax, jaxlib, diffrax, equinox,
  lineax, optimistix and numpy;
- the call: the pytree structure of the arguments, every non-array leaf (its ``repr``), and
  every array leaf's shape, dtype, weak type and placement;
- what JAX traces and compiles with: the configuration values that change tracing (64-bit
  mode, dtype and rank promotion, matmul precision, the PRNG), ``XLA_FLAGS``, the compiler
  options, the devices (platform, kind, ids) and the host's processor.

A call whose non-array leaves have no stable ``repr`` (a function or object printed with its
address), a call under a trace (inside ``jax.jit``, ``jax.grad``, ``jax.vmap``), a function
with non-array outputs, and any backend but the CPU run as plain `equinox.filter_jit`. A
program that calls back into Python (a host callback) is compiled but not kept. The kept
programs stay out of JAX's persistent cache (an executable JAX loaded from there does not
serialize whole; only the compiling thread's setting changes, so other threads' programs are
written there as usual). A file that cannot be read or loaded (another jaxlib, a truncated
write) is compiled again and replaced. Threads that make the same first call at once share one
compilation.

Runtime changes to module-level values of the package (monkeypatching) are not part of the
key, so the cache is off unless `set_executable_cache` or `configure_compilation_cache` turns
it on (the ``afbl`` command does). A loaded executable is the one compiled before, so results
are bitwise the same. Loading unpickles the file, which can run code: keep the folder as
private as the compiled programs themselves (it is the user's own cache folder by default).
"""

from __future__ import annotations

import functools
import hashlib
import importlib.metadata
import io
import os
import pickle
import platform
import re
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

import equinox as eqx
import jax
import numpy as np

try:  # JAX's setting as a per-thread context (other threads' compilations keep it)
    from jax._src.config import (
        persistent_cache_min_compile_time_secs as _min_compile_time,
    )
except ImportError:  # another jax: the global setting, one compilation at a time
    _min_compile_time = None

EXECUTABLES_SUBFOLDER = "executables"
"""Subfolder of the compilation-cache folder that holds the serialized executables."""
LOAD_EVENT = "/afbl_jax/executable_cache/load"
"""`jax.monitoring` time span of a `CachedJit` call that loaded its executable from the folder
(key, read and load) instead of compiling it."""

_CONFIG_KEYS = (
    "jax_enable_x64",
    "jax_numpy_dtype_promotion",
    "jax_numpy_rank_promotion",
    "jax_default_matmul_precision",
    "jax_default_prng_impl",
    "jax_threefry_partitionable",
    "jax_enable_checks",
    "jax_debug_nans",
    "jax_debug_infs",
    "jax_disable_jit",
)
_DISTRIBUTIONS = ("jax", "jaxlib", "diffrax", "equinox", "lineax", "optimistix", "numpy")
_ADDRESS = re.compile(r" at 0x[0-9a-fA-F]+")
_CALLBACK = re.compile(r"custom_call @\w*callback")

_state: dict[str, Path | None] = {"folder": None}


def set_executable_cache(folder: str | os.PathLike | None) -> Path | None:
    """Keep serialized executables in ``folder`` (created when first written); None: off.
    Returns the folder in use."""
    _state["folder"] = None if folder is None else Path(folder)
    return _state["folder"]


def executable_cache_folder() -> Path | None:
    """The folder `set_executable_cache` set, or None when the cache is off."""
    return _state["folder"]


@functools.cache
def _environment_digest() -> str:
    h = hashlib.sha256()
    root = Path(__file__).resolve().parents[1]
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    for name in _DISTRIBUTIONS:
        try:
            version = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            version = "-"
        h.update(f"{name}={version};".encode())
    h.update(_cpu_model().encode())
    return h.hexdigest()


def _cpu_model() -> str:
    """The first processor's model name and feature flags (XLA compiles for the host's)."""
    lines = []
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if not line.strip():
                    break
                if line.startswith(("model name", "flags")):
                    lines.append(line)
    except OSError:
        pass
    return "".join(lines) or platform.machine()


def _placement(x) -> str:
    if isinstance(x, jax.Array):
        if isinstance(x, jax.core.Tracer):
            raise TypeError("traced")
        return f"{x.sharding}|{getattr(x, 'committed', True)}"
    return "host"


def _call_key(name: str, options: dict, dyn, static) -> str | None:
    """The cache key of a call (hex), or None when the call has no stable key."""
    leaves, treedef = jax.tree.flatten(dyn)
    static_leaves, static_def = jax.tree.flatten(static)
    with np.printoptions(threshold=sys.maxsize, floatmode="unique"):  # arrays in full
        parts = [name, repr(sorted(options.items())), str(treedef), str(static_def)]
        parts += [repr(v) for v in static_leaves]
    try:
        for x in leaves:
            a = jax.typeof(x)
            parts.append(f"{a.shape}{a.dtype}{getattr(a, 'weak_type', False)}{_placement(x)}")
    except TypeError:
        return None
    text = "\n".join(parts)
    if _ADDRESS.search(text):
        return None
    devices = ",".join(f"{d.platform}:{d.device_kind}:{d.id}" for d in jax.devices())
    config = ",".join(f"{k}={getattr(jax.config, k, None)}" for k in _CONFIG_KEYS)
    env = "\n".join([_environment_digest(), devices, config, os.environ.get("XLA_FLAGS", ""), text])
    return hashlib.sha256(env.encode()).hexdigest()


def _equinox_missing():
    try:
        from equinox._module._flatten import MISSING
    except ImportError:  # another equinox: its modules' tree definitions may not round-trip
        return None
    return MISSING


class _Pickler(pickle.Pickler):
    """Pickles equinox's field sentinel as a reference to itself: a module's tree definition
    compares its static fields with the sentinel by identity, so a copy would not unflatten."""

    def reducer_override(self, obj):
        missing = _equinox_missing()
        if missing is not None and obj is missing:
            return _equinox_missing, ()
        return NotImplemented


@functools.cache
def _prepare_runtime() -> None:
    """Lower a small linear solve once: jaxlib sets up the LAPACK kernels that compiled CPU
    programs call (`jax.numpy.linalg.solve`) when it first lowers one, and a loaded program
    that calls them before that crashes."""
    jax.jit(jax.numpy.linalg.solve).lower(np.eye(2), np.ones(2))


def _load(path: Path, in_tree):
    if not path.exists():
        return None
    _prepare_runtime()
    try:
        with open(path, "rb") as f:
            payload, out_tree, device_ids = pickle.load(f)
        from jax.experimental.serialize_executable import deserialize_and_load

        by_id = {d.id: d for d in jax.devices()}
        devices = [by_id[i] for i in device_ids]
        return deserialize_and_load(payload, in_tree, out_tree, execution_devices=devices)
    except Exception:  # missing, truncated, or from another jaxlib: compile again
        return None


def _store(path: Path, compiled) -> None:
    try:
        from jax.experimental.serialize_executable import serialize

        payload, _, out_tree = serialize(compiled)
        device_ids = [d.id for d in compiled.runtime_executable().local_devices()]
        with io.BytesIO() as buffer:
            _Pickler(buffer).dump((payload, out_tree, device_ids))
            blob = buffer.getvalue()
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
        with os.fdopen(fd, "wb") as f:
            f.write(blob)
        os.replace(tmp, path)
    except Exception:  # not serializable (host callbacks) or not writable: stay uncached
        return


_hits = threading.local()
_global_setting = threading.Lock()


def _count_hit(event: str, **_) -> None:
    # JAX records the event in the thread that compiles
    if event == "/jax/compilation_cache/cache_hits":
        _hits.count = getattr(_hits, "count", 0) + 1


@functools.cache
def _listen_for_hits() -> None:
    jax.monitoring.register_event_listener(_count_hit)


def _compile_fresh(lowered):
    """(compiled, serializable): compile ``lowered`` without writing it to JAX's persistent
    cache. An executable that JAX loaded from its persistent cache serializes without its
    compiled functions (it loads, then fails to run), so the programs of this cache are kept
    out of JAX's cache (their module names are their own) and a compilation that JAX answered
    from its cache all the same is not serialized. Both hold for this thread's compilation
    only: other threads may compile (and write JAX's cache) meanwhile."""
    _listen_for_hits()
    before = getattr(_hits, "count", 0)
    if _min_compile_time is not None:
        with _min_compile_time(float("inf")):
            compiled = lowered.compile()
    else:
        with _global_setting:
            minimum = jax.config.jax_persistent_cache_min_compile_time_secs
            jax.config.update("jax_persistent_cache_min_compile_time_secs", float("inf"))
            try:
                compiled = lowered.compile()
            finally:
                jax.config.update("jax_persistent_cache_min_compile_time_secs", minimum)
    return compiled, getattr(_hits, "count", 0) == before


class CachedJit:
    """``equinox.filter_jit(fn, compiler_options=...)`` whose compiled executables are also
    kept in the folder of `set_executable_cache` (see the module docstring); with the cache
    off, on a non-CPU backend, under a trace, or for a call without a stable key, exactly
    ``filter_jit``. ``name`` names the files and the compiled module, and is part of the key.
    ``fn``'s outputs must be arrays for its executables to be kept (else ``filter_jit``)."""

    def __init__(self, fn: Callable, name: str, compiler_options: dict | None = None):
        self._fn = fn
        self._name = name
        self._options = dict(compiler_options or {})
        self._jit = eqx.filter_jit(fn, compiler_options=self._options or None)
        self._compiled: dict[str, object] = {}
        self._locks: dict[str, threading.Lock] = {}
        self._locks_lock = threading.Lock()

    def _key_lock(self, key: str) -> threading.Lock:
        with self._locks_lock:
            return self._locks.setdefault(key, threading.Lock())

    def __call__(self, *args):
        folder = executable_cache_folder()
        if folder is None or jax.default_backend() != "cpu":
            return self._jit(*args)
        dyn, static = eqx.partition(args, eqx.is_array)
        key = _call_key(self._name, self._options, dyn, static)
        if key is None:
            return self._jit(*args)
        if key not in self._compiled:
            with self._key_lock(key):  # a call from another thread compiles it once
                if key not in self._compiled:
                    path = folder / f"{self._name}-{key[:40]}.exe"
                    start = time.time()
                    compiled = _load(path, jax.tree.structure(((dyn,), {})))
                    if compiled is not None:
                        jax.monitoring.record_event_time_span(LOAD_EVENT, start, time.time())
                    self._compiled[key] = compiled or self._compile(path, dyn, static)
        compiled = self._compiled[key]
        return self._jit(*args) if compiled is None else compiled(dyn)

    def _compile(self, path: Path, dyn, static):
        """Compile the call (None: it cannot be compiled as a plain ``jax.jit`` of its arrays)
        and keep the executable in ``path`` where it can be serialized."""
        fn = self._fn

        def flat(d):
            return fn(*eqx.combine(d, static))

        flat.__name__ = f"{self._name}_executable"  # the compiled module's name
        try:
            lowered = jax.jit(flat, compiler_options=self._options or None).lower(dyn)
        except TypeError:  # non-array outputs: filter_jit handles them
            return None
        if _CALLBACK.search(lowered.as_text()):  # calls back into this process: not kept
            return lowered.compile()
        compiled, serializable = _compile_fresh(lowered)
        if serializable:
            _store(path, compiled)
        return compiled
