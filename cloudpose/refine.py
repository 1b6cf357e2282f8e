"""ICP refinement of a network pose estimate against the object's model points.

The paper's schedule (docs/design.md "Refinement"): Open3D point-to-point ICP, 10 iterations, the
maximum correspondence distance starting at 0.01 m and shrinking by 10% after each iteration.
The observed segment (source) is registered to the model points posed by the estimate (target),
so each observed point finds its model point and the model's hidden back side does not pull the
fit; the resulting correction is composed with the estimate.

Two implementations give the same poses:

- ``icp_refine_open3d``: the reference, ten calls of ``o3d.pipelines.registration.registration_icp``
  with ``max_iteration=1`` each and the shrinking radius (Open3D rebuilds its KD-tree every call).
- ``icp_refine`` / ``icp_refine_batch``: the fast path. ICP is invariant to a rigid motion
  applied to both clouds, so it runs in the model frame: the observed points are mapped by the
  inverse estimate, the target is the raw model, and one KD-tree per model serves every
  iteration and every instance of that model. Each iteration is one nearest-neighbour query
  bounded by the current radius and one closed-form (Umeyama, no scale) alignment, exactly
  Open3D's ``TransformationEstimationPointToPoint``.

Open3D semantics reproduced here (``RegistrationICP`` with ``max_iteration=1``): a source point
corresponds to its nearest target point if their squared distance is below the squared radius;
the update is Umeyama's rotation (reflection-corrected as in Eigen's ``umeyama``) on those pairs,
or the identity when there are none; the returned fitness and inlier RMSE are re-evaluated after
the update with the same radius: fitness = inliers / source points, inlier_rmse =
sqrt(mean squared inlier distance) (0 when no inlier). With one iteration per call, Open3D's
convergence criteria (relative fitness / RMSE 1e-6) never stop a call early. One deliberate
difference: with exactly two correspondences the rotation is undetermined and Eigen returns an
arbitrary one; the fast path then moves by the translation only.

Where numba is installed, the whole loop runs compiled (``cloudpose.kernels.icp_model_frame``):
the first iteration's correspondences come from a bounded k-d tree search, later ones from a
walk over the model's Delaunay graph from each point's previous nearest point, skipped while
the point has not moved far enough to leave that point's Voronoi cell. Each correspondence is
the exact nearest model point, so the poses are those of the pykdtree loop, which stays as the
fallback.

The guard (``ICPSettings.fallback``, off in the paper's schedule): ICP has no notion of having
failed, and a start far from the object converges to whatever surface lies within the radius.
With the guard on, a refinement whose final fitness is below ``min_fitness`` returns the initial
pose instead (``ICPSolution.fallback``). The inlier RMSE cannot serve: it is measured within the
last radius (3.9 mm in the paper's schedule), so it stays near 2.5 mm whether ICP converged or
not (reports/diagnostics/icp_fallback.md).

Choosing among starts (``ICPSettings.select``, ``icp.select``): with several starts, each
refinement is scored by ICP's fitness alone (``fitness``) or by how the posed model agrees with
the frame's depth (``depth``, :func:`depth_score`): fitness and coverage of the segment, minus
the share of model points that lie in front of the observed surface, in space the sensor saw
through (free-space violations). The depth score needs the frame's depth and intrinsics
(:class:`DepthView`; :func:`segment_views` reads them for a segment set).

Many segments at once (:func:`refine_poses`): every row of a segment set refined from its
:class:`Estimates`, with ICP's figures per row (:class:`ICPStats`); several estimates of the
same rows (an ensemble's networks, a combination's methods) are each refined and, per row, the
refinement of the best score kept (:func:`refine_ensemble`, :func:`select_refinements`).

Threads: the fast path runs BLAS and pykdtree on one thread while it works (``threadpoolctl``);
a 1,000-point query gains nothing from a second thread, and OpenMP's spinning fork/join made it
10-30x slower whenever another process held a core.
"""

from __future__ import annotations

import functools
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation
from threadpoolctl import ThreadpoolController
from tqdm.auto import tqdm

