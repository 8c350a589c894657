"""pyarrow, with the C library's allocator: every module of the recording imports it from
here.

pyarrow allocates from mimalloc by default, which reserves a 1 GiB arena up front; under
real-time scheduling (``mlockall(MCL_CURRENT | MCL_FUTURE)``, :mod:`hil.rt.scheduling`)
that whole reservation becomes resident and locked: ``hil run`` measured 1.8 GB of RSS
instead of 0.8 GB.  ``ARROW_DEFAULT_MEMORY_POOL`` is read once, when pyarrow first
allocates, so it is set here, before the import (unless the environment already says
otherwise).
"""

import os

os.environ.setdefault("ARROW_DEFAULT_MEMORY_POOL", "system")

import pyarrow as pa  # noqa: E402  (the pool must be chosen before pyarrow loads)

__all__ = ["pa"]
