"""Render every report of a preset from the runs in MLflow, and log it back to MLflow.

Output folder ``reports/{preset}/`` (:func:`default_out_dir`; ``runs/reports/{preset}/`` for a
preset whose reports a checkout does not commit):

- ``table1_overall``, ``table2_per_class`` (shared-0, without and with ICP), ``table3_shared_layers``
  (group shared), ``table4_rotation`` (groups rotation and loss): each ``.md``, ``.tex``, ``.csv``;
- ``claims.md`` / ``claims.csv``: every difference the paper claims, with a 95% CI and a verdict;
- ``occlusion.png`` / ``.csv`` (shared-0 without and with ICP) and per group
  ``occlusion_{group}``, ``curves_{group}``, ``training_{group}``, ``rot_err_{group}`` PNGs;
- ``table_masks`` and ``occlusion_masks`` (report ``masks``, :mod:`cloudpose.report.segmentation`):
  shared-0 under each test-time mask source, once such evaluations exist;
- ``README.md``: the index.

Each group's files (and the overall ones) are also logged as artifacts of one run named
``report/{group}/{preset}`` in the group's experiment, replaced on every render.
"""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from cloudpose.data.keys import DataKey
from cloudpose.registry import get_group, groups, resolve
from cloudpose.report import plots, segmentation
from cloudpose.report.claims import (
    ClaimResult,
    across_budgets,
    budgets_frame,
    budgets_markdown,
    claims_frame,
    claims_markdown,
    evaluate_claims,
    update_verdicts_block,
)
from cloudpose.report.committed import refuse_empty, report_folder
from cloudpose.report.formats import Provenance, write_text
from cloudpose.report.runs import RunSet, load_runs
from cloudpose.report.tables import (
    BASELINE_LABELS,
    table1_overall,
    table2_per_class,
    table3_shared_layers,
    table4_rotation,
)
from cloudpose.store import runs as run_records
from cloudpose.store import tracking
from cloudpose.train.loop import online_epoch_steps

TABLE4_GROUPS = ("rotation", "loss", "symmetry")
"""The groups whose rows Table IV holds, one section each."""
GROUP_TABLE = {
    "shared": "table3_shared_layers",
    **dict.fromkeys(TABLE4_GROUPS, "table4_rotation"),
    segmentation.GROUP: "table_masks",
}
"""The table each report run's MLflow note shows."""
OVERALL = ("table1_overall", "table2_per_class", "occlusion", "claims")

DESCRIPTIONS = {
    "table1_overall": "Table I: overall AD AUC, ADS AUC, ADS < 1 cm of shared-0 without and with "
    "ICP, beside the paper's rows",
    "table2_per_class": "Table II: per-class accuracy after ICP beside the paper's 'Ours' columns",
    "table3_shared_layers": "Table III: shared layers (without ICP), with parameter counts",
    "table4_rotation": "Table IV: rotation representation and loss, rotation error < 10/15/20°",
    "table_masks": "segmentation quality: shared-0 under each test-time mask source (ground "
    "truth, degraded), without and with ICP, beside the paper's PoseCNN-mask figures",
    "claims": "every difference the paper claims: measured difference, 95% CI over seeds, verdict",
    "occlusion": "ADS < 1 cm accuracy per occlusion bin, shared-0 without and with ICP",
    "occlusion_masks": "ADS < 1 cm accuracy per occlusion bin, shared-0 under each mask source",
    "occlusion_{g}": "ADS < 1 cm accuracy per occlusion bin, variants of group {g}",
    "curves_{g}": "AD and ADS accuracy-threshold curves (0-10 cm), variants of group {g}",
    "training_{g}": "training loss and validation ADS AUC per epoch, variants of group {g}",
    "rot_err_{g}": "rotation-error histograms, variants of group {g}",
}


@dataclass
class ReportResult:
    """What one render wrote."""

    out_dir: Path
    files: list[Path]
    runs: RunSet
    claims: list[ClaimResult] = field(default_factory=list)
    mlflow_runs: dict[str, str] = field(default_factory=dict)
    """group -> run id of its report run."""


