"""synth compiles its fit's programs in the background (data_synth.background,
fitting.precompile): the fit that follows compiles nothing; the layout is make_dataset's
dataset before rendering; the process is waited for, or ended where synth fails."""

import argparse
import hashlib
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from data_synth import background, make_dataset
from data_synth.options import layout_of
from data_synth.scenes import dataset_layout
from diffshade.host import warmup
from diffshade.io import compile_cache, program_entries, xla_cache
from fitting.precompile import (
    GREY,
    await_background,
    grey_targets,
    lock_path,
    wait_for_background,
)

ROOT = Path(__file__).resolve().parent.parent
SYNTH = ["synth", "--size", "16", "--views", "2", "--lights", "2", "-o", "data"]
FIT = ["fit", "data", "-o", "fit", "--quiet"]


def _run(argv, cwd, env):
    return subprocess.run([sys.executable, "-m", "diffshade", *argv], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=900, check=True)


def _compiled(log):
    """The programs JAX compiled (not loaded from its cache) in a run's log."""
    compiled = re.findall(r"Finished XLA compilation of jit\((\S+)\)", log)
    loaded = re.findall(r"Persistent compilation cache hit for 'jit_(\S+)'", log)
    for name in loaded:
        compiled.remove(name)
    return compiled


@pytest.mark.parametrize("in_background", [False, True])
def test_the_fit_after_synth_compiles_nothing(tmp_path, in_background):
    """As on a fresh install (the JAX kernels, empty caches): with the background compile
    the fit loads every program; without it (DIFFSHADE_WARMUP=0) it compiles its own."""
    env = {k: v for k, v in os.environ.items() if k != warmup.SWITCH}
    env |= {"PYTHONPATH": os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")]),
            "DIFFSHADE_COMPILE_CACHE": "1", "DIFFSHADE_COMPILE_CACHE_DIR": str(tmp_path / "c"),
            "DIFFSHADE_KERNELS": "jax"}
    _run(SYNTH, tmp_path, env if in_background else env | {warmup.SWITCH: "0"})
    fit = _run(FIT, tmp_path, env | {"JAX_LOG_COMPILES": "1"})
    compiled = _compiled(fit.stderr)
    if in_background:
        assert compiled == []
    else:  # the rasterization, the parts and the Jacobian programs at least
        assert {"_fragments", "view_parts", "normal_system"} <= set(compiled)
    assert "material.mtl" in fit.stdout


def _same(a, b):
    """Two pytrees of one structure with equal leaves."""
    (leaves_a, tree_a), (leaves_b, tree_b) = jax.tree.flatten(a), jax.tree.flatten(b)
    assert tree_a == tree_b
    for x, y in zip(leaves_a, leaves_b, strict=True):
        np.testing.assert_array_equal(x, y)


def test_the_layout_is_the_dataset_before_rendering():
    kwargs = {"n_views": 2, "n_lights": 2, "size": 12, "seed": 3, "shading": "gouraud"}
    made = make_dataset("torus", **kwargs, noise_std=0.1)
    layout = dataset_layout("torus", **kwargs)
    np.testing.assert_array_equal(layout.mesh.vertices, made.mesh.vertices)
    np.testing.assert_array_equal(layout.model, made.model)
    assert layout.settings == made.settings
    _same(layout.truth, made.truth)
    for got, want in zip(layout.views, made.views, strict=True):
        _same((got.camera, got.lights), (want.camera, want.lights))
        np.testing.assert_array_equal(got.target, np.zeros_like(want.target))
    assert all(np.all(v.target == GREY) for v in grey_targets(layout).views)


def test_the_background_layout_follows_synths_options():
    args = argparse.Namespace(shape="box", scene=None, material="0.1,0.5,0.3,20", views=1,
                              lights=3, size=10, seed=0, shading=None, texture=None)
    layout = layout_of(args)
    assert len(layout.views) == 3 and layout.views[0].target.shape == (10, 10, 3)
    np.testing.assert_allclose(np.asarray(layout.truth.kd), 0.5)
    assert set(background.LAYOUT_OPTIONS) <= set(vars(args))


def test_it_applies_only_with_the_store_on_and_not_switched_off(tmp_path, monkeypatch):
    assert background.SWITCH == warmup.SWITCH  # one switch for both
    monkeypatch.setattr(compile_cache, "_store", None)
    assert not background.applies()  # library use, or DIFFSHADE_COMPILE_CACHE=0
    monkeypatch.setattr(compile_cache, "_store", str(tmp_path / "programs"))
    monkeypatch.setattr(background, "_cores", lambda: 2)
    monkeypatch.setenv(warmup.SWITCH, "0")
    assert not background.applies()
    monkeypatch.delenv(warmup.SWITCH)
    assert background.applies()
    monkeypatch.setattr(background, "_cores", lambda: 1)
    assert not background.applies() and background.start(None) is None


def test_a_failed_synth_ends_the_process_a_finished_one_leaves_it():
    process = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        start = time.perf_counter()
        background.finish(process)
        assert process.poll() is None and time.perf_counter() - start < 5
        background.finish(process, failed=True)
        assert process.returncode is not None and time.perf_counter() - start < 30
    finally:
        process.kill()
        process.wait()
    background.finish(None)  # nothing started: nothing to do


_HOLD = """
import fcntl, sys, time
with open(sys.argv[1], "ab") as lock:
    fcntl.flock(lock, fcntl.LOCK_EX)
    print("held", flush=True)
    time.sleep(float(sys.argv[2]))
"""


