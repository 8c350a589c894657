"""Loaders that never crash or hang (issue 27, item 4).

Every file a person names -- a machine file, a part program, a servo trace, a study
file -- is either read or refused with the loader's own error in one line naming the
file; never a traceback, never a read that blocks:

* the reader (:mod:`plant.files`) refuses a directory, a FIFO, a socket and a device
  before any read, a file above the loader's size bound unread, and bytes that are not
  UTF-8 with their line and offset;
* TOML nested deeper than :data:`plant.config.MAX_NESTING` is refused before tomllib's
  recursion can exhaust the stack (brackets counted outside strings and comments) and
  after parsing (dotted keys);
* part programs: a number of more than nine digits before the point, and a block that
  would end more than :data:`~hil.controller.interpolator.MAX_PROGRAM_S` into the program
  (a feed of 1e-6 mm/min, a dwell of years), each naming the line, the word and the
  unit;
* servo traces for ``hil identify``: a NaN, an infinity or a value beyond
  :data:`~hil.trace_file.MAX_VALUE` named with its line and column, a single row refused
  before any fit;
* a study whose experiment stands the axis beyond its travel is refused before it starts
  (exit 2), and a study whose every sample failed ends with exit 2 and one line;
* a hypothesis fuzz test per loader (structured-but-wrong text and random bytes): each
  case ends in success or the loader's one refusal error within its deadline; and the
  cases the attacker found, from the command line: exit 2, one line on stderr, no
  traceback.
"""

import os
import socket
import subprocess
import sys
from datetime import timedelta
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
import tomllib
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hil.controller.config import AxisLimits
from hil.controller.interpolator import MAX_PROGRAM_S, plan
from hil.controller.path import parse_path_program, plan_path
from hil.controller.program import MAX_NUMBER, ProgramError, parse_program, read_program
from hil.identify.record import load_record
from hil.study.keys import StudySpecError
from hil.study.spec import load_study
from hil.trace_file import MAX_VALUE, TraceFormatError
from plant.config import MAX_NESTING, load_machine, read_toml
from plant.errors import ConfigError
from plant.files import read_bytes, read_text
from plant.machines import load_machine_set
from tests.conftest import CONFIGS, ROOT

ARROW = CONFIGS / "arrow500_x.toml"
ARROW_TEXT = ARROW.read_text()
#: a manifest of two axes, its axis files named by absolute path
MANIFEST_TEXT = (CONFIGS / "machines" / "arrow500_xy.toml").read_text().replace(
    '"../arrow500_x.toml"', f'"{ARROW}"')
CI_STUDY = CONFIGS / "studies" / "ci_small.toml"
#: the study file with its machine named by absolute path, so that it loads from anywhere
STUDY_TEXT = CI_STUDY.read_text().replace('"../arrow500_x.toml"', f'"{ARROW}"')
#: the Arrow 500 X's interpolator limits, about (m/s, m/s^2, m/s^3)
LIMITS = AxisLimits(0.5, 2.0, 50.0)
#: hypothesis: each case within its deadline (a hang or a blow-up, not a slow machine: the
#: loaders take milliseconds), no example database in the repository
FUZZ = settings(max_examples=200, deadline=timedelta(seconds=10), database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                       HealthCheck.function_scoped_fixture])


def one_line(message: str, path: Path | str) -> str:
    """``message`` after checking it is one line that starts with ``path``."""
    assert "\n" not in message and message.startswith(str(path)), message
    return message


# --- the reader ------------------------------------------------------------------------------

def _directory(path: Path) -> Path:
    path.mkdir()
    return path


def _fifo(path: Path) -> Path:
    os.mkfifo(path)  # nobody writes it: a read would block forever
    return path


def _socket(path: Path) -> Path:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.bind(str(path))
    sock.close()
    return path


NON_REGULAR = {
    "a directory": (_directory, "is a directory, not a part program"),
    "a FIFO": (_fifo, "not a regular file (a FIFO)"),
    "a socket": (_socket, "not a regular file (a socket)"),
    "a character device": (lambda path: Path("/dev/zero"),
                           "not a regular file (a character device)"),
}


