"""Commands that make and prepare data: render a synthetic set, export it as BOP, cache segments."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from cloudpose.cli.app import (
    DataOpt,
    PresetOpt,
    ProgressOpt,
    SetOpt,
    VariantOpt,
    app,
    config_of,
    recorded_command,
)
from cloudpose.config import Config
from cloudpose.registry import DEFAULT_PRESET


@app.command()
def synth(
    ctx: typer.Context,
    out: Annotated[
        Path | None,
        typer.Option(
            help="Output root (YCB-Video layout); default data/synth-seedS[-vV].",
            file_okay=False,
        ),
    ] = None,
    train_frames: Annotated[int, typer.Option(help="Training frames.")] = 800,
    test_frames: Annotated[int, typer.Option(help="Test frames, listed in keyframe.txt.")] = 150,
    seed: Annotated[int, typer.Option(help="Scene seed.")] = 0,
    noise: Annotated[bool, typer.Option("--noise/--no-noise", help="Depth-sensor noise.")] = True,
    uniform_rotation: Annotated[
        bool, typer.Option("--uniform-rotation/--table", help="Objects in full SO(3).")
    ] = False,
    synth_version: Annotated[
        int | None,
        typer.Option(help="Generator version (data.synth_version); default the newest."),
    ] = None,
    compare_real: Annotated[
        list[Path] | None,
        typer.Option(
            help="Render nothing; compare synthetic frames of versions 1 and 2 with these real "
            "frames (YCB-Video roots or depth.png + label.png folders; repeatable)."
        ),
    ] = None,
    compare_frames: Annotated[
        int, typer.Option(help="Synthetic test frames per version in --compare-real.")
    ] = 20,
    report: Annotated[
        Path | None, typer.Option(help="Write the --compare-real table here (Markdown).")
    ] = None,
    workers: Annotated[int | None, typer.Option(help="Processes (default: all cores).")] = None,
    progress: ProgressOpt = True,
) -> None:
    """Render a synthetic YCB-Video-layout dataset from the 21 real model point sets (resumable),
    or with --compare-real measure it against real frames."""
    from cloudpose.config import DataConfig

    if compare_real:
        from cloudpose.report.fidelity import compare_real as compare

        versions = (synth_version,) if synth_version else (1, 2)
        text = compare(compare_real, versions, compare_frames, seed, recorded_command(ctx))
        if report is not None:
            from cloudpose.files import atomic_text

            atomic_text(report, text)
            typer.echo(f"wrote {report}")
        else:
            typer.echo(text)
        return
    from cloudpose.data.dataset import synthetic_root
    from cloudpose.data.synth import synthesize

    version = {} if synth_version is None else {"synth_version": synth_version}
    cfg = DataConfig(synth_seed=seed, noise=noise, uniform_rotation=uniform_rotation, **version)
    out = out or synthetic_root(cfg, Path.cwd())
    s = synthesize(
        out,
        train_frames,
        test_frames,
        seed=seed,
        noise=noise,
        uniform_rotation=uniform_rotation,
        workers=workers,
        progress=progress,
        version=cfg.synth_version,
    )
    typer.echo(
        f"{out}: {s.frames_written} frames written, {s.frames_skipped} already there, "
        f"{s.seconds:.1f} s"
    )


@app.command()
def export(
    data: Annotated[
        Path, typer.Option(help="YCB-Video-layout root to export (real or synthetic).")
    ],
    out: Annotated[Path, typer.Option(help="New folder for the exported dataset.")],
    format_: Annotated[
        str, typer.Option("--format", help="Target layout: bop (BOP ycbv).")
    ] = "bop",
    frames: Annotated[
        str, typer.Option(help="Frames written to test/: keyframe, all, or an image set.")
    ] = "keyframe",
    train: Annotated[
        bool, typer.Option("--train/--no-train", help="Also write image_sets/train.txt frames.")
    ] = False,
    progress: ProgressOpt = True,
) -> None:
    """Write a YCB-Video-layout dataset in the BOP ycbv layout (reads back to the same segments)."""
    if format_ != "bop":
        raise ValueError(f"--format {format_!r}: expected bop")
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out}: is a file; expected a new (or empty) folder")
    from cloudpose.data.bop import export_bop

    s = export_bop(data, out, frames=frames, train=train, progress=progress)
    typer.echo(
        f"{s.root}: {s.frames} frames, {s.instances} instances, {s.targets} BOP19 targets "
        "(BOP ycbv layout)"
    )


@app.command()
def prepare(
    variant: VariantOpt = "shared-0",
    preset: PresetOpt = DEFAULT_PRESET,
    data: DataOpt = "",
    histogram: Annotated[
        Path | None, typer.Option(help="Also plot the test set's occlusion factors to this PNG.")
    ] = None,
    set_: SetOpt = None,
    seeds: Annotated[
        int,
        typer.Option(
            help="On-line presets: also synthesize the training chunks of seeds 1..S into the "
            "project's chunk store, which every variant of the preset then reads."
        ),
    ] = 0,
    workers: Annotated[
        int | None, typer.Option(help="Synthesis processes for --seeds (default: all cores).")
    ] = None,
    progress: ProgressOpt = True,
) -> None:
    """Synthesize (if needed) and cache the segments of a preset's train and test sets."""
    from cloudpose.data.dataset import prepare_data

    cfg = config_of(variant, preset, 1, data, set_)
    prepared = prepare_data(cfg.data, Path.cwd(), progress=progress)
    train_set, test_set = prepared.train, prepared.test
    typer.echo(f"train: {len(train_set)} segments, test: {len(test_set)} segments")
    if seeds > 0:
        _store_seeds(cfg, list(prepared.dataset.classes), seeds, workers, progress)
    if histogram is not None:
        from cloudpose.report.plots import occlusion_histogram

        title = (
            f"Occlusion factors of the {preset}-preset test set: {len(test_set)} instances\n"
            f"(cloudpose prepare --preset {preset} --histogram ...; data {prepared.data_key[:10]})"
        )
        counts = occlusion_histogram(test_set, histogram, title)
        typer.echo(f"occlusion bins (10% wide): {counts.tolist()} -> {histogram}")


