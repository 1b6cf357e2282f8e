"""The ``cloudpose`` command line: every stage of the pipeline, and the ablation suite.

The Makefile's targets are thin calls of these commands.

One file over ~450 lines on purpose: each command is a short Typer function that parses its
options and calls the library; split across files they would only add imports.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import click
import typer
from typer.core import TyperGroup

from cloudpose.config import DEFAULT_PRESET


class _Commands(TyperGroup):
    """Every command with one error handler: bad input is one line on stderr, exit 2.

    The library raises ``ValueError`` / ``FileNotFoundError`` naming the file, field or name
    and what was expected (:class:`~cloudpose.tracking.StoreError` for a store that cannot be
    opened, ``ConnectionError`` for a service such as Ray that cannot be reached);
    ``cloudpose --debug ...`` shows the traceback instead.
    """

    def invoke(self, ctx: click.Context):
        from cloudpose.tracking import StoreError

        try:
            return super().invoke(ctx)
        except (ValueError, FileNotFoundError, ConnectionError, StoreError) as exc:
            if _DEBUG:
                raise
            message = " ".join(str(exc).split()) or type(exc).__name__
            typer.secho(f"error: {message}", fg=typer.colors.RED, err=True)
            raise typer.Exit(2) from None

    def get_command(self, ctx: click.Context, cmd_name: str):
        cmd = super().get_command(ctx, cmd_name)
        if cmd is not None:
            _help_layout(cmd, ctx)
        return cmd

    def format_help(self, ctx: click.Context, formatter) -> None:
        _help_layout(self, ctx)
        return super().format_help(ctx, formatter)


PIPED_HELP_WIDTH = 120
"""Columns of ``--help`` when the output is not a terminal and COLUMNS is unset (rich's
default there, 80, leaves the help column so narrow that it cuts words with an ellipsis)."""


def _help_layout(cmd, ctx: click.Context) -> None:
    """Help as it reads in a terminal, also when piped; flags shown without a value type.

    Typer shows every option's type, flags too (``--debug <bool>``), as if a flag took a
    value; a flag gets an empty metavar here, so its help shows none.
    """
    import os
    import sys

    from typer import rich_utils

    if rich_utils.MAX_WIDTH is None and "COLUMNS" not in os.environ and not sys.stdout.isatty():
        rich_utils.MAX_WIDTH = PIPED_HELP_WIDTH
    for p in cmd.get_params(ctx):
        if getattr(p, "is_flag", False) and p.metavar is None:
            p.metavar = ""


app = typer.Typer(
    cls=_Commands,
    help="Depth-only 6D pose regression on point clouds (Gao et al., ICRA 2020): "
    "synthetic data, training, ICP, evaluation and the paper's ablations.",
    no_args_is_help=True,
    pretty_exceptions_show_locals=False,
)

VariantOpt = Annotated[str, typer.Option(help="Variant name (`cloudpose variants` lists them).")]
PresetOpt = Annotated[
    str,
    typer.Option(help="Preset (`cloudpose presets` lists them; ablations/presets.toml)."),
]
SeedOpt = Annotated[int, typer.Option(help="Training seed.")]
DataOpt = Annotated[
    str,
    typer.Option(
        "--data", help="Dataset root, YCB-Video or BOP ycbv layout; empty = the synthetic default."
    ),
]
DeviceOpt = Annotated[
    str, typer.Option(help="auto (CUDA when available, as in training), cpu or cuda.")
]
ProgressOpt = Annotated[bool, typer.Option("--progress/--no-progress", help="Progress bars.")]
FramesOpt = Annotated[
    str,
    typer.Option(help="With --data: keyframe (BOP: the BOP19 test targets), all, or an image set."),
]
DryRunOpt = Annotated[
    bool, typer.Option("--dry-run", help="Print the plan (frames, runs, time) and stop.")
]
OutOpt = Annotated[
    Path | None,
    typer.Option(
        help="Reports folder; default reports/PRESET, or runs/reports/PRESET in a checkout that "
        "commits no reports of PRESET."
    ),
]
SetOpt = Annotated[
    list[str] | None,
    typer.Option(
        "--set",
        help="Override one config field, section.field=value (TOML value; repeatable), "
        "e.g. --set model.rotation_input=centred --set train.epochs=3. An override is another "
        "config: its own run folder and MLflow run.",
    ),
]


def _group_names() -> str:
    """The registered ablation groups, for help texts: ``shared, rotation, loss or symmetry``."""
    from cloudpose.config import groups

    names = list(groups())
    return ", ".join(names[:-1]) + " or " + names[-1] if len(names) > 1 else "".join(names)


_DEBUG = False
"""``--debug``: bad input raises with its traceback instead of the one-line error."""


@app.callback()
def _main(
    debug: Annotated[
        bool, typer.Option("--debug", help="Show the traceback of an error (default: one line).")
    ] = False,
) -> None:
    global _DEBUG
    _DEBUG = debug
    import warnings

    # "warning: message", without the source line that Python prints beneath it
    warnings.formatwarning = lambda message, *args, **kwargs: f"warning: {message}\n"
    from cloudpose import runtime

    runtime.reexec_with_allocator()
    runtime.configure_threads()


def recorded_command(ctx: typer.Context) -> str:
    """The running command as the user gave it (the options they set, in a canonical order):
    the provenance line written beside a report or figure. Read from the command's context, so
    it is the same however the command was started (console script, ``python -m``, a test)."""
    import shlex

    parts = ["cloudpose", *ctx.command_path.split()[1:]]
    for p in ctx.command.params:
        value = ctx.params.get(p.name)
        source = ctx.get_parameter_source(p.name)
        given = source is not None and source.name != "DEFAULT"
        if p.param_type_name != "option" or value is None or not given:
            continue
        if p.is_flag:
            parts.append(p.opts[0] if value else (p.secondary_opts or p.opts)[0])
            continue
        for v in value if p.multiple else [value]:
            parts += [p.opts[0], str(v)]
    return shlex.join(parts)


def _config(variant: str, preset: str, seed: int, data: str = "", sets=None, **train):
    from cloudpose.config import parse_overrides, resolve

    overrides: dict = parse_overrides(sets)
    if data:
        overrides.setdefault("data", {})["root"] = data
    train = {k: v for k, v in train.items() if v is not None}
    if train:
        overrides.setdefault("train", {}).update(train)
    return resolve(variant, preset, seed, overrides or None)


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
    """Print the presets (ablations/presets.toml) with what each is for."""
    from cloudpose.config import presets as registered

    for name, why in registered().items():
        typer.echo(f"{name:<14} {why}")


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
            "--table", help="Table version (a run's loss.symmetry_table): 1 or 2 (package doc)."
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


@app.command()
def synth(
    ctx: typer.Context,
    out: Annotated[
        Path | None,
        typer.Option(help="Output root (YCB-Video layout); default data/synth-seedS[-vV]."),
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
    progress: ProgressOpt = True,
) -> None:
    """Synthesize (if needed) and cache the segments of a preset's train and test sets."""
    from cloudpose.data.dataset import prepare_data

    cfg = _config(variant, preset, 1, data)
    prepared = prepare_data(cfg.data, Path.cwd(), progress=progress)
    train_set, test_set = prepared.train, prepared.test
    typer.echo(f"train: {len(train_set)} segments, test: {len(test_set)} segments")
    if histogram is not None:
        from cloudpose.report.plots import occlusion_histogram

        title = (
            f"Occlusion factors of the {preset}-preset test set: {len(test_set)} instances\n"
            f"(cloudpose prepare --preset {preset} --histogram ...; data {prepared.key[:10]})"
        )
        counts = occlusion_histogram(test_set, histogram, title)
        typer.echo(f"occlusion bins (10% wide): {counts.tolist()} -> {histogram}")


