"""A baseline evaluated like a network: the preset's test set, the same ICP after, the same
instance table and metrics, logged to MLflow (experiment ``cloudpose-baselines``).

A segment the method cannot register (too few points, no pose found) counts as a miss: its
errors are infinite, as for a network's miss. The run is named ``baseline-{method}/{preset}/
seed{S}`` and tagged like a training run (``variant`` = ``baseline-{method}``, ``preset``,
``seed``, ``data``, ``config`` = a hash of the settings), so the reports find it beside the
networks and leave out runs of other settings. A call whose run is already logged (same
method, preset, seed, data, settings, split and subsample, FINISHED) returns that run instead of
computing it again, as ``cloudpose ablate`` skips finished variants; ``rerun=True`` computes and
logs a new one, and the reports take the newest per seed.

A long run (point-pair features take about a second per segment) loses nothing when it is
stopped: the estimates are saved as they are computed (at most :data:`cloudpose.methods.SAVE_EVERY_S` apart,
and at once on Ctrl-C or SIGTERM) to
``runs/baseline-{method}/{preset}/seed{S}-{data}-{settings}[/{split}-{limit}]/progress.npz``,
and the next call with the same data, settings, split and subsample continues from them. The
file is removed once the run is logged, so a later call computes afresh.

On a user's dataset (``data=ROOT``, either layout, ``frames`` as ``cloudpose evaluate
--data`` takes them) the preset gives the segment settings only. The run is logged under the
data's identity as an evaluation on that data is
(:func:`cloudpose.store.metric_names.data_evaluation_name`): metrics
``{folder}-{frames}-{data_key}/...``, tags ``data`` = the segments' data key, ``split`` = that
name, ``eval/{name}/split`` = the frame list in words, run name
``baseline-{method}/{preset}/seed{S}+{name}-{settings}``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pandas as pd

from cloudpose.baselines import load_settings
from cloudpose.baselines.base import BaselineSettings, settings_fingerprint
from cloudpose.config import PAPER_RADIUS, ICPConfig
from cloudpose.data.cache import SegmentSet, segments_for
from cloudpose.data.dataset import folder_segments, prepare_data
from cloudpose.data.keys import DataKey
from cloudpose.data.layout import describe_split, open_dataset, real_dev_root
from cloudpose.evaluate import log_evaluation
from cloudpose.methods import (
    Baseline,
    Estimated,
    EstimateProgress,
    score,
    summary_metrics,
    video_metrics,
)
from cloudpose.refine import ICPSettings
from cloudpose.registry import DEFAULT_PRESET, resolve
from cloudpose.store import instances, runs, tracking
from cloudpose.store.metric_names import data_evaluation_name
from cloudpose.store.runs import run_folder
from cloudpose.train.loop import split_frames

GROUP = "baselines"
SPLITS = ("test", "val", "real")
"""Where a baseline is evaluated: the preset's test set, its validation frames (where settings
are tuned), or the packaged real development frames (:func:`cloudpose.data.layout.real_dev_root`,
with per-video metrics)."""


@dataclass(frozen=True)
class BaselineOutcome:
    """The instance table, the logged metrics and the MLflow run."""

    table: pd.DataFrame
    metrics: dict[str, float]
    run_id: str | None
    failures: int
    reused: bool = False  # an earlier finished run of the same call, not computed again
    name: str = "test"
    """The metric prefix: the split, or the data's identity with ``data``."""
    split: str = ""
    """The frame list evaluated, in words (:func:`cloudpose.data.layout.describe_split`)."""


def subsample(n: int, limit: int | None) -> np.ndarray:
    """Indices of an evenly spaced subsample of ``limit`` of ``n`` instances (all if None)."""
    if limit is None or limit >= n:
        return np.arange(n)
    if limit < 1:
        raise ValueError(f"--limit {limit}: expected a positive number of instances")
    return np.unique(np.linspace(0, n - 1, limit).round().astype(np.int64))