from cloudpose import kernels
from cloudpose.config import MAX_RADIUS, PAPER_RADIUS, START_GROUPS
from cloudpose.geometry.rigid import umeyama_from_moments
from cloudpose.kernels.model_index import ModelIndex


@functools.cache
def start_rotations(starts: int) -> np.ndarray:
    """(starts, 3, 3) rotations ICP starts from, applied in the model frame; the identity first."""
    if starts not in START_GROUPS:
        raise ValueError(f"starts: expected one of {sorted(START_GROUPS)}, got {starts!r}")
    if starts == 1:
        return np.eye(3)[None]
    group = Rotation.create_group(START_GROUPS[starts]).as_matrix()
    identity = np.isclose(group, np.eye(3), atol=1e-9).all(axis=(1, 2))
    out = np.concatenate([np.eye(3)[None], group[~identity]])
    out.setflags(write=False)
    return out


SELECTIONS = ("fitness", "depth")
"""How the ICP starts are scored (``ICPSettings.select``, ``icp.select``): ``fitness``, the
share of observed points within the last radius (Open3D's); ``depth``, :func:`depth_score`."""

FREE_SPACE_TOL = 0.01
"""Metres by which a posed model point must lie in front of the observed surface to count as a
free-space violation, and within which a segment point counts as covered (:func:`depth_score`)."""


class DepthView(NamedTuple):
    """The observed depth an instance's segment came from (``ICPSettings.select = "depth"``).

    Attributes:
        depth: (H, W) depth in metres, 0 = no reading.
        K: (3, 3) intrinsics.
    """

    depth: np.ndarray
    K: np.ndarray


class DepthAgreement(NamedTuple):
    """How a posed model agrees with the observed depth (:func:`depth_agreement`).

    Attributes:
        coverage: share of segment points within :data:`FREE_SPACE_TOL` of the posed model.
        violation: share of the posed model's points that project onto a pixel with a depth
            reading and lie more than :data:`FREE_SPACE_TOL` in front of it: space the sensor
            saw through (0 when none projects onto a reading).
    """

    coverage: float
    violation: float


def depth_agreement(
    observed: np.ndarray,
    model: np.ndarray | ModelIndex,
    R: np.ndarray,
    t: np.ndarray,
    view: DepthView,
    tol: float = FREE_SPACE_TOL,
) -> DepthAgreement:
    """Coverage of the segment and free-space violations of the model posed by ``(R, t)``.

    Args:
        observed: (N, 3) segment points, camera frame, metres.
        model: (P, 3) model points (model frame, metres) or their :class:`ModelIndex`.
        R: (3, 3) rotation model -> camera; t: (3,) translation, metres.
        view: the frame's depth and intrinsics.
        tol: metres (:data:`FREE_SPACE_TOL`).
    """
    index = _index_of(model)
    X = index.points @ R.T + t  # (P, 3) posed model, camera frame
    z = X[:, 2]
    H, W = view.depth.shape
    front = z > 1e-6
    uv = np.full((len(X), 2), -1, dtype=np.int64)
    proj = X[front] @ np.asarray(view.K, dtype=np.float64).T
    uv[front] = np.floor(proj[:, :2] / proj[:, 2:3] + 0.5).astype(np.int64)
    inside = front & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
    d = np.zeros(len(X))
    d[inside] = view.depth[uv[inside, 1], uv[inside, 0]]
    seen = inside & (d > 0)
    violation = float(np.mean(z[seen] < d[seen] - tol)) if seen.any() else 0.0
    q = (np.asarray(observed, dtype=np.float64) - t) @ R  # segment in the model frame
    _, idx = index.tree.query(q, k=1, distance_upper_bound=tol)
    coverage = float(np.mean(idx < len(index.points))) if len(q) else 0.0
    return DepthAgreement(coverage, violation)


def depth_score(fitness: float, agreement: DepthAgreement) -> float:
    """The ``depth`` selection's score of an ICP start: (fitness + coverage) / 2 - violation.

    Fitness and coverage reward explaining the segment (within the last radius and within
    :data:`FREE_SPACE_TOL`); a model that sticks out into space the sensor saw through loses
    the share of its points that do. Weights fixed by the form, not fitted to any data.
    """
    return 0.5 * (fitness + agreement.coverage) - agreement.violation


