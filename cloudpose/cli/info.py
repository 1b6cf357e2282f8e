"""Commands that list what the suite holds: variants, presets, symmetry tables, an experiment log."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from cloudpose.cli.app import (
    app,
    recorded_command,
)


@app.command()
def variants() -> None:
    """Print the variant registry: name, groups, what it changes, parameter count."""
    from cloudpose.models import variant_table

    rows = variant_table()
    wn = max(len("variant"), *(len(r["name"]) for r in rows))
    wg = max(len("groups"), *(len(",".join(r["groups"])) for r in rows))
    header = f"{'variant':<{wn}} {'groups':<{wg}} {'parameters':>11}  changes"
    typer.echo(header)
    typer.echo("-" * len(header))
    for r in rows:
        groups = ",".join(r["groups"])
        typer.echo(f"{r['name']:<{wn}} {groups:<{wg}} {r['parameters']:>11,}  {r['changes']}")


@app.command()
def presets() -> None:
    """Print the presets (cloudpose/resources/registry/presets.toml) with what each is for."""
    from cloudpose.registry import presets as registered

    found = registered()
    width = max(map(len, found), default=0)
    for name, why in found.items():
        typer.echo(f"{name:<{width}}  {why}")


@app.command()
def symmetries(
    write: Annotated[
        bool, typer.Option("--write/--check", help="Rewrite the packaged table, or compare.")
    ] = False,
    bop: Annotated[
        Path | None,
        typer.Option(
            help="Also compare with a BOP ycbv root's models/models_info.json (or that file)."
        ),
    ] = None,
    table_version: Annotated[
        int,
        typer.Option(
            "--table",
            help="Table version (a run's loss.symmetry_table): 1 (turns about the model axes "
            "only; the committed cpu results used it) or 2 (also about the points' principal "
            "axes and centroid; the current one).",
        ),
    ] = 2,
) -> None:
    """Print each class's symmetries as seen in depth (the table the losses and metrics use)."""
    from cloudpose.geometry.symmetry import bop_disagreements_at, symmetry_from_json, sync_table

    synced = sync_table(table_version, write)
    for name, entry in synced.table["classes"].items():
        typer.echo(f"{name:<24} {symmetry_from_json(entry).describe()}")
    typer.echo(f"{'wrote' if write else 'checked'} {synced.path}: matches the models")
    if bop is not None:
        path, diffs = bop_disagreements_at(bop, list(synced.table["classes"]))
        for line in diffs:
            typer.echo(f"differs from BOP: {line}")
        typer.echo(f"{path}: {len(diffs)} classes differ from the table")


@app.command()
def experiments(
    ctx: typer.Context,
    group: Annotated[
        list[str], typer.Option(help="Group whose MLflow experiment to list (repeat for several).")
    ],
    out: Annotated[
        Path, typer.Option(help="Markdown file to write (the values go beside it as .csv).")
    ],
    against: Annotated[
        str | None,
        typer.Option(help="List changes relative to this preset (default: each run's own)."),
    ] = None,
    preset: Annotated[
        str | None, typer.Option(help="List only the runs of this preset (default: every run).")
    ] = None,
) -> None:
    """An experiment log: every finished run of a group, its overrides and its rotation errors."""
    from cloudpose.report.experiments import write_log

    path = write_log(group, out, recorded_command(ctx), against=against, preset=preset)
    typer.echo(f"wrote {path}")
