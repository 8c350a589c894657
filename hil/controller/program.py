"""Part programs for one axis: a Sinumerik-style G-code subset -> frozen blocks in SI.

One block per line::

    N10 G90 G71          ; absolute dimensions, metric (the defaults)
    N20 G0 X250          ; rapid traverse at the axis's maximum velocity (MD32000)
    N30 G1 X250.5 F200   ; linear move at 200 mm/min; F is modal
    N40 G4 F0.5          ; dwell 0.5 s (Sinumerik: F in a G4 block is seconds)
    N50 G91 X-50         ; incremental: 50 mm back, still G1 at F200
    N60 M10              ; clamp the axis (the machine's clamp M function)
    N70 G4 F2            ; clamped: clamping monitoring instead of standstill monitoring
    N80 M11              ; unclamp
    N90 M30              ; end of program (M2 also)

Words: ``N`` block number (optional, first in the block), ``G0``/``G1`` (modal motion),
``G4`` (dwell, alone in its block with ``F`` in seconds), ``G90``/``G91`` (absolute /
incremental, modal, default G90), ``G71`` (metric; ``G70`` inch is refused), the axis
word, ``F`` feed in mm/min (deg/min for a rotary axis), ``M2``/``M30`` end, and the
axis's clamp and unclamp M functions (:class:`ClampCodes`, machine data; M10 and M11 by
default), each alone in its block.  A motion block for a clamped axis is a program error
(the line and the clamping block named): unclamp first.  A program starts unclamped.
Comments run from ``;`` to the end of the line, or sit between ``(`` and ``)``.  Linear
axes (X Y Z U V W) take mm, rotary axes (A B C) take degrees.  A program is written for
one axis letter; a word for another axis is refused (:mod:`hil.controller.path` reads
programs of several axes).

Numbers are plain decimals (no exponent) below :data:`MAX_NUMBER` in magnitude: nine
digits before the point.  A program file is read through :func:`plant.files.read_text`
(a directory, a FIFO or a device is refused unread; at most :data:`MAX_PROGRAM_BYTES`;
UTF-8).

Every error is a :class:`ProgramError` naming the source, the line and the word.
"""

import functools
import math
import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from enum import Enum
from pathlib import Path

from plant.files import read_text

LINEAR_AXES = "XYZUVW"
ROTARY_AXES = "ABC"
_NUMBER = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)")
_END_CODES = (2, 30)
#: a number word's magnitude stays below this (nine digits before the decimal point:
#: 1000 km in mm, more than any machine travels); more is a typing error, and from 310
#: digits on not even a float (it reads as infinity)
MAX_NUMBER = 1e9
#: a program file larger than this is refused unread, bytes (a part program of this subset
#: is a few hundred blocks; ten megabytes are a quarter of a million)
MAX_PROGRAM_BYTES = 10_000_000
#: a word longer than this is shown cut short in a message
_SHOWN = 24


class ProgramError(ValueError):
    """A part program cannot be read; the message names the source, line and word.

    ``line`` 0 is the file as a whole (missing, not a regular file, not UTF-8): the
    message then names the file itself, as :mod:`plant.files` words it.  ``reason`` is
    the message without the source and line."""

    def __init__(self, source: str, line: int, message: str):
        self.source = source
        self.line = line
        self.reason = message
        super().__init__(f"{source} line {line}: {message}" if line else message)


class BlockKind(str, Enum):
    """What a block does."""
    MOVE = "move"
    DWELL = "dwell"
    CLAMP = "clamp"
    UNCLAMP = "unclamp"


@dataclass(frozen=True)
class ClampCodes:
    """The M functions that clamp and unclamp an axis (machine data: the machine's PLC
    clamps it; ``[controller] clamp_m_code``, ``unclamp_m_code``)."""
    clamp: int = 10
    unclamp: int = 11

    def __post_init__(self):
        if self.clamp == self.unclamp:
            raise ValueError(f"clamp and unclamp need two M functions, both are "
                             f"M{self.clamp}")


