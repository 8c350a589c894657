"""Write the identified machine file: the input file's text with the fitted keys changed
or added in place, each marked, every other line and comment kept.

TOML has no writer in the standard library, and a round trip through a writer would
lose the comments that cite where every value comes from; editing the text keeps them.
"""

import math
import re
from pathlib import Path

_SECTION = re.compile(r"^\s*\[([A-Za-z0-9_.]+)\]\s*(#.*)?$")
_KEY = re.compile(r"^(\s*)([A-Za-z0-9_]+)(\s*=\s*)")


def toml_value(value) -> str:
    """A Python value as a TOML literal (bool, int, float, str, list/tuple of those)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"cannot write {value} to a machine file")
        return repr(float(f"{value:.7g}"))
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {type(value).__name__} to a machine file")


def patch_config(text: str, changes: dict, note: str) -> str:
    """Apply ``{"section": {"key": value}}`` to a machine file's text.

    A key already in its section has its value replaced (the old value is kept in the
    comment); a missing key is added at the end of its section; a missing section is
    appended.  Every changed line ends with ``# <note>``.
    """
    lines = text.splitlines()
    pending = {sec: dict(values) for sec, values in changes.items()}
    out: list[str] = []
    section = None

    def flush(sec):
        for key, value in pending.pop(sec, {}).items():
            out.append(f"{key} = {toml_value(value)}  # {note}")

    for line in lines:
        m = _SECTION.match(line)
        if m:
            # keys still pending for the section that ends here go before its trailing blanks
            tail = []
            while out and not out[-1].strip():
                tail.append(out.pop())
            flush(section)
            out.extend(tail)
            section = m.group(1)
            out.append(line)
            continue
        k = _KEY.match(line)
        if k and section in pending and k.group(2) in pending[section]:
            value = pending[section].pop(k.group(2))
            old = line[k.end():].split("#", 1)[0].strip()
            out.append(f"{k.group(1)}{k.group(2)}{k.group(3)}{toml_value(value)}"
                       f"  # {note} (was {old})")
            continue
        out.append(line)
    flush(section)
    for sec in list(pending):
        out += ["", f"[{sec}]"]
        flush(sec)
    return "\n".join(out) + "\n"


def write_config(src: str | Path, dst: str | Path, changes: dict, note: str) -> None:
    """Write ``src`` with ``changes`` applied (see :func:`patch_config`) to ``dst``."""
    Path(dst).write_text(patch_config(Path(src).read_text(), changes, note))
