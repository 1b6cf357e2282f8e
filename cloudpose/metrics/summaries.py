"""Summaries of per-instance errors: the toolbox's AUC, shares under a threshold, per-class
tables, and accuracy per occlusion bin."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import pandas as pd

AUC_MAX_THRESHOLD = 0.1
"""Upper end of the AUC threshold range, metres (YCB-Video toolbox)."""

SUMMARY_KEYS = (
    "ad_auc",
    "ads_auc",
    "ads_lt_1cm",
    "rot_lt_10deg",
    "rot_lt_15deg",
    "rot_lt_20deg",
    "trans_lt_1cm",
)
"""Keys of ``summarize``'s pooled figures, each a fraction in [0, 1]."""

# Points per vectorised chunk: AD's temporaries stay in cache; ADS's KD-tree calls stay large
# enough to amortise their threads while bounding memory (~6 MB of query points).

# ---------------------------------------------------------------------------------------------
# Accuracy curves and AUC


def _check_distances(distances: np.ndarray) -> np.ndarray:
    d = np.asarray(distances, dtype=np.float64)
    if d.ndim != 1:
        raise ValueError(f"distances: expected shape (M,), got {d.shape}")
    if np.isnan(d).any() or (d < 0).any():
        raise ValueError("distances: expected values >= 0 or inf (misses), got NaN or negative")
    return d


def voc_ap_auc(distances: np.ndarray, max_threshold: float = AUC_MAX_THRESHOLD) -> float:
    """Area under the accuracy-threshold curve, the YCB-Video toolbox's VOCap.

    docs/design.md: distances above 0.1 m become infinite; sort the finite ones,
    d_1 <= ... <= d_k, with accuracy a_j = j / n (n = all instances, misses included). Let
    x = [0, d_1..d_k, 0.1] and y = [0, a_1..a_k, a_k]; make y non-decreasing (running max);
    AUC = 10 * sum over the indices i where x[i] != x[i-1] of (x[i] - x[i-1]) * y[i].
    (10 = 1 / max_threshold.) 1.0 is perfect; tables show it x 100.

    Args:
        distances: (M,) per-instance errors in metres, ``inf`` for misses.
        max_threshold: upper end of the threshold range, metres (0.1 in the toolbox).

    Returns:
        AUC in [0, 1]; 0 when no distance is within range; NaN when M = 0.
    """
    d = _check_distances(distances)
    n = len(d)
    if n == 0:
        return float("nan")
    d = np.where(d > max_threshold, np.inf, d)
    finite = np.sort(d[np.isfinite(d)])
    k = len(finite)
    if k == 0:
        return 0.0
    acc = np.arange(1, k + 1) / n
    x = np.concatenate([[0.0], finite, [max_threshold]])
    y = np.concatenate([[0.0], acc, [acc[-1]]])
    y = np.maximum.accumulate(y)
    i = np.flatnonzero(x[1:] != x[:-1]) + 1
    return float(np.sum((x[i] - x[i - 1]) * y[i]) / max_threshold)


def accuracy_curve(distances: np.ndarray, thresholds: np.ndarray) -> np.ndarray:
    """Share of all instances (misses included) whose distance is <= each threshold.

    The staircase the AUC integrates; for plots.

    Args:
        distances: (M,) metres, ``inf`` for misses.
        thresholds: (T,) metres.

    Returns:
        (T,) fractions in [0, 1] (NaN when M = 0).
    """
    d = np.sort(_check_distances(distances))
    thresholds = np.asarray(thresholds, dtype=np.float64)
    if len(d) == 0:
        return np.full(thresholds.shape, np.nan)
    return np.searchsorted(d, thresholds, side="right") / len(d)


def fraction_below(distances: np.ndarray, threshold: float) -> float:
    """Share of all instances (misses included) with distance strictly below ``threshold``
    (the paper's "ADS < 1 cm"); NaN when there are none."""
    d = np.asarray(distances, dtype=np.float64)
    if d.size == 0:
        return float("nan")
    return float(np.mean(d < threshold))


# ---------------------------------------------------------------------------------------------
# Summaries


