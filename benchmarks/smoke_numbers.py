"""Every variant's smoke-preset numbers, to show a refactoring changes no result.

Runs ``cloudpose run --variant V --preset smoke --seed S`` for every registered variant in one
scratch project (the smoke data is made once) and writes each run's final metrics (training
loss, validation and test figures, with and without ICP) as one CSV row. ``compare`` reads two
such files and prints the largest difference per metric; exit 1 when one exceeds the tolerance.

    python benchmarks/smoke_numbers.py record before.csv            # with today's code
    PYTHONPATH=/path/to/other/checkout python benchmarks/smoke_numbers.py record after.csv
    python benchmarks/smoke_numbers.py compare before.csv after.csv

The runs are deterministic on one machine for a seed (the same code gives the same numbers to
the last digit); across machines or thread counts float sums may differ in the last bits, so
``compare`` takes a tolerance.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

import pandas as pd
import typer

app = typer.Typer(add_completion=False, no_args_is_help=True)


def _variants() -> list[str]:
    from cloudpose.registry import variants

    return list(variants())


@app.command()
def record(
    out: Path,
    seed: int = 1,
    variants: str = typer.Option("", help="Comma-separated variants; default all."),
    project: Path | None = typer.Option(None, help="Project folder to reuse (default a temp one)."),
) -> None:
    """Train + evaluate every variant on the smoke preset and write the metrics to OUT."""
    names = [v for v in variants.split(",") if v] or _variants()
    with tempfile.TemporaryDirectory(prefix="cloudpose-smoke-numbers-") as tmp:
        where = project or Path(tmp)
        where.mkdir(parents=True, exist_ok=True)
        env = {**os.environ, "MLFLOW_TRACKING_URI": f"sqlite:///{where / 'mlflow.db'}"}
        for name in names:
            cmd = [
                sys.executable,
                "-m",
                "cloudpose.cli",
                "run",
                "--variant",
                name,
                "--preset",
                "smoke",
                "--seed",
                str(seed),
                "--no-progress",
            ]
            typer.echo(f"{name}: {' '.join(cmd[2:])}")
            subprocess.run(cmd, cwd=where, env=env, check=True, capture_output=True)
        rows = _metrics(env["MLFLOW_TRACKING_URI"], names, seed)
    rows.to_csv(out, index=False)
    typer.echo(f"{len(rows)} variants -> {out}")


def _metrics(uri: str, names: list[str], seed: int) -> pd.DataFrame:
    import mlflow

    mlflow.set_tracking_uri(uri)
    runs = mlflow.search_runs(search_all_experiments=True, filter_string="tags.preset = 'smoke'")
    runs = runs[runs["tags.variant"].isin(names) & (runs["tags.seed"] == str(seed))]
    cols = sorted(
        c
        for c in runs.columns
        if c.startswith("metrics.") and "time" not in c and "per_s" not in c and "_ms" not in c
    )
    out = runs[["tags.variant", *cols]].rename(columns=lambda c: c.split(".", 1)[-1])
    return out.sort_values("variant").reset_index(drop=True)


@app.command()
def compare(before: Path, after: Path, tol: float = 1e-6) -> None:
    """Largest absolute difference per metric between two recordings; exit 1 above TOL."""
    a, b = (pd.read_csv(p).set_index("variant").sort_index() for p in (before, after))
    if list(a.index) != list(b.index):
        raise typer.BadParameter(f"variants differ: {list(a.index)} vs {list(b.index)}")
    common = [c for c in a.columns if c in b.columns]
    diff = (a[common] - b[common]).abs().max().sort_values(ascending=False)
    typer.echo(diff.head(15).to_string())
    worst = float(diff.max()) if len(diff) else 0.0
    typer.echo(f"{len(common)} metrics x {len(a)} variants; largest difference {worst:.3g}")
    raise typer.Exit(1 if worst > tol else 0)


if __name__ == "__main__":
    app()
