"""The compiled kernel behind diffshade.shading.compact.active_indices: the positions of the
first `capacity` True entries of a boolean mask, and how many there are.

One pass over the mask, written for numba: XLA's own `jnp.nonzero` (a cumulative sum and a
scatter) costs more than lighting the active slots it finds. Called from NumPy
(`first_active`) on the callback path and through the FFI handler (`first_active_into`,
writing into XLA's buffers) under jit.
"""

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def first_active(mask, capacity):
    """(indices [capacity] int32 of the first `capacity` True entries of mask [N], padded
    with N; count [] int32 of all True entries)."""
    idx, count = np.empty(capacity, np.int32), np.empty(1, np.int32)
    first_active_into(mask, idx, count)
    return idx, count[0]


@numba.njit(cache=True, nogil=True)
def first_active_into(mask, idx, count):
    """first_active writing into idx [capacity] and count [1] (the FFI handler's form)."""
    n = mask.shape[0]
    found = 0
    for i in range(n):
        if mask[i]:
            if found < idx.shape[0]:
                idx[found] = i
            found += 1
    for i in range(min(found, idx.shape[0]), idx.shape[0]):
        idx[i] = n
    count[0] = found