@dataclass(frozen=True)
class BaselineCall:
    """What makes two calls of :func:`run_baseline` the same run: the method and its settings
    (fingerprint), the preset, seed and data, the split and subsample, in one project."""

    project_dir: Path
    method: str
    preset: str
    seed: int
    data_key: DataKey
    settings_fp: str
    split: str = "test"
    limit: int | None = None

    def progress_path(self) -> Path:
        """Where this run keeps its partial estimates: ``progress.npz`` in the run folder of
        variant ``baseline-{method}`` (:func:`cloudpose.store.runs.run_folder`), one subfolder per
        other split or subsample."""
        folder = run_folder(
            f"baseline-{self.method}",
            self.preset,
            self.seed,
            self.data_key,
            self.settings_fp,
            self.project_dir,
        )
        if self.split != "test" or self.limit is not None:
            folder = folder / f"{self.split}-{self.limit or 'all'}"
        return folder / "progress.npz"

    def finished(self, icp: bool = True) -> BaselineOutcome | None:
        """The newest FINISHED run of this call (with its ICP evaluation when ``icp``), with
        its instance table, or None."""
        client = tracking.setup(self.project_dir)
        extra = (
            f"tags.config = '{self.settings_fp}' and tags.split = '{self.split}' "
            f"and tags.subsample = '{self.limit or 'all'}' and tags.kind = 'baseline'"
        )
        runs = tracking.find_runs(
            client,
            variant=f"baseline-{self.method}",
            preset=self.preset,
            seed=self.seed,
            data=self.data_key,
            extra_filter=extra,
        )
        key = f"{self.split}_icp/ads_auc"
        runs = [r for r in runs if not icp or key in r.data.metrics]
        if not runs:
            return None
        run = runs[0]
        table = instances.read_artifact_table(client, run, f"eval/{self.split}/instances.csv")
        metrics = dict(run.data.metrics)
        failures = int(metrics.get(f"{self.split}/failures", 0))
        split = run.data.tags.get(f"eval/{self.split}/split", "")
        return BaselineOutcome(
            table, metrics, run.info.run_id, failures, reused=True, name=self.split, split=split
        )


def split_segments(cfg, split: str, project_dir: Path, progress: bool = True):
    """``(prepared, dataset, segments)`` of one of :data:`SPLITS` for a run config ``cfg``:
    the preset's prepared data (its data key identifies the run's data whatever the split), the
    dataset the segments come from (their models), and the segments: the test set, the real
    development frames (all 61, cached beside the preset's), or the validation frames held
    out of the training set."""
    prepared = prepare_data(cfg.data, project_dir, progress=progress)
    if split == "test":
        return prepared, prepared.dataset, prepared.test
    if split == "real":
        dataset = open_dataset(real_dev_root())
        cache_dir = project_dir / "data" / "cache"
        pool = segments_for(dataset, "all", cfg.data, cache_dir=cache_dir, progress=progress)
        return prepared, dataset, pool
    val = split_frames(prepared.train.frame_id, cfg.train.val_fraction)
    return prepared, prepared.dataset, prepared.train.subset(val)


class _Pool(NamedTuple):
    """The segments a baseline is evaluated on and what names them.

    Attributes:
        dataset: where the segments come from (their models and class names).
        segments: every segment of the split or frame list.
        data_key: the key of the data the run is tagged with (MLflow tag ``data``).
        split: the metric prefix (a split, or the data's identity with ``data``).
        described: the frame list in words with ``data``, else "".
    """

    dataset: object
    segments: SegmentSet
    data_key: DataKey
    split: str
    described: str