@pytest.mark.parametrize("make, fragment", NON_REGULAR.values(), ids=NON_REGULAR.keys())
def test_a_file_that_is_not_regular_is_refused_before_any_read(tmp_path, make, fragment):
    """A directory, a FIFO nobody writes, a socket, /dev/zero (a read never ends): each
    refused in one line naming the path and what it is, by stat, before a byte is read."""
    path = make(tmp_path / "p.nc")
    with pytest.raises(ConfigError) as err:
        read_text(path, "part program", 1000)
    assert fragment in one_line(str(err.value), path)


def test_a_file_larger_than_its_bound_is_refused_unread(tmp_path):
    """A file of bound + 1 bytes is refused naming both sizes; one of the bound is read."""
    path = tmp_path / "big.toml"
    path.write_bytes(b"#" * 101)
    with pytest.raises(ConfigError) as err:
        read_bytes(path, "machine file", 100)
    assert "101 bytes, more than a machine file can be (100 bytes)" in one_line(
        str(err.value), path)
    path.write_bytes(b"#" * 100)
    assert read_bytes(path, "machine file", 100) == b"#" * 100


def test_bytes_that_are_not_utf8_are_named_with_line_and_offset(tmp_path):
    """The first byte that is not UTF-8: its value, its line and its offset; the loader's
    own error class carries the message; a byte order mark is dropped."""
    path = tmp_path / "t.csv"
    path.write_bytes(b"t_s\n0.0\n\xff1.0\n")
    with pytest.raises(TraceFormatError) as err:
        read_text(path, "servo trace", 1000, TraceFormatError)
    assert "not UTF-8 text (byte 0xff at line 3, offset 8)" in one_line(str(err.value), path)
    path.write_bytes(b"\xef\xbb\xbft_s\n")
    assert read_text(path, "servo trace", 1000) == "t_s\n"


# --- TOML nesting ----------------------------------------------------------------------------

def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


DEEP = {
    "arrays 500 deep": "[a]\nx = " + "[" * 500 + "]" * 500 + "\n",
    "inline tables 500 deep": "x = " + "{a = " * 500 + "1" + "}" * 500 + "\n",
    "a dotted key 5000 parts long": "[machine]\nname." + ".".join(["a"] * 5000) + " = 1\n",
    "a table header 5000 parts long": "[" + ".".join(["a"] * 5000) + "]\nx = 1\n",
    "arrays after a string ending in quotes": 'x = ["""a"""", ' + "[" * 500 + "]" * 501 + "\n",
}


@pytest.mark.parametrize("text", DEEP.values(), ids=DEEP.keys())
def test_toml_nested_beyond_the_bound_is_refused_not_recursed(tmp_path, text):
    """Nesting that made tomllib (or a repr of the result) raise RecursionError: refused
    in one line naming the bound, whichever way the nesting is written (a multi-line
    string may end in two more quotes: the bracket count knows where it ends)."""
    path = _write(tmp_path / "deep.toml", text)
    with pytest.raises(ConfigError) as err:
        load_machine(path)
    assert f"nested more than {MAX_NESTING} deep" in one_line(str(err.value), path)


def test_nesting_up_to_the_bound_parses_and_brackets_in_strings_do_not_count(tmp_path):
    """Reference: tomllib on the same text.  Arrays and dotted keys exactly MAX_NESTING
    deep read as tomllib reads them, one more is refused; brackets inside strings of
    every kind and in comments are not nesting."""
    arrays = "x = " + "[" * MAX_NESTING + "]" * MAX_NESTING + "\n"
    dotted = ".".join(["a"] * (MAX_NESTING + 1)) + " = 1\n"
    quoted = ('s = "' + "[" * 100 + '"\nl = \'' + "{" * 100 + "'\nm = \"\"\"" + "[" * 100
              + '\\""""\nn = \'\'\'' + "[" * 100 + "''''\n# " + "[" * 100 + "\n")
    for text in (arrays, dotted, quoted):
        assert read_toml(_write(tmp_path / "ok.toml", text)) == tomllib.loads(text)
    for text in ("x = " + "[" * (MAX_NESTING + 1) + "]" * (MAX_NESTING + 1) + "\n",
                 ".".join(["a"] * (MAX_NESTING + 2)) + " = 1\n"):
        with pytest.raises(ConfigError, match="nested more than"):
            read_toml(_write(tmp_path / "deep.toml", text))


