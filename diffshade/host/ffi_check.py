"""What an FFI handler of ffi.py expects of XLA's call frame, and the check of each call.

A handler's `Target` lists a spec per argument and result buffer (`spec`: dtype, rank,
fixed trailing dims, a rule on its size or its batch axes) and the names of the int64
attributes it reads. `tables` turns them into arrays, and `check` compares the call frame
with them, and with the layout of xla_ffi (struct sizes, the FFI API version XLA reports,
the execution stage), before the handler reads anything else: a mismatch becomes a
message naming the target, what it was given and what it expected, which the handler
returns as an XLA error (xla_ffi.error). XLA's metadata query is answered on the way, and
the attributes' values are read (in the order of the target's names).

Compile time shapes this module: `check` is compiled once for every target (its tables
are arrays of one type each, never tuples whose types differ by target, nor literal
constants, which numba would compile a copy of the function for each), and the messages
are bytes written into a uint8 buffer (numba's unicode strings cost seconds to compile).
"""

import numba
import numpy as np

from diffshade.host import numba_cache  # noqa: F401 (numba's cache saves, locked)
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
    S8,
    S32,
    S64,
    STAGE_EXECUTE,
    VERSION_MAJOR,
    VERSION_MINOR,
    answer_metadata,
    attribute_index,
    attribute_kind,
    attribute_value,
    buffer_dim,
    buffer_size,
    int32,
    item,
    metadata_query,
    name_table,
    word,
    words,
)

# A buffer's spec, nine ints (`spec`): dtype (FLOAT: F32 or F64), least and most rank
# (ANY: no bound), its last three dims (0: any; the last first), then a rule on its number
# of elements or leading axes, the rule's reference and its factor:
#   TIMES:    elements == elements(argument ref) * factor
#   PER_LAST: elements == elements(argument ref) * last dim of argument factor
#   IMAGES:   elements == elements(result ref) * the first three attributes (width * height
#             * k)
#   BATCH:    the axes before the last `factor` broadcast against the shape of result ref
FLOAT, ANY = -1, -1
FREE, TIMES, PER_LAST, IMAGES, BATCH = 0, 1, 2, 3, 4
#: bytes of a message buffer (a longer message is cut, its last byte stays NUL)
MESSAGE_BYTES = 512


def spec(dtype, rank, dims=(), rule=FREE, ref=0, factor=1):
    """A buffer's spec: `rank` an int or (least, most), most = ANY for no bound; dims: the
    last dims, from the last (0: any)."""
    least, most = (rank, rank) if isinstance(rank, int) else rank
    dims = tuple(dims) + (0,) * (3 - len(dims))
    return (dtype, least, most, *dims, rule, ref, factor)


def tables(name, args, rets, attrs):
    """check's arguments for a target: (name [n + 1] uint8 NUL-terminated, arg specs
    [len(args), 9] int64, ret specs [len(rets), 9] int64, attribute names (xla_ffi.name_table))."""
    def specs(rows):
        return np.array(rows, np.int64).reshape(len(rows), 9)
    return (np.frombuffer(name.encode("ascii") + b"\0", np.uint8), specs(args), specs(rets),
            name_table(attrs))


# -- messages: bytes in a NUL-terminated uint8 buffer -----------------------------------------

@numba.njit(cache=True, nogil=True)
def _end(out):
    """Length of the message in `out` (bytes before the first NUL)."""
    for i in range(out.shape[0]):
        if out[i] == 0:
            return i
    return out.shape[0]


@numba.njit(cache=True, nogil=True)
def _put(out, piece):
    """Append the bytes (or NUL-terminated uint8 array) `piece` to the message in `out`."""
    at = _end(out)
    for i in range(len(piece)):
        if piece[i] == 0 or at >= out.shape[0] - 1:
            break
        out[at] = piece[i]
        at += 1


@numba.njit(cache=True, nogil=True)
def _number(out, value):
    """Append the decimal digits of the integer `value` to the message in `out`."""
    digits = np.zeros(21, np.uint8)
    at, rest = 20, abs(value)
    while True:
        at -= 1
        digits[at] = 48 + rest % 10
        rest //= 10
        if rest == 0:
            break
    if value < 0:
        at -= 1
        digits[at] = 45
    _put(out, digits[at:])


@numba.njit(cache=True, nogil=True)
def _dtype_name(out, code):
    if code == PRED:
        _put(out, b"bool (PRED)")
    elif code == S8:
        _put(out, b"int8 (S8)")
    elif code == S32:
        _put(out, b"int32 (S32)")
    elif code == S64:
        _put(out, b"int64 (S64)")
    elif code == F32:
        _put(out, b"float32 (F32)")
    elif code == F64:
        _put(out, b"float64 (F64)")
    elif code == FLOAT:
        _put(out, b"float32 or float64")
    else:
        _put(out, b"XLA_FFI_DataType ")
        _number(out, code)


