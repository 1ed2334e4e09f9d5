"""Compile the programs of a default `diffshade fit` of a dataset without fitting it.

What a fit compiles depends on the dataset's geometry (mesh, cameras, image sizes, which
pixels are covered), its lights and settings, not on the targets' values. `diffshade
synth` knows all of that before it renders the targets, so on a machine of several cores
it runs `precompile` on the dataset's layout in a second process while it renders
(data_synth.background): the programs go into the command line's program store and JAX's
compilation cache (diffshade.io.compile_cache), and the `diffshade fit` that follows loads
them instead of compiling them.

That process holds a lock for the dataset's folder (`lock_path`) while it runs. The
`diffshade fit` of that folder, while the lock is held, waits for each program it does not
find in the caches until the process has written it (`await_background`), so that it loads
the programs rather than compiling them a second time alongside, and starts on each as
soon as it is there: its first steps run while the process compiles the later ones.
`wait_for_background` waits for the whole process instead.

`precompile` takes the fit's own steps, once each and in the fit's order, on grey
targets: the cache (fitting.model.cache.build_cache), the closed-form start
(fitting.run.start_run), one Levenberg-Marquardt step, the report's standard errors and
misfit check (fitting.driver.fit_result) and the first view's panel renders
(fitting.report.result.panel_renders). A fit with other options (--fit, --loss,
--method ...) compiles what these do not cover, as it would have anyway.
"""

import dataclasses
import fcntl
import hashlib
import os
import time

import numpy as np

from diffshade.io import await_producer, store_dir

#: the targets' colour while precompiling: inside (0, 1), so that every pixel counts
GREY = 0.5
#: the longest a fit waits for a background precompile of its dataset, in seconds (it
#: takes a few; a fit after a stuck one compiles its own programs)
PATIENCE = 120.0


def lock_path(dataset_path) -> str | None:
    """The lock file of a background precompile of the dataset folder `dataset_path`, in
    the compilation cache's folder; None while the program store is off (library use)."""
    store = store_dir()
    if store is None:
        return None
    digest = hashlib.sha256(os.path.realpath(dataset_path).encode()).hexdigest()[:16]
    return os.path.join(os.path.dirname(store), f"precompile-{digest}.lock")


def wait_for_background(dataset_path, patience=PATIENCE) -> None:
    """Return once no background precompile of `dataset_path` holds its lock, or after
    `patience` seconds."""
    path = lock_path(dataset_path)
    if path is None or not os.path.exists(path):
        return
    deadline = time.monotonic() + patience
    try:
        with open(path, "rb") as lock:
            while True:
                try:
                    fcntl.flock(lock, fcntl.LOCK_SH | fcntl.LOCK_NB)
                    return
                except BlockingIOError:
                    if time.monotonic() > deadline:
                        return
                    time.sleep(0.02)
    except OSError:  # a lock file that cannot be read: nothing to wait for
        return


def await_background(dataset_path, patience=PATIENCE) -> None:
    """Until no background precompile of `dataset_path` holds its lock, or for at most
    `patience` seconds from now, have the caches wait for a missing program rather than
    compile it (diffshade.io.xla_cache.await_producer; module docstring)."""
    path = lock_path(dataset_path)
    if path is None or not os.path.exists(path):
        return
    try:
        lock = open(path, "rb")  # kept open until the process is done (busy)
    except OSError:  # a lock file that cannot be read: nothing to wait for
        return
    deadline = time.monotonic() + patience

    def busy():
        try:
            if time.monotonic() <= deadline:
                fcntl.flock(lock, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
        lock.close()
        return False

    await_producer(busy)


def grey_targets(dataset):
    """`dataset` (a fitting.Dataset) with every target a uniform GREY of its shape and
    dtype."""
    views = [dataclasses.replace(v, target=np.full_like(v.target, GREY))
             for v in dataset.views]
    return dataclasses.replace(dataset, views=views)


def precompile(dataset) -> None:
    """Compile (and run once) the programs `diffshade fit DATASET` runs with its default
    options on `dataset` (a fitting.Dataset)'s geometry (module docstring); its targets
    are not read."""
    # the fit's modules: neither synth nor the fit's await_background imports them here
    from fitting.data.views import material_for
    from fitting.driver import fit_result
    from fitting.inputs import fit_spec
    from fitting.model.cache import build_cache
    from fitting.report.result import panel_renders
    from fitting.run import advance, finish, start_run
    from fitting.solve.distribute import for_options
    from fitting.solve.options import FitOptions
    from fitting.spec.params import DEFAULT_INIT, start_material

    dataset = grey_targets(dataset)
    spec, options = fit_spec(), FitOptions()
    init = start_material(material_for(dataset, DEFAULT_INIT, "init"), spec)
    views = for_options(build_cache(dataset, init, edge_margin=options.edge_margin), options)
    state = start_run(views, spec, init, options)
    advance(state, views, should_stop=lambda: True)  # one step
    finish(state, views)
    result = fit_result(state, dataset, views)
    panel_renders(dataset, result, init, [0])
