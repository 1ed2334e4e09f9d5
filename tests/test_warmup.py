"""A fresh install's first run (diffshade/host/warmup.py): where numba's cache lacks the
handlers a command uses, the run takes the JAX kernels and a background process compiles
the handlers into the cache; DIFFSHADE_KERNELS says what kernels='auto' means."""

import fcntl
import json
import os
import subprocess
import sys

import pytest

from diffshade.host import warmup
from diffshade.settings import AUTO_KERNELS, RenderSettings

# prints what cold_start did, the start of the warm-up process recorded instead of run
_COLD_START = """
import json, os
from diffshade.host import warmup
import sys
started = []
warmup.start = started.extend
missing = warmup.cold_start(warmup.command_targets(sys.argv[1:]))
print(json.dumps([missing, os.environ.get("DIFFSHADE_KERNELS"), started]))
"""

_PENDING = """
import json, sys
from diffshade.host import warmup
print(json.dumps(warmup.pending(sys.argv[1:])))
"""

_LOCK_PATH = """
import json
from diffshade.host import warmup
print(json.dumps(warmup.lock_path()))
"""


def _env(numba_dir, **extra):
    env = {k: v for k, v in os.environ.items() if k not in (warmup.SWITCH, AUTO_KERNELS)}
    return env | {"NUMBA_CACHE_DIR": str(numba_dir)} | extra


def _run(code, env, *args):
    done = subprocess.run([sys.executable, "-c", code, *args], env=env, capture_output=True,
                          text=True, timeout=600, check=True)
    return json.loads(done.stdout.splitlines()[-1])


def test_auto_kernels_follow_the_environment(monkeypatch):
    monkeypatch.setenv(AUTO_KERNELS, "jax")
    assert not RenderSettings().use_host_kernels()
    assert RenderSettings(kernels="host").use_host_kernels()
    monkeypatch.setenv(AUTO_KERNELS, "host")
    assert RenderSettings().use_host_kernels()
    assert not RenderSettings(kernels="jax").use_host_kernels()
    monkeypatch.setenv(AUTO_KERNELS, "gpu")
    with pytest.raises(ValueError, match=f"{AUTO_KERNELS} \\(environment\\): got 'gpu'"):
        RenderSettings().use_host_kernels()


def test_cold_start_on_an_empty_numba_cache(tmp_path):
    targets = list(warmup.COMMAND_TARGETS)
    assert _run(_COLD_START, _env(tmp_path)) == [targets, "jax", targets]
    # switched off, or the kernels chosen by the user: nothing changes
    assert _run(_COLD_START, _env(tmp_path, DIFFSHADE_WARMUP="0")) == [[], None, []]
    assert _run(_COLD_START, _env(tmp_path, DIFFSHADE_KERNELS="host")) == [[], "host", []]


_FLAGS_AFTER_COLD_START = """
import json, os
from diffshade.host import warmup
warmup.start = lambda targets: None
missing = warmup.cold_start()
flags = os.environ.get("XLA_FLAGS", "").split()
print(json.dumps([bool(missing), [f for f in flags if "ynn_fusion" not in f]]))
"""


def test_a_cold_run_compiles_for_a_quick_start(tmp_path):
    """Where it goes cold, a run adds COLD_XLA_FLAGS before XLA starts; the user's own
    choice of an option stands; a warm numba cache, a platform other than the CPU, or
    XLA started already leave XLA_FLAGS as they were (diffshade.host.cputune's flag
    aside; another platform: the next test)."""
    went, flags = _run(_FLAGS_AFTER_COLD_START, _env(tmp_path, XLA_FLAGS=""))
    assert went and flags == list(warmup.COLD_XLA_FLAGS)
    mine = "--xla_backend_optimization_level=2"
    went, flags = _run(_FLAGS_AFTER_COLD_START, _env(tmp_path, XLA_FLAGS=mine))
    assert went and flags == [mine, "--xla_cpu_use_fusion_emitters=false"]
    started = _FLAGS_AFTER_COLD_START.replace("warmup.start =", "import jax; jax.devices(); "
                                              "warmup.start =")
    went, flags = _run(started, _env(tmp_path, XLA_FLAGS=""))
    assert went and flags == []
    # several CPU devices: 'auto' means the JAX kernels anyway, no cold start, no flags
    went, flags = _run(_FLAGS_AFTER_COLD_START, _env(tmp_path, XLA_FLAGS="",
                                                     JAX_NUM_CPU_DEVICES="2"))
    assert not went and flags == []


