"""Shared test fixtures: paths of the repository, its configs and the shared data."""

import os
import secrets
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = ROOT / "configs"
SHARED = ROOT.parent / "shared"
#: a session of at least this many tests fills numba's cache from a second process
WARM_KERNELS_FROM = 200
_WARMER = pytest.StashKey[subprocess.Popen]()


def pytest_collection_finish(session):
    """A whole suite's session starts ``tests/warm_kernels.py`` beside it (at nice 10: it
    takes the core the suite leaves idle); the process exits at once where the cache is
    warm already, and is stopped with the session.  Its output goes to
    ``<tmp>/feeddrive-warm-kernels.log``.  ``HIL_TESTS_NO_WARMER=1`` leaves it out (to
    time the suite without it)."""
    if (len(session.items) < WARM_KERNELS_FROM or session.config.option.collectonly
            or os.environ.get("HIL_TESTS_NO_WARMER") == "1"):
        return
    log = open(Path(tempfile.gettempdir()) / "feeddrive-warm-kernels.log", "w")  # noqa: SIM115
    session.config.stash[_WARMER] = subprocess.Popen(
        [sys.executable, "-m", "tests.warm_kernels"], cwd=ROOT, stdout=log,
        stderr=subprocess.STDOUT, preexec_fn=lambda: os.nice(10))
    log.close()


def pytest_sessionfinish(session):
    warmer = session.config.stash.get(_WARMER, None)
    if warmer is not None and warmer.poll() is None:
        warmer.terminate()
        warmer.wait(timeout=10)



@pytest.fixture(scope="session")
def configs_dir() -> Path:
    return CONFIGS


@pytest.fixture(scope="session")
def experiment_rows():
    """``hil validate``'s experiment by its registry name -> its rows (``run_all`` with that
    one only, no plots), each experiment run once per session: the physics tests check its
    verification rows and tests/test_validate_rows.py every row's kind, seed passage and
    verdict, on the same (frozen) rows."""
    from hil.validate.core import run_all

    done: dict[str, list] = {}

    def rows(name: str) -> list:
        if name not in done:
            done[name] = run_all(None, [name])
        return done[name]
    return rows


@pytest.fixture
def multicast_group():
    """A multicast group of its own, routed over lo for the test: (group, port)."""
    if shutil.which("ip") is None:
        pytest.skip("no `ip` command to route the multicast group over lo")
    group = f"239.255.{secrets.randbelow(256)}.{1 + secrets.randbelow(254)}"
    added = subprocess.run(["ip", "route", "add", f"{group}/32", "dev", "lo"],
                           check=False, capture_output=True, text=True)
    if added.returncode != 0:
        pytest.skip(f"cannot route {group} over lo: {added.stderr.strip()}")
    try:
        route = subprocess.run(["ip", "route", "get", group], capture_output=True,
                               text=True, check=True).stdout
        assert " dev lo " in route, route
        yield group, 40000 + secrets.randbelow(20000)
    finally:
        subprocess.run(["ip", "route", "del", f"{group}/32", "dev", "lo"], check=True)