def render_reports(
    preset: str,
    group_names: list[str] | None = None,
    *,
    out_dir: Path | None = None,
    project_dir: Path | None = None,
    command: str | None = None,
    data_key: DataKey | None = None,
    log_mlflow: bool = True,
    client=None,
    readme: Path | None = None,
    against: str | None = None,
    echo: Callable[[str], object] = print,
    only_occlusion: bool = False,
) -> ReportResult:
    """Render the reports of ``group_names`` (default: every group) from MLflow runs.

    Tables I and II, the overall occlusion plot and claims.md are rendered every time (from
    whatever runs exist); a group's table and figures only when its runs exist, the ``masks``
    report only when shared-0 has evaluations under other mask sources.

    Args:
        preset: training preset whose runs to report.
        group_names: ablation groups, and ``masks`` (:mod:`cloudpose.report.segmentation`);
            None = all of them.
        out_dir: output folder; default :func:`default_out_dir`.
        project_dir: folder of the default MLflow store (cwd).
        command: the command named in every file; default this process's command line.
        data_key: the data key of the runs to report; default the one most runs were trained on.
        log_mlflow: also log the files to a ``report/{group}/{preset}`` run per group.
        readme: also replace the preset's verdict table in this hand-written file
            (:func:`~cloudpose.report.claims.update_verdicts_block`).
        client: an ``MlflowClient`` (default: the project's store).
        against: another preset (e.g. the same recipe at another budget): claims.md and
            claims.csv also give its verdicts and, per claim, whether the verdict holds,
            changes or is undecided across the two (:func:`~cloudpose.report.claims.across_budgets`).
        echo: where the one-line notes go (a redirected folder, a replaced committed report).
        only_occlusion: write the occlusion plots only (``occlusion.*`` and the groups'
            ``occlusion_GROUP.png``): no tables, claims, index or MLflow report run.

    Raises:
        NoRunsError: the store holds no finished, evaluated run of ``preset`` (nothing is
            written).

    The default folder is :func:`default_out_dir`, except that the committed reports of a
    preset are rendered over only by runs that include every committed (variant, seed)
    (:func:`~cloudpose.report.committed.report_folder`).
    """
    project_dir = (project_dir or Path.cwd()).resolve()
    if readme is not None and not readme.is_file():
        raise ValueError(f"--readme {readme}: no such file")
    client = client or tracking.setup(project_dir)
    names = _group_names(group_names)
    command = command or tracking.command_line()
    renderer = tracking.git_commit()
    runs = load_runs(preset, data_key=data_key, client=client)
    refuse_empty(len(runs.records), preset, project_dir, "the report")
    pairs = {(r.variant, r.seed) for r in runs.records}
    out_dir = report_folder(
        preset,
        project_dir,
        out_dir,
        default_out_dir(project_dir, preset),
        pairs,
        echo,
        data_key=runs.data_key,
    )
    out_dir.mkdir(parents=True, exist_ok=True)
    tabled = _say_lacking_tables(runs, echo)
    if only_occlusion:
        files = _render_occlusion_only(runs, tabled, names, out_dir, command, renderer)
        return ReportResult(out_dir, files, runs, [], {})
    prov_all = Provenance.of(runs, command, renderer)
    written = {"overall": _render_overall(runs, tabled, out_dir, command, renderer)}
    results, claim_files = _render_claims(runs, preset, against, client, out_dir, prov_all)
    written["overall"] += claim_files
    if readme is not None:
        update_verdicts_block(readme, preset, results, prov_all)
    for g in names:
        if g == segmentation.GROUP:
            written[g] = segmentation.render(runs, out_dir, command, renderer)
        else:
            written[g] = _render_group(runs, g, out_dir, command, renderer, tabled)
    written["overall"].append(_write_index(out_dir, prov_all, preset))
    mlflow_runs = {}
    if log_mlflow:
        mlflow_runs = _log_report_runs(client, names, preset, written, prov_all, project_dir)
    files = sorted({p for ps in written.values() for p in ps})
    return ReportResult(out_dir, files, runs, results, mlflow_runs)


def _group_names(group_names: list[str] | None) -> list[str]:
    """The groups to render: ``group_names``, or every ablation group and ``masks``; an unknown
    name raises with the valid list."""
    names = [*groups(), segmentation.GROUP] if group_names is None else list(group_names)
    for g in names:
        if g != segmentation.GROUP:
            get_group(g)
    return names


def _with_baselines(runs: RunSet) -> RunSet:
    """shared-0's runs and the baselines' (Tables I and II, the overall occlusion plot)."""
    return runs.subset(["shared-0", *(v for v in runs.variants if v.startswith("baseline-"))])


