"""JAX's persistent compilation cache for the command line: `enable()`, called once at start.

A fresh `diffshade fit` spends most of its first seconds compiling; with the cache a
second run loads the compiled programs from disk instead (docs/cli.md, "Time to first
result"; benchmarks/time_to_first_result.py measures both). The cache is on by default
for the `diffshade` command and off for library use (a library does not write into the
user's home behind their back):

- DIFFSHADE_COMPILE_CACHE=0 turns it off;
- DIFFSHADE_COMPILE_CACHE_DIR=PATH puts it elsewhere; the default is
  $XDG_CACHE_HOME/diffshade/jax, else ~/.cache/diffshade/jax;
- a cache directory already configured for JAX (JAX_COMPILATION_CACHE_DIR or
  jax.config) is left as it is.

Every program is cached however quickly it compiled (JAX's default skips those that
compile in under 1 s, as most of a fit's programs do). JAX never caches a program that
contains a host callback; on CPU diffshade's compiled kernels are XLA FFI custom calls
(diffshade.host.ffi), which it does cache (with DIFFSHADE_FFI=0 they are host callbacks, and
the programs that rasterize are compiled afresh in every process).

JAX computes a program's cache key from its lowered module, so even a warm run traces
and lowers every program, which is not quick for a fit's biggest. The program store
skips that for the few big programs of a fit (`stored_jit` marks them): with the cache
on, their compiled executables are also kept whole in the folder `programs` of the
cache directory, keyed by a hash of the package's source, JAX, the backend, the CPU and
the arguments' shapes (StoredProgram), and a later process loads them without tracing.
The store keeps the programs of the current source only (an edit of diffshade or
fitting starts it afresh; the other folders are removed). Like JAX's cache, an entry is
an executable loaded by pickle: keep the cache directory private to its user.
"""

import contextlib
import functools
import hashlib
import inspect
import os
import pickle
import platform
import shutil
import sys
import tempfile

import jax
import numpy as np

__all__ = ["FAST_COMPILE", "LIGHT_COMPILE", "StoredProgram", "cache_dir", "enable",
           "environment_key", "store_dir", "stored_jit"]

ENV_SWITCH = "DIFFSHADE_COMPILE_CACHE"
ENV_DIR = "DIFFSHADE_COMPILE_CACHE_DIR"


def cache_dir() -> str:
    """Where the cache goes: DIFFSHADE_COMPILE_CACHE_DIR, else the user's cache folder."""
    if os.environ.get(ENV_DIR):
        return os.path.expanduser(os.environ[ENV_DIR])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "diffshade", "jax")


def enable() -> str | None:
    """Turn the persistent compilation cache on (before the first compilation); returns its
    directory, or None when DIFFSHADE_COMPILE_CACHE=0 switched it off."""
    global _store
    if os.environ.get(ENV_SWITCH, "1").strip().lower() in ("0", "false", "no", "off"):
        return None
    if jax.config.jax_compilation_cache_dir:
        path = jax.config.jax_compilation_cache_dir
    else:
        path = cache_dir()
        jax.config.update("jax_compilation_cache_dir", path)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    _store = os.path.join(path, STORE_FOLDER)
    return path


# ---- the program store: compiled programs kept whole, skipping tracing and lowering ----

# XLA options for a program that runs once or a few times on small data: without LLVM's
# optimizations it compiles in about half the CPU time, and runs about as fast where
# the work is small (rasterizing a view's geometry once, the report's renders); not for
# programs a fit calls many times (fitting.solve.linear.view_parts, normal_system: there it
# runs several times slower). XLA's HLO passes still run; no fast-math either way, so
# values change by float rounding at most. benchmarks/fit_compile.py measures it
# (docs/performance.md, "Time to first result and compile time").
FAST_COMPILE = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}
# For the programs a fit calls many times: LLVM's -O1 instead of XLA's default -O2 compiles
# them faster, and they ran as fast in the README's fit.
LIGHT_COMPILE = {"xla_backend_optimization_level": 1}

