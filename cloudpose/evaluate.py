"""Evaluation of a trained run on a test set, with and without ICP, logged to MLflow.

Per instance: AD, ADS, rotation error, translation error, the estimated pose, occlusion factor,
class, and whether it was a miss (no usable segment point: every error infinite, as the
YCB-Video toolbox counts it). Every evaluation names its frame list in words (MLflow tag
``eval/{name}/split``: ``YCB-Video keyframe (2949 frames)``, ``BOP19 ycbv test targets (900
images)``).
Summaries (:func:`cloudpose.metrics.summarize`) are logged as metrics ``{name}/...`` for the
network alone and ``{name}_icp/...`` after ICP, pooled and class-mean; the per-class detail
(and per video, on the real frames) is a table ``eval/{name}/per_class.csv``
(``per_video.csv``), the per-instance table an artifact ``eval/{name}/instances.parquet``. The
names and metric keys are :mod:`cloudpose.store.metric_names`.
"""

from __future__ import annotations

import dataclasses
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd

from cloudpose import runtime
from cloudpose.data.cache import segments_for
from cloudpose.data.dataset import Prepared, folder_segments, only_classes, prepare_data
from cloudpose.data.keys import DataKey, same_data
from cloudpose.data.layout import describe_split, open_dataset, real_dev_root
from cloudpose.data.mask_sources import mask_source_label
from cloudpose.failures import DiskFullError, disk_full
from cloudpose.methods import (
    Network,
    check_ensemble,
    load_network,
    score,
    summary_metrics,
    video_metrics,
)
from cloudpose.refine import ICPSettings, schedule_for
from cloudpose.store import instances, runs, tracking
from cloudpose.store.headline import headline
from cloudpose.store.metric_names import (
    ICP_SUFFIX,
    OWN_TEST,
    REAL_DEV,
    data_evaluation_name,
    detail_artifact,
    detail_table,
    own_test_name,
    split_detail,
    write_detail,
)
from cloudpose.store.pretrained import is_pretrained


def evaluate_real(run: str, **kwargs) -> EvalOutcome:
    """:func:`evaluate` on the real development frames (:func:`real_dev_root`, all 61), logged
    as :data:`REAL_DEV` with per-video metrics beside the pooled ones (the table
    ``eval/real/per_video.csv``)."""
    out = evaluate(run, data=str(real_dev_root()), frames="all", name=REAL_DEV, **kwargs)
    per_video = video_metrics(out.table, out.name)
    if kwargs.get("log", True) and out.run_id is not None:
        client = tracking.setup(kwargs.get("project_dir") or Path.cwd())
        log_detail(client, out.run_id, out.name, per_video)
    return dataclasses.replace(out, metrics={**out.metrics, **per_video})


@dataclass(frozen=True)
class EvalOutcome:
    """Per-instance table, summary metrics and where they were logged."""

    table: pd.DataFrame
    metrics: dict[str, float]
    run_id: str | None
    name: str = OWN_TEST
    """The metric prefix the evaluation was logged under."""
    source: str = ""
    """Which run, checkpoint and data were evaluated, in words."""
    split: str = ""
    """The frame list evaluated, in words (:func:`cloudpose.data.layout.describe_split`):
    ``YCB-Video keyframe (2949 frames)``, ``BOP19 ycbv test targets (900 images)``; also the
    run's MLflow tag ``eval/{name}/split``."""


def check_evaluation_name(name: str, data: str | Path | None) -> str:
    """``name`` if a user may name an evaluation so (``--name``), else ``ValueError``.

    It becomes a metric prefix (``{name}/...`` and ``{name}_icp/...``) and an artifact folder
    (``eval/{name}``), so it is one safe path component (:func:`tracking.check_name`). It may
    not be a prefix that training logs per epoch (``train``, ``val``, ``fit``, ``time``: an
    evaluation would add a point to those curves), nor end in ``_icp`` (the suffix of an
    evaluation's ICP results). :data:`OWN_TEST` belongs to the run's own test set (refused with
    other ``data``) and :data:`REAL_DEV` to the packaged real development frames.
    """
    tracking.check_name("--name", name)
    if name in runs.TRAINING_PREFIXES:
        prefixes = ", ".join(runs.TRAINING_PREFIXES)
        raise ValueError(
            f"--name {name!r} is a metric prefix of training ({prefixes}): an evaluation under "
            "it would add points to the training curves; choose another name"
        )
    if name.endswith(ICP_SUFFIX):
        raise ValueError(
            f"--name {name!r}: names ending in _icp are the ICP results of another evaluation; "
            "choose another name"
        )
    if data is not None and name == OWN_TEST:
        raise ValueError(
            f"--name {name!r} is reserved for the run's own test set; leave it unset to "
            "name the evaluation by its data"
        )
    is_real = data is not None and Path(data).resolve() == real_dev_root().resolve()
    if name == REAL_DEV and not is_real:
        raise ValueError(
            f"--name {name!r} is reserved for the packaged real development frames; leave it "
            "unset to name the evaluation by its data"
        )
    return name


