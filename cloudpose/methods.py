"""What estimates a pose, and the one scorer of every estimate.

Every study (``cloudpose evaluate``, ``compare``, ``stress``, ``showcase``, the baseline runs)
is a loop over methods x conditions x refinements on top of this module. A *method*
(:class:`Method`) takes a set of segments and gives its poses of them (:class:`Estimated`);
:func:`score` refines those poses by one ICP (:class:`~cloudpose.refine.ICPSettings`) and
scores them into one instance table (:func:`instance_table`). "Where do I add a method?":
here, as a class with an ``estimate(segs)``; every study then runs it.

The kinds:

- :class:`Network`: a trained network, or several as an ensemble (each network's estimate is
  refined and, per object, the refinement of the best score kept), each loaded by
  :func:`load_network` (an MLflow run, a run folder or the shipped network) into a
  :class:`LoadedNetwork`.
- :class:`Baseline`: a classical registration of ``baselines.toml`` (FPFH + RANSAC,
  point-pair features); a segment it cannot register is a miss. Its estimates can be kept as
  they are computed (:class:`EstimateProgress`), so a stopped call resumes.
- :class:`NoEstimate`: the control, the identity rotation at the segment's mean (what ICP
  starts from when nothing estimated the pose).
- :func:`combine`: several methods' estimates as one; per object the refinement that agrees
  best with the depth is kept.

An instance table's summaries, as the metrics an evaluation logs under its name
(:mod:`cloudpose.store.metric_names`): :func:`summary_metrics` (pooled, class mean, per class)
and :func:`video_metrics` (per video).
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import pandas as pd
import torch
from tqdm.auto import tqdm

from cloudpose import baselines, infer  # by module: the tests replace their functions
from cloudpose.baselines.base import BaselineSettings, NotRegistered, not_poses
from cloudpose.config import Config
from cloudpose.failures import sigterm_as_interrupt
from cloudpose.files import CorruptFileError, atomic_write, read_npz
from cloudpose.geometry.symmetry import rotation_errors_modulo_symmetry
from cloudpose.metrics import flatten_summary, pose_errors, summarize
from cloudpose.refine import Estimates, ICPSettings, refine_ensemble, segment_views
from cloudpose.store import runs
from cloudpose.store.metric_names import ERROR_COLUMNS, METHODS, method_prefixes
from cloudpose.store.pretrained import shipped
from cloudpose.store.runs import local_checkpoint
from cloudpose.store.tracking import metric_key

NETWORK = "network"
BASELINE_LABELS = {"fpfh": "FPFH + RANSAC", "ppf": "point-pair features"}
CONTROL = "none"
"""The control beside the methods: no estimate, the identity rotation at the segment's mean,
refined alike (what a refinement finds on its own; a wide one from many starts is a search of
its own)."""
COMBINED = "+"
"""Joins the methods of a combination (``network+fpfh``)."""

SECONDS_PER_INSTANCE = {"segment": 0.05, "net": 0.03, "fpfh": 0.6, "ppf": 3.5}
"""Planning figures per instance on one busy core, until a result file measured them."""
SECONDS_PER_MODEL = {"fpfh": 0.03, "ppf": 25.0}
"""Planning figures of a baseline's one-off preparation per model on one busy core: FPFH's
model features, point-pair features' detector training (its hash table of model point pairs;
422-602 s for the 21 models, logged as ``prepare_s`` of the baseline runs)."""
SAVE_EVERY_S = 1.0
"""Seconds between two saves of a baseline's estimates: what a ``kill -9`` can lose at most (an
interrupt saves them all)."""


# --------------------------------------------------------------------------- what a method gives


@dataclass(frozen=True)
class Estimated:
    """A method's poses of every segment of a set.

    Attributes:
        name: :data:`NETWORK`, a baseline (``fpfh``, ``ppf``), the control (:data:`CONTROL`) or
            a combination (``network+fpfh``).
        label: in words.
        estimates: one :class:`~cloudpose.refine.Estimates` per network of an ensemble or per
            estimate of a combination, else one; empty where a study read every result from
            its files instead.
        ok: per segment, whether the method gave a pose (a baseline's unregistered segment:
            False, a miss).
        ms_per_object: milliseconds of the estimate per valid segment.
        prepare_seconds: a one-off preparation of the models (point-pair features' hash
            tables), kept off ``ms_per_object``.
        parts: a combination's methods (:func:`combine`); empty for one method.
    """

    name: str
    label: str
    estimates: tuple[Estimates, ...]
    ok: np.ndarray
    ms_per_object: float
    prepare_seconds: float = 0.0
    parts: tuple[str, ...] = ()


class Method(Protocol):
    """Anything that estimates the poses of a set of segments."""

    name: str
    label: str

    def estimate(self, segs) -> Estimated:
        """Its poses of every segment of ``segs`` (a
        :class:`~cloudpose.data.segment_set.SegmentSet`); a row it gives no pose is not ``ok``."""
        ...


def _ms(seconds: float, segs) -> float:
    return 1000 * seconds / max(int(np.sum(segs.valid)), 1)


# --------------------------------------------------------------------------- networks


@dataclass(frozen=True)
class LoadedNetwork:
    """A network ready to estimate, and what it is.

    Attributes:
        name: as the user named it (a run name, id or folder, ``pretrained``, a checkpoint).
        run_id: its MLflow run id; None for the shipped network or a bare checkpoint.
        model: the network, folded for inference (:func:`cloudpose.infer.load_checkpoint`).
        config: its run's config.
        checkpoint: the checkpoint read, in words.
    """

    name: str
    run_id: str | None
    model: torch.nn.Module
    config: Config
    checkpoint: str

    @classmethod
    def from_checkpoint(cls, path: str | Path, device: str = "cpu") -> LoadedNetwork:
        """The network of a ``model.pt`` / ``last.pt`` file, with no run behind it."""
        model, cfg = infer.load_checkpoint(path, device)
        return cls(str(path), None, model, cfg, str(path))

    @property
    def device(self) -> torch.device:
        return next(self.model.buffers()).device


def load_network(client, run: str, device: str) -> LoadedNetwork:
    """The network of ``run`` (:func:`cloudpose.store.runs.local_checkpoint`); a checkpoint
    downloaded from the run's artifacts is read and removed with its folder."""
    with local_checkpoint(client, run) as (run_id, ckpt):
        try:
            model, cfg = infer.load_checkpoint(ckpt, device)
        except ValueError as exc:
            if not runs.is_run_folder(ckpt.parent):
                raise
            raise ValueError(
                f"{exc}; rerun the run's train command (cloudpose train with its variant, "
                "preset, seed and settings): it rewrites model.pt from last.pt or the MLflow run"
            ) from exc
        kept = run_id is None or runs.is_run_folder(ckpt.parent)  # shipped, or in its folder
        label = str(ckpt) if kept else "model.pt (downloaded)"
    return LoadedNetwork(run, run_id, model, cfg, label)


