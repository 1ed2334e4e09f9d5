"""A fresh install's first run: the host kernels compile in the background, the run uses JAX's.

numba compiles the FFI handlers (ffi.py) the first time a program uses them and keeps them
in its cache. On a fresh install that cache is empty, and compiling the handlers of a
render (the hard search, the fragment geometry, the interpolation: COMMAND_TARGETS) costs
tens of seconds of CPU; the same render through the jax.numpy kernels (RenderSettings
kernels='jax') compiles in a few. So the command line (diffshade.cli.program) calls
`cold_start()` first: where numba's cache lacks one of those handlers (`pending`; a textured
command's also the texture lookup's, TEXTURE_TARGETS), it sets
DIFFSHADE_KERNELS=jax in its own environment (settings.AUTO_KERNELS: kernels='auto' then
means 'jax' in that process) and starts `python -m diffshade.host.warmup TARGET ...`, a
detached process of low priority that compiles the pending handlers into numba's cache
(`start`). The runs after it find them there and use the host kernels. The two paths
render the same images (to float rounding: tests/test_tile_search.py, test_transforms.py).

A cold run's programs are compiled for a quick start (`COLD_XLA_FLAGS`, added to XLA_FLAGS
where the user's do not name them): they run once or a few times, the host kernels take over
from the next run on, so their compile time matters more than their speed. XLA's loop
emitters in place of its MLIR fusion emitters take about a third off a README synth's CPU
time, LLVM's -O1 a little more. The flags are the process's (and its children's: synth's
background compilation of its fit), so that every program of the run, `diffshade.render`'s
included, is compiled alike: synth's targets stay the render's bit for bit, and the fit
loads the programs its synth's background compiled (the program store's key holds
XLA_FLAGS). The test suite compiles with the same emitters (tests/conftest.py), so the JAX
kernels' images are held to the host kernels' with them.

The warm-up runs at the lowest priority (`NICENESS`): on a machine of few cores it takes
little from the run that started it, nor from the next command of a script, which finds
the warm-up still running (its lock held) and starts no second one.

Nothing happens where DIFFSHADE_WARMUP=0 or DIFFSHADE_KERNELS is set in the environment,
where 'auto' does not mean the host kernels anyway (another backend, several devices), or
where the handlers are not used (DIFFSHADE_FFI=0, ffi.unavailable). One warm-up process
at a time compiles into a numba cache (a lock file, `lock_path`); a second one exits.
"""

import fcntl
import hashlib
import os
import subprocess
import sys
import tempfile

from diffshade.settings import AUTO_KERNELS, RenderSettings

#: the environment variable that turns the cold start off ("0")
SWITCH = "DIFFSHADE_WARMUP"
#: the FFI targets the commands use with default settings (render, synth and fit: float32
#: hard raster)
COMMAND_TARGETS = ("diffshade_search_hard_f32_i32", "diffshade_geometry_forward_f32",
                   "diffshade_interpolate_forward_f32")
#: the texture lookup's targets, which only a textured command uses (fit --texture, synth
#: --texture, render of a scene with a texture): the others neither wait for them nor
#: compile them
TEXTURE_TARGETS = ("diffshade_texture_forward_f32", "diffshade_texture_backward_f32")
#: XLA's flags for a cold run's programs (module docstring)
COLD_XLA_FLAGS = ("--xla_cpu_use_fusion_emitters=false", "--xla_backend_optimization_level=1")
#: the warm-up process's niceness, the lowest priority: where it shares a core with the run
#: it was started by, it takes ~1.5 % of it (niceness 10: ~10 %); not the idle scheduling
#: policy, under which a busy machine would starve it for hours
NICENESS = 19


def pending(targets=COMMAND_TARGETS):
    """The targets whose handler numba's cache does not hold (a list, in order). Asks the
    cache's index without compiling or loading anything; where the index cannot be read,
    none are pending (the run then compiles what it needs, as without a cold start)."""
    from numba.core.caching import FunctionCache
    from numba.core.registry import cpu_target

    from diffshade.host import ffi

    try:
        codegen = cpu_target.target_context.codegen()
        missing = []
        for target in targets:
            cache = FunctionCache(ffi.HANDLERS[target])
            index = cache._cache_file._load_index()  # numba's own cache lookup, less the load
            if cache._index_key(ffi.SIGNATURE, codegen) not in index:
                missing.append(target)
        return missing
    except Exception:  # another numba's cache internals: behave as before the cold start
        return []


def _switched_on():
    """Whether the environment leaves the cold start on (module docstring)."""
    from diffshade.host import ffi, hostcall

    if os.environ.get(SWITCH) == "0" or os.environ.get(AUTO_KERNELS):
        return False
    return os.environ.get(hostcall.FFI_SWITCH) != "0" and ffi.unavailable() is None


def applies():
    """Whether a command run may start cold (module docstring: what turns it off). Asks
    which backend 'auto' kernels find, which starts XLA."""
    return _switched_on() and RenderSettings().use_host_kernels()


def command_targets(argv):
    """The targets a command line (argv, less the program) uses: COMMAND_TARGETS, and
    TEXTURE_TARGETS where it asks for a texture (--texture: fit, synth). A render of a
    scene file with textures finds them when it has read the scene (cold_start there)."""
    textured = any(a == "--texture" or a.startswith("--texture=") for a in argv)
    return COMMAND_TARGETS + (TEXTURE_TARGETS if textured else ())