STORE_FOLDER = "programs"
_MAGIC = b"diffshade-program 1\n"
_PLAIN = b"plain jit"  # an entry's content for a program that is not stored: call jit
_store = None  # the store's folder while enable() has it on; None: every call goes to jit
_environment = None  # (hash of what every stored program depends on, its folder name)


def store_dir() -> str | None:
    """The program store's folder (STORE_FOLDER inside the cache directory), or None while
    it is off (library use, or DIFFSHADE_COMPILE_CACHE=0)."""
    return _store


def _package_sources():
    """(relative path, bytes) of every .py file of diffshade and fitting, sorted."""
    # this file is diffshade/io/compile_cache.py: the root holds diffshade/ and fitting/
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    found = []
    for package in ("diffshade", "fitting"):
        folder = os.path.join(root, package)
        for dirpath, dirnames, names in os.walk(folder):
            dirnames[:] = sorted(d for d in dirnames if d != "__pycache__")
            for name in sorted(names):
                if name.endswith(".py"):
                    path = os.path.join(dirpath, name)
                    with open(path, "rb") as f:
                        found.append((os.path.relpath(path, root), f.read()))
    return sorted(found)


def _cpu_identity() -> str:
    """The host CPU's model and feature flags (XLA compiles for the CPU it runs on)."""
    try:
        with open("/proc/cpuinfo") as f:
            lines = [line for line in f.read().splitlines()
                     if line.startswith(("model name", "flags", "Features", "CPU part"))]
        return "\n".join(sorted(set(lines)))
    except OSError:
        return platform.processor()


def environment_key() -> str:
    """Hash of everything a stored program depends on besides its own arguments: the
    source of diffshade and fitting, the Python, JAX and jaxlib versions, the backend, its
    device, the host CPU and XLA_FLAGS (computed once per process; the JAX settings that
    can change within a process are each call's: _jax_settings)."""
    global _environment
    if _environment is None:
        import jaxlib

        digest = hashlib.sha256()
        for path, text in _package_sources():
            digest.update(path.encode() + b"\0" + hashlib.sha256(text).digest())
        device = jax.devices()[0]
        settings = [sys.version, jax.__version__, jaxlib.__version__, jax.default_backend(),
                    device.platform, device.device_kind, device.client.platform_version,
                    platform.machine(), _cpu_identity(), os.environ.get("XLA_FLAGS", "")]
        digest.update(repr(settings).encode())
        _environment = digest.hexdigest()
    return _environment


_SETTINGS = ("jax_enable_x64", "jax_default_matmul_precision", "jax_default_prng_impl",
             "jax_threefry_partitionable", "jax_numpy_dtype_promotion")


def _jax_settings():
    """The JAX settings in force (jax.enable_x64 and the like change them for a block of
    code) that change the program compiled for the same arguments."""
    return tuple(repr(getattr(jax.config, name, None)) for name in _SETTINGS)


def _leaf_signature(leaf, device):
    """(shape, dtype, weak) of an argument leaf, or None for one the store does not keep a
    program for (a tracer: the call is inside another trace; an array on another device
    or sharded; an unusual leaf type)."""
    if isinstance(leaf, jax.core.Tracer):
        return None
    if isinstance(leaf, jax.Array):
        if leaf.sharding.device_set != {device}:
            return None
        return leaf.shape, str(leaf.dtype), bool(leaf.weak_type)
    if isinstance(leaf, np.ndarray | np.generic):
        return leaf.shape, str(leaf.dtype), False
    if type(leaf) in (bool, int, float, complex):
        return (), type(leaf).__name__, True
    return None


def _has_address(text: str) -> bool:
    """A repr that names an object's memory address differs between processes."""
    return " at 0x" in text