def _pool(
    cfg, split: str, data: str | Path | None, frames: str, project_dir: Path, progress: bool
) -> _Pool:
    """The segments of ``split`` for run config ``cfg``, or of ``frames`` of the dataset at
    ``data`` (then named by that data's identity,
    :func:`cloudpose.store.metric_names.data_evaluation_name`)."""
    if data is None:
        prepared, dataset, segments = split_segments(cfg, split, project_dir, progress)
        return _Pool(dataset, segments, prepared.data_key, split, "")
    dataset = open_dataset(data)
    segments = folder_segments(dataset, frames, cfg.data, project_dir, progress)
    name = data_evaluation_name(data, frames, segments.data_key)
    return _Pool(dataset, segments, segments.data_key, name, describe_split(dataset, frames))


def _metrics(
    table: pd.DataFrame, split: str, estimated: Estimated, icp_ms: float | None, failures: int
) -> dict[str, float]:
    """The run's metrics: the table's summaries (per video too on the real frames), the
    milliseconds per object of the method and of ICP (``icp_ms`` None: no ICP), the
    preparation seconds and the failures."""
    metrics = summary_metrics(table, split)
    if split == "real":
        metrics.update(video_metrics(table, split))
    metrics[f"{split}/net_ms_per_object"] = estimated.ms_per_object
    metrics[f"{split}/prepare_s"] = estimated.prepare_seconds
    if icp_ms is not None:
        metrics[f"{split}/icp_ms_per_object"] = icp_ms
    metrics[f"{split}/failures"] = float(failures)
    return metrics


def _data_params(cfg, data: str | Path | None) -> dict[str, object]:
    """The MLflow params of the data: the ``data.*`` settings, the rotation metric's symmetry
    table, and the root of a user's dataset."""
    params: dict[str, object] = {k: v for k, v in cfg.flat().items() if k.startswith("data.")}
    params["loss.symmetry_table"] = cfg.loss.symmetry_table
    if data is not None:
        params["data.root"] = str(Path(data).resolve())
    return params


def run_baseline(
    method: str,
    preset: str = DEFAULT_PRESET,
    seed: int = 1,
    *,
    project_dir: Path | None = None,
    limit: int | None = None,
    split: str = "test",
    data: str | Path | None = None,
    frames: str = "keyframe",
    overrides: dict | None = None,
    icp: bool = True,
    progress: bool = True,
    log: bool = True,
    rerun: bool = False,
    icp_radius: float = PAPER_RADIUS,
    icp_starts: int = 1,
    icp_select: str = "fitness",
) -> BaselineOutcome:
    """Evaluate baseline ``method`` on ``preset``'s test set (or an evenly spaced ``limit`` of
    its instances) with and without ICP; log to MLflow when ``log``.

    ``icp_radius``, ``icp_starts``, ``icp_select``: ICP's first correspondence distance
    (:func:`cloudpose.refine.schedule_for`; the paper's 0.01 m by default), its starts and
    how they are scored, as ``cloudpose evaluate --refine radius=,starts=,select=``
    refine a network's estimate. Other values than the paper's (0.01, 1, fitness) are
    settings of the run (``icp_*`` beside the method's, in its fingerprint), so it is a run
    of its own, which the reports, made with the paper's ICP, leave out.

    ``split="val"`` evaluates on the validation frames held out of the training set (the same
    frames every network validates on), with metrics under ``val/``: where settings are
    chosen (``overrides`` replaces some of ``baselines.toml``'s values), never on the test set.
    ``split="real"`` evaluates on the real development frames, metrics under ``real/`` (and
    per video ``real/video/SEQ/...``), as every network run's evaluation does.
    ``data`` evaluates on ``frames`` of a dataset root of either layout instead (module doc);
    the preset then gives the segment settings and classes.

    With ``log``, a FINISHED run of the same call is returned as it is (``reused``) unless
    ``rerun``.
    """
    if split not in SPLITS:
        raise ValueError(f"--split {split!r}: expected one of {', '.join(SPLITS)}")
    if data is not None and split != "test":
        raise ValueError(f"--split {split} and --data: give one (--data tests on that folder)")

    project_dir = (project_dir or Path.cwd()).resolve()
    settings = load_settings(method).with_overrides(overrides)
    icp_cfg = ICPConfig(radius=icp_radius, starts=icp_starts, select=icp_select)  # checked
    icp_settings = ICPSettings.from_config(icp_cfg)
    paper = ICPConfig()
    other = {
        f"icp_{k}": getattr(icp_cfg, k)
        for k in ("radius", "starts", "select")
        if getattr(icp_cfg, k) != getattr(paper, k)
    }
    if other:
        settings = replace(settings, values={**settings.values, **other})
    cfg = resolve("shared-0", preset, seed)
    pool = _pool(cfg, split, data, frames, project_dir, progress)
    split = pool.split
    models = pool.dataset.models()
    segs = pool.segments.subset(subsample(len(pool.segments), limit))
    call = BaselineCall(
        project_dir,
        method,
        preset,
        seed,
        pool.data_key,
        settings_fingerprint(settings),
        split,
        limit,
    )
    if log and not rerun:
        done = call.finished(icp)
        if done is not None:
            return done
    state = EstimateProgress(call.progress_path(), len(segs))
    estimated = Baseline(method, models, seed, settings, progress).estimate(segs, state)
    n_valid = int(np.sum(segs.valid))
    failures = n_valid - int(np.sum(np.asarray(segs.valid, dtype=bool) & estimated.ok))
    scored = score(
        segs, estimated, pool.dataset, icp_settings if icp else None,
        symmetry_table=cfg.loss.symmetry_table, models=models, progress=progress,
    )  # fmt: skip
    table = scored.table
    icp_ms = scored.refine_ms if icp else None
    metrics = _metrics(table, split, estimated, icp_ms, failures)
    record = BaselineRecord(call, settings, table, metrics, _data_params(cfg, data), pool.described)
    run_id = _log(record) if log else None
    state.remove()
    return BaselineOutcome(table, metrics, run_id, failures, name=split, split=pool.described)