@numba.njit(cache=True, nogil=True)
def _rank_text(out, least, most):
    if most == ANY:
        _put(out, b"at least ")
        _number(out, least)
    else:
        _number(out, least)
        if least != most:
            _put(out, b" to ")
            _number(out, most)


# -- the checks: each writes what is wrong into `out` (left empty where nothing is) -----------

@numba.njit(cache=True, nogil=True)
def _attribute_problem(frame, names, values, out):
    """The attributes the handler reads, each an int64 scalar, into values."""
    for a in range(names.shape[0]):
        index = attribute_index(frame, names[a])
        if index < 0:
            _put(out, b"no attribute '")
            _put(out, names[a])
            _put(out, b"' (an int64 scalar)")
            return
        kind, dtype = attribute_kind(frame, index)
        if kind != ATTR_SCALAR or dtype != S64:
            _put(out, b"attribute '")
            _put(out, names[a])
            _put(out, b"' is of XLA_FFI_AttrType ")
            _number(out, kind)
            _put(out, b" and XLA_FFI_DataType ")
            _number(out, dtype)
            _put(out, b", expected an int64 scalar")
            return
        values[a] = attribute_value(frame, index)


@numba.njit(cache=True, nogil=True)
def _batch_problem(frame, buffer, ref, factor, out):
    """The buffer's axes before its last `factor` against the shape of result ref."""
    shape = item(frame, FRAME_RETS, ref)
    lead = word(buffer, BUFFER_RANK) - factor
    out_rank = word(shape, BUFFER_RANK)
    dims, wanted = words(word(buffer, BUFFER_DIMS), lead), words(word(shape, BUFFER_DIMS),
                                                                  out_rank)
    if lead > out_rank:
        _put(out, b"has ")
        _number(out, lead)
        _put(out, b" batch axes, result ")
        _number(out, ref)
        _put(out, b" fewer")
        return
    for axis in range(lead):
        want = wanted[out_rank - lead + axis]
        if dims[axis] != 1 and dims[axis] != want:
            _put(out, b"has ")
            _number(out, dims[axis])
            _put(out, b" at batch axis ")
            _number(out, axis)
            _put(out, b", expected 1 or ")
            _number(out, want)
            _put(out, b" (result ")
            _number(out, ref)
            _put(out, b")")
            return


@numba.njit(cache=True, nogil=True)
def _rule_problem(frame, buffer, rule, values, out):
    """What breaks the buffer's rule (rule: its spec)."""
    kind, ref, factor = rule[6], rule[7], rule[8]
    if kind == BATCH:
        _batch_problem(frame, buffer, ref, factor, out)
        return
    if kind == TIMES:
        want = buffer_size(item(frame, FRAME_ARGS, ref)) * factor
    elif kind == PER_LAST:
        want = buffer_size(item(frame, FRAME_ARGS, ref)) * buffer_dim(
            item(frame, FRAME_ARGS, factor), -1)
    elif kind == IMAGES:
        want = buffer_size(item(frame, FRAME_RETS, ref)) * values[0] * values[1] * values[2]
    else:
        return
    elements = buffer_size(buffer)
    if elements == want:
        return
    _put(out, b"has ")
    _number(out, elements)
    _put(out, b" elements, expected ")
    _number(out, want)
    if kind == TIMES:
        _put(out, b" (")
        _number(out, factor)
        _put(out, b" per element of argument ")
    elif kind == PER_LAST:
        _put(out, b" (the last dim of argument ")
        _number(out, factor)
        _put(out, b" per element of argument ")
    else:
        _put(out, b" (width * height * k per element of result ")
    _number(out, ref)
    _put(out, b")")


@numba.njit(cache=True, nogil=True)
def _buffer_problem(buffer, expected, out):
    """What in the XLA_FFI_Buffer at `buffer` differs from its spec `expected`."""
    if word(buffer, 0) < BUFFER_SIZE:
        _put(out, b"is an XLA_FFI_Buffer of ")
        _number(out, word(buffer, 0))
        _put(out, b" bytes, expected at least ")
        _number(out, np.int64(BUFFER_SIZE))
        return
    dtype, rank = int32(buffer, BUFFER_DTYPE), word(buffer, BUFFER_RANK)
    want = expected[0]
    if dtype != want and not (want == FLOAT and (dtype == F32 or dtype == F64)):
        _put(out, b"has dtype ")
        _dtype_name(out, dtype)
        _put(out, b", expected ")
        _dtype_name(out, want)
        return
    if rank < expected[1] or (expected[2] != ANY and rank > expected[2]):
        _put(out, b"has rank ")
        _number(out, rank)
        _put(out, b", expected ")
        _rank_text(out, expected[1], expected[2])
        return
    dims = words(word(buffer, BUFFER_DIMS), rank)
    for back in range(3):
        size = expected[3 + back]
        if size != 0 and dims[rank - 1 - back] != size:
            _put(out, b"has ")
            _number(out, dims[rank - 1 - back])
            _put(out, b" at axis ")
            _number(out, -1 - back)
            _put(out, b", expected ")
            _number(out, size)
            return