@app.command("same-data")
def same_data(
    run: Annotated[
        str,
        typer.Option(
            help="A run of a preset, evaluated on its test set: name variant/preset/seedS, "
            "MLflow run id or run folder."
        ),
    ],
) -> None:
    """Whether a run's data is the data its preset makes here under another key (frames
    rendered on another CPU): its test instances against today's, point by point count. If so,
    prints the entries that cloudpose/resources/registry/same_data.toml needs for the runner
    and the reports to take the run's data as today's."""
    from cloudpose.store import tracking
    from cloudpose.store.rekey import SAME_POINT_SHARE, compare_test_segments
    from cloudpose.store.runs import resolve_run_id

    try:  # as every command that takes --run resolves it
        run_id = resolve_run_id(tracking.setup(Path.cwd()), run)
    except ValueError as exc:
        said = str(exc)
        raise ValueError(said if said.startswith("--run") else f"--run {run!r}: {said}") from exc
    c = compare_test_segments(run_id, Path.cwd())
    for kind, (old, new) in c.keys.items():
        typer.echo(f"{kind} key: the run's {old}, here {new}" + (" (equal)" if old == new else ""))
    typer.echo(
        f"test instances: the run's {c.instances[0]}, here {c.instances[1]}; {c.unmatched} in "
        f"one only, {c.other_class} of another class, {c.other_count} with another point count "
        f"(largest change {100 * c.largest_share:.3f}% of a segment's points; the same data "
        f"allows {100 * SAME_POINT_SHARE:.1f}%)"
    )
    if not c.same:
        typer.echo("not the same data: its runs stay apart from today's")
        raise typer.Exit(1)
    entry = c.entry(f"checked by cloudpose same-data --run {run}")
    if not entry:
        typer.echo("the same data, already under the same or listed keys: nothing to add")
        return
    typer.echo(f"the same data; add to cloudpose/resources/registry/same_data.toml:\n\n{entry}")


def _store_seeds(
    cfg: Config, class_names: list[str], seeds: int, workers: int | None, progress: bool
):
    from cloudpose.data.synth.chunks import ChunkStore
    from cloudpose.data.synth.online import store_chunks
    from cloudpose.train.loop import ONLINE_STORE_ENV, online_chunks, online_store_root

    if cfg.data.train_source != "online":
        raise ValueError(
            f"--seeds: preset {cfg.preset!r} trains on rendered frames (data.train_source="
            f"{cfg.data.train_source!r}); only an on-line preset has chunks to store"
        )
    root = online_store_root(Path.cwd())
    if root is None:
        raise ValueError(f"--seeds: the chunk store is switched off ({ONLINE_STORE_ENV}=0)")
    settings, chunk_size, n_chunks = online_chunks(cfg, class_names)
    for seed in range(1, seeds + 1):
        made = store_chunks(settings, seed, chunk_size, n_chunks, root, workers, progress)
        typer.echo(f"seed {seed}: {n_chunks} chunks of {chunk_size} segments ({made} made)")
    folder = ChunkStore(root, settings, chunk_size).folder
    size = sum(f.stat().st_size for f in folder.rglob("*.npz"))
    typer.echo(f"chunk store: {folder} ({size / 2**20:.0f} MiB)")
