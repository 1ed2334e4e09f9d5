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
