"""Metric names: the prefixes evaluations are logged under in MLflow and the keys of their
summaries.

An evaluation named ``NAME`` logs the network's summaries as ``NAME/...`` and those after ICP
as ``NAME_icp/...`` (:func:`method_prefixes`); its instance table lies in ``eval/NAME/`` and
its tags are ``eval/NAME/data``, ``eval/NAME/split``. The names: :data:`OWN_TEST` (a run's own
test set, :func:`own_test_name` under another mask source), :data:`REAL_DEV` (the packaged real
development frames), and :func:`data_evaluation_name` (any other dataset, by its identity).

The detail of an evaluation, per class (``NAME/class/CLASS/KEY``, ``NAME_icp/class/...``) and
per video (``NAME/video/SEQ/KEY``), is a table beside its instance table,
``eval/NAME/per_class.csv`` and ``eval/NAME/per_video.csv`` (:func:`detail_artifact`: one row
per metric prefix and class or video, one column per key), not hundreds of MLflow metrics that
the UI's run page and chart view would list one by one; the run's metrics are the pooled and
class-mean summaries (:func:`split_detail`). Runs logged before keep the detail as metric keys;
:class:`DetailReader` reads either, so a reader asks for ``test_icp/class/025_mug/ads_auc`` of any
run.

This module imports without torch, so the reports read these names at the top of their
modules; an instance table's summaries under these names are
:func:`cloudpose.methods.summary_metrics` and :func:`cloudpose.methods.video_metrics`.
"""

from __future__ import annotations

import math
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

import pandas as pd

from cloudpose.data.keys import DataKey
from cloudpose.data.mask_sources import mask_source_label
from cloudpose.store import tracking
from cloudpose.store.tracking import metric_key

if TYPE_CHECKING:
    import pandas as pd

OWN_TEST = "test"
"""Metric prefix of a run's evaluation on its own test set (``test/...``, ``test_icp/...``).
Reserved: an evaluation on other data (``--data``) is named by that data's identity."""

REAL_DEV = "real"
"""Metric prefix of a run's evaluation on the packaged real development frames
(:func:`cloudpose.data.layout.real_dev_root`): ``real/...``, ``real_icp/...``, per video
``real/video/0000/...`` (in ``eval/real/per_video.csv``)."""

DETAIL_KINDS = ("class", "video")
"""What an evaluation's detail is grouped by: ``{prefix}/class/{CLASS}/{key}`` and
``{prefix}/video/{SEQ}/{key}``."""

METHODS = ("net", "icp")
"""Column prefixes of the per-instance table: the network's estimate, then after ICP."""

ICP_SUFFIX = "_icp"
"""What an evaluation's name gets for its results after ICP (``test_icp/ads_auc``)."""

ERROR_COLUMNS = ("ad", "ads", "rot_err_deg", "rot_sym_err_deg", "trans_err")
"""The per-instance error columns of each method (``net_ads``, ``icp_ads``, ...)."""


def method_prefixes(name: str) -> dict[str, str]:
    """``{method: metric prefix}`` of an evaluation named ``name``: ``net`` -> ``name``,
    ``icp`` -> ``name_icp``."""
    return {"net": name, "icp": f"{name}{ICP_SUFFIX}"}


def own_test_name(segmentation: str | None = None) -> str:
    """Metric prefix of a run's evaluation on its own test set: :data:`OWN_TEST` with the run's
    own masks (``segmentation`` None), ``test-{segmentation}`` under another mask source
    (``test-degraded-medium``; the ``+ ICP`` results under ``test-degraded-medium_icp``)."""
    if not segmentation:
        return OWN_TEST
    return metric_key(f"{OWN_TEST}-{mask_source_label(segmentation)}")


def data_evaluation_name(root: str | Path, frames: str, data_key: DataKey) -> str:
    """Metric prefix of an evaluation on ``frames`` of the dataset at ``root``, by the data's
    identity.

    ``{folder}-{frames}-{data_key[:10]}`` with ``data_key`` the key of the segments
    (:func:`cloudpose.data.cache.cache_key`): two folders with one basename, or one folder's
    keyframes and all its frames, get different names; the same bytes anywhere get one name.
    """
    return metric_key(f"{Path(root).resolve().name}-{frames}-{data_key[:10]}")


def detail_kind(key: str) -> str | None:
    """``class`` or ``video`` for a detail key (``test_icp/class/025_mug/ads_auc``,
    ``real/video/0000/count``), else None (``test/class_mean/ads_auc`` is a summary)."""
    parts = key.split("/")
    return parts[1] if len(parts) == 4 and parts[1] in DETAIL_KINDS else None


