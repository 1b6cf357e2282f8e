"""``cloudpose stress``: the stress curves of :mod:`cloudpose.studies.stress`, computed (resumable) and
rendered into reports/PRESET/stress.md."""

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
    parse_refine,
    recorded_command,
    refine_option,
    spec_parts,
)
from cloudpose.registry import DEFAULT_PRESET

SAMPLE = {
    "instances": None,
    "fpfh-instances": None,
    "ppf-instances": None,
    "ppf-levels": "all",
    "synth-frames": 60,
    "seed": 1,
}
"""The sweep's ``--sample`` settings and their defaults (None: every instance)."""
QUICK = {"instances": 24, "fpfh-instances": 12, "ppf-instances": 4, "synth-frames": 8}
"""What ``--sample quick`` sets (a look at every curve in minutes, not a measurement)."""
COUNTS = {
    "instances": (1, "a positive number of instances per source (default all)"),
    "fpfh-instances": (0, "a number of instances (0: none; default all)"),
    "ppf-instances": (0, "a number of instances (0: none; default all)"),
    "synth-frames": (1, "a positive number of frames"),
    "seed": (None, "a whole number"),
}
"""The least value of each count of ``--sample`` (None: any) and what it is, for its message."""
STEPS = ("sweep", "report")
"""What ``--steps`` runs, in this order (``--pack`` packs between the two)."""

SampleOpt = Annotated[
    str | None,
    typer.Option(
        metavar="[quick,]KEY=VALUE",
        help="How much of each source the sweep takes, comma-separated KEY=VALUE parts: "
        "instances=N (evenly spaced instances per source; default all), fpfh-instances=N "
        "(FPFH + RANSAC on evenly spaced of those; default all, 0: none), ppf-instances=N "
        "(point-pair features likewise, ~3.5 s an object; default all, 0: none), "
        "ppf-levels=all|ends (point-pair features at every level, or at the identity and each "
        "perturbation's farthest level only; default all), synth-frames=N (synthetic test "
        "frames 0..N-1 of the preset to draw from; default 60), seed=N (of every random "
        "choice of the sweep; default 1). quick: 24 instances, FPFH + RANSAC on 12, "
        "point-pair features on 4, from 8 synthetic frames (a look, not a measurement), each "
        "part beside it replacing one, e.g. quick,ppf-instances=0.",
    ),
]
StepsOpt = Annotated[
    str,
    typer.Option(
        help="What to do, comma-separated: sweep (compute the results into --results, "
        "resumable), report (render the report from them: --results a folder or an archive); "
        "none: neither, only --pack. --pack packs after the sweep, before the report.",
    ),
]


@app.command()
def stress(
    ctx: typer.Context,
    preset: PresetOpt = DEFAULT_PRESET,
    run: Annotated[
        list[str] | None,
        typer.Option(
            help="A network to stress (repeatable): a trained run (folder, MLflow id or name), "
            "a checkpoint file (model.pt), or pretrained (the shipped network)."
        ),
    ] = None,
    ensemble: Annotated[
        bool,
        typer.Option(
            "--ensemble",
            help="Also the networks given as one (cloudpose evaluate --ensemble): per object "
            "the refinement of best ICP fitness kept (the depth does not follow a perturbation "
            "of the points).",
        ),
    ] = False,
    only: Annotated[
        list[str] | None,
        typer.Option(
            help="A source (real, synth) or perturbation (dilate, erode, shift, holes, noise, "
            "smooth, bias, cut, points, lateral) to run (repeatable; default every source and "
            "every perturbation)."
        ),
    ] = None,
    sample: SampleOpt = None,
    refine: Annotated[str | None, refine_option("stress")] = None,
    results: Annotated[
        Path | None,
        typer.Option(
            help="Folder of the sweep's results (default runs/stress/PRESET); with --steps "
            "report also an archive of them (--pack)."
        ),
    ] = None,
    pack: Annotated[
        Path | None,
        typer.Option(
            help="Also write the results the report is rendered from into this .tar.xz "
            "(megabytes, not the frames' cache: what a committed report keeps beside it)."
        ),
    ] = None,
    steps: StepsOpt = "sweep,report",
    out: OutOpt = None,
    dry_run: DryRunOpt = False,
    progress: ProgressOpt = True,
) -> None:
    """Stress curves: real development and synthetic test segments perturbed in steps (mask
    dilated / eroded, depth holes, noise, bias, a cut plane, point count, one side missing), the
    network with and without ICP against FPFH + RANSAC and point-pair features at each step;
    resumable, the plan and its time printed first."""
    from cloudpose.store.tracking import check_name

    check_name("--preset", preset)
    icp_radius = parse_refine("stress", refine).fields["radius"]
    todo = parse_steps(steps, pack)
    taken = parse_sample(sample)
    sources, perturbations = split_only(only or [])
    project = Path.cwd()
    results = results or project / "runs" / "stress" / preset
    if "sweep" in todo:
        if results.is_file():
            raise typer.BadParameter(
                f"--results {results}: a sweep writes into a folder; an archive is read with "
                "--steps report"
            )
        _sweep(
            results, preset, _all_methods(run or [], project, taken, ensemble), sources,
            perturbations, taken, progress=progress, dry_run=dry_run, icp_radius=icp_radius,
        )  # fmt: skip
    if dry_run:
        return
    target = (out or _default_out(project, preset)) if "report" in todo else None
    _pack_and_render(ctx, preset, results, pack, target, out)


