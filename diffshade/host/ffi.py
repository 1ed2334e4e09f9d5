"""The host kernels as XLA FFI targets: compiled handlers XLA calls with its own buffers.

Through a Python callback (hostcall.py), every call of a host kernel under `jit` goes
from XLA's thread into Python (the GIL), wraps the operands as NumPy arrays, runs the
kernel, and XLA copies the kernel's freshly allocated results into its own buffers: ~1 ms
per call of the geometry kernels of a 256^2, K = 8 soft render (~10 MB of results), on
top of the kernel. As an XLA FFI custom call (`jax.ffi`), XLA calls a compiled handler
with the addresses of its operand and result buffers: the kernel reads and writes them
in place, with no Python, no GIL and no copy.

Each handler here is a numba `cfunc` with XLA's FFI handler signature,
`XLA_FFI_Error* handler(XLA_FFI_CallFrame*)`, reading the call frame through xla_ffi (the
layout of xla/ffi/api/c_api.h, checked against the installed header by the tests). Before
it touches a buffer it checks the call against its `Target`: the frame's struct_size and
the FFI API version XLA reports, the execution stage, the number of arguments and
results, each buffer's dtype, rank, fixed trailing dims and size against the others, and
the int64 attributes it reads by name (ffi_check). A mismatch is returned as an
XLA_FFI_Error naming the target and what it expected, which `jit` raises in Python. It
answers XLA's metadata query (the FFI API version of that header, asked once when the
target is registered), and otherwise wraps each buffer as an array of its dtype and shape
and calls the kernel. Static settings (image size, K, flags) travel as int64 attributes
named as in Target.attrs, then numba's thread count (THREADS). Float operands are float32,
or float64 under x64: a target per dtype (`target_for`).

A target is compiled (or loaded from numba's cache) and registered with XLA the first
time a program using it is lowered (`lowering`), so importing diffshade compiles nothing.
Targets exist for the CPU only. hostcall.host_call uses the Python callback instead on
other platforms, for operand types no handler takes, where `unavailable` says why not (a
jaxlib whose FFI API major version differs, or whose minor version is older than the
layout's; numba's workqueue threading layer; hostcall warns), and where the environment
sets DIFFSHADE_FFI=0.
"""

import threading
from typing import NamedTuple

import jax
import numba
import numpy as np
from numba import carray, cfunc, types

from diffshade.host import active_kernel, candidates, texture_kernels, xla_ffi
from diffshade.host import fragment_kernels as kernels
from diffshade.host.ffi_check import (
    ANY,
    BATCH,
    FLOAT,
    IMAGES,
    PER_LAST,
    TIMES,
    check,
    spec,
    tables,
)
from diffshade.host.xla_ffi import (
    BUFFER_DATA,
    BUFFER_DIMS,
    BUFFER_DTYPE,
    BUFFER_RANK,
    F32,
    F64,
    FRAME_ARGS,
    FRAME_RETS,
    PRED,
    S8,
    S32,
    S64,
    address_of,
    buffer_dim,
    buffer_size,
    error,
    int32,
    item,
    metadata_query,
    pointer,
    word,
    words,
)
from diffshade.numerics import tiny

#: the attribute lowering appends to every call: numba's thread count when lowered (the
#: kernels' parallel parts; numba.get_num_threads in a handler would keep numba from
#: caching it)
THREADS = "threads"

#: the C signature of an FFI handler: XLA_FFI_Error* (XLA_FFI_CallFrame*)
SIGNATURE = types.voidptr(types.voidptr)
#: numerics.tiny of each float dtype (numba freezes them as constants)
_TINY32, _TINY64 = tiny(np.float32), tiny(np.float64)