@dataclass(frozen=True)
class ICPSettings:
    """The refinement schedule.

    Attributes:
        iterations: number of ICP iterations (one Open3D call each in the reference).
        max_distance: maximum correspondence distance of the first iteration, metres.
        shrink: factor applied to the distance after each iteration (0.9 = shrink by 10%).
        fallback: keep the initial pose when the refinement's fitness is below
            ``min_fitness`` (the paper has no such guard).
        min_fitness: with ``fallback``, the least share of observed points within the last
            radius for the refined pose to be kept (0..1).
        starts: rotations of the estimate ICP starts from, keeping the best fit: 1 (the
            estimate only, the paper), 12, 24 or 60 (:data:`START_GROUPS`; module doc).
        start_margin: share of observed points by which another start's score must exceed
            the estimate's own to replace it (0..1).
        select: how the starts are scored (:data:`SELECTIONS`): ``fitness`` (ICP's fitness
            alone) or ``depth`` (:func:`depth_score`: fitness, coverage of the segment and
            free-space violations against the observed depth; needs the frame's depth).
    """

    iterations: int = 10
    max_distance: float = PAPER_RADIUS
    shrink: float = 0.9
    fallback: bool = False
    min_fitness: float = 0.1
    starts: int = 1
    start_margin: float = 0.02
    select: str = "fitness"

    def __post_init__(self) -> None:
        if self.select not in SELECTIONS:
            raise ValueError(
                f"ICPSettings.select: expected one of {', '.join(SELECTIONS)}, got {self.select!r}"
            )
        if not 0 <= self.min_fitness <= 1:
            raise ValueError(f"ICPSettings.min_fitness: expected in [0, 1], got {self.min_fitness}")
        if self.iterations < 1:
            raise ValueError(f"ICPSettings.iterations: expected >= 1, got {self.iterations}")
        if not self.max_distance > 0:
            raise ValueError(
                f"ICPSettings.max_distance: expected > 0 metres, got {self.max_distance}"
            )
        if not 0 < self.shrink <= 1:
            raise ValueError(f"ICPSettings.shrink: expected in (0, 1], got {self.shrink}")
        if self.starts not in START_GROUPS:
            raise ValueError(
                f"ICPSettings.starts: expected one of {sorted(START_GROUPS)}, got {self.starts!r}"
            )
        if not 0 <= self.start_margin <= 1:
            raise ValueError(
                f"ICPSettings.start_margin: expected in [0, 1], got {self.start_margin}"
            )

    @classmethod
    def from_config(cls, icp) -> ICPSettings:
        """The schedule with the guard of a run's ``icp`` config section
        (:class:`cloudpose.config.ICPConfig`)."""
        return cls(
            fallback=icp.fallback,
            min_fitness=icp.fallback_min_fitness,
            starts=icp.starts,
            start_margin=icp.start_margin,
            select=getattr(icp, "select", "fitness"),
            **schedule_for(getattr(icp, "radius", PAPER_RADIUS)),
        )

    def radii(self) -> list[float]:
        """Maximum correspondence distance of each iteration, metres (repeated multiplication,
        the same floats in both implementations)."""
        out, r = [], float(self.max_distance)
        for _ in range(self.iterations):
            out.append(r)
            r *= self.shrink
        return out


def schedule_for(radius: float) -> dict[str, float | int]:
    """``max_distance`` and ``iterations`` of the schedule whose first correspondence distance
    is ``radius`` (metres, at least the paper's 0.01): the paper's 10 iterations at a 10% shrink,
    and as many more as it takes the shrink to bring ``radius`` down to the paper's first
    radius, so every schedule ends within 5% of the paper's last radius (3.9 mm). A wider
    first radius reaches estimates that are farther off, in translation above all
    (reports/diagnostics/icp_radius_*.md); the last iterations are as tight as the paper's."""
    base = ICPSettings()
    if not PAPER_RADIUS <= radius <= MAX_RADIUS:
        raise ValueError(
            f"ICP radius {radius} m: expected from the paper's {PAPER_RADIUS} to {MAX_RADIUS} m"
        )
    extra = round(float(np.log(radius / base.max_distance) / -np.log(base.shrink)))
    return {"max_distance": float(radius), "iterations": base.iterations + extra}


