"""The folder tree's data-flow rule: plant imports nothing from hil or io_adapters, and
io_adapters nothing from plant or hil (style guide habit 11).  Checked on the source
with the ast module, so a lazy import inside a function is caught as well."""

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest
import tomllib

ROOT = Path(__file__).resolve().parent.parent
FORBIDDEN = {"plant": {"hil", "io_adapters"}, "io_adapters": {"plant", "hil"}}
PLANT_ALLOWED_THIRD_PARTY = {"numpy", "numba", "scipy"}


def imported_top_names(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_package_does_not_import_downstream(package):
    """No module of ``package`` imports a package that sits after it in the data flow."""
    files = sorted((ROOT / package).rglob("*.py"))
    assert files, f"{package}/ has no Python files"
    for f in files:
        bad = imported_top_names(f) & FORBIDDEN[package]
        assert not bad, f"{f.relative_to(ROOT)} imports {sorted(bad)}"


def test_plant_uses_only_numpy_numba_scipy():
    """plant/ depends on numpy, numba and scipy (linear algebra at build time) besides the
    standard library."""
    import sys

    stdlib = set(sys.stdlib_module_names)
    for f in sorted((ROOT / "plant").rglob("*.py")):
        third = imported_top_names(f) - stdlib - {"plant"}
        assert third <= PLANT_ALLOWED_THIRD_PARTY, f"{f.relative_to(ROOT)} imports {third}"


def test_the_kernel_guard_catches_a_violation(tmp_path):
    """The checker itself finds a forbidden import (so the tests above can fail)."""
    bad = tmp_path / "m.py"
    bad.write_text("def f():\n    from hil.cli import main\n")
    assert "hil" in imported_top_names(bad)


def _loaded(module: str, others: set[str]) -> list[str]:
    """Which of ``others`` importing ``module`` loads, in a fresh interpreter."""
    probe = (f"import json, sys, {module}; "
             f"print(json.dumps(sorted({sorted(others)!r} & sys.modules.keys())))")
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                          cwd=ROOT, timeout=120, check=True)
    return json.loads(done.stdout)


def test_the_controller_process_loads_no_plotting_or_analysis_stack():
    """``hil controller`` starts once per loopback run, and its start is on the test's and
    the user's clock: matplotlib and scipy.signal (``hil sim``'s figures and ``hil
    measure``'s analysis, about 0.8 s of imports) are no part of its work."""
    assert _loaded("hil.runtime.controller_proc", {"matplotlib", "scipy.signal"}) == []


def test_the_emulator_loads_no_can_stack():
    """``hil run`` over UDP or serial needs neither canopen nor python-can (and asammdf,
    pandas behind them: 0.65 s of a 1.1 s start); a ``can://`` URL loads them when the
    endpoint opens."""
    assert _loaded("hil.runtime.emulator", {"can", "canopen", "asammdf"}) == []


def test_hil_version_says_the_packages_version():
    """``hil --version`` prints the version pyproject.toml declares, exit status 0."""
    done = subprocess.run([sys.executable, "-m", "hil.cli", "--version"], capture_output=True,
                          text=True, cwd=ROOT, timeout=120, check=True)
    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    assert done.stdout.strip() == f"hil {declared}"


def test_the_command_line_imports_only_the_command_it_runs():
    """``hil --help`` lists every command without importing their modules (the CAN stack,
    asammdf, Dask, matplotlib: 2.8 s of a start before) or the plant (numba, scipy: 0.4
    s); a named command gets its options from its own module, every one of them."""
    probe = ("import json, sys; from hil.cli import build_parser; "
             "p = build_parser(['--help']); "
             "cmds = p._subparsers._group_actions[0].choices; "
             "print(json.dumps([sorted(cmds), sorted({'can', 'canopen', 'asammdf', "
             "'distributed', 'matplotlib', 'numba', 'scipy', 'pyarrow', 'plant'} "
             "& sys.modules.keys())]))")
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                          cwd=ROOT, timeout=120, check=True)
    commands, loaded = json.loads(done.stdout)
    assert loaded == []
    from hil.cli import build_parser
    benches = ("fuzz", "tick", "can", "identify", "study", "controller", "linuxcnc")
    for argv in [[c] for c in commands if c != "bench"] + [["bench", b] for b in benches]:
        parser = build_parser(argv)
        chosen = parser._subparsers._group_actions[0].choices[argv[0]]
        if argv[0] == "bench":
            chosen = chosen._subparsers._group_actions[0].choices[argv[1]]
        assert "func" in chosen._defaults, argv


