"""Per-instance pose errors as the YCB-Video toolbox computes them: AD, ADS, rotation and
translation error (formula functions with plain arguments; fast and reference twins).

- AD  = mean over model points x of |(R x + t) - (R^ x + t^)| (Hinterstoisser et al., ACCV 2012)
- ADS = mean over x1 of min over x2 of |(R x1 + t) - (R^ x2 + t^)| (ibid.; the toolbox's ADD-S)
- rotation error = geodesic angle between R and R^ (degrees); translation error = |t - t^|.

(R, t) is the ground truth, (R^, t^) the estimate. Arguments come in bop_toolkit's order,
estimate first: ``add(R_est, t_est, R_gt, t_gt, pts)``, ``adi(...)``, ``te(t_est, t_gt)``
(bop_toolkit_lib/pose_error.py). ADS is not symmetric in the two poses (each ground-truth-posed
point's nearest estimate-posed point): swapped poses have the same shapes and give another
number, which no check can catch. So AD, ADS, their twins and :func:`pose_errors` take the
poses as keyword-only arguments, ``R_est=, t_est=, R_gt=, t_gt=``, and every call says which
pose is which (AD is symmetric, but it is called beside ADS with the same arguments, so it takes
them the same way). The model points come first and positional: no pose can stand in for them
unnoticed ((P, 3) points against (M, 3, 3) rotations). :func:`translation_error` (here) and
:func:`~cloudpose.geometry.rigid.rotation_error_deg` are symmetric (a swap gives the same
number, tested), so they stay positional: ``translation_error(t_est, t_gt)``.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from cloudpose import kernels
from cloudpose.geometry.rigid import rotation_error_deg
from cloudpose.kernels.model_index import ModelIndex

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
    R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]:
    """Return (M, 3, 3), (M, 3), (M, 3, 3), (M, 3) float64 arrays (R_est, t_est, R_gt, t_gt)
    and whether the input was a single unbatched pose."""
    arrays = [np.asarray(a, dtype=np.float64) for a in (R_est, t_est, R_gt, t_gt)]
    single = arrays[0].ndim == 2
    if single:
        arrays = [a[None] for a in arrays]
    M = len(arrays[0])
    expected = [(M, 3, 3), (M, 3), (M, 3, 3), (M, 3)]
    for name, a, shape in zip(("R_est", "t_est", "R_gt", "t_gt"), arrays, expected, strict=True):
        if a.shape != shape:
            raise ValueError(f"{name}: expected shape {shape}, got {a.shape}")
    return (*arrays, single)  # type: ignore[return-value]


def _out(values: np.ndarray, single: bool) -> np.ndarray:
    return values[0] if single else values


# ---------------------------------------------------------------------------------------------
# AD / ADS


def add_distance(
    model_points: np.ndarray,
    *,
    R_est: np.ndarray,
    t_est: np.ndarray,
    R_gt: np.ndarray,
    t_gt: np.ndarray,
) -> np.ndarray:
    """AD: mean distance between corresponding model points under the two poses (vectorised).

    Args:
        model_points: (P, 3) model points, metres.
        R_est, t_est: (M, 3, 3), (M, 3) estimated poses, model -> camera (or one (3, 3), (3,)).
        R_gt, t_gt: (M, 3, 3), (M, 3) ground-truth poses.

    Returns:
        (M,) AD in metres (a 0-d array for one unbatched pose).
    """
    X = _check_model(model_points)
    R_est, t_est, R_gt, t_gt, single = _check_poses(R_est, t_est, R_gt, t_gt)
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
    *,
    R_est: np.ndarray,
    t_est: np.ndarray,
    R_gt: np.ndarray,
    t_gt: np.ndarray,
) -> np.ndarray:
    """AD, one instance at a time, exactly as written (the twin of ``add_distance``)."""
    X = _check_model(model_points)
    R_est, t_est, R_gt, t_gt, single = _check_poses(R_est, t_est, R_gt, t_gt)
    out = np.empty(len(R_gt))
    for k in range(len(R_gt)):
        p_gt = X @ R_gt[k].T + t_gt[k]
        p_est = X @ R_est[k].T + t_est[k]
        out[k] = np.linalg.norm(p_gt - p_est, axis=1).mean()
    return _out(out, single)


def adds_distance(
    model_points: np.ndarray,
    *,
    R_est: np.ndarray,
    t_est: np.ndarray,
    R_gt: np.ndarray,
    t_gt: np.ndarray,
    index: ModelIndex | None = None,
) -> np.ndarray:
    """ADS: mean over ground-truth-posed points of the distance to the nearest estimate-posed
    point (vectorised, one KD-tree per model).

    The estimate-posed cloud is the model cloud moved rigidly, so instead of building a tree on
    it per instance, each ground-truth-posed point is mapped into the estimate's model frame,
    q = R^T((R x + t) - t^), and looked up in the model's own tree: the same distances.

    Args:
        model_points: (P, 3) model points, metres.
        R_est, t_est: (M, 3, 3), (M, 3) estimated poses, model -> camera (or one (3, 3), (3,));
            R_est must be orthonormal (the mapping uses R^T as the inverse: a float32-rounded
            rotation, off by ~1e-7, gives ADS within ~1e-7 relative of the per-instance tree's).
        R_gt, t_gt: (M, 3, 3), (M, 3) ground-truth poses.
        index: optional prebuilt ``ModelIndex(model_points)`` (default: the cached one).

    Returns:
        (M,) ADS in metres (a 0-d array for one unbatched pose).
    """
    X = _check_model(model_points)
    R_est, t_est, R_gt, t_gt, single = _check_poses(R_est, t_est, R_gt, t_gt)
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
    *,
    R_est: np.ndarray,
    t_est: np.ndarray,
    R_gt: np.ndarray,
    t_gt: np.ndarray,
) -> np.ndarray:
    """ADS, one instance at a time with a KD-tree built on each estimate (bop_toolkit's ``adi``;
    the twin of ``adds_distance``)."""
    from scipy.spatial import cKDTree

    X = _check_model(model_points)
    R_est, t_est, R_gt, t_gt, single = _check_poses(R_est, t_est, R_gt, t_gt)
    out = np.empty(len(R_gt))
    for k in range(len(R_gt)):
        p_est = X @ R_est[k].T + t_est[k]
        p_gt = X @ R_gt[k].T + t_gt[k]
        d, _ = cKDTree(p_est).query(p_gt, k=1)
        out[k] = d.mean()
    return _out(out, single)


# ---------------------------------------------------------------------------------------------
# Translation error (the rotation error is cloudpose.geometry.rigid.rotation_error_deg)


def translation_error(t_est: np.ndarray, t_gt: np.ndarray) -> np.ndarray:
    """Euclidean distance between translations (bop_toolkit's ``te``; symmetric).

    Args:
        t_est: (..., 3) metres.
        t_gt: (..., 3) metres.

    Returns:
        (...) metres.
    """
    return np.linalg.norm(np.asarray(t_gt, float) - np.asarray(t_est, float), axis=-1)


# ---------------------------------------------------------------------------------------------
# Many instances of mixed classes


def pose_errors(
    model_points_by_class: Mapping[int, np.ndarray],
    cls_ids: np.ndarray,
    *,
    R_est: np.ndarray,
    t_est: np.ndarray,
    R_gt: np.ndarray,
    t_gt: np.ndarray,
    miss: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Per-instance AD, ADS, rotation and translation errors; misses get infinite errors.

    Args:
        model_points_by_class: class id (1-based) -> (P, 3) model points, metres.
        cls_ids: (M,) class id of each instance.
        R_est, t_est: (M, 3, 3), (M, 3) estimated poses, model -> camera (ignored, may be
            NaN, for misses).
        R_gt, t_gt: (M, 3, 3), (M, 3) ground-truth poses.
        miss: (M,) True where the instance has no estimate; None = no misses.

    Returns:
        Columns for a DataFrame, each (M,): ``cls_id``, ``miss``, ``ad`` and ``ads`` (metres),
        ``rot_err_deg``, ``trans_err`` (metres).
    """
    cls_ids = np.asarray(cls_ids).astype(np.int64)
    if cls_ids.ndim != 1:
        raise ValueError(f"cls_ids: expected shape (M,), got {cls_ids.shape}")
    M = len(cls_ids)
    R_est, t_est, R_gt, t_gt, single = _check_poses(R_est, t_est, R_gt, t_gt)
    if single or len(R_est) != M:
        raise ValueError(
            f"R_est: expected shape ({M}, 3, 3) (one per cls_ids entry), got {np.shape(R_est)}"
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
        poses = {"R_est": R_est[sel], "t_est": t_est[sel], "R_gt": R_gt[sel], "t_gt": t_gt[sel]}
        ad[sel] = add_distance(X, **poses)
        ads[sel] = adds_distance(X, **poses)
    rot[hit] = rotation_error_deg(R_gt[hit], R_est[hit])
    trans[hit] = translation_error(t_est[hit], t_gt[hit])
    return {
        "cls_id": cls_ids,
        "miss": miss,
        "ad": ad,
        "ads": ads,
        "rot_err_deg": rot,
        "trans_err": trans,
    }
