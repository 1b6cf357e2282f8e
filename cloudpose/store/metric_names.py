"""Metric names: the prefixes evaluations are logged under in MLflow and the keys of their
summaries.

An evaluation named ``NAME`` logs the network's summaries as ``NAME/...`` and those after ICP
as ``NAME_icp/...`` (:func:`method_prefixes`); its instance table lies in ``eval/NAME/`` and
its tags are ``eval/NAME/data``, ``eval/NAME/split``. The names: :data:`OWN_TEST` (a run's own
test set, :func:`own_test_name` under another mask source), :data:`REAL_DEV` (the packaged real
development frames), and :func:`data_evaluation_name` (any other dataset, by its identity).

This module imports without torch, so the reports read these names at the top of their
modules; :func:`summary_metrics` and :func:`video_metrics` import the metrics (and torch) when
called.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

from cloudpose.data.keys import DataKey
from cloudpose.data.mask_sources import mask_source_label
from cloudpose.store.tracking import metric_key

if TYPE_CHECKING:
    import pandas as pd

OWN_TEST = "test"
"""Metric prefix of a run's evaluation on its own test set (``test/...``, ``test_icp/...``).
Reserved: an evaluation on other data (``--data``) is named by that data's identity."""

REAL_DEV = "real"
"""Metric prefix of a run's evaluation on the packaged real development frames
(:func:`cloudpose.data.layout.real_dev_root`): ``real/...``, ``real_icp/...``, per video
``real/video/0000/...``."""

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


def _by_method(df: pd.DataFrame, name: str) -> Iterator[tuple[str, pd.DataFrame]]:
    """``(metric prefix, table with the method's error columns unprefixed)`` per method."""
    prefixes = method_prefixes(name)
    for method in METHODS:
        if f"{method}_ads" not in df:
            continue
        yield prefixes[method], df.rename(columns={f"{method}_{k}": k for k in ERROR_COLUMNS})


def summary_metrics(df: pd.DataFrame, name: str) -> dict[str, float]:
    """MLflow metrics of a per-instance table: pooled, class-mean and per-class, per method."""
    from cloudpose.metrics import flatten_summary, summarize

    out: dict[str, float] = {}
    for prefix, sub in _by_method(df, name):
        for key, value in flatten_summary(summarize(sub)).items():
            out[metric_key(prefix, key)] = float(value)
    return out


def video_metrics(df: pd.DataFrame, name: str) -> dict[str, float]:
    """Pooled metrics of each video (the ``SEQ`` of ``SEQ/FRAME``), per method, as
    ``{name}/video/{SEQ}/{key}``: consecutive frames of a video show one scene, so a set of a
    few videos is a few scenes and is read per video as well as pooled."""
    from cloudpose.metrics import summarize

    out: dict[str, float] = {}
    video = df["frame_id"].astype(str).str.split("/").str[0]
    for prefix, sub in _by_method(df, name):
        for seq, part in sub.groupby(video.to_numpy()):
            for key, value in summarize(part, by_class=False)["pooled"].items():
                out[metric_key(prefix, f"video/{seq}/{key}")] = float(value)
    return out
