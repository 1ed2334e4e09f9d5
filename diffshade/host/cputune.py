"""Two process settings that make XLA on CPU run diffshade's backward passes faster.

Applied once, when diffshade is imported (`apply()`); set DIFFSHADE_CPU_TUNING=0 in the
environment to leave the process untouched. Both were found by profiling the soft
rasterizer's forward + backward pass (docs/soft-rasterization.md, "How it works", "CPU
settings"):

1. XLA's YNNPACK reduce and dot fusions. jaxlib 0.10 hands reductions to YNNPACK, which
   runs the small reductions of a backward pass (the transpose of broadcasting a
   per-fragment scalar to RGB: a reduce over an axis of 3) single-threaded, where XLA's
   own loop emitter is several times faster; and its dots, whose call costs ~45 us even
   for a render's [V, 4] x [4, 4] vertex transforms (the judged scene's projection alone:
   125 us with YNNPACK's dots, 62 us with XLA's; YNNPACK pays off on large matrix
   products, which diffshade does not compute). We add
   `--xla_cpu_experimental_ynn_fusion_type=-reduce,-individual_dot` to XLA_FLAGS, unless
   XLA_FLAGS already names that flag. XLA reads its flags when its CPU client starts, so this only
   takes effect when diffshade is imported before the first JAX computation. jaxlib aborts
   on a flag it does not know, so it is only added for jaxlib versions known to have it.
2. glibc malloc returning XLA's temporary buffer to the kernel after every call. The
   buffer (hundreds of bytes per pixel per K in a soft render's backward pass) is
   allocated with mmap and unmapped when the call ends, so every call page-faults it in
   afresh, a page at a time. mallopt keeps freed memory in the process instead (one arena,
   no mmap for large blocks, no trimming below 1 GiB). The cost: the process keeps its
   peak heap size after large calls, as with jemalloc or tcmalloc.
"""

import ctypes
import os
import sys

YNN_FLAG = "--xla_cpu_experimental_ynn_fusion_type=-reduce,-individual_dot"
#: jaxlib minor versions whose XLA knows the YNN flag (an unknown flag aborts the process)
YNN_JAXLIB = ("0.10",)
# mallopt parameters (glibc malloc.h)
_M_TRIM_THRESHOLD, _M_MMAP_MAX, _M_ARENA_MAX = -1, -4, -8


def enabled() -> bool:
    return os.environ.get("DIFFSHADE_CPU_TUNING", "1") != "0"


def _jaxlib_minor():
    try:
        import jaxlib
        return ".".join(jaxlib.__version__.split(".")[:2])
    except (ImportError, AttributeError):
        return None


def tune_xla_flags() -> bool:
    """Disable YNNPACK reduce and dot fusions in XLA_FLAGS; True if the flag was added."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "ynn_fusion_type" in flags or _jaxlib_minor() not in YNN_JAXLIB:
        return False
    os.environ["XLA_FLAGS"] = f"{flags} {YNN_FLAG}".strip()
    return True


def tune_malloc() -> bool:
    """Keep freed heap memory in the process (glibc only); True if mallopt accepted it."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    return all(mallopt(param, value) == 1 for param, value in
               ((_M_ARENA_MAX, 1), (_M_MMAP_MAX, 0), (_M_TRIM_THRESHOLD, 1 << 30)))


def apply():
    """Apply both settings unless DIFFSHADE_CPU_TUNING=0: {'xla_flags': bool, 'malloc': bool}."""
    if not enabled():
        return {"xla_flags": False, "malloc": False}
    return {"xla_flags": tune_xla_flags(), "malloc": tune_malloc()}