def parse_steps(spec: str, pack: Path | None) -> set[str]:
    """The steps ``--steps`` names (:data:`STEPS`, or ``none``); ``ValueError`` for another
    word, or for ``none`` without ``--pack`` (nothing to do)."""
    words, given = spec_parts("--steps", spec)
    if given or not words or any(w not in (*STEPS, "none") for w in words):
        raise ValueError(f"--steps {spec!r}: expected {', '.join(STEPS)} (comma-separated) or none")
    todo = set(words) - {"none"}
    if not todo and pack is None:
        raise ValueError("--steps none: nothing to do without --pack")
    return todo


def parse_sample(spec: str | None) -> dict:
    """``--sample`` as the sweep's settings by parameter name (``fpfh_instances``, ...): the
    defaults (:data:`SAMPLE`), :data:`QUICK` where it says ``quick``, each part given replacing
    one; ``ValueError`` naming the first part that is not a setting or below its least value
    (:data:`COUNTS`)."""
    words, given = spec_parts("--sample", spec or "")
    if words not in ([], ["quick"]):
        raise ValueError(f"--sample {spec!r}: expected quick and KEY=VALUE parts")
    out = SAMPLE | (QUICK if words else {})
    for key, text in given.items():
        part = f"--sample {key}={text}"
        if key == "ppf-levels":
            if text not in ("all", "ends"):
                raise ValueError(f"{part}: expected all or ends")
            out[key] = text
            continue
        if key not in COUNTS:
            raise ValueError(f"{part}: expected a key of {', '.join(SAMPLE)}")
        least, what = COUNTS[key]
        try:
            n = int(text)
        except ValueError:
            raise ValueError(f"{part}: expected {what}") from None
        if least is not None and n < least:
            raise ValueError(f"{part}: expected {what}")
        out[key] = n
    return {k.replace("-", "_"): v for k, v in out.items()}


def split_only(only: list[str]) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """``--only`` as (sources, perturbations), each empty for all; ``ValueError`` naming the
    words that are neither."""
    from cloudpose.studies import perturbations as pt

    unknown = [w for w in only if w not in pt.SOURCES and w not in pt.PERTURBATIONS]
    if unknown:
        raise ValueError(
            f"--only {', '.join(unknown)}: expected sources ({', '.join(pt.SOURCES)}) or "
            f"perturbations ({', '.join(pt.PERTURBATIONS)})"
        )
    sources = tuple(w for w in only if w in pt.SOURCES)
    return sources, tuple(w for w in only if w not in pt.SOURCES)


def _default_out(project: Path, preset: str) -> Path:
    from cloudpose.report.build import default_out_dir

    return default_out_dir(project, preset)


