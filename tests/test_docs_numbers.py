"""Every figure the hand-written pages quote is one their sources hold (README.md,
reports/README.md and every docs/ page but design.md, whose figures are the method's constants),
and every local link of the hand-written pages leads somewhere.

A page is read in blocks (paragraphs, tables, list items); a block that quotes a decimal figure
must link the report it comes from, in the block or in the caption just before it, and each
figure must be one of that report's (as it prints it). A mean with its spread (``91.3 ± 0.2``,
``+-`` too) must be one the report prints together, an interval (``+1.9 [+1.7, +2.2]``) one row
of it, and a whole number in a table cell (seeds, steps), or one with its unit in a block that
quotes results (``264 instances``, ``~106 ms``), one the report holds. A verdict table
that ``cloudpose report --readme`` renders between ``<!-- verdicts PRESET -->`` markers comes
from that preset's ``claims.md``, and the verdict counts the pages write out are counted from
the claims they link. A figure that drifts from its source, or one quoted without a source,
fails here, naming the page, the line and the figure.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
NOT_RESULTS = {
    "docs/design.md": "the method's constants (radii, learning rate, BN momentum, the AUC's "
    "range), the paper's and presets.toml's: no measured figure, no report linked",
}
"""Hand-written pages whose decimal figures are not results, and why."""

PAGES = [
    "README.md",
    "reports/README.md",
    *sorted(
        name
        for p in (ROOT / "docs").glob("*.md")
        if (name := str(p.relative_to(ROOT))) not in NOT_RESULTS
    ),
]
"""The pages whose figures :func:`problems` checks against the reports they link."""

LINKED_PAGES = sorted(
    str(p.relative_to(ROOT))
    for p in [ROOT / "README.md", *(ROOT / "docs").glob("*.md"), *(ROOT / "reports").rglob("*.md")]
    if "mlflow-store" not in p.parts  # a committed store's artifacts, as the runs logged them
)
"""The pages whose links :func:`test_every_local_link_resolves` follows: the hand-written ones
and the rendered reports beside them."""

RENDERED = re.compile(r"<!-- (/?)verdicts (\S+) -->")

FIGURE = re.compile(r"(?<![\w.\-/])\d+\.\d+(?![\w/]|\.\d)")
"""A decimal figure (91.3, 0.2), not part of a version, an address, a name or a path."""

SPREAD = re.compile(r"(?<![\w.])(\d+\.\d+) ?(?:±|\+-) ?(\d+\.\d+)")
"""A mean with its spread, ``91.3 ± 0.2`` or ``91.3 +- 0.2``."""

INTERVAL = re.compile(r"(?<![\w.])([+-]?\d+\.\d+) \[([+-]?\d+\.\d+), ([+-]?\d+\.\d+)\]")
"""A difference with its interval, ``+1.9 [+1.7, +2.2]``."""

COUNTED = re.compile(
    r"(?<![\w.,\-/])(~?)(\d{1,3}(?:,\d{3})+|\d+)(?![\d,.]\d) ?(ms|instances|frames|object poses)\b"
)
"""A whole number with what it counts or measures (``~106 ms``, ``264 instances``), checked in a
block that quotes results: with ``~`` any figure of the source that starts with it (106.6) holds
it; the source may print it without the thousands comma."""

WHOLE = re.compile(r"\d{1,3}(?:,\d{3})+|\d+")
"""A whole number as a table cell prints it (10, 4,096)."""

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
        if path.is_file() and path.suffix in {".md", ".csv", ".tex", ".toml"}:
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
        if not figures and not any(WHOLE.fullmatch(c) for c in _cells(CODE.sub("", block))):
            continue
        sources = _sources(block, page)
        sources += [claims for a, b, claims in rendered if a <= line < b]
        if not sources and k and blocks[k - 1][1].lstrip().startswith(("Sources", "From")):
            sources = _sources(blocks[k - 1][1], page)
        if not sources and not figures:
            continue  # a table of counts that cites nothing (options, defaults) is not a result
        if not sources:
            out.append(f"{name}:{line}: {figures[:4]} quoted without a linked report")
            continue
        held = set().union(*(_figures_of(p) for p in sources))
        missing = [f for f in figures if f not in held]
        missing += _compound_missing(CODE.sub("", block), sources)
        if missing:
            shown = ", ".join(p.name for p in sources)
            out.append(f"{name}:{line}: {missing} not in {shown}")
    return out


def _cells(block: str) -> list[str]:
    """The cells of a block's table rows, stripped."""
    return [
        cell.strip()
        for row in block.splitlines()
        if row.lstrip().startswith("|")
        for cell in row.strip().strip("|").split("|")
    ]


