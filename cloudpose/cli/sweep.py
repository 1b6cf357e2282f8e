"""Commands of the ablation suite: a group over seeds (until its claims are decided), the mask ablation."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from cloudpose.cli.app import (
    DryRunOpt,
    FreshOpt,
    OutOpt,
    PresetOpt,
    ProgressOpt,
    SetOpt,
    app,
    group_names,
    recorded_command,
    spec_parts,
)
from cloudpose.registry import DEFAULT_PRESET


@app.command()
def ablate(
    group: Annotated[str, typer.Option(help=f"Ablation group: {group_names()}.")],
    preset: PresetOpt = DEFAULT_PRESET,
    seeds: Annotated[int, typer.Option(help="Seeds 1..S per variant.")] = 3,
    keep_going: Annotated[
        bool, typer.Option("--keep-going/--stop-on-failure", help="Go on after a failed run.")
    ] = False,
    progress: ProgressOpt = True,
    set_: SetOpt = None,
    executor: Annotated[
        str,
        typer.Option(
            metavar="local|ray[,KEY=VALUE]",
            help="Where the runs train: local (here, one run after another) or ray (a Ray task "
            "per run), then Ray's settings, comma-separated: address=HOST:PORT (the cluster; "
            "default $RAY_ADDRESS, else Ray on this machine), cpus-per-run=N (CPUs and threads "
            "of each run; default 1), gpus-per-run=N (default 0), connect-timeout=S (seconds "
            "to wait for the address to answer; default 30), e.g. ray,address=HEAD:6379 or "
            "ray,cpus-per-run=8.",
        ),
    ] = "local",
    dry_run: DryRunOpt = False,
    out: OutOpt = None,
    fresh: FreshOpt = False,
    until_resolved: Annotated[
        int | None,
        typer.Option(
            "--until-resolved",
            metavar="MAX_SEEDS",
            help="Then add seeds to the variants of the group's undecided claims until each "
            "is decided or has MAX_SEEDS seeds (claims.md names the rule, whose cap is 10).",
        ),
    ] = None,
    only: Annotated[
        list[str] | None,
        typer.Option(
            help="Only this member of the group (repeatable), e.g. --group shared --only "
            "shared-0 --only shared-all."
        ),
    ] = None,
) -> None:
    """Train + evaluate every variant of a group over seeds (finished runs skipped), then report.

    Prints its plan first: frames to render, runs to train and those finished before, time."""
    from cloudpose.registry import parse_overrides
    from cloudpose.report.committed import sweep_store
    from cloudpose.suite.ablate import resolve_claims, run_group
    from cloudpose.suite.cluster import RayOptions
    from cloudpose.suite.plan import plan_group

    overrides = parse_overrides(set_) or None
    executor, ray_settings = parse_executor(executor)
    if until_resolved is not None and until_resolved < seeds:
        raise typer.BadParameter(f"--until-resolved {until_resolved} is below --seeds {seeds}")
    sweep_store(preset, Path.cwd(), fresh, typer.echo)
    try:
        plan = plan_group(
            group, preset, seeds, Path.cwd(), overrides=overrides, out_dir=out, only=only
        )
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--only") from exc
    typer.echo(plan.text())
    if dry_run:
        return
    ray = RayOptions(**ray_settings)
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
        report=until_resolved is None,
        only=only,
        other_data=fresh,
    )
    if until_resolved is not None:
        from cloudpose.report import render_reports

        resolve_claims(
            group,
            preset,
            Path.cwd(),
            max_seeds=until_resolved,
            overrides=overrides,
            progress=progress,
            keep_going=keep_going,
            executor=executor,
            ray=ray,
            only=only,
            other_data=fresh,
        )
        res.report = render_reports(preset, [group], project_dir=Path.cwd(), out_dir=out)
    counts = {s: sum(r.status == s for r in res.runs) for s in ("trained", "skipped", "failed")}
    typer.echo(
        f"{group}/{preset}: "
        + ", ".join(f"{n} {s}" for s, n in counts.items())
        + f"; reports in {res.report.out_dir}; log {res.log}"
    )


RAY_SETTINGS = {
    "address": "address",
    "cpus-per-run": "cpus_per_run",
    "gpus-per-run": "gpus_per_run",
    "connect-timeout": "connect_timeout_s",
}
"""``--executor ray``'s settings -> the fields of the cluster options they set."""


def parse_executor(spec: str) -> tuple[str, dict]:
    """``--executor`` as (executor, its Ray settings by field name); ``ValueError`` naming the
    part for another executor, another setting, a setting that is not a number, or a setting
    beside ``local``, which would ignore it."""
    from cloudpose.suite.cluster import EXECUTORS

    words, given = spec_parts("--executor", spec)
    if len(words) != 1 or words[0] not in EXECUTORS:
        raise ValueError(f"--executor {spec!r}: expected one of {', '.join(EXECUTORS)}")
    settings: dict = {}
    for key, text in given.items():
        part = f"--executor {words[0]},{key}={text}"
        if words[0] != "ray":
            raise ValueError(f"{part}: a Ray setting; the {words[0]} executor takes none")
        if key not in RAY_SETTINGS:
            raise ValueError(f"{part}: expected a setting of {', '.join(RAY_SETTINGS)}")
        if key == "address":
            settings["address"] = text
            continue
        try:
            settings[RAY_SETTINGS[key]] = float(text)
        except ValueError:
            raise ValueError(f"{part}: expected a number") from None
    return words[0], settings


@app.command("ablate-masks")
def ablate_masks(
    ctx: typer.Context,
    preset: PresetOpt = DEFAULT_PRESET,
    seeds: Annotated[int, typer.Option(help="Seeds 1..S of shared-0.")] = 3,
    progress: ProgressOpt = True,
    dry_run: DryRunOpt = False,
    out: OutOpt = None,
    fresh: FreshOpt = False,
) -> None:
    """Segmentation quality: shared-0 (trained on ground truth) under each test mask source.

    Sources gt and degraded-mild|medium|strong, with and without ICP. Missing shared-0 seeds
    are trained, evaluations already logged are skipped; then table_masks and occlusion_masks
    in reports/PRESET/ and the MLflow run report/masks/PRESET. Prints its plan first.
    """
    from cloudpose.report.committed import sweep_store
    from cloudpose.suite.masks import mask_ablation
    from cloudpose.suite.plan import plan_masks

    sweep_store(preset, Path.cwd(), fresh, typer.echo)
    typer.echo(plan_masks(preset, seeds, Path.cwd(), out_dir=out).text())
    if dry_run:
        return
    res = mask_ablation(
        preset,
        seeds,
        Path.cwd(),
        progress,
        command=recorded_command(ctx),
        out_dir=out,
        other_data=fresh,
    )
    trained = sum(r.status == "trained" for r in res.runs)
    done = sum(e.status == "evaluated" for e in res.evaluations)
    typer.echo(
        f"masks/{preset}: shared-0 {trained} trained, {len(res.runs) - trained} found; "
        f"{done} evaluations made, {len(res.evaluations) - done} logged before; "
        f"reports in {res.report.out_dir}; log {res.log}"
    )
