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
fitting starts it afresh; the other folders are removed).

While another process compiles into the caches (synth's background compilation of the
fit that follows it, fitting.precompile), a program missing from either one is waited for
until that process has written it or is done (diffshade.io.xla_cache.await_producer),
rather than compiled a second time alongside.

What is read from the cache is run, so it is held to the rules ssh holds ~/.ssh to
(diffshade.io.private_files; docs/cli.md, "Time to first result", Trust):
- the folders are created with mode 0700; the cache directory, `programs` and its folder
  of this environment's programs, and every entry, must be this user's and not writable
  by group or others, else they are refused with a warning and the programs compile
  normally (for JAX's cache where diffshade configures it: diffshade.io.xla_cache);
- an entry is JSON and XLA's executable, never pickle (diffshade.io.program_entries): its
  full key is compared with the key of the call; an entry over its size limit is refused
  before it is read; one of another key (renamed or copied), or damaged, or whose program
  fails on its first call, is removed and the program compiled again.
"""

import functools
import hashlib
import inspect
import os
import platform
import sys

import jax
import numpy as np

from diffshade.io import xla_cache
from diffshade.io.private_files import Untrusted, private_folder, warn_once
from diffshade.io.program_entries import PLAIN, read_entry, remove, write_entry

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


def _private(path) -> bool:
    """Whether `path` is a private folder (created so when missing); warns if not."""
    try:
        private_folder(path)
        return True
    except Untrusted as err:
        warn_once(f"{err}; the compilation cache there is not used, programs compile "
                  "normally")
    except OSError as err:
        warn_once(f"cache folder {path!r}: {err.strerror}; the compilation cache is not "
                  "used, programs compile normally")
    return False


def enable() -> str | None:
    """Turn the persistent compilation cache on (before the first compilation); returns its
    directory, or None when DIFFSHADE_COMPILE_CACHE=0 switched it off or the folder is
    not private (a warning says why)."""
    global _store
    if os.environ.get(ENV_SWITCH, "1").strip().lower() in ("0", "false", "no", "off"):
        return None
    user_set = jax.config.jax_compilation_cache_dir
    path = user_set or cache_dir()
    if not _private(path):
        _store = None  # a folder set for JAX stays JAX's: its cache is as the user set it
        return user_set or None
    if not user_set:
        xla_cache.guard(path)
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
    device, the host CPU, XLA_FLAGS and DIFFSHADE_KERNELS (what kernels="auto" means: a
    first run's programs are built for the JAX kernels; computed once per process; the JAX
    settings that can change within a process are each call's: _jax_settings)."""
    global _environment
    if _environment is None:
        import jaxlib

        digest = hashlib.sha256()
        for path, text in _package_sources():
            digest.update(path.encode() + b"\0" + hashlib.sha256(text).digest())
        device = jax.devices()[0]
        settings = [sys.version, jax.__version__, jaxlib.__version__, jax.default_backend(),
                    device.platform, device.device_kind, device.client.platform_version,
                    platform.machine(), _cpu_identity(), os.environ.get("XLA_FLAGS", ""),
                    os.environ.get("DIFFSHADE_KERNELS", "")]
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


def _storable(compiled) -> bool:
    """Whether an executable can be loaded in another process: not when XLA's program
    has custom calls (LAPACK's, for a matrix inverse, and the like): on CPU the
    serialized executable holds the addresses of their kernels in this process, and
    calling it in another crashes."""
    try:
        return "custom-call" not in compiled.as_text()
    except Exception:
        return False


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
        self.unproven = {}  # memo -> its entry's path, for a loaded program not yet run
        functools.update_wrapper(self, fun)

    def lower(self, *args, **kwargs):
        return self.jitted.lower(*args, **kwargs)

    def clear_cache(self):
        self.loaded.clear()
        self.unproven.clear()
        self.jitted.clear_cache()

    def __call__(self, *args, **kwargs):
        if _store is None:
            return self.jitted(*args, **kwargs)
        memo, dynamic = self._program(args, kwargs)
        compiled = None if memo is None else self.loaded[memo]
        if compiled is None:
            return self.jitted(*args, **kwargs)
        if memo not in self.unproven:
            return compiled(**dynamic)
        try:  # a program loaded from the store, on its first call
            out = compiled(**dynamic)
        except Exception:  # whatever the entry holds, it is not this call's program
            remove(self.unproven.pop(memo))
            self.loaded[memo] = None
            return self.jitted(*args, **kwargs)
        self.unproven.pop(memo)
        return out

    def _program(self, args, kwargs):
        """(memo, dynamic keyword arguments): self.loaded[memo] is the call's Compiled
        program, or None for jit's; (None, None) when the store does not keep the call."""
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
        return memo, dynamic

    def key(self, memo):
        """The full key of a call's program (JSON-ready): environment_key() and the
        description of the call (class docstring); None for one that cannot be keyed."""
        tree, signatures, static, settings = memo
        described = repr((self.name, str(tree), signatures, static, settings,
                          self.compiler_options))
        return None if _has_address(described) else [environment_key(), described]

    def _load_or_compile(self, memo, arguments, device):
        key = self.key(memo)
        if key is None:
            return None
        name = hashlib.sha256(key[1].encode()).hexdigest()
        path = os.path.join(_store, key[0], f"{name}.bin")
        xla_cache.await_entry(path)  # where another process is compiling it now
        entry = read_entry(path, key, memo[0], device)
        if entry is PLAIN:
            return None
        if entry is not None:
            self.unproven[memo] = path
            return entry
        lowered = self.jitted.lower(**arguments)
        if _has_host_callbacks(lowered) or "custom_call" in lowered.as_text():
            write_entry(path, key, None, device)  # this and later processes go to jit
            return None
        compiled = _fresh_compile(lowered)
        write_entry(path, key, compiled if _storable(compiled) else None, device)
        return compiled


def stored_jit(fun=None, *, static_argnames=(), compiler_options=None):
    """Decorator: StoredProgram(fun, static_argnames, compiler_options), like
    `functools.partial(jax.jit, static_argnames=..., compiler_options=...)`."""
    if fun is None:
        return functools.partial(stored_jit, static_argnames=static_argnames,
                                 compiler_options=compiler_options)
    return StoredProgram(fun, static_argnames, compiler_options)