def check_member(cfg, other, run: str, option: str = "--ensemble") -> None:
    """``ValueError`` unless the network of ``run`` (config ``other``) can join an ensemble with
    the first network's (``cfg``): the same data section (the segments and classes it was
    trained and is tested on) and the same rotation modulo symmetry (its errors' table).
    ``option`` names the command-line option that gave ``run``, for the message."""
    mine, theirs = dataclasses.asdict(cfg.data), dataclasses.asdict(other.data)
    fields = [f"data.{k}" for k in mine if mine[k] != theirs.get(k)]
    if cfg.loss.symmetry_table != other.loss.symmetry_table:
        fields.append("loss.symmetry_table")
    if fields:
        raise ValueError(
            f"{option} {run}: its network differs from the first network's in "
            f"{', '.join(fields)}; an ensemble joins networks of the same preset (other seeds "
            "or variants)"
        )


def network_identity(net: LoadedNetwork) -> str:
    """The identity of a network: its MLflow run id, or for a shipped network (no run id) its
    run's id and 12 hex digits of its weights' checksum (one run can be shipped again, e.g. in
    half precision)."""
    if net.run_id is not None:
        return net.run_id
    info = shipped(net.name).info
    return f"{info['run_id']}:{info['sha256'][:12]}"


def check_ensemble(loaded: list[LoadedNetwork], option: str) -> list[str]:
    """The identities (:func:`network_identity`) of an ensemble's networks, the first the one
    the others join.

    Raises:
        ValueError: naming ``option`` and the run, for a network that cannot join the first
            (:func:`check_member`) or that is in the ensemble already: the same MLflow run,
            named again, by another name, or as the network the package ships from it.
    """
    ids = [network_identity(n) for n in loaded]
    run_ids = [i.split(":")[0] for i in ids]
    for k in range(1, len(loaded)):
        check_member(loaded[0].config, loaded[k].config, loaded[k].name, option)
        if run_ids[k] in run_ids[:k]:
            raise ValueError(
                f"{option} {loaded[k].name}: run {run_ids[k]} is in the ensemble already"
            )
    return ids


