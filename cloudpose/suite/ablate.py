"""The ablation runner: train and evaluate every variant of a group over seeds, then report.

For each member variant and seed, a run that already finished *and* was evaluated in MLflow for
the same variant, preset, seed, data key and config is skipped; anything else is trained
(:func:`cloudpose.train.loop.train` resumes an interrupted run from its checkpoint) and evaluated
(:func:`cloudpose.evaluate.evaluate`). So an interrupted suite, rerun, continues where it stopped.
One line per run goes to ``runs/ablate-{group}-{preset}.log``. Executors: ``local`` trains the
runs here, one after another; ``ray`` submits each as a Ray task to a cluster and collects them as
they finish (:mod:`cloudpose.suite.cluster`).

Built on the runner: :func:`run_group` (a group, then its reports), :func:`resolve_claims`
(seeds added until the paper's claims are decided) and :func:`occlusion_report`. The mask
ablation is :mod:`cloudpose.suite.masks`; what a suite will do, before it starts, is
:mod:`cloudpose.suite.plan`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from cloudpose.config import Config
from cloudpose.data import dataset
from cloudpose.registry import get_group, resolve
from cloudpose.report import render_reports
from cloudpose.report.claims import evaluate_claims, paper_claims, seeds_wanted
from cloudpose.report.runs import load_runs
from cloudpose.report.stats import MAX_SEEDS, UNRESOLVED
from cloudpose.store import tracking
from cloudpose.store.runs import TEST_KEY, finished_run, run_dir, run_name
from cloudpose.suite import pipeline
from cloudpose.suite.cluster import EXECUTORS, RayOptions, RaySweep, check_cluster, import_ray
from cloudpose.suite.plan import (
    finished_run_any_data,
    format_seconds,
    missing_report_runs,
    seed_list,
)


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


def _seconds_per_run_before(client, preset: str, epochs: int) -> float | None:
    """Estimated training seconds of one run from earlier runs' ``time/epoch_s`` (last epoch)."""
    per_epoch = [
        r.data.metrics["time/epoch_s"]
        for r in tracking.find_runs(client, preset=preset)
        if "time/epoch_s" in r.data.metrics
    ]
    return sum(per_epoch) / len(per_epoch) * epochs if per_epoch else None


@dataclass
class _Progress:
    """What one :func:`ensure_runs` call tells: each run's status, its log line and its echo.

    Attributes:
        n: runs in the suite.
        log_path: the suite's log (one line per run).
        echo: where the progress lines go.
        prior: estimated seconds of one run from earlier runs in the store, or None.
        durations: seconds of the runs trained whole in this call.
        statuses: {1-based run number: its status}.
    """

    n: int
    log_path: Path
    echo: Callable[[str], None]
    prior: float | None
    durations: list[float] = field(default_factory=list)
    statuses: dict[int, RunStatus] = field(default_factory=dict)

    def _record(self, k: int, cfg: Config, st: RunStatus, ads_auc: float | None, what: str) -> None:
        name = run_name(cfg.variant, cfg.preset, cfg.seed)
        self.statuses[k] = st
        _log(self.log_path, k, self.n, name, st, ads_auc)
        self.echo(f"[{k}/{self.n}] {name}: {what}")

    def say(self, k: int, cfg: Config, what: str) -> None:
        """A progress line about run ``k`` that records nothing."""
        self.echo(f"[{k}/{self.n}] {run_name(cfg.variant, cfg.preset, cfg.seed)}: {what}")

    def skipped(self, k: int, cfg: Config, done) -> None:
        """Run ``k`` finished and was evaluated before (``done``: its MLflow run)."""
        st = RunStatus(cfg.variant, cfg.seed, "skipped", done.info.run_id, 0.0)
        self._record(k, cfg, st, done.data.metrics.get(TEST_KEY), "finished before, skipped")

    def starting(self, k: int, cfg: Config, left: int) -> None:
        """Run ``k`` starts here, ``left`` runs to go with it: the time they may take."""
        per_run = sum(self.durations) / len(self.durations) if self.durations else self.prior
        self.say(
            k,
            cfg,
            f"training + evaluation; {left} run(s) left, "
            f"estimated {format_seconds(per_run * left if per_run else None)} to go",
        )

    def trained(
        self,
        k: int,
        cfg: Config,
        run_id: str,
        auc: float | None,
        seconds: float,
        whole: bool = True,
    ) -> None:
        """Run ``k`` was trained and evaluated in ``seconds``; ``whole``: not resumed from its
        checkpoint (only such runs tell how long a run takes)."""
        if whole:
            self.durations.append(seconds)
        st = RunStatus(cfg.variant, cfg.seed, "trained", run_id, seconds)
        self._record(
            k,
            cfg,
            st,
            auc,
            f"done in {format_seconds(seconds)}; test ADS AUC "
            f"{100 * (math.nan if auc is None else auc):.1f}",
        )

    def failed(self, k: int, cfg: Config, exc: BaseException, seconds: float) -> None:
        """Run ``k`` raised ``exc`` after ``seconds``."""
        error = f"{type(exc).__name__}: {exc}"
        st = RunStatus(cfg.variant, cfg.seed, "failed", None, seconds, error)
        self._record(k, cfg, st, None, f"FAILED ({error})")

    def interrupted(self, k: int, cfg: Config, seconds: float) -> None:
        """Run ``k`` was interrupted (Ctrl-C): logged, the suite stops."""
        st = RunStatus(cfg.variant, cfg.seed, "interrupted", None, seconds)
        _log(self.log_path, k, self.n, run_name(cfg.variant, cfg.preset, cfg.seed), st, None)


