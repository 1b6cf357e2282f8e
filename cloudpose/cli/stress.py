"""``cloudpose stress``: the stress curves of :mod:`cloudpose.studies.stress`, computed (resumable) and
rendered into reports/PRESET/stress.md."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from cloudpose.cli.app import (
    DryRunOpt,
    IcpRadiusOpt,
    OutOpt,
    PresetOpt,
    ProgressOpt,
    app,
    check_icp_options,
    recorded_command,
)
from cloudpose.config import PAPER_RADIUS
from cloudpose.registry import DEFAULT_PRESET

QUICK = {"instances": 24, "fpfh_instances": 12, "ppf_instances": 4, "synth_frames": 8}
"""What ``--quick`` sets (a look at every curve in minutes, not a measurement)."""


@app.command()
def stress(
    ctx: typer.Context,
    preset: PresetOpt = DEFAULT_PRESET,
    checkpoint: Annotated[
        list[Path] | None,
        typer.Option(help="A network checkpoint (model.pt) to stress (repeatable)."),
    ] = None,
    run: Annotated[
        list[str] | None,
        typer.Option(
            help="A trained run (folder, MLflow id or name, or pretrained: the shipped "
            "network) to stress (repeatable)."
        ),
    ] = None,
    instances: Annotated[
        int | None,
        typer.Option(help="Evenly spaced instances per source (default all)."),
    ] = None,
    fpfh_instances: Annotated[
        int | None,
        typer.Option(help="FPFH + RANSAC on evenly spaced of those (default all; 0: none)."),
    ] = None,
    ppf_instances: Annotated[
        int | None,
        typer.Option(
            help="Point-pair features on evenly spaced of those (~3.5 s an object; 0: none)."
        ),
    ] = None,
    ppf_levels: Annotated[
        str,
        typer.Option(
            help="Point-pair features at every level (all) or at the identity and each "
            "perturbation's farthest level only (ends)."
        ),
    ] = "all",
    synth_frames: Annotated[
        int, typer.Option(help="Synthetic test frames 0..N-1 of the preset to draw from.")
    ] = 60,
    source: Annotated[
        list[str] | None, typer.Option(help="real and/or synth (repeatable; default both).")
    ] = None,
    only: Annotated[
        list[str] | None, typer.Option(help="Perturbations to run (repeatable; default all).")
    ] = None,
    icp_selection: Annotated[
        int,
        typer.Option(
            help="Also compare how ICP starts are chosen (1 start; 24 / 60 by fitness or by the "
            "depth, icp.select) on this many unperturbed instances per source (0: not).",
        ),
    ] = 0,
    ensemble: Annotated[
        bool,
        typer.Option(
            "--ensemble",
            help="Also the networks given as one (cloudpose evaluate --ensemble): per object "
            "the refinement of best ICP fitness kept (the depth does not follow a perturbation "
            "of the points).",
        ),
    ] = False,
    seed: Annotated[int, typer.Option(help="Seed of every random choice of the sweep.")] = 1,
    icp_radius: IcpRadiusOpt = None,
    quick: Annotated[
        bool, typer.Option("--quick", help="A small subsample (a look, not a measurement).")
    ] = False,
    results: Annotated[
        Path | None,
        typer.Option(
            help="Folder of the sweep's results (default runs/stress/PRESET); with "
            "--report-only also an archive of them (--pack)."
        ),
    ] = None,
    pack: Annotated[
        Path | None,
        typer.Option(
            help="Also write the results the report is rendered from into this .tar.xz "
            "(megabytes, not the frames' cache: what a committed report keeps beside it)."
        ),
    ] = None,
    report: Annotated[
        bool, typer.Option("--report/--no-report", help="Render the report after the sweep.")
    ] = True,
    report_only: Annotated[
        bool, typer.Option("--report-only", help="Only render the report from the results.")
    ] = False,
    out: OutOpt = None,
    dry_run: DryRunOpt = False,
    progress: ProgressOpt = True,
) -> None:
    """Stress curves: real development and synthetic test segments perturbed in steps (mask
    dilated / eroded, depth holes, noise, bias, a cut plane, point count, one side missing), the
    network with and without ICP against FPFH + RANSAC and point-pair features at each step;
    resumable, the plan and its time printed first."""
    from cloudpose.registry import resolve
    from cloudpose.report.build import default_out_dir
    from cloudpose.report.stress import render_stress_report
    from cloudpose.store.tracking import check_name
    from cloudpose.studies import perturbations as pt
    from cloudpose.studies import stress as st

    check_name("--preset", preset)
    icp_radius = PAPER_RADIUS if icp_radius is None else icp_radius
    check_icp_options(radius=icp_radius)
    check_counts(
        instances=instances, fpfh_instances=fpfh_instances, ppf_instances=ppf_instances,
        synth_frames=synth_frames, icp_selection=icp_selection,
    )  # fmt: skip
    project = Path.cwd()
    results = results or project / "runs" / "stress" / preset
    if not report_only and results.is_file():
        raise typer.BadParameter(
            f"--results {results}: a sweep writes into a folder; an archive is read with "
            "--report-only"
        )
    if not report_only:
        if quick:
            instances = instances or QUICK["instances"]
            fpfh_instances = fpfh_instances or QUICK["fpfh_instances"]
            ppf_instances = ppf_instances or QUICK["ppf_instances"]
            synth_frames = QUICK["synth_frames"]
        methods = _all_methods(
            checkpoint or [], run or [], project, fpfh_instances, ppf_instances, ppf_levels,
            ensemble,
        )  # fmt: skip
        _sweep(
            results,
            resolve("shared-0", preset, seed),
            methods,
            sources=tuple(source or pt.SOURCES),
            only=tuple(only or ()),
            instances=instances,
            synth_frames=synth_frames,
            seed=seed,
            icp_selection=icp_selection,
            progress=progress,
            dry_run=dry_run,
            icp_radius=icp_radius,
        )
    if dry_run:
        return
    with st.results_folder(results) as folder:
        if pack is not None:
            n = st.pack_results(folder, pack)
            typer.echo(f"packed {n} result files into {pack} ({pack.stat().st_size / 1e6:.2f} MB)")
        if report:  # --report-only --no-report: only --pack
            files = render_stress_report(
                folder, out or default_out_dir(project, preset), command=recorded_command(ctx)
            )
            typer.echo(" ".join(str(f) for f in files))


COUNTS = {
    "instances": (1, "a positive number of instances per source (default all)"),
    "fpfh_instances": (0, "a number of instances (0: none; default all)"),
    "ppf_instances": (0, "a number of instances (0: none; default all)"),
    "synth_frames": (1, "a positive number of frames"),
    "icp_selection": (0, "a number of instances (0: none)"),
}
"""The least value of each count option of ``stress`` and what it is, for its message."""


def check_counts(**given: int | None) -> None:
    """``ValueError`` naming the first option of :data:`COUNTS` in ``given`` (by parameter
    name) below its least value; None is its default."""
    for name, value in given.items():
        least, what = COUNTS[name]
        if value is not None and value < least:
            raise ValueError(f"--{name.replace('_', '-')} {value}: expected {what}")


def _all_methods(
    checkpoints: list[Path],
    runs: list[str],
    project: Path,
    fpfh_instances: int | None,
    ppf_instances: int | None,
    ppf_levels: str,
    ensemble: bool = False,
) -> list:
    """The networks named (and, with ``ensemble``, all of them as one) and the baselines not
    left out (a limit of 0), as :class:`cloudpose.studies.stress.SweepMethod`; BadParameter when there is
    none, ``ppf_levels`` is not ``all`` or ``ends``, or an ensemble has fewer than two
    networks."""
    from cloudpose.studies import stress as st

    methods = _network_methods(checkpoints, runs, project)
    if ensemble:
        if len(methods) < 2:
            raise typer.BadParameter(
                f"--ensemble joins the networks given: {len(methods)} given, at least 2 needed"
            )
        methods.append(st.SweepMethod("ensemble", members=tuple(m.checkpoint for m in methods)))
    if ppf_levels not in ("all", "ends"):
        raise typer.BadParameter(f"--ppf-levels {ppf_levels!r}: expected all or ends")
    methods += [
        st.SweepMethod(name, limit=limit, ends_only=ends)
        for name, limit, ends in (
            ("fpfh", fpfh_instances, False),
            ("ppf", ppf_instances, ppf_levels == "ends"),
        )
        if limit != 0  # 0: left out
    ]
    if not methods:
        raise typer.BadParameter("no method: give a --checkpoint or --run, or a baseline")
    return methods


def _sweep(results: Path, cfg, methods: list, *, icp_selection: int, dry_run: bool, **kw) -> None:
    """The stress sweep (:func:`cloudpose.studies.stress.run_sweep`), then, unless ``dry_run``, the
    comparison of ICP start selections on ``icp_selection`` instances per source (0: none)."""
    from cloudpose.studies import stress as st

    if icp_selection:
        raise typer.BadParameter(
            "the start-selection study is retired: `cloudpose compare --icp-select` answers it",
            param_hint="--icp-selection",
        )
    st.run_sweep(results, cfg, methods, echo=typer.echo, dry_run=dry_run, **kw)


def _network_methods(checkpoints: list[Path], runs: list[str], project: Path):
    """One :class:`cloudpose.studies.stress.SweepMethod` per checkpoint, named ``net-seed{S}`` by the seed in
    its config (``net-seed{S}-{k}`` where two share a seed); none without any (a call that
    adds a baseline to a sweep's results)."""
    from cloudpose.infer import load_checkpoint
    from cloudpose.studies.stress import SweepMethod

    paths = list(checkpoints)
    if runs:
        from cloudpose.store.pretrained import is_pretrained, shipped
        from cloudpose.store.runs import client_for, resolve_run

        client = client_for(runs, project)
        paths += [shipped(r).path if is_pretrained(r) else resolve_run(client, r)[1] for r in runs]
    out: list[SweepMethod] = []
    for path in paths:
        _, cfg = load_checkpoint(path, "cpu")
        name = f"net-seed{cfg.seed}"
        if any(m.name == name for m in out):
            name += f"-{len(out)}"
        out.append(SweepMethod(name, Path(path)))
    return out
