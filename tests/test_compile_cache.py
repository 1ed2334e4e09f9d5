"""The command line's persistent compilation cache (diffshade.io.compile_cache).

JAX decides once per process whether it uses a cache, at the first compilation, so each
behaviour is checked in a fresh interpreter: the files that appear in the cache folder,
and JAX's own log of a cache hit in a second process. (The test session itself runs with
DIFFSHADE_COMPILE_CACHE=0, set in conftest.py, so in-process CLI tests write nothing
into the user's cache.)"""

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffshade import cli
from diffshade.io import compile_cache

ROOT = Path(__file__).resolve().parent.parent

# Enables the cache as the CLI does, compiles one program, prints the folder enable() chose,
# then calls a stored program (compile_cache.stored_jit) and prints its value and how many
# times it was traced (0: loaded from the program store).
SCRIPT = """
import jax
from diffshade.io import compile_cache
print(compile_cache.enable())
jax.jit(lambda x: x * 2.0 + 1.0)(jax.numpy.arange(3.0)).block_until_ready()
traced = []

@compile_cache.stored_jit
def twice(x):
    traced.append(1)
    return x * 2.0

print(float(twice(jax.numpy.arange(3.0))[2]), len(traced))
"""


def run(tmp_path, **env):
    """(stdout, stderr) of SCRIPT in a fresh interpreter, with env on top of a clean one."""
    base = {k: v for k, v in os.environ.items()
            if not k.startswith(("DIFFSHADE_COMPILE_CACHE", "JAX_COMPILATION_CACHE"))}
    base["PYTHONPATH"] = os.pathsep.join([str(ROOT), base.get("PYTHONPATH", "")])
    done = subprocess.run([sys.executable, "-c", SCRIPT], env=base | env, cwd=tmp_path,
                          capture_output=True, text=True, check=True)
    shown, stored = done.stdout.strip().splitlines()
    assert stored.split()[0] == "4.0"
    return shown, done.stderr, int(stored.split()[1])


def files(path):
    return [p for p in Path(path).rglob("*") if p.is_file()] if Path(path).exists() else []


def test_cache_dir_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.delenv("DIFFSHADE_COMPILE_CACHE_DIR", raising=False)
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))
    assert compile_cache.cache_dir() == str(tmp_path / ".cache" / "diffshade" / "jax")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert compile_cache.cache_dir() == str(tmp_path / "xdg" / "diffshade" / "jax")
    monkeypatch.setenv("DIFFSHADE_COMPILE_CACHE_DIR", "~/mine")
    assert compile_cache.cache_dir() == str(tmp_path / "mine")


def test_a_second_process_loads_what_the_first_compiled(tmp_path):
    cache = tmp_path / "cache"
    shown, _, traced = run(tmp_path, DIFFSHADE_COMPILE_CACHE_DIR=str(cache))
    assert shown == str(cache) and traced == 1
    written = files(cache)
    assert written, "nothing was written to the cache"
    assert files(cache / compile_cache.STORE_FOLDER), "nothing was written to the store"
    _, log, traced = run(tmp_path, DIFFSHADE_COMPILE_CACHE_DIR=str(cache),
                         JAX_LOG_COMPILES="1")
    assert "Persistent compilation cache hit" in log
    assert traced == 0  # the stored program was loaded whole, not traced
    assert sorted(files(cache)) == sorted(written)


def test_switched_off_it_writes_nothing(tmp_path):
    shown, _, traced = run(tmp_path, DIFFSHADE_COMPILE_CACHE="0",
                           XDG_CACHE_HOME=str(tmp_path / "xdg"), HOME=str(tmp_path))
    assert shown == "None" and traced == 1
    assert files(tmp_path) == []


def test_a_cache_folder_set_for_jax_is_kept(tmp_path):
    shown, _, _ = run(tmp_path, JAX_COMPILATION_CACHE_DIR=str(tmp_path / "jax"),
                   JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
                   DIFFSHADE_COMPILE_CACHE_DIR=str(tmp_path / "ours"))
    assert shown == str(tmp_path / "jax")
    assert files(tmp_path / "jax") and not files(tmp_path / "ours")


def test_the_command_line_enables_it_first(monkeypatch, capsys):
    calls = []
    monkeypatch.setattr(compile_cache, "enable", lambda: calls.append("enable"))
    assert cli.main(["--help"]) == 0
    assert calls == ["enable"]


# ---- the program store (StoredProgram), in this process ----

TRACES = []
FRESH_COMPILE = compile_cache._fresh_compile


def _affine(x, table, scale=2.0, power=1):
    """(x**power * scale + sum(table['b']), cumsum(x)); power is static."""
    TRACES.append(power)
    return x**power * scale + jnp.sum(table["b"]), jnp.cumsum(x)


def _reference(x, table, scale=2.0, power=1):
    x = np.asarray(x, np.float64)
    return x**power * scale + np.sum(table["b"]), np.cumsum(x)


@pytest.fixture
def store(tmp_path, monkeypatch):
    """The program store switched on in a temporary folder (as enable() does)."""
    folder = tmp_path / "programs"
    monkeypatch.setattr(compile_cache, "_store", str(folder))
    return folder


