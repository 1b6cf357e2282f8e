"""Like for like on one set of frames (``cloudpose compare``): the network and the classical
registrations on the same segments, every estimate refined by the same ICP.

A user with real frames (their own YCB-Video test videos, a BOP ycbv folder; by default the 61
packaged development frames) asks one question: on these frames, how does the network compare with
FPFH + RANSAC and point-pair features? Answering it by hand takes an evaluation, two baseline runs
and their refinements, and a table put together from their logs, where a mismatch (another frame
list, another refinement for one method) goes unseen. Here every method estimates the pose of the
same segments once, and each estimate is refined by each of the same ICP schedules
(:func:`refinements`: the paper's, and the recipe ``--refine`` names); the report puts the results
side by side, pooled, per video and per object pose, with the network's difference to each method
paired over the object poses (an object stands still in a video while the camera moves, so its
instances are one pose seen many times; :func:`cloudpose.report.real.versus_baseline`).

Nothing is logged to MLflow. The output folder holds ``compare.json`` (what was compared: data
key, frames, the networks' MLflow run ids, the baselines' seed), ``estimates/network.npz`` (the
networks' poses), ``tables/METHOD-REFINEMENT.csv`` (the instance tables of
:func:`cloudpose.methods.instance_table`, with the translation error split along and across
the viewing ray), and the report ``compare.md`` with its figure ``compare.png``; a folder
holding another comparison is refused, never mixed. The classical methods' estimates, which do
not depend on the networks, are kept for every comparison of the project on the same segments
(:func:`baseline_estimates_path`), saved as they are computed and on Ctrl-C or SIGTERM (which
stops a call as Ctrl-C does): an interrupted call resumes, and a comparison of other networks
on the same frames reuses them. What a folder keeps is checked before it is used: a cached
estimate that is unreadable, lacks an array or is no pose (an all-zero rotation), and a table
that lacks a column, lists other instances or is not the file written (its checksum, kept in
``tables/icp_ms.json``), are each named in a one-line warning and computed again.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from cloudpose import baselines, refine, runtime  # by module: the tests replace their functions
from cloudpose.baselines.base import not_poses, settings_fingerprint
from cloudpose.data.dataset import folder_segments
from cloudpose.data.layout import describe_split, open_dataset, real_dev_root
from cloudpose.evaluate import icp_label
from cloudpose.failures import sigterm_as_interrupt
from cloudpose.files import CorruptFileError, atomic_text, atomic_write, read_json, read_npz, why
from cloudpose.methods import (
    BASELINE_LABELS,
    COMBINED,
    CONTROL,
    NETWORK,
    SECONDS_PER_INSTANCE,
    SECONDS_PER_MODEL,
    Baseline,
    Estimated,
    EstimateProgress,
    Network,
    NoEstimate,
    check_ensemble,
    combine,
    combined_label,
    load_network,
    no_estimate,
    score,
)
from cloudpose.metrics import stage_summary
from cloudpose.refine import Estimates, ICPSettings, schedule_for
from cloudpose.store.metric_names import data_evaluation_name
from cloudpose.store.pretrained import PRETRAINED, shipped
from cloudpose.store.runs import client_for

BASELINES = BASELINE_LABELS
STAGE_ESTIMATE = "estimate"
"""The stage of a method's own estimate, before any refinement, in the pooled rows."""
METHODS = {**BASELINES, CONTROL: NoEstimate.label}
RECIPE = {"starts": 24, "select": "depth", "radius": 0.18}
"""The refinement compared beside the paper's by default: 24 starts kept by their agreement with
the depth, from an 18 cm first radius (docs/ensemble.md, "A wider first radius")."""
MACHINE = "machines"
"""The key of ``tables/icp_ms.json`` listing the CPUs the folder's refinements were timed on."""
CHECKSUMS = "sha256"
"""The key of ``tables/icp_ms.json`` holding each table's SHA-256 as written (table name ->
hex digest): a table changed since is computed again."""
PREPARATION = {"ppf": "training {n} detector(s) first"}
"""A method's one-off stage per model, in the plan's words, where it takes time of its own
(point-pair features' hash tables; FPFH's model features take milliseconds)."""


