"""The README as a guide and the docs/ pages as its reference (issue: README as a guide).

Each test reads the files as committed and checks one promise the README makes to a new
user: it is short, its links lead somewhere, it names no one's machine, its commands leave
the checkout as it was, and its test command is the one CI runs.
"""

import re
import shlex
import subprocess
import unicodedata
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
DOCS = sorted((ROOT / "docs").glob("*.md"))
PAGES = [README, *DOCS]
#: Every text file the docs hold, generated reports included.
DOC_TEXTS = [README, *sorted(f for f in (ROOT / "docs").rglob("*")
                             if f.suffix in (".md", ".json", ".toml"))]

#: Markdown links and images: [text](target) and ![alt](target); code spans are removed
#: before matching, so a link written inside backticks is not one.
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
#: An absolute path of somebody's machine: a home, root's home, the work tree of a build
#: machine, a user's temporary folder with a name in it.
MACHINE_PATH = re.compile(r"(?<![\w.~-])/(?:work|home|root|Users|mnt/data|tmp/wt-)[/\w.-]*")
#: Options whose value is a folder or file a command writes.
OUTPUT_OPTIONS = ("--out", "-o", "--record")


def _without_code(text: str) -> str:
    """``text`` without fenced blocks and inline code spans."""
    text = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
    return re.sub(r"`[^`\n]*`", "", text)


def _anchor(heading: str) -> str:
    """GitHub's anchor of a Markdown heading: lower case, punctuation dropped, spaces to
    hyphens."""
    text = heading.strip().lower()
    text = "".join(c for c in text if c in " -_" or unicodedata.category(c)[0] in "LN")
    return text.replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    text = re.sub(r"^```.*?^```", "", page.read_text(), flags=re.S | re.M)
    return {_anchor(m.group(1)) for m in re.finditer(r"^#+ (.+)$", text, flags=re.M)}


def _links(page: Path) -> list[str]:
    return LINK.findall(_without_code(page.read_text()))


def _sh_blocks(text: str) -> list[str]:
    return re.findall(r"^```sh\n(.*?)^```", text, flags=re.S | re.M)


def _commands(block: str) -> list[list[str]]:
    """The block's command lines as argument lists: continuation lines joined, comments
    and shell control (``&``, ``;``, ``&&``) split off."""
    joined = block.replace("\\\n", " ")
    commands = []
    for line in joined.splitlines():
        line = line.split(" #", 1)[0].strip()
        for part in re.split(r"\s(?:&&|;|&)(?:\s|$)|\s&$|;\s*", line):
            if part.strip():
                commands.append(shlex.split(part))
    return commands


def _outputs(argv: list[str]) -> list[str]:
    """The output paths ``argv`` names with --out, -o or --record."""
    outs = []
    for i, arg in enumerate(argv):
        for opt in OUTPUT_OPTIONS:
            if arg == opt and i + 1 < len(argv):
                outs.append(argv[i + 1])
            elif arg.startswith(opt + "="):
                outs.append(arg.split("=", 1)[1])
    return outs


def test_readme_is_under_500_lines():
    """The README is a guide, not the reference: fewer than 500 lines (the issue's bound)."""
    n = len(README.read_text().splitlines())
    assert n < 500, f"README.md has {n} lines; move reference text into docs/"


@pytest.mark.parametrize("page", PAGES, ids=[p.name for p in PAGES])
def test_relative_links_resolve(page):
    """Every relative link and image of the README and of docs/*.md names a file or
    folder in the repository, and an anchor into a Markdown page names one of its
    headings (checked against the files on disk and GitHub's anchor rule)."""
    broken = []
    for target in _links(page):
        if re.match(r"[a-z]+:", target):
            continue  # http(s), mailto: not this test's business
        path, _, anchor = target.partition("#")
        dest = page if not path else (page.parent / path).resolve()
        if not dest.exists() or ROOT not in (dest, *dest.parents):
            broken.append(target)
        elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
            broken.append(target)
    assert not broken, f"{page.name}: links that lead nowhere: {broken}"


def test_link_checker_sees_a_broken_link(tmp_path):
    """The checks above can fail: a missing file and a missing anchor are both found."""
    page = tmp_path / "page.md"
    page.write_text("# Here\n\n[a](missing.md) [b](#here) [c](#not-here) `[d](code.md)`\n")
    assert _links(page) == ["missing.md", "#here", "#not-here"]
    assert "here" in _anchors(page) and "not-here" not in _anchors(page)
    assert _anchor("`hil demo`'s verdict") == "hil-demos-verdict"


@pytest.mark.parametrize("page", DOC_TEXTS, ids=[str(p.relative_to(ROOT)) for p in DOC_TEXTS])
def test_no_absolute_machine_path(page):
    """No page, and no report committed under docs/, names an absolute path of a machine
    (/work/..., /home/..., /root/...): a reader's checkout is somewhere else.  Paths inside
    the repository are written relative to its root."""
    found = MACHINE_PATH.findall(page.read_text())
    assert not found, f"{page.name}: {found}"
    assert MACHINE_PATH.findall("files in /work/main/demo-out/ and /home/me/x") == [
        "/work/main/demo-out/", "/home/me/x"]


def test_readme_commands_write_only_into_ignored_folders():
    """Every command in the README's sh blocks that names its output (--out, -o,
    --record) writes under a folder git ignores (``git check-ignore``), so following the
    README never changes the checkout; regenerating docs/ is docs/maintenance.md's job."""
    outputs = []
    for block in _sh_blocks(README.read_text()):
        for argv in _commands(block):
            outputs += _outputs(argv)
    assert len(outputs) >= 10, outputs  # the tour names its outputs: the parse found them
    tracked = []
    for out in outputs:
        probe = f"{out.rstrip('/')}/probe.file"
        r = subprocess.run(["git", "check-ignore", "-q", "--no-index", probe], cwd=ROOT)
        if r.returncode != 0:
            tracked.append(out)
    assert not tracked, f"README commands that write where git tracks: {tracked}"


def test_output_parser_sees_every_form():
    """The command parser behind the test above finds outputs after continuation lines,
    in backgrounded commands and in every option form."""
    block = ("hil run a.toml --record out/run &\nhil sim a \\\n    --out docs/x\n"
             "hil eds a -o=eds # a comment --out no\nkill %1; wait\n")
    outs = [o for argv in _commands(block) for o in _outputs(argv)]
    assert outs == ["out/run", "docs/x", "eds"]


def test_readme_test_command_is_what_ci_runs():
    """The README's test command is, character for character, the command .ci/run runs
    (CI runs the README's line verbatim)."""
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    ci_command = [line for line in ci if line.strip() and not line.startswith(("#", "set ", "cd "))
                  and "pytest" in line]
    readme_command = [c.strip() for block in _sh_blocks(README.read_text())
                      for c in block.splitlines() if "pytest" in c]
    assert ci_command and readme_command
    assert readme_command[0] == ci_command[-1].strip()
