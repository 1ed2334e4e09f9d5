"""host_call (diffshade/host/hostcall.py) on both of its callback paths: its own no-copy
primitive (where this JAX has the internals it is lowered with) and jax.pure_callback,
against the same maths in jax.numpy, under jit and vmap (one call per member, and one
batched call); and the warning when it falls back to pure_callback."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffshade.host import hostcall


def _twice_sin(x, y):
    return (2.0 * np.sin(x) + y,)


def _call(x, y, batched=False):
    shape = (jax.ShapeDtypeStruct(x.shape[-1:], x.dtype),)
    return hostcall.host_call(_twice_sin, shape, x, y, batched=batched)[0]


@pytest.fixture(params=["primitive", "pure_callback"])
def path(request, monkeypatch):
    if request.param == "primitive" and not hostcall._no_copy():
        pytest.fail(f"host_call's no-copy primitive is unavailable under JAX "
                    f"{jax.__version__}: {hostcall._no_copy_missing()}")
    if request.param == "pure_callback":
        monkeypatch.setattr(hostcall, "_no_copy", lambda: False)
    return request.param


@pytest.mark.parametrize("batched", [False, True])
def test_host_call_equals_jax_numpy_under_jit_and_vmap(path, batched):
    x = jnp.linspace(-2.0, 3.0, 12, dtype=jnp.float32).reshape(3, 4)
    y = jnp.arange(4, dtype=jnp.float32)
    want = 2.0 * jnp.sin(x) + y
    got_jit = jax.jit(lambda a: _call(a, y))(x[0])
    got_vmap = jax.jit(jax.vmap(lambda a: _call(a, y, batched)))(x)
    np.testing.assert_allclose(got_jit, want[0], rtol=1e-6)
    np.testing.assert_allclose(got_vmap, want, rtol=1e-6)


def test_host_call_keeps_float64_under_enable_x64(path):
    with jax.enable_x64(True):
        x = jnp.asarray([0.1, 0.2, 1e-300], jnp.float64)
        y = jnp.zeros(3, jnp.float64)
        got = jax.jit(lambda a: _call(a, y))(x)
        assert got.dtype == jnp.float64
        np.testing.assert_array_equal(np.asarray(got), 2.0 * np.sin(np.asarray(x)))


def test_missing_internals_fall_back_to_pure_callback_with_one_warning(monkeypatch):
    monkeypatch.setattr(hostcall, "jax_callback", None)
    monkeypatch.setattr(hostcall, "_WARNED", set())
    x = jnp.linspace(-1.0, 1.0, 4, dtype=jnp.float32)
    with pytest.warns(hostcall.FallbackWarning, match="jax.pure_callback"):
        got = jax.jit(lambda a: _call(a, x))(x)
    np.testing.assert_allclose(got, 2.0 * np.sin(np.asarray(x)) + np.asarray(x), rtol=1e-6)
    with warnings.catch_warnings():
        warnings.simplefilter("error", hostcall.FallbackWarning)
        jax.jit(lambda a: _call(a, 2.0 * x))(x)


def test_primitive_lowers_as_pure_callback_without_the_internals(monkeypatch):
    # an FFI call lowered for another platform than the CPU takes this branch: the
    # primitive bound directly, without an FFI target, stands for it here
    monkeypatch.setattr(hostcall, "jax_callback", None)
    monkeypatch.setattr(hostcall, "_WARNED", set())
    x = jnp.linspace(-1.0, 1.0, 4, dtype=jnp.float32)
    shapes = (jax.ShapeDtypeStruct((4,), jnp.float32),)
    bind = lambda a: hostcall._host_p.bind(a, a, fn=_twice_sin, result_shapes=shapes,
                                           batched=False, ffi=None)[0]
    with pytest.warns(hostcall.FallbackWarning):
        text = jax.jit(bind).lower(x).as_text()
        got = jax.jit(bind)(x)
    assert "callback" in text
    np.testing.assert_allclose(got, 2.0 * np.sin(np.asarray(x)) + np.asarray(x), rtol=1e-6)
