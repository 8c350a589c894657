"""Shared test fixtures: paths of the repository, its configs and the shared data."""

import os
import secrets
import shutil
import subprocess
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from multiprocessing import get_context
from pathlib import Path
from unittest import mock

import pytest

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = ROOT / "configs"
SHARED = ROOT.parent / "shared"


@contextmanager
def spawned_pool(workers: int):
    """A process pool of ``workers`` spawned processes whose BLAS (numpy's and scipy's
    OpenBLAS) runs on one thread.  Each process replays records in compiled loops between
    BLAS calls on long vectors (the refinement's sum of squares over an EMPS record's
    50 000 residuals), after which OpenBLAS's second thread spins for a while: on the
    2-vCPU VM the processes' spinning threads took the cores the others' replays needed
    (test_identify_cli's EMPS fixture 43 s, its two runs 32 and 49 s of CPU; 29 s and 16
    and 27 s on one thread each)."""
    with mock.patch.dict(os.environ, {"OPENBLAS_NUM_THREADS": "1"}), \
            ProcessPoolExecutor(workers, mp_context=get_context("spawn")) as pool:
        yield pool


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


#: every test's setup, call and teardown time, s, written at the session's end: where the
#: suite's minutes go (pytest prints only the slowest 30); out/ is ignored by git
DURATIONS_JSON = ROOT / "out" / "test_durations.json"
_durations: list[dict] = []


def pytest_runtest_logreport(report):
    _durations.append({"test": report.nodeid, "phase": report.when,
                       "s": round(report.duration, 3), "outcome": report.outcome})


def pytest_sessionfinish(session):
    if not _durations:
        return
    import json

    DURATIONS_JSON.parent.mkdir(exist_ok=True)
    DURATIONS_JSON.write_text(json.dumps(
        {"total_s": round(sum(d["s"] for d in _durations), 1), "phases": _durations}))
