"""Commands of one run: train, evaluate, predict, the main job (``run``) and the classical baselines."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from cloudpose.cli.app import (
    DataOpt,
    DeviceOpt,
    DryRunOpt,
    FramesOpt,
    FreshOpt,
    PresetOpt,
    ProgressOpt,
    SeedOpt,
    SetOpt,
    VariantOpt,
    app,
    config_of,
    parse_refine,
    recorded_command,
    refine_option,
    refinement_of,
)
from cloudpose.registry import DEFAULT_PRESET


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
    from cloudpose.store.runs import display_name
    from cloudpose.suite.pipeline import train_run
    from cloudpose.train import distributed

    cfg = config_of(
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
    refine: Annotated[str | None, refine_option("evaluate")] = None,
    real: Annotated[
        bool,
        typer.Option(
            "--real", help="Test on the packaged real development frames (61, per video): real/..."
        ),
    ] = False,
    ensemble: Annotated[
        list[str] | None,
        typer.Option(
            help="Another run whose network joins --run's (repeatable; the same preset, e.g. "
            "other seeds): each estimate refined by ICP, per object the refinement with the "
            "best score of --refine's select kept (depth: agreement with the frame's depth). "
            "Logged in --run as {name}-ensembleN."
        ),
    ] = None,
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
            help="Also write the poses (after ICP, or the network's with --refine none) as a "
            "BOP results CSV for bop_toolkit."
        ),
    ] = None,
    force: Annotated[
        bool, typer.Option("--force", help="Overwrite an existing --bop-csv.")
    ] = False,
    progress: ProgressOpt = True,
) -> None:
    """Evaluate a trained run, with and without ICP; logs the table and metrics to MLflow.

    ICP is the run's own (the paper's, as the ablation tables) unless --refine says otherwise;
    another refinement is logged under a name of its own. Every instance's errors are in the
    run's artifacts, eval/NAME/instances.parquet."""
    from cloudpose.data.bop import check_results_destination, write_evaluation_csv
    from cloudpose.evaluate import evaluate as evaluate_fn

    if bop_csv is not None:
        check_results_destination(bop_csv, force)
    from cloudpose.evaluate import evaluate_real

    refined = parse_refine("evaluate", refine)
    if ensemble and not refined.icp:
        raise ValueError(
            "--ensemble keeps one of the networks' ICP refinements; --refine none has none"
        )
    if real and (data is not None or name is not None):
        raise ValueError("--real names its own data and metric prefix; drop --data and --name")
    kwargs = dict(
        icp=refined.icp,
        icp_overrides=refined.overrides(),
        progress=progress,
        device=device,
        ensemble=ensemble,
    )
    if real:
        out = evaluate_real(run, segmentation=segmentation, **kwargs)
    else:
        out = evaluate_fn(
            run, data=data, frames=frames, name=name, segmentation=segmentation, **kwargs
        )
    where = (
        f"logged as {out.name}/... and {out.name}_icp/..."
        if out.run_id is not None
        else "not logged (the shipped network has no MLflow run)"
    )
    typer.echo(f"evaluated {out.source}; {where}")
    _print_summary(out.metrics)
    if bop_csv is not None:
        n, method = write_evaluation_csv(out, bop_csv, refined.icp)
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
    from cloudpose.registry import presets

    meaning = {
        "smoke": "a plumbing check: a few seconds of training, its numbers mean nothing. "
        "`cloudpose showcase` (make showcase) shows the shipped, trained network at work.",
    }.get(preset, f"preset {preset!r}: {presets().get(preset, '')}")
    from cloudpose.registry import get_group, resolve
    from cloudpose.suite.plan import estimate_run_s

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
    refine: Annotated[str | None, refine_option("predict")] = None,
    overlay: Annotated[
        str,
        typer.Option(
            help="Where to write the overlay PNG: a .png file, a folder (prediction.png inside "
            "it; one that exists, or a name ending in /), or a name without a suffix (.png is "
            "added)."
        ),
    ] = "prediction.png",
    device: DeviceOpt = "auto",
) -> None:
    """Estimate each labelled object's pose in one frame; print poses (with how each agrees
    with the depth: ICP fitness, coverage of the segment, share of the model in front of the
    observed surface) and the objects not posed, write an overlay picture and name it."""
    from cloudpose.predict import predict as predict_fn

    refined = parse_refine("predict", refine)
    overrides = refined.overrides()
    result = predict_fn(
        depth,
        label,
        checkpoint,
        color=color,
        meta=meta,
        intrinsics=intrinsics,
        depth_factor=depth_factor,
        icp=refined.icp,
        icp_overrides=overrides,
        overlay=overlay,
        device=device,
    )
    if refined.icp and result.poses:
        typer.echo(
            f"refinement: {refinement_of(overrides)}"
            + ("; --refine paper: the paper's ICP" if refined.recipe != "paper" else "")
        )
    for p in result.poses:
        typer.echo(p.describe())
    for line in result.notes(depth, label):
        typer.echo(line)
    typer.echo(f"overlay: {result.overlay}")


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
    from cloudpose.store.runs import display_name
    from cloudpose.suite.pipeline import train_and_evaluate
    from cloudpose.suite.plan import plan_configs

    cfg = config_of(variant, preset, seed, data, set_)
    if group is not None:
        from cloudpose.store.tracking import check_name

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
    refine: Annotated[str | None, refine_option("baseline")] = None,
    rerun: Annotated[
        bool, typer.Option(help="Compute and log a new run even if this one is logged.")
    ] = False,
    fresh: FreshOpt = False,
    progress: ProgressOpt = True,
) -> None:
    """A classical baseline on a preset's test set (or --data), with and without ICP; logs to
    MLflow.

    A finished run of the same method, preset, seed, data, settings, split and subsample is
    shown, not computed again (--rerun computes a new one). As a sweep does, it reads and
    adds to the committed sweep of a preset the checkout commits (stores/PRESET/) unless
    MLFLOW_TRACKING_URI names a store or --fresh asks for ./mlflow.db."""
    from cloudpose.registry import parse_overrides
    from cloudpose.report.committed import sweep_store
    from cloudpose.store.tracking import STORE_DB
    from cloudpose.studies.baseline_runs import run_baseline

    refined = parse_refine("baseline", refine)
    fields = refined.fields
    overrides = {
        k: v
        for section in parse_overrides([f"b.{s}" for s in set_ or []]).values()
        for k, v in section.items()
    }
    said = []
    store = sweep_store(preset, Path.cwd(), fresh, said.append)
    if store != f"./{STORE_DB}" or fresh:  # named where it is not the project's own
        for line in said:
            typer.echo(line)
    out = run_baseline(
        method,
        preset,
        seed,
        limit=limit,
        split=split,
        data=data,
        frames=frames,
        overrides=overrides,
        icp=refined.icp,
        progress=progress,
        rerun=rerun,
        icp_radius=fields["radius"],
        icp_starts=fields["starts"],
        icp_select=fields["select"],
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
def compare(
    ctx: typer.Context,
    data: Annotated[
        str | None,
        typer.Option(
            help="Dataset root, YCB-Video or BOP ycbv layout (default: the 61 packaged real "
            "development frames)."
        ),
    ] = None,
    frames: Annotated[
        str | None,
        typer.Option(
            help="Its frame list: keyframe (BOP: the BOP19 test targets), all, or an image set "
            "(default: all of the packaged frames, keyframe of --data)."
        ),
    ] = None,
    run: Annotated[
        list[str] | None,
        typer.Option(
            help="The network: a run (name variant/preset/seedS, id or folder) or pretrained "
            "(the default); repeated, an ensemble (per object the refinement that the select "
            "of --refine scores best kept)."
        ),
    ] = None,
    method: Annotated[
        list[str] | None,
        typer.Option(
            help="Methods beside it: fpfh, ppf, none (no estimate: the identity at the segment's "
            "mean, refined alike; what the refinement finds alone). Default: all three."
        ),
    ] = None,
    combine: Annotated[
        list[str] | None,
        typer.Option(
            help="Also a combination, e.g. network+fpfh (repeatable): each estimate of its "
            "methods refined alike, per object the refinement that agrees best with the depth "
            "kept; a method beside the others."
        ),
    ] = None,
    seed: Annotated[int, typer.Option(help="The classical methods' random seed.")] = 1,
    refine: Annotated[str | None, refine_option("compare")] = None,
    out: Annotated[
        Path | None,
        typer.Option(
            help="The comparison's folder (default runs/compare/DATA-IDENTITY/KEY, KEY of the "
            "networks and seed).",
            file_okay=False,
        ),
    ] = None,
    device: DeviceOpt = "auto",
    progress: ProgressOpt = True,
) -> None:
    """The network, FPFH + RANSAC, point-pair features and no estimate at all on the same
    segments of one set of frames, every estimate refined by the same ICPs (the paper's and a
    wider one), side by side: pooled, per video and per object pose, the network's difference
    to each paired over object poses (compare.md, compare.png). Resumable; logs nothing."""
    from cloudpose.report.compare import render
    from cloudpose.studies.compare import run_compare

    fields = parse_refine("compare", refine).fields
    done = run_compare(
        out,
        data=data,
        frames=frames,
        runs=run,
        methods=method,
        combine=combine,
        seed=seed,
        starts=fields["starts"],
        select=fields["select"],
        radius=fields["radius"],
        device=device,
        progress=progress,
    )
    report, figure = render(done, recorded_command(ctx))
    typer.echo(done.described)
    typer.echo(f"report: {report}; figure: {figure}")