def _render_occlusion_only(
    runs: RunSet, tabled: RunSet, names: list[str], out_dir: Path, command: str, renderer: str
) -> list[Path]:
    """``only_occlusion``: the overall occlusion plot and each group's, nothing else."""
    drawn = tabled.subset(_with_baselines(runs).variants)
    files = _occlusion_overall(drawn, out_dir, Provenance.of(drawn, command, renderer))
    for g in names:
        sub, series = _group_series(tabled, g)
        if series:
            files.append(
                _occlusion_group(sub, g, series, out_dir, Provenance.of(sub, command, renderer))
            )
    return sorted(files)


def _render_overall(
    runs: RunSet, tabled: RunSet, out_dir: Path, command: str, renderer: str
) -> list[Path]:
    """Tables I and II and the overall occlusion plot, once shared-0 has runs (else none)."""
    base = runs.subset(["shared-0"])
    if not base.records:
        return []
    with_baselines = _with_baselines(runs)
    prov = Provenance.of(base, command, renderer)
    files = table1_overall(with_baselines).write(out_dir, prov)
    files += table2_per_class(with_baselines).write(out_dir, prov)
    drawn = tabled.subset(with_baselines.variants)
    return files + _occlusion_overall(drawn, out_dir, Provenance.of(drawn, command, renderer))


def _render_claims(
    runs: RunSet, preset: str, against: str | None, client, out_dir: Path, prov: Provenance
) -> tuple[list[ClaimResult], list[Path]]:
    """``claims.md`` and ``claims.csv`` (with preset ``against``'s verdicts beside, across the
    two budgets, where one is named): the claims' results and the two files."""
    results = evaluate_claims(runs)
    claims_md, claims_df = claims_markdown(results, prov), claims_frame(results)
    if against is not None:
        rows = across_budgets(
            results, evaluate_claims(load_runs(against, client=client)), (preset, against)
        )
        budgets = {p: budget_words(p) for p in (preset, against)}
        claims_md += "\n" + budgets_markdown(rows, preset, against, budgets)
        claims_df = claims_df.merge(
            budgets_frame(rows, against), on=["claim", "metric"], how="outer", sort=False
        )
    write_text(out_dir / "claims.md", claims_md)
    claims_csv = f"# {prov.line()}\n" + claims_df.to_csv(index=False, float_format="%.3f")
    write_text(out_dir / "claims.csv", claims_csv)
    return results, [out_dir / "claims.md", out_dir / "claims.csv"]


def _log_report_runs(
    client,
    names: list[str],
    preset: str,
    written: dict[str, list[Path]],
    prov: Provenance,
    project_dir: Path,
) -> dict[str, str]:
    """Each group's files and the overall ones as its ``report/{group}/{preset}`` run
    (:func:`log_report_run`), for each group that wrote any: group -> run id."""
    return {
        g: log_report_run(client, g, preset, written[g] + written["overall"], prov, project_dir)
        for g in names
        if written[g]
    }


def default_out_dir(project_dir: Path, preset: str) -> Path:
    """Where the reports of ``preset`` go unless a folder is named: ``reports/{preset}``.

    In a git checkout whose ``reports/`` holds committed results, a preset without committed
    reports of its own (``smoke``, a new preset) renders into the ignored
    ``runs/reports/{preset}`` instead, so trying a command leaves the committed results as
    they are; the presets whose reports are committed (``cpu``, ...) render over them.
    """
    reports = Path(project_dir) / "reports"
    if _tracked(reports) and not _tracked(reports / preset):
        return Path(project_dir) / "runs" / "reports" / preset
    return reports / preset


def _tracked(path: Path) -> bool:
    """Whether git tracks a file under ``path`` (False outside a checkout or without git)."""
    if not path.parent.is_dir():
        return False
    try:
        out = subprocess.run(
            ["git", "ls-files", "--", path.name],
            cwd=path.parent,
            capture_output=True,
            text=True,
            timeout=30,
        )
    except (OSError, subprocess.SubprocessError):
        return False
    return out.returncode == 0 and bool(out.stdout.strip())


def _say_lacking_tables(runs: RunSet, echo: Callable[[str], object]) -> RunSet:
    """The runs with their test instance table; a one-line warning naming each run without
    one, what the report does without it and the command that writes it again."""
    lacking = runs.lacking_instances()
    if lacking:
        named = ", ".join(f"{r.variant} seed {r.seed} ({r.run_id[:8]})" for r in lacking)
        echo(
            f"warning: {len(lacking)} run(s) lack their instance table "
            f"(eval/test/instances.parquet): {named}; the occlusion plots leave them out (their "
            "provenance lists the seeds drawn), the claims of their variants use the runs' "
            "metrics, not the instances. `cloudpose evaluate --run RUN_ID` writes it again"
        )
    return runs.with_instances()


