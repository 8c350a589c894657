"""Values on a grid (ticks times a period, counts times a resolution) as the float nearest
their exact value, so that a file written with ``repr`` shows the exact decimal: tick 36
of a 125 µs period prints as ``0.0045``, not ``0.0045000000000000005`` (36 * 0.000125 in
floats rounds twice), and 1234567 counts of a 0.1 µm scale as ``123.4567`` mm.

The step is an exact fraction (:func:`decimal_step` recovers the decimal a float step was
written as); :func:`on_grid` multiplies in integers and divides once, which IEEE 754
rounds correctly, wherever the integers stay exact in a float.
"""

import math
from fractions import Fraction

import numpy as np

#: integers up to this magnitude are exact in a float64
EXACT_INT = 2 ** 53
#: :func:`decimal_step` accepts a decimal this many ulps from the float: a step computed
#: by two roundings (lead/2π over counts/2π, a period of ns times 1e-9) is off by one or two
ROUNDING_ULPS = 2


def decimal_step(step: float) -> Fraction:
    """The shortest decimal within :data:`ROUNDING_ULPS` of ``step`` (any unit), exactly:
    the value a machine file's ``1e-7`` or a computed ``5.0000000000000004e-08`` (2.5 mm
    lead over 50 000 counts) stands for.

    Raises:
        ValueError: ``step`` is NaN or infinite.
    """
    if not math.isfinite(step):
        raise ValueError(f"a grid step must be a finite number, not {step!r}")
    for digits in range(1, 18):
        text = f"{step:.{digits}g}"
        if abs(float(text) - step) <= ROUNDING_ULPS * math.ulp(step):
            return Fraction(text)
    return Fraction(step)  # 17 digits always read back: not reached


def on_grid(n: np.ndarray, step: Fraction) -> np.ndarray:
    """``n * step`` as float64: the float nearest the exact product wherever every ``n`` is
    a whole number (counts are recorded as floats) and ``|n| * numerator`` and the
    denominator are exact in a float (below 2**53: counts of a 0.1 µm scale up to 900 km);
    else ``n`` times the float nearest ``step``, one rounding more (NaN stays NaN)."""
    n = np.asarray(n)
    p, q = step.numerator, step.denominator
    whole = n.dtype.kind in "iu" or bool(np.all(n == np.round(n)))
    largest = int(np.max(np.abs(n))) if n.size and whole else 0
    if whole and q < EXACT_INT and largest * abs(p) < EXACT_INT:
        return (n.astype(np.int64) * p).astype(np.float64) / q
    return n * float(step)
