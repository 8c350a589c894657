"""Where numba keeps compiled kernels: one folder per version of the sources.

numba's on-disk cache checks only the source file of the function it loads,
not the files of the functions (and module constants) compiled into it, so a
changed effect module would leave a stale composed kernel in the cache, and so
would a changed drive cycle or record layout in the emulator's compiled tick
(``hil.runtime.steady_tick`` compiles in ``hil.drive.compiled``,
``io_adapters.codec_compiled`` and ``io_adapters.udp_steady``'s layout).
Keying the cache folder on a hash of every source file of the packages whose
kernels are compiled together rules that out; the other packages' files are
read, never imported.  Respects ``NUMBA_CACHE_DIR`` as the base folder.
"""

import hashlib
import os
from pathlib import Path

import numba

#: the packages whose kernels are compiled together (this one among them)
PACKAGES = ("plant", "hil", "io_adapters")


def configure() -> Path:
    """Point numba's cache at ``<base>/<hash of the PACKAGES' sources>`` (those present);
    return that folder."""
    root = Path(__file__).resolve().parent.parent
    digest = hashlib.sha256()
    for package in PACKAGES:
        for src in sorted((root / package).rglob("*.py")):
            digest.update(src.relative_to(root).as_posix().encode())
            digest.update(src.read_bytes())
    base = os.environ.get("NUMBA_CACHE_DIR") or str(Path.home() / ".cache" / "feeddrive-hil")
    folder = Path(base) / f"numba-{digest.hexdigest()[:16]}"
    numba.config.CACHE_DIR = str(folder)
    return folder