@dataclass(frozen=True)
class Block:
    """One executable block in SI units of the axis (m for linear, rad for rotary).

    ``start`` and ``target`` are the axis positions before and after the block (equal
    for a dwell and a clamp).  ``feed`` is the programmed path velocity in m/s or rad/s,
    ``inf`` for a rapid (G0) move (the interpolator clips every feed to the axis's maximum
    velocity) and 0 otherwise.  ``dwell_s`` is the dwell time in s (0 for a move).
    ``m_code`` is the M function of a clamp or unclamp block (0 otherwise).  ``line`` is
    the 1-based line of the program text.
    """
    kind: BlockKind
    line: int
    start: float
    target: float
    feed: float = 0.0
    rapid: bool = False
    dwell_s: float = 0.0
    m_code: int = 0


@dataclass(frozen=True)
class Program:
    """A parsed program: its axis letter, whether that axis is rotary (rad) or linear (m),
    the axis position it starts from (m or rad), its blocks in order and the source that
    names it in messages (a file name)."""
    axis: str
    rotary: bool
    start: float
    blocks: tuple[Block, ...]
    source: str = "<program>"

    @property
    def end(self) -> float:
        """Axis position after the last block (m or rad)."""
        return self.blocks[-1].target if self.blocks else self.start


ErrorFactory = Callable[[str], ProgramError]
"""Builds the :class:`ProgramError` of the line being parsed from a message."""


@dataclass
class _Modal:
    """Modal state carried from block to block while parsing."""
    pos: float
    absolute: bool = True
    motion: int | None = None
    feed: float | None = None
    clamped_at: int = 0  # line of the block that clamped the axis; 0: not clamped


@dataclass(frozen=True)
class _Words:
    """The words of one block, numbers as written (mm, mm/min, s)."""
    g: tuple[int, ...]
    axis: float | None
    axis_word: str
    f: float | None


def _scales(rotary: bool) -> tuple[float, float]:
    """(position, feed) factors from program units (mm, mm/min or deg, deg/min) to SI."""
    if rotary:
        return math.pi / 180.0, math.pi / 180.0 / 60.0
    return 1e-3, 1e-3 / 60.0


def _strip_comments(text: str, err: ErrorFactory) -> str:
    """The code of one line without its ``;`` and ``( )`` comments."""
    code = []
    i = 0
    while i < len(text):
        c = text[i]
        if c == ";":
            break
        if c == "(":
            close = text.find(")", i)
            if close < 0:
                raise err(f"comment '{text[i:]}' is not closed with ')'")
            i = close + 1
            code.append(" ")
            continue
        if c == ")":
            raise err("')' without an opening '('")
        code.append(c)
        i += 1
    return "".join(code)


def _tokens(code: str, err: ErrorFactory) -> list[tuple[str, str, float]]:
    """(word as written, letter, value) for each word of a comment-free line."""
    out = []
    for m in re.finditer(r"\S+?(?=[A-Za-z]|\s|$)", code):
        word = m.group(0).upper()
        letter, digits = word[0], word[1:]
        if not letter.isalpha():
            raise err(f"unexpected '{shown(word)}' (a word is a letter followed by a number)")
        if not _NUMBER.fullmatch(digits):
            raise err(f"bad number in word '{shown(word)}'")
        value = float(digits)
        if not abs(value) < MAX_NUMBER:
            raise err(f"number in word '{shown(word)}' is too large: at most nine digits "
                      f"before the decimal point (below {MAX_NUMBER:.0e} of the word's unit: "
                      "mm, deg, mm/min, deg/min or s)")
        out.append((word, letter, value))
    return out


def shown(word: str) -> str:
    """``word`` for a message, cut short when it is longer than a real word can be."""
    return word if len(word) <= _SHOWN else f"{word[:_SHOWN]}… ({len(word)} characters)"


@dataclass(frozen=True)
class SortedWords:
    """The words of one line: G codes, {letter: value} of the axis letters and F,
    {letter: the word as written}, end of program (M2/M30), and the clamp M functions."""
    g: tuple[int, ...]
    values: dict
    written: dict
    end: bool
    m: tuple[int, ...]

    def m_function(self, err: ErrorFactory) -> int | None:
        """The block's clamp M function, or None; refused unless it stands alone."""
        if not self.m:
            return None
        if len(self.m) > 1 or self.g or self.values or self.end:
            raise err(f"M{self.m[0]} (clamping) must stand alone in its block")
        return self.m[0]


