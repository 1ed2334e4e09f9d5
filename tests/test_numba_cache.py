"""numba's cache under processes that save at once (diffshade/host/numba_cache.py): every
signature saved stays in the index, and names the data saved for it."""

import multiprocessing

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
