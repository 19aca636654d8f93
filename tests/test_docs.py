"""The documentation stays true to the code and to itself: docs/options.md
lists exactly the options ``component_container --help`` lists, and every
relative link of the README and of docs/ reaches a file (and the heading it
names, if it names one)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from cloneguard.container import cli

ROOT = Path(__file__).resolve().parents[1]
OPTIONS_PAGE = ROOT / "docs" / "options.md"
# Mentioned on the options page, and not the container's own options.
NOT_CONTAINER_OPTIONS = {"--ros-args"}
# Pages whose relative links must resolve: the README, docs/, and the
# pages outside docs/ that docs/index.md lists.
LINKED_PAGES = sorted(
    [
        ROOT / "README.md",
        *(ROOT / "docs").glob("*.md"),
        ROOT / "CONTRIBUTING.md",
        ROOT / "CHANGELOG.md",
        ROOT / "bench" / "README.md",
        ROOT / "reports" / "README.md",
        ROOT / "container" / "isolated" / "README.md",
        ROOT / "container" / "intra" / "README.md",
    ]
)
README_MAX_LINES = 150

_OPTION = re.compile(r"(?<![\w-])--?[A-Za-z][\w-]*")
_FENCE = re.compile(r"^(```|~~~)")
_HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")
_LINK = re.compile(r"\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
_CODE_SPAN = re.compile(r"(`+)(?:(?!\1).)+?\1")


def _help_text(capsys, monkeypatch) -> str:
    """``component_container --help``, from the container's own parser
    (cli.parse_args), in this process: no ROS context is made."""
    monkeypatch.setenv("COLUMNS", "200")
    with pytest.raises(SystemExit) as exit_:
        cli.parse_args(["--help"])
    assert exit_.value.code in (0, None)
    return capsys.readouterr().out


def _help_options(text: str) -> set[str]:
    """The option strings of --help's option lines (``  -h, --help  ...``,
    ``  --profile {per-node,shared}``), not those its help texts mention."""
    found = set()
    for line in text.splitlines():
        m = re.match(r"^  (-\S.*?)(?:\s{2,}|$)", line)
        if m:
            found.update(_OPTION.findall(m.group(1)))
    return found


def _prose_lines(path: Path) -> list[str]:
    """A markdown file's lines outside fenced code blocks."""
    lines, fenced = [], False
    for line in path.read_text().splitlines():
        if _FENCE.match(line.strip()):
            fenced = not fenced
            continue
        if not fenced:
            lines.append(line)
    return lines


def _documented_options() -> set[str]:
    """The options the page documents: the first cell of its tables' rows."""
    found = set()
    for line in _prose_lines(OPTIONS_PAGE):
        if line.startswith("|"):
            first_cell = re.split(r"(?<!\\)\|", line)[1]
            found.update(_OPTION.findall(first_cell))
    return found


def test_help_lists_options_at_all(capsys, monkeypatch):
    options = _help_options(_help_text(capsys, monkeypatch))
    assert {"--help", "--isolated", "--profile", "--pkeys"} <= options


def test_every_option_of_help_is_on_the_options_page(capsys, monkeypatch):
    missing = _help_options(_help_text(capsys, monkeypatch)) - _documented_options()
    assert not missing, f"in --help but not documented in docs/options.md: {sorted(missing)}"


def test_every_option_on_the_options_page_is_in_help(capsys, monkeypatch):
    gone = _documented_options() - _help_options(_help_text(capsys, monkeypatch))
    assert not gone, f"documented in docs/options.md but not in --help: {sorted(gone)}"


def test_the_options_page_mentions_no_other_option(capsys, monkeypatch):
    known = _help_options(_help_text(capsys, monkeypatch)) | NOT_CONTAINER_OPTIONS
    text = "\n".join(_prose_lines(OPTIONS_PAGE))
    unknown = {opt for opt in _OPTION.findall(text) if opt.startswith("--")} - known
    assert not unknown, f"docs/options.md mentions options --help does not have: {sorted(unknown)}"


def _slug(heading: str) -> str:
    """The anchor GitHub gives a heading: lower case, punctuation dropped
    (hyphens and underscores kept), spaces made hyphens."""
    text = _CODE_SPAN.sub(lambda m: m.group(0).strip("`"), heading)
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", text)  # a link's text only
    return re.sub(r"[^\w\- ]", "", text.strip().lower()).replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    anchors: set[str] = set()
    seen: dict[str, int] = {}
    for line in _prose_lines(path):
        m = _HEADING.match(line)
        if not m:
            continue
        slug = _slug(m.group(2))
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        anchors.add(slug if n == 0 else f"{slug}-{n}")
    return anchors


def _links(path: Path) -> list[str]:
    links = []
    for line in _prose_lines(path):
        links += _LINK.findall(_CODE_SPAN.sub("", line))
    return links


def _broken_links(path: Path) -> list[str]:
    broken = []
    for target in _links(path):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto: ...
            continue
        file_part, _, anchor = target.partition("#")
        dest = (path.parent / file_part).resolve() if file_part else path
        if not dest.exists():
            broken.append(f"{target}: no such file")
        elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
            broken.append(f"{target}: no heading #{anchor} in {dest.relative_to(ROOT)}")
    return broken


