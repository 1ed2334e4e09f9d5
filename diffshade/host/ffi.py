"""The host kernels as XLA FFI targets: compiled handlers XLA calls with its own buffers.

Through a Python callback (hostcall.py), every call of a host kernel under `jit` goes
from XLA's thread into Python (the GIL), wraps the operands as NumPy arrays, runs the
kernel, and XLA copies the kernel's freshly allocated results into its own buffers: ~1 ms
per call of the geometry kernels of a 256^2, K = 8 soft render (~10 MB of results), on
top of the kernel. As an XLA FFI custom call (`jax.ffi`), XLA calls a compiled handler
with the addresses of its operand and result buffers: the kernel reads and writes them
in place, with no Python, no GIL and no copy.

Each handler here is a numba `cfunc` with XLA's FFI handler signature,
`XLA_FFI_Error* handler(XLA_FFI_CallFrame*)`. It reads the call frame as int64 words
(XLA's C API, xla/ffi/api/c_api.h, as jaxlib 0.10 ships it; `FRAME_*` below), answers
XLA's metadata query (the FFI API version, asked once when the target is registered),
and otherwise wraps each buffer as an array of its dtype and shape and calls the kernel.
Static settings (image size, K, flags) travel as int64 attributes named a0, a1, ...
(XLA passes attributes sorted by name), then numba's thread count. Float operands are
float32, or float64 under x64: a target per dtype (`target_for`).

A target is compiled (or loaded from numba's cache) and registered with XLA the first
time a program using it is lowered (`lowering`), so importing diffshade compiles nothing.
Targets exist for the CPU only. hostcall.host_call uses the Python callback instead on
other platforms, for operand types no handler takes, with JAX versions other than the
one this layout was read from (hostcall.NO_COPY_JAX), with numba's workqueue threading
layer (`available`), and where the environment sets DIFFSHADE_FFI=0.
"""

import threading

import jax
import numba
import numpy as np
from numba import carray, cfunc, types
from numba.core import cgutils
from numba.extending import intrinsic

from diffshade.host import active_kernel, candidates
from diffshade.host import fragment_kernels as kernels
from diffshade.numerics import tiny

# XLA_FFI_CallFrame as int64 words: struct_size, extension_start, api, ctx, stage; then
# XLA_FFI_Args (struct_size, extension_start, size, types, args), XLA_FFI_Rets (same,
# rets) and XLA_FFI_Attrs (struct_size, extension_start, size, types, names, attrs)
FRAME_WORDS, FRAME_EXTENSION, FRAME_ARGS, FRAME_RETS, FRAME_ATTRS = 21, 1, 9, 14, 20
# XLA_FFI_Buffer as int64 words: struct_size, extension_start, dtype, data, rank, dims
BUFFER_DTYPE, BUFFER_DATA, BUFFER_RANK, BUFFER_DIMS = 2, 3, 4, 5
# XLA_FFI_DataType of float64 (the handlers that read a float argument of either width)
F64 = 12
# XLA_FFI_Extension_Metadata; the FFI API version the handlers declare (XLA accepts 0.1
# up to its own, 0.3 in jaxlib 0.10)
METADATA_EXTENSION, API_MAJOR, API_MINOR = 1, 0, 1
#: the attribute lowering appends to every call: numba's thread count when lowered (the
#: kernels' parallel parts; numba.get_num_threads in a handler would keep numba from
#: caching it)
THREADS = -1

_SIGNATURE = types.voidptr(types.voidptr)
#: numerics.tiny of each float dtype (numba freezes them as constants)
_TINY32, _TINY64 = tiny(np.float32), tiny(np.float64)


