"""The host a run's timing belongs to: kernel, preemption model, CPU, frequency governors,
virtualisation, Python and numba.

:func:`host_fingerprint` reads it from ``/proc``, ``/sys`` and ``systemd-detect-virt``.
Each fact comes from one documented place; a file that is missing or unreadable gives
``"unavailable"`` (or the fallback named below) and never an exception, so a container or
a kernel without cpufreq still gets a report.  The paths are module attributes so tests
can point them at a fake tree.
"""

import os
import platform
import re
import shutil
import subprocess
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

#: "1" on a PREEMPT_RT kernel (absent on other kernels)
REALTIME_PATH = Path("/sys/kernel/realtime")
CPUINFO_PATH = Path("/proc/cpuinfo")
#: holds cpuN/cpufreq/scaling_governor
CPU_SYSFS = Path("/sys/devices/system/cpu")
UNAVAILABLE = "unavailable"
#: longest wait for systemd-detect-virt, s
DETECT_VIRT_TIMEOUT_S = 5.0


def _read(path: Path) -> str | None:
    """The file's text, stripped, or None if it cannot be read."""
    try:
        return path.read_text(errors="replace").strip()
    except OSError:
        return None


def _cpuinfo_fields(name: str) -> list[str]:
    """Every value of ``name`` in /proc/cpuinfo (one per CPU on x86), in order."""
    text = _read(CPUINFO_PATH) or ""
    return [value.strip() for key, _, value in (line.partition(":") for line in text.splitlines())
            if key.strip() == name]


def preempt_rt() -> tuple[bool, str]:
    """(PREEMPT_RT kernel or not, where that was read): ``/sys/kernel/realtime`` when the
    kernel has it, otherwise a ``PREEMPT_RT`` word in ``uname -v``."""
    flag = _read(REALTIME_PATH)
    if flag is not None:
        return flag == "1", str(REALTIME_PATH)
    return "PREEMPT_RT" in os.uname().version.split(), "uname -v"


def preemption_model() -> str:
    """The preemption word of ``uname -v`` (PREEMPT_RT, PREEMPT_DYNAMIC, PREEMPT, ...),
    or "none stated"."""
    words = [w for w in os.uname().version.split() if w.startswith("PREEMPT")]
    return " ".join(words) or "none stated"


def cpu_model() -> str:
    """The first ``model name`` of /proc/cpuinfo (x86), else its ``Hardware``/``Model`` line
    (Arm), else the machine type of ``uname -m``."""
    for key in ("model name", "Hardware", "Model"):
        values = _cpuinfo_fields(key)
        if values:
            return values[0]
    return platform.machine() or UNAVAILABLE


def cpu_count() -> int:
    """``processor`` entries in /proc/cpuinfo, else ``os.cpu_count()`` (0 if unknown)."""
    return len(_cpuinfo_fields("processor")) or os.cpu_count() or 0


def _cpu_numbers() -> list[int]:
    """The CPUs sysfs lists (cpuN folders), else 0 .. cpu_count() - 1."""
    try:
        found = sorted(int(m.group(1)) for p in CPU_SYSFS.iterdir()
                       if (m := re.fullmatch(r"cpu(\d+)", p.name)))
    except OSError:
        found = []
    return found or list(range(cpu_count()))


def governors() -> dict[str, str]:
    """``{"cpuN": scaling governor}`` per CPU; "unavailable" where cpufreq does not say
    (a VM, or a kernel without cpufreq)."""
    return {f"cpu{n}": _read(CPU_SYSFS / f"cpu{n}" / "cpufreq" / "scaling_governor") or UNAVAILABLE
            for n in _cpu_numbers()}


def _detect_virt(exe: str, which: str) -> str | None:
    try:
        res = subprocess.run([exe, f"--{which}"], capture_output=True, text=True,
                             timeout=DETECT_VIRT_TIMEOUT_S, check=False)
    except (OSError, subprocess.SubprocessError):
        return None
    return res.stdout.strip() or None  # "none" (exit status 1) when there is none


def virtualization() -> str:
    """A hint, not a proof: ``systemd-detect-virt --vm`` and ``--container`` when installed
    (e.g. "vm kvm, container docker"); otherwise whether /proc/cpuinfo sets the
    ``hypervisor`` flag."""
    exe = shutil.which("systemd-detect-virt")
    if exe is not None:
        vm, container = _detect_virt(exe, "vm"), _detect_virt(exe, "container")
        if vm is not None or container is not None:
            return f"vm {vm or UNAVAILABLE}, container {container or UNAVAILABLE}"
    flags = _cpuinfo_fields("flags")
    if not flags:
        return UNAVAILABLE
    return ("hypervisor flag set in /proc/cpuinfo (VM, type unknown)"
            if "hypervisor" in flags[0].split() else "no hypervisor flag in /proc/cpuinfo")


def _package_version(name: str) -> str:
    try:
        return version(name)
    except PackageNotFoundError:
        return "not installed"


def host_fingerprint() -> dict:
    """The host's facts as a JSON-ready dict (every key always present)::

        {"kernel_release", "kernel_version", "machine", "preempt_rt": bool,
         "preempt_rt_source", "preemption", "cpu_model", "cpu_count": int,
         "governors": {"cpuN": str}, "virtualization", "python", "numba"}
    """
    rt, rt_source = preempt_rt()
    uname = os.uname()
    return {"kernel_release": uname.release, "kernel_version": uname.version,
            "machine": uname.machine, "preempt_rt": rt, "preempt_rt_source": rt_source,
            "preemption": preemption_model(), "cpu_model": cpu_model(), "cpu_count": cpu_count(),
            "governors": governors(), "virtualization": virtualization(),
            "python": platform.python_version(), "numba": _package_version("numba")}
