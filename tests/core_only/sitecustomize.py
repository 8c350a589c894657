"""Put this folder first on PYTHONPATH and name top-level modules in ``HIL_TESTS_WITHOUT``
(comma-separated): every process started so, its children too, sees them as not installed.
tests/test_extras.py uses it to run the core commands as a core-only install would (without
the optional extras of pyproject.toml) and the extras' commands as they fail there."""

import os
import sys
from importlib.abc import MetaPathFinder

_WITHOUT = frozenset(filter(None, os.environ.get("HIL_TESTS_WITHOUT", "").split(",")))


class _NotInstalled(MetaPathFinder):
    """Refuses the named modules and their submodules, as a missing package does."""

    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in _WITHOUT:
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None


if _WITHOUT:
    sys.meta_path.insert(0, _NotInstalled())