def _summary_row(df: pd.DataFrame) -> dict[str, float]:
    return {
        "ad_auc": voc_ap_auc(df["ad"].to_numpy()),
        "ads_auc": voc_ap_auc(df["ads"].to_numpy()),
        "ads_lt_1cm": fraction_below(df["ads"], 0.01),
        "rot_lt_10deg": fraction_below(df["rot_err_deg"], 10.0),
        "rot_lt_15deg": fraction_below(df["rot_err_deg"], 15.0),
        "rot_lt_20deg": fraction_below(df["rot_err_deg"], 20.0),
        "rot_err_median_deg": float(np.median(df["rot_err_deg"])) if len(df) else float("nan"),
        "trans_lt_1cm": fraction_below(df["trans_err"], 0.01),
        **(
            {
                "rot_sym_lt_10deg": fraction_below(df["rot_sym_err_deg"], 10.0),
                "rot_sym_lt_15deg": fraction_below(df["rot_sym_err_deg"], 15.0),
                "rot_sym_lt_20deg": fraction_below(df["rot_sym_err_deg"], 20.0),
                "rot_sym_err_median_deg": float(np.median(df["rot_sym_err_deg"])),
            }
            if "rot_sym_err_deg" in df and len(df)
            else {}
        ),
        "count": float(len(df)),
    }


def _as_frame(results: pd.DataFrame | Mapping[str, Any]) -> pd.DataFrame:
    df = results if isinstance(results, pd.DataFrame) else pd.DataFrame(dict(results))
    missing = [c for c in ("cls_id", "ad", "ads", "rot_err_deg", "trans_err") if c not in df]
    if missing:
        raise ValueError(f"results: missing columns {missing}; got {list(df.columns)}")
    return df


def per_class_table(results: pd.DataFrame | Mapping[str, Any]) -> pd.DataFrame:
    """Summary figures of each class.

    Args:
        results: per-instance errors (``pose_errors`` output or a DataFrame with its columns);
            a ``class`` column (names), if present, labels the rows.

    Returns:
        DataFrame with one row per class in class-id order, indexed by the class name (``class``
        column) or else by ``cls_id``; columns ``SUMMARY_KEYS`` (fractions) and ``count``, all
        numbers.
    """
    df = _as_frame(results)
    rows, labels = [], []
    for c, g in df.groupby("cls_id", sort=True):
        rows.append(_summary_row(g))
        labels.append(str(g["class"].iloc[0]) if "class" in g else int(c))
    table = pd.DataFrame(rows, columns=[*SUMMARY_KEYS, "count"])
    table.index = pd.Index(labels, name="class" if "class" in df else "cls_id")
    return table


def summarize(results: pd.DataFrame | Mapping[str, Any], by_class: bool = True) -> dict[str, Any]:
    """Summary figures pooled over all instances, as the mean of per-class values, per class.

    Every figure is a fraction in [0, 1] (reports show x 100): ``SUMMARY_KEYS`` =
    ad_auc, ads_auc, ads_lt_1cm, rot_lt_10deg, rot_lt_15deg, rot_lt_20deg, trans_lt_1cm.

    Args:
        results: per-instance errors (``pose_errors`` output or a DataFrame with its columns:
            cls_id, ad, ads, rot_err_deg, trans_err; misses carry inf).
        by_class: include the per-class table.

    Returns:
        ``{"pooled": {key: value, "count": M}`` (over all instances, the paper's and PoseCNN's
        way), ``"class_mean": {key: unweighted mean over classes}``,
        ``"per_class": per_class_table(results)`` (empty when ``by_class`` is False)``}``.
        ``flatten_summary`` turns it into MLflow-style keys.
    """
    df = _as_frame(results)
    table = per_class_table(df)
    return {
        "pooled": _summary_row(df),
        "class_mean": {
            k: float(table[k].mean()) if len(table) else float("nan") for k in SUMMARY_KEYS
        },
        "per_class": table if by_class else table.iloc[:0],
    }


def flatten_summary(summary: Mapping[str, Any]) -> dict[str, float]:
    """``summarize``'s result as flat keys: ``ads_auc``, ``class_mean/ads_auc``,
    ``class/<label>/ads_auc``, ... (labels may need MLflow key cleaning)."""
    out = dict(summary["pooled"])
    out.update({f"class_mean/{k}": v for k, v in summary["class_mean"].items()})
    for label, row in summary["per_class"].iterrows():
        out.update({f"class/{label}/{k}": float(v) for k, v in row.items()})
    return out