@app.command()
def train(
    ctx: typer.Context,
    variant: VariantOpt = "shared-0",
    preset: PresetOpt = DEFAULT_PRESET,
    seed: SeedOpt = 1,
    data: DataOpt = "",
    epochs: Annotated[int | None, typer.Option(help="Override the preset's epochs.")] = None,
    precision: Annotated[str | None, typer.Option(help="fp32 or bf16.")] = None,
    device: Annotated[str | None, typer.Option(help="auto, cpu or cuda.")] = None,
    group: Annotated[str | None, typer.Option(help="Experiment group for a new run.")] = None,
    progress: ProgressOpt = True,
    set_: SetOpt = None,
    nproc: Annotated[
        int,
        typer.Option(
            help="Processes on this machine training the run together (torchrun; the batch is "
            "split between them). Under torchrun, leave it at 1.",
        ),
    ] = 1,
) -> None:
    """Train one variant (resumes an interrupted run of the same settings)."""
    from cloudpose import distributed
    from cloudpose.pipeline import train_run
    from cloudpose.runs import display_name

    cfg = _config(
        variant, preset, seed, data, set_, epochs=epochs, precision=precision, device=device
    )
    if nproc > 1:
        import shlex

        args = shlex.split(recorded_command(ctx))[1:]
        raise typer.Exit(distributed.relaunch_under_torchrun(args, nproc))
    with distributed.from_env() as world:
        out = train_run(cfg, group=group, progress=progress, world=world)
    if world.is_main:
        typer.echo(f"run {display_name(cfg)} (MLflow run {out.run_id}, folder {out.run_dir})")
        for k, v in sorted(out.metrics.items()):
            typer.echo(f"  {k:<28} {v:.4f}")


