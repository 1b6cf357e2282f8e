"""The docs/ pages stay readable and true (issue 62).

Each page is at most 10,000 bytes (a longer one is a lab notebook or two topics: cut the history,
split the page); the index ``docs/README.md`` links every other page; ``docs/commands.md`` has a
table row for every command the CLI registers, and no page names a ``cloudpose NAME`` in its code
that the CLI does not register, nor an option (``cloudpose NAME ... --option``; the README and
the Makefile's recipes too) that NAME does not take; every relative link of a page leads to a
file (and a ``#heading`` to a heading of it). Reads the pages and the typer app only: nothing
runs, nothing is written.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from typer.main import get_command

from cloudpose.cli import app

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
PAGES = sorted(p.name for p in DOCS.glob("*.md"))
MAX_BYTES = 10_000

FENCE = re.compile(r"^(`{3,}|~{3,}).*?^\1[ \t]*$", re.M | re.S)
INLINE_CODE = re.compile(r"`[^`\n]*`")
LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
HEADING = re.compile(r"^#{1,6}[ \t]+(.+?)[ \t]*#*[ \t]*$", re.M)
COMMAND = re.compile(r"(?<![\w./-])cloudpose ([a-z][a-z0-9-]*)")
TABLE_ROW = re.compile(r"^\|\s*`cloudpose ([a-z][a-z0-9-]*)`", re.M)


def _text(page: Path) -> str:
    return page.read_text(encoding="utf-8")


def _prose(text: str) -> str:
    """The page without its code: links in a code block or span are not links."""
    return INLINE_CODE.sub("", FENCE.sub("", text))


def _code(text: str) -> list[str]:
    """Every fenced block and inline code span of the page."""
    blocks = [m.group(0) for m in FENCE.finditer(text)]
    return blocks + INLINE_CODE.findall(FENCE.sub("", text))


def _links(text: str) -> list[str]:
    """The relative targets of a page's markdown links (web and mail addresses left out)."""
    targets = LINK.findall(_prose(text))
    return [t for t in targets if "://" not in t and not t.startswith("mailto:")]


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading: markup dropped, lower case, punctuation out, spaces ``-``."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link keeps its text
    text = re.sub(r"[`*_]|<[^>]+>", "", text).strip().lower()
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def _anchors(text: str) -> set[str]:
    """The anchors of a markdown text's headings (a repeated one numbered as GitHub numbers it)."""
    seen: dict[str, int] = {}
    out = set()
    for heading in HEADING.findall(FENCE.sub("", text)):
        slug = _slug(heading)
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        out.add(slug if n == 0 else f"{slug}-{n}")
    return out


def _registered() -> set[str]:
    """The commands the CLI registers, read from the typer app itself."""
    return set(get_command(app).commands)


def test_the_docs_folder_has_its_index_and_the_commands_page():
    assert "README.md" in PAGES, "docs/README.md, the index of docs/, is missing"
    assert "commands.md" in PAGES, "docs/commands.md, the list of commands, is missing"


@pytest.mark.parametrize("name", PAGES)
def test_a_page_is_at_most_10_kb(name):
    size = len((DOCS / name).read_bytes())
    assert size <= MAX_BYTES, (
        f"docs/{name} is {size:,} bytes, over {MAX_BYTES:,}: cut its history and repetition "
        "(the reports keep the figures) or split it into two pages, each in docs/README.md"
    )


def test_the_index_links_every_page():
    linked = {t.split("#")[0] for t in _links(_text(DOCS / "README.md"))}
    missing = [name for name in PAGES if name != "README.md" and name not in linked]
    assert not missing, f"docs/README.md has no line linking: {', '.join(missing)}"


def test_the_commands_page_has_a_line_for_every_command():
    rows = set(TABLE_ROW.findall(_text(DOCS / "commands.md")))
    missing = sorted(
        name
        for name, command in get_command(app).commands.items()
        if not command.hidden and name not in rows
    )
    assert not missing, "docs/commands.md has no table row for: " + ", ".join(
        f"`cloudpose {name}`" for name in missing
    )


@pytest.mark.parametrize("name", PAGES)
def test_a_page_names_no_command_that_does_not_exist(name):
    """``cloudpose NAME`` in the code of docs/commands.md (and of every other page) is a command."""
    named = {n for code in _code(_text(DOCS / name)) for n in COMMAND.findall(code)}
    unknown = sorted(named - _registered())
    assert not unknown, f"docs/{name} names commands the CLI does not register: " + ", ".join(
        f"`cloudpose {command}`" for command in unknown
    )


CALL = re.compile(r"(?<![\w./-])cloudpose ([a-z][a-z0-9-]*)([^|;&`#\n]*)")
OPTION = re.compile(r"(?<![\w-])--[a-z][a-z0-9-]*")