def settings_overrides(fields: dict) -> dict:
    """The fields of :class:`ICPSettings` a refinement's ``{"starts", "select", "radius"}``
    (any of them; :func:`cloudpose.config.refinement`) set: the radius as its schedule
    (:func:`schedule_for`)."""
    out = {k: fields[k] for k in ("starts", "select") if k in fields}
    if "radius" in fields:
        out |= schedule_for(fields["radius"])
    return out


class ICPSolution(NamedTuple):
    """A refined pose with Open3D's quality figures for the last iteration.

    Attributes:
        R: (3, 3) refined rotation, model -> camera.
        t: (3,) refined translation, metres.
        fitness: share of observed points with a model point within the last radius (0..1).
        inlier_rmse: RMS distance of those pairs, metres (0 when there are none).
        fallback: the guard kept the initial pose (``R``, ``t`` are the start; ``fitness`` and
            ``inlier_rmse`` still describe the refinement it rejected).
    """

    R: np.ndarray
    t: np.ndarray
    fitness: float
    inlier_rmse: float
    fallback: bool = False


class ICPStats(NamedTuple):
    """The quality figures of many refinements (rows of a segment set).

    Attributes:
        fitness: (M,) :attr:`ICPSolution.fitness` (NaN for a row not refined).
        inlier_rmse: (M,) :attr:`ICPSolution.inlier_rmse`, metres (NaN for a row not refined).
        fallback: (M,) bool, :attr:`ICPSolution.fallback`.
    """

    fitness: np.ndarray
    inlier_rmse: np.ndarray
    fallback: np.ndarray


def _guard(
    sol: ICPSolution, R_init: np.ndarray, t_init: np.ndarray, settings: ICPSettings
) -> ICPSolution:
    """``sol``, or the initial pose when the guard is on and the fitness is too low."""
    if settings.fallback and sol.fitness < settings.min_fitness:
        return ICPSolution(R_init.copy(), t_init.copy(), sol.fitness, sol.inlier_rmse, True)
    return sol


# ---------------------------------------------------------------------------------------------
# Input checks


def _check_points(name: str, a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name}: expected shape (N, 3), got {a.shape}")
    return a