@app.command()
def evaluate(
    run: Annotated[str, typer.Option(help="Run folder, MLflow run id, or variant/preset/seedS.")],
    data: Annotated[
        str | None, typer.Option(help="Dataset root to test on, YCB-Video or BOP ycbv layout.")
    ] = None,
    frames: FramesOpt = "keyframe",
    icp: Annotated[bool, typer.Option("--icp/--no-icp", help="Also evaluate after ICP.")] = True,
    icp_fallback: Annotated[
        bool | None,
        typer.Option(
            "--icp-fallback/--no-icp-fallback",
            help="Keep the network's pose where ICP's fitness is below the default "
            "icp.fallback_min_fitness (default: the run's icp settings). Other settings than "
            "the run's are logged as {name}-fallback / {name}-nofallback.",
        ),
    ] = None,
    real: Annotated[
        bool,
        typer.Option(
            "--real", help="Test on the packaged real development frames (61, per video): real/..."
        ),
    ] = False,
    show_instances: Annotated[bool, typer.Option(help="Print every instance's errors.")] = False,
    name: Annotated[
        str | None,
        typer.Option(help="Metric prefix (default: test, or the --data folder's identity)."),
    ] = None,
    device: DeviceOpt = "auto",
    segmentation: Annotated[
        str | None,
        typer.Option(
            "--segmentation",
            "--masks",
            help="Test masks: gt, degraded-mild|medium|strong (imitated network errors), or "
            "posecnn:DIR (PoseCNN's results_PoseCNN_RSS2018 from the YCB_Video_toolbox); "
            "default the run's own.",
        ),
    ] = None,
    bop_csv: Annotated[
        Path | None,
        typer.Option(
            help="Also write the poses (after ICP, or the network's with --no-icp) as a BOP "
            "results CSV for bop_toolkit."
        ),
    ] = None,
    force: Annotated[
        bool, typer.Option("--force", help="Overwrite an existing --bop-csv.")
    ] = False,
    progress: ProgressOpt = True,
) -> None:
    """Evaluate a trained run, with and without ICP; logs the table and metrics to MLflow."""
    from cloudpose.data.bop import check_results_destination, write_evaluation_csv
    from cloudpose.evaluate import evaluate as evaluate_fn

    if bop_csv is not None:
        check_results_destination(bop_csv, force)
    from cloudpose.evaluate import evaluate_real
    from cloudpose.refine import ICPSettings

    settings = None if icp_fallback is None else ICPSettings(fallback=icp_fallback)
    if real and (data is not None or name is not None):
        raise ValueError("--real names its own data and metric prefix; drop --data and --name")
    kwargs = dict(icp=icp, icp_settings=settings, progress=progress, device=device)
    if real:
        out = evaluate_real(run, segmentation=segmentation, **kwargs)
    else:
        out = evaluate_fn(
            run, data=data, frames=frames, name=name, segmentation=segmentation, **kwargs
        )
    typer.echo(f"evaluated {out.source}; logged as {out.name}/... and {out.name}_icp/...")
    _print_summary(out.metrics)
    if show_instances:
        typer.echo(out.table.to_string(index=False, float_format=lambda x: f"{x:.4f}"))
    if bop_csv is not None:
        n, method = write_evaluation_csv(out, bop_csv, icp)
        typer.echo(f"{bop_csv}: {n} poses ({method}) in the BOP results format")


SUMMARY_COLUMNS = {
    "ad_auc": "AD AUC",
    "ads_auc": "ADS AUC",
    "ads_lt_1cm": "ADS<1cm",
    "rot_sym_lt_10deg": "rot<10deg*",
    "rot_lt_10deg": "rot<10deg",
    "trans_lt_1cm": "trans<1cm",
}
"""The summary's columns, in percent: AUCs as the YCB-Video toolbox computes them, the shares
of instances under a threshold (* = rotation error modulo the object's symmetries)."""
SUMMARY_FOOTNOTE = (
    "* rot<10deg*: rotation error < 10 deg modulo the object's symmetries (a can turned about "
    "its axis is not an error); rot<10deg: the plain angle, as the paper reports it."
)


def _print_summary(metrics: dict[str, float]) -> None:
    keys = list(SUMMARY_COLUMNS)
    prefixes = sorted({k.split("/")[0] for k in metrics})
    w = max([16] + [len(p.replace("_icp", " + ICP")) + 2 for p in prefixes])
    typer.echo(f"{'(%)':<{w}}" + "".join(f"{SUMMARY_COLUMNS[k]:>12}" for k in keys))
    for p in prefixes:
        vals = [metrics.get(f"{p}/{k}") for k in keys]
        if all(v is None for v in vals):
            continue
        label = p.replace("_icp", " + ICP")
        typer.echo(
            f"{label:<{w}}"
            + "".join(f"{100 * v:>12.1f}" if v is not None else f"{'':>12}" for v in vals)
        )
    typer.echo(SUMMARY_FOOTNOTE)