def _pack_and_render(
    ctx, preset: str, results: Path, pack: Path | None, out: Path | None, given: Path | None
) -> None:
    """Pack the results (``--pack``), then render the report from them into ``out`` (None: no
    report; ``given``: the --out the user gave), or beside it when ``out`` keeps committed
    results these lack (:func:`cloudpose.report.stress.report_folder`)."""
    from cloudpose.report.stress import render_stress_report, report_folder
    from cloudpose.studies import stress as st

    with st.results_folder(results) as folder:
        if pack is not None:
            n = st.pack_results(folder, pack)
            typer.echo(f"packed {n} result files into {pack} ({pack.stat().st_size / 1e6:.2f} MB)")
        if out is not None:
            out = report_folder(preset, Path.cwd(), given, out, folder, typer.echo)
            files = render_stress_report(folder, out, command=recorded_command(ctx))
            typer.echo(" ".join(str(f) for f in files))


def _all_methods(runs: list[str], project: Path, taken: dict, ensemble: bool = False) -> list:
    """The networks named (and, with ``ensemble``, all of them as one) and the baselines not
    left out (a limit of 0) by ``taken`` (:func:`parse_sample`), as
    :class:`cloudpose.studies.stress.SweepMethod`; BadParameter when there is none, or an ensemble has fewer
    than two networks."""
    from cloudpose.studies import stress as st

    methods = _network_methods(runs, project)
    if ensemble:
        if len(methods) < 2:
            raise typer.BadParameter(
                f"--ensemble joins the networks given: {len(methods)} given, at least 2 needed"
            )
        methods.append(st.SweepMethod("ensemble", members=tuple(m.checkpoint for m in methods)))
    methods += [
        st.SweepMethod(name, limit=limit, ends_only=ends)
        for name, limit, ends in (
            ("fpfh", taken["fpfh_instances"], False),
            ("ppf", taken["ppf_instances"], taken["ppf_levels"] == "ends"),
        )
        if limit != 0  # 0: left out
    ]
    if not methods:
        raise typer.BadParameter("no method: give a --run, or a baseline")
    return methods


def _sweep(
    results: Path, preset: str, methods: list, sources, perturbations, taken: dict, **kw
) -> None:
    """The stress sweep (:func:`cloudpose.studies.stress.run_sweep`) of ``preset``'s data."""
    from cloudpose.registry import resolve
    from cloudpose.studies import perturbations as pt
    from cloudpose.studies import stress as st

    st.run_sweep(
        results,
        resolve("shared-0", preset, taken["seed"]),
        methods,
        echo=typer.echo,
        sources=sources or pt.SOURCES,
        only=perturbations,
        instances=taken["instances"],
        synth_frames=taken["synth_frames"],
        seed=taken["seed"],
        **kw,
    )


def _is_checkpoint(value: str) -> bool:
    """Whether a ``--run`` value names a checkpoint file (model.pt), not a run."""
    return value.endswith(".pt") or Path(value).is_file()


def _network_methods(runs: list[str], project: Path):
    """One :class:`cloudpose.studies.stress.SweepMethod` per network, in the order given: a checkpoint file
    as it is, a run by its checkpoint; named ``net-seed{S}`` by the seed in its config
    (``net-seed{S}-{k}`` where two share a seed); none without any (a call that adds a
    baseline to a sweep's results)."""
    from cloudpose.infer import load_checkpoint
    from cloudpose.studies.stress import SweepMethod

    named = [r for r in runs if not _is_checkpoint(r)]
    resolved: dict[str, tuple[str | None, Path]] = {}
    if named:
        from cloudpose.store.pretrained import is_pretrained, shipped
        from cloudpose.store.runs import client_for, resolve_run

        client = client_for(named, project)
        resolved = {
            r: (None, shipped(r).path) if is_pretrained(r) else resolve_run(client, r)
            for r in named
        }
    out: list[SweepMethod] = []
    for run in runs:
        run_id, path = resolved.get(run, (None, Path(run)))
        _, cfg = load_checkpoint(path, "cpu")
        name = f"net-seed{cfg.seed}"
        if any(m.name == name for m in out):
            name += f"-{len(out)}"
        out.append(SweepMethod(name, Path(path), run_id=run_id))
    return out
