"""numba's on-disk cache, made safe for processes that compile the same kernel at once.

numba keeps, per function, an index (signature -> data file) and numbered data files. Its
`IndexDataCacheFile.save` reads the index, picks the first unused number, writes the index
and then the data, with nothing held between: two processes that compile two signatures
of one kernel at once (pytest's workers on an empty cache, the CLI's background warm-up
beside a notebook) can both pick number 1, and the index can end up naming a data file
the other process wrote, for the other signature. The next process then loads machine
code compiled for other argument types, and crashes.

`install` (run on import by every module that defines cached kernels) holds an exclusive
`flock` on the cache folder for the whole of each save, so that a save sees the index the
one before it wrote. Loads need no lock: each file is replaced whole (numba writes a
temporary file and renames it). Where `fcntl` is missing (Windows) nothing changes.
numba is pinned to one minor version (pyproject.toml); should its class change, the
cache is left as numba ships it.

numba keys a cached kernel on the source of its own file only: a kernel that calls (or
inlines) one from another module, and an FFI handler (ffi.py) that compiles the kernels
it runs into its own code, would load stale machine code after that other module
changed. `install` therefore stamps every kernel of this folder with the sources of all
its modules (`_folder_stamp`): a change to any of them recompiles them all.

A second flaw of numba's cache is avoided by how the kernels are written: a cached
function that calls a parallel one, compiled in a process that loaded the parallel one
from the cache, is saved broken, and the next process that loads it crashes (numba issue
#8578; tests/test_numba_cache.py repeats it). So the NumPy-facing forms of the parallel
kernels (geometry_forward, interpolate_at, put_rows, sample_forward, ...: new arrays, then
the `_into` kernel) are plain Python, not compiled.
"""

import functools
import hashlib
import os

try:
    import fcntl
except ImportError:  # not POSIX
    fcntl = None

from numba.core import caching


def _locked(save):
    @functools.wraps(save)
    def locked_save(self, key, data):
        try:
            folder = os.open(self._cache_path, os.O_RDONLY)
        except OSError:  # no folder to lock: numba's own error, if any, follows
            return save(self, key, data)
        try:
            fcntl.flock(folder, fcntl.LOCK_EX)
            return save(self, key, data)
        finally:
            os.close(folder)  # releases the lock
    locked_save.diffshade_locked = True
    return locked_save


#: folders whose kernels are stamped with all the folder's sources: this module's (the
#: host kernels'); tests add their own
FOLDERS = {os.path.dirname(os.path.abspath(__file__))}


def _folder_sources(folder):
    """(path, mtime, size) of every Python module of `folder`, sorted."""
    paths = sorted(os.path.join(folder, name) for name in os.listdir(folder)
                   if name.endswith(".py"))
    return tuple((path, os.stat(path).st_mtime, os.stat(path).st_size) for path in paths)


@functools.cache
def _digest(sources):
    """sha256 of the modules' names and contents (sources: _folder_sources())."""
    hasher = hashlib.sha256()
    for path, _, _ in sources:
        with open(path, "rb") as file:
            hasher.update(os.path.basename(path).encode() + b"\0" + file.read() + b"\0")
    return hasher.digest()


def _folder_stamp(stamp):
    """Wrap numba's get_source_stamp: for a kernel of one of FOLDERS, the digest of all
    that folder's modules (else numba's own stamp, of the kernel's file)."""
    @functools.wraps(stamp)
    def folder_stamp(self):
        path = getattr(self, "_py_file", None)
        folder = os.path.dirname(os.path.abspath(path)) if path else None
        if folder not in FOLDERS:
            return stamp(self)
        return _digest(_folder_sources(folder))
    folder_stamp.diffshade_folder = True
    return folder_stamp


def install():
    """Wrap numba's cache saves in the folder's lock, and stamp this folder's kernels with
    all its sources (once per process)."""
    mixin = getattr(caching, "_SourceFileBackedLocatorMixin", None)
    stamp = getattr(mixin, "get_source_stamp", None)
    if stamp is not None and not getattr(stamp, "diffshade_folder", False):
        mixin.get_source_stamp = _folder_stamp(stamp)
    cls = getattr(caching, "IndexDataCacheFile", None)
    save = getattr(cls, "save", None)
    if (fcntl is None or save is None or getattr(save, "diffshade_locked", False)
            or not hasattr(cls, "_load_index")):
        return
    cls.save = _locked(save)


install()
