"""Counting XLA compilations through JAX's public monitoring hooks.

`with compiles() as counted:` registers a listener with
`jax.monitoring.register_event_duration_secs_listener` for the block; JAX records the
backend-compile event once per program it hands to XLA (a jit cache miss that gets as far
as compiling), with the jitted function's name. `counted.of(fun)` is how many programs of
`fun` (a jitted function, a function wrapped with functools.wraps around one, or its bare
name) were compiled in the block: a second call that recompiles shows as one more.
Nested jits are part of their caller's program and are not counted on their own.

This replaces reading a jitted function's private `_cache_size()`. test_compiles.py checks
that the counter sees a fresh compile, a recompile for new shapes, and no compile for a
call that hits the cache, so that a count of 0 elsewhere cannot pass because JAX stopped
recording the event.
"""

import collections
import contextlib

import jax

#: the event JAX records around each XLA compilation (jax._src.dispatch.BACKEND_COMPILE_EVENT)
BACKEND_COMPILE = "/jax/core/compile/backend_compile_duration"


class Compiles(collections.Counter):
    """Compilations per program name ('jit(name)', as JAX reports them)."""

    def of(self, fun) -> int:
        """Programs of `fun` compiled: fun a jitted function (or a functools.wraps
        wrapper of one, named after it) or a function's bare name."""
        name = fun if isinstance(fun, str) else fun.__name__
        return self[f"jit({name})"]


@contextlib.contextmanager
def compiles():
    """Yield a Compiles counter that the compilations inside the block increment."""
    counted = Compiles()

    def listen(event, duration, fun_name="", **kwargs):
        if event == BACKEND_COMPILE:
            counted[fun_name] += 1

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        yield counted
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