def _check_executor(executor: str, ray: RayOptions | None) -> None:
    """Raise for an unknown executor; for ``ray``, before any data is made, say how to install
    Ray where it is missing and whether the cluster answers (not after a long data
    preparation)."""
    if executor not in EXECUTORS:
        raise ValueError(f"executor {executor!r}: expected one of {', '.join(EXECUTORS)}")
    if executor == "ray":
        import_ray()
        check_cluster(ray or RayOptions())


def _data_once(project_dir: Path, progress: bool) -> Callable[[Config], dataset.Prepared]:
    """``data_of(cfg)``: the prepared data of a config, made once per data config and shared by
    its runs."""
    prepared: dict[str, dataset.Prepared] = {}

    def data_of(cfg: Config) -> dataset.Prepared:
        config = repr(cfg.data)
        if config not in prepared:
            prepared[config] = dataset.prepare_data(cfg.data, project_dir, progress=progress)
        return prepared[config]

    return data_of


def _train_here(
    book: _Progress,
    k: int,
    cfg: Config,
    data: dataset.Prepared,
    *,
    project_dir: Path,
    group: str,
    progress: bool,
    keep_going: bool,
) -> None:
    """Train and evaluate run ``k`` in this process; a failure raises unless ``keep_going``."""
    resumed = (run_dir(cfg, data.data_key, project_dir) / "last.pt").is_file()
    t0 = time.monotonic()
    try:
        result = pipeline.train_and_evaluate(
            cfg, project_dir=project_dir, group=group, progress=progress, data=data
        )
    except KeyboardInterrupt:
        book.interrupted(k, cfg, time.monotonic() - t0)
        raise
    except Exception as exc:
        book.failed(k, cfg, exc, time.monotonic() - t0)
        if not keep_going:
            raise
        return
    auc = result.evaluation.metrics.get(TEST_KEY)
    book.trained(k, cfg, result.train.run_id, auc, time.monotonic() - t0, not resumed)


def _collect(book: _Progress, sweep: RaySweep, keep_going: bool) -> None:
    """Record the Ray runs as they finish; a failure raises unless ``keep_going``."""
    for k, cfg, res, exc in sweep.results():
        if exc is not None:
            book.failed(k, cfg, exc, math.nan)
            if not keep_going:
                raise exc
            continue
        book.trained(k, cfg, res["run_id"], res["test_ads_auc"], res["seconds"])


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
    other_data: bool = False,
) -> list[RunStatus]:
    """Train and evaluate every (variant, seed) that has no finished, evaluated run yet.

    A run to train whose exact config has finished on data of another key (the same recipe
    rendered on a kind of CPU not yet listed in ``same_data.toml``, or by changed code) stops
    the sweep before it trains anything, naming a run to check with ``cloudpose same-data``:
    hours of retraining are not started on a guess. ``other_data`` trains them anyway.

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
        other_data: train a run even when its config finished on data of another key.

    Returns:
        One status per (variant, seed), in order.

    Raises:
        OtherDataError: without ``other_data``, runs to train have finished on other data.
    """
    _check_executor(executor, ray)
    project_dir = (project_dir or Path.cwd()).resolve()
    echo = echo or (lambda s: print(s, flush=True))
    seeds = seed_list(seeds)
    client = tracking.setup(project_dir)
    log_path = project_dir / "runs" / f"ablate-{group}-{preset}.log"
    log_path.parent.mkdir(parents=True, exist_ok=True)
    todo = [resolve(v, preset, s, overrides) for v in variants for s in seeds]
    data_of = _data_once(project_dir, progress)
    pending = [cfg for cfg in todo if finished_run(client, cfg, data_of(cfg).data_key) is None]
    if not other_data:
        _refuse_other_data(client, pending, data_of)
    prior = _seconds_per_run_before(client, preset, todo[0].train.epochs) if todo else None
    book = _Progress(len(todo), log_path, echo, prior)
    echo(
        f"ablation {group}/{preset}: {len(todo)} runs ({len(variants)} variants x "
        f"{len(seeds)} seeds), {len(todo) - len(pending)} already done, {len(pending)} to run "
        f"({executor}); log {log_path}"
    )
    sweep = None
    if executor == "ray" and pending:
        tracking.experiment_id(client, group, project_dir)  # made here, not by racing tasks
        sweep = RaySweep(ray or RayOptions(), project_dir, group)
    try:
        for k, cfg in enumerate(todo, 1):
            done = finished_run(client, cfg, data_of(cfg).data_key)
            if done is not None:
                book.skipped(k, cfg, done)
            elif sweep is not None:
                sweep.submit(k, cfg)
                book.say(k, cfg, "submitted to Ray")
            else:
                book.starting(k, cfg, len(pending) - pending.index(cfg) if cfg in pending else 1)
                _train_here(
                    book,
                    k,
                    cfg,
                    data_of(cfg),
                    project_dir=project_dir,
                    group=group,
                    progress=progress,
                    keep_going=keep_going,
                )
        if sweep is not None:
            _collect(book, sweep, keep_going)
    finally:
        if sweep is not None:
            sweep.close()
    return [book.statuses[k] for k in sorted(book.statuses)]