@dataclass(frozen=True)
class Refinement:
    """One ICP every method's estimate goes through.

    Attributes:
        name: its file name part: ``icp`` (the paper's) or ``icp-starts24-selectdepth-radius180mm``.
        label: in words, for the report.
        settings: the ICP (:class:`cloudpose.refine.ICPSettings`).
    """

    name: str
    label: str
    settings: object


def refinements(starts: int, select: str, radius: float, networks: int = 1) -> list[Refinement]:
    """The paper's ICP (one start, ICP's fitness, 1 cm first radius), and the one of ``starts``,
    ``select``, ``radius`` unless it is the paper's (:func:`cloudpose.refine.schedule_for`).
    With one start and one network (``networks``) there is nothing to select among, so
    ``select`` is the paper's whatever it says."""
    paper = ICPSettings()
    if starts == 1 and networks == 1:
        select = paper.select
    out = [Refinement("icp", "+ ICP (paper)", paper)]
    other = ICPSettings(starts=starts, select=select, **schedule_for(radius))
    if other != paper:
        words = [f"{starts} start{'s' if starts > 1 else ''}", f"by {select}"]
        words.append(f"{100 * radius:g} cm")
        label = f"+ ICP ({', '.join(words)})"
        out.append(Refinement(f"icp-{icp_label(other, paper)}", label, other))
    return out


@dataclass(frozen=True)
class MethodComparison:
    """A finished comparison (:func:`cloudpose.report.compare.render` writes its report).

    Attributes:
        out_dir: its folder.
        tables: the instance tables per (method, refinement name).
        contenders: the methods, the network first.
        refinements: the ICPs, the paper's first.
        timing: milliseconds per object of each method's estimate (``METHOD-estimate``) and of
            each refinement (``METHOD-REFINEMENT``), the CPU they were timed on
            (:data:`MACHINE`) and each table's checksum (:data:`CHECKSUMS`).
        described: the data in words.
        source: the networks in words.
    """

    out_dir: Path
    tables: dict[tuple[str, str], pd.DataFrame]
    contenders: list[Estimated]
    refinements: list[Refinement]
    timing: dict
    described: str
    source: str