def test_only_a_single_cpu_device_ahead_gets_the_quick_start(monkeypatch):
    """The flags are for the CPU's programs of a run on the JAX kernels: not where
    JAX_PLATFORMS puts another platform first, nor with several host devices."""
    import jax

    monkeypatch.setenv("XLA_FLAGS", "")
    was = jax.config.jax_platforms
    try:
        for platforms, ahead in (("cpu", True), ("cuda,cpu", False), ("tpu", False)):
            jax.config.update("jax_platforms", platforms)
            assert warmup._one_cpu_device_ahead() is ahead
        jax.config.update("jax_platforms", "cpu")
        monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=4")
        assert warmup._one_cpu_device_ahead() is False

    finally:
        jax.config.update("jax_platforms", was)


def test_the_quick_start_flags_are_known_to_this_xla():
    """jaxlib aborts the process on an XLA flag it does not know."""
    code = ("import os; os.environ['XLA_FLAGS'] = " + repr(" ".join(warmup.COLD_XLA_FLAGS))
            + "; import jax, jax.numpy as jnp; print(float(jax.jit(jnp.sin)(0.5)))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=300, check=True)
    assert abs(float(done.stdout) - 0.479425538604203) < 1e-6


def test_a_textured_command_warms_the_texture_lookup_too(tmp_path):
    """fit/synth --texture add the texture lookup's handlers; other commands do not."""
    plain, textures = list(warmup.COMMAND_TARGETS), list(warmup.TEXTURE_TARGETS)
    for argv in (["fit", "data", "-o", "out", "--texture", "kd=32"],
                 ["synth", "--texture=16", "-o", "out"]):
        assert _run(_COLD_START, _env(tmp_path), *argv) == [plain + textures, "jax",
                                                            plain + textures]
    assert _run(_COLD_START, _env(tmp_path), "fit", "data", "-o", "out") == [
        plain, "jax", plain]
    assert _run(_PENDING, _env(tmp_path), *textures) == textures


@pytest.mark.cost(15)
def test_warmup_compiles_into_numba_cache(tmp_path):
    env = _env(tmp_path)
    asked = ["diffshade_active", "diffshade_geometry_forward_f32"]
    assert _run(_PENDING, env, *asked) == asked
    subprocess.run([sys.executable, "-m", "diffshade.host.warmup", "diffshade_active"],
                   env=env, check=True, timeout=600)
    assert _run(_PENDING, env, *asked) == ["diffshade_geometry_forward_f32"]
    bad = subprocess.run([sys.executable, "-m", "diffshade.host.warmup", "diffshade_nothing"],
                         env=env, capture_output=True, text=True, timeout=600)
    assert bad.returncode != 0 and "got targets ['diffshade_nothing']" in bad.stderr


def test_one_warmup_at_a_time(tmp_path, monkeypatch):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    with open(warmup.lock_path(), "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        assert warmup.compile_targets(["diffshade_active"]) is False
        assert warmup.running()
    assert not warmup.running()


def test_a_run_while_a_warmup_compiles_starts_no_second(tmp_path):
    """The second command of a script (synth, then fit) finds the first one's warm-up
    compiling: it takes the JAX kernels too, and starts no warm-up of its own."""
    env = _env(tmp_path)
    targets = list(warmup.COMMAND_TARGETS)
    with open(_run(_LOCK_PATH, env), "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        assert _run(_COLD_START, env) == [targets, "jax", []]
    assert _run(_COLD_START, env) == [targets, "jax", targets]


@pytest.mark.skipif(not os.path.exists("/proc/self/autogroup"),
                    reason="no autogroup scheduling on this kernel: niceness is all there is")
def test_warmup_lowers_its_sessions_priority():
    """In a session of its own (as `start` runs it), lower_priority sets both the process's
    niceness and its session's autogroup niceness to NICENESS (what decides its share of
    the CPU against the command's session under autogroup scheduling)."""
    code = ("import json, os; from diffshade.host import warmup; warmup.lower_priority(); "
            "print(json.dumps([os.nice(0), open('/proc/self/autogroup').read()]))")
    nice, group = json.loads(subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True,
        start_new_session=True).stdout)
    assert nice == warmup.NICENESS
    assert group.split()[-1] == str(warmup.NICENESS)
    # not the leader of its session (run from a terminal): the session keeps its own. A
    # process in the kernel's root autogroup (one whose ancestors never started a session,
    # as in some containers) reads that file as empty.
    mine = open("/proc/self/autogroup").read()
    nice, group = json.loads(subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout)
    assert nice == warmup.NICENESS
    assert group == mine