def _next_steps(preset: str) -> None:
    """What the numbers mean for ``preset``, and where to look next."""
    from cloudpose.config import presets

    meaning = {
        "smoke": "a plumbing check: a few seconds of training, its numbers mean nothing.",
    }.get(preset, f"preset {preset!r}: {presets().get(preset, '')}")
    from cloudpose.config import get_group, resolve
    from cloudpose.plan import estimate_run_s

    typer.echo(f"\nWhat this is: {meaning}")
    runs = len(get_group("shared").members) * 3
    per_run, _ = estimate_run_s(resolve("shared-0", DEFAULT_PRESET))
    typer.echo(
        "Next: `make mlflow-ui` and open http://127.0.0.1:5000 to browse the run; "
        "`make ablation-shared` trains the paper's shared-layer ablation on the default preset "
        f"({DEFAULT_PRESET}), {runs} runs (every variant x 3 seeds) x ~{per_run / 60:.0f} min = "
        f"~{runs * per_run / 3600:.1f} h on a 2-core CPU, and renders its tables into "
        f"reports/{DEFAULT_PRESET}/; `--dry-run` prints that plan without training."
    )


@app.command()
def predict(
    depth: Annotated[Path, typer.Option(help="Depth PNG (uint16).")],
    label: Annotated[Path, typer.Option(help="Label PNG (class ids, 0 = background).")],
    checkpoint: Annotated[str, typer.Option(help="model.pt, run folder, run id or run name.")],
    color: Annotated[Path | None, typer.Option(help="Color PNG for the overlay.")] = None,
    meta: Annotated[Path | None, typer.Option(help="YCB-Video meta.mat (intrinsics).")] = None,
    intrinsics: Annotated[
        str | None, typer.Option(help="fx,fy,cx,cy when there is no meta (default: YCB-Video).")
    ] = None,
    depth_factor: Annotated[float, typer.Option(help="Depth units per metre.")] = 10000.0,
    icp: Annotated[bool, typer.Option("--icp/--no-icp", help="Refine with ICP.")] = True,
    overlay: Annotated[Path, typer.Option(help="Where to write the overlay PNG.")] = Path(
        "prediction.png"
    ),
    device: DeviceOpt = "auto",
) -> None:
    """Estimate each labelled object's pose in one frame; print poses, write an overlay picture."""
    from cloudpose.predict import predict as predict_fn

    result = predict_fn(
        depth,
        label,
        checkpoint,
        color=color,
        meta=meta,
        intrinsics=intrinsics,
        depth_factor=depth_factor,
        icp=icp,
        overlay=overlay,
        device=device,
    )
    for p in result.poses:
        typer.echo(p.describe())
    typer.echo(f"overlay: {overlay}")


@app.command()
def run(
    variant: VariantOpt = "shared-0",
    preset: PresetOpt = DEFAULT_PRESET,
    seed: SeedOpt = 1,
    data: DataOpt = "",
    progress: ProgressOpt = True,
    set_: SetOpt = None,
    group: Annotated[str | None, typer.Option(help="Experiment group for a new run.")] = None,
    dry_run: DryRunOpt = False,
) -> None:
    """The main job: synthesize + prepare (if needed), train, evaluate with and without ICP.

    Prints its plan first: frames to render, whether the run is trained already, time."""
    from cloudpose.pipeline import train_and_evaluate
    from cloudpose.plan import plan_configs
    from cloudpose.runs import display_name

    cfg = _config(variant, preset, seed, data, set_)
    if group is not None:
        from cloudpose.tracking import check_name

        check_name("group", group)
    plan = plan_configs(
        [cfg],
        title=f"main job {display_name(cfg)}",
        project_dir=Path.cwd(),
        finished="finished before (training skipped, evaluated again)",
    )
    typer.echo(plan.text())
    if dry_run:
        return
    if preset in EXPECTED_WARNINGS:
        _mark_expected(*EXPECTED_WARNINGS[preset])
    result = train_and_evaluate(cfg, group=group, progress=progress)
    out, ev = result.train, result.evaluation
    typer.echo(f"\nrun {display_name(cfg)} (MLflow run {out.run_id}, folder {out.run_dir})")
    typer.echo(f"test set: {ev.source}; without and with ICP refinement:")
    metrics = dict(ev.metrics)
    if result.real is not None:
        typer.echo(f"real development frames: {result.real.split} (4 videos, 4 scenes)")
        metrics.update({k: v for k, v in result.real.metrics.items() if "/video/" not in k})
    _print_summary(metrics)
    _next_steps(preset)


