"""The install's optional extras (hil/extras.py, pyproject.toml): the core commands run
without them, a command that needs one says which to install.

A core-only install is imitated by tests/core_only/sitecustomize.py, which makes the extras'
modules missing in a process and its children (``CORE_ONLY_ENV``); ``hil demo``, the README's
main job, runs so in tests/test_loopback.py."""

import re
import subprocess
import sys
import tomllib
from importlib.metadata import packages_distributions

from hil.extras import EXTRA_OF_MODULE
from tests.conftest import CONFIGS, ROOT
from tests.runtime_helpers import CORE_ONLY_ENV, write_unchecked_recording

PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]


def _names(requirements: list[str]) -> set[str]:
    """The distributions ``requirements`` name, and the extras of theirs they ask for
    (``dask[distributed]`` -> dask, distributed), lower case."""
    names = set()
    for req in requirements:
        m = re.match(r"\s*([A-Za-z0-9_.-]+)(?:\[([^\]]*)\])?", req)
        names.add(m.group(1).lower())
        names.update(e.strip().lower() for e in (m.group(2) or "").split(",") if e.strip())
    return names


def _core_only(*argv: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "hil.cli", *argv], cwd=ROOT,
                          env=CORE_ONLY_ENV, capture_output=True, text=True, timeout=300)


def test_each_extra_module_is_installed_by_the_extra_named_for_it_and_not_by_the_core():
    """hil/extras.py against pyproject.toml: the extra it names for a module lists the
    distribution that installs the module (importlib.metadata's map of the environment),
    the core dependencies list none of them, and ``all`` and ``test`` bring every extra."""
    extras = PYPROJECT["optional-dependencies"]
    core = _names(PYPROJECT["dependencies"])
    installed_by = packages_distributions()
    for module, extra in EXTRA_OF_MODULE.items():
        dists = {d.lower() for d in installed_by[module]} | {module.lower()}
        assert dists & _names(extras[extra]), (module, extra, extras[extra])
        assert not dists & core, (module, "is a core dependency")
    assert _names(extras["all"]) >= {"feeddrive-hil", *EXTRA_OF_MODULE.values()}
    assert "feeddrive-hil" in _names(extras["test"]) and "all" in _names(extras["test"])


def test_the_core_commands_run_without_the_extras(tmp_path):
    """``hil --help`` and ``hil sim`` on the Arrow 500 X in a process where Dask, SALib,
    Optuna, uvloop, Bokeh and asammdf are missing (hil demo, with hil run, hil controller and
    hil report: tests/test_loopback.py)."""
    assert _core_only("--help").returncode == 0
    done = _core_only("sim", str(CONFIGS / "arrow500_x.toml"), "--program",
                      str(ROOT / "programs" / "demo_moves.nc"), "--out", str(tmp_path))
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "trace.csv").stat().st_size > 0


def test_a_command_that_needs_a_missing_extra_names_it(tmp_path):
    """hil study, hil bench study (Dask), hil export --to mdf4 (asammdf) and hil scope
    (Bokeh) in a core-only
    process end with exit status 2 and the pip command of their extra, not a traceback."""
    run = tmp_path / "run"
    run.mkdir()
    write_unchecked_recording(run)
    for argv, extra in (
            (["study", str(CONFIGS / "studies" / "ci_small.toml"), "--out",
              str(tmp_path / "study")], "study"),
            (["bench", "study", "--json"], "study"),
            (["export", str(run), "--to", "mdf4"], "mdf"),
            (["scope", str(run)], "scope")):
        done = _core_only(*argv)
        named = f"hil {argv[0]} {argv[1]}" if argv[0] == "bench" else f"hil {argv[0]}"
        assert done.returncode == 2, (argv, done.stderr)
        assert "Traceback" not in done.stderr, done.stderr
        assert (f"{named} needs the optional '{extra}' packages" in done.stderr
                and f"pip install 'feeddrive-hil[{extra}]'" in done.stderr), done.stderr
