"""Every figure the front pages quote is one their sources hold (README.md, reports/README.md),
and every local link of the hand-written pages leads somewhere.

A page is read in blocks (paragraphs, tables, list items); a block that quotes a decimal figure
must link the report it comes from, in the block or in the caption just before it, and each
figure must be one of that report's (as it prints it). A verdict table that ``cloudpose report
--readme`` renders between ``<!-- verdicts PRESET -->`` markers comes from that preset's
``claims.md``. A figure that drifts from its source, or one quoted without a source, fails here,
naming the page, the line and the figure.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = ["README.md", "reports/README.md"]

LINKED_PAGES = sorted(
    str(p.relative_to(ROOT))
    for p in [ROOT / "README.md", *(ROOT / "docs").glob("*.md"), *(ROOT / "reports").rglob("*.md")]
    if "mlflow-store" not in p.parts  # a committed store's artifacts, as the runs logged them
)
"""The pages whose links :func:`test_every_local_link_resolves` follows: the hand-written ones
and the rendered reports beside them."""

RENDERED = re.compile(r"<!-- (/?)verdicts (\S+) -->")

FIGURE = re.compile(r"(?<![\w.\-/])\d+\.\d+(?![\w/])")
"""A decimal figure (91.3, 0.2), not part of a version, a name or a path."""

LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")


def _blocks(text: str) -> list[tuple[int, str]]:
    """(first line number, text) of each block: runs of lines between blank lines, each list
    item a block of its own; code fences left out."""
    out: list[tuple[int, str]] = []
    lines, start, fence = [], 0, False
    for i, line in enumerate(text.splitlines(), 1):
        if line.startswith("```"):
            fence = not fence
            continue
        if fence:
            continue
        item = re.match(r"\s*[-*] ", line) is not None
        if not line.strip() or item:
            if lines:
                out.append((start, "\n".join(lines)))
            lines, start = ([line], i) if item else ([], 0)
            continue
        if not lines:
            start = i
        lines.append(line)
    if lines:
        out.append((start, "\n".join(lines)))
    return out


def _sources(block: str, page: Path) -> list[Path]:
    found = []
    for target in LINK.findall(block):
        if "://" in target:
            continue
        path = (page.parent / target).resolve()
        if path.is_file() and path.suffix in {".md", ".csv", ".tex"}:
            found.append(path)
    return found


CODE = re.compile(r"`[^`]*`")
"""Inline code: commands and options (``--icp-radius 0.18``) are not quoted figures."""


def _figures_of(path: Path) -> set[str]:
    return set(FIGURE.findall(path.read_text(encoding="utf-8")))


def _rendered(text: str) -> list[tuple[int, int, Path]]:
    """(first line, last line, claims.md) of each verdict table ``cloudpose report --readme``
    renders into ``text``."""
    out, open_at = [], {}
    for i, line in enumerate(text.splitlines(), 1):
        m = RENDERED.fullmatch(line.strip())
        if m and not m.group(1):
            open_at[m.group(2)] = i
        elif m and m.group(2) in open_at:
            out.append((open_at.pop(m.group(2)), i, ROOT / "reports" / m.group(2) / "claims.md"))
    return out


def problems(page: Path) -> list[str]:
    """One line per figure of ``page`` that its linked reports do not hold, or that it
    quotes without linking one."""
    text = page.read_text(encoding="utf-8")
    blocks, rendered = _blocks(text), _rendered(text)
    name = str(page.relative_to(ROOT)) if page.is_relative_to(ROOT) else page.name
    out = []
    for k, (line, block) in enumerate(blocks):
        figures = FIGURE.findall(CODE.sub("", block))
        if not figures:
            continue
        sources = _sources(block, page)
        sources += [claims for a, b, claims in rendered if a <= line < b]
        if not sources and k and blocks[k - 1][1].lstrip().startswith(("Sources", "From")):
            sources = _sources(blocks[k - 1][1], page)
        if not sources:
            out.append(f"{name}:{line}: {figures[:4]} quoted without a linked report")
            continue
        held = set().union(*(_figures_of(p) for p in sources))
        missing = [f for f in figures if f not in held]
        if missing:
            shown = ", ".join(p.name for p in sources)
            out.append(f"{name}:{line}: {missing} not in {shown}")
    return out


@pytest.mark.parametrize("page_name", PAGES)
def test_every_quoted_figure_is_in_the_report_it_links(page_name):
    found = problems(ROOT / page_name)
    assert not found, "\n".join(found)


def test_the_checker_catches_a_drifted_figure_and_one_without_a_source(tmp_path):
    (tmp_path / "table.md").write_text("| shared-0 | 91.3 ± 0.2 |\n")
    page = tmp_path / "page.md"
    page.write_text(
        "Sources: [Table I](table.md).\n\n| method | ADS |\n|---|---:|\n| ours | 91.4 ± 0.2 |\n"
        "| ours + ICP | 91.3 ± 0.2 |\n\nNo source here: 12.5.\n\n- an item, [linked](table.md): 91.3\n"
        "\n<!-- verdicts cpu-online -->\n| claim | ADS AUC |\n|---|---|\n| a | x [+0.8] |\n"
        "| b | y [+99.9] |\n<!-- /verdicts cpu-online -->\n\nAfter the block: 0.8.\n"
    )
    assert problems(page) == [
        "page.md:3: ['91.4'] not in table.md",
        "page.md:8: ['12.5'] quoted without a linked report",
        "page.md:12: ['99.9'] not in claims.md",  # a rendered table is the preset's claims.md
        "page.md:19: ['0.8'] quoted without a linked report",
    ]
    assert FIGURE.findall("v2.13.0, 91.3 ± 0.2, shared-1.42x, 0.18 m") == ["91.3", "0.2", "0.18"]


def test_the_readme_verdict_counts_are_those_of_the_claims_it_links():
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    lines = [line for line in readme.splitlines() if line.startswith("Verdicts: ")]
    assert len(lines) == 1, "README.md quotes the verdict counts once, on a line 'Verdicts: ...'"
    claims = (ROOT / "reports" / "cpu-online" / "claims.md").read_text(encoding="utf-8")
    assert f"Summary: {lines[0].removeprefix('Verdicts: ')}" in claims


def test_the_readme_budget_counts_are_those_of_the_4x_claims():
    readme = " ".join((ROOT / "README.md").read_text(encoding="utf-8").split())
    quoted = re.findall(r"holds: (\d+); changes: (\d+); undecided: (\d+), of (\d+)", readme)
    assert len(quoted) == 1, "README.md quotes the across-budget counts once"
    claims = (ROOT / "reports" / "cpu-online-4x" / "claims.md").read_text(encoding="utf-8")
    on_reports = " ".join((ROOT / "reports" / "README.md").read_text(encoding="utf-8").split())
    quoted = [q[:3] for q in quoted]
    quoted += re.findall(r"(\d+) hold, (\d+) change and (\d+) are undecided", on_reports)
    held = re.findall(
        r"Summary: holds: (\d+); changes: (\d+); undecided: (\d+) \(of (\d+)\)", claims
    )
    assert len(quoted) == 2 and {q for q in quoted} == {h[:3] for h in held}, (quoted, held)


def test_the_readme_stays_short_and_opens_with_its_commands():
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(readme.encode()) <= 12 * 1024
    first = "\n".join(readme.splitlines()[:60])
    for command in (
        "make setup",
        "make test-all",
        "make ablation-shared",
        "make occlusion-report",
        "make mlflow-ui",
        "](",
    ):
        assert command in first, command
    assert "![" in first, "a picture in the first screen"


def test_the_docs_index_lists_every_docs_file():
    index = (ROOT / "docs" / "README.md").read_text(encoding="utf-8")
    listed = set(re.findall(r"\]\(([\w-]+\.md)\)", index))
    present = {p.name for p in (ROOT / "docs").glob("*.md")} - {"README.md"}
    assert listed == present


@pytest.mark.parametrize("page_name", LINKED_PAGES)
def test_every_local_link_resolves(page_name):
    page = ROOT / page_name
    text = page.read_text(encoding="utf-8")
    targets = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)
    broken = [t for t in targets if "://" not in t and not (page.parent / t).exists()]
    assert not broken, f"{page_name}: links to nothing: {broken}"
