"""The ablation runner: train and evaluate every variant of a group over seeds, then report.

The runner (:func:`ensure_runs`) and the suites built on it stay in one file over ~450 lines on
purpose: each suite is the runner plus its reports, with the runner's skip rule and log lines.

For each member variant and seed, a run that already finished *and* was evaluated in MLflow for
the same variant, preset, seed, data fingerprint and config is skipped; anything else is trained
(:func:`cloudpose.train.train` resumes an interrupted run from its checkpoint) and evaluated
(:func:`cloudpose.evaluate.evaluate`). So an interrupted suite, rerun, continues where it stopped.
One line per run goes to ``runs/ablate-{group}-{preset}.log``. Executors: ``local`` trains the
runs here, one after another; ``ray`` submits each as a Ray task to a cluster and collects them as
they finish (:mod:`cloudpose.cluster`).

The mask ablation (:func:`mask_ablation`) keeps the network fixed instead: shared-0, trained on
ground-truth masks, is tested under each test-time mask source, and evaluations already logged
are skipped the same way.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

from cloudpose import tracking
from cloudpose.cluster import EXECUTORS, RayOptions, check_cluster, import_ray
from cloudpose.config import Config, get_group, resolve
from cloudpose.runs import TEST_KEY, finished_run, run_name


@dataclass(frozen=True)
class RunStatus:
    """What happened to one (variant, seed) of a suite.

    Attributes:
        status: "skipped" (finished and evaluated before), "trained" (trained and/or evaluated
            in this call) or "failed".
        seconds: wall time spent on it in this call.
    """

    variant: str
    seed: int
    status: str
    run_id: str | None
    seconds: float
    error: str = ""


@dataclass
class SuiteResult:
    """The runs of a suite and the report it rendered."""

    group: str
    preset: str
    runs: list[RunStatus] = field(default_factory=list)
    report: object | None = None
    log: Path | None = None


def seed_list(seeds: int | Iterable[int]) -> list[int]:
    """``3`` -> [1, 2, 3]; a list is taken as it is (sorted, duplicates dropped)."""
    if isinstance(seeds, int):
        if seeds < 1:
            raise ValueError(f"seeds must be >= 1, got {seeds}")
        return list(range(1, seeds + 1))
    out = sorted({int(s) for s in seeds})
    if not out:
        raise ValueError("seeds is empty")
    return out


def _seconds_per_run_before(client, preset: str, epochs: int) -> float | None:
    """Estimated training seconds of one run from earlier runs' ``time/epoch_s`` (last epoch)."""
    per_epoch = [
        r.data.metrics["time/epoch_s"]
        for r in tracking.find_runs(client, preset=preset)
        if "time/epoch_s" in r.data.metrics
    ]
    return sum(per_epoch) / len(per_epoch) * epochs if per_epoch else None


def _fmt_s(s: float | None) -> str:
    if s is None or not math.isfinite(s):
        return "unknown"
    s = round(s)
    return f"{s // 3600}h{s % 3600 // 60:02d}m" if s >= 3600 else f"{s // 60}m{s % 60:02d}s"