def test_hil_runs_help_names_every_adapter_scheme_with_its_options():
    """``hil run --help``: udp://, serial:// and can:// each with the options a first run
    needs (the wire, the node-ID and rated current)."""
    from hil.cli import build_parser
    parser = build_parser(["run"])
    run = parser._subparsers._group_actions[0].choices["run"]
    text = next(a.help for a in run._actions if "--adapter" in a.option_strings)
    for scheme in ("udp://HOST:PORT", "serial://PATH", "can://INTERFACE/CHANNEL"):
        assert scheme in text, scheme
    assert "wire=msgpack|fixed" in text and "node=N&rated_current_ma=MA" in text


def test_every_command_ends_its_help_with_an_example_that_parses():
    """Each command's and benchmark's ``--help`` ends with one example command line, as
    written (not wrapped), and the example parses with the options its own module adds;
    ``hil validate --only`` lists the experiments it takes and refuses another name."""
    import shlex

    from hil.cli import BENCH_EXAMPLES, EXAMPLES, build_parser
    for example in [*EXAMPLES.values(), *BENCH_EXAMPLES.values()]:
        argv = shlex.split(example)
        assert argv[0] == "hil", argv
        parser = build_parser(argv[1:])
        args = parser.parse_args(argv[1:])
        assert callable(args.func), argv
        chosen = parser._subparsers._group_actions[0].choices[argv[1]]
        if argv[1] == "bench":
            chosen = chosen._subparsers._group_actions[0].choices[argv[2]]
        assert chosen.format_help().rstrip().endswith("example:\n  " + example), argv
    validate = build_parser(["validate"])._subparsers._group_actions[0].choices["validate"]
    assert "coulomb_hold" in validate.format_help()
    with pytest.raises(SystemExit):
        build_parser(["validate"]).parse_args(["validate", "--only", "no_such_experiment"])


def _has_default(default) -> bool:
    """Whether an option's default is one its help must state: not None, False or an
    empty list (0 and 0.0 count)."""
    if default is None or default is False:
        return False
    return not (isinstance(default, (list, tuple)) and not default)


def _as_written(default) -> tuple[str, ...]:
    """How a help text may write a default: as str() does, a number as :g does (30 for
    30.0), a path in the repository relative to its root."""
    if isinstance(default, (str, Path)) and Path(default).is_relative_to(ROOT):
        return (str(Path(default).relative_to(ROOT)),)
    if isinstance(default, (int, float)):
        return str(default), f"{default:g}"
    return (str(default),)


def _defaults_unstated() -> list[str]:
    """Every command's and benchmark's optional argument without a help text, or whose
    default (not None or False; not a flag) its help does not state, as 'hil CMD --OPT'."""
    import argparse

    from hil.cli import BENCH_EXAMPLES, EXAMPLES, build_parser
    flags = (argparse._StoreTrueAction, argparse._StoreFalseAction, argparse._HelpAction,
             argparse._VersionAction, argparse._StoreConstAction, argparse._CountAction)
    argvs = [[c] for c in EXAMPLES if c != "bench"] + [["bench", b] for b in BENCH_EXAMPLES]
    offenders = []
    for argv in argvs:
        chosen = build_parser(argv)._subparsers._group_actions[0].choices[argv[0]]
        if argv[0] == "bench":
            chosen = chosen._subparsers._group_actions[0].choices[argv[1]]
        for action in chosen._actions:
            if not action.option_strings:
                continue
            name = f"hil {' '.join(argv)} {action.option_strings[-1]}"
            text, default = action.help or "", action.default
            if not text or text == argparse.SUPPRESS:
                offenders.append(f"{name}: no help")
            elif (not isinstance(action, flags) and _has_default(default)
                  and "%(default)" not in text
                  and not any(w in text for w in _as_written(default))):
                offenders.append(f"{name}: default {default!r} not stated ({text!r})")
    return offenders


def test_every_option_has_a_help_that_states_its_default():
    """Each optional argument of every command and benchmark says what it means, and one
    with a default (not None or False, not a flag) says the default, as %(default)s or
    the value itself."""
    offenders = _defaults_unstated()
    assert offenders == [], "\n".join(offenders)