def _compound_missing(block: str, sources: list[Path]) -> list[str]:
    """The spreads, intervals and table whole numbers of ``block`` its sources do not hold as
    written: a mean with another figure's spread, an interval's ends from two rows, a count of
    seeds the table does not have."""
    lines = [
        line.replace("+-", "±")
        for p in sources
        for line in p.read_text(encoding="utf-8").splitlines()
    ]
    out = [
        f"{mean} ± {sd}"
        for mean, sd in SPREAD.findall(block)
        if not any(f"{mean} ± {sd}" in line for line in lines)
    ]
    out += [
        f"{d} [{lo}, {hi}]"
        for d, lo, hi in INTERVAL.findall(block)
        if not any(d in line and f"[{lo}, {hi}]" in line for line in lines)
    ]
    text = "\n".join(lines)
    for about, number, unit in COUNTED.findall(block):
        digits = ",?".join(number.replace(",", ""))  # 2,053 as the source prints it, or 2053
        after = r"(?:\.\d+)?" if about else ""
        if not re.search(rf"(?<![\w.,]){digits}{after}(?![\w]|[.,]\d)", text):
            out.append(f"{about}{number} {unit}")
    for cell in _cells(block):
        if WHOLE.fullmatch(cell):
            alone = re.compile(rf"(?<![\w.,]){re.escape(cell)}(?![\w]|[.,]\d)")
            if not any(alone.search(line) for line in lines):
                out.append(cell)
    return out


@pytest.mark.parametrize("page_name", PAGES)
def test_every_quoted_figure_is_in_the_report_it_links(page_name):
    found = problems(ROOT / page_name)
    assert not found, "\n".join(found)


def test_the_checker_catches_a_drifted_figure_and_one_without_a_source(tmp_path):
    (tmp_path / "table.md").write_text(
        "| shared-0 | 91.3 ± 0.2 | 10 | 1,024 |\n| a | +1.9 | [+1.7, +2.2] |\n"
        "| b | +0.5 | [-0.2, +1.2] |\n| l2 | 90.0 ± 0.3 | 3 | 0.2 |\n"
    )
    page = tmp_path / "page.md"
    page.write_text(
        "Sources: [Table I](table.md).\n\n| method | ADS |\n|---|---:|\n| ours | 91.4 ± 0.2 |\n"
        "| ours + ICP | 91.3 ± 0.2 |\n\nNo source here: 12.5.\n\n- an item, [linked](table.md): 91.3\n"
        "\n<!-- verdicts cpu-online -->\n| claim | ADS AUC |\n|---|---|\n| a | x [+0.8] |\n"
        "| b | y [+99.9] |\n<!-- /verdicts cpu-online -->\n\nAfter the block: 0.8.\n\n"
        "[Its rows](table.md): 91.3 +- 0.3 (each figure there, not together), +1.9 [+1.7, +2.2]\n"
        "and +1.9 [+1.7, +1.2] (ends from two rows).\n\nFrom [it](table.md):\n\n"
        "| seeds | points | steps |\n|---:|---:|---:|\n| 10 | 1,024 | 4,096 |\n| 3 | 1 | 024 |\n\n"
        "[It](table.md): 90.0 ± 0.3 at ~91 ms and 1024 frames, not 12 instances nor ~92 ms.\n"
    )
    assert problems(page) == [
        "page.md:3: ['91.4', '91.4 ± 0.2'] not in table.md",
        "page.md:8: ['12.5'] quoted without a linked report",
        "page.md:12: ['99.9'] not in claims.md",  # a rendered table is the preset's claims.md
        "page.md:19: ['0.8'] quoted without a linked report",
        "page.md:21: ['91.3 ± 0.3', '+1.9 [+1.7, +1.2]'] not in table.md",
        "page.md:26: ['4,096', '1', '024'] not in table.md",  # 1 and 024 are parts of 1,024
        "page.md:31: ['12 instances', '~92 ms'] not in table.md",
    ]
    assert FIGURE.findall("v2.13.0, 91.3 ± 0.2, shared-1.42x, 0.18 m, 127.0.0.1") == [
        "91.3",
        "0.2",
        "0.18",
    ]


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