def ray_split(t_est: np.ndarray, t_gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The translation error ``t_est - t_gt`` (N, 3) split into its length along the viewing ray
    through the true centre (the camera at the origin) and across it, metres (N,) each: depth
    scale against a centre that moves sideways."""
    err = np.asarray(t_est, float) - np.asarray(t_gt, float)
    ray = np.asarray(t_gt, float) / np.linalg.norm(t_gt, axis=1, keepdims=True)
    along = np.sum(err * ray, axis=1)
    across = np.linalg.norm(err - along[:, None] * ray, axis=1)
    return np.abs(along), across


def _manifest(path: Path, wanted: dict) -> None:
    """Write ``wanted`` as the folder's ``compare.json``, or refuse a folder that holds a
    comparison of other data, frames, networks or seed (naming the field), or a classical
    method's results with other settings (``wanted["settings"]``: method -> settings
    fingerprint); methods may be added to a folder (each has its own files)."""
    fix = f"give another --out or remove {path.parent}"
    have: dict = {}
    if path.is_file():
        have = read_json(path, "a comparison's record", fix)
        if not isinstance(have, dict):
            raise ValueError(f"{path}: not a comparison's record (a JSON object); {fix}")
        for key, value in wanted.items():
            if key == "settings":
                continue
            if have.get(key) != value:
                raise ValueError(
                    f"{path.parent} holds a comparison of another {key} ({have.get(key)!r}, "
                    f"this call {value!r}); {fix}"
                )
        for method, fp in wanted.get("settings", {}).items():
            old = have.get("settings", {}).get(method, fp)
            if old != fp:
                raise ValueError(
                    f"{path.parent} holds {method}'s results with other settings (fingerprint "
                    f"{old}, baselines.toml now {fp}); {fix}"
                )
    settings = {**have.get("settings", {}), **wanted.get("settings", {})}
    record = {**have, **wanted, "settings": settings}
    if record != have:
        atomic_text(path, json.dumps(record, indent=2) + "\n")


_ERRORS = ("ad", "ads", "rot_err_deg", "rot_sym_err_deg", "trans_err", "trans_along",
           "trans_across")  # fmt: skip
TABLE_COLUMNS = (
    "frame_id", "instance", "cls_id", "class", "miss",
    *(f"{stage}_{k}" for stage in ("net", "icp") for k in _ERRORS),
)  # fmt: skip
"""The columns of an instance table that the report reads (:func:`_refine` writes them)."""


def table_problem(table: pd.DataFrame, segs=None) -> str | None:
    """What makes ``table`` no instance table of the comparison, in words (the columns of
    :data:`TABLE_COLUMNS` it lacks; with ``segs``, rows that are not the segments'), or None."""
    missing = [c for c in TABLE_COLUMNS if c not in table.columns]
    if missing:
        return f"lacks column(s) {', '.join(missing)}"
    if segs is not None:
        rows = list(zip(table["frame_id"].astype(str), table["instance"].astype(int), strict=True))
        want = list(zip(np.asarray(segs.frame_id).astype(str), np.asarray(segs.instance).astype(int),
                        strict=True))  # fmt: skip
        if rows != want:
            return f"lists {len(rows)} instances that are not the {len(want)} segments compared"
    return None


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _checksums(timing: dict) -> dict:
    """The tables' recorded checksums (:data:`CHECKSUMS`); none where the record is not a
    mapping."""
    sums = timing.get(CHECKSUMS)
    return sums if isinstance(sums, dict) else {}


def _kept_table(out_dir: Path, method: str, ref: Refinement, timing: dict, segs):
    """``out_dir``'s table of ``method`` after ``ref`` if it was written whole (its timing is
    recorded after the table), is an instance table of ``segs`` (:func:`table_problem`) and is
    the file written (its checksum in :data:`CHECKSUMS`, where recorded), else None: a table
    that fails is warned of, naming the file and why, and computed again."""
    key = f"{method}-{ref.name}"
    path = out_dir / "tables" / f"{key}.csv"
    if not (path.is_file() and key in timing and f"{method}-estimate" in timing):
        return None
    try:
        table = pd.read_csv(path, dtype={"frame_id": str})
        problem = table_problem(table, segs)
    except (ValueError, OSError, KeyError) as exc:  # empty, garbled, not UTF-8
        problem = f"is not a readable table ({why(exc)})"
    recorded = _checksums(timing).get(key)
    if problem is None and recorded is not None and recorded != _sha256(path):
        problem = "is not the table this comparison wrote (its checksum differs: edited since?)"
    if problem is not None:
        warnings.warn(f"{path}: {problem}; computed again", stacklevel=2)
        return None
    return table


def _timings(path: Path) -> dict:
    """The milliseconds already measured in a comparison's folder (``tables/icp_ms.json``);
    empty, with a warning, where the file is unreadable: every table is then computed again."""
    if not path.is_file():
        return {}
    try:
        return read_json(path, "a comparison's timings", "its tables are computed again")
    except CorruptFileError as exc:
        print(f"warning: {exc}", flush=True)
        return {}


def _network(segs, network: Network, path: Path) -> Estimated:
    """``network`` (:class:`cloudpose.methods.Network`; more than one an ensemble) on
    ``segs``; its estimates cached at ``path`` (:func:`_cached_network`)."""
    cached = _cached_network(path, len(network.members), segs) if path.is_file() else None
    if cached is not None:
        ests = tuple(Estimates(R, t) for R, t in zip(cached["R"], cached["t"], strict=True))
        ok = np.ones(len(segs), dtype=bool)
        return Estimated(NETWORK, network.label, ests, ok, float(cached["ms"]))
    done = network.estimate(segs)
    arrays = {"R": np.stack([e.R for e in done.estimates]),
              "t": np.stack([e.t for e in done.estimates]), "ms": done.ms_per_object}  # fmt: skip
    atomic_write(path, lambda tmp: np.savez(tmp, **arrays), suffix=".npz")
    return done


def _cached_network(path: Path, networks: int, segs) -> dict[str, np.ndarray] | None:
    """The arrays ``R`` (K, M, 3, 3), ``t`` (K, M, 3) and ``ms`` of the networks' estimates
    cached at ``path`` for ``networks`` networks (K) on ``segs`` (M), or None: a cache of
    another ensemble or segments is computed again, and so, with a one-line warning naming it,
    is one that is unreadable, lacks an array, or holds a valid segment's estimate that is no
    pose (:func:`cloudpose.baselines.base.not_poses`: an all-zero rotation)."""
    try:
        f = read_npz(path, ("R", "t", "ms"), "the networks' estimates")
        if f["R"].shape[:2] != (networks, len(segs)):
            return None
        shapes = (f["R"].shape, f["t"].shape, f["ms"].shape)
        if shapes != ((networks, len(segs), 3, 3), (networks, len(segs), 3), ()):
            raise CorruptFileError(path, f"the networks' estimates of other shapes {shapes}")
        valid = np.flatnonzero(np.asarray(segs.valid, dtype=bool))
        each = zip(f["R"], f["t"], strict=True)  # per network
        bad = sum(int(np.sum(not_poses(R[valid], t[valid]))) for R, t in each)
        if bad:
            raise CorruptFileError(
                path,
                f"the networks' estimates hold {bad} that are no pose (a rotation that is not "
                "one, or a value not finite)",
            )
    except CorruptFileError as exc:
        warnings.warn(f"{exc}; computed again", stacklevel=3)
        return None
    return f


def baseline_estimates_path(project_dir: Path, method: str, seed: int, data_key: str) -> Path:
    """Where a baseline's estimates of one set of segments are kept, for every comparison of the
    project on them: they depend on the segments (``data_key``), the method's settings
    (``baselines.toml``, by fingerprint) and the seed, not on the networks beside them."""
    fp = settings_fingerprint(baselines.load_settings(method))
    return (
        project_dir / "runs" / "compare" / "estimates" / f"{method}-{fp}-seed{seed}-{data_key}.npz"
    )


def combination(text: str, names: list[str]) -> tuple[str, ...]:
    """The methods of ``--combine`` ``text`` (``network+fpfh``), in the order of ``names`` (the
    network and the methods of the call); ``ValueError`` naming the option unless it names two
    or more of them, each once."""
    parts = text.split(COMBINED)
    if len(parts) < 2 or len(set(parts)) < len(parts) or not set(parts) <= set(names):
        raise ValueError(
            f"--combine {text!r}: expected two or more of {', '.join(names)} joined by "
            f"{COMBINED!r}, each once (a method also given by --method)"
        )
    return tuple(n for n in names if n in parts)


def _from_tables(
    first: pd.DataFrame, name: str, label: str, timing: dict, parts: tuple[str, ...] = ()
) -> Estimated:
    """A method whose every table is kept: no estimates, its misses (and empty segments) read
    from its ``first`` table, its time from ``timing``."""
    ok = ~first["miss"].to_numpy(dtype=bool)
    return Estimated(name, label, (), ok, timing[f"{name}-estimate"], parts=parts)


def _refine(
    contender: Estimated,
    segs,
    dataset,
    models: dict,
    refinement: Refinement,
    symmetry_table: int,
    progress: bool = False,
):
    """``(instance table, ICP milliseconds per object)`` of ``contender`` after ``refinement``
    (:func:`cloudpose.methods.score`) against ``models`` (``dataset.models()``), with the
    translation error split along and across the viewing ray (``*_trans_along`` /
    ``*_trans_across``, :func:`ray_split`)."""
    scored = score(
        segs, contender, dataset, refinement.settings,
        symmetry_table=symmetry_table, models=models, progress=progress, quiet=True,
    )  # fmt: skip
    table = scored.table
    t_gt = np.asarray(segs.t, float)
    miss = table["miss"].to_numpy(dtype=bool)
    for stage, e in scored.poses.items():
        along, across = ray_split(np.nan_to_num(e.t), t_gt)
        table[f"{stage}_trans_along"] = np.where(miss, np.inf, along)
        table[f"{stage}_trans_across"] = np.where(miss, np.inf, across)
    return table, scored.refine_ms


ICP_SECONDS = 1.2e-4
"""Planning figure: seconds of ICP per object, start and iteration on one core (the paper's
schedule, 10 iterations from one start, ~1 ms an object)."""


def plan(
    segs,
    states: dict,
    todo: dict[str, list[Refinement]],
    estimates: dict[str, int] | None = None,
) -> str:
    """What a call will compute and about how long it takes, before it starts: for each
    classical method whose refinements are to compute, the estimates left (``states``:
    method -> :class:`cloudpose.methods.EstimateProgress`;
    :data:`cloudpose.methods.SECONDS_PER_INSTANCE`) and the one-off preparation of the models
    they need (:data:`cloudpose.methods.SECONDS_PER_MODEL`: PPF's detector training, named
    where :data:`PREPARATION` has words for it), and the refinements ``todo`` per method
    (:data:`ICP_SECONDS`, once for each of the method's ``estimates``: an ensemble's networks,
    a combination's methods; default one)."""
    valid = np.asarray(segs.valid, dtype=bool)
    n = int(valid.sum())
    parts, seconds = [], 0.0
    for method, state in states.items():
        left = np.flatnonzero(valid & ~state.done)
        models = len(set(np.asarray(segs.cls_id)[left].tolist()))
        seconds += len(left) * SECONDS_PER_INSTANCE[method] + models * SECONDS_PER_MODEL[method]
        said = "kept" if len(left) == 0 else f"{len(left)} of {n} to compute"
        if len(left) and method in PREPARATION:
            said += ", " + PREPARATION[method].format(n=models)
        parts.append(f"{method} estimates: {said}")
    refs = [(m, r) for m, rs in todo.items() for r in rs]
    each = estimates or {}
    seconds += sum(
        n * ICP_SECONDS * r.settings.starts * r.settings.iterations * each.get(m, 1)
        for m, r in refs
    )
    parts.append(f"{len(refs)} refinement(s) to compute")
    return (
        f"compare: {len(segs)} instances; "
        + "; ".join(parts)
        + (f"; about {seconds / 60:.0f} min on one core" if seconds >= 60 else "")
    )


def _warm_up(segs, models: dict, refs: list[Refinement]) -> None:
    """Refine one segment with each refinement first, so that no method's milliseconds per
    object hold the one-off setup (Open3D's, the model clouds') of the first refinement."""
    first = np.flatnonzero(segs.valid)[:1]
    if len(first) == 0:
        return
    one = segs.subset(first)
    start = no_estimate(one)
    for ref in refs:
        refine.refine_poses(one, start, models, dataclasses.replace(ref.settings, select="fitness"))


def _described(run: str, run_id: str | None) -> str:
    """A network of the comparison in words: the shipped one's record, or the run and its id."""
    return shipped(run).describe() if run_id is None else f"{run} (MLflow run {run_id[:8]})"


def run_compare(
    out_dir: Path | None = None,
    *,
    data: str | Path | None = None,
    frames: str | None = None,
    runs: list[str] | None = None,
    methods: list[str] | None = None,
    combine: list[str] | None = None,
    seed: int = 1,
    starts: int = RECIPE["starts"],
    select: str = RECIPE["select"],
    radius: float = RECIPE["radius"],
    project_dir: Path | None = None,
    device: str = "auto",
    progress: bool = True,
) -> MethodComparison:
    """Compare the network with ``methods`` on ``frames`` of ``data``
    (:func:`cloudpose.report.compare.render` writes the report).

    Args:
        out_dir: the comparison's folder (default ``runs/compare/{data's identity}/{key}`` in
            ``project_dir``: :func:`cloudpose.store.metric_names.data_evaluation_name`, and 8
            hex digits of the networks' run ids and the seed).
        data: a dataset root in either layout (:mod:`cloudpose.data.layout`); None: the 61
            packaged real development frames.
        frames: its frame list (default ``all`` of the packaged frames, else ``keyframe``).
        runs: the network: a run (name, id or folder) or ``pretrained``; more than one is an
            ensemble (:func:`cloudpose.refine.refine_ensemble`). Default: the shipped network.
        methods: methods beside it (:data:`METHODS`; default FPFH + RANSAC, point-pair
            features and the control of no estimate, :data:`CONTROL`).
        combine: combinations of the network and ``methods``, each ``A+B[+C]``
            (:func:`combination`): every estimate of each refined alike, per object the
            refinement kept that agrees best with the depth (:func:`_refine`), a method beside
            the others.
        seed: the baselines' random seed (RANSAC's draws).
        starts, select, radius: the refinement beside the paper's (:func:`refinements`).
        project_dir: where the segment caches and the MLflow store of ``runs`` are.
        device: where the network runs.
    """
    runs = list(runs or [PRETRAINED])
    methods = list(METHODS) if methods is None else list(methods)
    for m in methods:
        if m not in METHODS:
            raise ValueError(f"--method {m!r}: expected one of {', '.join(METHODS)}")
    if len(set(runs)) < len(runs) or len(set(methods)) < len(methods):
        raise ValueError("--run / --method: each at most once")
    names = [NETWORK, *methods]
    combos = [combination(c, names) for c in combine or ()]
    if len(set(combos)) < len(combos):
        raise ValueError("--combine: each combination at most once")
    project_dir = Path(project_dir or Path.cwd()).resolve()
    refs = refinements(starts, select, radius, len(runs))
    root = Path(data) if data is not None else real_dev_root()
    frames = frames or ("all" if data is None else "keyframe")
    dataset = open_dataset(root)
    client = client_for(runs, project_dir)
    network = Network(tuple(load_network(client, r, device) for r in runs))
    cfg = network.members[0].config
    ids = check_ensemble(list(network.members), "--run")
    runtime.configure_threads(cfg.train.threads)
    segs = folder_segments(dataset, frames, cfg.data, project_dir, progress)
    if len(segs) == 0:
        raise ValueError(f"{root}: no annotated object in its {frames} frames")
    if out_dir is None:  # one folder per data and per networks
        key = hashlib.sha256(json.dumps([ids, seed]).encode()).hexdigest()[:8]
        name = data_evaluation_name(root, frames, segs.data_key)
        out_dir = project_dir / "runs" / "compare" / name / key
    out_dir = Path(out_dir)
    where = "the packaged real development frames" if data is None else str(root)
    described = f"{len(segs)} instances of {describe_split(dataset, frames)}, {where}"
    fps = {m: settings_fingerprint(baselines.load_settings(m)) for m in methods if m in BASELINES}
    _manifest(
        out_dir / "compare.json",
        {"data": str(segs.data_key), "frames": frames, "networks": ids, "seed": seed,
         "settings": fps},
    )  # fmt: skip
    timing_path = out_dir / "tables" / "icp_ms.json"
    timing = _timings(timing_path)
    combined = [COMBINED.join(parts) for parts in combos]
    kept = {(m, r.name): table for m in names + combined for r in refs
            if (table := _kept_table(out_dir, m, r, timing, segs)) is not None}  # fmt: skip
    todo = {m: [r for r in refs if (m, r.name) not in kept] for m in names + combined}
    needed = {m for parts, c in zip(combos, combined, strict=True) if todo[c] for m in parts}
    states = {
        m: EstimateProgress(baseline_estimates_path(project_dir, m, seed, str(segs.data_key)),
                            len(segs))
        for m in methods if m != CONTROL and (todo[m] or m in needed)
    }  # fmt: skip
    counts = {NETWORK: len(network.members)}
    counts |= {
        c: sum(counts.get(m, 1) for m in parts) for parts, c in zip(combos, combined, strict=True)
    }
    print(plan(segs, states, todo, counts), flush=True)
    models = dataset.models()
    with sigterm_as_interrupt():  # a kill stops as Ctrl-C does: what is done is kept
        if any(todo.values()):
            _warm_up(segs, models, refs)
        estimating = _Estimating(segs, models, seed, states, progress, out_dir)
        contenders = _contenders(network, names, combos, todo, needed, kept, refs, timing,
                                 estimating)  # fmt: skip
        tables: dict[tuple[str, str], pd.DataFrame] = {}
        for c in contenders:
            for ref in refs:
                if ref not in todo[c.name]:
                    tables[(c.name, ref.name)] = kept[(c.name, ref.name)]
                    continue
                tables[(c.name, ref.name)] = _write_table(
                    c, segs, dataset, models, ref, cfg.loss.symmetry_table, out_dir, timing,
                    progress,
                )  # fmt: skip
    source = "; ".join(_described(n.name, n.run_id) for n in network.members)
    return MethodComparison(out_dir, tables, contenders, refs, timing, described, source)


@dataclass(frozen=True)
class _Estimating:
    """What a method's estimate of the comparison's segments needs: the segments, their
    models, the baselines' seed and kept estimates (method -> :class:`EstimateProgress`),
    whether to show progress, and the folder (the networks' estimates are kept there)."""

    segs: object
    models: dict
    seed: int
    states: dict
    progress: bool
    out_dir: Path


def _contenders(
    network: Network, names: list[str], combos: list[tuple[str, ...]], todo: dict,
    needed: set, kept: dict, refs: list[Refinement], timing: dict, at: _Estimating,
) -> list[Estimated]:  # fmt: skip
    """Each method of ``names`` and each combination of ``combos`` with its estimates: read
    from the folder's tables where every one of its refinements is kept (``todo`` empty, and
    not ``needed`` by a combination left to compute), else estimated
    (:mod:`cloudpose.methods`)."""
    out: list[Estimated] = []
    for m in names:
        if not todo[m] and m not in needed:  # every table is there: no estimate is needed
            label = network.label if m == NETWORK else METHODS[m]
            out.append(_from_tables(kept[(m, refs[0].name)], m, label, timing))
        elif m == NETWORK:
            out.append(_network(at.segs, network, at.out_dir / "estimates" / "network.npz"))
        elif m == CONTROL:
            out.append(NoEstimate().estimate(at.segs))
        else:
            baseline = Baseline(m, at.models, at.seed, progress=at.progress)
            out.append(baseline.estimate(at.segs, at.states[m]))
    by_name = {c.name: c for c in out}
    for parts in combos:
        members = [by_name[p] for p in parts]
        m = COMBINED.join(parts)
        if not todo[m]:
            first = kept[(m, refs[0].name)]
            out.append(_from_tables(first, m, combined_label(members), timing, parts))
        else:
            out.append(combine(parts, members))
    return out


def _write_table(
    c: Estimated, segs, dataset, models: dict, ref: Refinement, symmetry_table: int,
    out_dir: Path, timing: dict, progress: bool,
) -> pd.DataFrame:  # fmt: skip
    """:func:`_refine` ``c`` by ``ref`` into ``out_dir/tables/METHOD-REFINEMENT.csv``, then
    its milliseconds, the CPU and the file's checksum into ``timing`` and
    ``tables/icp_ms.json`` (after the table: a table without them was not written whole)."""
    key = f"{c.name}-{ref.name}"
    path = out_dir / "tables" / f"{key}.csv"
    if progress:
        print(f"{c.label} {ref.label} on {len(segs)} instances ...", flush=True)
    table, ms = _refine(c, segs, dataset, models, ref, symmetry_table, progress)
    atomic_write(path, lambda tmp: table.to_csv(tmp, index=False), suffix=".csv")
    timing.update({key: ms, f"{c.name}-estimate": c.ms_per_object})
    timing[MACHINE] = sorted({*timing.get(MACHINE, []), runtime.describe_cpu()})
    timing[CHECKSUMS] = {**_checksums(timing), key: _sha256(path)}
    atomic_text(out_dir / "tables" / "icp_ms.json", json.dumps(timing, indent=2) + "\n")
    return table


SUMMARY_FRACTIONS = ("ads_auc", "ad_auc", "rot_sym_lt_10deg", "trans_lt_1cm")
SUMMARY_MEDIANS = ("trans_median_mm", "along_median_mm", "across_median_mm")


def summary(table: pd.DataFrame, stage: str) -> dict[str, float]:
    """Pooled figures of one stage (``net`` or ``icp``) of an instance table: ADS AUC, AD AUC,
    rotation < 10 deg modulo symmetry, translation < 1 cm (fractions), median translation and
    its parts along and across the viewing ray (mm) (:func:`cloudpose.metrics.stage_summary`)."""
    out = stage_summary(table, stage, medians=SUMMARY_MEDIANS)
    return {k: float(out[k]) for k in SUMMARY_FRACTIONS + SUMMARY_MEDIANS}


def rows(tables: dict, contenders, refs) -> pd.DataFrame:
    """One row per method and stage (its estimate, then after each refinement): ``method``,
    ``stage``, ``label`` and :func:`summary`'s figures; the estimate's figures are read from
    the paper's refinement's table (an ensemble: the network whose refinement it kept)."""
    out = []
    for c in contenders:
        first = tables[(c.name, refs[0].name)]
        out.append({"method": c.name, "stage": STAGE_ESTIMATE, "label": c.label,
                    **summary(first, "net")})  # fmt: skip
        for ref in refs:
            out.append({"method": c.name, "stage": ref.name, "label": f"{c.label} {ref.label}",
                        **summary(tables[(c.name, ref.name)], "icp")})  # fmt: skip
    return pd.DataFrame(out)