def _check_pose(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if R.shape != (3, 3):
        raise ValueError(f"R_init: expected shape (3, 3), got {R.shape}")
    if t.shape != (3,):
        raise ValueError(f"t_init: expected shape (3,), got {t.shape}")
    return R, t


def _check_view(settings: ICPSettings, view: DepthView | None) -> None:
    if settings.select == "depth" and settings.starts > 1:
        if view is None:
            raise ValueError(
                "ICP starts scored by depth (select='depth') need the frame's depth: pass view"
            )
        if np.ndim(view.depth) != 2 or np.shape(view.K) != (3, 3):
            raise ValueError(
                f"view: expected (H, W) depth and (3, 3) K, got {np.shape(view.depth)} and "
                f"{np.shape(view.K)}"
            )


def _degenerate(R: np.ndarray, t: np.ndarray, why: str) -> ICPSolution:
    warnings.warn(f"ICP skipped ({why}); returning the initial pose", stacklevel=3)
    return ICPSolution(R.copy(), t.copy(), 0.0, 0.0)


# ---------------------------------------------------------------------------------------------
# Fast path


def _index_of(model_points: np.ndarray | ModelIndex) -> ModelIndex:
    """The model's shared index (built once per distinct point set, see ``ModelIndex.of``)."""
    if isinstance(model_points, ModelIndex):
        return model_points
    X = _check_points("model_points", model_points)
    if len(X) == 0:
        raise ValueError("model_points: expected at least one point, got 0")
    return ModelIndex.of(X)


_controller: ThreadpoolController | None = None


def _single_threaded():
    """Context that runs BLAS and pykdtree's OpenMP on one thread.

    One object's 1,000-point queries and 4 x 4 products are too small to gain from threads,
    and spinning fork/join turned 4 ms refinements into 40-120 ms ones when another process
    (or torch's own thread pool) held one of the two cores.
    """
    global _controller
    if _controller is None:  # made once: it lists the process's loaded thread pools
        _controller = ThreadpoolController()
    return _controller.limit(limits=1)


def icp_refine(
    observed: np.ndarray,
    model_points: np.ndarray | ModelIndex,
    R_init: np.ndarray,
    t_init: np.ndarray,
    settings: ICPSettings = ICPSettings(),
    view: DepthView | None = None,
) -> ICPSolution:
    """Refine one pose estimate with point-to-point ICP (fast path, same poses as Open3D's).

    Args:
        observed: (N, 3) observed segment points, camera frame, metres.
        model_points: (P, 3) model points in the model frame, metres, or a prebuilt
            ``ModelIndex`` of them (reuse it across instances of the model).
        R_init: (3, 3) estimated rotation, model -> camera.
        t_init: (3,) estimated translation, metres.
        settings: the schedule, the guard and the starts.
        view: the frame's depth and intrinsics; needed with ``settings.select == "depth"``
            and more than one start.

    Returns:
        The refined pose with Open3D's fitness and inlier RMSE for the last iteration (of the
        start kept, with ``settings.starts`` > 1); the initial pose (``fallback`` True) when ``settings.fallback`` and the fitness is below
        ``settings.min_fitness``. With fewer than 3 observed points, or no model point within
        the first radius, the initial pose with fitness 0 (and a warning).
    """
    observed = _check_points("observed", observed)
    R_init, t_init = _check_pose(R_init, t_init)
    _check_view(settings, view)
    if len(observed) < 3:
        return _degenerate(R_init, t_init, f"{len(observed)} observed points, need >= 3")
    index = _index_of(model_points)
    if index.compiled is not None:  # compiled: no BLAS or OpenMP threads to hold back
        sol = _refine_starts(observed, index, R_init, t_init, settings, view)
    else:
        with _single_threaded():
            sol = _refine_starts(observed, index, R_init, t_init, settings, view)
    return _guard(sol, R_init, t_init, settings)


def _refine_starts(
    observed: np.ndarray,
    index: ModelIndex,
    R_init: np.ndarray,
    t_init: np.ndarray,
    settings: ICPSettings,
    view: DepthView | None = None,
) -> ICPSolution:
    """ICP from the estimate and, with ``settings.starts`` > 1, from each turned start; the best
    by ``settings.select`` (the estimate's own unless another beats it by more than
    ``start_margin``)."""
    radii = settings.radii()
    best = _icp_model_frame(observed, index, R_init, t_init, radii)
    if settings.starts == 1:
        return best

    def score(sol: ICPSolution) -> float:
        if settings.select == "fitness":
            return sol.fitness
        return depth_score(sol.fitness, depth_agreement(observed, index, sol.R, sol.t, view))

    to_beat = score(best) + settings.start_margin
    for D in start_rotations(settings.starts)[1:]:
        sol = _icp_model_frame(observed, index, R_init @ D, t_init, radii, quiet=True)
        if sol is None:
            continue
        s = score(sol)
        if s > to_beat:
            best, to_beat = sol, s
    return best


def _icp_model_frame(
    observed: np.ndarray,
    index: ModelIndex,
    R_init: np.ndarray,
    t_init: np.ndarray,
    radii,
    quiet: bool = False,
) -> ICPSolution | None:
    """One refinement in the model frame; with ``quiet``, None instead of the warned initial
    pose when no model point lies within the first radius."""
    N = len(observed)
    if index.compiled is not None and np.isfinite(observed).all():
        T_acc, n_inl, sum_d2 = kernels.icp_model_frame(
            index.compiled, (observed - t_init) @ R_init, np.asarray(radii, dtype=np.float64)
        )
        if n_inl < 0:
            if quiet:
                return None
            return _degenerate(R_init, t_init, f"no model point within {radii[0]} m")
        R = R_init @ T_acc[:3, :3].T
        t = t_init - R @ T_acc[:3, 3]
        return ICPSolution(R, t, n_inl / N, float(np.sqrt(sum_d2 / n_inl)) if n_inl else 0.0)
    cur = np.empty((N, 4))  # homogeneous observed points in the estimate's model frame
    cur[:, :3] = (observed - t_init) @ R_init  # R^T (p - t), row-major
    cur[:, 3] = 1.0
    T_acc = np.eye(4)  # accumulated correction: cur = src_h @ T_acc.T
    tree, model_h = index.tree, index.sorted_h
    for i, r in enumerate(radii):
        _, idx = tree.query(cur[:, :3], k=1, distance_upper_bound=r, sqr_dists=True)
        matched = np.take(model_h, idx, axis=0)  # (N, 4); zero rows for "no neighbour"
        S = matched.T @ cur  # (4, 4) moments of the correspondences
        if i == 0 and S[3, 3] == 0:
            if quiet:
                return None
            return _degenerate(R_init, t_init, f"no model point within {r} m")
        T_u = umeyama_from_moments(S)
        cur = cur @ T_u.T
        T_acc = T_u @ T_acc
    r = radii[-1]
    d2, idx = tree.query(cur[:, :3], k=1, distance_upper_bound=r, sqr_dists=True)
    found = idx < len(index.points)
    n_inl = int(found.sum())
    rmse = float(np.sqrt(d2[found].mean())) if n_inl else 0.0
    # cur = A R_init^T (p - t_init) + a ~ m  =>  p ~ R_init A^T (m - a) + t_init
    R = R_init @ T_acc[:3, :3].T
    t = t_init - R @ T_acc[:3, 3]
    return ICPSolution(R, t, n_inl / N, rmse)


def icp_refine_batch(
    observed: Sequence[np.ndarray],
    model_points: Sequence[np.ndarray | ModelIndex],
    R_init: np.ndarray,
    t_init: np.ndarray,
    settings: ICPSettings = ICPSettings(),
    views: Sequence[DepthView | None] | None = None,
) -> list[ICPSolution]:
    """Refine many pose estimates (the same result as ``icp_refine`` on each).

    Instances that share a model (the same points or ``ModelIndex``) share one index.

    Args:
        observed: M arrays (N_i, 3), camera frame, metres.
        model_points: M arrays (P_i, 3) in the model frame or ``ModelIndex`` objects (pass the
            same object for every instance of a class).
        R_init: (M, 3, 3) estimated rotations, model -> camera.
        t_init: (M, 3) estimated translations, metres.
        settings: the schedule.
        views: M depth views (``settings.select == "depth"``), or None.

    Returns:
        M solutions, in input order.
    """
    M = len(observed)
    if len(model_points) != M:
        raise ValueError(
            f"model_points: expected {M} entries (one per observed), got {len(model_points)}"
        )
    R_init = np.asarray(R_init, dtype=np.float64)
    t_init = np.asarray(t_init, dtype=np.float64)
    if R_init.shape != (M, 3, 3):
        raise ValueError(f"R_init: expected shape ({M}, 3, 3), got {R_init.shape}")
    if t_init.shape != (M, 3):
        raise ValueError(f"t_init: expected shape ({M}, 3), got {t_init.shape}")
    out = []
    with _single_threaded():
        for i in range(M):
            obs = _check_points(f"observed[{i}]", observed[i])
            if len(obs) < 3:
                out.append(
                    _degenerate(R_init[i], t_init[i], f"{len(obs)} observed points, need >= 3")
                )
                continue
            view = views[i] if views is not None else None
            _check_view(settings, view)
            index = _index_of(model_points[i])
            sol = _refine_starts(obs, index, R_init[i], t_init[i], settings, view)
            out.append(_guard(sol, R_init[i], t_init[i], settings))
    return out


# ---------------------------------------------------------------------------------------------
# Reference


def icp_refine_open3d(
    observed: np.ndarray,
    model_points: np.ndarray,
    R_init: np.ndarray,
    t_init: np.ndarray,
    settings: ICPSettings = ICPSettings(),
) -> ICPSolution:
    """The reference refinement: one Open3D ``registration_icp`` call per iteration.

    Same arguments and result as ``icp_refine``. Source = observed points, target = model
    points posed by the estimate; the accumulated correction T (observed -> posed model) is
    composed with the estimate as T^-1 (R_init, t_init).
    """
    import open3d as o3d

    if settings.starts != 1:
        raise ValueError(
            f"icp_refine_open3d refines from the estimate only (starts=1), got {settings.starts}"
        )
    reg = o3d.pipelines.registration
    observed = _check_points("observed", observed)
    model_points = _check_points("model_points", model_points)
    R_init, t_init = _check_pose(R_init, t_init)
    if len(observed) < 3:
        return _degenerate(R_init, t_init, f"{len(observed)} observed points, need >= 3")
    if len(model_points) == 0:
        return _degenerate(R_init, t_init, "no model points")

    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(observed))
    target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(model_points @ R_init.T + t_init))
    estimation = reg.TransformationEstimationPointToPoint(False)
    criteria = reg.ICPConvergenceCriteria(max_iteration=1)
    T = np.eye(4)
    result = None
    radii = settings.radii()
    for i, r in enumerate(radii):
        result = reg.registration_icp(source, target, r, T, estimation, criteria)
        T = np.asarray(result.transformation)
        if i == 0 and result.fitness == 0 and np.array_equal(T, np.eye(4)):
            # No correspondence at the start: Open3D made the identity update.
            return _degenerate(R_init, t_init, f"no model point within {r} m")
    assert result is not None
    # observed ~ T^-1 (R_init m + t_init)
    R_T, t_T = T[:3, :3], T[:3, 3]
    R = R_T.T @ R_init
    t = R_T.T @ (t_init - t_T)
    sol = ICPSolution(R, t, float(result.fitness), float(result.inlier_rmse))
    return _guard(sol, R_init, t_init, settings)