def icp_label(settings: ICPSettings, own: ICPSettings) -> str:
    """How ``settings`` differ from a run's own ICP, as an evaluation name's suffix:
    ``fallback`` / ``nofallback`` where the guard differs, ``starts24`` where the starts do,
    ``selectdepth`` where the score does, ``radius50mm`` where the schedule does (joined by
    ``-``); ``other`` for any other difference."""
    parts = []
    if (settings.fallback, settings.min_fitness) != (own.fallback, own.min_fitness):
        parts.append("fallback" if settings.fallback else "nofallback")
    if (settings.starts, settings.start_margin) != (own.starts, own.start_margin):
        parts.append(f"starts{settings.starts}")
    if settings.select != own.select:
        parts.append(f"select{settings.select}")
    schedule = ("max_distance", "iterations", "shrink")
    if any(getattr(settings, k) != getattr(own, k) for k in schedule):
        try:
            widened = ICPSettings(**schedule_for(settings.max_distance))
        except ValueError:  # a first radius below the paper's: no schedule of icp.radius
            return "other"
        if any(getattr(settings, k) != getattr(widened, k) for k in schedule):
            return "other"
        parts.append(f"radius{1000 * settings.max_distance:g}mm")
    return "-".join(parts) or "other"


@dataclass(frozen=True)
class _TestData:
    """What an evaluation scores: the segments, their dataset, and how they are named.

    Attributes:
        segs: the segments (a :class:`~cloudpose.data.segment_set.SegmentSet`).
        dataset: their dataset (models, class names).
        data_key: the segments' data key (tag ``eval/{name}/data``).
        name: the metric prefix before any ICP suffix.
        split: the frame list in words (tag ``eval/{name}/split``).
        label: the data in words, for messages.
    """

    segs: Any
    dataset: Any
    data_key: DataKey
    name: str
    split: str
    label: str


def _test_data(
    cfg,
    data: str | None,
    frames: str,
    name: str | None,
    masks: str | None,
    own_data: Prepared | None,
    project_dir: Path,
    progress: bool,
) -> _TestData:
    """The run's own test set (``data`` None) or ``frames`` of the dataset at ``data``, under
    mask source ``masks`` (None: the run's own), named ``name`` or by default."""
    seg_cfg = dataclasses.replace(cfg.data, segmentation=masks) if masks else cfg.data
    if data is None:
        own = own_data or prepare_data(cfg.data, project_dir, progress=progress)
        segs, dataset = own.test, own.dataset
        split = describe_split(dataset, "test")
        label = f"the run's own test set, {split} in {dataset.root}"
        if masks:  # the same frames, segmented otherwise (cached beside the run's own)
            segs = only_classes(
                segments_for(dataset, "test", seg_cfg, cache_dir=own.cache_dir, progress=progress),
                dataset,
                cfg.data.classes,
            )
            label += f" with {masks} masks"
        name = name or own_test_name(masks)
        return _TestData(segs, dataset, segs.data_key, name, split, label)
    dataset = open_dataset(data)
    segs = folder_segments(dataset, frames, seg_cfg, project_dir, progress)
    suffix = f"-{mask_source_label(masks)}" if masks else ""
    name = name or tracking.metric_key(data_evaluation_name(data, frames, segs.data_key) + suffix)
    split = describe_split(dataset, frames)
    return _TestData(
        segs, dataset, segs.data_key, name, split, f"{split} in {Path(data).resolve()}"
    )


