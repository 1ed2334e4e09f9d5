"""The compile counter of compiles.py against jit's own behaviour, known in advance: a
fresh function compiles once, a call with the same shapes and dtypes is a cache hit, new
shapes compile again, a nested jit is part of its caller's program, and only the
block's compilations are counted."""

import functools

import jax
import jax.numpy as jnp
from compiles import compiles


def test_counts_a_fresh_compile_a_cache_hit_and_a_recompile():
    @jax.jit
    def inner(x):
        return x * 2.0

    @jax.jit
    def outer(x):
        return inner(x) + 1.0

    with compiles() as first:
        outer(jnp.ones(3))
    with compiles() as again:
        outer(jnp.ones(3) * 5.0)
    with compiles() as reshaped:
        outer(jnp.ones(4))
    assert (first.of(outer), again.of(outer), reshaped.of(outer)) == (1, 0, 1)
    assert first.of(inner) == 0  # inlined into outer's program
    assert first.of("outer") == 1


def test_a_wrapper_is_counted_under_the_jitted_function_it_wraps():
    @jax.jit
    def _scaled(x):
        return x * 3.0

    @functools.wraps(_scaled)
    def scaled(x):
        return _scaled(x)

    with compiles() as counted:
        scaled(jnp.ones(2))
        scaled(jnp.ones(2))
    assert counted.of(scaled) == 1


def test_compiles_after_the_block_are_not_counted():
    with compiles() as counted:
        pass
    jax.jit(lambda x: x - 1.0)(jnp.ones(5))
    assert sum(counted.values()) == 0