def ensure_runs(
    variants: list[str],
    preset: str,
    seeds: int | Iterable[int],
    *,
    group: str,
    project_dir: Path | None = None,
    progress: bool = True,
    keep_going: bool = False,
    overrides: dict | None = None,
    echo: Callable[[str], None] | None = None,
    executor: str = "local",
    ray: RayOptions | None = None,
) -> list[RunStatus]:
    """Train and evaluate every (variant, seed) that has no finished, evaluated run yet.

    Args:
        variants: variant names.
        preset: training preset.
        seeds: S (seeds 1..S) or a list of seeds.
        group: the experiment a new run goes to.
        project_dir: folder of ``data/``, ``runs/`` and the default MLflow store (cwd).
        progress: per-epoch progress bars (from training) and ICP bars.
        keep_going: after a failed run, log it and go on with the next (default: raise).
        overrides: config overrides (``{"train": {"epochs": 1}}``), as in ``resolve``.
        echo: where the per-run progress lines go (default: print).
        executor: "local" (here, one run after another) or "ray" (a Ray task per run).
        ray: the cluster and each task's resources, for the ray executor.

    Returns:
        One status per (variant, seed), in order.
    """
    from cloudpose import pipeline
    from cloudpose.data import dataset

    if executor not in EXECUTORS:
        raise ValueError(f"executor {executor!r}: expected one of {', '.join(EXECUTORS)}")
    if executor == "ray":
        # before any data is made: without Ray, say how to install it; a cluster that does not
        # answer is said before a long data preparation, not after
        import_ray()
        check_cluster(ray or RayOptions())
    project_dir = (project_dir or Path.cwd()).resolve()
    echo = echo or (lambda s: print(s, flush=True))
    seeds = seed_list(seeds)
    client = tracking.setup(project_dir)
    log_path = project_dir / "runs" / f"ablate-{group}-{preset}.log"
    log_path.parent.mkdir(parents=True, exist_ok=True)
    todo = [resolve(v, preset, s, overrides) for v in variants for s in seeds]
    prepared: dict[str, dataset.Prepared] = {}

    def data_of(cfg: Config) -> dataset.Prepared:
        key = repr(cfg.data)
        if key not in prepared:  # made once per data config, shared by its runs
            prepared[key] = dataset.prepare_data(cfg.data, project_dir, progress=progress)
        return prepared[key]

    def fingerprint(cfg: Config) -> str:
        return data_of(cfg).key

    pending = [cfg for cfg in todo if finished_run(client, cfg, fingerprint(cfg)) is None]
    prior = _seconds_per_run_before(client, preset, todo[0].train.epochs) if todo else None
    durations: list[float] = []
    out: dict[int, RunStatus] = {}
    echo(
        f"ablation {group}/{preset}: {len(todo)} runs ({len(variants)} variants x "
        f"{len(seeds)} seeds), {len(todo) - len(pending)} already done, {len(pending)} to run "
        f"({executor}); log {log_path}"
    )

    def failed(k: int, cfg: Config, exc: BaseException, seconds: float) -> None:
        name = run_name(cfg.variant, cfg.preset, cfg.seed)
        st = RunStatus(
            cfg.variant, cfg.seed, "failed", None, seconds, f"{type(exc).__name__}: {exc}"
        )
        out[k] = st
        _log(log_path, k, len(todo), name, st, None)
        echo(f"[{k}/{len(todo)}] {name}: FAILED ({st.error})")

    def trained(k: int, cfg: Config, run_id: str, auc: float | None, seconds: float) -> None:
        name = run_name(cfg.variant, cfg.preset, cfg.seed)
        durations.append(seconds)
        st = RunStatus(cfg.variant, cfg.seed, "trained", run_id, seconds)
        out[k] = st
        _log(log_path, k, len(todo), name, st, auc)
        echo(
            f"[{k}/{len(todo)}] {name}: done in {_fmt_s(seconds)}; test ADS AUC "
            f"{100 * (math.nan if auc is None else auc):.1f}"
        )

    sweep = None
    if executor == "ray" and pending:
        from cloudpose.cluster import RaySweep

        tracking.experiment_id(client, group, project_dir)  # made here, not by racing tasks
        sweep = RaySweep(ray or RayOptions(), project_dir, group)
    try:
        for k, cfg in enumerate(todo, 1):
            name = run_name(cfg.variant, cfg.preset, cfg.seed)
            data = fingerprint(cfg)
            done = finished_run(client, cfg, data)
            if done is not None:
                st = RunStatus(cfg.variant, cfg.seed, "skipped", done.info.run_id, 0.0)
                out[k] = st
                _log(log_path, k, len(todo), name, st, done.data.metrics.get(TEST_KEY))
                echo(f"[{k}/{len(todo)}] {name}: finished before, skipped")
                continue
            if sweep is not None:
                sweep.submit(k, cfg)
                echo(f"[{k}/{len(todo)}] {name}: submitted to Ray")
                continue
            left = len(pending) - pending.index(cfg) if cfg in pending else 1
            per_run = sum(durations) / len(durations) if durations else prior
            echo(
                f"[{k}/{len(todo)}] {name}: training + evaluation; {left} run(s) left, "
                f"estimated {_fmt_s(per_run * left if per_run else None)} to go"
            )
            t0 = time.monotonic()
            try:
                result = pipeline.train_and_evaluate(
                    cfg, project_dir=project_dir, group=group, progress=progress, data=data_of(cfg)
                )
            except KeyboardInterrupt:
                st = RunStatus(cfg.variant, cfg.seed, "interrupted", None, time.monotonic() - t0)
                _log(log_path, k, len(todo), name, st, None)
                raise
            except Exception as exc:
                failed(k, cfg, exc, time.monotonic() - t0)
                if not keep_going:
                    raise
                continue
            auc = result.evaluation.metrics.get(TEST_KEY)
            trained(k, cfg, result.train.run_id, auc, time.monotonic() - t0)
        for k, cfg, res, exc in sweep.results() if sweep is not None else ():
            if exc is not None:
                failed(k, cfg, exc, math.nan)
                if not keep_going:
                    raise exc
                continue
            trained(k, cfg, res["run_id"], res["test_ads_auc"], res["seconds"])
    finally:
        if sweep is not None:
            sweep.close()
    return [out[k] for k in sorted(out)]