# --- part programs ---------------------------------------------------------------------------

def test_a_feed_that_would_take_years_is_refused_naming_block_word_and_unit():
    """G1 X10 F0.000001: 10 mm at 1e-6 mm/min is 6e8 s (the 1.09 TiB the issue found);
    refused by the planner naming the line, the F word and mm/min, and the bound.
    Reference: 10 mm / (1e-6 mm/min) = 1e7 min.  The same move at F1 (600 s) plans."""
    prog = parse_program("G90 G71\nG1 X10 F0.000001\nM30\n", source="slow.nc")
    with pytest.raises(ProgramError) as err:
        plan(prog, LIMITS)
    message = str(err.value)
    assert message.startswith("slow.nc line 2: ") and "\n" not in message
    assert "'F1e-06' (mm/min)" in message and "move of 10 mm" in message
    assert "6e+08 s" in message and f"at most {MAX_PROGRAM_S:g} s" in message
    assert plan(parse_program("G1 X10 F1\n"), LIMITS).duration_s == pytest.approx(600.0,
                                                                                  abs=1.0)


def test_a_dwell_or_a_path_move_beyond_the_bound_is_refused_too():
    """G4 F1e8 (seconds) and a two-axis move at 1e-6 mm/min along the path: the same
    refusal, from the single-axis and the path planner."""
    with pytest.raises(ProgramError, match=r"line 1: the dwell 'G4 F1e\+08'"):
        plan(parse_program("G4 F100000000\n"), LIMITS)
    path = parse_path_program("G1 X3 Y4 F0.000001\n", ("X", "Y"), source="xy.nc")
    with pytest.raises(ProgramError, match=r"xy.nc line 1: the move of 5 mm at 'F1e-06'"):
        plan_path(path, (LIMITS, LIMITS))


def test_a_number_of_more_than_nine_digits_before_the_point_is_refused():
    """X with 401 digits (OverflowError before: the float is infinite) and X1e9 written out
    are refused naming the line and the word cut short; 999999999.9 reads."""
    for digits in ("9" * 401, "1000000000"):
        with pytest.raises(ProgramError) as err:
            parse_program(f"G0 X{digits}\n", source="p.nc")
        assert one_line(str(err.value), "p.nc line 1: number in word 'X")
        assert "at most nine digits before the decimal point" in str(err.value)
        assert len(str(err.value)) < 300
    assert parse_program("G0 X999999999.9\n").end == pytest.approx(999999999.9e-3)
    assert MAX_NUMBER == 1e9


@pytest.mark.parametrize("make, fragment", [
    (lambda p: p.write_bytes(b"G0 X1\n\xff\xfe\n") and p, "not UTF-8 text (byte 0xff at line 2"),
    (_directory, "is a directory, not a part program"),
    (_fifo, "not a regular file (a FIFO)"),
], ids=["not UTF-8", "a directory", "a FIFO"])
def test_a_program_file_that_cannot_be_text_is_a_program_error(tmp_path, make, fragment):
    """The program readers raise ProgramError (what every caller catches), one line naming
    the file."""
    path = tmp_path / "p.nc"
    make(path)
    with pytest.raises(ProgramError) as err:
        read_program(path)
    assert fragment in one_line(str(err.value), path)


# --- fuzz ------------------------------------------------------------------------------------

NASTY = ["nan", "inf", "-inf", "1e309", "1e300", "-1e300", "-1", "0", "1", '"text"',
         "[1, 2]", "[]", "{a = 1}", "{}", "true", "1979-05-27", "'''x'''", '"\\u0000"',
         "[" * 40 + "]" * 40, "{a = " * 30 + "1" + "}" * 30, '"a\\nb"', "0x10", "+inf"]