def cold_start(targets=COMMAND_TARGETS):
    """For a command run: where the host kernels it uses (`targets`) are not compiled
    yet, run this process on the JAX kernels, compiled for a quick start where XLA has not
    started yet (COLD_XLA_FLAGS), and start compiling the host kernels in the background
    (unless a warm-up of this cache is compiling already: a later run compiles the rest).
    Returns the targets not compiled yet (empty: nothing changed)."""
    if not _switched_on():
        return []
    missing = pending(targets)
    if not missing:
        return []
    if not _xla_started() and _one_cpu_device_ahead():
        compile_for_a_quick_start()  # before applies() starts XLA, which reads the flags once
    if not applies():
        return []
    os.environ[AUTO_KERNELS] = "jax"
    if not running():
        start(missing)
    return missing


def _xla_started() -> bool:
    """Whether XLA's client has started in this process (it has read XLA_FLAGS then);
    unknown (another JAX's internals): True."""
    try:
        from jax._src import xla_bridge

        return xla_bridge.backends_are_initialized()
    except (ImportError, AttributeError):
        return True


def _one_cpu_device_ahead() -> bool:
    """Whether XLA, once started, will run on a single CPU device (where 'auto' means the
    host kernels), judged before it starts: the first platform JAX_PLATFORMS names, else
    no accelerator plugin of JAX's installed; and no count of host devices asked for (in
    XLA_FLAGS or jax_num_cpu_devices)."""
    import importlib.metadata
    import importlib.util

    import jax

    if "xla_force_host_platform_device_count" in os.environ.get("XLA_FLAGS", ""):
        return False
    if getattr(jax.config, "jax_num_cpu_devices", -1) not in (-1, 1):
        return False
    if jax.config.jax_platforms:
        return jax.config.jax_platforms.split(",")[0].strip() == "cpu"
    return (importlib.util.find_spec("jax_plugins") is None
            and importlib.util.find_spec("libtpu") is None
            and not importlib.metadata.entry_points(group="jax_plugins"))


def compile_for_a_quick_start():
    """Add COLD_XLA_FLAGS to XLA_FLAGS, each unless XLA_FLAGS names its option already
    (the user's choice stands)."""
    flags = os.environ.get("XLA_FLAGS", "")
    named = {flag.split("=")[0].lstrip("-") for flag in flags.split()}
    added = [flag for flag in COLD_XLA_FLAGS if flag.split("=")[0].lstrip("-") not in named]
    os.environ["XLA_FLAGS"] = " ".join([flags, *added]).strip()


def start(targets):
    """Start the detached warm-up process compiling `targets` into numba's cache."""
    env = {k: v for k, v in os.environ.items() if k != AUTO_KERNELS}
    subprocess.Popen([sys.executable, "-m", "diffshade.host.warmup", *targets], env=env,
                     stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                     stderr=subprocess.DEVNULL, start_new_session=True)


def lock_path():
    """The lock file of the warm-ups of this numba cache (NUMBA_CACHE_DIR, else the one
    beside the package): held while one compiles."""
    from diffshade.host import ffi

    place = os.environ.get("NUMBA_CACHE_DIR", "") + "\0" + os.path.abspath(ffi.__file__)
    digest = hashlib.sha256(place.encode()).hexdigest()[:16]
    return os.path.join(tempfile.gettempdir(), f"diffshade-warmup-{os.getuid()}-{digest}.lock")


def running():
    """Whether a warm-up of this numba cache holds its lock (is compiling) now."""
    with open(lock_path(), "a") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
        fcntl.flock(lock, fcntl.LOCK_UN)
        return False


def wait():
    """Return once no warm-up of this numba cache is compiling (benchmarks time the runs
    after one)."""
    with open(lock_path(), "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)


def compile_targets(targets):
    """Compile the handlers of `targets` into numba's cache, unless another warm-up of
    this cache holds the lock; True where they were compiled here."""
    from diffshade.host import ffi

    with open(lock_path(), "a") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return False
        for target in targets:
            ffi.compile_handler(target)
        return True


def lower_priority():
    """Run this process at NICENESS, and its session too where Linux groups by session.

    Under the kernel's autogroup scheduling (on by default in desktop distributions), the
    CPU is shared between sessions first and a process's niceness ranks it only within its
    own. The warm-up runs in a session of its own (`start`), so its niceness alone would
    still give it a core that the command's session wanted: with a second process there
    (synth's background compilation of its fit, data_synth.background) the two commands'
    processes shared one core while the warm-up had the other. So it also sets its
    session's autogroup niceness (/proc/self/autogroup, which any process may raise) —
    only where it leads its session, so that `python -m diffshade.host.warmup` typed in a
    terminal does not slow the terminal's other work. Where that file is absent or
    refuses, its own niceness is all there is."""
    os.nice(NICENESS)
    if os.getsid(0) != os.getpid():
        return
    try:
        with open("/proc/self/autogroup", "w") as autogroup:
            autogroup.write(str(NICENESS))
    except OSError:
        pass


def main(argv):
    """python -m diffshade.host.warmup [TARGET ...] (default: COMMAND_TARGETS)."""
    from diffshade.host import ffi

    unknown = [t for t in argv if t not in ffi.TARGETS]
    if unknown:
        raise SystemExit(f"diffshade.host.warmup: got targets {unknown}; expected names of "
                         "diffshade.host.ffi.TARGETS")
    lower_priority()
    compile_targets(argv or COMMAND_TARGETS)


if __name__ == "__main__":
    main(sys.argv[1:])