@dataclass(frozen=True)
class BaselineRecord:
    """What a computed baseline run logs to MLflow.

    Attributes:
        call: the call that computed it (method, preset, seed, data key, settings fingerprint,
            split, subsample, project).
        settings: the method's settings (params ``baseline.*``).
        table: the per-instance table (artifact ``eval/{split}/instances.csv``).
        metrics: the run's metrics.
        data_params: params of the data (:func:`_data_params`).
        described: a user's frame list in words (tags ``eval/{split}/data`` and
            ``eval/{split}/split``), or "" for one of :data:`SPLITS`.
    """

    call: BaselineCall
    settings: BaselineSettings
    table: pd.DataFrame
    metrics: dict[str, float]
    data_params: dict[str, object]
    described: str = ""


def _log(record: BaselineRecord) -> str:
    """Log ``record`` as a new FINISHED run of experiment :data:`GROUP`; its run id."""
    call = record.call
    client = tracking.setup(call.project_dir)
    exp = tracking.experiment_id(client, GROUP, call.project_dir)
    tags = runs.baseline_tags(
        call.method,
        GROUP,
        call.preset,
        call.seed,
        call.data_key,
        call.settings_fp,
        limit=call.limit,
        split=call.split,
    )
    own = settings_fingerprint(load_settings(call.method))
    name = runs.baseline_name(
        call.method, call.preset, call.seed, call.split, call.settings_fp, own
    )
    params = {f"baseline.{k}": v for k, v in record.settings.values.items()} | record.data_params
    run_id = runs.create_run_record(client, exp, name, tags, params)
    log_evaluation(client, run_id, call.split, record.table, record.metrics)
    if record.described:  # a user's data, tagged as an evaluation of it is
        client.set_tag(run_id, f"eval/{call.split}/data", call.data_key)
        client.set_tag(run_id, f"eval/{call.split}/split", record.described)
    client.set_terminated(run_id, "FINISHED")
    return run_id
