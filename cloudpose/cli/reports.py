"""Commands that render reports from the runs in MLflow: tables and claims, the real frames, curves, occlusion."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from cloudpose.cli.app import (
    DryRunOpt,
    OutOpt,
    PresetOpt,
    ProgressOpt,
    app,
    recorded_command,
)
from cloudpose.registry import DEFAULT_PRESET, presets


def _committed_if_lacking(preset: str, lacking=None) -> None:
    """Read the preset's committed store (``reports/PRESET/mlflow-store/``, unpacked once
    into ``stores/PRESET``) when no store is named and the project's own lacks the runs
    (:mod:`cloudpose.report.committed`)."""
    from cloudpose.report.committed import holds_preset, use_committed_store

    project = Path.cwd()
    use_committed_store(
        preset, project, lacking or (lambda: not holds_preset(project, preset)), typer.echo
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
    readme: Annotated[
        Path | None,
        typer.Option(
            help="Also replace the preset's verdict table in this file: the lines between "
            "'<!-- verdicts PRESET -->' and '<!-- /verdicts PRESET -->' (reports/README.md)."
        ),
    ] = None,
    against: Annotated[
        str | None,
        typer.Option(
            help="Another preset (the same recipe at another budget): claims.md and claims.csv "
            "set its verdicts beside this one's, each claim marked holds, changes or undecided."
        ),
    ] = None,
) -> None:
    """Render the tables, claims and figures of a preset from existing MLflow runs only."""
    from cloudpose.report import render_reports
    from cloudpose.store.tracking import check_name

    check_name("--preset", preset)  # it names the output folder reports/PRESET
    if against is not None and against not in presets():
        raise typer.BadParameter(
            f"unknown preset {against!r}; valid presets: {', '.join(presets())}",
            param_hint="--against",
        )
    _committed_if_lacking(preset)
    groups = None if all_groups or not group else list(group)
    res = render_reports(
        preset,
        groups,
        project_dir=Path.cwd(),
        data_key=data,
        log_mlflow=mlflow,
        command=recorded_command(ctx),
        out_dir=out,
        readme=readme,
        against=against,
        echo=typer.echo,
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
        Path | None, typer.Option(help="Output folder (default reports/PRESET).", file_okay=False)
    ] = None,
) -> None:
    """The 61 real development frames per video and pooled: the network (shared-0) and both
    classical baselines, without and with ICP, from existing runs only (lists what is missing)."""
    from cloudpose.report.real import render_real_report

    _committed_if_lacking(preset)
    report, files = render_real_report(
        preset,
        Path.cwd(),
        out_dir=out,
        command=recorded_command(ctx),
        seeds=seeds,
        echo=typer.echo,
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
    from cloudpose.report.curves import curves_csv, fetch_curves, plot_curves
    from cloudpose.store import tracking

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
    from cloudpose.registry import get_group, resolve
    from cloudpose.suite.ablate import occlusion_report as occlusion_fn
    from cloudpose.suite.plan import estimate_run_s, missing_report_runs, plan_runs

    variants = list(get_group(group).members) if group else ["shared-0"]
    if not train_missing:
        _committed_if_lacking(
            preset, lambda: bool(missing_report_runs(variants, preset, seeds, Path.cwd()))
        )
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
        typer.echo(f"plan: occlusion report {preset}: {_runs_found(variants, preset)}")
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
        echo=typer.echo,
    )
    if not res.files:
        raise ValueError(
            f"occlusion-report: no run of {', '.join(variants)} ({preset}) has an instance table "
            "(eval/test/instances.parquet); nothing written (`cloudpose evaluate --run RUN` "
            "writes it)"
        )
    for p in res.files:
        typer.echo(str(p))


def _runs_found(variants: list[str], preset: str) -> str:
    """The runs an occlusion plot draws from: each variant's seeds and the baselines'."""
    from cloudpose.report.runs import load_runs

    runs = load_runs(preset)
    drawn = [*variants, *(b for b in runs.variants if b.startswith("baseline-"))]
    parts = [
        f"{v} seed{'s' if len(found) > 1 else ''} {', '.join(str(r.seed) for r in found)}"
        for v in drawn
        if (found := runs.of(v))
    ]
    return f"from {sum(len(runs.of(v)) for v in drawn)} existing runs ({'; '.join(parts)})"