EXPECTED_WARNINGS = {
    "smoke": (
        "ICP ",
        "expected on the smoke preset: a network trained for seconds on 12 frames starts ICP "
        "far from the objects",
    )
}
"""preset -> (start of a warning, why it is expected there): said once, beside the warning."""


def _mark_expected(prefix: str, why: str) -> None:
    """Say once, beside the first warning that starts with ``prefix``, why it is expected."""
    import warnings

    base = warnings.formatwarning
    said = []

    def formatwarning(message, *args, **kwargs) -> str:
        text = base(message, *args, **kwargs)
        if str(message).startswith(prefix) and not said:
            said.append(True)
            return text.rstrip("\n") + f" ({why})\n"
        return text

    warnings.formatwarning = formatwarning


@app.command()
def baseline(
    method: Annotated[str, typer.Option(help="fpfh (FPFH + RANSAC) or ppf (point-pair features).")],
    preset: PresetOpt = DEFAULT_PRESET,
    seed: SeedOpt = 1,
    limit: Annotated[
        int | None, typer.Option(help="An evenly spaced subsample of this many test instances.")
    ] = None,
    split: Annotated[
        str,
        typer.Option(
            help="test, val (held-out training frames: where to tune), or real (the packaged "
            "real development frames, per video)."
        ),
    ] = "test",
    data: Annotated[
        str | None,
        typer.Option(
            help="Dataset root to test on instead, YCB-Video or BOP ycbv layout (the preset "
            "gives the segment settings); logged under the data's identity, as evaluate --data."
        ),
    ] = None,
    frames: FramesOpt = "keyframe",
    set_: Annotated[
        list[str] | None,
        typer.Option("--set", help="Replace a setting of baselines.toml, key=value (repeatable)."),
    ] = None,
    icp: Annotated[bool, typer.Option("--icp/--no-icp", help="Also evaluate after ICP.")] = True,
    rerun: Annotated[
        bool, typer.Option(help="Compute and log a new run even if this one is logged.")
    ] = False,
    progress: ProgressOpt = True,
) -> None:
    """A classical baseline on a preset's test set (or --data), with and without ICP; logs to
    MLflow.

    A finished run of the same method, preset, seed, data, settings, split and subsample is
    shown, not computed again (``--rerun`` computes a new one)."""
    from cloudpose.baselines.run import run_baseline
    from cloudpose.config import parse_overrides

    overrides = {
        k: v
        for section in parse_overrides([f"b.{s}" for s in set_ or []]).values()
        for k, v in section.items()
    }
    out = run_baseline(
        method,
        preset,
        seed,
        limit=limit,
        split=split,
        data=data,
        frames=frames,
        overrides=overrides,
        icp=icp,
        progress=progress,
        rerun=rerun,
    )
    on = f"{out.split} in {data}, {preset} settings" if data is not None else preset
    if out.reused:
        typer.echo(
            f"baseline {method} on {on} (seed {seed}): already logged; --rerun runs it again"
        )
    typer.echo(
        f"baseline {method} on {on} (seed {seed}): {len(out.table)} instances, "
        f"{out.failures} not registered (misses); logged as {out.name}/...; "
        f"MLflow run {out.run_id}"
    )
    _print_summary(out.metrics)
    ms = out.metrics[f"{out.name}/net_ms_per_object"]
    typer.echo(f"{ms:.0f} ms per object ({method} alone)")


