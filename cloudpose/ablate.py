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

from cloudpose import pipeline, tracking
from cloudpose.cluster import EXECUTORS, RayOptions, RaySweep, check_cluster, import_ray
from cloudpose.config import Config, get_group, resolve
from cloudpose.data import dataset
from cloudpose.data.dataset import data_fingerprint, dataset_root, synthetic_root
from cloudpose.data.mask_sources import get_mask_source
from cloudpose.data.synth.frames import frame_id
from cloudpose.data.synth.write import _frame_done
from cloudpose.evaluate import evaluate
from cloudpose.report import render_reports, segmentation
from cloudpose.report.build import default_out_dir
from cloudpose.report.claims import evaluate_claims, paper_claims, seeds_wanted
from cloudpose.report.runs import load_runs
from cloudpose.report.stats import UNRESOLVED
from cloudpose.runs import TEST_KEY, finished_run, run_has_config, run_name


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
    out_dir: Path | None = None,
) -> SuiteResult:
    """Train and evaluate every member of ``group`` over ``seeds``, then render its reports.

    Args:
        group: ablation group (``ablations/variants.toml``; :func:`cloudpose.config.groups`).
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
        out_dir: the reports' folder (default :func:`cloudpose.report.build.default_out_dir`).
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
        result.report = render_reports(
            preset, [group], project_dir=project_dir, command=command, out_dir=out_dir
        )
    return result


MAX_SEEDS = 10
"""Default cap on the seeds :func:`resolve_claims` adds to a variant."""


@dataclass
class ResolveRound:
    """One round of :func:`resolve_claims`: the seeds it asked for and what the claims said."""

    wanted: dict[str, int]
    unresolved: int
    claims: int
    runs: list[RunStatus] = field(default_factory=list)


def resolve_claims(
    group: str,
    preset: str,
    project_dir: Path | None = None,
    *,
    max_seeds: int = MAX_SEEDS,
    step: int = 2,
    overrides: dict | None = None,
    echo: Callable[[str], None] | None = None,
    replicates: int = 500,
    **ensure_kwargs,
) -> list[ResolveRound]:
    """Add seeds to the variants of ``group``'s claims until each is decided or at the cap.

    Each round measures the paper's claims whose two sides are both members of ``group``
    (:func:`cloudpose.report.claims.evaluate_claims` on the preset's runs), asks
    :func:`cloudpose.report.claims.seeds_wanted` which variants need more seeds for a claim that
    is "not resolved" with an interval wider than twice its margin, trains at most ``step`` more
    seeds of each through :func:`ensure_runs` (finished runs skipped, the same executors), and
    measures again. It stops when no claim wants seeds, or every variant that wants them has
    ``max_seeds``.

    Args:
        group: ablation group whose claims to decide.
        preset: training preset.
        project_dir: the project folder (cwd).
        max_seeds: the cap on seeds per variant.
        step: most seeds added to a variant per round (the estimate of
            :func:`~cloudpose.report.claims.seeds_wanted` can overshoot; a verdict reached
            earlier saves the rest).
        overrides: config overrides of every run.
        echo: where progress lines go (default: print).
        replicates: bootstrap replicates per claim in the rounds' measurements.
        **ensure_kwargs: passed to :func:`ensure_runs` (progress, keep_going, executor, ray).

    Returns:
        One :class:`ResolveRound` per measurement, the last one with nothing wanted or capped.
    """
    if max_seeds < 1 or step < 1:
        raise ValueError(f"max_seeds and step must be >= 1, got {max_seeds} and {step}")
    members = set(get_group(group).members)
    claims = [c for c in paper_claims() if {c.favoured[0], c.other[0]} <= members]
    project_dir = (project_dir or Path.cwd()).resolve()
    echo = echo or (lambda s: print(s, flush=True))
    client = tracking.setup(project_dir)
    rounds: list[ResolveRound] = []
    while True:
        runs = load_runs(preset, client=client)
        results = evaluate_claims(runs, claims, replicates=replicates)
        unresolved = sum(r.diff.verdict == UNRESOLVED for r in results)
        have = {v: len(runs.of(v)) for v in members}
        wanted = {
            v: min(n, have.get(v, 0) + step)
            for v, n in seeds_wanted(results, cap=max_seeds).items()
            if v in members
        }
        rnd = ResolveRound(wanted, unresolved, len(results))
        rounds.append(rnd)
        echo(
            f"claims of {group}/{preset}: {unresolved} of {len(results)} not resolved; "
            + (
                "more seeds for " + ", ".join(f"{v} -> {n}" for v, n in wanted.items())
                if wanted
                else f"no variant needs more seeds (cap {max_seeds})"
            )
        )
        if not wanted:
            return rounds
        if (
            len(rounds) > 1
            and rounds[-2].wanted == wanted
            and not any(st.status == "trained" for st in rounds[-2].runs)
        ):
            raise RuntimeError(
                f"claims of {group}/{preset}: the last round trained no run and the same seeds "
                f"are still wanted ({wanted}); see the log in {project_dir / 'runs'}"
            )
        for variant, n in wanted.items():
            rnd.runs += ensure_runs(
                [variant],
                preset,
                n,
                group=group,
                project_dir=project_dir,
                overrides=overrides,
                echo=echo,
                **ensure_kwargs,
            )


def occlusion_report(
    preset: str,
    seeds: int | list[int] = 3,
    project_dir: Path | None = None,
    progress: bool = True,
    *,
    group: str | None = None,
    train_missing: bool = False,
    command: str | None = None,
    echo: Callable[[str], None] | None = None,
    out_dir: Path | None = None,
):
    """The occlusion plot: shared-0 without and with ICP (and a group's variants if asked).

    Renders from the runs in MLflow only. With ``train_missing`` the runs it needs that the
    store lacks are trained and evaluated first; without, a missing run raises
    :class:`MissingRuns` naming them.
    """
    project_dir = (project_dir or Path.cwd()).resolve()
    variants = list(get_group(group).members) if group else ["shared-0"]
    if not train_missing:
        missing = missing_report_runs(variants, preset, seeds, project_dir)
        if missing:
            raise MissingRuns(missing)
    else:
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
        preset, [group] if group else [], project_dir=project_dir, command=command, out_dir=out_dir
    )


class MissingRuns(ValueError):
    """A report needs runs that the store does not hold (:attr:`names`)."""

    def __init__(self, names: list[str]):
        self.names = names
        super().__init__(f"{len(names)} run(s) missing from the store: {', '.join(names)}")


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
        result.report = render_reports(
            preset, [segmentation.GROUP], project_dir=project_dir, command=command, out_dir=out_dir
        )
    return result


# --- plans: what a suite will do, printed before it starts -------------------------------

RENDER_S_PER_FRAME = 1 / 2.94 + 1 / 12.9
"""Seconds to render one synthetic frame and cache its segments on a 2-core CPU: synthesis at
2.9 and segment preparation at 12.9 frames/s (``make bench``, reports/benchmarks.md)."""

TRAIN_S_PER_POINT = 2.1e-5
"""Training seconds per (sample x input point), per-epoch validation included: shared-0 on the
cpu preset took ~19.5 s an epoch of 3,583 segments x 256 points on a 2-core CPU (the committed
store, reports/cpu/mlflow-store.tar.xz; 25 epochs, ~8 min)."""

EVAL_S_PER_TEST_FRAME = 1.0
"""Seconds of evaluation (network, ICP, metrics, with and without ICP) per test frame, from
the same runs: ~11 min a run, of which ~2.5 min after training for 150 test frames."""

RUN_OVERHEAD_S = 30.0
"""Seconds a run spends regardless of its size: start-up, BatchNorm re-estimation, the real
development frames' evaluation, MLflow logging."""

SEGMENTS_PER_FRAME = 4.5
"""Training segments per synthetic training frame (the cpu preset: 3,583 from 800 frames,
10% of them held out)."""


@dataclass(frozen=True)
class PlannedRun:
    """One (variant, seed) of a plan.

    Attributes:
        status: "finished" (a finished, evaluated run of this config on this data exists: it
            is skipped) or "to train".
        run_id: the finished run, if any.
    """

    variant: str
    seed: int
    preset: str
    status: str
    run_id: str | None = None

    @property
    def name(self) -> str:
        return run_name(self.variant, self.preset, self.seed)


@dataclass
class Plan:
    """What a command will do before it does it: frames, runs, evaluations, time.

    Attributes:
        title: what runs, e.g. ``ablation shared/cpu``.
        frames: dataset root -> (frames to render, frames it needs).
        runs: every (variant, seed), finished or to train.
        per_run_s: estimated seconds of one run (training + evaluation).
        per_run_source: where ``per_run_s`` comes from, in words.
        evaluations: extra evaluations of finished runs (name -> seconds each), e.g. the mask
            ablation's sources.
        notes: further lines (what follows the runs, caveats).
        data_ready: whether every dataset is rendered (the finished runs are found by the
            data's fingerprint, so before rendering none is known for certain).
        matched_elsewhere: with the data not rendered, runs of the same config that the
            store holds finished on some data.
        finished: what happens to a finished run, in words.
    """

    title: str
    frames: dict[str, tuple[int, int]] = field(default_factory=dict)
    runs: list[PlannedRun] = field(default_factory=list)
    per_run_s: float | None = None
    per_run_source: str = ""
    evaluations: list[tuple[str, float]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    data_ready: bool = True
    matched_elsewhere: int = 0
    finished: str = "finished before (skipped)"

    @property
    def to_train(self) -> list[PlannedRun]:
        return [r for r in self.runs if r.status != "finished"]

    @property
    def render_s(self) -> float:
        return sum(n for n, _ in self.frames.values()) * RENDER_S_PER_FRAME

    @property
    def total_s(self) -> float | None:
        if self.to_train and self.per_run_s is None:
            return None
        runs = len(self.to_train) * (self.per_run_s or 0.0)
        return self.render_s + runs + sum(s for _, s in self.evaluations)

    def lines(self) -> list[str]:
        """The plan as the commands print it."""
        out = [f"plan: {self.title}"]
        for root, (todo, wanted) in self.frames.items():
            if todo:
                out.append(
                    f"  data: render {todo:,} of {wanted:,} frames into {root} "
                    f"(~{_fmt_s(todo * RENDER_S_PER_FRAME)} at {RENDER_S_PER_FRAME:.2f} s a frame "
                    "on 2 cores, reports/benchmarks.md)"
                )
            else:
                out.append(f"  data: {root}, all {wanted:,} frames rendered")
        if self.runs:
            variants = list(dict.fromkeys(r.variant for r in self.runs))
            seeds = sorted({r.seed for r in self.runs})
            done = len(self.runs) - len(self.to_train)
            out.append(
                f"  runs: {len(self.runs)} ({len(variants)} variant(s) x {len(seeds)} seed(s)): "
                f"{done} {self.finished}, {len(self.to_train)} to train + evaluate"
            )
            for v in variants:
                mine = [r for r in self.runs if r.variant == v]
                parts = []
                for status in ("finished", "to train"):
                    s = [str(r.seed) for r in mine if r.status == status]
                    if s:
                        parts.append(f"seed {','.join(s)} {status}")
                out.append(f"    {v:<18} {'; '.join(parts)}")
            if not self.data_ready:
                more = (
                    f" ({self.matched_elsewhere} of them have finished runs of the same config "
                    "in the store)"
                    if self.matched_elsewhere
                    else ""
                )
                out.append(
                    "    (the data is not rendered yet, so every run counts as to train"
                    f"{more}; a run finished on identical data is skipped after rendering)"
                )
        for name, seconds in self.evaluations:
            out.append(f"  evaluate: {name} (~{_fmt_s(seconds)})")
        n = len(self.to_train)
        if n:
            out.append(
                f"  time: ~{_fmt_s(self.per_run_s)} a run ({self.per_run_source}); "
                f"{n} run(s) x ~{_fmt_s(self.per_run_s)} = ~{_fmt_s(n * (self.per_run_s or 0))}"
            )
        total = self.total_s
        out.append(
            f"  total: ~{_fmt_s(total)}" + (" (nothing to do)" if not total else "")
            if total is not None
            else "  total: unknown"
        )
        out += [f"  {line}" for line in self.notes]
        return out

    def text(self) -> str:
        return "\n".join(self.lines())


def estimate_run_s(cfg: Config) -> tuple[float, str]:
    """Seconds one run of ``cfg`` takes (training + evaluation), from its settings alone.

    The rates are the cpu preset's shared-0 runs on a 2-core CPU (:data:`TRAIN_S_PER_POINT`,
    :data:`EVAL_S_PER_TEST_FRAME`, :data:`RUN_OVERHEAD_S`); variants that share layers train
    faster, a GPU much faster.

    Returns:
        (seconds, where the figure comes from, in words).
    """
    t, d = cfg.train, cfg.data
    if d.train_source == "online":
        samples = d.online_epoch_segments
    else:
        samples = d.train_frames * SEGMENTS_PER_FRAME
    steps = t.epochs * max(1, math.ceil(samples / t.batch_size))
    train_s = steps * t.batch_size * t.n_points * TRAIN_S_PER_POINT
    seconds = RUN_OVERHEAD_S + train_s + d.test_frames * EVAL_S_PER_TEST_FRAME
    source = (
        f"from the preset: {steps:,} Adam steps of {t.batch_size} x {t.n_points} points and "
        f"{d.test_frames} test frames at the rate of shared-0 on the cpu preset, 2-core CPU"
    )
    return seconds, source


def _measured_run_s(client, preset: str, variants: list[str]) -> tuple[float, int] | None:
    """Median wall time of the finished runs of ``preset`` in the store (of ``variants`` when
    they have any), and how many runs it is from."""
    found = [
        r
        for r in tracking.find_runs(client, preset=preset)
        if r.info.end_time and r.info.start_time and TEST_KEY in r.data.metrics
    ]
    own = [r for r in found if r.data.tags.get("variant") in variants]
    runs = own or found
    if not runs:
        return None
    seconds = sorted((r.info.end_time - r.info.start_time) / 1000 for r in runs)
    return seconds[len(seconds) // 2], len(seconds)


def _frames_to_render(cfg: Config, project_dir: Path) -> tuple[str, int, int, bool]:
    """(root, frames to render, frames needed, whether its image sets list what ``cfg``
    asks for) of ``cfg``'s synthetic data; a real root needs no rendering."""
    d = cfg.data
    if d.root:
        return str(dataset_root(d, project_dir)), 0, 0, True
    root = synthetic_root(d, project_dir)
    wanted = [("train", i) for i in range(d.train_frames)]
    wanted += [("test", i) for i in range(d.test_frames)]
    todo = sum(not _frame_done(root, frame_id(s, i)) for s, i in wanted)
    lists = True
    for name, n in (("train", d.train_frames), ("test", d.test_frames)):
        path = root / "image_sets" / f"{name}.txt"
        lines = path.read_text().split() if path.is_file() else []
        lists = lists and len(lines) == n
    try:
        shown = str(root.relative_to(project_dir))
    except ValueError:
        shown = str(root)
    return shown, todo, len(wanted), lists


def plan_runs(
    variants: list[str],
    preset: str,
    seeds: int | Iterable[int],
    *,
    title: str,
    project_dir: Path | None = None,
    overrides: dict | None = None,
) -> Plan:
    """The plan of :func:`ensure_runs` for ``variants`` x ``seeds`` (:func:`plan_configs`)."""
    todo = [resolve(v, preset, s, overrides) for v in variants for s in seed_list(seeds)]
    return plan_configs(todo, title=title, project_dir=project_dir)


def plan_configs(
    todo: list[Config],
    *,
    title: str,
    project_dir: Path | None = None,
    finished: str = "finished before (skipped)",
) -> Plan:
    """The plan of training and evaluating ``todo``, made without rendering or training.

    Frames are counted on disk; a run counts as finished when the store holds a finished,
    evaluated run of its config on its data (the data's fingerprint needs the rendered frames:
    before they exist, every run counts as to train). The time of a run is the median of the
    preset's finished runs in the store when there are any, else :func:`estimate_run_s`.

    Args:
        todo: the runs' configs.
        title: what the plan is of.
        project_dir: folder of ``data/`` and the default MLflow store (cwd).
        finished: what happens to a finished run, in words.
    """
    project_dir = (project_dir or Path.cwd()).resolve()
    client = tracking.setup(project_dir)
    plan = Plan(title, finished=finished)
    preset = todo[0].preset if todo else ""
    variants = list(dict.fromkeys(c.variant for c in todo))
    keys: dict[str, str | None] = {}
    for cfg in todo:
        k = repr(cfg.data)
        if k in keys:
            continue
        root, n, wanted, lists = _frames_to_render(cfg, project_dir)
        plan.frames[root] = (n, wanted)
        ready = n == 0 and lists
        keys[k] = data_fingerprint(cfg.data, project_dir) if ready else None
        plan.data_ready = plan.data_ready and ready
    for cfg in todo:
        data = keys[repr(cfg.data)]
        done = finished_run(client, cfg, data) if data is not None else None
        if data is None and finished_run_any_data(client, cfg) is not None:
            plan.matched_elsewhere += 1
        plan.runs.append(
            PlannedRun(
                cfg.variant,
                cfg.seed,
                preset,
                "finished" if done is not None else "to train",
                done.info.run_id if done is not None else None,
            )
        )
    measured = _measured_run_s(client, preset, variants)
    if measured is not None:
        plan.per_run_s = measured[0]
        plan.per_run_source = (
            f"median wall time of {measured[1]} finished {preset} run(s) in this MLflow store"
        )
    elif todo:
        plan.per_run_s, plan.per_run_source = estimate_run_s(todo[0])
    return plan


def finished_run_any_data(client, cfg: Config):
    """The newest finished, evaluated run of exactly ``cfg`` on any data, or None (what a
    report, which reads MLflow only, can use)."""
    for r in tracking.find_runs(client, variant=cfg.variant, preset=cfg.preset, seed=cfg.seed):
        if TEST_KEY in r.data.metrics and run_has_config(r, cfg):
            return r
    return None


def plan_group(
    group: str,
    preset: str,
    seeds: int | Iterable[int] = 3,
    project_dir: Path | None = None,
    *,
    overrides: dict | None = None,
    report: bool = True,
    out_dir: Path | None = None,
) -> Plan:
    """The plan of :func:`run_group`: the group's runs, then its reports."""
    project_dir = (project_dir or Path.cwd()).resolve()
    g = get_group(group)
    plan = plan_runs(
        list(g.members),
        preset,
        seeds,
        title=f"ablation {group}/{preset}, seeds {_seed_text(seeds)}",
        project_dir=project_dir,
        overrides=overrides,
    )
    if report:
        out = out_dir or default_out_dir(project_dir, preset)
        plan.notes.append(f"then: the group's reports into {_shown(out, project_dir)}/")
    return plan


def plan_masks(
    preset: str,
    seeds: int | Iterable[int] = 3,
    project_dir: Path | None = None,
    *,
    sources: Iterable[str] | None = None,
    out_dir: Path | None = None,
) -> Plan:
    """The plan of :func:`mask_ablation`: the shared-0 runs, then one evaluation per seed and
    mask source that is not logged yet (each ~ a run's evaluation)."""
    project_dir = (project_dir or Path.cwd()).resolve()
    sources = list(segmentation.SOURCES if sources is None else sources)
    plan = plan_runs(
        [segmentation.VARIANT],
        preset,
        seeds,
        title=f"mask ablation {preset}, seeds {_seed_text(seeds)}, sources {', '.join(sources)}",
        project_dir=project_dir,
    )
    client = tracking.setup(project_dir)
    cfg = resolve(segmentation.VARIANT, preset)
    each = cfg.data.test_frames * EVAL_S_PER_TEST_FRAME + RUN_OVERHEAD_S / 3
    logged = 0
    for r in plan.runs:
        metrics = client.get_run(r.run_id).data.metrics if r.run_id else {}
        todo = []
        for source in sources:
            name = segmentation.evaluation_name(source)
            if f"{name}/ads_auc" in metrics and f"{name}_icp/ads_auc" in metrics:
                logged += 1
            elif r.run_id or name != TEST_KEY.split("/")[0]:  # a new run evaluates its own
                todo.append(source)
        if todo:
            label = f"{r.name} under {', '.join(todo)} masks, ~{_fmt_s(each)} each"
            plan.evaluations.append((label, each * len(todo)))
    plan.notes.append(f"{logged} mask evaluation(s) logged before (skipped)")
    out = out_dir or default_out_dir(project_dir, preset)
    plan.notes.append(f"then: table_masks and occlusion_masks into {_shown(out, project_dir)}/")
    return plan


def missing_report_runs(
    variants: list[str], preset: str, seeds: int | Iterable[int], project_dir: Path | None = None
) -> list[str]:
    """Names of the runs a report of ``variants`` x ``seeds`` needs that the store lacks (a
    finished, evaluated run of the config on any data; the report reads MLflow only)."""
    client = tracking.setup((project_dir or Path.cwd()).resolve())
    return [
        run_name(v, preset, s)
        for v in variants
        for s in seed_list(seeds)
        if finished_run_any_data(client, resolve(v, preset, s)) is None
    ]


def _seed_text(seeds: int | Iterable[int]) -> str:
    s = seed_list(seeds)
    return (
        f"{s[0]}-{s[-1]}"
        if s == list(range(s[0], s[-1] + 1)) and len(s) > 1
        else ",".join(map(str, s))
    )


def _shown(path: Path, project_dir: Path) -> str:
    try:
        return str(Path(path).resolve().relative_to(project_dir))
    except ValueError:
        return str(path)