def _mutated(draw, lines: list[str]) -> str:
    """``lines`` with one to four mutations: a value replaced by a nasty one, a line
    dropped, doubled or replaced by random text, a key with a newline in its name."""
    lines = list(lines)
    for _ in range(draw(st.integers(1, 4))):
        i = draw(st.integers(0, len(lines) - 1))
        how = draw(st.sampled_from(["value"] * 6 + ["drop", "double", "text", "key"]))
        if how == "value" and " = " in lines[i]:
            lines[i] = lines[i].split(" = ")[0] + " = " + draw(st.sampled_from(NASTY))
        elif how == "drop":
            del lines[i]
        elif how == "double":
            lines.insert(i, lines[i])
        elif how == "text":
            lines[i] = draw(st.text(max_size=40))
        else:
            lines.insert(i, '"a\\nb" = ' + draw(st.sampled_from(NASTY)))
        if not lines:
            lines = [""]
    return "\n".join(lines) + "\n"


@st.composite
def toml_files(draw, *texts: str) -> bytes:
    """One of ``texts`` (machine files, manifests, study files) mutated, random text, or
    random bytes."""
    kind = draw(st.sampled_from(["mutated", "mutated", "text", "bytes"]))
    if kind == "mutated":
        return _mutated(draw, draw(st.sampled_from(texts)).splitlines()).encode()
    if kind == "text":
        return draw(st.text(max_size=400)).encode("utf-8", "surrogatepass")
    return draw(st.binary(max_size=400))


@FUZZ
@given(data=toml_files(ARROW_TEXT, MANIFEST_TEXT))
def test_fuzz_machine_file(tmp_path, data):
    """Any machine file or manifest: loaded, or a ConfigError of one line naming the
    file."""
    path = tmp_path / "fuzz.toml"
    path.write_bytes(data)
    try:
        load_machine_set(path)
    except ConfigError as exc:
        one_line(str(exc), path)


@FUZZ
@given(data=toml_files(STUDY_TEXT))
def test_fuzz_study_file(tmp_path, data):
    """Any study file: loaded, or a StudySpecError of one line naming the file."""
    path = tmp_path / "fuzz_study.toml"
    path.write_bytes(data)
    try:
        load_study(path)
    except StudySpecError as exc:
        one_line(str(exc), path)


NUMBERS = st.one_of(st.integers(-10**12, 10**12).map(str),
                    st.floats(allow_nan=False, allow_infinity=False).map(lambda x: f"{x:f}"),
                    st.integers(0, 500).map(lambda n: "9" * n),
                    st.integers(0, 60).map(lambda n: "0." + "0" * n + "1"),
                    st.sampled_from(["", ".", "-", "1e5", "nan", "inf", "+.5", "--1"]))
WORDS = st.one_of(st.builds(lambda letter, n: letter + n,
                            st.sampled_from(list("GXYFMNAZC")), NUMBERS),
                  st.sampled_from(["G0", "G1", "G4", "G90", "G91", "G70", "M10", "M11", "M30",
                                   "(comment", ")", "; comment", "(ok)"]),
                  st.text(max_size=8))


@st.composite
def programs(draw) -> str:
    """Lines of G-code words, plausible and not."""
    lines = draw(st.lists(st.lists(WORDS, max_size=5), max_size=8))
    return "\n".join(" ".join(words) for words in lines)


@FUZZ
@given(text=programs())
def test_fuzz_part_program(text):
    """Any part program, single-axis and on two axes: parsed and planned and sampled at a
    4 ms IPO cycle (the allocation the tiny feed blew up), or a ProgramError naming the
    source and the line."""
    try:
        plan(parse_program(text, source="fuzz.nc"), LIMITS).ipo_points(0.004)
    except ProgramError as exc:
        one_line(str(exc), "fuzz.nc line ")
    try:
        for profile in plan_path(parse_path_program(text, ("X", "Y"), source="fuzz.nc"),
                                 (LIMITS, LIMITS)):
            profile.ipo_points(0.004)
    except ProgramError as exc:
        one_line(str(exc), "fuzz.nc line ")