def _score(
    network: Network,
    test: _TestData,
    name: str,
    icp_settings: ICPSettings | None,
    progress: bool,
    symmetry_table: int,
) -> tuple[pd.DataFrame, dict[str, float]]:
    """The per-instance table and metrics of ``network`` (several networks: an ensemble,
    :class:`cloudpose.methods.Network`) on ``test``, and after ICP with ``icp_settings`` (None:
    no ICP), with milliseconds per object (:func:`cloudpose.methods.score`)."""
    estimated = network.estimate(test.segs)
    scored = score(
        test.segs, estimated, test.dataset, icp_settings,
        symmetry_table=symmetry_table, progress=progress,
    )  # fmt: skip
    metrics = summary_metrics(scored.table, name)
    metrics[tracking.metric_key(name, "net_ms_per_object")] = estimated.ms_per_object
    if icp_settings is not None:
        metrics[tracking.metric_key(name, "icp_ms_per_object")] = scored.refine_ms
    return scored.table, metrics


def evaluate(
    run: str,
    *,
    data: str | None = None,
    frames: str = "keyframe",
    name: str | None = None,
    icp: bool = True,
    icp_overrides: dict[str, Any] | None = None,
    project_dir: Path | None = None,
    progress: bool = True,
    log: bool = True,
    device: str = "auto",
    own_data: Prepared | None = None,
    segmentation: str | None = None,
    ensemble: list[str] | None = None,
) -> EvalOutcome:
    """Evaluate a trained run on its own test set or on a YCB-Video-layout folder ``data``.

    Args:
        run: run folder, MLflow run id, or run name (:func:`cloudpose.store.runs.resolve_run`).
        data: dataset root in either layout (YCB-Video or BOP ycbv,
            :mod:`cloudpose.data.layout`); None = the run's own test set.
        frames: with ``data``: frame list to read ("keyframe" = YCB-Video's keyframes or the
            BOP19 test targets, "all", or an image_sets name).
        name: metric prefix; default :data:`OWN_TEST` for the run's own test set, else
            :func:`~cloudpose.store.metric_names.data_evaluation_name` (a name of the user's: :func:`check_evaluation_name`).
        icp: also evaluate after ICP refinement.
        icp_overrides: fields of :class:`~cloudpose.refine.ICPSettings` to change from the
            run's own (``cfg.icp``), e.g. ``{"starts": 24}``. Other settings than the run's
            name the evaluation ``{name}-{icp_label(...)}`` (``test-fallback``,
            ``real-starts24``), so they never replace the run's own ICP results.
        log: log the table and metrics to the run in MLflow.
        device: where the network runs ("auto": CUDA when available, as in training).
        own_data: the run's own data, prepared (the pipeline passes what it trained on);
            default: prepared here from the run's config.
        segmentation: where the test masks come from, if not from the run's config (e.g.
            ``degraded-medium``, :mod:`cloudpose.data.masks`, or PoseCNN's results
            ``posecnn:DIR``, :mod:`cloudpose.data.posecnn`); the evaluation is then named
            ``{test or the data's name}-{label}`` (:func:`mask_source_label`).
        ensemble: further runs (as ``run``) whose networks join ``run``'s: each network's
            estimate is refined by ICP and per instance the refinement with the best score
            of ``icp.select`` is kept (:func:`~cloudpose.refine.select_refinements`; ``depth``
            reads the frames' depth). Logged in ``run`` as ``{name}-ensemble{N}`` (N
            networks), the members' identities in the tag ``eval/{name}/ensemble``
            (:func:`cloudpose.methods.network_identity`: run ids, and a shipped network's with its checksum).

    Raises:
        ValueError: no instance to evaluate; a ``name`` that :func:`check_evaluation_name`
            refuses; ``name`` already holding an evaluation of other data in this run.
    """
    if name is not None:
        check_evaluation_name(name, data)
    project_dir = (project_dir or Path.cwd()).resolve()
    log = log and not is_pretrained(run)  # the shipped network has no MLflow run to log to
    client = runs.client_for([run, *(ensemble or ())], project_dir)
    first = load_network(client, run, device)
    run_id, cfg = first.run_id, first.config
    if ensemble and not icp:
        raise ValueError(
            "--ensemble keeps one of the networks' ICP refinements; drop --refine none"
        )
    members = [load_network(client, other, device) for other in ensemble or ()]
    ids = check_ensemble([first, *members], "--ensemble")
    runtime.configure_threads(cfg.train.threads)  # the run's own: the numbers depend on it
    masks = segmentation if segmentation not in (None, cfg.data.segmentation) else None
    test = _test_data(cfg, data, frames, name, masks, own_data, project_dir, progress)
    name = test.name
    own_icp = ICPSettings.from_config(cfg.icp)
    icp_settings = dataclasses.replace(own_icp, **(icp_overrides or {}))
    if icp and icp_settings != own_icp:
        name = tracking.metric_key(f"{name}-{icp_label(icp_settings, own_icp)}")
    if members:
        name = tracking.metric_key(f"{name}-ensemble{len(members) + 1}")
    if len(test.segs) == 0:
        raise ValueError(
            f"no instance to evaluate in {test.label} (no annotated object in its frames"
            + (f" of the classes {list(cfg.data.classes)})" if cfg.data.classes else ")")
        )
    tag = f"eval/{name}/data"
    logged = client.get_run(run_id).data.tags.get(tag) if log else None
    if logged is not None and not same_data(logged, test.data_key):
        raise ValueError(
            f"run {run_id} already holds an evaluation named {name!r} of other data (key "
            f"{logged}, this data {test.data_key}); choose another --name"
        )
    network = Network((first, *members))
    table, metrics = _score(
        network, test, name, icp_settings if icp else None, progress, cfg.loss.symmetry_table
    )
    if log:
        try:
            log_evaluation(client, run_id, name, table, metrics)
            client.set_tag(run_id, tag, test.data_key)
            client.set_tag(run_id, f"eval/{name}/split", test.split)
            if masks:
                client.set_tag(run_id, f"eval/{name}/segmentation", masks)
            if members:
                client.set_tag(run_id, f"eval/{name}/ensemble", ",".join(ids))
        except Exception as exc:
            full = _disk_full(exc, client, run_id)
            if full is None:
                raise
            raise full from exc
    who = f"run {run_id}" if run_id is not None else f"the shipped network {run!r}"
    source = f"{who}, checkpoint {first.checkpoint}, {len(test.segs)} instances of {test.label}"
    if members:
        source += f"; ensemble with {', '.join(m.run_id or m.checkpoint for m in members)}"
    return EvalOutcome(table, metrics, run_id, name, source, test.split)


