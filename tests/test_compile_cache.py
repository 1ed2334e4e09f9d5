"""The command line's persistent compilation cache (diffshade.io.compile_cache).

JAX decides once per process whether it uses a cache, at the first compilation, so each
behaviour is checked in a fresh interpreter: the files that appear in the cache folder,
and JAX's own log of a cache hit in a second process. (The test session itself runs with
DIFFSHADE_COMPILE_CACHE=0, set in conftest.py, so in-process CLI tests write nothing
into the user's cache.)

The store's trust rules are checked against what an attacker or an accident leaves in
the folder: crafted entries whose checksums are right (a pickle that would make a folder
if it were loaded), entries swapped or grown to 8 GB, folders and entries that group or
another user can write; the reference is the program's value computed with numpy, and
whether the payload's folder exists afterwards."""

import hashlib
import json
import os
import pickle
import subprocess
import sys
import threading
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffshade import cli
from diffshade.io import compile_cache, private_files, program_entries, xla_cache

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
    for path in written:  # private: JAX's entries (diffshade.io.xla_cache) and the store's
        assert path.stat().st_mode & 0o777 == 0o600, path
        assert path.suffix in (".bin", xla_cache.SUFFIX), path
    for folder in {path.parent for path in written}:
        assert folder.stat().st_mode & 0o777 == 0o700, folder
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
    """The program store switched on in a temporary folder (as enable() does), with its
    checks of folders and its warnings fresh."""
    folder = tmp_path / "programs"
    monkeypatch.setattr(compile_cache, "_store", str(folder))
    monkeypatch.setattr(program_entries, "_folders", {})
    monkeypatch.setattr(private_files, "_warned", set())
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


@pytest.mark.parametrize("damage", ["flipped byte", "truncated", "not an entry"])
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
        blob = b"not an entry"
    path.write_bytes(blob)
    program.loaded.clear()
    check(program(X, TABLE, power=2), X, TABLE, power=2)
    assert entries(store) == [path] and path.read_bytes() != blob  # written anew
    program.loaded.clear()
    no_compiling(monkeypatch)
    check(program(X, TABLE, power=2), X, TABLE, power=2)


class _MakeFolder:
    """A pickle of this makes the folder `path` when it is loaded."""

    def __init__(self, path):
        self.path = path

    def __reduce__(self):
        return os.mkdir, (self.path,)


def _head_and_code(path):
    """(JSON head, executable bytes) of a version 2 entry, parsed here independently."""
    blob = path.read_bytes()
    magic, line, code = blob.split(b"\n", 2)
    assert magic + b"\n" == program_entries.MAGIC
    return json.loads(line), code


def _entry(head, code):
    head = dict(head, code_bytes=len(code), code_sha256=hashlib.sha256(code).hexdigest())
    return program_entries.MAGIC + json.dumps(head).encode() + b"\n" + code


@pytest.mark.parametrize("craft", ["version 1 entry", "pickle as executable",
                                   "node type outside the project"])
def test_a_crafted_entry_with_valid_checksums_runs_no_code(store, tmp_path, craft):
    """An entry whose checksums are right but whose content would run code if it were
    unpickled, or names a callable as a result's node type: refused, removed, compiled
    afresh; the code never ran."""
    program = compile_cache.StoredProgram(_affine, ("power",))
    program(X, TABLE, power=2)
    (path,) = entries(store)
    head, code = _head_and_code(path)
    made = tmp_path / "made-by-the-payload"
    payload = pickle.dumps((code, _MakeFolder(str(made))))
    if craft == "version 1 entry":  # the store's old format: the payload was unpickled
        blob = (b"diffshade-program 1\n" + hashlib.sha256(payload).hexdigest().encode()
                + b"\n" + payload)
    elif craft == "pickle as executable":
        blob = _entry(head, payload)
    else:
        program_head = dict(head["program"], out_tree=["os:system", "touch " + str(made), []])
        blob = _entry(dict(head, program=program_head), code)
    path.write_bytes(blob)
    program.loaded.clear()
    check(program(X, TABLE, power=2), X, TABLE, power=2)
    assert not made.exists()
    assert entries(store) == [path] and _head_and_code(path) == (head, code)  # anew


def test_entries_swapped_with_one_another_are_compiled_afresh(store, monkeypatch):
    """Each entry carries its full key: an entry moved onto another program's name is
    not loaded (the program compiles and its own entry replaces it)."""
    program = compile_cache.StoredProgram(_affine, ("power",))
    program(X, TABLE, power=2)
    program(X[:3], TABLE, power=3)
    first, second = entries(store)
    a, b = first.read_bytes(), second.read_bytes()
    first.write_bytes(b)
    second.write_bytes(a)
    program.loaded.clear()
    check(program(X, TABLE, power=2), X, TABLE, power=2)
    check(program(X[:3], TABLE, power=3), X[:3], TABLE, power=3)
    assert {first.read_bytes(), second.read_bytes()} == {a, b}
    assert _head_and_code(first)[0]["key"] != _head_and_code(second)[0]["key"]
    program.loaded.clear()
    no_compiling(monkeypatch)
    check(program(X, TABLE, power=2), X, TABLE, power=2)
    check(program(X[:3], TABLE, power=3), X[:3], TABLE, power=3)


