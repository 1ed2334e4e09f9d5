"""`diffshade synth` compiles, on a second core, the programs of the fit that follows it.

The README's first line is `diffshade synth -o out/data && diffshade fit out/data -o
out/fit`. On a fresh install both commands spend most of their time compiling, one
program after another on one core. But what the fit compiles depends on the dataset's
geometry, lights and settings only (fitting.precompile), and synth knows those before it
renders the targets. So while synth renders, `start` runs `python -m data_synth.background
OPTIONS` — the same dataset's layout (data_synth.scenes.dataset_layout) through
fitting.precompile — into the command line's compilation cache and program store
(diffshade.io.compile_cache), and the fit then loads those programs instead of compiling
them. A fit with other options, or of other data, compiles what it needs as before.

The process holds a lock for the dataset's folder while it runs
(fitting.precompile.lock_path: synth takes it and hands it over); the fit of that folder,
after loading the dataset and while the lock is held, waits for each program until the
process has written it (fitting.precompile.await_background), so that the fit's start
(its imports, the dataset, its first steps) runs alongside the end of the compilation and
no program is compiled twice.
synth does not wait for it (`finish`), except to end it where synth failed. Ended at any
point, it leaves the caches whole: their entries are written atomically and checked when
read.

Nothing is started for library use (the cache is off there), where DIFFSHADE_WARMUP=0
(SWITCH, which turns the fresh install's background compilations off),
or on a machine with a single core to run it on, where it would only slow synth down.
"""

import fcntl
import json
import os
import subprocess
import sys

from diffshade.io import enable_compile_cache, store_dir
from fitting.precompile import lock_path

#: the environment variable that turns the background compilations off ("0"): the fresh
#: install's (diffshade.host.warmup.SWITCH) and this one
SWITCH = "DIFFSHADE_WARMUP"

#: the synth options that make the dataset's layout (data_synth.options.layout_of)
LAYOUT_OPTIONS = ("shape", "scene", "material", "views", "lights", "size", "seed", "shading",
                  "texture")


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def applies() -> bool:
    """Whether a synth run compiles its fit's programs in the background (module
    docstring)."""
    return (store_dir() is not None and os.environ.get(SWITCH) != "0"
            and _cores() >= 2)


def start(args):
    """Start precompiling the fit of the dataset synth's `args` describe, holding its lock
    (module docstring); returns the process, or None where that does not apply or another
    holds the lock."""
    if not applies():
        return None
    options = json.dumps({name: getattr(args, name) for name in LAYOUT_OPTIONS})
    try:
        with open(lock_path(args.output), "ab") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
            # the process inherits the locked file: the lock is held until it exits
            return subprocess.Popen([sys.executable, "-m", "data_synth.background", options],
                                    stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                    stderr=subprocess.DEVNULL, pass_fds=(lock.fileno(),))
    except OSError:  # that dataset's fit is being compiled already, or no lock to be had:
        return None  # synth runs as without it


def finish(process, failed=False):
    """After synth's own work: where synth `failed`, end the process `start` gave (its
    dataset will not be fitted); else leave it compiling."""
    if process is not None and failed:
        process.kill()
        process.wait()


def main(argv):
    """python -m data_synth.background OPTIONS (JSON of LAYOUT_OPTIONS)."""
    from argparse import Namespace

    from data_synth.options import layout_of
    from fitting.precompile import precompile

    enable_compile_cache()
    precompile(layout_of(Namespace(**json.loads(argv[0]))))


if __name__ == "__main__":
    main(sys.argv[1:])