def entries(folder):
    return sorted(p for p in files(folder) if p.suffix == ".bin")


def no_compiling(monkeypatch):
    """From now on a program must come from the store: compiling one fails the test."""
    def refuse(_lowered):
        raise AssertionError("compiled, not loaded from the store")
    monkeypatch.setattr(compile_cache, "_fresh_compile", refuse)


def check(out, *args, **kwargs):
    for got, want in zip(out, _reference(*args, **kwargs), strict=True):
        np.testing.assert_allclose(np.asarray(got), want, rtol=1e-6, atol=1e-6)


X = np.linspace(-1.0, 2.0, 5, dtype=np.float32)
TABLE = {"b": np.arange(3, dtype=np.float32)}


def test_a_stored_program_loads_and_computes_the_same(store, monkeypatch):
    program = compile_cache.StoredProgram(_affine, ("power",))
    first = program(jnp.asarray(X), TABLE, 0.5, power=3)
    check(first, X, TABLE, 0.5, power=3)
    assert len(entries(store)) == 1
    program.loaded.clear()  # as a new process: only the file is left
    no_compiling(monkeypatch)
    traced = len(TRACES)
    again = program(jnp.asarray(X), TABLE, scale=0.5, power=3)  # keywords: the same entry
    assert len(TRACES) == traced, "a stored program was traced again"
    for a, b in zip(first, again, strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert len(entries(store)) == 1


def test_other_shapes_dtypes_and_static_arguments_get_their_own_program(store, monkeypatch):
    program = compile_cache.StoredProgram(_affine, ("power",))
    calls = [((X, TABLE, 0.5), {"power": 2}),
             ((X[:4], TABLE, 0.5), {"power": 2}),  # shape
             ((X.astype(np.float16), TABLE, 0.5), {"power": 2}),  # dtype
             ((X, TABLE, 0.5), {"power": 3}),  # static argument
             ((X, TABLE, np.float32(0.5)), {"power": 2}),  # a weakly typed scalar no more
             ((X, {"b": TABLE["b"], "c": TABLE["b"]}, 0.5), {"power": 2})]  # structure
    for count, (args, kwargs) in enumerate(calls, 1):
        check(program(*args, **kwargs), *args, **kwargs)
        assert len(entries(store)) == count
    program.loaded.clear()
    no_compiling(monkeypatch)
    for args, kwargs in calls:  # each loads its own program back, and no other's
        check(program(*args, **kwargs), *args, **kwargs)
    monkeypatch.setattr(compile_cache, "_fresh_compile", FRESH_COMPILE)
    with jax.enable_x64(True):  # another JAX setting: not the float32 program
        x64 = program(X.astype(np.float64), TABLE, 0.5, power=2)
        assert x64[0].dtype == np.float64
        check(x64, X, TABLE, 0.5, power=2)
    assert len(entries(store)) == len(calls) + 1


@pytest.mark.parametrize("damage", ["flipped byte", "truncated", "valid hash, bad pickle"])
def test_a_damaged_entry_is_compiled_afresh_and_replaced(store, monkeypatch, damage):
    program = compile_cache.StoredProgram(_affine, ("power",))
    program(X, TABLE, power=2)
    (path,) = entries(store)
    blob = path.read_bytes()
    if damage == "flipped byte":
        blob = blob[:-100] + bytes([blob[-100] ^ 0xFF]) + blob[-99:]
    elif damage == "truncated":
        blob = blob[:len(blob) // 2]
    else:
        payload = b"not a pickle"
        blob = (compile_cache._MAGIC + hashlib.sha256(payload).hexdigest().encode() + b"\n"
                + payload)
    path.write_bytes(blob)
    program.loaded.clear()
    check(program(X, TABLE, power=2), X, TABLE, power=2)
    assert entries(store) == [path] and path.read_bytes() != blob  # written anew
    program.loaded.clear()
    no_compiling(monkeypatch)
    check(program(X, TABLE, power=2), X, TABLE, power=2)


@pytest.mark.parametrize("on", [False, True])
def test_compiler_options_reach_the_compiled_program(on, tmp_path, monkeypatch):
    """An option XLA does not know fails the compile: so the options reach it, through
    jit with the store off and through the store's own compile (on)."""
    if on:
        monkeypatch.setattr(compile_cache, "_store", str(tmp_path / "programs"))
    program = compile_cache.StoredProgram(_affine, ("power",),
                                          compiler_options={"xla_no_such_option": True})
    with pytest.raises(Exception, match="xla_no_such_option"):
        program(X, TABLE, power=2)


def test_compiler_options_are_in_the_key(store, monkeypatch):
    plain = compile_cache.StoredProgram(_affine, ("power",))
    fast = compile_cache.StoredProgram(_affine, ("power",),
                                       compiler_options=compile_cache.FAST_COMPILE)
    check(plain(X, TABLE, power=2), X, TABLE, power=2)
    check(fast(X, TABLE, power=2), X, TABLE, power=2)  # its own entry, not plain's
    assert len(entries(store)) == 2
    fast.loaded.clear()
    no_compiling(monkeypatch)
    check(fast(X, TABLE, power=2), X, TABLE, power=2)
    assert len(entries(store)) == 2


def test_the_fit_compiles_its_run_once_programs_fast():
    from fitting.model import cache
    from fitting.report import result as report
    from fitting.solve import gauss_newton, linear

    fast = tuple(sorted(compile_cache.FAST_COMPILE.items()))
    for program in (cache._project, cache._fragments, report._render_fragments):
        assert program.compiler_options == fast, program.name
    light = tuple(sorted(compile_cache.LIGHT_COMPILE.items()))
    for program in (gauss_newton.normal_system, linear.view_parts):  # called many times
        assert program.compiler_options == light, program.name
    assert cache._geometry.compiler_options == ()  # its rounding, magnified by shininess


def test_switched_off_or_inside_a_trace_it_is_plain_jit(tmp_path, monkeypatch):
    program = compile_cache.StoredProgram(_affine, ("power",))
    assert compile_cache.store_dir() is None  # the tests run with the cache off
    check(program(X, TABLE, power=2), X, TABLE, power=2)
    assert files(tmp_path) == [] and not program.loaded
    folder = tmp_path / "programs"
    monkeypatch.setattr(compile_cache, "_store", str(folder))
    inner = jax.jit(lambda x: program(x, TABLE, power=2)[0])(X)  # a tracer: not stored
    np.testing.assert_allclose(inner, _reference(X, TABLE, power=2)[0], rtol=1e-6)
    slope = jax.grad(lambda s: program(X, TABLE, s, power=1)[0].sum())(0.5)
    np.testing.assert_allclose(slope, X.sum(), rtol=1e-6)  # d/ds sum(x s + 3) = sum(x)
    assert files(folder) == []


def test_the_key_follows_the_package_source(monkeypatch):
    paths = [path for path, _ in compile_cache._package_sources()]
    assert os.path.join("fitting", "solve", "linear.py") in paths
    assert os.path.join("diffshade", "io", "compile_cache.py") in paths
    monkeypatch.setattr(compile_cache, "_environment", None)
    before = compile_cache.environment_key()
    edited = [(p, t + b"\n# edited" if p.endswith("linear.py") else t)
              for p, t in compile_cache._package_sources()]
    monkeypatch.setattr(compile_cache, "_package_sources", lambda: edited)
    monkeypatch.setattr(compile_cache, "_environment", None)
    assert compile_cache.environment_key() != before


def test_a_fit_program_from_the_store_equals_jit(store, monkeypatch):
    from data_synth import make_dataset
    from fitting import DEFAULT_INIT, FitSpec
    from fitting.model import build_cache
    from fitting.model.batch import batched
    from fitting.solve.gauss_newton import normal_system
    from fitting.spec.params import material_values

    dataset = make_dataset(size=16, n_views=2, n_lights=1)
    data = build_cache(dataset, DEFAULT_INIT)  # its geometry programs are stored too
    spec = FitSpec()
    before = len(entries(store))
    values = material_values(DEFAULT_INIT, spec, None, n_views=2)
    slopes = np.ones(sum(np.size(v) for v in jax.tree.leaves(values)), np.float32)
    stacked = batched(data)
    want = normal_system.jitted(values, slopes, stacked, spec, "mse")
    normal_system.loaded.clear()
    normal_system(values, slopes, stacked, spec, "mse")
    assert len(entries(store)) == before + 1
    normal_system.loaded.clear()
    no_compiling(monkeypatch)
    got = normal_system(values, slopes, stacked, spec, "mse")
    for g, w in zip(got, want, strict=True):
        np.testing.assert_allclose(np.asarray(g), np.asarray(w), rtol=1e-6, atol=1e-7)


def test_a_program_with_a_host_callback_is_not_stored(store):
    def host_square(x):
        return np.asarray(x) ** 2

    def squared_plus_one(x):
        shape = jax.ShapeDtypeStruct(x.shape, x.dtype)
        return jax.pure_callback(host_square, shape, x) + 1.0

    program = compile_cache.StoredProgram(squared_plus_one)
    for _ in range(2):
        np.testing.assert_allclose(program(X), X.astype(np.float64) ** 2 + 1.0, rtol=1e-6)
        program.loaded.clear()
    assert_plain(store)


def assert_plain(store):
    """The store holds one entry, which says: call jit (no executable)."""
    (path,) = entries(store)
    assert path.read_bytes().endswith(compile_cache._PLAIN)


def test_a_program_with_custom_calls_is_not_stored(store, monkeypatch):
    # on CPU, LAPACK's kernels are custom calls whose addresses a serialized executable
    # keeps: loaded in another process it would crash
    program = compile_cache.StoredProgram(lambda a: jnp.linalg.inv(a) @ a)
    matrix = np.array([[2.0, 1.0], [0.5, 3.0]], np.float32)
    np.testing.assert_allclose(program(matrix), np.eye(2), atol=1e-6)
    assert_plain(store)
    program.loaded.clear()
    no_compiling(monkeypatch)  # the entry sends it to jit, which compiles on its own
    np.testing.assert_allclose(program(matrix), np.eye(2), atol=1e-6)
