"""The mask ablation: segmentation quality as an ablation.

The network stays fixed: shared-0, trained on ground-truth masks by the ablation runner
(:func:`cloudpose.suite.ablate.ensure_runs`), is tested under each test-time mask source (ground
truth and imitated segmentation errors, :mod:`cloudpose.report.segmentation`), with and
without ICP; evaluations already logged are skipped, so a rerun does only what is missing.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

from cloudpose.data.mask_sources import get_mask_source
from cloudpose.evaluate import evaluate
from cloudpose.report import render_reports, segmentation
from cloudpose.store import tracking
from cloudpose.store.runs import run_name
from cloudpose.suite.ablate import RunStatus, ensure_runs
from cloudpose.suite.plan import format_seconds


@dataclass(frozen=True)
class MaskEvaluation:
    """One evaluation of the mask ablation: a seed's shared-0 under one mask source.

    Attributes:
        status: "logged" (found in the run, left alone) or "evaluated" (in this call).
        name: its metric prefix (``test-degraded-medium``; ``test`` for ground truth).
        seconds: wall time spent on it in this call.
    """

    seed: int
    source: str
    status: str
    name: str
    ads_auc: float
    ads_auc_icp: float
    seconds: float = 0.0


@dataclass
class MaskAblationResult:
    """The shared-0 runs, the evaluations under each mask source, and the report."""

    preset: str
    runs: list[RunStatus]
    evaluations: list[MaskEvaluation]
    report: object | None = None
    log: Path | None = None


def mask_ablation(
    preset: str,
    seeds: int | list[int] = 3,
    project_dir: Path | None = None,
    progress: bool = True,
    *,
    sources: Iterable[str] | None = None,
    report: bool = True,
    command: str | None = None,
    echo: Callable[[str], None] | None = None,
    out_dir: Path | None = None,
    other_data: bool = False,
) -> MaskAblationResult:
    """Segmentation quality as an ablation: shared-0, trained on ground-truth masks, tested
    under each mask source, with and without ICP; then the ``masks`` report.

    The shared-0 runs are the ablation runner's (:func:`ensure_runs`: trained only if no
    finished run of the config on the data exists). Each run gets one evaluation of its own
    test set per source (:func:`cloudpose.evaluate.evaluate` with ``segmentation``), logged to
    the run as ``test-{source}/...`` and ``test-{source}_icp/...`` (``test`` for ground
    truth); one already logged with its ICP results is left alone, so a rerun only does what
    is missing. One line per evaluation goes to ``runs/ablate-masks-{preset}.log``.

    Args:
        preset: training preset.
        seeds: S (seeds 1..S) or a list of seeds.
        project_dir: folder of ``data/``, ``runs/``, ``reports/`` and the MLflow store (cwd).
        progress: progress bars.
        sources: mask sources (default :data:`cloudpose.report.segmentation.SOURCES`: ``gt``
            and the three degradations).
        report: render the reports afterwards (the ``masks`` report and the overall ones).
        command: the command line the reports name (default: this process's).
        echo: where progress lines go (default: print).
        out_dir: the reports' folder (default :func:`cloudpose.report.build.default_out_dir`).
        other_data: train shared-0 seeds whose config finished on data of another key
            (:func:`~cloudpose.suite.ablate.ensure_runs`).
    """
    project_dir = (project_dir or Path.cwd()).resolve()
    echo = echo or (lambda s: print(s, flush=True))
    sources = list(segmentation.SOURCES if sources is None else sources)
    for s in sources:
        get_mask_source(s)  # unknown names raise with the valid list, before any training
    statuses = ensure_runs(
        [segmentation.VARIANT],
        preset,
        seeds,
        group="shared",
        project_dir=project_dir,
        progress=progress,
        echo=echo,
        other_data=other_data,
    )
    client = tracking.setup(project_dir)
    log_path = project_dir / "runs" / f"ablate-{segmentation.GROUP}-{preset}.log"
    evaluations: list[MaskEvaluation] = []
    todo = [(st, s) for st in statuses for s in sources]
    for k, (st, source) in enumerate(todo, 1):
        name = segmentation.mask_source_evaluation_name(source)
        label = f"[{k}/{len(todo)}] {run_name(segmentation.VARIANT, preset, st.seed)} {source}"
        data = client.get_run(st.run_id).data
        # the instance table is logged before the metrics (evaluate.log_evaluation)
        if f"{name}/ads_auc" in data.metrics and f"{name}_icp/ads_auc" in data.metrics:
            ev = MaskEvaluation(
                st.seed,
                source,
                "logged",
                name,
                data.metrics[f"{name}/ads_auc"],
                data.metrics[f"{name}_icp/ads_auc"],
            )
            echo(f"{label}: logged before, skipped")
        else:
            t0 = time.monotonic()
            out = evaluate(
                st.run_id, segmentation=source, project_dir=project_dir, progress=progress
            )
            ev = MaskEvaluation(
                st.seed,
                source,
                "evaluated",
                out.name,
                out.metrics.get(f"{out.name}/ads_auc", math.nan),
                out.metrics.get(f"{out.name}_icp/ads_auc", math.nan),
                time.monotonic() - t0,
            )
            echo(
                f"{label}: evaluated in {format_seconds(ev.seconds)}; ADS AUC {100 * ev.ads_auc:.1f}, "
                f"+ ICP {100 * ev.ads_auc_icp:.1f}"
            )
        evaluations.append(ev)
        with log_path.open("a", encoding="utf-8") as f:
            f.write(
                f"{time.strftime('%Y-%m-%d %H:%M:%S')}\t{k}/{len(todo)}\t"
                f"{run_name(segmentation.VARIANT, preset, st.seed)}\t{source}\t{ev.status}\t"
                f"{ev.seconds:.1f}s\trun_id={st.run_id}\tads_auc={100 * ev.ads_auc:.1f}\t"
                f"ads_auc_icp={100 * ev.ads_auc_icp:.1f}\n"
            )
    result = MaskAblationResult(preset, statuses, evaluations, log=log_path)
    if report:
        result.report = render_reports(
            preset, [segmentation.GROUP], project_dir=project_dir, command=command, out_dir=out_dir
        )
    return result
