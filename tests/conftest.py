"""Shared fixtures for the renderer tests.

float64: the renderer tests compare against float64 references with tight tolerances, so
they run under `jax.enable_x64(True)`, scoped to each test by the `x64` fixture (a test
module opts in with `pytestmark = pytest.mark.usefixtures("x64")`). It is a context
manager, not a session-wide `jax.config.update`, so that it does not leak into other test
modules that expect JAX's float32 default. Scenes must be built *inside* the test (or in
a fixture that depends on `x64`), because builders take the default float dtype at call
time. A float32 test in such a module nests `with jax.enable_x64(False):` and builds its
scene inside that block.

`mesh` builds a Mesh from plain arrays in the current default float dtype with the
normals given as they are (`mesh_from_arrays` computes or renormalizes them), so that
closed-form tests see exactly the vertices and normals they wrote down.

Compilation: the suite is dominated by XLA compiling many small programs that each run
a few times, so the tests compile without LLVM's backend optimizations (XLA's own HLO
passes still run; no fast-math either way, so values change by rounding at most). That
takes about a third off the CPU time of the gradient checks (test_transforms'
check_grads: 3 min 36 s -> 2 min 24 s of CPU) and a quarter off tests that run fits
(test_fitting.py + test_accuracy_quick.py: 3 min 29 s -> 2 min 41 s), measured with
`time pytest -n 0 FILES` with and without the variable below. They also emit XLA's
fusions with its classic elemental emitter instead of the MLIR fusion emitters
(--xla_cpu_use_fusion_emitters=false): the same HLO, the same IEEE operations, lowered
to LLVM by another route. Compiling test_transforms' soft Phong gradient (jax path)
took 9.2 s of CPU with the MLIR emitters and 3.4 s without (the gradients equal to
5e-14 relative); per file, CPU seconds with `-n 0` before -> after: test_transforms
589 -> 242, test_hard_cases 388 -> 210, test_gradients 74 -> 31, test_tile_search
63 -> 48 (a loaded 2-core machine; the commit that added the flag has the details). Set
DIFFSHADE_TEST_FULL_OPT=1 to test the fully optimized programs users run.
"""

import collections
import os
import resource
import time

if os.environ.get("DIFFSHADE_TEST_FULL_OPT") != "1":  # before jax initializes its backend
    os.environ["XLA_FLAGS"] = " ".join([
        os.environ.get("XLA_FLAGS", ""), "--xla_backend_optimization_level=0",
        "--xla_llvm_disable_expensive_passes=true",
        "--xla_cpu_use_fusion_emitters=false"]).strip()

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from diffshade.numerics import float_dtype  # noqa: E402
from diffshade.scene.mesh import Mesh  # noqa: E402

# The command line turns JAX's persistent compilation cache on (diffshade.io.compile_cache).
# Tests run it in-process and in subprocesses; they must not write into the user's cache
# folder, nor switch the cache on for the rest of the session.
os.environ["DIFFSHADE_COMPILE_CACHE"] = "0"
# A command run in a subprocess would otherwise, where numba's cache is empty, render with
# the JAX kernels and start compiling the host ones in the background
# (diffshade.host.warmup); tests/test_warmup.py tests that on its own.
os.environ["DIFFSHADE_WARMUP"] = "0"


@pytest.fixture(scope="session")
def cli_env(tmp_path_factory):
    """The environment for a `diffshade` command run in a subprocess: the command line's
    compilation cache on, as for a user, in one folder shared by this test session (all
    its xdist workers) and deleted with its temporary files, so that a subprocess loads
    the programs an earlier one compiled (the fits the interrupt tests signal)."""
    base = tmp_path_factory.getbasetemp()
    shared = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base
    return dict(os.environ, DIFFSHADE_COMPILE_CACHE="1",
                DIFFSHADE_COMPILE_CACHE_DIR=str(shared / "diffshade-compile-cache"))


@pytest.fixture
def x64():
    with jax.enable_x64(True):
        yield


def make_mesh(vertices, faces, normals=None):
    """Mesh with vertices [V, 3], faces [F, 3] and normals [V, 3] (default: every vertex
    gets the unit normal of the first face, right for planar meshes)."""
    verts = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int32)
    if normals is None:
        tri = verts[faces[0]]
        normals = np.broadcast_to(np.cross(tri[1] - tri[0], tri[2] - tri[0]), verts.shape)
    normals = np.asarray(normals, np.float64)
    normals = normals / np.linalg.norm(normals, axis=-1, keepdims=True)
    dt = float_dtype()
    return Mesh(jnp.asarray(verts, dt), jnp.asarray(faces), jnp.asarray(normals, dt))


@pytest.fixture
def mesh():
    """The `make_mesh` builder (see the module docstring)."""
    return make_mesh