def segment_views(dataset, segs) -> list[DepthView | None]:
    """The depth view of every row of a segment set (``segs.frame_id``), each frame read once
    from ``dataset`` (:mod:`cloudpose.data.layout`); None for a row without a frame id."""
    cache: dict[str, DepthView] = {}
    out: list[DepthView | None] = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a frame's read warnings were given when it was cached
        for fid in np.asarray(segs.frame_id).astype(str):
            if not fid:
                out.append(None)
                continue
            if fid not in cache:
                f = dataset.frame(fid)
                cache[fid] = DepthView(f.depth, np.asarray(f.K, dtype=np.float64))
            out.append(cache[fid])
    return out


# --------------------------------------------------------------------------- many segments


@dataclass(frozen=True)
class Estimates:
    """Poses of every row of a segment set; rows that are misses hold NaN."""

    R: np.ndarray  # (M, 3, 3)
    t: np.ndarray  # (M, 3) metres

    @classmethod
    def kept(cls, candidates: list[Estimates], pick: np.ndarray) -> Estimates:
        """Per row, the pose of ``candidates[pick[row]]`` (several estimates of the same rows,
        :func:`select_refinements`)."""
        return cls(
            _per_row([c.R for c in candidates], pick), _per_row([c.t for c in candidates], pick)
        )