@FUZZ
@given(data=st.binary(max_size=400))
def test_fuzz_part_program_bytes(tmp_path, data):
    """Any bytes as a program file: parsed, or a ProgramError naming the file."""
    path = tmp_path / "fuzz.nc"
    path.write_bytes(data)
    try:
        read_program(path)
    except ProgramError as exc:
        one_line(str(exc), path)


VALUES = st.one_of(st.floats(width=64), st.sampled_from(["nan", "inf", "-inf", "1e309",
                                                         "", "x", "1,2", " 1"]).map(str))
COLUMNS = ["t_s", "pos_set_mm", "pos_mm", "iq_a"]


@st.composite
def traces(draw) -> bytes:
    """A servo trace with the identification columns and rows of any values (time
    regular or not), or random text, or random bytes."""
    kind = draw(st.sampled_from(["rows", "rows", "text", "bytes"]))
    if kind == "bytes":
        return draw(st.binary(max_size=400))
    if kind == "text":
        return draw(st.text(max_size=400)).encode("utf-8", "surrogatepass")
    n = draw(st.integers(0, 6))
    dt = draw(st.sampled_from(["0.001", "0", "-1", "nan", "x"]))
    lines = [f"# sample_time_s: {dt}"] if draw(st.booleans()) else []
    lines.append(",".join(draw(st.permutations(COLUMNS))))
    regular = draw(st.booleans())
    for k in range(n):
        row = [f"{k * 0.001!r}" if regular else str(draw(VALUES))]
        row += [str(draw(VALUES)) for _ in COLUMNS[1:]]
        lines.append(",".join(row))
    return ("\n".join(lines) + "\n").encode()


@FUZZ
@given(data=traces())
def test_fuzz_identify_trace(tmp_path, data):
    """Any servo trace for ``hil identify``: a record of finite, bounded values and two
    samples at least, or a TraceFormatError of one line naming the file."""
    path = tmp_path / "fuzz.csv"
    path.write_bytes(data)
    try:
        rec = load_record(path)
    except TraceFormatError as exc:
        one_line(str(exc), path)
        return
    for values in (rec.pos_set, rec.pos, rec.effort):
        assert np.all(np.abs(values) < MAX_VALUE) and rec.n >= 2


# --- studies ---------------------------------------------------------------------------------

def test_a_step_beyond_the_travel_is_refused_before_the_study_starts(tmp_path):
    """at_mm = 5000 on the Arrow 500 X (travel 510 mm): refused naming the key, the value,
    the machine file and its travel in mm and m, before any sample runs (every one failed
    before); a step whose target leaves the travel likewise; one at 250 mm loads."""
    path = _write(tmp_path / "far.toml", STUDY_TEXT.replace("at_mm = 250.0", "at_mm = 5000.0"))
    with pytest.raises(StudySpecError) as err:
        load_study(path)
    assert ("[experiment] at_mm = 5000 mm lies outside the travel of "
            f"{ARROW}, 0 .. 510 mm ([table] travel_m = 0.51 m)") in one_line(str(err.value), path)
    path = _write(tmp_path / "edge.toml", STUDY_TEXT.replace("at_mm = 250.0", "at_mm = 509.8"))
    with pytest.raises(StudySpecError, match=r"at_mm \+ amplitude_mm = 510.3 mm lies outside"):
        load_study(path)
    assert load_study(_write(tmp_path / "ok.toml", STUDY_TEXT)).experiments[0].opts.at_mm == 250.0


