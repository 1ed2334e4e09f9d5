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

Every program is cached however quickly it compiled (JAX's default skips those under 1 s,
and most of a fit's programs compile in 0.1-1 s each). JAX never caches a program that
contains a host callback: on CPU, rasterization runs diffshade's compiled kernels through
`jax.pure_callback` (diffshade.hostop), so the programs that rasterize are compiled afresh
in every process; the fit's steps, which shade cached fragments, are cached.
"""

import os

import jax

__all__ = ["cache_dir", "enable"]

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
    if os.environ.get(ENV_SWITCH, "1").strip().lower() in ("0", "false", "no", "off"):
        return None
    if jax.config.jax_compilation_cache_dir:
        return jax.config.jax_compilation_cache_dir
    path = cache_dir()
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    return path