def _per_row(candidates: list[np.ndarray], pick: np.ndarray) -> np.ndarray:
    """Row ``i`` of ``candidates[pick[i]]``, for arrays of the same rows."""
    return np.stack(candidates)[pick, np.arange(len(pick))]


def refine_poses(
    segs,
    est: Estimates,
    models_by_class: dict[int, np.ndarray],
    settings: ICPSettings | None = None,
    progress: bool = False,
    views=None,
) -> tuple[Estimates, ICPStats]:
    """ICP-refine every valid row; returns the refined poses and, per row, Open3D's fitness and
    inlier RMSE and whether the guard kept the estimate (``settings.fallback``; NaN / False
    for rows that are misses).

    The observed cloud is the segment's cached FPS points without the fill-by-repeat copies
    (``points[:count]``). ``views``: per row, the frame's depth
    (:func:`cloudpose.refine.segment_views`), which ``settings.select == "depth"`` needs.
    """
    settings = settings or ICPSettings()
    R, t = est.R.copy(), est.t.copy()
    fitness = np.full(len(segs), np.nan)
    rmse = np.full(len(segs), np.nan)
    kept = np.zeros(len(segs), dtype=bool)
    index = {c: ModelIndex.of(m) for c, m in models_by_class.items()}  # shared with ADS
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for i in tqdm(np.flatnonzero(segs.valid), disable=not progress, desc="ICP", unit="obj"):
            sol = icp_refine(
                segs.observed(i).astype(np.float64),
                index[int(segs.cls_id[i])],
                est.R[i],
                est.t[i],
                settings,
                view=views[i] if views is not None else None,
            )
            R[i], t[i], fitness[i], rmse[i], kept[i] = sol
    if caught:
        # One line instead of one per object: far-off estimates leave ICP nothing to match.
        warnings.warn(
            f"ICP kept the network's pose for {len(caught)} of {int(np.sum(segs.valid))} "
            f"objects (e.g. {caught[0].message})",
            stacklevel=2,
        )
    return Estimates(R, t), ICPStats(fitness, rmse, kept)


