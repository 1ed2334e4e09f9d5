"""numba's cache under processes that save at once (diffshade/host/numba_cache.py): every
signature saved stays in the index, and names the data saved for it."""

import multiprocessing
import os
import subprocess
import sys

from numba.core import caching

from diffshade.host import numba_cache

PROCESSES, SAVES = 4, 40
STAMP = (1.0, 100)


def _saver(folder, worker, start):
    start.wait()
    cache = caching.IndexDataCacheFile(folder, "kernel-12.py311", STAMP)
    for i in range(SAVES):
        cache.save(("signature", worker, i), ("code", worker, i))


def test_saves_at_once_keep_each_signature_with_its_own_data(tmp_path):
    assert getattr(caching.IndexDataCacheFile.save, "diffshade_locked", False)
    numba_cache.install()  # again: a no-op, not a second lock around the first
    assert not getattr(caching.IndexDataCacheFile.save.__wrapped__, "diffshade_locked", False)
    context = multiprocessing.get_context("spawn")  # no fork of a process running JAX
    start = context.Event()
    workers = [context.Process(target=_saver, args=(str(tmp_path), w, start))
               for w in range(PROCESSES)]
    for worker in workers:
        worker.start()
    start.set()
    for worker in workers:
        worker.join(60)
        assert worker.exitcode == 0
    cache = caching.IndexDataCacheFile(str(tmp_path), "kernel-12.py311", STAMP)
    index = cache._load_index()
    keys = {("signature", w, i) for w in range(PROCESSES) for i in range(SAVES)}
    assert set(index) == keys  # no save lost
    assert len(set(index.values())) == len(keys)  # one data file each
    for key in keys:
        assert cache.load(key) == ("code",) + key[1:]


_CALL = """
import sys
import numpy as np
from diffshade.host import fragment_kernels as kernels
rng = np.random.default_rng(3)
ids = rng.integers(-1, 7, 300).astype(np.int32)
bary, corners = rng.uniform(size=(300, 3)), rng.normal(size=(7, 3, 4))
rows = rng.integers(0, 310, 500).astype(np.int32)
if sys.argv[1] == "into":
    out = np.empty((500, 4))
    kernels.interpolate_at_into(rows, ids, bary, corners, 2, out)
else:
    out = kernels.interpolate_at(rows, ids, bary, corners, 2)
want = np.array([bary[r] @ corners[ids[r]] if r < 300 and ids[r] >= 0 else np.zeros(4)
                 for r in rows])
assert np.allclose(out, want, rtol=1e-12, atol=1e-12)
"""


def test_a_kernel_first_called_in_another_process_still_loads(tmp_path):
    """The parallel interpolate_at_into compiled and cached by one process; its NumPy form
    then called in a second process (which loads the kernel from the cache) and in a
    third: each runs and gives the loop's values. With the NumPy form compiled and cached
    too, the third process crashed (numba issue #8578)."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    for form in ("into", "wrapper", "wrapper"):
        run = subprocess.run([sys.executable, "-c", _CALL, form], env=env,
                             capture_output=True, text=True, timeout=300)
        assert run.returncode == 0, (form, run.stderr[-2000:])


_CALLER = """
import sys
sys.path.insert(0, sys.argv[1])
from diffshade.host import numba_cache
if sys.argv[2] == "stamped":
    numba_cache.FOLDERS.add(sys.argv[1])
import caller
print(caller.twice())
"""


def _write_kernels(folder, value):
    (folder / "callee.py").write_text(
        f"import numba\n\n\n@numba.njit(cache=True)\ndef value():\n    return {value}\n")
    (folder / "caller.py").write_text(
        "import numba\n\nfrom callee import value\n\n\n@numba.njit(cache=True)\n"
        "def twice():\n    return 2 * value()\n")


def test_a_kernel_recompiles_when_another_module_of_its_folder_changes(tmp_path):
    """A cached kernel (caller.twice) that compiles in one from another module of its
    folder (callee.value): after callee.py changes, a new process must not load the
    caller's stale code. With the folder stamped (numba_cache.FOLDERS, as the host
    kernels' folder is) it gives the new value; with numba's own stamp (the caller's file
    only) it still gives the old one, which shows the test can tell them apart."""
    assert getattr(caching._SourceFileBackedLocatorMixin.get_source_stamp,
                   "diffshade_folder", False)
    for mode, after in (("stamped", 14), ("numba's", 6)):
        folder = tmp_path / mode.strip("'")
        folder.mkdir()
        env = dict(os.environ, NUMBA_CACHE_DIR=str(folder / "cache"))
        outputs = []
        for value in (3, 7):
            _write_kernels(folder, value)
            run = subprocess.run([sys.executable, "-c", _CALLER, str(folder), mode], env=env,
                                 capture_output=True, text=True, timeout=300)
            assert run.returncode == 0, run.stderr[-2000:]
            outputs.append(int(run.stdout.split()[-1]))
        assert outputs == [6, after], (mode, outputs)
