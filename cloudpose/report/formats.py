"""What every report writes: a :class:`Table` as Markdown, LaTeX and CSV, under the
:class:`Provenance` line that says what made it (figures carry the same line).

Markdown is to read, LaTeX (booktabs) to paste, CSV (the numbers as numeric columns) to
compute with.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from cloudpose.files import atomic_text, atomic_write
from cloudpose.report.runs import RunSet

_COMMAND = re.compile(r"made by `[^`]*`", re.IGNORECASE)
"""The command in a provenance line (:meth:`Provenance.line`)."""


def same_but_command(old: str, new: str) -> bool:
    """Whether two renders of a report say the same but for the command their provenance
    line names."""
    return _COMMAND.sub("made by ``", old) == _COMMAND.sub("made by ``", new)


def write_text(path: Path, text: str) -> Path:
    """Write a report's text (atomically), leaving a file that holds it already but for the
    command in its provenance line: a command that renders the same numbers from the same runs
    changes no file, so ``git status`` shows only what a render changed."""
    path = Path(path)
    try:
        if path.is_file() and same_but_command(path.read_text(encoding="utf-8"), text):
            return path
    except (OSError, UnicodeDecodeError):
        pass  # unreadable: written anew
    return atomic_text(path, text)


def write_png(fig, path: Path, dpi: int, metadata: dict | None = None) -> Path:
    """Write a matplotlib figure as a PNG at ``dpi`` (atomically, its folder made; ``metadata``
    its text chunks, None: matplotlib's), then close it: the last step of every report figure
    (:func:`cloudpose.report.plots.finish` writes the ones with a provenance footer)."""
    import matplotlib.pyplot as plt  # loaded already by whoever drew ``fig``

    atomic_write(
        path, lambda tmp: fig.savefig(tmp, dpi=dpi, format="png", metadata=metadata), ".png"
    )
    plt.close(fig)
    return Path(path)


@dataclass(frozen=True)
class Provenance:
    """What made a report: the command, preset, data, seeds and code versions."""

    command: str
    preset: str
    data: str
    seeds: tuple[int, ...]
    commits: tuple[str, ...]
    renderer: str = ""

    @classmethod
    def of(cls, runs: RunSet, command: str, renderer: str = "") -> Provenance:
        return cls(
            command,
            runs.preset,
            runs.data_label(),
            tuple(runs.seeds),
            tuple(runs.commits),
            renderer,
        )

    def line(self) -> str:
        seeds = ", ".join(map(str, self.seeds)) or "none"
        commits = ", ".join(self.commits) or "none"
        text = (
            f"made by `{self.command}`; preset {self.preset}; data: {self.data}; "
            f"seeds {seeds}; code {commits} (git commit of the runs)"
        )
        if self.renderer:
            text += f"; rendered by code {self.renderer}"
        return text


@dataclass
class Table:
    """A rendered table.

    Attributes:
        name: file stem (``table3_shared_layers``).
        title: caption.
        header: one (group, column) pair per column; group "" for a single-level column.
        rows: formatted cells, one list per row; a row ``None`` is a section break.
        data: the numeric content for the CSV.
        notes: sentences printed under the table.
        text_cols: leading left-aligned columns (LaTeX); the rest are right-aligned numbers.
    """

    name: str
    title: str
    header: list[tuple[str, str]]
    rows: list[list[str] | None]
    data: pd.DataFrame
    notes: list[str] = field(default_factory=list)
    text_cols: int = 1

    def markdown(self, prov: Provenance) -> str:
        cols = [f"{g} ({c})" if g else c for g, c in self.header]
        lines = [f"# {self.title}", "", f"_{prov.line()}_", ""]
        lines.append("| " + " | ".join(cols) + " |")
        lines.append(
            "|" + "|".join("---" if i < self.text_cols else "---:" for i in range(len(cols))) + "|"
        )
        for row in self.rows:
            if row is not None:
                lines.append("| " + " | ".join(row) + " |")
        lines.append("")
        lines += [f"{n}  " for n in self.notes]
        return "\n".join(lines).rstrip() + "\n"

    def latex(self, prov: Provenance) -> str:
        n = len(self.header)
        align = "l" * self.text_cols + "r" * (n - self.text_cols)
        out = [
            f"% {prov.line()}",
            "% needs \\usepackage{booktabs,amssymb}",
            "\\begin{table}[t]",
            "\\centering",
            f"\\caption{{{_tex(self.title)}}}",
            f"\\begin{{tabular}}{{{align}}}",
            "\\toprule",
        ]
        if any(g for g, _ in self.header):
            top, rules, i = [], [], 0
            while i < n:
                g = self.header[i][0]
                j = i
                while j < n and self.header[j][0] == g:
                    j += 1
                if g:
                    top.append(f"\\multicolumn{{{j - i}}}{{c}}{{{_tex(g)}}}")
                    rules.append(f"\\cmidrule(lr){{{i + 1}-{j}}}")
                else:
                    top += [""] * (j - i)
                i = j
            out.append(" & ".join(top) + " \\\\")
            out.append(" ".join(rules))
        out.append(" & ".join(_tex(c) for _, c in self.header) + " \\\\")
        out.append("\\midrule")
        for row in self.rows:
            out.append("\\midrule" if row is None else " & ".join(_tex(c) for c in row) + " \\\\")
        out += ["\\bottomrule", "\\end{tabular}", "\\end{table}"]
        out += [f"% {n}" for n in self.notes]
        return "\n".join(out) + "\n"

    def csv(self, prov: Provenance) -> str:
        return f"# {prov.line()}\n" + self.data.to_csv(index=False, float_format="%.4f")

    def write(self, out_dir: Path, prov: Provenance) -> list[Path]:
        """Write ``{name}.md``, ``.tex`` and ``.csv`` into ``out_dir``; returns the paths."""
        out_dir.mkdir(parents=True, exist_ok=True)
        paths = []
        for ext, text in (
            ("md", self.markdown(prov)),
            ("tex", self.latex(prov)),
            ("csv", self.csv(prov)),
        ):
            paths.append(write_text(out_dir / f"{self.name}.{ext}", text))
        return paths


_TEX = {
    "\\": r"\textbackslash{}",
    "&": r"\&",
    "%": r"\%",
    "$": r"\$",
    "#": r"\#",
    "_": r"\_",
    "{": r"\{",
    "}": r"\}",
    "~": r"\textasciitilde{}",
    "^": r"\textasciicircum{}",
    "±": r"$\pm$",
    "<": r"$<$",
    ">": r"$>$",
    "°": r"$^\circ$",
    "–": "--",
    "✓": r"\checkmark",
}


def _tex(text: str) -> str:
    return "".join(_TEX.get(ch, ch) for ch in str(text))