def refinement_scores(
    segs,
    refined: Estimates,
    stats: ICPStats,
    models_by_class: dict[int, np.ndarray],
    select: str,
    views=None,
) -> np.ndarray:
    """(M,) score of each row's refinement (:func:`refine_poses`) under ``select``: ICP's
    fitness (``"fitness"``) or the depth score (``"depth"``,
    :func:`cloudpose.refine.depth_score`: coverage of the segment and free-space violations
    against ``views``, the rows' depth); -inf for a row not refined (a miss)."""
    if select not in SELECTIONS:
        raise ValueError(f"select: expected one of {', '.join(SELECTIONS)}, got {select!r}")
    if select == "depth" and views is None:
        raise ValueError('select "depth" needs the rows\' depth views (segment_views)')
    score = np.full(len(segs), -np.inf)
    index = {c: ModelIndex.of(m) for c, m in models_by_class.items()}
    for i in np.flatnonzero(segs.valid):
        fit = float(stats.fitness[i])
        if not np.isfinite(fit):
            continue
        if select == "fitness":
            score[i] = fit
            continue
        agree = depth_agreement(
            segs.observed(i).astype(np.float64),
            index[int(segs.cls_id[i])],
            refined.R[i],
            refined.t[i],
            views[i],
        )
        score[i] = depth_score(fit, agree)
    return score


def select_refinements(
    segs,
    refined: list[Estimates],
    stats: list[ICPStats],
    models_by_class: dict[int, np.ndarray],
    select: str,
    views=None,
) -> np.ndarray:
    """Per row of ``segs``, which of several refinements of it to keep (an ensemble: each
    network's estimate refined by ICP, :func:`refine_poses`): the highest
    :func:`refinement_scores` under ``select``.

    Returns:
        (M,) int indices into ``refined``; the first on a tie and for a miss.
    """
    if len(refined) != len(stats) or not refined:
        raise ValueError(
            f"refined and stats: one of each per network, got {len(refined)} and {len(stats)}"
        )
    scores = [
        refinement_scores(segs, r, st, models_by_class, select, views)
        for r, st in zip(refined, stats, strict=True)
    ]
    return np.argmax(np.stack(scores), axis=0)


def refine_ensemble(
    segs,
    estimates: list[Estimates],
    models_by_class: dict[int, np.ndarray],
    settings: ICPSettings,
    views=None,
    progress: bool = False,
    choose: str | None = None,
) -> tuple[Estimates, ICPStats, np.ndarray]:
    """Several networks' estimates of the same rows as one: each refined by ICP
    (:func:`refine_poses` with ``settings``), per row the refinement with the best score of
    ``choose`` kept (default ``settings.select``, the score of the starts too;
    :func:`select_refinements`; one network: its own, unscored).

    Returns:
        The kept refinements, their ICP figures, and (M,) the index of the network each row
        kept (0 for a miss).
    """
    refined = [
        refine_poses(segs, e, models_by_class, settings, progress, views=views) for e in estimates
    ]
    if len(refined) == 1:
        return *refined[0], np.zeros(len(segs), dtype=np.int64)
    poses, stats = [r for r, _ in refined], [st for _, st in refined]
    pick = select_refinements(segs, poses, stats, models_by_class, choose or settings.select, views)
    kept_stats = ICPStats(*(_per_row(list(field), pick) for field in zip(*stats, strict=True)))
    return Estimates.kept(poses, pick), kept_stats, pick