def test_a_travel_varied_below_the_step_is_refused_at_its_end_of_range(tmp_path):
    """[vary.table] travel_m reaching down to 0.2 m leaves the step at 250 mm outside the
    travel of that machine: refused naming the parameter and its value."""
    path = _write(tmp_path / "short.toml",
                  STUDY_TEXT + "\n[vary.table.travel_m]\nuniform = [0.2, 0.5]\n")
    with pytest.raises(StudySpecError) as err:
        load_study(path)
    message = one_line(str(err.value), path)
    assert "at_mm = 250 mm lies outside the travel" in message
    assert "parameter 'table.travel_m' = 0.2 m, an end of its range" in message


def _all_failed(tmp_path: Path) -> tuple[Path, Path]:
    """A study of four samples whose stored results all failed (as at_mm = 5000 left them
    before the check); its study file and results folder."""
    from hil.study.store import ResultStore

    spec = _write(tmp_path / "s.toml", STUDY_TEXT.replace("samples = 16", "samples = 4"))
    study = load_study(spec)
    store = ResultStore(tmp_path / "out", study, fresh=True)
    n, columns = 4, {}
    for name in store.schema.names:
        columns[name] = ([float("nan")] * n if name in study.outputs else
                         [None] * n if name.startswith("curve_") else [1.0] * n)
    columns.update(sample_id=list(range(n)), worker=["w"] * n, started_utc=[0] * n,
                   finished_utc=[0] * n,
                   status=["RuntimeError: not enabled after 1000 ticks:\nfault 7500h"] * n)
    store.write(pa.table(columns, schema=store.schema))
    return spec, tmp_path / "out"


def test_a_study_whose_every_sample_failed_ends_with_exit_2_and_one_line(tmp_path):
    """The report of a study in which no sample ran (the curve bands broadcast an empty
    array before): written, and ``hil study`` exits 2 with one line giving the count and
    the first reason (its newline folded)."""
    spec, out = _all_failed(tmp_path)
    done = hil("study", spec, "--out", out, "--report-only")
    refused_in_one_line(done, "hil study: every one of the 4 samples failed, sample 0: "
                        "RuntimeError: not enabled after 1000 ticks: fault 7500h")
    assert (out / "report.md").is_file()


# --- from the command line -------------------------------------------------------------------