def _log(path: Path, k: int, n: int, name: str, st: RunStatus, ads_auc: float | None) -> None:
    stamp = time.strftime("%Y-%m-%d %H:%M:%S")
    auc = f"{100 * ads_auc:.1f}" if ads_auc is not None else "-"
    line = (
        f"{stamp}\t{k}/{n}\t{name}\t{st.status}\t{st.seconds:.1f}s\t"
        f"run_id={st.run_id or '-'}\ttest_ads_auc={auc}"
    )
    if st.error:
        line += f"\terror={st.error}"
    with path.open("a", encoding="utf-8") as f:
        f.write(line + "\n")


def run_group(
    group: str,
    preset: str,
    seeds: int | list[int] = 3,
    project_dir: Path | None = None,
    progress: bool = True,
    *,
    keep_going: bool = False,
    report: bool = True,
    command: str | None = None,
    overrides: dict | None = None,
    echo: Callable[[str], None] | None = None,
    executor: str = "local",
    ray: RayOptions | None = None,
) -> SuiteResult:
    """Train and evaluate every member of ``group`` over ``seeds``, then render its reports.

    Args:
        group: ablation group (``ablations/variants.toml``: shared, rotation, loss).
        preset: training preset (``ablations/presets.toml``).
        seeds: S (seeds 1..S) or a list of seeds.
        project_dir: folder of ``data/``, ``runs/``, ``reports/`` and the MLflow store (cwd).
        progress: progress bars.
        keep_going: go on after a failed run (it is logged); default: stop.
        report: render the group's reports afterwards (:func:`cloudpose.report.render_reports`).
        command: the command line the reports name (default: this process's).
        overrides: config overrides for every run.
        echo: where progress lines go (default: print).
        executor, ray: where the runs train (:func:`ensure_runs`).
    """
    g = get_group(group)
    project_dir = (project_dir or Path.cwd()).resolve()
    statuses = ensure_runs(
        list(g.members),
        preset,
        seeds,
        group=group,
        project_dir=project_dir,
        progress=progress,
        keep_going=keep_going,
        overrides=overrides,
        echo=echo,
        executor=executor,
        ray=ray,
    )
    result = SuiteResult(
        group, preset, statuses, log=project_dir / "runs" / f"ablate-{group}-{preset}.log"
    )
    if report:
        from cloudpose.report import render_reports

        result.report = render_reports(preset, [group], project_dir=project_dir, command=command)
    return result


def occlusion_report(
    preset: str,
    seeds: int | list[int] = 3,
    project_dir: Path | None = None,
    progress: bool = True,
    *,
    group: str | None = None,
    train: bool = True,
    command: str | None = None,
    echo: Callable[[str], None] | None = None,
):
    """The occlusion plot: shared-0 without and with ICP (and a group's variants if asked).

    Trains and evaluates the missing runs first unless ``train`` is False, then renders the
    reports (the overall ones, and the group's when ``group`` is given).
    """
    from cloudpose.report import render_reports

    project_dir = (project_dir or Path.cwd()).resolve()
    variants = list(get_group(group).members) if group else ["shared-0"]
    if train:
        ensure_runs(
            variants,
            preset,
            seeds,
            group=group or "shared",
            project_dir=project_dir,
            progress=progress,
            echo=echo,
        )
    return render_reports(
        preset, [group] if group else [], project_dir=project_dir, command=command
    )


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
    """
    from cloudpose.data.segments import get_mask_source
    from cloudpose.evaluate import evaluate
    from cloudpose.report import segmentation

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
    )
    client = tracking.setup(project_dir)
    log_path = project_dir / "runs" / f"ablate-{segmentation.GROUP}-{preset}.log"
    evaluations: list[MaskEvaluation] = []
    todo = [(st, s) for st in statuses for s in sources]
    for k, (st, source) in enumerate(todo, 1):
        name = segmentation.evaluation_name(source)
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
                f"{label}: evaluated in {_fmt_s(ev.seconds)}; ADS AUC {100 * ev.ads_auc:.1f}, "
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
        from cloudpose.report import render_reports

        result.report = render_reports(
            preset, [segmentation.GROUP], project_dir=project_dir, command=command
        )
    return result
