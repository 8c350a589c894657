"""Flat offsets into the kernel's arrays as integers the compiler can see are non-negative.

The params and state vectors hold their block offsets and node counts as float64
(:mod:`plant.layout`).  Converted with ``int()`` they are signed, and numba wraps every
signed index that might be negative (``a[i]`` reads ``a[i + len]`` for ``i < 0``): a
compare and select on each access of the sub-step's hot loops, and an address LLVM can no
longer fold.  :func:`offset` masks the value to :data:`INDEX_BITS` bits, so LLVM knows the
sign bit is clear, and so is that of every sum of a few such offsets: the wrap disappears
from those accesses at the price of one ``and`` where the offset is read.  The kernel's
arrays hold a few hundred values, far below the mask.
"""

from numba import njit

#: bits an offset or count keeps: 16 M entries, ample for any axis (a few hundred) while
#: sums of a few offsets stay far from the sign bit
INDEX_BITS = 24
_MASK = (1 << INDEX_BITS) - 1


@njit(cache=True, error_model="numpy", inline="always")
def offset(x):
    """The whole number ``x`` (a non-negative offset or count held as float64, or an int)
    as a non-negative int the compiler can prove non-negative."""
    return int(x) & _MASK
