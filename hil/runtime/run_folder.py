"""The run folder of ``hil run --record DIR``: checked before ``ready:``, written without
following a symlink, never overwriting a run unless told to.

:meth:`RunFolder.open` makes the folder if it is missing, opens it once (every file is
then created relative to that descriptor, so renaming or replacing the path later does
not redirect a write), checks that it is writable, and refuses a folder that already
holds a run (any of :data:`RUN_FILES`) unless ``force`` is given, in which case those
names are removed first (a symlink is removed, never its target).  Every file is created
with ``O_CREAT | O_EXCL | O_NOFOLLOW``: an entry planted under one of its names between
the check and the write -- a symlink above all -- makes the write fail rather than go
through it.  :meth:`RunFolder.check_space` refuses a folder without room for the
recording the run asks for, saying the figure; :meth:`RunFolder.hold_reserve` then takes
:data:`RESERVE_BYTES` that a full disk gives back to the run's last writes.

The reserve is a file allocated and unlinked at once, held by its open descriptor only:
its blocks stay taken while the descriptor is open and go back to the file system when
it closes -- :meth:`RunFolder.release_reserve`, or the kernel when the process ends in
whatever way, SIGKILL included.  So no exit path leaves it behind (a named file would
outlive a killed process).  The descriptor is close-on-exec: the recording's writer
process does not hold it.

Every refusal is a :class:`RunFolderError` naming the folder, the file and the reason;
``hil run`` prints it and exits 2 before it prints ``ready:``.
"""

import errno
import json
import os
import threading
from pathlib import Path

from hil.runtime.common import RuntimeInputError, _finite

RECORDING = "recording.arrows"
EVENTS = "events.arrows"
REPORT = "report.json"
#: the files of a run: a folder holding any of them holds a run
RUN_FILES = (RECORDING, EVENTS, REPORT)
_CREATE = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC
_PROBE = ".hil-run-probe"
_RESERVE = ".hil-run-reserve"
#: room held back while the run writes, given back for its last writes when the disk is
#: full (the recording's end, the events, report.json), bytes
RESERVE_BYTES = 1_000_000


class RunFolderError(RuntimeInputError):
    """The run folder cannot take the run; the message names the folder and why."""


def _strerror(e: OSError) -> str:
    return f"{e.strerror or e} (errno {errno.errorcode.get(e.errno, e.errno)})"


def human_bytes(n: float) -> str:
    """``n`` bytes in B, kB, MB, GB or TB (powers of 1000), three significant digits."""
    for unit in ("B", "kB", "MB", "GB"):
        if abs(n) < 1000:
            return f"{n:.3g} {unit}"
        n /= 1000
    return f"{n:.3g} TB"


