"""XLA's FFI C API as the handlers of ffi.py read it: the call frame's layout, and the calls.

Every offset, struct size and enum value below is read from `xla/ffi/api/c_api.h`, the
header jaxlib ships (`jax.ffi.include_dir()`), at FFI API version API_MAJOR.API_MINOR;
tests/test_ffi.py compiles a C program against the installed header and compares. Offsets
are in bytes, for LP64 (pointers, size_t and int64_t of 8 bytes; enums of 4).

The API is versioned: within a major version, XLA only appends fields to its structs (and
says how much of each it filled in `struct_size`), so a layout read from minor version m
holds for every XLA of the same major version and minor version >= m. `supported()` is the
gate (the header's version). At every call a handler checks (ffi_check.check) the frame's
`struct_size` and the version XLA reports in its `api`, then what the frame carries
against the handler's expectations, and reports a mismatch as an XLA_FFI_Error
made by the API's own XLA_FFI_Error_Create (`error`), which `jit` raises in Python. When
XLA asks for a handler's metadata, it declares API_MAJOR.API_MINOR (`answer_metadata`).

The accessors are numba functions on raw addresses (int64), inlined into the handlers.
"""

import os
import re

import jax
import numba
import numpy as np
from llvmlite import ir
from numba import carray, types
from numba.core import cgutils
from numba.extending import intrinsic

from diffshade.host import numba_cache  # noqa: F401 (numba's cache saves, locked)

#: the header the layout comes from, under jax.ffi.include_dir()
HEADER = os.path.join("xla", "ffi", "api", "c_api.h")
#: XLA_FFI_API_MAJOR, XLA_FFI_API_MINOR of that header: what the handlers declare
API_MAJOR, API_MINOR = 0, 3

# XLA_FFI_Extension_Base: struct_size, type (XLA_FFI_Extension_Type), next
EXTENSION_TYPE = 8
EXTENSION_BASE_SIZE = 24  # XLA_FFI_Extension_Base_STRUCT_SIZE
EXTENSION_METADATA = 1  # XLA_FFI_Extension_Metadata

# XLA_FFI_Api_Version: struct_size, extension_start, major_version, minor_version (int)
VERSION_MAJOR, VERSION_MINOR = 16, 20
VERSION_SIZE = 24  # XLA_FFI_Api_Version_STRUCT_SIZE

# XLA_FFI_Api: struct_size, extension_start, api_version, internal_api, then function
# pointers, XLA_FFI_Error_Create first (present since API 0.0)
API_VERSION, API_ERROR_CREATE = 16, 48

# XLA_FFI_Error_Create_Args: struct_size, extension_start, message (const char*), errc
ERROR_MESSAGE, ERROR_CODE = 16, 24
ERROR_ARGS_SIZE = 28  # XLA_FFI_Error_Create_Args_STRUCT_SIZE
INVALID_ARGUMENT = 3  # XLA_FFI_Error_Code_INVALID_ARGUMENT

# XLA_FFI_CallFrame: struct_size, extension_start, api, ctx, stage (XLA_FFI_ExecutionStage),
# then XLA_FFI_Args args, XLA_FFI_Rets rets, XLA_FFI_Attrs attrs (embedded), future
FRAME_EXTENSION, FRAME_API, FRAME_STAGE = 8, 16, 32
FRAME_ARGS, FRAME_RETS, FRAME_ATTRS = 40, 80, 120
FRAME_SIZE = 168  # XLA_FFI_CallFrame_STRUCT_SIZE (up to attrs)
STAGE_EXECUTE = 3  # XLA_FFI_ExecutionStage_EXECUTE

# XLA_FFI_Args / XLA_FFI_Rets: struct_size, extension_start, size, types, args / rets
LIST_SIZE, LIST_TYPES, LIST_ITEMS = 16, 24, 32
ARGS_SIZE = RETS_SIZE = 40  # XLA_FFI_Args_STRUCT_SIZE, XLA_FFI_Rets_STRUCT_SIZE
BUFFER_TYPE = 1  # XLA_FFI_ArgType_BUFFER = XLA_FFI_RetType_BUFFER

# XLA_FFI_Attrs: struct_size, extension_start, size, types, names (XLA_FFI_ByteSpan**),
# attrs (sorted by name)
ATTRS_NAMES, ATTRS_ITEMS = 32, 40
ATTRS_SIZE = 48  # XLA_FFI_Attrs_STRUCT_SIZE
ATTR_SCALAR = 3  # XLA_FFI_AttrType_SCALAR
# XLA_FFI_ByteSpan: ptr, len; XLA_FFI_Scalar: dtype, value (void*)
SPAN_LENGTH, SCALAR_VALUE = 8, 8