def sort_words(code: str, axes: str, err: ErrorFactory, foreign: Callable[[str], str],
               m_codes: frozenset = frozenset()) -> SortedWords:
    """Sort one comment-free line's words.  An axis word of another letter is refused
    with ``foreign(word)``; an M function other than M2, M30 and those of ``m_codes``,
    and anything else unknown, as such."""
    g: list[int] = []
    values: dict[str, float] = {}
    written: dict[str, str] = {}
    m: list[int] = []
    end = False
    for i, (word, letter, value) in enumerate(_tokens(code, err)):
        if letter == "N":
            if i != 0 or value != int(value) or value < 0:
                raise err(f"block number '{word}' must come first and be a whole number")
        elif letter == "G":
            g.append(_g_code(word, value, err))
        elif letter == "M" and value in _END_CODES:
            end = True
        elif letter == "M" and value in m_codes:
            m.append(int(value))
        elif letter in axes or letter == "F":
            if letter in values:
                raise err(f"word {letter} appears twice ('{word}')")
            values[letter] = value
            written[letter] = word
        elif letter in LINEAR_AXES + ROTARY_AXES:
            raise err(foreign(word))
        else:
            raise err(f"unknown word '{shown(word)}'")
    return SortedWords(tuple(g), values, written, end, tuple(m))


def program_lines(text: str, source: str, axes: str, foreign: Callable[[str], str],
                  m_codes: frozenset) -> Iterator[tuple[int, ErrorFactory, SortedWords]]:
    """Each line of a program with a block on it: (its 1-based number, the factory of its
    :class:`ProgramError`, its words, :func:`sort_words`); a block after the end of the
    program (M2/M30) is refused."""
    ended = False
    for line, raw in enumerate(text.splitlines(), start=1):
        err = functools.partial(ProgramError, source, line)
        code = _strip_comments(raw, err)
        if not code.strip():
            continue
        if ended:
            raise err(f"block '{code.strip()}' after the end of the program (M2/M30)")
        words = sort_words(code, axes, err, foreign, m_codes)
        yield line, err, words
        ended = words.end


def clamped_error(axis: str, word: str, clamped_at: int, codes: ClampCodes) -> str:
    """The message for a motion block of a clamped axis."""
    return (f"'{word}' moves axis {axis}, clamped since line {clamped_at} "
            f"(M{codes.clamp}): unclamp it with M{codes.unclamp} first")


def _words(w: SortedWords, axis: str) -> _Words:
    """One line's words as G codes, axis and F."""
    return _Words(w.g, w.values.get(axis), w.written.get(axis, ""), w.values.get("F"))


def _g_code(word: str, value: float, err: ErrorFactory) -> int:
    """The G code's number, refusing inch units and codes outside the subset."""
    if value == 70:
        raise err(f"'{word}' (inch) is refused: programs are metric (G71)")
    if value not in (0, 1, 4, 71, 90, 91):
        raise err(f"unknown word '{word}' (supported: G0 G1 G4 G71 G90 G91)")
    return int(value)


def _check_groups(g: tuple[int, ...], err: ErrorFactory) -> None:
    """At most one code of each G group in a block."""
    for group in ((0, 1, 4), (90, 91)):
        found = [c for c in g if c in group]
        if len(found) > 1:
            raise err("conflicting " + " and ".join(f"G{c}" for c in found))


def _clamp_block(code: int, st: _Modal, codes: ClampCodes, line: int) -> Block:
    """The block of a clamp or unclamp M function; the clamp state updated."""
    clamp = code == codes.clamp
    st.clamped_at = (st.clamped_at or line) if clamp else 0
    return Block(BlockKind.CLAMP if clamp else BlockKind.UNCLAMP, line, st.pos, st.pos,
                 m_code=code)