@intrinsic
def _pointer(typingctx, address):
    """An int64 address (or a void pointer, unchanged) as a void pointer (for carray)."""
    if address == types.voidptr:
        return types.voidptr(address), lambda context, builder, signature, args: args[0]
    if not isinstance(address, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        return builder.inttoptr(args[0], cgutils.voidptr_t)
    return types.voidptr(address), codegen


@numba.njit(cache=True, nogil=True, inline="always")
def _words(address, count):
    return carray(_pointer(address), (count,), np.int64)


@numba.njit(cache=True, nogil=True)
def _answered_metadata(frame):
    """Whether the call is XLA's metadata query (then answered: the API version the
    handler implements, no traits). XLA_FFI_Metadata_Extension: the extension base
    (struct_size, type, next) and a pointer to XLA_FFI_Metadata (struct_size, then
    XLA_FFI_Api_Version: struct_size, extension_start, major, minor (int32 each), then the
    traits (uint32))."""
    if frame[FRAME_EXTENSION] == 0:
        return False
    extension = _words(frame[FRAME_EXTENSION], 4)
    if (extension[1] & 0xFFFFFFFF) != METADATA_EXTENSION:
        return False
    metadata = carray(_pointer(extension[3]), (9,), np.int32)
    metadata[6], metadata[7], metadata[8] = API_MAJOR, API_MINOR, 0
    return True


@numba.njit(cache=True, nogil=True, inline="always")
def _buffer(frame, which, index):
    """The XLA_FFI_Buffer words of argument (which = FRAME_ARGS) or result (FRAME_RETS)
    `index`."""
    return _words(_words(frame[which], index + 1)[index], 6)


@numba.njit(cache=True, nogil=True, inline="always")
def _size(buffer):
    """Number of elements."""
    rank = buffer[BUFFER_RANK]
    dims = _words(buffer[BUFFER_DIMS], max(rank, 1))
    n = 1
    for i in range(rank):
        n *= dims[i]
    return n


@numba.njit(cache=True, nogil=True, inline="always")
def _dim(buffer, axis):
    """Size of an axis (negative: from the end)."""
    rank = buffer[BUFFER_RANK]
    return _words(buffer[BUFFER_DIMS], rank)[axis % rank]


@numba.njit(cache=True, nogil=True, inline="always")
def _attribute(frame, index):
    """int64 attribute `index` (a0, a1, ... in name order; negative: from the end): an
    XLA_FFI_Scalar (dtype, value pointer)."""
    index = index + frame[FRAME_ATTRS - 3] if index < 0 else index  # from the end
    scalar = _words(_words(frame[FRAME_ATTRS], index + 1)[index], 2)
    return _words(scalar[1], 1)[0]


@numba.njit(cache=True, nogil=True, inline="always")
def _dtype(frame, which, index):
    return _buffer(frame, which, index)[BUFFER_DTYPE] & 0xFFFFFFFF


@numba.njit(cache=True, nogil=True, inline="always")
def _array2(frame, which, index, tail, dtype):
    """A buffer as [N / tail, tail] of `dtype`."""
    b = _buffer(frame, which, index)
    return carray(_pointer(b[BUFFER_DATA]), (_size(b) // tail, tail), dtype)


@numba.njit(cache=True, nogil=True, inline="always")
def _array3(frame, which, index, middle, tail, dtype):
    """A buffer as [N / (middle * tail), middle, tail] of `dtype`."""
    b = _buffer(frame, which, index)
    return carray(_pointer(b[BUFFER_DATA]), (_size(b) // (middle * tail), middle, tail),
                  dtype)


@numba.njit(cache=True, nogil=True, inline="always")
def _flat(frame, which, index, dtype):
    b = _buffer(frame, which, index)
    return carray(_pointer(b[BUFFER_DATA]), (_size(b),), dtype)


# -- fragment geometry (raster.fragment_geometry) ------------------------------------------
# arguments: ids [R, W, K] int32, corner_w [F, 3], corner_z [F, 3], coeffs [F, 3, 3], scr
# [F, 3, 2]; attributes: width, height, soft. Forward results: bary [R, W, K, 3], depth
# and dist [R, W, K]; backward: cotangents of those three follow the arguments, results
# are the gradients of the four per-face arrays.

@numba.njit(cache=True, nogil=True)
def _geometry_inputs(frame, dtype):
    """(ids [P, K], corner_w, corner_z, coeffs, scr, width, height, soft): the kernels'
    leading arguments."""
    k = _dim(_buffer(frame, FRAME_ARGS, 0), -1)
    return (_array2(frame, FRAME_ARGS, 0, k, np.int32), _array2(frame, FRAME_ARGS, 1, 3, dtype),
            _array2(frame, FRAME_ARGS, 2, 3, dtype), _array3(frame, FRAME_ARGS, 3, 3, 3, dtype),
            _array3(frame, FRAME_ARGS, 4, 3, 2, dtype), _attribute(frame, 0),
            _attribute(frame, 1), _attribute(frame, 2) != 0)


@numba.njit(cache=True, nogil=True)
def _geometry_forward(frame, dtype, tiny):
    ids, corner_w, corner_z, coeffs, scr, width, height, soft = _geometry_inputs(frame, dtype)
    k = ids.shape[1]
    kernels.geometry_forward_into(
        ids, corner_w, corner_z, coeffs, scr, width, height, soft, tiny,
        _attribute(frame, THREADS), _array3(frame, FRAME_RETS, 0, k, 3, dtype),
        _array2(frame, FRAME_RETS, 1, k, dtype), _array2(frame, FRAME_RETS, 2, k, dtype))


@numba.njit(cache=True, nogil=True)
def _geometry_backward(frame, dtype, tiny):
    ids, corner_w, corner_z, coeffs, scr, width, height, soft = _geometry_inputs(frame, dtype)
    k = ids.shape[1]
    kernels.geometry_backward_into(
        ids, corner_w, corner_z, coeffs, scr, width, height, soft, tiny,
        _attribute(frame, THREADS), _array3(frame, FRAME_ARGS, 5, k, 3, dtype),
        _array2(frame, FRAME_ARGS, 6, k, dtype), _array2(frame, FRAME_ARGS, 7, k, dtype),
        _array2(frame, FRAME_RETS, 0, 3, dtype), _array2(frame, FRAME_RETS, 1, 3, dtype),
        _array3(frame, FRAME_RETS, 2, 3, 3, dtype), _array3(frame, FRAME_RETS, 3, 3, 2, dtype))


# -- interpolation (interpolate.interpolate_corners) ---------------------------------------
# arguments: ids [R, W, K] int32, bary [R, W, K, 3], corners [F, 3, C]; forward result
# [R, W, K, C]; backward: the cotangent [R, W, K, C] follows, results g_bary and g_corners.

@numba.njit(cache=True, nogil=True)
def _interpolate_forward(frame, dtype):
    k = _dim(_buffer(frame, FRAME_ARGS, 0), -1)
    c = _dim(_buffer(frame, FRAME_ARGS, 2), -1)
    kernels.interpolate_forward_into(
        _array2(frame, FRAME_ARGS, 0, k, np.int32), _array3(frame, FRAME_ARGS, 1, k, 3, dtype),
        _array3(frame, FRAME_ARGS, 2, 3, c, dtype), _attribute(frame, THREADS),
        _array3(frame, FRAME_RETS, 0, k, c, dtype))


@numba.njit(cache=True, nogil=True)
def _interpolate_backward(frame, dtype):
    k = _dim(_buffer(frame, FRAME_ARGS, 0), -1)
    c = _dim(_buffer(frame, FRAME_ARGS, 2), -1)
    kernels.interpolate_backward_into(
        _array2(frame, FRAME_ARGS, 0, k, np.int32), _array3(frame, FRAME_ARGS, 1, k, 3, dtype),
        _array3(frame, FRAME_ARGS, 2, 3, c, dtype), _array3(frame, FRAME_ARGS, 3, k, c, dtype),
        _attribute(frame, THREADS), _array3(frame, FRAME_RETS, 0, k, 3, dtype),
        _array3(frame, FRAME_RETS, 1, 3, c, dtype))


# -- active slots (compact.active_indices) --------------------------------------------------
# argument: mask [N] bool; results: indices [capacity] int32, count [] int32

@numba.njit(cache=True, nogil=True)
def _active(frame):
    active_kernel.first_active_into(_flat(frame, FRAME_ARGS, 0, np.bool_),
                                    _flat(frame, FRAME_RETS, 0, np.int32),
                                    _flat(frame, FRAME_RETS, 1, np.int32))


# -- candidate search (raster.search.search_faces) ------------------------------------------
# arguments: clip [*B, V, 4], faces [*B, F, 3] int32 or int64, near, far, radius, sigma and
# gamma [*B] (each broadcast against the batch shape B); attributes: width, height, k,
# cull_backfaces, perspective. Results: face ids [*B, H, W, k] int32, dropped [*B] int32.
# The soft target runs the soft search whatever the radius (find_candidates picks the
# hard one where every radius is 0: settings never give a soft render that radius).

@numba.njit(cache=True, nogil=True)
def _member(view, lead, buffer, core):
    """Index into argument `buffer` (leading axes broadcast against the batch shape
    `lead`, then `core` axes of its own) of batch member `view` (row-major in lead)."""
    rank = buffer[BUFFER_RANK]
    dims = _words(buffer[BUFFER_DIMS], max(rank, 1))
    axes = rank - core
    index, stride, rest = 0, 1, view
    for axis in range(lead.shape[0] - 1, -1, -1):
        coordinate = rest % lead[axis]
        rest //= lead[axis]
        own = axis - (lead.shape[0] - axes)
        if own >= 0:
            if dims[own] > 1:
                index += coordinate * stride
            stride *= dims[own]
    return index


@numba.njit(cache=True, nogil=True)
def _per_view(frame, index, lead, views):
    """Argument `index` ([*B], broadcast; float32 or float64) as float64 [views]."""
    buffer = _buffer(frame, FRAME_ARGS, index)
    out = np.empty(views)
    if (buffer[BUFFER_DTYPE] & 0xFFFFFFFF) == F64:
        values64 = _flat(frame, FRAME_ARGS, index, np.float64)
        for v in range(views):
            out[v] = values64[_member(v, lead, buffer, 0)]
    else:
        values32 = _flat(frame, FRAME_ARGS, index, np.float32)
        for v in range(views):
            out[v] = values32[_member(v, lead, buffer, 0)]
    return out


@numba.njit(cache=True, nogil=True)
def _search_inputs(frame, dtype, face_dtype):
    """What the search of every view needs: (ids [views * H * W * k], dropped [views],
    views, groups (1: one mesh for every view, else one per view), faces of group g
    (_group_faces), clips [views, V, 4], radii [views], params [views, 4] (sigma, gamma,
    near, far), width, height, k, cull, perspective, threads)."""
    ids = _flat(frame, FRAME_RETS, 0, np.int32)
    out_dropped = _buffer(frame, FRAME_RETS, 1)
    dropped = _flat(frame, FRAME_RETS, 1, np.int32)
    views = dropped.shape[0]
    lead = _words(out_dropped[BUFFER_DIMS], max(out_dropped[BUFFER_RANK], 1)).copy()
    if out_dropped[BUFFER_RANK] == 0:
        lead[0] = 1
    clip_buffer, face_buffer = _buffer(frame, FRAME_ARGS, 0), _buffer(frame, FRAME_ARGS, 1)
    clip_in = _array3(frame, FRAME_ARGS, 0, _dim(clip_buffer, -2), 4, dtype)
    clips = np.empty((views, clip_in.shape[1], 4))
    for v in range(views):
        clips[v] = clip_in[_member(v, lead, clip_buffer, 2)]
    faces_in = _array3(frame, FRAME_ARGS, 1, _dim(face_buffer, -2), 3, face_dtype)
    groups = 1 if faces_in.shape[0] == 1 else views
    faces = np.empty((groups, faces_in.shape[1], 3), np.int64)
    for g in range(groups):
        faces[g] = faces_in[_member(g, lead, face_buffer, 2) if groups > 1 else 0]
    near, far = _per_view(frame, 2, lead, views), _per_view(frame, 3, lead, views)
    radii = _per_view(frame, 4, lead, views)
    params = np.empty((views, 4))
    params[:, 0] = _per_view(frame, 5, lead, views)
    params[:, 1] = _per_view(frame, 6, lead, views)
    params[:, 2], params[:, 3] = near, far
    return (ids, dropped, views, faces, clips, radii, params, _attribute(frame, 0),
            _attribute(frame, 1), _attribute(frame, 2), _attribute(frame, 3) != 0,
            _attribute(frame, 4) != 0, _attribute(frame, THREADS))


@numba.njit(cache=True, nogil=True, inline="always")
def _write_group(ids, dropped, g, per_group, found, lost):
    """Group g's face ids and dropped counts into the results."""
    pixels = found.shape[1] * found.shape[2]
    ids[g * per_group * pixels:(g + 1) * per_group * pixels] = found.reshape(-1)
    for v in range(per_group):
        dropped[g * per_group + v] = lost[v]


# the soft and the hard search are separate targets, so that a program compiles only the
# kernel it uses; views of one mesh are searched in one call, else one call per view


@numba.njit(cache=True, nogil=True)
def _search_soft(frame, dtype, face_dtype):
    (ids, dropped, views, faces, clips, radii, params, width, height, k, cull, perspective,
     _) = _search_inputs(frame, dtype, face_dtype)
    per_group = views // faces.shape[0]
    pixels = width * height
    for g in range(faces.shape[0]):
        chosen = slice(g * per_group, (g + 1) * per_group)
        found = ids[g * per_group * pixels * k:(g + 1) * per_group * pixels * k]
        lost = candidates._search_soft_into(clips[chosen], faces[g], width, height, k, cull,
                                            radii[chosen], params[chosen], perspective,
                                            found.reshape((per_group, pixels, k)))
        for v in range(per_group):
            dropped[g * per_group + v] = lost[v]


@numba.njit(cache=True, nogil=True)
def _search_hard(frame, dtype, face_dtype):
    (ids, dropped, views, faces, clips, _, _, width, height, k, cull, _,
     threads) = _search_inputs(frame, dtype, face_dtype)
    per_group = views // faces.shape[0]
    for g in range(faces.shape[0]):
        chosen = slice(g * per_group, (g + 1) * per_group)
        found, lost = candidates._search_hard(clips[chosen], faces[g], width, height, k, cull,
                                              min(height, 2 * threads))
        _write_group(ids, dropped, g, per_group, found, lost)


#: the handlers' bodies, by the number a handler is made with (_handler)
_BODIES = ("active", "geometry_forward", "geometry_backward", "interpolate_forward",
           "interpolate_backward", "search_soft", "search_hard")


def _handler(name, body, dtype=np.float32, other=np.int32):
    """The FFI handler `name`: answers XLA's metadata query, else runs the body
    _BODIES[body] on the frame with dtype (and `other`: the geometry's tiny, the
    search's face dtype). A closure per target over plain constants, which numba freezes:
    the branches of the other bodies are pruned before compiling, and the constants are
    part of the cache's key (a closure over the body's dispatcher would not be cached)."""
    def handler(address):
        frame = _words(address, FRAME_WORDS)
        if _answered_metadata(frame):
            return _pointer(0)
        if body == 0:
            _active(frame)
        elif body == 1:
            _geometry_forward(frame, dtype, other)
        elif body == 2:
            _geometry_backward(frame, dtype, other)
        elif body == 3:
            _interpolate_forward(frame, dtype)
        elif body == 4:
            _interpolate_backward(frame, dtype)
        elif body == 5:
            _search_soft(frame, dtype, other)
        else:
            _search_hard(frame, dtype, other)
        return _pointer(0)
    handler.__name__ = handler.__qualname__ = f"_handler_{name}"
    return handler


#: target name -> handler (compiled on first use); a target per operand dtype, so that a
#: program compiles only the dtypes it uses
_HANDLERS = {"diffshade_active": _handler("active", 0)}
for _width, _dtype, _tiny in (("f32", np.float32, _TINY32), ("f64", np.float64, _TINY64)):
    for _body in range(1, 5):
        _name = f"{_BODIES[_body]}_{_width}"
        _HANDLERS[f"diffshade_{_name}"] = _handler(_name, _body, _dtype, _tiny)
    for _ints, _int in (("i32", np.int32), ("i64", np.int64)):
        for _body in (5, 6):
            _name = f"{_BODIES[_body]}_{_width}_{_ints}"
            _HANDLERS[f"diffshade_{_name}"] = _handler(_name, _body, _dtype, _int)
_REGISTERED = {}
_REGISTERING = threading.Lock()


def available() -> bool:
    """Whether the handlers may be used (the JAX version is hostcall's check): a numba
    threading layer that runs parallel kernels started from two threads at once (OpenMP
    or TBB: XLA may run two independent custom calls together, where the host callbacks
    take a lock; numba's fallback layer, workqueue, aborts on that)."""
    numba.get_num_threads()  # starts the threading layer
    return numba.threading_layer() in ("omp", "tbb")


def target_for(base, args):
    """The target of `base` (geometry_forward, search, ...) for operands `args`, or None
    where no handler takes their dtypes: float32 or float64 (one of them for all of a
    call's float operands, but the search's per-view scalars), int32 face ids, bool masks,
    the search's faces int32 or int64."""
    dtypes = [np.dtype(a.dtype) for a in args]
    floats = {d for d in dtypes if d.kind == "f"}
    width = {np.dtype(np.float32): "f32", np.dtype(np.float64): "f64"}
    if not floats <= set(width):
        return None
    if base in ("search_soft", "search_hard"):
        ints = {np.dtype(np.int32): "i32", np.dtype(np.int64): "i64"}
        if dtypes[0].kind != "f" or dtypes[1] not in ints:
            return None
        return f"diffshade_{base}_{width[dtypes[0]]}_{ints[dtypes[1]]}"
    if base == "active":
        return "diffshade_active" if dtypes == [np.dtype(np.bool_)] else None
    if len(floats) != 1 or not all(d.kind == "f" or d == np.int32 for d in dtypes):
        return None
    return f"diffshade_{base}_{width[floats.pop()]}"


def _register(target):
    """Compile (or load from numba's cache) and register a handler, once per process (a
    lock: two threads may lower programs at once)."""
    with _REGISTERING:
        if target in _REGISTERED:
            return
        # starts numba's threading layer, which defines the symbols (allocate_sched, ...)
        # that the parallel kernels' code refers to: a cfunc loaded from numba's cache
        # does not start it
        numba.get_num_threads()
        handler = cfunc(_SIGNATURE, nogil=True, cache=True)(_HANDLERS[target])
        jax.ffi.register_ffi_target(target, jax.ffi.pycapsule(handler.address),
                                    platform="cpu")
        _REGISTERED[target] = handler  # kept alive: XLA holds only its address


def lowering(ctx, operands, target, attributes):
    """The MLIR of a call of `target` (registered on first use) with int attributes
    a0, a1, ... = attributes, then numba's thread count (THREADS)."""
    _register(target)
    values = (*attributes, numba.get_num_threads())
    assert len(values) <= 10, "a10 would sort before a2: the handlers read by position"
    named = {f"a{i}": np.int64(int(value)) for i, value in enumerate(values)}
    return jax.ffi.ffi_lowering(target)(ctx, *operands, **named)