def _series(runs: RunSet, variant: str, label: str, method: str = "net"):
    tables = [t for r in runs.of(variant) if (t := r.instances()) is not None]
    return plots.Series(label, tables, method) if tables else None


def _occlusion_overall(runs: RunSet, out_dir: Path, prov: Provenance) -> list[Path]:
    candidates = [
        _series(runs, "shared-0", "shared-0, network alone", "net"),
        _series(runs, "shared-0", "shared-0 + ICP", "icp"),
    ]
    candidates += [
        _series(runs, b, f"{BASELINE_LABELS.get(b, b)} + ICP", "icp")
        for b in runs.variants
        if b.startswith("baseline-")
    ]
    series = [s for s in candidates if s]
    series = [s for s in series if f"{s.method}_ads" in s.tables[0]]
    if not series:
        return []
    png = plots.plot_occlusion(
        series,
        out_dir / "occlusion.png",
        prov,
        "ADS < 1 cm accuracy vs occlusion (shared-0"
        + (" and the baselines)" if len(series) > 2 else ")"),
    )
    csv = out_dir / "occlusion.csv"
    write_text(
        csv,
        f"# {prov.line()}\n"
        + plots.occlusion_frame(series).to_csv(index=False, float_format="%.2f"),
    )
    return [png, csv]


def _group_series(runs: RunSet, g: str):
    """A group's runs, its provenance's run set and one occlusion series per variant present."""
    group = get_group(g)
    sub = runs.subset(group.members)
    present = [v for v in group.members if sub.of(v)]
    return sub, [s for v in present if (s := _series(sub, v, f"{v} ({group.labels.get(v, v)})"))]


def _occlusion_group(sub: RunSet, g: str, series, out_dir: Path, prov: Provenance) -> Path:
    base_icp = _series(sub, "shared-0", "shared-0 + ICP", "icp")
    occ = series + ([base_icp] if base_icp and "icp_ads" in base_icp.tables[0] else [])
    return plots.plot_occlusion(
        occ, out_dir / f"occlusion_{g}.png", prov, f"ADS < 1 cm accuracy vs occlusion, group {g}"
    )


def _render_group(
    runs: RunSet, g: str, out_dir: Path, command: str, renderer: str, tabled: RunSet
) -> list[Path]:
    """A group's table and figures: the per-instance ones (occlusion, threshold curves,
    rotation errors) from ``tabled``, the runs of ``runs`` with their instance tables."""
    sub = runs.subset(get_group(g).members)
    if not sub.records:
        return []
    drawn, series = _group_series(tabled, g)
    prov = Provenance.of(sub, command, renderer)
    files: list[Path] = []
    if g == "shared":
        files += table3_shared_layers(sub).write(out_dir, prov)
    else:
        both = runs.subset(set().union(*(get_group(n).members for n in TABLE4_GROUPS)))
        files += table4_rotation(both).write(out_dir, Provenance.of(both, command, renderer))
    if series:
        drawn_prov = Provenance.of(drawn, command, renderer)
        files.append(_occlusion_group(drawn, g, series, out_dir, drawn_prov))
        files.append(
            plots.plot_threshold_curves(
                series,
                out_dir / f"curves_{g}.png",
                drawn_prov,
                f"Accuracy-threshold curves, group {g}, without ICP",
            )
        )
        files.append(
            plots.plot_rotation_histograms(
                series,
                out_dir / f"rot_err_{g}.png",
                drawn_prov,
                f"Rotation error, group {g}, without ICP",
            )
        )
    group = get_group(g)
    histories = {
        f"{v} ({group.labels.get(v, v)})": [
            {k: r.history(k) for k in ("train/loss", "val/ads_auc")} for r in sub.of(v)
        ]
        for v in group.members
        if sub.of(v)
    }
    files.append(
        plots.plot_training_curves(
            histories, out_dir / f"training_{g}.png", prov, f"Training curves, group {g}"
        )
    )
    return files


def _describe(stem: str) -> str:
    if stem in DESCRIPTIONS:
        return DESCRIPTIONS[stem]
    for key, text in DESCRIPTIONS.items():
        if "{g}" in key and stem.startswith(key.split("{g}")[0]):
            return text.format(g=stem[len(key.split("{g}")[0]) :])
    return ""


