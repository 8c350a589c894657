"""The plant kernel's sub-step ported to C (``substep.c``), built with the system compiler
and loaded with ctypes: the baseline ``hil bench plant`` measures the numba kernel against.

The port has the same equations in the same floating-point order as :mod:`plant.kernel`
and is compiled with ``-O2 -ffp-contract=off`` (no fused multiply-add), so from the same
arrays it gives the same state to the last bit (``tests/test_csubstep.py``).  The indices
come from ``layout.h``, written here from :mod:`plant.layout`, so the two never drift.  It
covers the Arrow 500 X's models (d-q motor, screw, lumped solver, Karnopp friction):
:meth:`CStep.supports` says whether a params vector is one of them.

The shared object is kept in ``<NUMBA_CACHE_DIR or ~/.cache/feeddrive-hil>/csubstep-<hash>``,
the hash covering the source, the header and the compiler's command line.
"""

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from plant import layout
from plant.effects.friction import STRIBECK_CUTOFF

SOURCE = Path(__file__).resolve().parent / "substep.c"
#: the compiler flags: optimised as a release build, no contraction into FMA (bit-identity)
CFLAGS = ("-O2", "-ffp-contract=off", "-fPIC", "-shared", "-std=c11", "-D_GNU_SOURCE")
_PREFIXES = ("P_", "S_", "I_", "O_", "MOTOR_", "MECH_", "SOLVER_", "INPUT_", "STATUS_")


class CCompilerMissing(RuntimeError):
    """No C compiler (``$CC``, ``cc`` or ``gcc``) on PATH."""


def compiler() -> str | None:
    """Path of the C compiler to use (``$CC``, else ``cc``, else ``gcc``), or None."""
    for name in (os.environ.get("CC"), "cc", "gcc"):
        if name and (found := shutil.which(name)):
            return found
    return None


def layout_header() -> str:
    """``layout.h``: every index and selector of :mod:`plant.layout` as a ``#define``, and
    the effects' constants the port uses."""
    lines = ["/* written by hil.bench.csubstep from plant/layout.py: do not edit */"]
    for name in sorted(vars(layout)):
        value = getattr(layout, name)
        if name.startswith(_PREFIXES) and type(value) is int:
            lines.append(f"#define {name} {value}")
    lines.append(f"#define STRIBECK_CUTOFF {STRIBECK_CUTOFF!r}")
    return "\n".join(lines) + "\n"


def _cache_base() -> Path:
    base = os.environ.get("NUMBA_CACHE_DIR") or str(Path.home() / ".cache" / "feeddrive-hil")
    return Path(base)


def build() -> Path:
    """Compile ``substep.c`` (once per source, header and compiler); the shared object.

    Raises:
        CCompilerMissing: no C compiler on PATH.
        RuntimeError: the compiler failed (its message attached).
    """
    cc = compiler()
    if cc is None:
        raise CCompilerMissing("no C compiler on PATH ($CC, cc or gcc): the C baseline of "
                               "hil bench plant needs one (apt-get install gcc)")
    header = layout_header()
    digest = hashlib.sha256()
    for part in (SOURCE.read_bytes(), header.encode(), " ".join((cc, *CFLAGS)).encode()):
        digest.update(part)
    folder = _cache_base() / f"csubstep-{digest.hexdigest()[:16]}"
    lib = folder / "substep.so"
    if lib.exists():
        return lib
    folder.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=folder) as tmp:
        (Path(tmp) / "layout.h").write_text(header)
        target = Path(tmp) / "substep.so"
        res = subprocess.run([cc, *CFLAGS, "-I", tmp, "-o", str(target), str(SOURCE), "-lm"],
                             capture_output=True, text=True, check=False)
        if res.returncode != 0:
            raise RuntimeError(f"{cc} failed on {SOURCE}:\n{res.stderr[-2000:]}")
        os.replace(target, lib)  # atomic: a concurrent build finds a whole file or none
    return lib


_DOUBLES = np.ctypeslib.ndpointer(dtype=np.float64, flags="C_CONTIGUOUS")


class CStep:
    """The C sub-step on a plant's arrays (the layout of :mod:`plant.layout`)."""

    def __init__(self):
        lib = ctypes.CDLL(str(build()))
        lib.c_supports.argtypes = [_DOUBLES]
        lib.c_supports.restype = ctypes.c_int
        lib.c_axis_step.argtypes = [_DOUBLES, _DOUBLES, _DOUBLES, _DOUBLES, ctypes.c_long,
                                    ctypes.c_long]
        lib.c_axis_step.restype = ctypes.c_int
        lib.c_time_calls.argtypes = [_DOUBLES, _DOUBLES, _DOUBLES, _DOUBLES, ctypes.c_long,
                                     ctypes.c_long, ctypes.c_long]
        lib.c_time_calls.restype = ctypes.c_double
        self._lib = lib

    def supports(self, params: np.ndarray) -> bool:
        """Whether the port runs the axis ``params`` describes (d-q motor, screw, lumped
        solver, no presliding, no fault terms: ``P_FAULTS`` 0)."""
        return bool(self._lib.c_supports(params))

    def axis_step(self, params: np.ndarray, state: np.ndarray, inp: np.ndarray,
                  out: np.ndarray, n_sub: int) -> int:
        """As :func:`plant.kernel.axis_step_nb`: ``n_sub`` sub-steps, then the outputs;
        the status code.  The arrays must be float64 and contiguous (ctypes checks)."""
        return int(self._lib.c_axis_step(params, state, inp, out, n_sub, state.size))

    def time_calls(self, params: np.ndarray, state: np.ndarray, inp: np.ndarray,
                   out: np.ndarray, n_sub: int, calls: int) -> float:
        """Wall time (ns) of ``calls`` calls of :meth:`axis_step`, looped in C."""
        return float(self._lib.c_time_calls(params, state, inp, out, n_sub, state.size,
                                            calls))