@dataclass(frozen=True)
class Network:
    """One network, or several as an ensemble (the first is the one evaluated)."""

    members: tuple[LoadedNetwork, ...]
    name: str = NETWORK

    @property
    def label(self) -> str:
        n = len(self.members)
        return self.name + (f" ({n} networks)" if n > 1 else "")

    def estimate(self, segs) -> Estimated:
        t0 = time.perf_counter()
        ests = tuple(
            infer.estimate_poses(n.model, segs, n.config.train.n_points, device=n.device)
            for n in self.members
        )
        seconds = time.perf_counter() - t0
        ok = np.ones(len(segs), dtype=bool)
        return Estimated(self.name, self.label, ests, ok, _ms(seconds, segs))


# --------------------------------------------------------------------------- baselines


class EstimateProgress:
    """Per-instance estimates of one baseline, saved atomically as they are computed (at
    ``path``; None: kept in memory only).

    ``done[i]`` says instance ``i`` was attempted; ``ok[i]`` that it was registered (then
    ``R[i]``, ``t[i]`` hold its pose); ``calls`` is the estimator's random-draw count, restored
    on resuming. A saved file that cannot serve (unreadable, lacking an array, of another
    instance count, or holding a registered pose that is no pose, :func:`not_poses`) is a cache:
    a one-line warning names it and its estimates are computed again.
    """

    FIELDS = ("R", "t", "done", "ok", "seconds", "calls")

    def __init__(self, path: Path | None, n: int) -> None:
        self.path = path
        self.R = np.tile(np.eye(3), (n, 1, 1))
        self.t = np.zeros((n, 3))
        self.done = np.zeros(n, dtype=bool)
        self.ok = np.zeros(n, dtype=bool)
        self.seconds = 0.0
        self.calls = 0
        self._saved_at = time.monotonic()
        if path is not None and path.is_file():
            saved = self._read(n)
            if saved is not None:
                self.R, self.t = saved["R"].astype(np.float64), saved["t"].astype(np.float64)
                self.done, self.ok = saved["done"].astype(bool), saved["ok"].astype(bool)
                self.seconds = float(saved["seconds"])
                self.calls = int(saved["calls"])

    def _read(self, n: int) -> dict[str, np.ndarray] | None:
        """The arrays of :attr:`path` if they can serve ``n`` instances, else None (warned)."""
        try:
            saved = read_npz(self.path, self.FIELDS, "a baseline's estimates")
            shapes = {"R": (n, 3, 3), "t": (n, 3), "done": (n,), "ok": (n,), "seconds": (),
                      "calls": ()}  # fmt: skip
            wrong = [f"{k} {saved[k].shape}, not {v}" for k, v in shapes.items()
                     if saved[k].shape != v]  # fmt: skip
            if wrong:
                raise CorruptFileError(
                    self.path, f"a baseline's estimates of other shapes ({'; '.join(wrong)})"
                )
            kept = np.flatnonzero(saved["done"].astype(bool) & saved["ok"].astype(bool))
            bad = kept[not_poses(saved["R"][kept], saved["t"][kept])]
            if len(bad):
                raise CorruptFileError(
                    self.path,
                    f"a baseline's estimates with {len(bad)} registered pose(s) that are no "
                    f"pose (instance {bad[0]}: a rotation that is not one, or a value not finite)",
                )
        except CorruptFileError as exc:
            warnings.warn(f"{exc}; its estimates are computed again", stacklevel=3)
            return None
        return saved

    def save(self, force: bool = False) -> None:
        """Write the estimates (atomically), unless ``force`` is False and they were written
        less than :data:`SAVE_EVERY_S` ago, or they are kept in memory only."""
        if self.path is None or (not force and time.monotonic() - self._saved_at < SAVE_EVERY_S):
            return
        arrays = dict(
            R=self.R, t=self.t, done=self.done, ok=self.ok, seconds=self.seconds, calls=self.calls
        )
        atomic_write(self.path, lambda tmp: np.savez(tmp, **arrays), suffix=".npz")
        self._saved_at = time.monotonic()

    def remove(self) -> None:
        if self.path is not None:
            self.path.unlink(missing_ok=True)