def _options_quoted(text: str) -> set[tuple[str, str]]:
    """(command, option) for every ``--option`` that follows ``cloudpose COMMAND`` on one line
    of the page's code (a fenced line continued by a backslash joins the next)."""
    quoted = set()
    for code in _code(text):
        for line in code.replace("\\\n", " ").splitlines():
            for name, rest in CALL.findall(line):
                quoted |= {(name, option) for option in OPTION.findall(rest)}
    return quoted


def _options_of(name: str) -> set[str]:
    command = get_command(app).commands[name]
    names = {o for p in command.params for o in [*p.opts, *getattr(p, "secondary_opts", [])]}
    return names | {"--help"}


@pytest.mark.parametrize("name", [*PAGES, "../README.md"])
def test_a_page_quotes_only_options_its_commands_take(name):
    """``cloudpose COMMAND ... --option`` in the code of a page (and of the README): an option
    of COMMAND, so no page keeps an option the CLI renamed or removed."""
    stale = sorted(
        f"cloudpose {command} {option}"
        for command, option in _options_quoted(_text(DOCS / name))
        if command in _registered() and option not in _options_of(command)
    )
    assert not stale, f"docs/{name} quotes options the CLI does not take: " + ", ".join(stale)


def test_the_makefile_passes_only_options_its_commands_take():
    recipes = (ROOT / "Makefile").read_text().replace("$(CLI) ", "cloudpose ")
    stale = sorted(
        f"cloudpose {command} {option}"
        for command, option in _options_quoted(f"```\n{recipes}\n```")
        if command in _registered() and option not in _options_of(command)
    )
    assert not stale, "the Makefile passes options the CLI does not take: " + ", ".join(stale)


@pytest.mark.parametrize("name", PAGES)
def test_every_relative_link_resolves(name):
    page = DOCS / name
    broken = []
    for target in _links(_text(page)):
        path, _, anchor = target.partition("#")
        file = (page.parent / path).resolve() if path else page
        if not file.exists():
            broken.append(f"{target} (no such file: {file.relative_to(ROOT)})")
        elif anchor and file.suffix == ".md" and anchor not in _anchors(_text(file)):
            broken.append(f"{target} (no heading #{anchor} in {file.relative_to(ROOT)})")
    assert not broken, f"docs/{name} links to nothing: " + "; ".join(broken)


def test_the_checks_catch_what_they_guard_against():
    """The parsers on a page made up for the test (in memory: nothing is written)."""
    there = (
        "# A wider first radius (`--icp-radius 0.18`)\n## Two\n## Two\n```\n# not a heading\n```\n"
    )
    page = (
        "See [there](there.md#a-wider-first-radius---icp-radius-018), [twice](there.md#two-1),\n"
        "[gone](gone.md), [web](https://example.org/x.md) and `[code](not-a-link.md)`.\n\n"
        "```sh\ncloudpose nosuch --flag   # [in a fence](fence.md)\n```\n"
        "| `cloudpose run` | the main job |\n"
    )
    assert _links(page) == [
        "there.md#a-wider-first-radius---icp-radius-018",
        "there.md#two-1",
        "gone.md",
    ]
    assert _anchors(there) == {"a-wider-first-radius---icp-radius-018", "two", "two-1"}
    assert TABLE_ROW.findall(page) == ["run"]
    assert {n for code in _code(page) for n in COMMAND.findall(code)} == {"nosuch", "run"}
    assert COMMAND.findall("`python -m cloudpose.cli train` `cloudpose/studies/stress.py`") == []
    quoted = "`cloudpose run --preset smoke | tee x --y`\n```sh\ncloudpose ablate --group g \\\n  --seeds 2\n```\n"
    assert _options_quoted(quoted) == {
        ("run", "--preset"),
        ("ablate", "--group"),
        ("ablate", "--seeds"),
    }


GLOSSARY_TERMS = (
    "AD",
    "ADS",
    "AD AUC, ADS AUC",
    "ADS < 1 cm",
    "rot. < 10°",
    "mod sym",
    "pp",
    "supported",
    "holds / changes / undecided",
    "reuse N",
    "bleeding masks",
    "first radius",
    "18 cm first radius",
    "turned starts",
    "by the depth",
    "wide refinement",
    "ensemble",
    "development frames",
    "rendered twins",
    "no estimate",
)
"""The terms the front pages use that a reader cannot guess (issue 62)."""


def test_the_glossary_defines_each_term_and_the_front_pages_link_it():
    glossary = _text(DOCS / "glossary.md")
    undefined = [t for t in GLOSSARY_TERMS if f"**{t}**" not in glossary]
    assert not undefined, f"docs/glossary.md defines no **{undefined[0]}**"
    readme = _text(ROOT / "README.md")
    assert readme.count("](docs/glossary.md)") == 1, "the README links the glossary once"
    assert "](../docs/glossary.md)" in _text(ROOT / "reports" / "README.md")