@app.command()
def ablate(
    group: Annotated[str, typer.Option(help=f"Ablation group: {_group_names()}.")],
    preset: PresetOpt = DEFAULT_PRESET,
    seeds: Annotated[int, typer.Option(help="Seeds 1..S per variant.")] = 3,
    keep_going: Annotated[
        bool, typer.Option("--keep-going/--stop-on-failure", help="Go on after a failed run.")
    ] = False,
    progress: ProgressOpt = True,
    set_: SetOpt = None,
    executor: Annotated[
        str, typer.Option(help="local (here, one run after another) or ray (a task per run).")
    ] = "local",
    address: Annotated[
        str | None,
        typer.Option(help="Ray cluster address; default $RAY_ADDRESS, else Ray on this machine."),
    ] = None,
    cpus_per_run: Annotated[float, typer.Option(help="Ray: CPUs (and threads) per run.")] = 1.0,
    gpus_per_run: Annotated[float, typer.Option(help="Ray: GPUs per run.")] = 0.0,
    connect_timeout: Annotated[
        float, typer.Option(help="Ray: seconds to wait for --address to answer.")
    ] = 30.0,
    dry_run: DryRunOpt = False,
    out: OutOpt = None,
    until_resolved: Annotated[
        bool,
        typer.Option(
            "--until-resolved",
            help="Then add seeds to the variants of the group's undecided claims until each "
            "is decided or at --max-seeds (claims.md names the rule).",
        ),
    ] = False,
    max_seeds: Annotated[
        int, typer.Option(help="With --until-resolved: the cap on seeds per variant.")
    ] = 10,
) -> None:
    """Train + evaluate every variant of a group over seeds (finished runs skipped), then report.

    Prints its plan first: frames to render, runs to train and those finished before, time."""
    from cloudpose.ablate import resolve_claims, run_group
    from cloudpose.cluster import RayOptions
    from cloudpose.config import parse_overrides
    from cloudpose.plan import plan_group

    overrides = parse_overrides(set_) or None
    plan = plan_group(group, preset, seeds, Path.cwd(), overrides=overrides, out_dir=out)
    typer.echo(plan.text())
    if dry_run:
        return
    ray = RayOptions(address, cpus_per_run, gpus_per_run, connect_timeout_s=connect_timeout)
    if until_resolved and max_seeds < seeds:
        raise typer.BadParameter(f"--max-seeds {max_seeds} is below --seeds {seeds}")
    res = run_group(
        group,
        preset,
        seeds,
        Path.cwd(),
        progress,
        keep_going=keep_going,
        overrides=overrides,
        executor=executor,
        ray=ray,
        out_dir=out,
        report=not until_resolved,
    )
    if until_resolved:
        from cloudpose.report import render_reports

        resolve_claims(
            group,
            preset,
            Path.cwd(),
            max_seeds=max_seeds,
            overrides=overrides,
            progress=progress,
            keep_going=keep_going,
            executor=executor,
            ray=ray,
        )
        res.report = render_reports(preset, [group], project_dir=Path.cwd(), out_dir=out)
    counts = {s: sum(r.status == s for r in res.runs) for s in ("trained", "skipped", "failed")}
    typer.echo(
        f"{group}/{preset}: "
        + ", ".join(f"{n} {s}" for s, n in counts.items())
        + f"; reports in {res.report.out_dir}; log {res.log}"
    )


@app.command("ablate-masks")
def ablate_masks(
    ctx: typer.Context,
    preset: PresetOpt = DEFAULT_PRESET,
    seeds: Annotated[int, typer.Option(help="Seeds 1..S of shared-0.")] = 3,
    progress: ProgressOpt = True,
    dry_run: DryRunOpt = False,
    out: OutOpt = None,
) -> None:
    """Segmentation quality: shared-0 (trained on ground truth) under each test mask source.

    Sources gt and degraded-mild|medium|strong, with and without ICP. Missing shared-0 seeds
    are trained, evaluations already logged are skipped; then table_masks and occlusion_masks
    in reports/PRESET/ and the MLflow run report/masks/PRESET. Prints its plan first.
    """
    from cloudpose.ablate_masks import mask_ablation
    from cloudpose.plan import plan_masks

    typer.echo(plan_masks(preset, seeds, Path.cwd(), out_dir=out).text())
    if dry_run:
        return
    res = mask_ablation(
        preset, seeds, Path.cwd(), progress, command=recorded_command(ctx), out_dir=out
    )
    trained = sum(r.status == "trained" for r in res.runs)
    done = sum(e.status == "evaluated" for e in res.evaluations)
    typer.echo(
        f"masks/{preset}: shared-0 {trained} trained, {len(res.runs) - trained} found; "
        f"{done} evaluations made, {len(res.evaluations) - done} logged before; "
        f"reports in {res.report.out_dir}; log {res.log}"
    )


def _serve_until_interrupted(cmd: list[str], env: dict[str, str], what: str) -> None:
    """Run a server that serves until interrupted (which ends this command too): any return of
    its own is a failure, said in one line, with its exit code (1 if it gave none)."""
    import os
    import subprocess

    code = subprocess.run(cmd, env={**os.environ, **env}, check=False).returncode
    typer.secho(
        f"error: the {what} stopped (exit code {code}); its output above says why",
        fg=typer.colors.RED,
        err=True,
    )
    raise typer.Exit(code if code > 0 else 1)


