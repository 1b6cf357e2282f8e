"""Commands of the shipped network: show it at work (``showcase``), make it from a run (``ship``)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from cloudpose.cli.app import ProgressOpt, app, recorded_command


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
    progress: ProgressOpt = True,
) -> None:
    """The shipped network (`pretrained`) and FPFH + RANSAC, without and with ICP, on the 61
    packaged real frames and the first synthetic test frames of its preset; an overlay of one
    real frame. Trains nothing, logs nothing."""
    from cloudpose.showcase import format_table, run_showcase

    shown = run_showcase(out, synthetic_frames, baseline, progress=progress)
    typer.echo(shown.described)
    typer.echo(format_table(shown.table))
    typer.echo(f"overlay of a real frame with the network's poses (+ ICP): {shown.overlay}")


@app.command()
def ship(
    ctx: typer.Context,
    run: Annotated[str, typer.Option(help="Finished run: name (variant/preset/seedS) or id.")],
    name: Annotated[str, typer.Option(help="Shipped name it replaces.")] = "pretrained",
    out: Annotated[
        Path | None,
        typer.Option(help="Folder to write (default: the package's resources).", file_okay=False),
    ] = None,
    half: Annotated[
        bool,
        typer.Option(
            "--half/--no-half", help="Half precision if every pose stays within 0.01 deg."
        ),
    ] = True,
    progress: ProgressOpt = True,
) -> None:
    """Package a finished run's network as the shipped one (weights, config and a record of the
    run, its data key and metrics, with a checksum), from this folder's MLflow store."""
    from cloudpose.conventions import resource_path
    from cloudpose.data.dataset import folder_segments
    from cloudpose.data.keys import DataKey
    from cloudpose.data.layout import open_dataset, real_dev_root
    from cloudpose.infer import load_checkpoint
    from cloudpose.store import tracking
    from cloudpose.store.pretrained import SHIPPED
    from cloudpose.store.pretrained import ship as write
    from cloudpose.store.runs import local_checkpoint

    if name not in SHIPPED:
        raise ValueError(f"--name {name!r}: expected one of {', '.join(SHIPPED)}")
    client = tracking.setup(Path.cwd())
    with local_checkpoint(client, run) as (run_id, ckpt):
        if run_id is None:
            raise ValueError(f"--run {run!r} is a shipped network already; name a trained run")
        _, cfg = load_checkpoint(ckpt)
        record = client.get_run(run_id)
        segs = folder_segments(open_dataset(real_dev_root()), "all", cfg.data, Path.cwd(), progress)
        path = write(
            ckpt,
            out or resource_path("pretrained"),
            SHIPPED[name],
            run_name=record.info.run_name,
            run_id=run_id,
            data_key=DataKey(record.data.tags.get("data", "")),
            fingerprint=record.data.tags.get("config", cfg.fingerprint()),
            metrics=record.data.metrics,
            command=recorded_command(ctx),
            check_segments=[("real development frames", segs)],
            half=half,
        )
    typer.echo(f"wrote {path} and {path.with_suffix('.json')}")