def estimate_all(
    estimator, models: dict, segs, state: EstimateProgress, method: str, progress: bool
) -> float:
    """Run ``estimator`` on every valid segment that ``state`` has not done yet, saving as it
    goes; an interrupt (Ctrl-C, or SIGTERM, taken as one) or an error saves every estimate
    made before it, says where, and is raised again, so that the same call resumes. Returns
    the seconds spent preparing the estimator's per-model state (PPF's detector training,
    shown as a bar of its own; kept off each segment's clock: a one-off cost per run, logged
    as ``prepare_s``)."""
    todo = np.flatnonzero(np.asarray(segs.valid, dtype=bool))
    left = todo[~state.done[todo]]
    if len(left) < len(todo):
        print(f"{method}: resuming from {state.path} ({len(todo) - len(left)} of {len(todo)} done)")
    classes = sorted(set(np.asarray(segs.cls_id)[left].tolist()) & set(models))
    with sigterm_as_interrupt():
        t0 = time.perf_counter()
        shown = progress and bool(classes)
        for c in tqdm(classes, disable=not shown, desc=f"{method} models", unit="model"):
            estimator.prepare([c])
        prepare_s = time.perf_counter() - t0
        bar = tqdm(
            left,
            initial=len(todo) - len(left),
            total=len(todo),
            disable=not progress,
            desc=method,
            unit="obj",
        )
        try:
            for i in bar:
                t0 = time.perf_counter()
                try:
                    pose = estimator.estimate(segs.observed(i), int(segs.cls_id[i]))
                except NotRegistered:
                    pose = None
                state.seconds += time.perf_counter() - t0
                if pose is not None:
                    state.R[i], state.t[i] = pose.R, pose.t
                state.ok[i] = pose is not None
                state.done[i] = True
                state.calls = estimator.calls  # the draws of the estimates done, not of one cut
                state.save()
        except BaseException as exc:
            state.save(force=True)
            if isinstance(exc, KeyboardInterrupt) and state.path is not None:
                done = int(state.done[todo].sum())
                print(
                    f"{method}: stopped at {done} of {len(todo)} estimates, kept in "
                    f"{state.path}; the same call resumes from them",
                    flush=True,
                )
            raise
        state.save(force=True)
    return prepare_s


@dataclass
class Baseline:
    """A classical registration of ``baselines.toml`` (:func:`cloudpose.baselines.make`).

    Attributes:
        name: the method (``fpfh``, ``ppf``).
        models: the models by class (``dataset.models()``).
        seed: RANSAC's and the detectors' random seed.
        settings: the method's settings (default ``baselines.toml``'s).
        progress: show progress bars.

    Its per-model state (features, PPF's hash tables) is built once and serves every
    :meth:`estimate`; each call's random draws start afresh (or from ``state``), so a set's
    poses do not depend on which sets this method estimated before.
    """

    name: str
    models: dict
    seed: int = 1
    settings: BaselineSettings | None = None
    progress: bool = False
    _estimator: Any = field(default=None, init=False, repr=False)

    @property
    def label(self) -> str:
        return BASELINE_LABELS.get(self.name, self.name)

    def estimate(self, segs, state: EstimateProgress | None = None) -> Estimated:
        """Its poses of ``segs``, resumed from ``state`` where given (and saved there as they
        are computed; :class:`EstimateProgress`)."""
        state = state if state is not None else EstimateProgress(None, len(segs))
        valid = np.asarray(segs.valid, dtype=bool)
        prepare_s = 0.0
        if not state.done[valid].all():
            if self._estimator is None:
                settings = self.settings or baselines.load_settings(self.name)
                self._estimator = baselines.make(self.name, self.models, settings, seed=self.seed)
            self._estimator.calls = state.calls
            prepare_s = estimate_all(
                self._estimator, self.models, segs, state, self.name, self.progress
            )
        return Estimated(
            self.name,
            self.label,
            (Estimates(state.R, state.t),),
            state.ok.copy(),
            1000 * state.seconds / max(int(valid.sum()), 1),
            prepare_s,
        )


# --------------------------------------------------------------------------- the control