# ------------------------------------------------------------------ test order (CI time)
# pytest-xdist's worksteal scheduler hands each worker one contiguous share of the
# collection (the first worker len // n tests, the next an even share of the rest, ...)
# and later lets an idle worker take the tail of a busy worker's queue. A few tests
# compile one large program each (catalogues of hard cases, vmapped gradient checks) and
# cost minutes where most cost a second; if two of them land at the end of one share,
# that worker runs alone for minutes while the other has finished. So tests marked
# `cost(seconds)` (CPU seconds measured on the 2-core CI machine) are dealt out first:
# each goes, heaviest first, to the share with the least marked cost so far, at the front
# of its share; the unmarked tests fill the shares in collection order (modules stay
# together, so their module-scoped fixtures compile once).


def xdist_shares(count, workers):
    """Sizes of the contiguous shares worksteal's first scheduling step sends."""
    sizes, left = [], count
    for i in range(workers):
        sizes.append(left // (workers - i))
        left -= sizes[-1]
    return sizes


def cost(item):
    marker = item.get_closest_marker("cost")
    return float(marker.args[0]) if marker else None


def module_cost(item):
    """A module marked as a whole (`pytestmark = pytest.mark.cost(s)`: its tests share a
    costly module fixture) is dealt as one unit of that cost."""
    marks = getattr(getattr(item, "module", None), "pytestmark", [])
    marks = marks if isinstance(marks, list) else [marks]
    return next((float(m.args[0]) for m in marks if m.name == "cost"), None)


def deal(items, workers):
    """`items` reordered so that each worker's share starts with its marked tests."""
    units, seen = [], {}
    for item in items:
        if module_cost(item) is not None:
            key = item.module.__name__
            if key not in seen:
                seen[key] = len(units)
                units.append(([], module_cost(item)))
            units[seen[key]][0].append(item)
        elif cost(item) is not None:
            units.append(([item], cost(item)))
    units.sort(key=lambda unit: unit[1], reverse=True)
    dealt = {id(i) for unit, _ in units for i in unit}
    unmarked = [i for i in items if id(i) not in dealt]
    sizes = xdist_shares(len(items), workers)
    heads, load = [[] for _ in sizes], [0.0] * len(sizes)
    for unit, seconds in units:
        k = min((k for k in range(len(sizes)) if len(heads[k]) + len(unit) <= sizes[k]),
                key=lambda k: load[k], default=int(np.argmin(load)))
        heads[k] += unit
        load[k] += seconds
    ordered, rest = [], iter(unmarked)
    for head, size in zip(heads, sizes, strict=True):
        ordered += head + [next(rest) for _ in range(max(0, size - len(head)))]
    return ordered + list(rest)


def pytest_collection_modifyitems(config, items):
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if workers > 1:
        items[:] = deal(items, workers)


# ------------------------------------------------------- CPU time per test (measuring)
# `--durations` reports wall time, which on a shared machine says little. With
# DIFFSHADE_TEST_CPU_DURATIONS=N the run ends with the N tests that took the most CPU
# time (this process's, and that of the subprocesses it waited for), per test its setup,
# call and teardown together (a module fixture's cost lands on the first test that uses
# it), and the total per file; under xdist each worker measures its own tests. This is
# how the cost(seconds) markers are measured (`-n 0`, or scaled to them).
CPU_DURATIONS = int(os.environ.get("DIFFSHADE_TEST_CPU_DURATIONS", "0") or 0)


def _cpu_seconds():
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + children.ru_utime + children.ru_stime


if CPU_DURATIONS:
    _cpu_by_test = collections.defaultdict(float)

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_makereport(item, call):
        report = (yield).get_result()
        start = getattr(item, "_cpu_start", None)
        now = _cpu_seconds()
        if start is not None:
            # a new list: a test's reports share the item's
            report.user_properties = [*report.user_properties, ("cpu_s", now - start)]
        item._cpu_start = now

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_protocol(item, nextitem):
        item._cpu_start = _cpu_seconds()
        yield

    def pytest_runtest_logreport(report):
        _cpu_by_test[report.nodeid] += sum(v for k, v in report.user_properties if k == "cpu_s")

    def pytest_terminal_summary(terminalreporter):
        per_file = collections.defaultdict(float)
        for nodeid, seconds in _cpu_by_test.items():
            per_file[nodeid.split("::")[0]] += seconds
        write = terminalreporter.write_line
        write(f"CPU seconds per test (the {CPU_DURATIONS} costliest of {len(_cpu_by_test)}; "
              f"total {sum(_cpu_by_test.values()):.1f} s):")
        for nodeid, seconds in sorted(_cpu_by_test.items(), key=lambda kv: -kv[1])[
                :CPU_DURATIONS]:
            write(f"{seconds:8.1f} {nodeid}")
        write("CPU seconds per file:")
        for path, seconds in sorted(per_file.items(), key=lambda kv: -kv[1]):
            write(f"{seconds:8.1f} {path}")