@pytest.mark.parametrize("page", LINKED_PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_resolves(page):
    broken = _broken_links(page)
    assert not broken, f"{page.relative_to(ROOT)}: " + "; ".join(broken)


def test_the_link_check_sees_links():
    """The checks above are not vacuous: the README links into docs/, and a
    link to a missing file or heading is found broken."""
    assert any(t.startswith("docs/") for t in _links(ROOT / "README.md"))
    assert "docs/index.md" in _links(ROOT / "README.md")
    assert "architecture.md#what-a-node-process-is" in _links(ROOT / "docs" / "options.md")


def test_the_slugs_are_githubs():
    assert _slug("The allocator guard (`allocguard.c`)") == "the-allocator-guard-allocguardc"
    assert _slug("Protection keys over node heaps (`heapkeys.c`, `--pkeys`)") == (
        "protection-keys-over-node-heaps-heapkeysc---pkeys"
    )
    assert _slug("1. Make your nodes loadable") == "1-make-your-nodes-loadable"
    assert _slug("From LoadNode to CRASHED") == "from-loadnode-to-crashed"


def test_the_readme_stays_short():
    lines = len((ROOT / "README.md").read_text().splitlines())
    assert lines <= README_MAX_LINES, f"README.md has {lines} lines; the reference belongs in docs/ (docs/index.md)"


# -- CONTRIBUTING's recipes name files and code that exist ------------------------------

CONTRIBUTING = ROOT / "CONTRIBUTING.md"
_EXTENSIONS = (".py", ".c", ".h", ".md", ".msg", ".toml", ".yaml", ".sh")
_IDENTIFIER = re.compile(r"^[A-Za-z_]\w*(?:\.[A-Za-z_]\w*)*$")


def _tracked() -> list[str]:
    import subprocess

    out = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    return out.splitlines()


def _spans(page: Path) -> list[str]:
    return [m.group(0).strip("`").strip() for m in _CODE_SPAN.finditer(page.read_text())]


def _recipe_paths(page: Path) -> list[str]:
    """Code spans that name a file or folder: with a slash, or a file name
    with a known extension (a pattern like ``faults/*.c`` counts)."""
    return [
        s
        for s in _spans(page)
        if " " not in s
        and "=" not in s
        and ("/" in s[1:] or (s.endswith(_EXTENSIONS) and s[0] != "."))
        and not s.startswith(("/", "-"))
    ]


def _recipe_names(page: Path) -> list[str]:
    """Code spans that name code: identifiers with an underscore, dotted or
    not (``cgr_event_write_death``, ``CloneCore.arm_crashed``), not file names."""
    return [s for s in _spans(page) if _IDENTIFIER.match(s) and "_" in s and not s.endswith(_EXTENSIONS)]


def test_every_file_contributing_names_exists():
    import fnmatch

    tracked = _tracked()
    missing = [
        p
        for p in _recipe_paths(CONTRIBUTING)
        if not any(
            fnmatch.fnmatch(t, p.rstrip("/") + ("/*" if p.endswith("/") else ""))
            or fnmatch.fnmatch(t, "*/" + p.rstrip("/") + ("/*" if p.endswith("/") else ""))
            for t in tracked
        )
    ]
    assert not missing, f"CONTRIBUTING.md names files the tree does not have: {missing}"


def test_every_name_contributing_gives_code_is_in_the_code():
    sources = "\n".join(
        (ROOT / t).read_text(errors="replace")
        for t in _tracked()
        if t.endswith((".py", ".c", ".h", ".toml")) and (ROOT / t).is_file()
    )
    missing = [n for n in _recipe_names(CONTRIBUTING) if not re.search(rf"\b{re.escape(n.split('.')[-1])}\b", sources)]
    assert not missing, f"CONTRIBUTING.md names code the tree does not have: {missing}"


def test_the_recipe_checks_see_names():
    """Not vacuous: the ComponentEvent recipe's files and functions are seen."""
    assert "container/isolated/clonecore/herald.c" in _recipe_paths(CONTRIBUTING)
    assert "faults/*.c" in _recipe_paths(CONTRIBUTING)
    assert "cgr_event_write_death" in _recipe_names(CONTRIBUTING)
    assert "herald_claim" in _recipe_names(CONTRIBUTING)


ISOLATED = ROOT / "container" / "isolated"
#: The isolated README's map: its parts (### headings), and the folder and
#: kinds of file they name between them.
MAP_PARTS = [
    (("`clonecore/`",), ISOLATED / "clonecore", (".c", ".h")),
    (("`allocguard/`",), ISOLATED / "allocguard", (".c", ".h")),
    (("One file, one artifact",), ISOLATED, (".c", ".cpp")),
    (("One file, one artifact", "The Python that runs them"), ISOLATED, (".py",)),
]


def _files(folder: Path, suffixes: tuple[str, ...]) -> set[str]:
    tracked = set(_tracked())
    return {p.name for p in folder.iterdir() if p.suffix in suffixes and str(p.relative_to(ROOT)) in tracked}


def _map_part(text: str, heading: str) -> set[str]:
    """The names in the first column of the table under the ``###``
    heading that begins with ``heading``."""
    part = text.split(f"### {heading}", 1)[1].split("\n### ", 1)[0]
    rows = [line for line in part.splitlines() if line.startswith("| `")]
    return {name for row in rows for name in re.findall(r"`([^`]+)`", row.split("|")[1])}


def test_the_isolated_readmes_map_names_every_file_of_each_folder_in_its_part():
    """Each folder of C is one artifact (clonecore/, allocguard/), and the
    map says so: a file added to a folder without its row, or a row left
    for a file gone or moved, fails here."""
    text = (ISOLATED / "README.md").read_text()
    for headings, folder, suffixes in MAP_PARTS:
        named = {n for h in headings for n in _map_part(text, h) if n.endswith(suffixes)}
        there = _files(folder, suffixes)
        assert named == there, f"{headings}: named, not there {named - there}; there, not named {there - named}"