@app.command("mlflow-server")
def mlflow_server(
    backend: Annotated[
        str | None,
        typer.Option(
            help="SQL store of runs (any SQLAlchemy URI); default SQLite ./mlflow-server/mlflow.db."
        ),
    ] = None,
    artifacts: Annotated[
        str | None, typer.Option(help="Artifact root; default ./mlflow-server/artifacts.")
    ] = None,
    host: Annotated[str, typer.Option(help="Interface to bind (0.0.0.0 for a cluster).")] = (
        "127.0.0.1"
    ),
    port: Annotated[int, typer.Option(help="TCP port.")] = 5000,
) -> None:
    """An MLflow tracking server (SQL backend, artifacts served through it) for several
    machines; clients set MLFLOW_TRACKING_URI=http://HOST:PORT."""

    from cloudpose.cluster import check_port_free
    from cloudpose.tracking import server_command

    check_port_free(host, port)
    server = server_command(backend, artifacts, host, port)
    typer.echo(f"MLflow server on http://{host}:{port} (store {server.backend})")
    _serve_until_interrupted(server.argv, server.env, f"MLflow server on {host}:{port}")


@app.command("mlflow-ui")
def mlflow_ui(
    backend: Annotated[
        str | None,
        typer.Option(help="Store to browse; default MLFLOW_TRACKING_URI, else ./mlflow.db."),
    ] = None,
    host: Annotated[str, typer.Option(help="Interface to bind.")] = "127.0.0.1",
    port: Annotated[int, typer.Option(help="TCP port.")] = 5000,
    serve: Annotated[
        bool, typer.Option("--serve/--no-serve", help="Start the UI (else only prepare and print).")
    ] = True,
) -> None:
    """The MLflow UI, opening on each experiment's runs grouped by variant with the headline
    metrics averaged over seeds. First logs the headline metrics of runs stored without them and
    the saved view "variants" on every cloudpose experiment (experiment tags), and prints each
    experiment's address."""
    import os

    from cloudpose import headline, tracking

    if backend:
        os.environ["MLFLOW_TRACKING_URI"] = backend
    uri = tracking.tracking_uri()
    remote = tracking.is_remote(uri)
    if serve and not remote:
        from cloudpose.cluster import check_port_free

        check_port_free(host, port)
    base = uri.rstrip("/") if remote else f"http://{host}:{port}"
    prepared = headline.prepare_ui(tracking.setup())
    backfilled = sum(p.backfilled for p in prepared)
    if backfilled:
        keys = ", ".join(headline.HEADLINE)
        typer.echo(f"headline metrics ({keys}) logged now for {backfilled} runs stored before them")
    shown = [p for p in prepared if p.runs]
    if shown:
        typer.echo(
            "Runs grouped by variant, headline metrics averaged over seeds (view "
            f'"{headline.VIEW_NAME}"):'
        )
        width = max(len(p.name) for p in shown)
        for p in shown:
            url = headline.view_url(base, p.experiment_id)
            typer.echo(f"  {p.name:<{width}}  {p.runs:>3} runs  {url}")
    else:
        typer.echo(f"no cloudpose run in {uri} yet")
    if not serve or remote:
        return
    typer.echo(f"MLflow UI on {base} (store {uri}); Ctrl-C ends it")
    cmd = headline.ui_command(uri, host, port)
    _serve_until_interrupted(
        cmd, {"MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false"}, f"MLflow UI on {host}:{port}"
    )


@app.command()
def report(
    ctx: typer.Context,
    group: Annotated[
        list[str] | None,
        typer.Option(
            help="Group(s) to render (repeatable), or masks (shared-0 under each mask source); "
            "default all."
        ),
    ] = None,
    all_groups: Annotated[bool, typer.Option("--all", help="Every group (the default).")] = False,
    preset: PresetOpt = DEFAULT_PRESET,
    data: Annotated[
        str | None, typer.Option(help="Data fingerprint to report; default the most used.")
    ] = None,
    mlflow: Annotated[
        bool, typer.Option("--mlflow/--no-mlflow", help="Also log the reports to MLflow.")
    ] = True,
    out: OutOpt = None,
) -> None:
    """Render the tables, claims and figures of a preset from existing MLflow runs only."""
    from cloudpose.report import render_reports
    from cloudpose.tracking import check_name

    check_name("--preset", preset)  # it names the output folder reports/PRESET
    groups = None if all_groups or not group else list(group)
    res = render_reports(
        preset,
        groups,
        project_dir=Path.cwd(),
        data=data,
        log_mlflow=mlflow,
        command=recorded_command(ctx),
        out_dir=out,
    )
    typer.echo(f"{len(res.files)} files from {len(res.runs.records)} runs in {res.out_dir}")


@app.command("real-report")
def real_report(
    ctx: typer.Context,
    preset: PresetOpt = DEFAULT_PRESET,
    seeds: Annotated[
        int, typer.Option(help="Network seeds 1..S expected (more found are shown too).")
    ] = 3,
    out: Annotated[
        Path | None, typer.Option(help="Output folder (default reports/PRESET).")
    ] = None,
) -> None:
    """The 61 real development frames per video and pooled: the network (shared-0) and both
    classical baselines, without and with ICP, from existing runs only (lists what is missing)."""
    from cloudpose.report.real import render_real_report

    report, files = render_real_report(
        preset, Path.cwd(), out_dir=out, command=recorded_command(ctx), seeds=seeds
    )
    for line in report.missing:
        typer.echo(f"missing: {line}")
    typer.echo(" ".join(str(f) for f in files))


