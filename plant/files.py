"""Files a person names: read whole, never blocked on, refused in one line when wrong.

Every loader of a file given on the command line (machine files and manifests, study
files, part programs, servo traces, EMPS records, a run's report) reads it through
:func:`read_bytes` or :func:`read_text`; a reader of its own (a run's recording) calls
:func:`refuse_special` before it opens the file.  The path is checked with ``os.stat``
before it is opened, so a directory, a FIFO, a socket or a device is refused unread (a
FIFO nobody writes blocks a read forever, ``/dev/zero`` never ends, and opening some
devices acts on them); it is then opened non-blocking and checked again with ``fstat``
(the path may have changed in between), and a regular file larger than the loader's bound
is refused before a byte is read.  Text is UTF-8; a byte that is not is named with its
line and offset.

Every refusal is one line that starts with the path and says why, raised as the caller's
own error class (``error``: any callable taking the message), so each loader keeps the
error its callers already catch: :class:`~plant.errors.ConfigError` by default.
"""

import os
import stat
from collections.abc import Callable
from pathlib import Path

from plant.errors import ConfigError

ErrorFactory = Callable[[str], Exception]
"""Builds the loader's exception from a one-line message that names the file."""

_KINDS = ((stat.S_ISFIFO, "a FIFO"), (stat.S_ISSOCK, "a socket"),
          (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"))


def _refuse_non_regular(path: Path, mode: int, what: str, error: ErrorFactory) -> None:
    if stat.S_ISREG(mode):
        return
    if stat.S_ISDIR(mode):
        raise error(f"{path}: is a directory, not a {what}")
    kind = next((name for test, name in _KINDS if test(mode)), "not a regular file")
    raise error(f"{path}: not a regular file ({kind}); a {what} is read from a regular "
                "file, never from a pipe or a device")


def shown_path(path: str | Path) -> str:
    """A file name as a message shows it: as written, or as a Python string literal when
    it holds a character that is not printable (a newline would break the one line)."""
    text = str(path)
    return text if text.isprintable() else repr(text)


def checked_name(path: str | Path, what: str, error: ErrorFactory = ConfigError) -> Path:
    """``path`` as a Path, refused (``error``) when its name holds a character that is not
    printable: a name read from another file may hold a newline, which would break a
    message's one line, or a NUL, which no system call takes.  Call it before
    ``Path.resolve``, which raises ValueError on a NUL."""
    if not str(path).isprintable():
        raise error(f"{shown_path(path)}: a {what}'s name with a character that is not "
                    "printable (a newline, a control character) is refused")
    return Path(path)


def refuse_special(path: str | Path, what: str, error: ErrorFactory = ConfigError) -> None:
    """Refuse (``error``) a ``path`` that exists and is not a regular file, before a reader
    of its own (pyarrow's, for a recording too large to read whole) opens it; a missing
    path is left to that reader."""
    path = checked_name(path, what, error)
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return
    except OSError as exc:
        raise error(f"{path}: cannot look at the {what}: {exc.strerror or exc}") from exc
    _refuse_non_regular(path, mode, what, error)


def read_bytes(path: str | Path, what: str, max_bytes: int,
               error: ErrorFactory = ConfigError) -> bytes:
    """The whole content of the regular file ``path``, at most ``max_bytes`` bytes.

    ``what`` names the file's role in the messages ("machine file", "part program").
    Raises ``error(message)``: the name holds a character that is not printable (a name
    read from another file may), the file is missing or cannot be opened, is not a
    regular file (checked before it is opened and again on the open descriptor), or is
    larger than ``max_bytes``."""
    path = checked_name(path, what, error)
    try:
        _refuse_non_regular(path, os.stat(path).st_mode, what, error)
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC)
    except FileNotFoundError as exc:
        raise error(f"{path}: no such {what}") from exc
    except OSError as exc:
        raise error(f"{path}: cannot open the {what}: {exc.strerror or exc}") from exc
    try:
        st = os.fstat(fd)
        _refuse_non_regular(path, st.st_mode, what, error)
        if st.st_size > max_bytes:
            raise error(f"{path}: {st.st_size} bytes, more than a {what} can be "
                        f"({max_bytes} bytes)")
        chunks, size = [], 0
        while size <= max_bytes:  # a read may return less than asked
            chunk = os.read(fd, max_bytes + 1 - size)
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
    except OSError as exc:
        raise error(f"{path}: cannot read the {what}: {exc.strerror or exc}") from exc
    finally:
        os.close(fd)
    if size > max_bytes:  # it grew after the fstat
        raise error(f"{path}: more than a {what} can be ({max_bytes} bytes)")
    return b"".join(chunks)


def read_text(path: str | Path, what: str, max_bytes: int,
              error: ErrorFactory = ConfigError) -> str:
    """The UTF-8 text of the regular file ``path`` (:func:`read_bytes`); a leading byte
    order mark is dropped.  A byte sequence that is not UTF-8 raises ``error`` naming the
    first bad byte, its line and its offset in the file."""
    data = read_bytes(path, what, max_bytes, error)
    try:
        return data.decode("utf-8").removeprefix("\ufeff")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise error(f"{path}: not UTF-8 text (byte 0x{data[exc.start]:02x} at line {line}, "
                    f"offset {exc.start}); a {what} is UTF-8 text") from exc