def hil(*args, timeout: float = 300.0) -> subprocess.CompletedProcess:
    """``hil ARGS`` in a process of its own (``timeout``: a hang ends the test)."""
    return subprocess.run([sys.executable, "-m", "hil.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout, cwd=ROOT,
                          check=False)


def refused_in_one_line(done: subprocess.CompletedProcess, start: str) -> str:
    """Exit status 2, no traceback, and stderr one line starting with ``start``."""
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(start), done.stderr
    return lines[0]


@pytest.fixture(scope="module")
def deep_toml(tmp_path_factory) -> Path:
    """A machine file of arrays nested 500 deep (RecursionError in hil run, sim and eds)."""
    return _write(tmp_path_factory.mktemp("deep") / "deep.toml", DEEP["arrays 500 deep"])


COMMANDS = {
    "hil sim": lambda deep, tmp: ("sim", deep, "--program", ROOT / "programs" / "demo_moves.nc",
                                  "--out", tmp),
    "hil run": lambda deep, tmp: ("run", deep, "--adapter", "udp://127.0.0.1:0"),
    "hil eds": lambda deep, tmp: ("eds", deep, "--adapter", "can://vcan0", "--out", tmp),
}


@pytest.mark.parametrize("args", COMMANDS.values(), ids=COMMANDS.keys())
def test_a_machine_file_nested_500_deep_is_refused_by_each_command(deep_toml, tmp_path,
                                                                   capsys, args):
    """The attacker's machine file: exit 2 and one line naming the file and the bound
    (in this process: a RecursionError would come back as an exception and fail it)."""
    line = refused_in_process(capsys, "hil", *args(deep_toml, tmp_path))
    assert f"{deep_toml}: tables and arrays nested more than {MAX_NESTING} deep" in line


PROGRAMS = {
    "a feed of 1e-6 mm/min": (b"G90 G71\nG1 X10 F0.000001\nM30\n",
                              "line 2: the move of 10 mm at 'F1e-06' (mm/min)"),
    "X with 401 digits": (b"G0 X" + b"9" * 401 + b"\nM30\n",
                          "line 1: number in word 'X9999"),
    "not UTF-8": (b"G0 X1\n\xff\xfe\nM30\n", ": not UTF-8 text (byte 0xff at line 2"),
    "a directory": (None, ": is a directory, not a part program"),
    "a FIFO": (os.mkfifo, ": not a regular file (a FIFO)"),
}


def _make(path: Path, content) -> Path:
    """``path`` as a file of ``content`` (bytes), a directory (None) or a FIFO (os.mkfifo)."""
    if content is None:
        path.mkdir()
    elif callable(content):
        content(path)
    else:
        path.write_bytes(content)
    return path


def in_process(capsys, *args) -> tuple[int, str]:
    """``hil ARGS`` through :func:`hil.cli.main` in this process: (exit status, stderr);
    an exception the command line lets through fails the test."""
    from hil.cli import main

    code = main([str(a) for a in args])
    return code, capsys.readouterr().err


def refused_in_process(capsys, start: str, *args) -> str:
    """In this process: exit status 2 and stderr one line starting with ``start``."""
    code, err = in_process(capsys, *args)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith(start), (code, err)
    return lines[0]


@pytest.mark.parametrize("content, fragment", PROGRAMS.values(), ids=PROGRAMS.keys())
def test_hil_sim_refuses_each_bad_program_in_one_line(tmp_path, capsys, content, fragment):
    """Each part program the attacker found (1.09 TiB allocation, OverflowError,
    UnicodeDecodeError, IsADirectoryError, a FIFO hanging past 20 s): exit 2, one line
    naming the file and what is wrong, the line, word and unit where there is one.  The
    FIFO in a process of its own, which a hang cannot keep."""
    path = _make(tmp_path / "p.nc", content)
    args = ("sim", ARROW, "--program", path, "--out", tmp_path / "out")
    if content is os.mkfifo:
        line = refused_in_one_line(hil(*args), f"hil: {path}")
    else:
        line = refused_in_process(capsys, f"hil: {path}", *args)
    assert fragment in line


def _trace(n: int = 300, bad: tuple[int, str, str] | None = None) -> bytes:
    """A servo trace of ``n`` rows at 1 ms (a slow sine move and its current), with
    ``bad`` = (row, column, text) written in place of one value."""
    t = np.arange(n) * 0.001
    pos = 10.0 * np.sin(2.0 * np.pi * t)
    rows = [[repr(float(v)) for v in row] for row in zip(t, pos, pos * 0.999, pos * 0.1)]
    if bad is not None:
        row, column, text = bad
        rows[row][COLUMNS.index(column)] = text
    lines = ["# sample_time_s: 0.001", ",".join(COLUMNS)] + [",".join(r) for r in rows]
    return ("\n".join(lines) + "\n").encode()


TRACES = {
    "a NaN": (_trace(bad=(100, "pos_mm", "nan")),
              ":103: column 'pos_mm' is nan (data row 101); every value must be finite"),
    "one inf": (_trace(bad=(100, "iq_a", "inf")), ":103: column 'iq_a' is inf (data row 101)"),
    "a value beyond the bound": (_trace(bad=(7, "iq_a", "1e300")),
                                 ":10: column 'iq_a' is 1e+300 (data row 8)"),
    "a single row": (_trace(1), ": 1 data row; a record needs two samples at least"),
    "binary": (b"\x00\xff\xfe\x89PNG\r\n", ": not UTF-8 text (byte 0xff at line 1, offset 1)"),
    "a FIFO": (os.mkfifo, ": not a regular file (a FIFO)"),
}


@pytest.mark.parametrize("content, fragment", TRACES.values(), ids=TRACES.keys())
def test_hil_identify_refuses_each_bad_trace_before_any_fit(tmp_path, capsys, content,
                                                             fragment):
    """Each trace the attacker found (LinAlgError from NaN or inf, ValueError from one
    row, UnicodeDecodeError, a FIFO that hung): exit 2, one line naming the file, and the
    line, the column and the data row of a bad value."""
    path = _make(tmp_path / "t.csv", content)
    args = ("identify", path, "--config", ARROW, "--out", tmp_path / "out", "--quiet",
            "--workers", "1")
    if content is os.mkfifo:
        line = refused_in_one_line(hil(*args), f"hil identify: {path}")
    else:
        line = refused_in_process(capsys, f"hil identify: {path}", *args)
    assert fragment in line


def test_hil_study_refuses_a_step_beyond_the_travel_with_exit_2(tmp_path, capsys):
    """The attacker's study (every sample failed, then a broadcast ValueError, exit 1):
    exit 2 and one line, before any worker starts."""
    path = _write(tmp_path / "far.toml", STUDY_TEXT.replace("at_mm = 250.0", "at_mm = 5000.0"))
    line = refused_in_process(capsys, f"hil study: {path}: [experiment] at_mm = 5000 mm",
                              "study", path, "--out", tmp_path / "out")
    assert "0 .. 510 mm" in line and not (tmp_path / "out").exists()


MAT_VALUES = st.one_of(
    st.lists(st.floats(width=64), max_size=6).map(np.array),
    st.integers(0, 3).flatmap(lambda r: st.integers(0, 3).map(
        lambda c: np.linspace(0.0, 1.0, r * c).reshape(r, c))),
    st.sampled_from(["text", "", True, 1 + 2j, -1.0, 0.0, 2.0, 1e300, float("nan")]),
    st.just({"a": 1.0}), st.just(np.array([[1.0, 2.0], [3.0, 4.0]])))


@st.composite
def mat_files(draw) -> dict:
    """EMPS .mat variables (t, qm, qg, vir, gtau, kp, kv, pulses_N) of any shape and type,
    some missing: a time axis of a few samples, regular or not."""
    n = draw(st.integers(0, 5))
    t = np.arange(n) * 0.001 if draw(st.booleans()) else draw(MAT_VALUES)
    names = draw(st.sets(st.sampled_from(["qm", "qg", "vir", "gtau", "kp", "kv",
                                          "pulses_N"])))
    good = {"qm": np.zeros(n), "qg": np.zeros(n), "vir": np.zeros(n), "pulses_N": np.zeros(n),
            "gtau": 1.0, "kp": 1.0, "kv": 1.0}
    return {"t": t, **{k: draw(MAT_VALUES) if k in names else v for k, v in good.items()}}


@FUZZ
@given(variables=mat_files(), cut=st.integers(0, 400))
def test_fuzz_identify_mat_record(tmp_path, variables, cut):
    """Any EMPS .mat record, whole or cut short after ``cut`` bytes: a record, or a
    TraceFormatError of one line naming the file."""
    from scipy.io import savemat

    path = tmp_path / "fuzz.mat"
    savemat(path, variables)
    if cut:
        path.write_bytes(path.read_bytes()[:cut])
    try:
        rec = load_record(path)
    except TraceFormatError as exc:
        one_line(str(exc), path)
        return
    assert rec.n >= 2 and np.all(np.isfinite(rec.pos)) and np.all(np.isfinite(rec.effort))


@pytest.mark.parametrize("name", ["report.json", "recording.arrows"])
def test_a_run_folder_file_that_is_a_fifo_is_refused_not_waited_on(tmp_path, name):
    """`hil report` on a run folder whose report.json or recording.arrows is a FIFO nobody
    writes: one line naming it, exit 2 or 1, in a process of its own that must end (a
    read would block forever)."""
    import subprocess
    import sys

    from tests.runtime_helpers import ENV
    (tmp_path / "run").mkdir()
    os.mkfifo(tmp_path / "run" / name)
    run = subprocess.run([sys.executable, "-m", "hil.cli", "report", str(tmp_path / "run")],
                         capture_output=True, text=True, timeout=60, env=ENV, check=False)
    assert run.returncode != 0
    assert "not a regular file (a FIFO)" in run.stderr
    assert "Traceback" not in run.stderr