def _has_host_callbacks(lowered) -> bool:
    """Whether a lowered program calls back into Python (jax.pure_callback ...): such an
    executable holds pointers into this process and must not be stored (JAX's cache
    refuses it too). Unknown (another JAX's internals): True."""
    try:
        return bool(lowered._lowering.compile_args["host_callbacks"])
    except (AttributeError, KeyError, TypeError):
        return True


def _fresh_compile(lowered):
    """lowered.compile() with JAX's persistent cache bypassed: an executable that JAX's
    cache loaded cannot be serialized again on CPU (its object code is left behind)."""
    from jax.experimental.compilation_cache import compilation_cache

    was = jax.config.jax_enable_compilation_cache
    compilation_cache.reset_cache()
    jax.config.update("jax_enable_compilation_cache", False)
    try:
        return lowered.compile()
    finally:
        jax.config.update("jax_enable_compilation_cache", was)
        compilation_cache.reset_cache()


def _read_entry(path, in_tree, device):
    """The Compiled program stored at path, or None when there is none or it cannot be
    used (a damaged file is removed, to be written anew)."""
    from jax.experimental import serialize_executable

    try:
        with open(path, "rb") as f:
            blob = f.read()
    except OSError:
        return None
    try:
        head, digest, payload = blob[:len(_MAGIC)], blob[len(_MAGIC):len(_MAGIC) + 64], \
            blob[len(_MAGIC) + 65:]
        if head != _MAGIC or hashlib.sha256(payload).hexdigest().encode() != digest:
            raise ValueError("damaged entry")
        if payload == _PLAIN:
            return _PLAIN
        executable, out_tree = pickle.loads(payload)
        return serialize_executable.deserialize_and_load(
            executable, in_tree, out_tree, execution_devices=[device])
    except Exception:  # any damage: compile afresh and write the entry again
        with contextlib.suppress(OSError):
            os.remove(path)
        return None


def _storable(compiled) -> bool:
    """Whether an executable can be loaded in another process: not when XLA's program
    has custom calls (LAPACK's, for a matrix inverse, and the like): on CPU the
    serialized executable holds the addresses of their kernels in this process, and
    calling it in another crashes."""
    try:
        return "custom-call" not in compiled.as_text()
    except Exception:
        return False


def _write_entry(path, compiled):
    """Serialize `compiled` (None: write the _PLAIN marker) to path atomically (a
    temporary file, then os.replace); programs that cannot be serialized, and a full or
    read-only disk, are skipped."""
    from jax.experimental import serialize_executable

    try:
        if compiled is None:
            payload = _PLAIN
        else:
            executable, _, out_tree = serialize_executable.serialize(compiled)
            payload = pickle.dumps((executable, out_tree), protocol=pickle.HIGHEST_PROTOCOL)
    except Exception:
        return
    folder = os.path.dirname(path)
    try:
        fresh = not os.path.isdir(folder)
        os.makedirs(folder, exist_ok=True)
        if fresh:  # programs of other sources or versions are never read again
            store = os.path.dirname(folder)
            for name in os.listdir(store):
                other = os.path.join(store, name)
                if other != folder and len(name) == 64 and os.path.isdir(other):
                    shutil.rmtree(other, ignore_errors=True)
        handle, temporary = tempfile.mkstemp(dir=folder, suffix=".tmp")
        with os.fdopen(handle, "wb") as f:
            f.write(_MAGIC + hashlib.sha256(payload).hexdigest().encode() + b"\n" + payload)
        os.replace(temporary, path)
    except OSError:
        with contextlib.suppress(OSError, UnboundLocalError):
            os.remove(temporary)


