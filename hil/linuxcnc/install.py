"""Where LinuxCNC is, how its programs are started, and the feeddrive HAL component built
for it.

LinuxCNC 2.9 (Debian's ``linuxcnc-uspace``) is found either

* **in a prefix**: the packages unpacked with ``dpkg -x`` into a folder (``.ci/test-deps``
  does this: nothing of the machine's own installation changes), named by the environment
  variable :data:`PREFIX_ENV` or at :data:`DEFAULT_PREFIX`; or
* **installed** (``/usr/bin/linuxcnc``, ``apt-get install linuxcnc-uspace``).

LinuxCNC's programs and scripts name their files by absolute paths (``/usr/bin/rtapi_app``,
``/usr/lib/linuxcnc/modules``, ``/etc/linuxcnc``), and ``rtapi_app`` loads a component only
from its modules folder.  So every LinuxCNC program runs in a private mount namespace
(``unshare --mount``) in which ``/usr`` and ``/etc`` are read-only overlays: the component
built here, then the prefix, then the machine's own.  The overlays exist for those
processes only and vanish with them; this needs root.  Without root, LinuxCNC must be
installed and the component installed into it (``halcompile --install``, which
:func:`build_component`'s error says).

LinuxCNC refuses to run its real-time part as root unless ``RTAPI_UID`` names the user to
drop to (:func:`environment`); with no PREEMPT_RT kernel it runs in POSIX non-real-time
mode: its servo thread is an ordinary thread and wakes as the scheduler lets it.
"""

import hashlib
import os
import pwd
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import io_adapters

#: the environment variable naming LinuxCNC's prefix
PREFIX_ENV = "HIL_LINUXCNC_PREFIX"
#: where .ci/test-deps unpacks it when the variable is not set
DEFAULT_PREFIX = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") \
    / "feeddrive-hil" / "linuxcnc"
#: the component's C source and the wire header it includes (package data)
COMPONENT_SOURCE = Path(__file__).resolve().parent / "hal" / "feeddrive.c"
WIRE_HEADER = Path(io_adapters.__file__).resolve().parent / "include" / "feeddrive_wire.h"
#: the modules folder of LinuxCNC's uspace build, inside the overlays
MODULES = Path("usr/lib/linuxcnc/modules")
#: the longest a component build may take, s
BUILD_TIMEOUT_S = 300.0


class LinuxCNCUnavailable(RuntimeError):
    """LinuxCNC cannot be run here; the message says why and what would fix it."""


@dataclass(frozen=True)
class LinuxCNC:
    """One LinuxCNC installation.

    Attributes:
        prefix: the folder its packages were unpacked into (``usr/``, ``etc/`` under it),
            or None for an installed LinuxCNC.
        layer: the folder whose ``usr/`` holds the built component (overlaid on ``/usr``
            above the prefix), or None before :func:`build_component`.
    """
    prefix: Path | None
    layer: Path | None = None

    @property
    def namespaced(self) -> bool:
        """Its programs run in a private mount namespace (root only)."""
        return self.prefix is not None or self.layer is not None

    def argv(self, argv: list[str]) -> list[str]:
        """``argv`` as it must be started: in the namespace with the overlays, or as it
        is."""
        if not self.namespaced:
            return list(argv)
        usr = [str(d / "usr") for d in (self.layer, self.prefix) if d is not None]
        etc = [str(self.prefix / "etc")] if self.prefix is not None else []
        mounts = [f"mount -t overlay overlay -o lowerdir={':'.join([*usr, '/usr'])} /usr"]
        if etc:
            mounts.append(f"mount -t overlay overlay -o lowerdir={etc[0]}:/etc /etc")
        script = " && ".join(mounts) + ' && exec "$@"'
        return ["unshare", "--mount", "--propagation", "private", "sh", "-c", script, "sh",
                *argv]


def find() -> LinuxCNC:
    """The LinuxCNC to use: the prefix of :data:`PREFIX_ENV` (which must hold it), else
    the one at :data:`DEFAULT_PREFIX`, else an installed one; LinuxCNCUnavailable saying
    how to get one otherwise."""
    named = os.environ.get(PREFIX_ENV)
    if named:
        prefix = Path(named)
        if not (prefix / "usr" / "bin" / "linuxcnc").exists():
            raise LinuxCNCUnavailable(f"{PREFIX_ENV}={named}: no usr/bin/linuxcnc there")
        return _checked(LinuxCNC(prefix.resolve()))
    if (DEFAULT_PREFIX / "usr" / "bin" / "linuxcnc").exists():
        return _checked(LinuxCNC(DEFAULT_PREFIX.resolve()))
    if Path("/usr/bin/linuxcnc").exists():
        return LinuxCNC(None)
    raise LinuxCNCUnavailable(
        f"LinuxCNC 2.9 is not installed: run .ci/test-deps (it unpacks Debian's "
        f"linuxcnc-uspace into {DEFAULT_PREFIX}), set {PREFIX_ENV}, or apt-get install "
        f"linuxcnc-uspace linuxcnc-uspace-dev")