# XLA_FFI_Buffer: struct_size, extension_start, dtype (XLA_FFI_DataType), data, rank, dims
BUFFER_DTYPE, BUFFER_DATA, BUFFER_RANK, BUFFER_DIMS = 16, 24, 32, 40
BUFFER_SIZE = 48  # XLA_FFI_Buffer_STRUCT_SIZE

# XLA_FFI_DataType (xla::PrimitiveType)
PRED, S8, S32, S64, F32, F64 = 1, 2, 4, 5, 11, 12

# XLA_FFI_Metadata_Extension: extension_base, metadata (XLA_FFI_Metadata*); XLA_FFI_Metadata:
# struct_size, api_version (XLA_FFI_Api_Version), traits (uint32)
METADATA_POINTER = 24
METADATA_EXTENSION_SIZE = 32  # XLA_FFI_Metadata_Extension_STRUCT_SIZE
METADATA_VERSION, METADATA_TRAITS = 8, 32
METADATA_SIZE = 36  # XLA_FFI_Metadata_STRUCT_SIZE


def header_version(include_dir=None):
    """(major, minor) of the FFI API in the installed jaxlib's header, or None where the
    header or its version macros are missing."""
    path = os.path.join(include_dir or jax.ffi.include_dir(), HEADER)
    try:
        with open(path) as header:
            text = header.read()
    except OSError:
        return None
    found = [re.search(rf"#define XLA_FFI_API_{part}\s+(\d+)", text) for part in
             ("MAJOR", "MINOR")]
    return None if None in found else tuple(int(m.group(1)) for m in found)


def compatible(major, minor):
    """Whether an XLA of FFI API major.minor lays out the call frame as this module says."""
    return major == API_MAJOR and minor >= API_MINOR


def supported():
    """None where the installed jaxlib's FFI API is one this layout holds for, else why
    not (a sentence)."""
    version = header_version()
    if version is None:
        return f"no FFI API version found in {HEADER} under jax.ffi.include_dir()"
    if not compatible(*version):
        return (f"jaxlib's FFI API is {version[0]}.{version[1]}; the handlers read the call "
                f"frame of API {API_MAJOR}.{API_MINOR} (any {API_MAJOR}.x, x >= {API_MINOR})")
    return None


# -- raw access (numba) ----------------------------------------------------------------------

