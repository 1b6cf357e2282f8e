"""Pose error metrics and their summaries, as the YCB-Video toolbox computes them.

DESIGN.md "Metrics":

- AD  = mean over model points x of |(R x + t) - (R^ x + t^)|                  (metres)
- ADS = mean over x1 of min over x2 of |(R x1 + t) - (R^ x2 + t^)|             (metres)
- rotation error = geodesic angle between R and R^ (degrees); translation error = |t - t^|.
- AUC = the toolbox's VOCap of the accuracy-threshold curve up to 0.1 m (``voc_ap_auc``).
- "<1cm" = share of instances with ADS < 0.01 m; rotation / translation shares likewise.

A miss (an instance without a usable segment or estimate) is never dropped: its errors are
infinite and it counts in every denominator, as in the toolbox.

Fast and reference twins: ``add_distance`` / ``adds_distance`` evaluate many instances at once
(ADS maps the ground-truth-posed points into the estimate's model frame, q = R^T((R x + t) - t^),
and queries the model's ``data.models.ModelIndex``, built once per model and shared with ICP);
``add_distance_reference`` / ``adds_distance_reference`` loop over instances and, for ADS, build a KD-tree on every
estimate as bop_toolkit's ``adi`` does. Tests show they agree.

Where numba is installed, ``adds_distance`` runs the compiled kernel
``cloudpose.kernels.adds_mean`` (parallel over instances): each nearest neighbour is found by a
downhill walk over the model's Delaunay graph, starting at the point's own model point or the
previous point's neighbour; the walk ends in the query's Voronoi cell, so the neighbour is
exact. The pykdtree path stays as the fallback and as a test twin.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import pandas as pd

from cloudpose import kernels
from cloudpose.data.models import ModelIndex

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
_AD_CHUNK_POINTS = 1 << 15
_ADS_CHUNK_POINTS = 1 << 18


# ---------------------------------------------------------------------------------------------
# Input checks


def _check_model(model_points: np.ndarray) -> np.ndarray:
    X = np.asarray(model_points, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3 or len(X) == 0:
        raise ValueError(f"model_points: expected shape (P, 3) with P >= 1, got {X.shape}")
    return X


def _check_poses(
    R_gt: np.ndarray, t_gt: np.ndarray, R_est: np.ndarray, t_est: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]:
    """Return (M, 3, 3), (M, 3), (M, 3, 3), (M, 3) float64 arrays and whether the input was a
    single unbatched pose."""
    arrays = [np.asarray(a, dtype=np.float64) for a in (R_gt, t_gt, R_est, t_est)]
    single = arrays[0].ndim == 2
    if single:
        arrays = [a[None] for a in arrays]
    M = len(arrays[0])
    expected = [(M, 3, 3), (M, 3), (M, 3, 3), (M, 3)]
    for name, a, shape in zip(("R_gt", "t_gt", "R_est", "t_est"), arrays, expected, strict=True):
        if a.shape != shape:
            raise ValueError(f"{name}: expected shape {shape}, got {a.shape}")
    return (*arrays, single)  # type: ignore[return-value]


def _out(values: np.ndarray, single: bool) -> np.ndarray:
    return values[0] if single else values


# ---------------------------------------------------------------------------------------------
# AD / ADS


def add_distance(
    model_points: np.ndarray,
    R_gt: np.ndarray,
    t_gt: np.ndarray,
    R_est: np.ndarray,
    t_est: np.ndarray,
) -> np.ndarray:
    """AD: mean distance between corresponding model points under the two poses (vectorised).

    Args:
        model_points: (P, 3) model points, metres.
        R_gt, t_gt: (M, 3, 3), (M, 3) ground-truth poses, model -> camera (or one (3, 3), (3,)).
        R_est, t_est: (M, 3, 3), (M, 3) estimated poses.

    Returns:
        (M,) AD in metres (a 0-d array for one unbatched pose).
    """
    X = _check_model(model_points)
    R_gt, t_gt, R_est, t_est, single = _check_poses(R_gt, t_gt, R_est, t_est)
    # (R x + t) - (R^ x + t^) = (R - R^) x + (t - t^): one (3C, 4) x (4, P) product per chunk.
    D = np.concatenate([R_gt - R_est, (t_gt - t_est)[:, :, None]], axis=2)  # (M, 3, 4)
    XhT = np.concatenate([X, np.ones((len(X), 1))], axis=1).T.copy()  # (4, P)
    out = np.empty(len(D))
    step = max(1, _AD_CHUNK_POINTS // len(X))
    for s in range(0, len(D), step):
        Dc = D[s : s + step]
        diff = (Dc.reshape(-1, 4) @ XhT).reshape(len(Dc), 3, len(X))  # (C, 3, P)
        out[s : s + step] = np.sqrt(np.einsum("cip,cip->cp", diff, diff)).mean(axis=1)
    return _out(out, single)


def add_distance_reference(
    model_points: np.ndarray,
    R_gt: np.ndarray,
    t_gt: np.ndarray,
    R_est: np.ndarray,
    t_est: np.ndarray,
) -> np.ndarray:
    """AD, one instance at a time, exactly as written (the twin of ``add_distance``)."""
    X = _check_model(model_points)
    R_gt, t_gt, R_est, t_est, single = _check_poses(R_gt, t_gt, R_est, t_est)
    out = np.empty(len(R_gt))
    for k in range(len(R_gt)):
        p_gt = X @ R_gt[k].T + t_gt[k]
        p_est = X @ R_est[k].T + t_est[k]
        out[k] = np.linalg.norm(p_gt - p_est, axis=1).mean()
    return _out(out, single)


def adds_distance(
    model_points: np.ndarray,
    R_gt: np.ndarray,
    t_gt: np.ndarray,
    R_est: np.ndarray,
    t_est: np.ndarray,
    *,
    index: ModelIndex | None = None,
) -> np.ndarray:
    """ADS: mean over ground-truth-posed points of the distance to the nearest estimate-posed
    point (vectorised, one KD-tree per model).

    The estimate-posed cloud is the model cloud moved rigidly, so instead of building a tree on
    it per instance, each ground-truth-posed point is mapped into the estimate's model frame,
    q = R^T((R x + t) - t^), and looked up in the model's own tree: the same distances.

    Args:
        model_points: (P, 3) model points, metres.
        R_gt, t_gt: (M, 3, 3), (M, 3) ground-truth poses, model -> camera (or one (3, 3), (3,)).
        R_est, t_est: (M, 3, 3), (M, 3) estimated poses; R_est must be orthonormal (the
            mapping uses R^T as the inverse: a float32-rounded rotation, off by ~1e-7, gives
            ADS within ~1e-7 relative of the per-instance tree's).
        index: optional prebuilt ``ModelIndex(model_points)`` (default: the cached one).

    Returns:
        (M,) ADS in metres (a 0-d array for one unbatched pose).
    """
    X = _check_model(model_points)
    R_gt, t_gt, R_est, t_est, single = _check_poses(R_gt, t_gt, R_est, t_est)
    index = index if index is not None else ModelIndex.of(X)
    if index.points.shape != X.shape:
        raise ValueError(
            f"index: built on {index.points.shape[0]} points, model_points has {X.shape[0]}"
        )
    Y = index.sorted_points  # the same points in Morton order (ADS is a mean: order-free)
    P = len(Y)
    A = np.swapaxes(R_est, 1, 2) @ R_gt  # (M, 3, 3): gt model frame -> est model frame
    b = np.einsum("mji,mj->mi", R_est, t_gt - t_est)  # (M, 3) = R^T (t - t^)
    W = np.concatenate([A, b[:, :, None]], axis=2)  # (M, 3, 4)
    if index.compiled is not None and np.isfinite(W).all():
        # compiled: a neighbour walk with an exactness certificate, k-d tree where it fails
        return _out(kernels.adds_mean(index.compiled, W), single)
    Yh = np.concatenate([Y, np.ones((P, 1))], axis=1)  # (P, 4)
    out = np.empty(len(W))
    step = max(1, _ADS_CHUNK_POINTS // P)
    for s in range(0, len(W), step):
        Wc = W[s : s + step]
        C = len(Wc)
        q = (Yh @ Wc.reshape(-1, 4).T).reshape(P, C, 3).transpose(1, 0, 2)  # (C, P, 3)
        d, _ = index.tree.query(np.ascontiguousarray(q).reshape(-1, 3), k=1)
        out[s : s + step] = d.reshape(C, P).mean(axis=1)
    return _out(out, single)


def adds_distance_reference(
    model_points: np.ndarray,
    R_gt: np.ndarray,
    t_gt: np.ndarray,
    R_est: np.ndarray,
    t_est: np.ndarray,
) -> np.ndarray:
    """ADS, one instance at a time with a KD-tree built on each estimate (bop_toolkit's ``adi``;
    the twin of ``adds_distance``)."""
    from scipy.spatial import cKDTree

    X = _check_model(model_points)
    R_gt, t_gt, R_est, t_est, single = _check_poses(R_gt, t_gt, R_est, t_est)
    out = np.empty(len(R_gt))
    for k in range(len(R_gt)):
        p_est = X @ R_est[k].T + t_est[k]
        p_gt = X @ R_gt[k].T + t_gt[k]
        d, _ = cKDTree(p_est).query(p_gt, k=1)
        out[k] = d.mean()
    return _out(out, single)


# ---------------------------------------------------------------------------------------------
# Rotation / translation errors


def rotation_error_deg(R_gt: np.ndarray, R_est: np.ndarray) -> np.ndarray:
    """Geodesic angle between rotations, degrees.

    Computed as atan2(|skew part|, (trace - 1) / 2) of R_gt^T R_est, accurate at 0 and at 180
    degrees where arccos of the trace is not.

    Args:
        R_gt: (..., 3, 3) rotations.
        R_est: (..., 3, 3) rotations.

    Returns:
        (...) angles in [0, 180] degrees.
    """
    R_gt = np.asarray(R_gt, dtype=np.float64)
    R_est = np.asarray(R_est, dtype=np.float64)
    if R_gt.shape[-2:] != (3, 3) or R_est.shape[-2:] != (3, 3):
        raise ValueError(
            f"R_gt, R_est: expected shape (..., 3, 3), got {R_gt.shape}, {R_est.shape}"
        )
    Rr = np.swapaxes(R_gt, -1, -2) @ R_est  # (..., 3, 3)
    v = np.stack(
        [
            Rr[..., 2, 1] - Rr[..., 1, 2],
            Rr[..., 0, 2] - Rr[..., 2, 0],
            Rr[..., 1, 0] - Rr[..., 0, 1],
        ],
        axis=-1,
    )  # 2 sin(theta) * axis
    sin = 0.5 * np.linalg.norm(v, axis=-1)
    cos = 0.5 * (np.trace(Rr, axis1=-2, axis2=-1) - 1.0)
    return np.degrees(np.arctan2(sin, cos))


def translation_error(t_gt: np.ndarray, t_est: np.ndarray) -> np.ndarray:
    """Euclidean distance between translations.

    Args:
        t_gt: (..., 3) metres.
        t_est: (..., 3) metres.

    Returns:
        (...) metres.
    """
    return np.linalg.norm(np.asarray(t_gt, float) - np.asarray(t_est, float), axis=-1)


# ---------------------------------------------------------------------------------------------
# Many instances of mixed classes


def pose_errors(
    model_points_by_class: Mapping[int, np.ndarray],
    cls_ids: np.ndarray,
    R_gt: np.ndarray,
    t_gt: np.ndarray,
    R_est: np.ndarray,
    t_est: np.ndarray,
    miss: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Per-instance AD, ADS, rotation and translation errors; misses get infinite errors.

    Args:
        model_points_by_class: class id (1-based) -> (P, 3) model points, metres.
        cls_ids: (M,) class id of each instance.
        R_gt, t_gt: (M, 3, 3), (M, 3) ground-truth poses, model -> camera.
        R_est, t_est: (M, 3, 3), (M, 3) estimated poses (ignored, may be NaN, for misses).
        miss: (M,) True where the instance has no estimate; None = no misses.

    Returns:
        Columns for a DataFrame, each (M,): ``cls_id``, ``miss``, ``ad`` and ``ads`` (metres),
        ``rot_err_deg``, ``trans_err`` (metres).
    """
    cls_ids = np.asarray(cls_ids).astype(np.int64)
    if cls_ids.ndim != 1:
        raise ValueError(f"cls_ids: expected shape (M,), got {cls_ids.shape}")
    M = len(cls_ids)
    R_gt, t_gt, R_est, t_est, single = _check_poses(R_gt, t_gt, R_est, t_est)
    if single or len(R_gt) != M:
        raise ValueError(
            f"R_gt: expected shape ({M}, 3, 3) (one per cls_ids entry), got {np.shape(R_gt)}"
        )
    miss = np.zeros(M, dtype=bool) if miss is None else np.asarray(miss, dtype=bool)
    if miss.shape != (M,):
        raise ValueError(f"miss: expected shape ({M},), got {miss.shape}")
    unknown = sorted(set(np.unique(cls_ids[~miss]).tolist()) - set(model_points_by_class))
    if unknown:
        raise ValueError(
            f"cls_ids: no model points for classes {unknown}; "
            f"model_points_by_class has {sorted(model_points_by_class)}"
        )
    bad = ~miss & ~(np.isfinite(R_est).all(axis=(1, 2)) & np.isfinite(t_est).all(axis=1))
    if bad.any():
        raise ValueError(
            f"R_est/t_est: non-finite estimates for instances {np.flatnonzero(bad)[:10].tolist()} "
            "not marked as misses"
        )

    ad = np.full(M, np.inf)
    ads = np.full(M, np.inf)
    rot = np.full(M, np.inf)
    trans = np.full(M, np.inf)
    hit = ~miss
    for c in np.unique(cls_ids[hit]):
        sel = np.flatnonzero(hit & (cls_ids == c))
        X = model_points_by_class[int(c)]
        args = (R_gt[sel], t_gt[sel], R_est[sel], t_est[sel])
        ad[sel] = add_distance(X, *args)
        ads[sel] = adds_distance(X, *args)
    rot[hit] = rotation_error_deg(R_gt[hit], R_est[hit])
    trans[hit] = translation_error(t_gt[hit], t_est[hit])
    return {
        "cls_id": cls_ids,
        "miss": miss,
        "ad": ad,
        "ads": ads,
        "rot_err_deg": rot,
        "trans_err": trans,
    }


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

    DESIGN.md: distances above 0.1 m become infinite; sort the finite ones,
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


def occlusion_bins(
    occlusion: np.ndarray, ads: np.ndarray, width: float = 0.1, threshold: float = 0.01
) -> pd.DataFrame:
    """ADS < 1 cm accuracy per occlusion bin (the paper's occlusion plot).

    Bins are [0, w), [w, 2w), ..., with the last closed at 1. Occlusion factors below 0 (a
    segmentation larger than the rendered silhouette) count in the first bin; NaN ones are left
    out. Misses (ADS inf) count as failures.

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
    n_bins = round(1.0 / width)
    if not np.isclose(n_bins * width, 1.0):
        raise ValueError(f"width: expected 1 / integer, got {width}")
    edges = np.round(np.linspace(0.0, 1.0, n_bins + 1), 12)
    keep = np.isfinite(occ)
    b = np.searchsorted(edges, np.clip(occ[keep], 0.0, 1.0), side="right") - 1
    b = np.minimum(b, n_bins - 1)
    ok = a[keep] < threshold
    count = np.bincount(b, minlength=n_bins)
    hits = np.bincount(b, weights=ok.astype(float), minlength=n_bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = np.where(count > 0, hits / np.maximum(count, 1), np.nan)
    return pd.DataFrame(
        {"bin_lo": edges[:-1], "bin_hi": edges[1:], "count": count, "ads_lt_1cm": frac}
    )