@app.command()
def curves(
    ctx: typer.Context,
    run: Annotated[
        list[str],
        typer.Option(help="Run (repeatable): name variant/preset/seedS, MLflow run id or folder."),
    ],
    out: Annotated[Path, typer.Option(help="PNG to write; the values go beside it as .csv.")],
    metric: Annotated[
        list[str] | None,
        typer.Option(help="Per-epoch metric (repeatable); default: rotation loss and error."),
    ] = None,
    title: Annotated[str, typer.Option(help="Figure title.")] = "",
    mark_epoch: Annotated[
        int | None, typer.Option(help="Dashed line at this epoch (e.g. where a preset stops).")
    ] = None,
    mark_label: Annotated[str, typer.Option(help="Text beside the dashed line.")] = "",
    x: Annotated[str, typer.Option(help="x axis: epoch, or step (Adam steps).")] = "epoch",
) -> None:
    """Per-epoch curves of any runs side by side (one panel per metric), from MLflow."""
    from cloudpose import tracking
    from cloudpose.report.curves import curves_csv, fetch_curves, plot_curves

    metrics = list(metric or ["train/loss_rot", "val/rot_err_median_deg"])
    command = f"`{recorded_command(ctx)}`"
    found = fetch_curves(tracking.setup(Path.cwd()), run, metrics)
    png = plot_curves(
        found,
        metrics,
        out,
        command=command,
        title=title,
        mark_epoch=mark_epoch,
        mark_label=mark_label,
        x=x,
    )
    typer.echo(f"{png}\n{curves_csv(found, metrics, out.with_suffix('.csv'), command)}")


@app.command("occlusion-report")
def occlusion_report(
    ctx: typer.Context,
    preset: PresetOpt = DEFAULT_PRESET,
    seeds: Annotated[int, typer.Option(help="Seeds 1..S.")] = 3,
    group: Annotated[
        str | None, typer.Option(help="Also plot this group's variants (shared-0 alone if unset).")
    ] = None,
    train_missing: Annotated[
        bool,
        typer.Option(
            "--train-missing",
            help="Train and evaluate the runs it needs that the store lacks first (hours on "
            "the cpu preset; prints the plan first). Without it, a missing run is an error.",
        ),
    ] = False,
    dry_run: DryRunOpt = False,
    out: OutOpt = None,
    progress: ProgressOpt = True,
) -> None:
    """ADS < 1 cm accuracy per occlusion bin: shared-0 without and with ICP (+ a group).

    Renders from the runs in MLflow only: with a run missing it names the runs and the command
    that trains them, and exits 1."""
    from cloudpose.ablate import occlusion_report as occlusion_fn
    from cloudpose.config import get_group, resolve
    from cloudpose.plan import estimate_run_s, missing_report_runs, plan_runs

    variants = list(get_group(group).members) if group else ["shared-0"]
    if train_missing:
        title = f"occlusion report {preset}, seeds 1-{seeds}"
        title += f", group {group}" if group else ""
        typer.echo(plan_runs(variants, preset, seeds, title=title, project_dir=Path.cwd()).text())
    else:
        missing = missing_report_runs(variants, preset, seeds, Path.cwd())
        if missing:
            per_run, _ = estimate_run_s(resolve(variants[0], preset))
            again = f"cloudpose occlusion-report --preset {preset} --seeds {seeds}"
            again += f" --group {group}" if group else ""
            typer.echo(
                f"occlusion-report renders from existing runs only, and {len(missing)} of the "
                f"{len(variants) * seeds} runs it needs are not in the MLflow store: "
                f"{', '.join(missing)}.\nTo train them (~{per_run / 60:.0f} min a run on a "
                f"2-core CPU; the plan is printed first): {again} --train-missing\n"
                f"  (make occlusion-runs PRESET={preset} SEEDS={seeds}"
                + (f" GROUP={group}" if group else "")
                + ")",
                err=True,
            )
            raise typer.Exit(1)
        typer.echo(f"plan: occlusion report {preset} from {len(variants) * seeds} existing runs")
    if dry_run:
        return
    res = occlusion_fn(
        preset,
        seeds,
        Path.cwd(),
        progress,
        group=group,
        train_missing=train_missing,
        command=recorded_command(ctx),
        out_dir=out,
    )
    for p in res.files:
        if p.stem.startswith("occlusion"):
            typer.echo(str(p))


if __name__ == "__main__":
    app()
