"""Where numba keeps compiled kernels: one folder per version of the plant's source.

numba's on-disk cache checks only the source file of the function it loads,
not the files of the functions that were inlined into it, so a changed effect
module would leave a stale composed kernel in the cache.  Keying the cache
folder on a hash of every source file of this package rules that out.
Respects ``NUMBA_CACHE_DIR`` as the base folder.
"""

import hashlib
import os
from pathlib import Path

import numba


def configure() -> Path:
    """Point numba's cache at ``<base>/<hash of plant sources>``; return that folder."""
    here = Path(__file__).resolve().parent
    digest = hashlib.sha256()
    for src in sorted(here.rglob("*.py")):
        digest.update(src.relative_to(here).as_posix().encode())
        digest.update(src.read_bytes())
    base = os.environ.get("NUMBA_CACHE_DIR") or str(Path.home() / ".cache" / "feeddrive-hil")
    folder = Path(base) / f"numba-{digest.hexdigest()[:16]}"
    numba.config.CACHE_DIR = str(folder)
    return folder