def no_estimate(segs) -> Estimates:
    """The control of any method: the identity rotation at the mean of each segment's
    observed points (what ICP starts from when nothing estimated the pose)."""
    n = len(segs)
    t = np.zeros((n, 3))
    for i in np.flatnonzero(segs.valid):
        t[i] = segs.observed(i).mean(axis=0)
    return Estimates(np.tile(np.eye(3), (n, 1, 1)), t)


@dataclass(frozen=True)
class NoEstimate:
    """The control (:data:`CONTROL`, :func:`no_estimate`)."""

    name: str = CONTROL
    label: str = "no estimate"

    def estimate(self, segs) -> Estimated:
        ok = np.ones(len(segs), dtype=bool)
        return Estimated(self.name, self.label, (no_estimate(segs),), ok, 0.0)


def combine(parts: tuple[str, ...], members: list[Estimated]) -> Estimated:
    """The combination of ``members`` (the estimates of ``parts``): every estimate of each, a
    member's miss filled with another member's estimate of that segment (a miss only where
    every member misses); its time, theirs together. :func:`score` keeps, per object, the
    refinement that agrees best with the depth."""
    ok = np.logical_or.reduce([c.ok for c in members])
    estimates = []
    for c in members:
        for e in c.estimates:
            R, t, left = e.R.copy(), e.t.copy(), ~c.ok
            for other in members:
                fill = left & other.ok
                R[fill], t[fill] = other.estimates[0].R[fill], other.estimates[0].t[fill]
                left &= ~fill
            estimates.append(Estimates(R, t))
    ms = sum(c.ms_per_object for c in members)
    label = combined_label(members)
    return Estimated(COMBINED.join(parts), label, tuple(estimates), ok, ms, parts=parts)


def combined_label(members: list[Estimated]) -> str:
    return " or ".join(c.label for c in members) + ", by the depth"


# --------------------------------------------------------------------------- the scorer


def instance_table(
    segs,
    estimates: dict[str, Estimates],
    models_by_class: dict[int, np.ndarray],
    class_names: list[str],
    symmetry_table: int = 1,
) -> pd.DataFrame:
    """Per-instance errors for each stage in ``estimates`` (``net``, ``icp``); rotation errors
    modulo symmetry by table ``symmetry_table`` (``loss.symmetry_table``)."""
    miss = ~np.asarray(segs.valid, dtype=bool)
    df = pd.DataFrame(
        {
            "frame_id": segs.frame_id,
            "instance": segs.instance,
            "cls_id": segs.cls_id.astype(int),
            "class": [class_names[int(c) - 1] for c in segs.cls_id],
            "occlusion": segs.occlusion,
            "points": segs.count,
            "miss": miss,
        }
    )
    for method, est in estimates.items():
        R_est = np.where(miss[:, None, None], np.eye(3), est.R)
        t_est = np.where(miss[:, None], 0.0, est.t)
        err = pose_errors(
            models_by_class,
            segs.cls_id.astype(int),
            R_est=R_est,
            t_est=t_est,
            R_gt=segs.R.astype(np.float64),
            t_gt=segs.t.astype(np.float64),
            miss=miss,
        )
        for key in ("ad", "ads", "rot_err_deg", "trans_err"):
            df[f"{method}_{key}"] = err[key]
        # the pose itself (for the BOP results CSV): R row-major, t in metres; "" for a miss
        df[f"{method}_R"] = _number_lists(est.R.reshape(-1, 9), miss)
        df[f"{method}_t"] = _number_lists(est.t, miss)
        df[f"{method}_rot_sym_err_deg"] = rotation_errors_modulo_symmetry(
            segs.cls_id, segs.R, R_est, class_names, miss, table=symmetry_table
        )
    return df


def _number_lists(rows: np.ndarray, miss: np.ndarray) -> list[str]:
    """Each row of (M, k) numbers as one space-separated string (17 significant digits, so
    float64 survives the CSV); "" where ``miss``."""
    return ["" if m else " ".join(f"{v:.17g}" for v in r) for r, m in zip(rows, miss, strict=True)]