def _checked(lc: LinuxCNC) -> LinuxCNC:
    """A prefix can be used only as root, with unshare."""
    if os.geteuid() != 0:
        raise LinuxCNCUnavailable(
            f"LinuxCNC in the prefix {lc.prefix} runs only as root (its files are overlaid "
            f"on /usr in a private mount namespace)")
    if shutil.which("unshare") is None:
        raise LinuxCNCUnavailable("unshare (util-linux) is not installed")
    try:  # a container may refuse mount namespaces or overlays
        done = subprocess.run(lc.argv(["true"]), capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired) as e:
        raise LinuxCNCUnavailable(f"cannot overlay the prefix {lc.prefix} on /usr: {e}") from e
    if done.returncode != 0:
        raise LinuxCNCUnavailable(f"cannot overlay the prefix {lc.prefix} on /usr in a mount "
                                  f"namespace: {done.stderr.strip()}")
    return lc


def unprivileged_uid() -> int:
    """The user LinuxCNC's real-time part drops to when started as root: ``nobody``."""
    try:
        return pwd.getpwnam("nobody").pw_uid
    except KeyError:
        return 65534


def environment(home: Path, socket_dir: Path) -> dict[str, str]:
    """The environment of LinuxCNC's programs: ``home`` (created) as HOME, where its
    scripts write their logs; rtapi_app's socket in ``socket_dir`` (which, as every folder
    above it, the unprivileged user must reach: a fresh folder under /tmp), ``RTAPI_UID``
    when root."""
    home.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "HOME": str(home), "RTAPI_FIFO_PATH": str(socket_dir / "rtapi_fifo")}
    if os.geteuid() == 0:
        uid = unprivileged_uid()
        os.chown(socket_dir, uid, -1)
        env["RTAPI_UID"] = str(uid)
    env.pop("DISPLAY", None)  # headless: no X display, whatever the caller has
    # LinuxCNC's Python is the system's, not this one's
    for name in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV"):
        env.pop(name, None)
    return env


def _source_key(lc: LinuxCNC) -> str:
    h = hashlib.sha256()
    for path in (COMPONENT_SOURCE, WIRE_HEADER):
        h.update(path.read_bytes())
    h.update(str(lc.prefix).encode())
    return h.hexdigest()[:16]


def build_component(lc: LinuxCNC, cache: Path) -> LinuxCNC:
    """``lc`` with the feeddrive component built (``halcompile --compile``) into a layer
    under ``cache``, reused while the sources are the same; LinuxCNCUnavailable if it cannot
    be built or (not root, an installed LinuxCNC) is not installed."""
    if os.geteuid() != 0 and lc.prefix is None:
        if (Path("/") / MODULES / "feeddrive.so").exists():
            return lc
        raise LinuxCNCUnavailable(
            f"the feeddrive component is not installed into LinuxCNC: copy {COMPONENT_SOURCE} "
            f"and {WIRE_HEADER} into one folder and run 'sudo halcompile --install "
            f"feeddrive.c' there, or run as root")
    layer = cache / f"feeddrive-{_source_key(lc)}"
    module = layer / MODULES / "feeddrive.so"
    if module.exists():
        return LinuxCNC(lc.prefix, layer)
    build = cache / "build"
    shutil.rmtree(build, ignore_errors=True)
    build.mkdir(parents=True)
    for path in (COMPONENT_SOURCE, WIRE_HEADER):
        shutil.copy(path, build / path.name)
    try:
        done = subprocess.run(lc.argv(["halcompile", "--compile", "feeddrive.c"]), cwd=build,
                              capture_output=True, text=True, timeout=BUILD_TIMEOUT_S)
    except (OSError, subprocess.TimeoutExpired) as e:
        raise LinuxCNCUnavailable(f"halcompile could not be run: {e}") from e
    if done.returncode != 0 or not (build / "feeddrive.so").exists():
        raise LinuxCNCUnavailable(f"halcompile --compile feeddrive.c failed:\n"
                                  f"{done.stdout}{done.stderr}")
    module.parent.mkdir(parents=True, exist_ok=True)
    shutil.copy(build / "feeddrive.so", module)
    return LinuxCNC(lc.prefix, layer)
