"""What an FFI handler of ffi.py expects of XLA's call frame, and the check of each call.

A handler's `Target` lists a spec per argument and result buffer (`spec`: dtype, rank,
fixed trailing dims, a rule on its size or its batch axes) and the names of the int64
attributes it reads. `check` compares the call frame with them, and with the layout of
xla_ffi (struct sizes, the FFI API version XLA reports, the execution stage), before the
handler reads anything else: a mismatch becomes a message naming the target, what it was
given and what it expected, which the handler returns as an XLA error (xla_ffi.error).
XLA's metadata query is answered on the way.
"""

import numba
import numpy as np

from diffshade.host.xla_ffi import (
    API_MAJOR,
    API_MINOR,
    API_VERSION,
    ARGS_SIZE,
    ATTR_SCALAR,
    ATTRS_SIZE,
    BUFFER_DIMS,
    BUFFER_DTYPE,
    BUFFER_RANK,
    BUFFER_SIZE,
    BUFFER_TYPE,
    F32,
    F64,
    FRAME_API,
    FRAME_ARGS,
    FRAME_ATTRS,
    FRAME_RETS,
    FRAME_SIZE,
    FRAME_STAGE,
    LIST_SIZE,
    LIST_TYPES,
    PRED,
    S32,
    S64,
    STAGE_EXECUTE,
    VERSION_MAJOR,
    VERSION_MINOR,
    answer_metadata,
    attribute,
    attribute_index,
    attribute_kind,
    buffer_dim,
    buffer_size,
    int32,
    item,
    metadata_query,
    word,
    words,
)

# A buffer's spec, a tuple of nine ints (`spec`): dtype (FLOAT: F32 or F64), least and most
# rank (ANY: no bound), its last three dims (0: any; the last first), then a rule on its
# number of elements or leading axes, the rule's reference and its factor:
#   TIMES:    elements == elements(argument ref) * factor
#   PER_LAST: elements == elements(argument ref) * last dim of argument factor
#   IMAGES:   elements == elements(result ref) * attributes width * height * k
#   BATCH:    the axes before the last `factor` broadcast against the shape of result ref
FLOAT, ANY = -1, -1
FREE, TIMES, PER_LAST, IMAGES, BATCH = 0, 1, 2, 3, 4


def spec(dtype, rank, dims=(), rule=FREE, ref=0, factor=1):
    """A buffer's spec: `rank` an int or (least, most), most = ANY for no bound; dims: the
    last dims, from the last (0: any)."""
    least, most = (rank, rank) if isinstance(rank, int) else rank
    dims = tuple(dims) + (0,) * (3 - len(dims))
    return (dtype, least, most, *dims, rule, ref, factor)


@numba.njit(cache=True, nogil=True)
def _dtype_name(code):
    if code == PRED:
        return "bool (PRED)"
    if code == S32:
        return "int32 (S32)"
    if code == S64:
        return "int64 (S64)"
    if code == F32:
        return "float32 (F32)"
    if code == F64:
        return "float64 (F64)"
    if code == FLOAT:
        return "float32 or float64"
    return "XLA_FFI_DataType " + str(code)


@numba.njit(cache=True, nogil=True)
def _rank_text(least, most):
    if most == ANY:
        return "at least " + str(least)
    if least == most:
        return str(least)
    return str(least) + " to " + str(most)


@numba.njit(cache=True, nogil=True)
def _attribute_problem(frame, attrs):
    """What is wrong with the attributes the handler reads (each an int64 scalar), or ''."""
    for a in range(len(attrs)):
        index = attribute_index(frame, attrs[a])
        if index < 0:
            return "no attribute '" + attrs[a] + "' (an int64 scalar)"
        kind, dtype = attribute_kind(frame, index)
        if kind != ATTR_SCALAR or dtype != S64:
            return ("attribute '" + attrs[a] + "' is of XLA_FFI_AttrType " + str(kind)
                    + " and XLA_FFI_DataType " + str(dtype) + ", expected an int64 scalar")
    return ""


@numba.njit(cache=True, nogil=True)
def _rule_problem(frame, buffer, rule):
    """What breaks the buffer's rule (rule: its spec's last three entries), or ''."""
    kind, ref, factor = rule[6], rule[7], rule[8]
    if kind == BATCH:
        shape = item(frame, FRAME_RETS, ref)
        lead = word(buffer, BUFFER_RANK) - factor
        out_rank = word(shape, BUFFER_RANK)
        dims, out = words(word(buffer, BUFFER_DIMS), lead), words(word(shape, BUFFER_DIMS),
                                                                   out_rank)
        if lead > out_rank:
            return "has " + str(lead) + " batch axes, result " + str(ref) + " fewer"
        for axis in range(lead):
            want = out[out_rank - lead + axis]
            if dims[axis] != 1 and dims[axis] != want:
                return ("has " + str(dims[axis]) + " at batch axis " + str(axis)
                        + ", expected 1 or " + str(want) + " (result " + str(ref) + ")")
        return ""
    elements = buffer_size(buffer)
    if kind == TIMES:
        want = buffer_size(item(frame, FRAME_ARGS, ref)) * factor
        what = " (" + str(factor) + " per element of argument " + str(ref) + ")"
    elif kind == PER_LAST:
        want = buffer_size(item(frame, FRAME_ARGS, ref)) * buffer_dim(
            item(frame, FRAME_ARGS, factor), -1)
        what = (" (the last dim of argument " + str(factor) + " per element of argument "
                + str(ref) + ")")
    elif kind == IMAGES:
        want = buffer_size(item(frame, FRAME_RETS, ref)) * (
            attribute(frame, "width") * attribute(frame, "height") * attribute(frame, "k"))
        what = " (width * height * k per element of result " + str(ref) + ")"
    else:
        return ""
    if elements != want:
        return "has " + str(elements) + " elements, expected " + str(want) + what
    return ""