@numba.njit(cache=True, nogil=True, inline="always")
def _array2(frame, which, index, tail, dtype):
    """Argument (which = FRAME_ARGS) or result (FRAME_RETS) `index` as [N / tail, tail] of
    `dtype`."""
    b = item(frame, which, index)
    return carray(pointer(word(b, BUFFER_DATA)), (buffer_size(b) // tail, tail), dtype)


@numba.njit(cache=True, nogil=True, inline="always")
def _array3(frame, which, index, middle, tail, dtype):
    """A buffer as [N / (middle * tail), middle, tail] of `dtype`."""
    b = item(frame, which, index)
    return carray(pointer(word(b, BUFFER_DATA)),
                  (buffer_size(b) // (middle * tail), middle, tail), dtype)


@numba.njit(cache=True, nogil=True, inline="always")
def _flat(frame, which, index, dtype):
    b = item(frame, which, index)
    return carray(pointer(word(b, BUFFER_DATA)), (buffer_size(b),), dtype)


# -- fragment geometry (raster.fragment_geometry) ------------------------------------------
# arguments: ids [R, W, K] int32, corner_w [F, 3], corner_z [F, 3], coeffs [F, 3, 3], scr
# [F, 3, 2]; attributes: width, height, soft. Forward results: bary [R, W, K, 3], depth
# and dist [R, W, K], the nearest edges [R, W, K] int8; backward: the nearest edges, then
# the cotangents of bary, depth and dist follow the arguments, results are the gradients
# of the four per-face arrays.

@numba.njit(cache=True, nogil=True)
def _geometry_inputs(frame, values, dtype):
    """(ids [P, K], corner_w, corner_z, coeffs, scr, width, height, soft): the kernels'
    leading arguments (values: the attributes, as Target.attrs names them)."""
    k = buffer_dim(item(frame, FRAME_ARGS, 0), -1)
    return (_array2(frame, FRAME_ARGS, 0, k, np.int32), _array2(frame, FRAME_ARGS, 1, 3, dtype),
            _array2(frame, FRAME_ARGS, 2, 3, dtype), _array3(frame, FRAME_ARGS, 3, 3, 3, dtype),
            _array3(frame, FRAME_ARGS, 4, 3, 2, dtype), values[0], values[1], values[2] != 0)


@numba.njit(cache=True, nogil=True)
def _geometry_forward(frame, values, dtype, tiny):
    ids, corner_w, corner_z, coeffs, scr, width, height, soft = _geometry_inputs(frame, values,
                                                                                 dtype)
    k = ids.shape[1]
    kernels.geometry_forward_into(
        ids, corner_w, corner_z, coeffs, scr, width, height, soft, tiny,
        values[3], _array3(frame, FRAME_RETS, 0, k, 3, dtype),
        _array2(frame, FRAME_RETS, 1, k, dtype), _array2(frame, FRAME_RETS, 2, k, dtype),
        _array2(frame, FRAME_RETS, 3, k, np.int8))


@numba.njit(cache=True, nogil=True)
def _geometry_backward(frame, values, dtype, tiny):
    ids, corner_w, corner_z, coeffs, scr, width, height, soft = _geometry_inputs(frame, values,
                                                                                 dtype)
    k = ids.shape[1]
    kernels.geometry_backward_into(
        ids, corner_w, corner_z, coeffs, scr, width, height, soft, tiny,
        values[3], _array2(frame, FRAME_ARGS, 5, k, np.int8),
        _array3(frame, FRAME_ARGS, 6, k, 3, dtype), _array2(frame, FRAME_ARGS, 7, k, dtype),
        _array2(frame, FRAME_ARGS, 8, k, dtype),
        _array2(frame, FRAME_RETS, 0, 3, dtype), _array2(frame, FRAME_RETS, 1, 3, dtype),
        _array3(frame, FRAME_RETS, 2, 3, 3, dtype), _array3(frame, FRAME_RETS, 3, 3, 2, dtype))


# -- interpolation (interpolate.interpolate_corners) ---------------------------------------
# arguments: ids [R, W, K] int32, bary [R, W, K, 3], corners [F, 3, C]; forward result
# [R, W, K, C]; backward: the cotangent [R, W, K, C] follows, results g_bary and g_corners.

@numba.njit(cache=True, nogil=True)
def _interpolate_forward(frame, values, dtype):
    k = buffer_dim(item(frame, FRAME_ARGS, 0), -1)
    c = buffer_dim(item(frame, FRAME_ARGS, 2), -1)
    kernels.interpolate_forward_into(
        _array2(frame, FRAME_ARGS, 0, k, np.int32), _array3(frame, FRAME_ARGS, 1, k, 3, dtype),
        _array3(frame, FRAME_ARGS, 2, 3, c, dtype), values[0],
        _array3(frame, FRAME_RETS, 0, k, c, dtype))


@numba.njit(cache=True, nogil=True)
def _interpolate_backward(frame, values, dtype):
    k = buffer_dim(item(frame, FRAME_ARGS, 0), -1)
    c = buffer_dim(item(frame, FRAME_ARGS, 2), -1)
    kernels.interpolate_backward_into(
        _array2(frame, FRAME_ARGS, 0, k, np.int32), _array3(frame, FRAME_ARGS, 1, k, 3, dtype),
        _array3(frame, FRAME_ARGS, 2, 3, c, dtype), _array3(frame, FRAME_ARGS, 3, k, c, dtype),
        values[0], _array3(frame, FRAME_RETS, 0, k, 3, dtype),
        _array3(frame, FRAME_RETS, 1, 3, c, dtype))


# -- interpolation at some fragments (interpolation.interpolate_rows_at) -------------------
# arguments: rows [M] int32, ids [N] int32, bary [N, 3], corners [F, 3, C]; result [M, C]

@numba.njit(cache=True, nogil=True)
def _interpolate_at(frame, values, dtype):
    c = buffer_dim(item(frame, FRAME_ARGS, 3), -1)
    kernels.interpolate_at_into(
        _flat(frame, FRAME_ARGS, 0, np.int32), _flat(frame, FRAME_ARGS, 1, np.int32),
        _array2(frame, FRAME_ARGS, 2, 3, dtype), _array3(frame, FRAME_ARGS, 3, 3, c, dtype),
        values[0], _array2(frame, FRAME_RETS, 0, c, dtype))


# -- texture lookup (texturing.sample_texels) ------------------------------------------------
# arguments: ids [M] int32 (texture offsets), uv [M, 2], texels [T, C]; attributes: height,
# width, clamp, uv_grad (read by the backward). Forward result [M, C]; backward: the
# cotangent [M, C] follows, results g_uv and g_texels.

@numba.njit(cache=True, nogil=True)
def _texture_forward(frame, values, dtype):
    c = buffer_dim(item(frame, FRAME_ARGS, 2), -1)
    texture_kernels.sample_forward_into(
        _flat(frame, FRAME_ARGS, 0, np.int32), _array2(frame, FRAME_ARGS, 1, 2, dtype),
        _array2(frame, FRAME_ARGS, 2, c, dtype), values[0], values[1], values[2] != 0,
        values[4], _array2(frame, FRAME_RETS, 0, c, dtype))


@numba.njit(cache=True, nogil=True)
def _texture_backward(frame, values, dtype):
    c = buffer_dim(item(frame, FRAME_ARGS, 2), -1)
    texture_kernels.sample_backward_into(
        _flat(frame, FRAME_ARGS, 0, np.int32), _array2(frame, FRAME_ARGS, 1, 2, dtype),
        _array2(frame, FRAME_ARGS, 2, c, dtype), _array2(frame, FRAME_ARGS, 3, c, dtype),
        values[0], values[1], values[2] != 0, values[3] != 0, values[4],
        _array2(frame, FRAME_RETS, 0, 2, dtype), _array2(frame, FRAME_RETS, 1, c, dtype))


# -- active slots (compact.active_indices) --------------------------------------------------
# argument: mask [N] bool; results: indices [capacity] int32, count [] int32

@numba.njit(cache=True, nogil=True)
def _active(frame):
    active_kernel.first_active_into(_flat(frame, FRAME_ARGS, 0, np.bool_),
                                    _flat(frame, FRAME_RETS, 0, np.int32),
                                    _flat(frame, FRAME_RETS, 1, np.int32))


# -- rows put back (compact.take_rows' transpose) --------------------------------------------
# arguments: idx [C] int32, rows [C, 3]; result out [N, 3]; attribute: clip

@numba.njit(cache=True, nogil=True)
def _put_rows(frame, values, dtype):
    active_kernel.put_rows_into(_flat(frame, FRAME_ARGS, 0, np.int32),
                                _array2(frame, FRAME_ARGS, 1, 3, dtype), values[0] != 0,
                                values[1], _array2(frame, FRAME_RETS, 0, 3, dtype))


# -- rows summed per group (compact.sum_rows) -------------------------------------------------
# arguments: idx [C] int32 (ascending), rows [C, 3]; result out [P, 3]; attribute: group

@numba.njit(cache=True, nogil=True)
def _sum_rows(frame, values, dtype):
    active_kernel.sum_rows_into(_flat(frame, FRAME_ARGS, 0, np.int32),
                                _array2(frame, FRAME_ARGS, 1, 3, dtype), values[0],
                                _array2(frame, FRAME_RETS, 0, 3, dtype))


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
    rank = word(buffer, BUFFER_RANK)
    dims = words(word(buffer, BUFFER_DIMS), rank)
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
def _per_view(frame, lead, views):
    """Arguments 2 to 6 (near, far, radius, sigma, gamma: each [*B], broadcast; float32 or
    float64) as float64 [5, views]."""
    out = np.empty((5, views))
    for index in range(2, 7):
        buffer = item(frame, FRAME_ARGS, index)
        if int32(buffer, BUFFER_DTYPE) == F64:
            values64 = _flat(frame, FRAME_ARGS, index, np.float64)
            for v in range(views):
                out[index - 2, v] = values64[_member(v, lead, buffer, 0)]
        else:
            values32 = _flat(frame, FRAME_ARGS, index, np.float32)
            for v in range(views):
                out[index - 2, v] = values32[_member(v, lead, buffer, 0)]
    return out


@numba.njit(cache=True, nogil=True)
def _search_inputs(frame, values, dtype, face_dtype):
    """What the search of every view needs: (ids [views * H * W * k], dropped [views],
    views, groups (1: one mesh for every view, else one per view), faces of group g
    (_group_faces), clips [views, V, 4], radii [views], params [views, 4] (sigma, gamma,
    near, far), width, height, k, cull, perspective, threads)."""
    ids = _flat(frame, FRAME_RETS, 0, np.int32)
    out_dropped = item(frame, FRAME_RETS, 1)
    dropped = _flat(frame, FRAME_RETS, 1, np.int32)
    views = dropped.shape[0]
    rank = word(out_dropped, BUFFER_RANK)
    lead = words(word(out_dropped, BUFFER_DIMS), rank).copy() if rank > 0 else np.ones(
        1, np.int64)
    clip_buffer, face_buffer = item(frame, FRAME_ARGS, 0), item(frame, FRAME_ARGS, 1)
    clip_in = _array3(frame, FRAME_ARGS, 0, buffer_dim(clip_buffer, -2), 4, dtype)
    clips = np.empty((views, clip_in.shape[1], 4))
    for v in range(views):
        clips[v] = clip_in[_member(v, lead, clip_buffer, 2)]
    faces_in = _array3(frame, FRAME_ARGS, 1, buffer_dim(face_buffer, -2), 3, face_dtype)
    groups = 1 if faces_in.shape[0] == 1 else views
    faces = np.empty((groups, faces_in.shape[1], 3), np.int64)
    for g in range(groups):
        faces[g] = faces_in[_member(g, lead, face_buffer, 2) if groups > 1 else 0]
    scalars = _per_view(frame, lead, views)
    params = np.empty((views, 4))
    params[:, 0], params[:, 1] = scalars[3], scalars[4]
    params[:, 2], params[:, 3] = scalars[0], scalars[1]
    return (ids, dropped, views, faces, clips, scalars[2].copy(), params, values[0], values[1],
            values[2], values[3] != 0, values[4] != 0, values[5])


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
def _search_soft(frame, values, dtype, face_dtype):
    (ids, dropped, views, faces, clips, radii, params, width, height, k, cull, perspective,
     threads) = _search_inputs(frame, values, dtype, face_dtype)
    per_group = views // faces.shape[0]
    pixels = width * height
    for g in range(faces.shape[0]):
        chosen = slice(g * per_group, (g + 1) * per_group)
        found = ids[g * per_group * pixels * k:(g + 1) * per_group * pixels * k]
        lost = candidates._search_soft_into(clips[chosen], faces[g], width, height, k, cull,
                                            radii[chosen], params[chosen], perspective,
                                            found.reshape((per_group, pixels, k)), threads)
        for v in range(per_group):
            dropped[g * per_group + v] = lost[v]


@numba.njit(cache=True, nogil=True)
def _search_hard(frame, values, dtype, face_dtype):
    (ids, dropped, views, faces, clips, _, _, width, height, k, cull, _,
     threads) = _search_inputs(frame, values, dtype, face_dtype)
    per_group = views // faces.shape[0]
    for g in range(faces.shape[0]):
        chosen = slice(g * per_group, (g + 1) * per_group)
        found, lost = candidates._search_hard(clips[chosen], faces[g], width, height, k, cull,
                                              min(height, 2 * threads))
        _write_group(ids, dropped, g, per_group, found, lost)


#: the handlers' bodies, by the number a handler is made with (_handler)
_BODIES = ("active", "geometry_forward", "geometry_backward", "interpolate_forward",
           "interpolate_backward", "search_soft", "search_hard", "texture_forward",
           "texture_backward", "put_rows", "interpolate_at", "sum_rows")


class Target(NamedTuple):
    """An FFI target: its handler runs body _BODIES[body] with dtype and `other` (the
    geometry's tiny, the search's face dtype) once the call frame holds buffers as `args`
    and `rets` say (ffi_check.spec) and the int64 attributes `attrs` (names; the last is
    THREADS, which lowering appends)."""

    body: int
    dtype: type
    other: object
    args: tuple
    rets: tuple
    attrs: tuple


def _geometry(body, f, dtype, tiny_value):
    """The fragment geometry's target (body 1: forward, 2: backward) of float code f."""
    ids = spec(S32, (1, ANY))
    faces = (spec(f, 2, (3,)), spec(f, 2, (3,)), spec(f, 3, (3, 3)), spec(f, 3, (2, 3)))
    per_id = (spec(f, (2, ANY), (3,), TIMES, 0, 3), spec(f, (1, ANY), (), TIMES, 0, 1),
              spec(f, (1, ANY), (), TIMES, 0, 1))
    edge = spec(S8, (1, ANY), (), TIMES, 0, 1)
    args, rets = (ids, *faces), (*per_id, edge)
    if body == 2:
        args = (*args, edge, *per_id)
        rets = tuple(s[:6] + (TIMES, i + 1, 1) for i, s in enumerate(faces))
    return Target(body, dtype, tiny_value, args, rets, ("width", "height", "soft", THREADS))


def _interpolation(body, f, dtype):
    """The interpolation's target (body 3: forward, 4: backward) of float code f."""
    ids, corners = spec(S32, (1, ANY)), spec(f, 3, (0, 3))
    bary = spec(f, (2, ANY), (3,), TIMES, 0, 3)
    out = spec(f, (2, ANY), (), PER_LAST, 0, 2)
    if body == 3:
        return Target(body, dtype, 0, (ids, bary, corners), (out,), (THREADS,))
    return Target(body, dtype, 0, (ids, bary, corners, out),
                  (bary, corners[:6] + (TIMES, 2, 1)), (THREADS,))


def _search(body, f, dtype, i, ints):
    """The candidate search's target (body 5: soft, 6: hard) of float code f, face ids of
    int code i."""
    per_view = spec(FLOAT, (0, ANY), (), BATCH, 1, 0)
    args = (spec(f, (2, ANY), (4,), BATCH, 1, 2), spec(i, (2, ANY), (3,), BATCH, 1, 2),
            *(per_view,) * 5)
    rets = (spec(S32, (3, ANY), (), IMAGES, 1), spec(S32, (0, ANY)))
    attrs = ("width", "height", "k", "cull_backfaces", "perspective", THREADS)
    return Target(body, dtype, ints, args, rets, attrs)


def _texture(body, f, dtype):
    """The texture lookup's target (body 7: forward, 8: backward) of float code f."""
    ids, uv, texels = spec(S32, (1, ANY)), spec(f, (2, ANY), (2,), TIMES, 0, 2), spec(f, 2)
    out = spec(f, (2, ANY), (), PER_LAST, 0, 2)
    attrs = ("height", "width", "clamp", "uv_grad", THREADS)
    if body == 7:
        return Target(body, dtype, 0, (ids, uv, texels), (out,), attrs)
    return Target(body, dtype, 0, (ids, uv, texels, out), (uv, texels[:6] + (TIMES, 2, 1)),
                  attrs)


def _handler(name, target):
    """The FFI handler of target `name`: answers XLA's metadata query, checks the call
    frame against the target (an XLA error where it differs), else runs the body. A
    closure per target over plain constants, which numba freezes: the branches of the
    other bodies are pruned before compiling, and the constants are part of the cache's
    key (a closure over the body's dispatcher would not be cached)."""
    body, dtype, other = target.body, target.dtype, target.other
    title, args, rets, attrs = tables(name, target.args, target.rets, target.attrs)

    def handler(address):
        frame = address_of(address)
        values = np.zeros(attrs.shape[0], np.int64)
        message = check(frame, title, args, rets, attrs, values)
        if message.size > 0:
            return pointer(error(frame, message))
        if metadata_query(frame):
            return pointer(0)
        if body == 0:
            _active(frame)
        elif body == 1:
            _geometry_forward(frame, values, dtype, other)
        elif body == 2:
            _geometry_backward(frame, values, dtype, other)
        elif body == 3:
            _interpolate_forward(frame, values, dtype)
        elif body == 4:
            _interpolate_backward(frame, values, dtype)
        elif body == 5:
            _search_soft(frame, values, dtype, other)
        elif body == 6:
            _search_hard(frame, values, dtype, other)
        elif body == 7:
            _texture_forward(frame, values, dtype)
        elif body == 8:
            _texture_backward(frame, values, dtype)
        elif body == 9:
            _put_rows(frame, values, dtype)
        elif body == 10:
            _interpolate_at(frame, values, dtype)
        else:
            _sum_rows(frame, values, dtype)
        return pointer(0)
    handler.__name__ = handler.__qualname__ = f"_handler_{name}"
    return handler


#: target name -> Target; a target per operand dtype, so that a program compiles only the
#: dtypes it uses
TARGETS = {"diffshade_active": Target(0, np.float32, 0, (spec(PRED, 1),),
                                      (spec(S32, 1), spec(S32, 0)), (THREADS,))}
for _width, _f, _dtype, _tiny in (("f32", F32, np.float32, _TINY32),
                                  ("f64", F64, np.float64, _TINY64)):
    for _body in (1, 2):
        TARGETS[f"diffshade_{_BODIES[_body]}_{_width}"] = _geometry(_body, _f, _dtype, _tiny)
    for _body in (3, 4):
        TARGETS[f"diffshade_{_BODIES[_body]}_{_width}"] = _interpolation(_body, _f, _dtype)
    for _body in (7, 8):
        TARGETS[f"diffshade_{_BODIES[_body]}_{_width}"] = _texture(_body, _f, _dtype)
    TARGETS[f"diffshade_put_rows_{_width}"] = Target(
        9, _dtype, 0, (spec(S32, 1), spec(_f, 2, (3,), TIMES, 0, 3)), (spec(_f, 2, (3,)),),
        ("clip", THREADS))
    TARGETS[f"diffshade_sum_rows_{_width}"] = Target(
        11, _dtype, 0, (spec(S32, 1), spec(_f, 2, (3,), TIMES, 0, 3)), (spec(_f, 2, (3,)),),
        ("group", THREADS))
    TARGETS[f"diffshade_interpolate_at_{_width}"] = Target(
        10, _dtype, 0, (spec(S32, 1), spec(S32, 1), spec(_f, 2, (3,), TIMES, 1, 3),
                        spec(_f, 3, (0, 3))), (spec(_f, 2, (), PER_LAST, 0, 3),), (THREADS,))
    for _ints, _i, _int in (("i32", S32, np.int32), ("i64", S64, np.int64)):
        for _body in (5, 6):
            TARGETS[f"diffshade_{_BODIES[_body]}_{_width}_{_ints}"] = _search(
                _body, _f, _dtype, _i, _int)
#: target name -> handler, a Python function (compile_handler compiles it)
HANDLERS = {name: _handler(name, target) for name, target in TARGETS.items()}
_REGISTERED = {}
_REGISTERING = threading.Lock()


def unavailable():
    """None where the handlers may be used, else why not (a sentence): the installed
    jaxlib's FFI API must be one whose call frame xla_ffi lays out, and numba's threading
    layer must run parallel kernels started from two threads at once (OpenMP or TBB: XLA
    may run two independent custom calls together, where the host callbacks take a lock;
    numba's fallback layer, workqueue, aborts on that)."""
    why = xla_ffi.supported()
    if why is not None:
        return why
    numba.get_num_threads()  # starts the threading layer
    layer = numba.threading_layer()
    if layer not in ("omp", "tbb"):
        return f"numba's threading layer is {layer!r}; the handlers need 'omp' or 'tbb'"
    return None


def target_for(base, args):
    """The target of `base` (geometry_forward, search, ...) for operands `args`, or None
    where no handler takes their dtypes: float32 or float64 (one of them for all of a
    call's float operands, but the search's per-view scalars), int32 face ids, int8
    nearest edges, bool masks, the search's faces int32 or int64."""
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
    if len(floats) != 1 or not all(d.kind == "f" or d in (np.int32, np.int8) for d in dtypes):
        return None
    return f"diffshade_{base}_{width[floats.pop()]}"


def compile_handler(target):
    """The compiled handler of `target` (numba's cfunc; compiled, or loaded from numba's
    cache, which it is saved to)."""
    # starts numba's threading layer, which defines the symbols (allocate_sched, ...) that
    # the parallel kernels' code refers to: a cfunc loaded from numba's cache does not
    numba.get_num_threads()
    return cfunc(SIGNATURE, nogil=True, cache=True)(HANDLERS[target])


def _register(target):
    """Compile (or load from numba's cache) and register a handler, once per process (a
    lock: two threads may lower programs at once)."""
    with _REGISTERING:
        if target in _REGISTERED:
            return
        handler = compile_handler(target)
        jax.ffi.register_ffi_target(target, jax.ffi.pycapsule(handler.address),
                                    platform="cpu")
        _REGISTERED[target] = handler  # kept alive: XLA holds only its address


def lowering(ctx, operands, target, attributes):
    """The MLIR of a call of `target` (registered on first use) with its int64 attributes
    (Target.attrs, by name) = attributes, then THREADS = numba's thread count."""
    names = TARGETS[target].attrs[:-1]
    if len(attributes) != len(names):
        raise ValueError(f"attributes of FFI target {target}: got {tuple(attributes)}, "
                         f"expected values of {names}")
    _register(target)
    named = {name: np.int64(int(value)) for name, value in zip(names, attributes, strict=True)}
    named[THREADS] = np.int64(numba.get_num_threads())
    return jax.ffi.ffi_lowering(target)(ctx, *operands, **named)