def detail_artifact(name: str, kind: str) -> str:
    """``eval/{name}/per_{kind}.csv``: where a run keeps evaluation ``name``'s detail of
    ``kind`` (both metric prefixes, ``name`` and ``name_icp``)."""
    if kind not in DETAIL_KINDS:
        raise ValueError(f"detail kind {kind!r}: expected one of {DETAIL_KINDS}")
    return f"eval/{name}/per_{kind}.csv"


def evaluation_of(prefix: str) -> str:
    """The evaluation a metric prefix belongs to: ``test_icp`` -> ``test``."""
    return prefix.removesuffix(ICP_SUFFIX)


def split_detail(metrics: dict[str, float]) -> tuple[dict[str, float], dict[str, dict]]:
    """``(summary metrics, {kind: detail metrics})``: the keys a run logs as MLflow metrics,
    and the per-class and per-video keys (:func:`detail_kind`) its detail tables hold."""
    summary: dict[str, float] = {}
    detail: dict[str, dict[str, float]] = {}
    for key, value in metrics.items():
        kind = detail_kind(key)
        if kind is None:
            summary[key] = value
        else:
            detail.setdefault(kind, {})[key] = value
    return summary, detail


def detail_table(metrics: dict[str, float], kind: str) -> pd.DataFrame:
    """The detail keys of ``kind`` among ``metrics`` as a table: columns ``prefix``, ``kind``
    (the class or video) and one per key, in the order first logged; a row per (prefix, class
    or video). :func:`detail_metrics` gives the keys back."""
    rows: dict[tuple[str, str], dict[str, float]] = {}
    keys: dict[str, None] = {}
    for key, value in metrics.items():
        if detail_kind(key) != kind:
            continue
        prefix, _, item, stat = key.split("/")
        rows.setdefault((prefix, item), {})[stat] = float(value)
        keys.setdefault(stat)
    table = pd.DataFrame(
        [{"prefix": p, kind: item, **vals} for (p, item), vals in rows.items()],
        columns=["prefix", kind, *keys],
    )
    return table.reset_index(drop=True)


def detail_metrics(table: pd.DataFrame, kind: str) -> dict[str, float]:
    """The metric keys of a detail table (:func:`detail_table`), finite values only (as an
    evaluation logs its metrics)."""
    out: dict[str, float] = {}
    stats = [c for c in table.columns if c not in ("prefix", kind)]
    for row in table.itertuples(index=False):
        values = dict(zip(table.columns, row, strict=True))
        for stat in stats:
            v = float(values[stat])
            if math.isfinite(v):
                out[metric_key(str(values["prefix"]), kind, str(values[kind]), stat)] = v
    return out


def write_detail(table: pd.DataFrame, path: str | Path) -> Path:
    """Write a detail table as CSV (shortest exact float text: it reads back the same)."""
    path = Path(path)
    table.to_csv(path, index=False, float_format=None)
    return path


def read_detail(path: str | Path, kind: str) -> pd.DataFrame:
    """A detail table as :func:`write_detail` wrote it (prefix, class and video as text: video
    ``0000`` stays ``0000``)."""
    return pd.read_csv(
        path, dtype={"prefix": str, kind: str}, keep_default_na=False, na_values=[""]
    )


class DetailReader:
    """A run's detail keys: its metrics first, then its detail tables, each read once (in
    place from a local store, downloaded from a remote one)."""

    def __init__(self, client, run_id: str, artifact_uri: str, metrics: dict[str, float]):
        self.client, self.run_id, self.artifact_uri = client, run_id, artifact_uri
        self.metrics = metrics
        self._tables: dict[tuple[str, str], dict[str, float]] = {}

    def get(self, key: str) -> float:
        """``key``'s value; NaN when neither the metrics nor the detail table hold it."""
        if key in self.metrics:
            return float(self.metrics[key])
        kind = detail_kind(key)
        if kind is None:
            return float("nan")
        name = evaluation_of(key.split("/")[0])
        if (name, kind) not in self._tables:
            self._tables[(name, kind)] = self._read(name, kind)
        return float(self._tables[(name, kind)].get(key, float("nan")))

    def _read(self, name: str, kind: str) -> dict[str, float]:
        rel = detail_artifact(name, kind)
        store = getattr(self.client, "tracking_uri", None)
        local = tracking.local_artifact(self.artifact_uri or "", rel, store)
        if local is not None:
            return detail_metrics(read_detail(local, kind), kind) if local.is_file() else {}
        if self.client is None:
            return {}
        with tempfile.TemporaryDirectory() as tmp:
            try:
                path = self.client.download_artifacts(self.run_id, rel, tmp)
            except Exception:  # no such table (MlflowException, OSError): no detail
                return {}
            return detail_metrics(read_detail(path, kind), kind)