class StoredProgram:
    """`jax.jit(fun, static_argnames=...)` whose compiled programs are also kept in the
    program store while the command line has it on (enable()): a later process loads a
    program whole, skipping the tracing and lowering that JAX's persistent cache needs to
    compute its key. Off (library use), or for a call it does not keep (inside another
    trace, on another device, a leaf it does not know, a program with host callbacks or
    custom calls: their entry only says so), a call is the jitted function's.

    The key of a program: environment_key() (the package's source, JAX, the backend, the
    CPU ...), the JAX settings in force (x64 ...), the function's module and name, its
    static arguments (repr), the structure, shapes and dtypes of its other arguments, and
    its XLA compiler_options (jax.jit's: they reach both jit and the store's compile, as
    the lowered program carries them; FAST_COMPILE and LIGHT_COMPILE are the fit's).
    Every argument must have a name (no *args or **kwargs): calls are made by keyword."""

    def __init__(self, fun, static_argnames=(), compiler_options=None):
        self.compiler_options = tuple(sorted((compiler_options or {}).items()))
        self.jitted = jax.jit(fun, static_argnames=static_argnames,
                              compiler_options=dict(self.compiler_options) or None)
        self.static_argnames = tuple(static_argnames)
        self.signature = inspect.signature(fun)
        if any(p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
               for p in self.signature.parameters.values()):
            raise TypeError(f"{fun.__qualname__}: *args and **kwargs cannot be stored")
        self.name = f"{fun.__module__}.{fun.__qualname__}"
        self.loaded = {}  # (tree, signatures, static, settings) -> Compiled, this process
        functools.update_wrapper(self, fun)

    def lower(self, *args, **kwargs):
        return self.jitted.lower(*args, **kwargs)

    def clear_cache(self):
        self.loaded.clear()
        self.jitted.clear_cache()

    def __call__(self, *args, **kwargs):
        if _store is None:
            return self.jitted(*args, **kwargs)
        compiled, dynamic = self._program(args, kwargs)
        if compiled is None:
            return self.jitted(*args, **kwargs)
        return compiled(**dynamic)

    def _program(self, args, kwargs):
        """(Compiled, dynamic keyword arguments), or (None, None) when not kept."""
        try:
            bound = self.signature.bind(*args, **kwargs)
        except TypeError:
            return None, None  # jit raises its own error
        bound.apply_defaults()
        static = tuple((n, bound.arguments[n]) for n in self.static_argnames)
        dynamic = {n: v for n, v in bound.arguments.items() if n not in self.static_argnames}
        leaves, tree = jax.tree.flatten(((), dynamic))
        device = jax.devices()[0]
        signatures = tuple(_leaf_signature(leaf, device) for leaf in leaves)
        if None in signatures:
            return None, None
        memo = (tree, signatures, static, _jax_settings())
        try:
            known = memo in self.loaded
        except TypeError:  # an unhashable static argument: jit will say so
            return None, None
        if not known:  # None: not kept (jit's own program)
            self.loaded[memo] = self._load_or_compile(memo, bound.arguments, device)
        compiled = self.loaded[memo]
        return (None, None) if compiled is None else (compiled, dynamic)

    def _load_or_compile(self, memo, arguments, device):
        tree, signatures, static, settings = memo
        described = repr((self.name, str(tree), signatures, static, settings,
                          self.compiler_options))
        if _has_address(described):
            return None
        key = hashlib.sha256(described.encode()).hexdigest()
        path = os.path.join(_store, environment_key(), f"{key}.bin")
        entry = _read_entry(path, tree, device)
        if entry is _PLAIN:
            return None
        if entry is not None:
            return entry
        lowered = self.jitted.lower(**arguments)
        if _has_host_callbacks(lowered) or "custom_call" in lowered.as_text():
            _write_entry(path, None)  # this and later processes go straight to jit
            return None
        compiled = _fresh_compile(lowered)
        _write_entry(path, compiled if _storable(compiled) else None)
        return compiled


def stored_jit(fun=None, *, static_argnames=(), compiler_options=None):
    """Decorator: StoredProgram(fun, static_argnames, compiler_options), like
    `functools.partial(jax.jit, static_argnames=..., compiler_options=...)`."""
    if fun is None:
        return functools.partial(stored_jit, static_argnames=static_argnames,
                                 compiler_options=compiler_options)
    return StoredProgram(fun, static_argnames, compiler_options)