def _disk_full(exc: BaseException, client, run_id: str) -> DiskFullError | None:
    """The one-line :class:`DiskFullError` of a full disk while logging an evaluation (naming
    the MLflow store for SQLite's "database or disk is full", else the run's artifact folder),
    else None."""
    db = tracking.sqlite_path(client.tracking_uri)
    if db is not None and "database or disk is full" in str(exc):
        where = db
    else:
        where = tracking.run_artifact(client, client.get_run(run_id), "eval")
    return disk_full(exc, where or tempfile.gettempdir(), then="rerun the evaluation")


def log_detail(client, run_id: str, name: str, metrics: dict[str, float]) -> dict[str, float]:
    """Log the per-class and per-video keys among ``metrics`` as the run's detail tables
    ``eval/{name}/per_class.csv`` and ``per_video.csv``
    (:func:`cloudpose.store.metric_names.detail_table`); returns the other keys."""
    summary, detail = split_detail(metrics)
    with tempfile.TemporaryDirectory() as tmp:
        for kind, keys in sorted(detail.items()):
            rel = detail_artifact(name, kind)
            path = write_detail(detail_table(keys, kind), Path(tmp) / Path(rel).name)
            client.log_artifact(run_id, str(path), artifact_path=str(Path(rel).parent))
    return summary


def log_evaluation(
    client, run_id: str, name: str, table: pd.DataFrame, metrics: dict[str, float]
) -> None:
    """An evaluation into its MLflow run: the instance table as ``eval/{name}/instances.parquet``
    (what the reports read; float32, :mod:`cloudpose.store.instances`), the per-class and
    per-video detail as tables beside it (:func:`log_detail`) and the other finite metrics; on
    the run's own test set (:data:`OWN_TEST`) also its headline metrics
    (:data:`cloudpose.store.headline.HEADLINE`)."""
    with tempfile.TemporaryDirectory() as tmp:
        path = instances.write_table(table, Path(tmp) / instances.PARQUET)
        client.log_artifact(run_id, str(path), artifact_path=f"eval/{name}")
    metrics = log_detail(client, run_id, name, metrics)
    if name == OWN_TEST:
        metrics = {**metrics, **headline(metrics)}
    client.log_batch(run_id, metrics=tracking.metric_batch(metrics, finite_only=True))