class RunFolder:
    """An open run folder (see the module docstring); close it when the run is written.

    Attributes:
        path: the folder as given.
        fd: the folder's descriptor, every file is created relative to it.
    """

    def __init__(self, path: Path, fd: int):
        self.path = path
        self.fd = fd
        self._reserve_fd = -1
        self._reserve_lock = threading.Lock()

    @classmethod
    def open(cls, path: Path | str, force: bool = False) -> "RunFolder":
        """Make (if missing), open and check the folder; with ``force`` remove a previous
        run's files.  Raises :class:`RunFolderError`."""
        path = Path(path)
        try:
            path.mkdir(parents=True, exist_ok=True)
            fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
        except FileExistsError as e:
            raise RunFolderError(f"--record {path}: exists and is not a folder") from e
        except OSError as e:
            raise RunFolderError(f"--record {path}: cannot make or open the run folder: "
                                 f"{_strerror(e)}") from e
        folder = cls(path, fd)
        try:
            folder._check_writable()
            folder._clear_previous(force)
        except RunFolderError:
            folder.close()
            raise
        return folder

    def hold_reserve(self) -> None:
        """Take :data:`RESERVE_BYTES` on the disk now (allocated, not sparse), so that the
        run's last writes fit once the disk is full (:meth:`release_reserve`); the file is
        unlinked at once and held open (module docstring).  A reserve a killed run of an
        older version left under the name is removed."""
        self.release_reserve()
        self.unlink(_RESERVE)
        fd = self.create(_RESERVE)
        try:
            self.unlink(_RESERVE)
            os.posix_fallocate(fd, 0, RESERVE_BYTES)
        except OSError as e:
            os.close(fd)
            raise RunFolderError(f"--record {self.path}: cannot hold back "
                                 f"{human_bytes(RESERVE_BYTES)} for the run's last writes: "
                                 f"{_strerror(e)}") from e
        with self._reserve_lock:
            self._reserve_fd = fd

    def release_reserve(self) -> None:
        """Give the reserve back: its descriptor closed, its blocks free (idempotent; safe
        from the recording's answer thread: one caller gets the descriptor to close)."""
        with self._reserve_lock:
            fd, self._reserve_fd = self._reserve_fd, -1
        if fd >= 0:
            os.close(fd)

    def _check_writable(self) -> None:
        try:
            self.unlink(_PROBE)
            os.close(self.create(_PROBE))
            self.unlink(_PROBE)
        except OSError as e:
            raise RunFolderError(f"--record {self.path}: the run folder is not writable: "
                                 f"{_strerror(e)}") from e

    def _clear_previous(self, force: bool) -> None:
        present = [name for name in RUN_FILES if self._exists(name)]
        if not present:
            return
        if not force:
            raise RunFolderError(f"--record {self.path}: the folder holds a run "
                                 f"({', '.join(present)}); give --force to replace it, or "
                                 "another folder")
        for name in present:
            try:
                self.unlink(name)
            except OSError as e:
                raise RunFolderError(f"--record {self.path}: cannot remove the previous "
                                     f"run's {name}: {_strerror(e)}") from e

    def _exists(self, name: str) -> bool:
        try:
            os.lstat(name, dir_fd=self.fd)
        except FileNotFoundError:
            return False
        return True

    def free_bytes(self) -> int:
        """Bytes free for an unprivileged writer on the folder's file system."""
        st = os.fstatvfs(self.fd)
        return st.f_bavail * st.f_frsize

    def check_space(self, need_bytes: float, what: str) -> None:
        """Refuse when the file system has less than ``need_bytes`` free; ``what`` says
        what they are for (it goes into the message)."""
        free = self.free_bytes()
        if free < need_bytes:
            raise RunFolderError(f"--record {self.path}: {human_bytes(free)} free, the "
                                 f"recording needs about {human_bytes(need_bytes)} ({what})")

    def create(self, name: str) -> int:
        """A new file ``name`` in the folder, opened for writing; fails if anything (a
        symlink included) already has that name."""
        return os.open(name, _CREATE, 0o644, dir_fd=self.fd)

    def unlink(self, name: str) -> None:
        """Remove ``name`` from the folder if it is there (a symlink itself, not its
        target)."""
        try:
            os.unlink(name, dir_fd=self.fd)
        except FileNotFoundError:
            pass

    def write_json(self, name: str, data: dict) -> Path:
        """Write ``data`` as strict JSON (NaN and inf become null) to ``name``, complete or
        absent: a temporary file created afresh, then renamed over ``name`` (a symlink
        there is replaced, not followed)."""
        text = json.dumps(_finite(data), indent=1, allow_nan=False) + "\n"
        tmp = f"{name}.tmp"
        self.unlink(tmp)
        fd = self.create(tmp)
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.replace(tmp, name, src_dir_fd=self.fd, dst_dir_fd=self.fd)
        return self.path / name

    def close(self) -> None:
        """Give the reserve back and close the folder's descriptor (idempotent)."""
        self.release_reserve()
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1

    def __enter__(self) -> "RunFolder":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