def test_a_loaded_program_that_fails_is_removed(store, monkeypatch):
    """An entry under the right key that holds another call's program (here: other
    shapes) fails on its first call: the call goes to jit and the entry is removed."""
    program = compile_cache.StoredProgram(_affine, ("power",))
    program(X, TABLE, power=2)
    program(X[:3], TABLE, power=2)
    first, second = entries(store)
    (head, _), (other, code) = _head_and_code(first), _head_and_code(second)
    first.write_bytes(_entry(dict(other, key=head["key"]), code))
    program.loaded.clear()
    removed = []
    monkeypatch.setattr(compile_cache, "remove", removed.append)  # after the first call
    for x in (X, X[:3]):
        check(program(x, TABLE, power=2), x, TABLE, power=2)
    assert removed == [str(first)]


def test_an_entry_grown_huge_is_not_read(store, monkeypatch):
    """An entry over MAX_ENTRY_BYTES (here 8 GB, sparse) is removed before it is read."""
    program = compile_cache.StoredProgram(_affine, ("power",))
    program(X, TABLE, power=2)
    (path,) = entries(store)
    blob = path.read_bytes()
    os.truncate(path, 8 * 2**30)
    program.loaded.clear()
    check(program(X, TABLE, power=2), X, TABLE, power=2)
    assert path.stat().st_size == len(blob)  # written anew


def _other_users(path, monkeypatch):
    """Make `path` another user's: chown it as root; as another user, which cannot,
    the check of ownership sees it as another's."""
    if os.geteuid() == 0:
        os.chown(path, 65534, -1)
        return
    inode, owned = path.stat().st_ino, private_files._owned
    monkeypatch.setattr(private_files, "_owned",
                        lambda info: info.st_ino != inode and owned(info))


@pytest.mark.parametrize("where", ["entry group-writable", "entry another user's",
                                   "folder group-writable", "folder another user's"])
def test_an_entry_or_folder_others_can_write_is_refused(store, monkeypatch, capsys, where):
    """As ssh does: not loaded, one warning naming it, the program compiled."""
    program = compile_cache.StoredProgram(_affine, ("power",))
    program(X, TABLE, power=2)
    (path,) = entries(store)
    blob = path.read_bytes()
    target = path if where.startswith("entry") else path.parent
    if where.endswith("group-writable"):
        target.chmod(0o664 if target == path else 0o775)
    else:
        _other_users(target, monkeypatch)
    compiled = []
    monkeypatch.setattr(compile_cache, "_fresh_compile",
                        lambda lowered: compiled.append(1) or FRESH_COMPILE(lowered))
    program.loaded.clear()
    program_entries._folders.clear()  # as a new process: the folders are checked again
    check(program(X, TABLE, power=2), X, TABLE, power=2)
    program.loaded.clear()
    check(program(X, TABLE, power=2), X, TABLE, power=2)
    err = capsys.readouterr().err
    assert err.count("diffshade: warning:") == 1 and str(target) in err, err
    if target == path:  # the store's own entry replaced it, private again, and is loaded
        assert "not loaded, the program is compiled" in err
        assert compiled == [1] and path.stat().st_mode & 0o777 == 0o600
    else:  # the folder is not used at all
        assert "the program store is not used, programs compile normally" in err
        assert compiled == [1, 1] and path.read_bytes() == blob


def test_the_store_creates_its_folders_private(store, monkeypatch):
    old = os.umask(0o002)
    try:
        program = compile_cache.StoredProgram(_affine, ("power",))
        program(X, TABLE, power=2)
    finally:
        os.umask(old)
    (path,) = entries(store)
    assert path.stat().st_mode & 0o777 == 0o600
    for folder in (store, path.parent):
        assert folder.stat().st_mode & 0o777 == 0o700


def test_the_command_line_refuses_a_cache_folder_others_can_write(tmp_path):
    cache = tmp_path / "cache"
    cache.mkdir()
    cache.chmod(0o777)
    shown, log, traced = run(tmp_path, DIFFSHADE_COMPILE_CACHE_DIR=str(cache))
    assert shown == "None" and traced == 1 and files(cache) == []
    (line,) = [x for x in log.splitlines() if "warning" in x]
    assert line.startswith("diffshade: warning: cache folder") and str(cache) in line
    assert "writable by group or others (mode 0777" in line


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
    for program in (cache._project, cache._host_searched, report._render_fragments):
        assert program.compiler_options == fast, program.name
    light = tuple(sorted(compile_cache.LIGHT_COMPILE.items()))
    # called many times, or holding JAX's tile search (5x slower at -O0)
    for program in (gauss_newton.normal_system, linear.view_parts, cache._jax_searched):
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
    head, code = _head_and_code(path)
    assert head["program"] is None and code == b""


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


