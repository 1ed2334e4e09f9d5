"""diffshade.host.cputune (process settings applied on import) and hostcall (float64 callbacks)."""

import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np

from diffshade.host import cputune
from diffshade.host.hostcall import host_call

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _import_diffshade(env_changes):
    """(XLA_FLAGS, CPU_TUNING) seen by a fresh process after `import diffshade`."""
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "DIFFSHADE_CPU_TUNING")}
    env.update(env_changes)
    code = ("import os, diffshade; print(os.environ.get('XLA_FLAGS', '')); "
            "print(diffshade.CPU_TUNING)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                         cwd=ROOT, check=True).stdout.splitlines()
    return out[0], out[1]


def test_import_disables_ynn_reduce_fusion_on_known_jaxlib():
    flags, tuning = _import_diffshade({})
    known = cputune._jaxlib_minor() in cputune.YNN_JAXLIB
    assert (cputune.YNN_FLAG in flags) == known
    assert f"'xla_flags': {known}" in tuning


def test_import_gives_small_dots_and_reductions_to_xla_not_ynnpack():
    """After `import diffshade` (before any JAX computation), a vertex transform's dot
    ([V, 4] x [4, 4]) and a reduction over an axis of 3 compile to XLA's own loops, not
    YNNPACK fusions; with DIFFSHADE_CPU_TUNING=0 the dot is YNNPACK's (which shows the
    test can tell them apart)."""
    if cputune._jaxlib_minor() not in cputune.YNN_JAXLIB:
        return
    code = ("import diffshade, jax, jax.numpy as jnp\n"
            "f = jax.jit(lambda v, m: (v @ m, jnp.sum(v.reshape(-1, 4, 3), -1)))\n"
            "v, m = jnp.ones((2562, 4)), jnp.ones((4, 4))\n"
            "print(f.lower(v, m).compile().as_text().count('ynn'))")
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "DIFFSHADE_CPU_TUNING")}
    counts = [int(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                                 env={**env, **change}, cwd=ROOT, check=True).stdout.split()[-1])
              for change in ({}, {"DIFFSHADE_CPU_TUNING": "0"})]
    assert counts[0] == 0 and counts[1] > 0, counts


def test_user_flags_and_opt_out_are_respected():
    flags, _ = _import_diffshade({"XLA_FLAGS": "--xla_cpu_experimental_ynn_fusion_type=reduce"})
    assert flags == "--xla_cpu_experimental_ynn_fusion_type=reduce"
    flags, tuning = _import_diffshade({"DIFFSHADE_CPU_TUNING": "0"})
    assert flags == "" and tuning == "{'xla_flags': False, 'malloc': False}"


def test_host_call_keeps_float64_under_the_x64_context_manager():
    # a value float32 cannot hold: 1 + 1e-10 becomes 1.0 if it is ever converted
    with jax.enable_x64(True):
        x = jnp.full((64, 64), 1.0 + 1e-10, jnp.float64)
        shapes = (jax.ShapeDtypeStruct((64, 64), jnp.float64),
                  jax.ShapeDtypeStruct((64, 64), jnp.int32))

        def host(a):
            assert a.dtype == np.float64
            return a - 1.0, np.full(a.shape, 7, np.int32)
        diff, ints = jax.jit(lambda x: host_call(host, shapes, x))(x)
        assert diff.dtype == jnp.float64
        np.testing.assert_allclose(np.asarray(diff), 1e-10, rtol=1e-6)
        assert np.all(np.asarray(ints) == 7)
        batched = jax.vmap(lambda x: host_call(host, shapes, x)[0])(jnp.stack([x, 2 * x]))
        np.testing.assert_allclose(np.asarray(batched[1]), 1.0 + 2e-10, rtol=1e-12)
