"""The machine files of a recorded run, rebuilt from the recording's metadata.

``hil run`` puts the text of every machine file it loaded (a manifest first, then each
axis's file) into the recording's schema metadata (``machine_files``: path -> text), so a
run folder can be replayed where those files have changed or do not exist.  The files are
written into a temporary folder under their recorded paths -- a relative path below a
folder deep enough that its leading ``..`` stay inside, an absolute one below the folder's
root -- so a manifest's relative ``file = "../arrow500_x.toml"`` finds its axis file as it
did in the run.
"""

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path, PurePosixPath


class ReplayError(ValueError):
    """A run folder that cannot be replayed; the message names the file and why."""


def _place(root: Path, recorded: str, depth: int) -> Path:
    norm = os.path.normpath(recorded)
    if os.path.isabs(norm):
        return root / "abs" / PurePosixPath(norm).relative_to("/")
    return root.joinpath("rel", *["d"] * depth, norm)


@contextmanager
def machine_files(meta: dict, where: str) -> Iterator[Path]:
    """The run's machine file (or manifest) rebuilt in a temporary folder, for the ``with``
    block; ``meta`` is the recording's metadata, ``where`` names it in errors."""
    files, main = meta.get("machine_files"), meta.get("machine_file")
    if not isinstance(files, dict) or not files or not isinstance(main, str):
        raise ReplayError(f"{where}: the metadata has no machine_files/machine_file; not a "
                          f"recording of hil run")
    depth = max(len(Path(os.path.normpath(p)).parts) for p in files)  # covers every '..'
    with tempfile.TemporaryDirectory(prefix="hil-replay-") as tmp:
        root = Path(tmp)
        for recorded, text in files.items():
            path = _place(root, recorded, depth)
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text)
        first = _place(root, main, depth)
        if not first.exists():
            raise ReplayError(f"{where}: machine_file {main!r} is not among the machine_files "
                              f"recorded ({', '.join(files)})")
        yield first