@intrinsic
def pointer(typingctx, address):
    """An int64 address (or a void pointer, unchanged) as a void pointer (for carray)."""
    if address == types.voidptr:
        return types.voidptr(address), lambda context, builder, signature, args: args[0]
    if not isinstance(address, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        return builder.inttoptr(args[0], cgutils.voidptr_t)
    return types.voidptr(address), codegen


@intrinsic
def _call(typingctx, function, argument):
    """function(argument) -> int64: a C function of one pointer returning a pointer, at
    the int64 address `function`; `argument` an int64 address."""
    if not (isinstance(function, types.Integer) and isinstance(argument, types.Integer)):
        return None

    def codegen(context, builder, signature, args):
        kind = ir.FunctionType(cgutils.voidptr_t, [cgutils.voidptr_t])
        target = builder.inttoptr(args[0], kind.as_pointer())
        result = builder.call(target, [builder.inttoptr(args[1], cgutils.voidptr_t)])
        return builder.ptrtoint(result, ir.IntType(64))
    return types.int64(function, argument), codegen


@numba.njit(cache=True, nogil=True, inline="always")
def word(address, offset):
    """The int64 (or pointer, size_t) at address + offset."""
    return carray(pointer(address + offset), (1,), np.int64)[0]


@numba.njit(cache=True, nogil=True, inline="always")
def int32(address, offset):
    """The int32 (or enum) at address + offset."""
    return np.int64(carray(pointer(address + offset), (1,), np.int32)[0])


@numba.njit(cache=True, nogil=True, inline="always")
def words(address, count):
    """`count` int64 from address (an array of pointers or dims)."""
    return carray(pointer(address), (max(count, 1),), np.int64)


@numba.njit(cache=True, nogil=True, inline="always")
def _set32(address, offset, value):
    carray(pointer(address + offset), (1,), np.int32)[0] = value


@numba.njit(cache=True, nogil=True, inline="always")
def _set64(address, offset, value):
    carray(pointer(address + offset), (1,), np.int64)[0] = value


@numba.njit(cache=True, nogil=True)
def error(frame, message):
    """An XLA_FFI_Error (INVALID_ARGUMENT) of `message` (uint8 bytes, NUL-terminated) by the
    frame's API; XLA copies the message and owns the error."""
    args = np.zeros(4, np.int64)  # XLA_FFI_Error_Create_Args (32 bytes)
    at = args.ctypes.data
    _set64(at, 0, ERROR_ARGS_SIZE)
    _set64(at, ERROR_MESSAGE, message.ctypes.data)
    _set32(at, ERROR_CODE, INVALID_ARGUMENT)
    api = word(frame, FRAME_API)
    return _call(word(api, API_ERROR_CREATE), at)


@numba.njit(cache=True, nogil=True)
def metadata_query(frame):
    """Whether the call is XLA's metadata query (the frame carries the metadata extension)."""
    extension = word(frame, FRAME_EXTENSION)
    return extension != 0 and int32(extension, EXTENSION_TYPE) == EXTENSION_METADATA


@numba.njit(cache=True, nogil=True)
def answer_metadata(frame):
    """Answer XLA's metadata query: the API version the handler implements, no traits.
    False where the extension or the metadata is smaller than this layout."""
    extension = word(frame, FRAME_EXTENSION)
    metadata = word(extension, METADATA_POINTER)
    if word(extension, 0) < METADATA_EXTENSION_SIZE or word(metadata, 0) < METADATA_SIZE:
        return False
    version = metadata + METADATA_VERSION
    _set64(version, 0, VERSION_SIZE)
    _set64(version, 8, 0)  # extension_start
    _set32(version, VERSION_MAJOR, API_MAJOR)
    _set32(version, VERSION_MINOR, API_MINOR)
    _set32(metadata, METADATA_TRAITS, 0)
    return True


@numba.njit(cache=True, nogil=True, inline="always")
def item(frame, which, index):
    """Address of argument (which = FRAME_ARGS) or result (FRAME_RETS) `index`."""
    return words(word(frame, which + LIST_ITEMS), index + 1)[index]


#: bytes of a row of name_table (names are cut to one less)
NAME_BYTES = 32


def name_table(names):
    """Attribute names as attribute_index reads them: uint8 [len(names), NAME_BYTES], each
    row an ASCII name padded with NULs (an array, not a str: numba compiles a function of a
    str once for every literal it is called with, and slowly)."""
    table = np.zeros((len(names), NAME_BYTES), np.uint8)
    for row, name in zip(table, names, strict=True):
        text = name.encode("ascii")
        if len(text) >= NAME_BYTES:
            raise ValueError(f"attribute name: got {name!r}; expected under {NAME_BYTES} "
                             "ASCII characters")
        row[:len(text)] = np.frombuffer(text, np.uint8)
    return table


@numba.njit(cache=True, nogil=True)
def attribute_index(frame, name):
    """Index of the attribute called `name` (a NUL-padded uint8 row of name_table), or -1."""
    length = 0
    while length < name.shape[0] and name[length] != 0:
        length += 1
    attrs = frame + FRAME_ATTRS
    size = word(attrs, LIST_SIZE)
    names = words(word(attrs, ATTRS_NAMES), size)
    for i in range(size):
        span = names[i]
        if word(span, SPAN_LENGTH) != length:
            continue
        text = carray(pointer(word(span, 0)), (max(length, 1),), np.uint8)
        same = True
        for j in range(length):
            if text[j] != name[j]:
                same = False
                break
        if same:
            return i
    return -1


@numba.njit(cache=True, nogil=True)
def attribute_kind(frame, index):
    """(XLA_FFI_AttrType, XLA_FFI_DataType of a scalar else 0) of attribute `index`."""
    attrs = frame + FRAME_ATTRS
    kind = int32(word(attrs, LIST_TYPES), 4 * index)
    if kind != ATTR_SCALAR:
        return kind, np.int64(0)
    return kind, int32(words(word(attrs, ATTRS_ITEMS), index + 1)[index], 0)


@numba.njit(cache=True, nogil=True)
def attribute_value(frame, index):
    """The int64 scalar attribute `index` (one whose kind attribute_kind checked)."""
    value = words(word(frame + FRAME_ATTRS, ATTRS_ITEMS), index + 1)[index]
    return word(word(value, SCALAR_VALUE), 0)


@intrinsic
def address_of(typingctx, ptr):
    """A void pointer (the handler's argument) as an int64 address."""
    if ptr != types.voidptr:
        return None

    def codegen(context, builder, signature, args):
        return builder.ptrtoint(args[0], ir.IntType(64))
    return types.int64(ptr), codegen


@numba.njit(cache=True, nogil=True, inline="always")
def buffer_size(buffer):
    """Number of elements of the XLA_FFI_Buffer at `buffer`."""
    rank = word(buffer, BUFFER_RANK)
    dims = words(word(buffer, BUFFER_DIMS), rank)
    n = 1
    for i in range(rank):
        n *= dims[i]
    return n


@numba.njit(cache=True, nogil=True, inline="always")
def buffer_dim(buffer, axis):
    """Size of an axis (negative: from the end) of the buffer at `buffer`."""
    rank = word(buffer, BUFFER_RANK)
    return words(word(buffer, BUFFER_DIMS), rank)[axis % rank]
