"""JAX's persistent compilation cache held to the program store's rules, in the folder
diffshade configures for it (diffshade.io.compile_cache.enable; a folder the user set for
JAX is JAX's own business and left as it is).

JAX's file cache (jax._src.lru_cache) writes entries with the user's umask and loads
whatever file bears a key's name. `guard(folder)` makes JAX use `PrivateCache` for that
folder instead:

- an entry is written atomically with mode 0600 and starts with its full key, which is
  compared on load: an entry renamed or copied onto another key's name is removed and the
  program compiled again;
- an entry that is not this user's plain file, or is writable by group or others, is
  refused with a warning (diffshade.io.private_files); one over MAX_ENTRY_BYTES, or
  damaged, is removed before it is read; either way the program compiles normally.

JAX's entries hold XLA executables only (no pickle): XLA's deserializer reads them.

While another process compiles into the caches (a fit's background precompile,
fitting.precompile: `await_producer`), an entry missing from either cache, JAX's or the
program store (diffshade.io.compile_cache), is waited for (`await_entry`) rather than
compiled a second time alongside; once that process is done, or the caller gives up on
it, a missing program compiles as before.
"""

import contextlib
import os
import pathlib
import time

from jax._src import compilation_cache
from jax._src.compilation_cache_interface import CacheInterface

from diffshade.io.private_files import (
    MAX_ENTRY_BYTES,
    read_cached,
    write_private,
)

__all__ = ["PrivateCache", "await_entry", "await_producer", "guard"]

MAGIC = b"diffshade-xla-cache 1\n"
SUFFIX = ".xla"
_guarded = set()  # the folders whose JAX cache is a PrivateCache
#: how often a missing entry is looked for while a producer compiles, in seconds
POLL = 0.02
_producer = None  # busy() -> bool while another process compiles into the caches


def await_producer(busy):
    """From now on, until `busy()` returns False (then never asked again), a program
    missing from the caches is waited for: another process is compiling it into them.
    None: stop waiting."""
    global _producer
    _producer = busy


def await_entry(path):
    """Return once the cache entry `path` exists, or at once where no producer is busy
    (await_producer)."""
    global _producer
    while _producer is not None and not os.path.exists(path):
        if not _producer():
            _producer = None
            return
        time.sleep(POLL)


class PrivateCache(CacheInterface):
    """A JAX compilation cache (get/put by key) in a private folder (module docstring)."""

    def __init__(self, path):
        self._path = pathlib.Path(path)

    def _file(self, key):
        if not key or "/" in key or key.startswith(".") or "\n" in key:
            return None  # JAX's keys are file names; anything else is not kept
        return self._path / f"{key}{SUFFIX}"

    def get(self, key):
        path = self._file(key)
        if path is not None:
            await_entry(path)
        blob = None if path is None else read_cached(path, MAX_ENTRY_BYTES)
        if blob is None:
            return None
        head = MAGIC + key.encode() + b"\n"
        if blob.startswith(head):
            return blob[len(head):]
        with contextlib.suppress(OSError):  # another key's entry, or damaged
            os.remove(path)
        return None

    def put(self, key, value):
        path = self._file(key)
        data = MAGIC + key.encode() + b"\n" + value
        if path is None or len(data) > MAX_ENTRY_BYTES:
            return
        with contextlib.suppress(OSError):  # a full or read-only disk: not cached
            write_private(path, data)


def _get_file_cache(path):
    if os.path.abspath(path) in _guarded:
        return PrivateCache(path), path
    return _jax_file_cache(path)


_jax_file_cache = compilation_cache.get_file_cache


def guard(folder):
    """From now on JAX's cache in `folder` is a PrivateCache (before its first use)."""
    _guarded.add(os.path.abspath(folder))
    compilation_cache.get_file_cache = _get_file_cache