@numba.njit(cache=True, nogil=True)
def _buffer_problem(frame, buffer, expected):
    """What in the XLA_FFI_Buffer at `buffer` differs from its spec `expected`, or ''."""
    if word(buffer, 0) < BUFFER_SIZE:
        return ("is an XLA_FFI_Buffer of " + str(word(buffer, 0)) + " bytes, expected at least "
                + str(BUFFER_SIZE))
    dtype, rank = int32(buffer, BUFFER_DTYPE), word(buffer, BUFFER_RANK)
    want = expected[0]
    if dtype != want and not (want == FLOAT and (dtype == F32 or dtype == F64)):
        return "has dtype " + _dtype_name(dtype) + ", expected " + _dtype_name(want)
    if rank < expected[1] or (expected[2] != ANY and rank > expected[2]):
        return "has rank " + str(rank) + ", expected " + _rank_text(expected[1], expected[2])
    dims = words(word(buffer, BUFFER_DIMS), rank)
    for back in range(3):
        size = expected[3 + back]
        if size != 0 and dims[rank - 1 - back] != size:
            return ("has " + str(dims[rank - 1 - back]) + " at axis " + str(-1 - back)
                    + ", expected " + str(size))
    return ""


@numba.njit(cache=True, nogil=True)
def _list_problem(frame, which, specs, what):
    """What is wrong with the arguments (which = FRAME_ARGS) or results (FRAME_RETS), or ''."""
    given = frame + which
    if word(given, 0) < ARGS_SIZE:  # = RETS_SIZE
        return (what + " list (XLA_FFI_Args/Rets) of " + str(word(given, 0))
                + " bytes, expected at least " + str(ARGS_SIZE))
    if word(given, LIST_SIZE) != len(specs):
        return str(word(given, LIST_SIZE)) + " " + what + "s, expected " + str(len(specs))
    kinds = word(given, LIST_TYPES)
    for i in range(len(specs)):
        if int32(kinds, 4 * i) != BUFFER_TYPE:
            return what + " " + str(i) + " is not a buffer"
        problem = _buffer_problem(frame, item(frame, which, i), specs[i])
        if problem == "":
            problem = _rule_problem(frame, item(frame, which, i), specs[i])
        if problem != "":
            return what + " " + str(i) + " " + problem
    return ""


@numba.njit(cache=True, nogil=True)
def _frame_problem(frame):
    """What in the call frame's header differs from this layout's, or ''."""
    if word(frame, 0) < FRAME_SIZE:
        return ("XLA_FFI_CallFrame of " + str(word(frame, 0)) + " bytes, expected at least "
                + str(FRAME_SIZE) + ": check the installed jaxlib")
    version = word(frame, FRAME_API) + API_VERSION
    major, minor = int32(version, VERSION_MAJOR), int32(version, VERSION_MINOR)
    if major != API_MAJOR or minor < API_MINOR:
        return ("XLA's FFI API is " + str(major) + "." + str(minor) + ", the handler reads "
                + str(API_MAJOR) + "." + str(API_MINOR) + " (any " + str(API_MAJOR)
                + ".x, x >= " + str(API_MINOR) + ")")
    return ""


@numba.njit(cache=True, nogil=True)
def check(frame, name, args, rets, attrs):
    """Why target `name` cannot run this call (a NUL-terminated uint8 message for `error`),
    or an empty array; XLA's metadata query is answered on the way (answer_metadata).
    args, rets: a spec per buffer (`spec`); attrs: names of the int64 attributes the
    target reads."""
    text = _frame_problem(frame)
    if text == "" and metadata_query(frame):
        if not answer_metadata(frame):
            text = "XLA_FFI_Metadata_Extension or XLA_FFI_Metadata smaller than this layout's"
    elif text == "":
        stage = int32(frame, FRAME_STAGE)
        if stage != STAGE_EXECUTE:
            text = "execution stage " + str(stage) + ", expected " + str(STAGE_EXECUTE)
        elif word(frame, FRAME_ATTRS) < ATTRS_SIZE:
            text = ("XLA_FFI_Attrs of " + str(word(frame, FRAME_ATTRS))
                    + " bytes, expected at least " + str(ATTRS_SIZE))
        else:
            text = _attribute_problem(frame, attrs)
        if text == "":
            text = _list_problem(frame, FRAME_ARGS, args, "argument")
        if text == "":
            text = _list_problem(frame, FRAME_RETS, rets, "result")
    if text == "":
        return np.zeros(0, np.uint8)
    text = name + ": " + text
    message = np.zeros(len(text) + 1, np.uint8)
    for i in range(len(text)):
        message[i] = ord(text[i]) if ord(text[i]) < 128 else ord("?")
    return message