@dataclass(frozen=True)
class Scored:
    """A method's estimate scored (:func:`score`).

    Attributes:
        table: the instance table: ``net_*`` the estimate (an ensemble's or a combination's:
            the one whose refinement was kept), ``icp_*`` the refined pose with ICP's
            ``icp_fitness``, ``icp_inlier_rmse``, ``icp_fallback``, and for several estimates
            ``ensemble_member`` (the index kept, -1 for a miss).
        refine_ms: milliseconds of the refinement per valid segment (0 without one).
        pick: per segment, the index of the estimate kept (0 for a miss or one estimate).
        poses: the poses scored, by stage (``net``, and ``icp`` after a refinement).
    """

    table: pd.DataFrame
    refine_ms: float
    pick: np.ndarray
    poses: dict[str, Estimates]


def score(
    segs,
    estimated: Estimated,
    dataset,
    refinement: ICPSettings | None,
    *,
    symmetry_table: int = 1,
    models: dict | None = None,
    views=None,
    progress: bool = False,
    quiet: bool = False,
) -> Scored:
    """Refine ``estimated``'s poses of ``segs`` by ``refinement`` (None: no refinement) and
    score them against ``dataset``'s models (``models``: ``dataset.models()`` where given).

    A segment the method gave no pose (``estimated.ok`` False) is a miss. Several estimates (an
    ensemble's networks) are each refined and, per segment, the refinement of the best
    ``refinement.select`` score kept; a combination's (``estimated.parts``), the one that agrees
    best with the depth (:func:`cloudpose.refine.refine_ensemble`). ``views``: the segments'
    depth (:func:`cloudpose.refine.segment_views`), read here where a depth score needs it.
    ``quiet``: no warning of ICP's (a degenerate segment's pose is scored all the same).
    """
    models = dataset.models() if models is None else models
    segs = segs.subset(np.arange(len(segs)))
    segs.valid = np.asarray(segs.valid, dtype=bool) & np.asarray(estimated.ok, dtype=bool)
    ests = list(estimated.estimates)
    pick = np.zeros(len(segs), dtype=np.int64)
    if refinement is None:
        est = {"net": ests[0]}
        table = instance_table(segs, est, models, dataset.classes, symmetry_table)
        return Scored(table, 0.0, pick, est)
    choose = "depth" if estimated.parts else None
    t0 = time.perf_counter()
    if views is None and "depth" in (refinement.select, choose):
        views = segment_views(dataset, segs)
    with warnings.catch_warnings():
        if quiet:
            warnings.simplefilter("ignore")
        icp, stats, pick = refine_ensemble(segs, ests, models, refinement, views, progress, choose)
    ms = _ms(time.perf_counter() - t0, segs)
    est = {"net": Estimates.kept(ests, pick), "icp": icp}
    table = instance_table(segs, est, models, dataset.classes, symmetry_table)
    table["icp_fitness"] = stats.fitness
    table["icp_inlier_rmse"] = stats.inlier_rmse
    table["icp_fallback"] = stats.fallback
    if len(ests) > 1:
        table["ensemble_member"] = np.where(segs.valid, pick, -1)
    return Scored(table, ms, pick, est)


# -- an instance table as MLflow metrics ------------------------------------------------------


def _by_method(df: pd.DataFrame, name: str) -> Iterator[tuple[str, pd.DataFrame]]:
    """``(metric prefix, table with the method's error columns unprefixed)`` per method."""
    prefixes = method_prefixes(name)
    for method in METHODS:
        if f"{method}_ads" not in df:
            continue
        yield prefixes[method], df.rename(columns={f"{method}_{k}": k for k in ERROR_COLUMNS})


def summary_metrics(df: pd.DataFrame, name: str) -> dict[str, float]:
    """MLflow metrics of a per-instance table: pooled, class-mean and per-class, per method."""
    out: dict[str, float] = {}
    for prefix, sub in _by_method(df, name):
        for key, value in flatten_summary(summarize(sub)).items():
            out[metric_key(prefix, key)] = float(value)
    return out


def video_metrics(df: pd.DataFrame, name: str) -> dict[str, float]:
    """Pooled metrics of each video (the ``SEQ`` of ``SEQ/FRAME``), per method, as
    ``{name}/video/{SEQ}/{key}``: consecutive frames of a video show one scene, so a set of a
    few videos is a few scenes and is read per video as well as pooled."""
    out: dict[str, float] = {}
    video = df["frame_id"].astype(str).str.split("/").str[0]
    for prefix, sub in _by_method(df, name):
        for seq, part in sub.groupby(video.to_numpy()):
            for key, value in summarize(part, by_class=False)["pooled"].items():
                out[metric_key(prefix, f"video/{seq}/{key}")] = float(value)
    return out
