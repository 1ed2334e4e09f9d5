"""LLVM intrinsics the compiled kernels share: an atomic counter that threads claim work
from (`claim`), and the builder helpers of the kernels' vector code (`compress`,
`popcount`)."""

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic


@intrinsic
def claim(typingctx, counter):
    """The next item of a counter shared by threads (counter [1] int64): its value before an
    atomic increment, so that each item goes to exactly one of the threads claiming them."""
    if not (isinstance(counter, types.Array) and counter.dtype == types.int64
            and counter.ndim == 1):
        return None

    def codegen(context, builder, signature, args):
        data = context.make_array(signature.args[0])(context, builder, args[0]).data
        return builder.atomic_rmw("add", data, ir.Constant(ir.IntType(64), 1), "monotonic")
    return types.int64(counter), codegen


def compress(builder, vector, mask):
    """The elements of `vector` (<n x double>, i64 or i32) where `mask` (<n x i1>), first
    (LLVM's vector compress: one instruction where the CPU has one, AVX-512's vcompress;
    elsewhere LLVM expands it)."""
    element = vector.type.element
    kind = "f64" if element == ir.DoubleType() else f"i{element.width}"
    function = cgutils.get_or_insert_function(
        builder.module, ir.FunctionType(vector.type, [vector.type, mask.type, vector.type]),
        f"llvm.experimental.vector.compress.v{vector.type.count}{kind}")
    return builder.call(function, [vector, mask, ir.Constant(vector.type, None)])


def popcount(builder, mask):
    """The number of set lanes of `mask` (<8 x i1>), as an i64."""
    bits = builder.bitcast(mask, ir.IntType(8))
    count = builder.call(cgutils.get_or_insert_function(
        builder.module, ir.FunctionType(ir.IntType(8), [ir.IntType(8)]), "llvm.ctpop.i8"),
        [bits])
    return builder.zext(count, ir.IntType(64))


def splat(builder, scalar, lanes):
    """<lanes x type of scalar> with every lane scalar."""
    vector = ir.VectorType(scalar.type, lanes)
    first = builder.insert_element(ir.Constant(vector, None), scalar,
                                   ir.Constant(ir.IntType(32), 0))
    return builder.shuffle_vector(first, ir.Constant(vector, None),
                                  ir.Constant(ir.VectorType(ir.IntType(32), lanes), [0] * lanes))


#: the most channels a row of Rows holds: one vector of 8 (float32: 256 bits, float64: 512)
ROW_LANES = 8


class Rows:
    """Builder helpers for rows of `channels` <= ROW_LANES float elements (numba dtype
    float32 or float64) as one vector of ROW_LANES whose lanes from `channels` on are
    masked: LLVM's masked loads and stores, which read and write nothing past a row (one
    instruction each with AVX-512). The kernels' loops over a row's channels, which LLVM
    kept scalar, become a vector operation per row, the same operations on each lane in
    the same order, so the same numbers."""

    def __init__(self, context, builder, dtype, channels):
        self.context, self.builder, self.dtype = context, builder, dtype
        element = context.get_data_type(dtype)
        self.vector = ir.VectorType(element, ROW_LANES)
        self.pointer = ir.PointerType(self.vector)
        i32, i64 = ir.IntType(32), ir.IntType(64)
        mask_type = ir.VectorType(ir.IntType(1), ROW_LANES)
        kind = "f32" if element == ir.FloatType() else "f64"
        self._load = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(self.vector, [self.pointer, i32, mask_type,
                                                          self.vector]),
            f"llvm.masked.load.v{ROW_LANES}{kind}.p0")
        self._store = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(ir.VoidType(), [self.vector, self.pointer, i32,
                                                            mask_type]),
            f"llvm.masked.store.v{ROW_LANES}{kind}.p0")
        lanes = ir.Constant(ir.VectorType(i64, ROW_LANES), list(range(ROW_LANES)))
        self.mask = builder.icmp_signed("<", lanes, splat(builder, channels, ROW_LANES))
        self._alignment = ir.Constant(i32, 1)

    def _at(self, data, offset):
        return self.builder.bitcast(self.builder.gep(data, [offset]), self.pointer)

    def load(self, data, offset):
        """The row of elements offset.. of data (a pointer to elements)."""
        return self.builder.call(self._load, [self._at(data, offset), self._alignment,
                                              self.mask, ir.Constant(self.vector, None)])

    def store(self, row, data, offset):
        self.builder.call(self._store, [row, self._at(data, offset), self._alignment,
                                        self.mask])

    def weight(self, value, numba_type):
        """A scalar (of numba_type) cast to the rows' dtype, in every lane."""
        return splat(self.builder, self.context.cast(self.builder, value, numba_type,
                                                     self.dtype), ROW_LANES)