def test_the_projection_program_is_stored_whole(store, monkeypatch):
    """project transforms normals without LAPACK's inverse (a custom call): the fit's
    projection program loads from the store, untraced, in a later process."""
    from diffshade.raster.projection import project
    from diffshade.scene.builtin import builtin_scene

    scene = builtin_scene("sphere", 32, 32)
    program = compile_cache.StoredProgram(project)
    first = program(scene)
    (path,) = entries(store)
    assert _head_and_code(path)[0]["program"] is not None
    program.loaded.clear()
    no_compiling(monkeypatch)
    again = program(scene)
    np.testing.assert_array_equal(np.asarray(first.normals), np.asarray(again.normals))


# ---- another process compiling into the caches (a fit's background precompile) ----


def _producing(monkeypatch, write=None, after=0.3, busy_for=None):
    """Have the caches wait on a producer that calls `write()` after `after` seconds (from
    another thread, as another process would write an entry), then stays busy for
    `busy_for` more seconds (None: until the test sets the event returned); returns
    (its thread, that event)."""
    done = threading.Event()
    monkeypatch.setattr(xla_cache, "_producer", None)  # restored after the test
    xla_cache.await_producer(lambda: not done.is_set())

    def produce():
        time.sleep(after)
        if write is not None:
            write()
        done.wait(busy_for)
        done.set()
    thread = threading.Thread(target=produce)
    thread.start()
    return thread, done


def test_a_missing_program_is_waited_for_while_a_producer_compiles(store, monkeypatch):
    """The program another process is compiling is loaded once it is written, while that
    process is still busy: neither compiled here nor waited for to the producer's end."""
    compile_cache.StoredProgram(_affine, ("power",))(X, TABLE, 0.5, power=2)
    (path,) = entries(store)  # what the other process will write, taken away meanwhile
    blob = path.read_bytes()
    path.unlink()
    no_compiling(monkeypatch)
    thread, done = _producing(monkeypatch, lambda: private_files.write_private(path, blob))
    try:
        start = time.perf_counter()
        out = compile_cache.StoredProgram(_affine, ("power",))(X, TABLE, 0.5, power=2)
        waited = time.perf_counter() - start
        busy = not done.is_set()
    finally:
        done.set()
        thread.join()
    check(out, X, TABLE, 0.5, power=2)
    assert waited >= 0.3 and busy  # loaded while the producer was still busy


def test_a_program_the_producer_does_not_write_compiles_once_it_is_done(store, monkeypatch):
    thread, _ = _producing(monkeypatch, busy_for=0.6)
    start = time.perf_counter()
    out = compile_cache.StoredProgram(_affine, ("power",))(X, TABLE, 0.5, power=3)
    assert time.perf_counter() - start >= 0.9  # waited for the producer, then compiled
    check(out, X, TABLE, 0.5, power=3)
    thread.join()
    assert xla_cache._producer is None and len(entries(store)) == 1  # asked no more


def test_jax_entries_are_waited_for_while_a_producer_compiles(tmp_path, monkeypatch):
    cache = xla_cache.PrivateCache(tmp_path)
    key = "jit_f-" + "a" * 64
    thread, done = _producing(monkeypatch, lambda: cache.put(key, b"executable bytes"),
                              busy_for=0.5)
    assert cache.get(key) == b"executable bytes"  # written by the producer meanwhile
    assert not done.is_set()
    assert cache.get("jit_g-" + "b" * 64) is None  # never written: None once it is done
    assert done.is_set()
    thread.join()


# ---- JAX's own cache, where diffshade configures it (diffshade.io.xla_cache) ----


@pytest.fixture
def jax_cache(tmp_path, monkeypatch):
    monkeypatch.setattr(private_files, "_warned", set())
    return xla_cache.PrivateCache(tmp_path)


def test_jax_entries_are_private_and_carry_their_key(jax_cache, tmp_path):
    key, other = "jit_f-" + "a" * 64, "jit_g-" + "b" * 64
    jax_cache.put(key, b"executable bytes")
    assert jax_cache.get(key) == b"executable bytes" and jax_cache.get(other) is None
    (path,) = files(tmp_path)
    assert path.stat().st_mode & 0o777 == 0o600
    path.rename(tmp_path / f"{other}{xla_cache.SUFFIX}")  # swapped onto another key
    assert jax_cache.get(other) is None and files(tmp_path) == []


def test_jax_entries_others_can_write_or_too_big_are_refused(jax_cache, tmp_path,
                                                            monkeypatch, capsys):
    key = "jit_f-" + "a" * 64
    jax_cache.put(key, b"executable bytes")
    (path,) = files(tmp_path)
    path.chmod(0o666)
    assert jax_cache.get(key) is None and files(tmp_path) == [path]
    line = capsys.readouterr().err.strip()
    assert line.startswith("diffshade: warning: cache entry") and str(path) in line
    path.chmod(0o600)
    monkeypatch.setattr(xla_cache, "MAX_ENTRY_BYTES", 20)
    assert jax_cache.get(key) is None and files(tmp_path) == []  # removed unread
