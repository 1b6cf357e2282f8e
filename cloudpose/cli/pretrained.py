"""Commands of the shipped network: show it at work (``showcase``), make it from a run (``ship``)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from cloudpose.cli.app import ProgressOpt, app, parse_refine, recorded_command, refine_option


@app.command()
def showcase(
    out: Annotated[
        Path,
        typer.Option(
            help="Folder for the synthetic frames, caches and the overlay.", file_okay=False
        ),
    ] = Path("runs/showcase"),
    synthetic_frames: Annotated[
        int, typer.Option(help="Synthetic test frames of the network's preset (0: none).")
    ] = 40,
    baseline: Annotated[
        str, typer.Option(help="Classical method beside it ('' for none).")
    ] = "fpfh",
    refine: Annotated[str | None, refine_option("showcase")] = None,
    progress: ProgressOpt = True,
) -> None:
    """The shipped network (`pretrained`) and FPFH + RANSAC on the same segments of the 61
    packaged real frames and the first synthetic test frames of its preset: each estimate, after
    the paper's ICP and after --refine; an overlay of one real frame. Trains nothing, logs
    nothing."""
    from cloudpose.studies.showcase import format_table, run_showcase

    recipe = parse_refine("showcase", refine).recipe
    shown = run_showcase(out, synthetic_frames, baseline, progress=progress, refine=recipe)
    typer.echo(shown.described)
    typer.echo(format_table(shown.table))
    typer.echo(f"overlay of a real frame, the network's poses refined ({recipe}): {shown.overlay}")


@app.command()
def ship(
    ctx: typer.Context,
    run: Annotated[str, typer.Option(help="Finished run: name (variant/preset/seedS) or id.")],
    name: Annotated[str, typer.Option(help="Shipped name it answers to.")] = "pretrained",
    out: Annotated[
        Path | None,
        typer.Option(help="Folder to write (default: the package's resources).", file_okay=False),
    ] = None,
    force: Annotated[
        bool,
        typer.Option(
            "--force",
            help="Replace the network that --name answers to in --out (its files are removed).",
        ),
    ] = False,
    reduce: Annotated[
        bool,
        typer.Option(
            "--reduce/--no-reduce",
            help="Float16, else float24 (3 bytes a weight), if every pose of the real "
            "development frames stays within 0.01 deg and 0.01 mm of float32's.",
        ),
    ] = True,
) -> None:
    """Package a finished run's network as a shipped one, VARIANT_PRESET_seedS.pt in --out
    (weights, config and a record of the run, its data key and metrics, with a checksum), from
    this folder's MLflow store. Names the run's preset and metrics first; a network the name
    answers to there already (the package's own, by default) is replaced only with --force,
    and its files are then removed."""
    from cloudpose.archive.checkpoints import PoseCheck
    from cloudpose.archive.ship import check_replace
    from cloudpose.archive.ship import ship as write
    from cloudpose.data.keys import DataKey
    from cloudpose.infer import load_checkpoint
    from cloudpose.store import tracking
    from cloudpose.store.pretrained import (
        SHIPPED,
        describe_record,
        describe_run,
        file_stem,
        shipped_folder,
    )
    from cloudpose.store.runs import display_name, local_checkpoint

    if name not in SHIPPED:
        raise ValueError(f"--name {name!r}: expected one of {', '.join(SHIPPED)}")
    folder = out or shipped_folder()
    client = tracking.setup(Path.cwd())
    with local_checkpoint(client, run) as (run_id, ckpt):
        if run_id is None:
            raise ValueError(f"--run {run!r} is a shipped network already; name a trained run")
        _, cfg = load_checkpoint(ckpt)
        record = client.get_run(run_id)
        run_name = display_name(cfg)
        stem = file_stem(run_name)
        incoming = describe_run(run_name, cfg.preset, record.data.metrics)
        replaced = check_replace(folder, stem, name, force=force, incoming=incoming)
        typer.echo(f"shipping {incoming}")
        typer.echo(f"as {name!r}: {folder / stem}.pt")
        if replaced is not None:
            typer.echo(f"replacing {describe_record(replaced)} ({replaced.with_suffix('.pt')})")
        path = write(
            ckpt,
            folder,
            stem,
            run_name=record.info.run_name,
            run_id=run_id,
            data_key=DataKey(record.data.tags.get("data", "")),
            fingerprint=record.data.tags.get("config", cfg.fingerprint()),
            metrics=record.data.metrics,
            command=recorded_command(ctx),
            check=PoseCheck(project_dir=Path.cwd()) if reduce else None,
            name=name,
            force=force,
        )
    typer.echo(f"wrote {path} and {path.with_suffix('.json')}")
    if replaced is not None and replaced.stem != stem:
        typer.echo(f"removed {replaced.with_suffix('.pt')} and {replaced}")