def _first_table_after(text: str, heading: str) -> tuple[list[str], list[list[str]], int]:
    """(header cells, body rows' cells, line after the table) of the first table below
    ``heading``."""
    lines = text.splitlines()
    start = lines.index(heading)
    at = next(i for i in range(start, len(lines)) if lines[i].startswith("|"))
    rows = []
    while at < len(lines) and lines[at].startswith("|"):
        rows.append([c.strip() for c in lines[at].strip().strip("|").split("|")])
        at += 1
    return rows[0], rows[2:], at


def test_the_readme_headline_compares_like_with_like():
    """The headline table sets the paper's plain metrics beside ours plain (AD AUC included),
    names each row's test data, and marks the measure the paper lacks (issue 62)."""
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    header, rows, after = _first_table_after(readme, "## Results")
    for column in ("test data", "AD AUC", "ADS AUC", "ADS < 1 cm", "rot. < 10°"):
        assert column in header, f"the headline has no plain column {column!r}: {header}"
    ours_only = [i for i, c in enumerate(header) if "mod sym" in c]
    assert ours_only and all("†" in header[i] for i in ours_only), header
    assert readme.splitlines()[after + 1].startswith("† a measure the paper lacks")
    data = header.index("test data")
    assert {row[data] for row in rows} <= {"real", "synthetic"}, rows
    paper = [row for row in rows if row[0].startswith("paper")]
    ours = [row for row in rows if row[0].startswith("ours")]
    assert paper and ours
    assert all(row[i] == "–" for row in paper for i in ours_only), "the paper has no mod sym"
    for column in ("AD AUC", "rot. < 10°"):  # plain beside plain, in one column
        i = header.index(column)
        assert FIGURE.search(paper[0][i]) and FIGURE.search(ours[0][i]), (column, rows)


def _glance_counts(claims: Path) -> dict[str, int]:
    """Verdicts of the rows with a paper figure (a ``[+x]`` in the cell) in claims.md's "At a
    glance" table, by verdict."""
    text = claims.read_text(encoding="utf-8")
    glance = text.split("## At a glance", 1)[1].split("\n## ", 1)[0]
    counts: dict[str, int] = {}
    for row in glance.splitlines():
        if not row.startswith("| ") or row.startswith("| claim"):
            continue
        for cell in row.strip().strip("|").split("|")[1:]:
            if "[" in cell:
                verdict = cell.split("[")[0].replace("*", "").strip()
                counts[verdict] = counts.get(verdict, 0) + 1
    return counts


def test_the_verdict_counts_written_out_are_those_of_the_claims():
    """reports/README.md's "What it says" counts the rows with a paper figure by verdict, in
    words: the counts of its claims.md (issue 62 found them off by one each)."""
    text = " ".join((ROOT / "reports" / "README.md").read_text(encoding="utf-8").split())
    found = re.search(
        r"Of (\d+) rows, (\d+) with a paper figure: (\d+) smaller than the paper's, (\d+) "
        r"equivalent, (\d+) contradicted, (\d+) larger than the paper's and (\d+) not resolved",
        text,
    )
    assert found, "reports/README.md no longer counts the rows with a paper figure"
    total, with_paper, smaller, equivalent, contradicted, larger, unresolved = map(
        int, found.groups()
    )
    claims = ROOT / "reports" / "cpu-online" / "claims.md"
    counts = _glance_counts(claims)
    assert {
        "smaller": smaller,
        "equivalent": equivalent,
        "contradicted": contradicted,
        "larger": larger,
        "not resolved": unresolved,
    } == counts
    summary = re.search(r"\(of (\d+); (\d+) rows have a paper figure\)", claims.read_text())
    assert summary and (total, with_paper) == tuple(map(int, summary.groups()))
    assert with_paper == sum(counts.values())
    rows = re.search(r"The (\d+) rows not resolved", text)
    assert rows and int(rows.group(1)) == unresolved


def test_the_results_page_stays_short_and_lists_its_sections():
    """reports/README.md: at most ~15 KB, its "Contents" linking every section, each link a
    heading of the page (issue 62)."""
    from tests.test_docs_pages import _anchors, _slug

    text = (ROOT / "reports" / "README.md").read_text(encoding="utf-8")
    assert len(text.encode()) <= 15 * 1024
    contents = text.split("Contents:", 1)[1].split("\n## ", 1)[0]
    linked = set(re.findall(r"\]\(#([^)]+)\)", contents))
    sections = {_slug(h) for h in re.findall(r"^## (.+)$", text, re.M)}
    assert sections <= linked, f"not in the contents: {sorted(sections - linked)}"
    assert linked <= _anchors(text), f"contents link no heading: {sorted(linked - _anchors(text))}"