@numba.njit(cache=True, nogil=True)
def _what(out, which):
    _put(out, b"argument" if which == FRAME_ARGS else b"result")


@numba.njit(cache=True, nogil=True)
def _list_problem(frame, which, specs, values, out):
    """What is wrong with the arguments (which = FRAME_ARGS) or results (FRAME_RETS)."""
    given = frame + which
    if word(given, 0) < ARGS_SIZE:  # = RETS_SIZE
        _what(out, which)
        _put(out, b" list (XLA_FFI_Args/Rets) of ")
        _number(out, word(given, 0))
        _put(out, b" bytes, expected at least ")
        _number(out, np.int64(ARGS_SIZE))
        return
    if word(given, LIST_SIZE) != specs.shape[0]:
        _number(out, word(given, LIST_SIZE))
        _put(out, b" ")
        _what(out, which)
        _put(out, b"s, expected ")
        _number(out, specs.shape[0])
        return
    kinds = word(given, LIST_TYPES)
    problem = np.zeros(MESSAGE_BYTES, np.uint8)
    for i in range(specs.shape[0]):
        if int32(kinds, 4 * i) != BUFFER_TYPE:
            _what(out, which)
            _put(out, b" ")
            _number(out, i)
            _put(out, b" is not a buffer")
            return
        _buffer_problem(item(frame, which, i), specs[i], problem)
        if problem[0] == 0:
            _rule_problem(frame, item(frame, which, i), specs[i], values, problem)
        if problem[0] != 0:
            _what(out, which)
            _put(out, b" ")
            _number(out, i)
            _put(out, b" ")
            _put(out, problem)
            return


@numba.njit(cache=True, nogil=True)
def _frame_problem(frame, out):
    """What in the call frame's header differs from this layout's."""
    if word(frame, 0) < FRAME_SIZE:
        _put(out, b"XLA_FFI_CallFrame of ")
        _number(out, word(frame, 0))
        _put(out, b" bytes, expected at least ")
        _number(out, np.int64(FRAME_SIZE))
        _put(out, b": check the installed jaxlib")
        return
    version = word(frame, FRAME_API) + API_VERSION
    major, minor = int32(version, VERSION_MAJOR), int32(version, VERSION_MINOR)
    if major != API_MAJOR or minor < API_MINOR:
        _put(out, b"XLA's FFI API is ")
        _number(out, major)
        _put(out, b".")
        _number(out, minor)
        _put(out, b", the handler reads ")
        _number(out, np.int64(API_MAJOR))
        _put(out, b".")
        _number(out, np.int64(API_MINOR))
        _put(out, b" (any ")
        _number(out, np.int64(API_MAJOR))
        _put(out, b".x, x >= ")
        _number(out, np.int64(API_MINOR))
        _put(out, b")")


@numba.njit(cache=True, nogil=True)
def _call_problem(frame, args, rets, attrs, values, out):
    """What in a call (not a metadata query) differs from the target's tables."""
    stage = int32(frame, FRAME_STAGE)
    if stage != STAGE_EXECUTE:
        _put(out, b"execution stage ")
        _number(out, stage)
        _put(out, b", expected ")
        _number(out, np.int64(STAGE_EXECUTE))
    elif word(frame, FRAME_ATTRS) < ATTRS_SIZE:
        _put(out, b"XLA_FFI_Attrs of ")
        _number(out, word(frame, FRAME_ATTRS))
        _put(out, b" bytes, expected at least ")
        _number(out, np.int64(ATTRS_SIZE))
    else:
        _attribute_problem(frame, attrs, values, out)
    if out[0] == 0:
        _list_problem(frame, np.int64(FRAME_ARGS), args, values, out)
    if out[0] == 0:
        _list_problem(frame, np.int64(FRAME_RETS), rets, values, out)


@numba.njit(cache=True, nogil=True)
def check(frame, name, args, rets, attrs, values):
    """Why target `name` cannot run this call (a NUL-terminated uint8 message for `error`),
    or an empty array; XLA's metadata query is answered on the way (answer_metadata), and
    otherwise the attributes' values written into values [len(attrs)] int64. name, args,
    rets, attrs: the target's `tables`."""
    out = np.zeros(MESSAGE_BYTES, np.uint8)
    _frame_problem(frame, out)
    if out[0] == 0 and metadata_query(frame):
        if not answer_metadata(frame):
            _put(out, b"XLA_FFI_Metadata_Extension or XLA_FFI_Metadata smaller than this "
                      b"layout's")
    elif out[0] == 0:
        _call_problem(frame, args, rets, attrs, values, out)
    if out[0] == 0:
        return np.zeros(0, np.uint8)
    message = np.zeros(MESSAGE_BYTES, np.uint8)
    _put(message, name)
    _put(message, b": ")
    _put(message, out)
    return message[:_end(message) + 1].copy()