class OtherDataError(ValueError):
    """Runs a sweep would train have finished on data of another key."""


def _refuse_other_data(client, pending: list[Config], data_of) -> None:
    """Raise :class:`OtherDataError` when a run of ``pending`` has finished, with its exact
    config, on data whose key is not the same data as the one rendered here."""
    elsewhere = [(cfg, finished_run_any_data(client, cfg)) for cfg in pending]
    elsewhere = [(cfg, run) for cfg, run in elsewhere if run is not None]
    if not elsewhere:
        return
    cfg, run = elsewhere[0]
    theirs, here = run.data.tags.get("data", "?"), data_of(cfg).data_key
    raise OtherDataError(
        f"{len(elsewhere)} of the {len(pending)} runs to train finished before with the same "
        f"config on data keyed {theirs} (e.g. {run_name(cfg.variant, cfg.preset, cfg.seed)}, "
        f"run {run.info.run_id}), and the data rendered here is keyed {here}: if it is the "
        f"same data rendered on another kind of CPU, `cloudpose same-data --run "
        f"{run.info.run_id}` checks it and prints the line of "
        "cloudpose/resources/registry/same_data.toml that lets the sweep reuse them; "
        "--fresh (FRESH=1) trains every run anew instead, into a store of its own"
    )


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
    only: Sequence[str] | None = None,
    other_data: bool = False,
) -> SuiteResult:
    """Train and evaluate every member of ``group`` over ``seeds``, then render its reports.

    Args:
        group: ablation group (``cloudpose/resources/registry/variants.toml``; :func:`cloudpose.registry.groups`).
        preset: training preset (``cloudpose/resources/registry/presets.toml``).
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
        only: these members of the group only (:meth:`cloudpose.registry.Group.pick`).
        other_data: train runs whose config finished on data of another key
            (:func:`ensure_runs`).
    """
    members = get_group(group).pick(only)
    project_dir = (project_dir or Path.cwd()).resolve()
    statuses = ensure_runs(
        list(members),
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
        other_data=other_data,
    )
    result = SuiteResult(
        group, preset, statuses, log=project_dir / "runs" / f"ablate-{group}-{preset}.log"
    )
    if report:
        result.report = render_reports(
            preset, [group], project_dir=project_dir, command=command, out_dir=out_dir
        )
    return result


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
    only: Sequence[str] | None = None,
    **ensure_kwargs,
) -> list[ResolveRound]:
    """Add seeds to the variants of ``group``'s claims until each is decided or at the cap.

    Each round measures the paper's claims whose two sides are both members of ``group``
    (:func:`cloudpose.report.claims.evaluate_claims` on the preset's runs), asks
    :func:`cloudpose.report.claims.seeds_wanted` which variants need more seeds for a claim that
    is "not resolved" but would be decided at some count up to the cap if its mean stayed,
    trains at most ``step`` more seeds of each through :func:`ensure_runs` (finished runs
    skipped, the same executors), and measures again. It stops when no claim wants seeds, or
    every variant that wants them has ``max_seeds``.

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
        only: these members of the group only (:meth:`cloudpose.registry.Group.pick`): the
            claims between two of them.
        **ensure_kwargs: passed to :func:`ensure_runs` (progress, keep_going, executor, ray).

    Returns:
        One :class:`ResolveRound` per measurement, the last one with nothing wanted or capped.
    """
    if max_seeds < 1 or step < 1:
        raise ValueError(f"max_seeds and step must be >= 1, got {max_seeds} and {step}")
    members = set(get_group(group).pick(only))
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
                else f"more seeds (cap {max_seeds}) would decide no other claim"
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

    Writes ``occlusion.png``/``.csv`` (and ``occlusion_GROUP.png``) only, from every finished
    run of those variants in MLflow (seeds ``1..seeds`` are the ones required). With ``train_missing`` the runs it needs that the
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
        preset,
        [group] if group else [],
        project_dir=project_dir,
        command=command,
        out_dir=out_dir,
        echo=echo or print,
        only_occlusion=True,
        log_mlflow=False,
    )


class MissingRuns(ValueError):
    """A report needs runs that the store does not hold (:attr:`names`)."""

    def __init__(self, names: list[str]):
        self.names = names
        super().__init__(f"{len(names)} run(s) missing from the store: {', '.join(names)}")