def _write_index(out_dir: Path, prov: Provenance, preset: str) -> Path:
    stems: dict[str, list[str]] = {}
    for p in sorted(out_dir.iterdir()):
        if p.is_file() and p.name != "README.md" and p.suffix in (".md", ".tex", ".csv", ".png"):
            stems.setdefault(p.stem, []).append(p.name)
    lines = [
        f"# Reports, preset `{preset}`",
        "",
        f"_{prov.line()}_",
        "",
        f"Rendered from the MLflow runs only (`cloudpose report --all --preset {preset}` "
        "renders them again; `make mlflow-ui` shows the runs). Our numbers are mean ± "
        "sample std over seeds, in percent; the paper's are its single runs on real "
        "YCB-Video.",
        "",
        "| report | files |",
        "|---|---|",
    ]
    order = [k.split("{g}")[0] for k in DESCRIPTIONS]

    def rank(stem: str) -> tuple[int, str]:
        hits = [i for i, k in enumerate(order) if stem == k or ("_" in k and stem.startswith(k))]
        return (hits[0] if hits else len(order), stem)

    for stem, names in sorted(stems.items(), key=lambda kv: rank(kv[0])):
        links = ", ".join(f"[{n}]({n})" for n in names)
        desc = _describe(stem) or stem
        lines.append(f"| {desc} | {links} |")
    path = out_dir / "README.md"
    return write_text(path, "\n".join(lines) + "\n")


def log_report_run(
    client,
    group: str,
    preset: str,
    files: list[Path],
    prov: Provenance,
    project_dir: Path | None = None,
) -> str:
    """Log ``files`` as the artifacts of run ``report/{group}/{preset}``, replacing an older one.

    The run carries tags ``kind=report``, ``report_group``, ``report_preset`` (and no
    ``variant``/``preset`` tags, so run look-ups by those never find it).
    """
    exp = tracking.experiment_id(client, group, project_dir)
    name = f"report/{group}/{preset}"
    old = client.search_runs(
        [exp],
        f"tags.kind = 'report' and tags.report_group = '{group}' and "
        f"tags.report_preset = '{preset}'",
    )
    for r in old:
        _remove_local_artifacts(tracking.run_artifact(client, r, ""))
        client.delete_run(r.info.run_id)
    note = _summary_note(group, preset, files, prov)
    tags = run_records.report_tags(
        group, preset, prov.command, prov.data, prov.seeds, prov.commits, note
    )
    # The experiment's description is the first thing its page shows: the group's table, so
    # the numbers that matter are there without choosing any column.
    client.set_experiment_tag(exp, "mlflow.note.content", note)
    run_id = run_records.create_run_record(client, exp, name, tags)
    for p in sorted(set(files)):
        if p.exists():
            client.log_artifact(run_id, str(p))
    client.set_terminated(run_id, "FINISHED")
    return run_id


def _summary_note(group: str, preset: str, files: list[Path], prov: Provenance) -> str:
    """Markdown for the MLflow UI: the group's table (as rendered) and where it comes from.

    The first line is plain text (group, preset, the table's title): the experiments list
    shows the description unrendered, cut to that line; the experiment's page renders the rest.
    """
    table = next((p for p in files if p.name == f"{GROUP_TABLE.get(group, '')}.md"), None)
    body = table.read_text(encoding="utf-8") if table is not None and table.exists() else ""
    title, _, rest = body.partition("\n")
    if title.startswith("# "):
        title, body = title[2:].strip(), rest.lstrip("\n")
    else:
        title = "Report"
    return (
        f"{group} ({preset} preset): {title}; every table and plot are artifacts of the run "
        f"report/{group}/{preset}.\n\n{body}\n\n{prov.line()}"
    )


def _remove_local_artifacts(path: Path | None) -> None:
    if path is None:
        return
    if path.is_dir() and path.name == "artifacts":
        shutil.rmtree(path, ignore_errors=True)


def budget_words(preset: str) -> str:
    """A preset's training budget in words: Adam steps, batch and distinct on-line segments."""
    cfg = resolve(preset=preset)
    batch = cfg.train.batch_size
    if cfg.data.train_source != "online":
        return f"{cfg.train.epochs} epochs of batch {batch} on rendered frames"
    steps = cfg.train.epochs * online_epoch_steps(cfg)
    distinct = steps * batch // cfg.data.online_reuse
    return f"{steps:,} Adam steps of batch {batch}, {distinct:,} distinct on-line segments"