def test_the_fit_waits_for_its_datasets_background_compile(tmp_path, monkeypatch):
    monkeypatch.setattr(compile_cache, "_store", str(tmp_path / "cache" / "programs"))
    (tmp_path / "cache").mkdir()
    path = lock_path(tmp_path / "data")
    assert path == lock_path(str(tmp_path / "x" / ".." / "data"))  # the folder, however named
    assert path != lock_path(tmp_path / "other")
    start = time.perf_counter()
    wait_for_background(tmp_path / "data")  # no lock file: no compile to wait for
    assert time.perf_counter() - start < 1.0
    holder = subprocess.Popen([sys.executable, "-c", _HOLD, path, "2"], stdout=subprocess.PIPE,
                              text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        start = time.perf_counter()
        wait_for_background(tmp_path / "data", patience=0.3)  # gives up
        assert 0.3 <= time.perf_counter() - start < 1.5 and holder.poll() is None
        wait_for_background(tmp_path / "data")
        assert holder.wait(1) == 0  # returned once the holder let go
    finally:
        holder.kill()
        holder.wait()


def test_the_fit_waits_for_each_program_while_its_datasets_background_compiles(
        tmp_path, monkeypatch):
    """While the lock is held, a missing program is waited for (at most `patience`);
    once the holder lets go, not any more."""
    monkeypatch.setattr(compile_cache, "_store", str(tmp_path / "cache" / "programs"))
    monkeypatch.setattr(xla_cache, "_producer", None)  # restored after the test
    (tmp_path / "cache").mkdir()
    missing = str(tmp_path / "cache" / "missing.xla")
    await_background(tmp_path / "data")  # no lock file: no compile to wait for
    assert xla_cache._producer is None
    holder = subprocess.Popen([sys.executable, "-c", _HOLD, lock_path(tmp_path / "data"),
                               "2"], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        await_background(tmp_path / "data", patience=0.3)
        start = time.perf_counter()
        xla_cache.await_entry(missing)  # gives up
        assert 0.3 <= time.perf_counter() - start < 1.5 and holder.poll() is None
        assert xla_cache._producer is None
        await_background(tmp_path / "data")
        xla_cache.await_entry(missing)
        assert holder.wait(1) == 0  # returned once the holder let go
        assert xla_cache._producer is None
    finally:
        holder.kill()
        holder.wait()


def _whole(path):
    """Whether a store entry is whole: its header's length and SHA-256 match its code."""
    blob = path.read_bytes()
    head, _, code = blob[len(program_entries.MAGIC):].partition(b"\n")
    head = json.loads(head)
    return (blob.startswith(program_entries.MAGIC) and head["code_bytes"] == len(code)
            and head["code_sha256"] == hashlib.sha256(code).hexdigest())


def test_a_killed_background_compile_leaves_the_cache_whole(tmp_path):
    """Killed while it compiles, the process leaves only whole entries and its lock free;
    the fit after it compiles the rest and runs."""
    env = {k: v for k, v in os.environ.items() if k != warmup.SWITCH}
    env |= {"PYTHONPATH": os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")]),
            "DIFFSHADE_COMPILE_CACHE": "1", "DIFFSHADE_COMPILE_CACHE_DIR": str(tmp_path / "c"),
            "DIFFSHADE_KERNELS": "jax"}
    _run(SYNTH, tmp_path, env | {warmup.SWITCH: "0"})
    options = {"shape": None, "scene": None, "material": None, "views": 2, "lights": 2,
               "size": 16, "seed": 0, "shading": None, "texture": None}
    process = subprocess.Popen([sys.executable, "-m", "data_synth.background",
                                json.dumps(options)], cwd=tmp_path, env=env)
    store = tmp_path / "c" / compile_cache.STORE_FOLDER
    deadline = time.monotonic() + 300
    while not list(store.rglob("*.bin")) and time.monotonic() < deadline:
        time.sleep(0.05)  # killed after its first program, while it compiles the next
    process.kill()
    process.wait()
    written = list(store.rglob("*.bin"))
    assert written and all(_whole(path) for path in written)
    fit = _run(FIT, tmp_path, env | {"JAX_LOG_COMPILES": "1"})
    assert "material.mtl" in fit.stdout and _compiled(fit.stderr)  # it compiled the rest


def test_one_background_compile_per_dataset(tmp_path, monkeypatch):
    monkeypatch.setattr(compile_cache, "_store", str(tmp_path / "cache" / "programs"))
    (tmp_path / "cache").mkdir()
    monkeypatch.setattr(background, "_cores", lambda: 2)
    monkeypatch.delenv(warmup.SWITCH, raising=False)
    args = argparse.Namespace(shape=None, scene=None, material=None, views=1, lights=1,
                              size=8, seed=0, shading=None, texture=None,
                              output=str(tmp_path / "data"))
    first = background.start(args)
    try:
        assert first is not None
        assert background.start(args) is None  # its lock is held: no second one
        holder = subprocess.run([sys.executable, "-c", _TRY_LOCK, lock_path(args.output)],
                                capture_output=True, text=True, check=True)
        assert holder.stdout.strip() == "held"  # by the process, synth's file closed
    finally:
        background.finish(first, failed=True)
    start = time.perf_counter()
    wait_for_background(args.output, patience=5.0)
    assert time.perf_counter() - start < 2.0  # ended, it let go of the lock


_TRY_LOCK = """
import fcntl, sys
with open(sys.argv[1], "rb") as lock:
    try:
        fcntl.flock(lock, fcntl.LOCK_SH | fcntl.LOCK_NB)
        print("free")
    except BlockingIOError:
        print("held")
"""