STAGE_ERRORS = ("ad", "ads", "rot_err_deg", "rot_sym_err_deg", "trans_err")
"""The error columns of a stage of an instance table (``net_ad``, ``icp_ad``, ...)."""

STAGE_MEDIANS = {
    "trans_median_mm": "trans_err",
    "along_median_mm": "trans_along",
    "across_median_mm": "trans_across",
}
"""Median translation figures (mm) of :func:`stage_summary`: key -> the stage's column (the
parts along and across the viewing ray are the comparison's, ``studies.compare.ray_split``)."""


def stage_summary(
    table: pd.DataFrame, stage: str, medians: tuple[str, ...] = ("trans_median_mm",)
) -> dict[str, float]:
    """Pooled figures of one stage (``net``: the method's estimate, ``icp``: after ICP) of an
    instance table whose columns are ``{stage}_{error}``: :func:`summarize`'s pooled figures
    (fractions, and ``count``) and the median of each of ``medians``
    (:data:`STAGE_MEDIANS`, mm; NaN for no instances). What the comparison and the stress
    sweep each pick their columns from."""
    sub = table.rename(columns={f"{stage}_{k}": k for k in STAGE_ERRORS})
    out = dict(summarize(sub, by_class=False)["pooled"])
    for key in medians:
        values = table[f"{stage}_{STAGE_MEDIANS[key]}"]
        out[key] = 1000 * float(np.median(values)) if len(values) else float("nan")
    return out


def occlusion_bin_index(occlusion: np.ndarray, width: float = 0.1) -> tuple[np.ndarray, int]:
    """Bin of each occlusion factor: [0, w), [w, 2w), ..., the last closed at 1.

    Factors below 0 (a segmentation larger than the rendered silhouette) fall in the first bin,
    above 1 in the last; NaN factors get -1 (left out of every bin).

    Args:
        occlusion: (M,) occlusion factors O = 1 - lambda / nu.
        width: bin width, 1 / an integer.

    Returns:
        (M,) int64 bin indices and the number of bins.
    """
    occ = np.asarray(occlusion, dtype=np.float64)
    n_bins = round(1.0 / width)
    if not np.isclose(n_bins * width, 1.0):
        raise ValueError(f"width: expected 1 / integer, got {width}")
    edges = np.round(np.linspace(0.0, 1.0, n_bins + 1), 12)
    b = np.searchsorted(edges, np.clip(np.nan_to_num(occ, nan=0.0), 0.0, 1.0), side="right") - 1
    b = np.minimum(b, n_bins - 1)
    return np.where(np.isfinite(occ), b, -1), n_bins


def occlusion_bins(
    occlusion: np.ndarray, ads: np.ndarray, width: float = 0.1, threshold: float = 0.01
) -> pd.DataFrame:
    """ADS < 1 cm accuracy per occlusion bin (the paper's occlusion plot).

    Bins as :func:`occlusion_bin_index`. Misses (ADS inf) count as failures.

    Args:
        occlusion: (M,) occlusion factors O = 1 - lambda / nu.
        ads: (M,) ADS, metres, ``inf`` for misses.
        width: bin width.
        threshold: the accuracy threshold, metres.

    Returns:
        DataFrame with columns bin_lo, bin_hi, count, ads_lt_1cm (NaN for an empty bin).
    """
    occ = np.asarray(occlusion, dtype=np.float64)
    a = np.asarray(ads, dtype=np.float64)
    if occ.shape != a.shape or occ.ndim != 1:
        raise ValueError(f"occlusion, ads: expected equal shapes (M,), got {occ.shape}, {a.shape}")
    index, n_bins = occlusion_bin_index(occ, width)
    edges = np.round(np.linspace(0.0, 1.0, n_bins + 1), 12)
    keep = index >= 0
    b = index[keep]
    ok = a[keep] < threshold
    count = np.bincount(b, minlength=n_bins)
    hits = np.bincount(b, weights=ok.astype(float), minlength=n_bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = np.where(count > 0, hits / np.maximum(count, 1), np.nan)
    return pd.DataFrame(
        {"bin_lo": edges[:-1], "bin_hi": edges[1:], "count": count, "ads_lt_1cm": frac}
    )
