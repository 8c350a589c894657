"""The reference for wake-up latency: ``cyclictest`` from Debian's ``rt-tests``.

``cyclictest`` sleeps with ``clock_nanosleep`` on absolute deadlines at a fixed interval,
as a C thread at SCHED_FIFO with its memory locked and ``/dev/cpu_dma_latency`` held at 0,
and records how late each wake-up was.  :func:`run_cyclictest` runs it for a while with
a histogram of 1 µs bins and reduces the histogram to the percentiles a
:class:`~hil.rt.loop.RealTimeLoop` reports.  The bins truncate to whole µs, so its
figures may read up to 1 µs lower than the same latencies measured in ns.

When ``cyclictest`` is not installed :func:`run_cyclictest` returns ``None``; install it
with ``apt-get install rt-tests``.
"""

import math
import shutil
import subprocess
import tempfile
from pathlib import Path

from hil.rt.loop import Percentiles, nearest_rank

#: histogram range (µs): long enough for the multi-millisecond pauses a VM shows.
DEFAULT_HISTOGRAM_US = 20_000


class CyclictestError(RuntimeError):
    """cyclictest ran but failed, or wrote a histogram this module cannot read."""


def parse_histogram(text: str) -> Percentiles:
    """Percentiles (µs) from cyclictest's ``-h`` output (stdout or ``--histfile``).

    Bin lines are ``<µs> <count> [<count> ...]`` (one count per thread, summed here);
    ``# Histogram Overflows`` are the samples past the last bin, ranked above it: a
    percentile that falls among them reads as ``# Max Latencies``.
    """
    bins_us: list[int] = []
    counts: list[int] = []
    max_us = overflows = None
    for line in text.splitlines():
        if line.startswith("#"):
            key, _, values = line[1:].partition(":")
            key = key.strip()
            if key == "Max Latencies":
                max_us = max(int(v) for v in values.split())
            elif key == "Histogram Overflows":
                overflows = sum(int(v) for v in values.split())
            continue
        fields = line.split()
        if len(fields) >= 2 and fields[0].isdigit():
            bins_us.append(int(fields[0]))
            counts.append(sum(int(c) for c in fields[1:]))
    if max_us is None or overflows is None or not bins_us:
        raise CyclictestError("not a cyclictest histogram: no bins, '# Max Latencies' "
                              "or '# Histogram Overflows' found")
    total = sum(counts) + overflows
    if total == 0:
        return Percentiles(*([float("nan")] * 4))

    def percentile_us(permille: int) -> float:
        rank = nearest_rank(permille, total)
        seen = 0
        for b, c in zip(bins_us, counts):
            seen += c
            if seen >= rank:
                return float(b)
        return float(max_us)

    return Percentiles(p50=percentile_us(500), p99=percentile_us(990),
                       p999=percentile_us(999), max=float(max_us))


def samples_beyond(text: str, threshold_us: float) -> tuple[int, int]:
    """From cyclictest's ``-h`` output: (samples whose latency exceeded ``threshold_us``,
    the overflows past the histogram's range among them; all samples).  A bin of b µs
    holds latencies in [b, b + 1): it counts when b >= ``threshold_us``."""
    beyond = total = 0
    overflows = 0
    for line in text.splitlines():
        if line.startswith("#"):
            key, _, values = line[1:].partition(":")
            if key.strip() == "Histogram Overflows":
                overflows = sum(int(v) for v in values.split())
            continue
        fields = line.split()
        if len(fields) >= 2 and fields[0].isdigit():
            n = sum(int(c) for c in fields[1:])
            total += n
            if int(fields[0]) >= threshold_us:
                beyond += n
    return beyond + overflows, total + overflows


def cyclictest_histogram(interval_us: int, seconds: float, priority: int = 80,
                         cpu: int | None = None,
                         histogram_us: int = DEFAULT_HISTOGRAM_US) -> str | None:
    """Run ``cyclictest -q -m -p <priority> -i <interval_us> -D <seconds> -h <range>
    [-a <cpu>]`` and return its histogram file's text (see :func:`run_cyclictest` for the
    arguments), or ``None`` when cyclictest is not installed.

    Raises:
        CyclictestError: it ran and failed (e.g. SCHED_FIFO refused to a non-root user).
    """
    exe = shutil.which("cyclictest")
    if exe is None:
        return None
    with tempfile.TemporaryDirectory(prefix="cyclictest-") as tmp:
        histfile = Path(tmp) / "histogram.txt"
        cmd = [exe, "-q", "-m", "-p", str(priority), "-i", str(int(interval_us)),
               "-D", str(max(1, math.ceil(seconds))), "-h", str(histogram_us),
               f"--histfile={histfile}"]
        if cpu is not None:
            cmd += ["-a", str(cpu)]
        res = subprocess.run(cmd, capture_output=True, text=True, check=False,
                             timeout=seconds + 60)
        if res.returncode != 0 or not histfile.exists():
            raise CyclictestError(f"{' '.join(cmd)} exited with {res.returncode}: "
                                  f"{(res.stderr or res.stdout).strip()[-500:]}")
        return histfile.read_text()


def run_cyclictest(interval_us: int, seconds: float, priority: int = 80,
                   cpu: int | None = None,
                   histogram_us: int = DEFAULT_HISTOGRAM_US) -> Percentiles | None:
    """Run ``cyclictest -q -m -p <priority> -i <interval_us> -D <seconds> -h ...``.

    Args:
        interval_us: wake-up interval (µs).
        seconds: duration, rounded up to whole seconds (cyclictest's resolution).
        priority: SCHED_FIFO priority of the measuring thread.
        cpu: pin the measuring thread to this CPU (``-a``), or leave it free.
        histogram_us: histogram range (µs); later wake-ups count as overflows.

    Returns:
        The wake-up latency percentiles (µs), or ``None`` when cyclictest is not installed.

    Raises:
        CyclictestError: it ran and failed (e.g. SCHED_FIFO refused to a non-root user).
    """
    text = cyclictest_histogram(interval_us, seconds, priority, cpu, histogram_us)
    return None if text is None else parse_histogram(text)