def _block(w: _Words, st: _Modal, rotary: bool, line: int, err: ErrorFactory) -> Block | None:
    """Update the modal state with one line's words; the block it executes, if any."""
    _check_groups(w.g, err)
    pos_scale, feed_scale = _scales(rotary)
    if 90 in w.g or 91 in w.g:
        st.absolute = 90 in w.g
    if 4 in w.g:
        if w.axis is not None:
            raise err(f"G4 must stand in its own block (found '{w.axis_word}')")
        if w.f is None or w.f < 0.0:
            got = "no F" if w.f is None else f"F{w.f:g}"
            raise err(f"G4 needs F<seconds> >= 0 (Sinumerik dwell time), got {got}")
        return Block(BlockKind.DWELL, line, st.pos, st.pos, dwell_s=w.f)
    for code in w.g:
        if code in (0, 1):
            st.motion = code
    if w.f is not None:
        if w.f <= 0.0:
            raise err(f"feed 'F{w.f:g}' must be > 0")
        st.feed = w.f * feed_scale
    if w.axis is None:
        return None
    if st.motion is None:
        raise err(f"'{w.axis_word}' without a motion mode (program G0 or G1 first)")
    if st.motion == 1 and st.feed is None:
        raise err(f"G1 move '{w.axis_word}' needs a feed: no F programmed yet")
    start = st.pos
    st.pos = w.axis * pos_scale if st.absolute else start + w.axis * pos_scale
    if st.motion == 0:
        return Block(BlockKind.MOVE, line, start, st.pos, feed=math.inf, rapid=True)
    return Block(BlockKind.MOVE, line, start, st.pos, feed=st.feed)


def parse_program(text: str, axis: str = "X", start: float = 0.0,
                  source: str = "<program>", clamp: ClampCodes = ClampCodes()) -> Program:
    """Parse a part program for the axis ``axis`` starting at ``start`` (m or rad), with
    the axis's clamp M functions ``clamp``.

    ``source`` names the program in error messages (a file name).  Raises
    :class:`ProgramError` on the first bad line; ValueError for an unknown axis letter.
    """
    if len(axis) != 1 or axis not in LINEAR_AXES + ROTARY_AXES:
        raise ValueError(f"axis letter {axis!r} is not one of {LINEAR_AXES + ROTARY_AXES}")
    rotary = axis in ROTARY_AXES
    st = _Modal(pos=start)
    blocks = []
    lines = program_lines(text, source, axis, lambda word: f"axis word '{word}' is not for "
                          f"this program's axis {axis} (single-axis programs only)",
                          frozenset((clamp.clamp, clamp.unclamp)))
    for line, err, sw in lines:
        m = sw.m_function(err)
        if m is not None:
            blocks.append(_clamp_block(m, st, clamp, line))
            continue
        w = _words(sw, axis)
        if w.axis is not None and st.clamped_at:
            raise err(clamped_error(axis, w.axis_word, st.clamped_at, clamp))
        block = _block(w, st, rotary, line, err)
        if block is not None:
            blocks.append(block)
    return Program(axis, rotary, start, tuple(blocks), source)


def read_program(path: str | Path, axis: str = "X", start: float = 0.0,
                 clamp: ClampCodes = ClampCodes()) -> Program:
    """Read and parse a part program file (see :func:`parse_program`); ProgramError
    also when the file cannot be read as text (:func:`read_program_text`)."""
    return parse_program(read_program_text(path), axis, start, source=str(path), clamp=clamp)


def read_program_text(path: str | Path) -> str:
    """The text of a program file, or a :class:`ProgramError` (line 0) naming the file:
    missing, not a regular file, larger than :data:`MAX_PROGRAM_BYTES`, not UTF-8."""
    return read_text(path, "part program", MAX_PROGRAM_BYTES,
                     functools.partial(ProgramError, str(path), 0))


def _number(x: float) -> str:
    """A program number to 1e-6 of its unit (1 nm, 1e-6 deg, 1e-6 mm/min, 1 us)."""
    return f"{x:.6f}".rstrip("0").rstrip(".")


def format_program(program: Program) -> str:
    """The program as text that :func:`parse_program` reads back (absolute, G90).

    Positions, feeds and dwell times are written to 1e-6 of their program unit (mm or
    deg, mm/min or deg/min, s): blocks read from absolute values with at most six
    decimals come back exactly, incremental sums to within their rounding.
    """
    pos_scale, feed_scale = _scales(program.rotary)
    a = program.axis
    lines = ["G90 G71"]
    for b in program.blocks:
        if b.kind is BlockKind.DWELL:
            lines.append(f"G4 F{_number(b.dwell_s)}")
        elif b.kind in (BlockKind.CLAMP, BlockKind.UNCLAMP):
            lines.append(f"M{b.m_code}")
        elif b.rapid:
            lines.append(f"G0 {a}{_number(b.target / pos_scale)}")
        else:
            lines.append(f"G1 {a}{_number(b.target / pos_scale)} F{_number(b.feed / feed_scale)}")
    lines.append("M30")
    return "\n".join(lines) + "\n"
