"""Stress curves: the real development frames and synthetic test frames, perturbed in controlled
steps (:mod:`cloudpose.studies.perturbations`), each method measured at every step
(``cloudpose stress``).

Each method (:class:`SweepMethod`: the network of each checkpoint, an ensemble, FPFH + RANSAC,
point-pair features) estimates the pose of every perturbed segment and is refined by the same
ICP (:mod:`cloudpose.methods`); the errors are the evaluation's
(:func:`cloudpose.methods.instance_table`): ADS AUC, rotation < 10 deg modulo symmetry,
translation < 1 cm, median translation.

Where real frames sit: the statistic each perturbation moves is measured on the unperturbed
real segments and on the synthetic ones at every level; the level at which the synthetic
statistic reaches the real one is the real frames' own level, marked on the curves
(:func:`real_level`).

Resumable: each (source, perturbation, level, method) is one CSV in ``OUT/results/``, written
once computed; a later call skips what is there. :func:`make_plan` says what is left and an
estimate of its time before anything runs.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import lzma
import tarfile
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from cloudpose.config import PAPER_RADIUS
from cloudpose.data.segment_set import SegmentSet
from cloudpose.files import atomic_write, checked_members
from cloudpose.methods import (
    SECONDS_PER_INSTANCE,
    SECONDS_PER_MODEL,
    Baseline,
    LoadedNetwork,
    Network,
    score,
)
from cloudpose.metrics import stage_summary
from cloudpose.refine import ICPSettings, schedule_for
from cloudpose.registry import DEFAULT_PRESET, resolve
from cloudpose.studies.perturbations import (
    PERTURBATIONS,
    SOURCES,
    STATISTICS,
    Perturbation,
    condition_segments,
    evenly_spaced,
    farthest_level,
    identity_level,
    open_source,
    segment_stats,
)

# --------------------------------------------------------------------------- methods


@dataclass(frozen=True)
class SweepMethod:
    """A pose method of the sweep: ``net-{label}`` (a checkpoint), ``ensemble`` (several, the
    refinement of best ICP fitness kept per object), ``fpfh`` or ``ppf``; each result holds
    its estimate (``net_*`` columns) and the same after ICP (``icp_*``)."""

    name: str
    checkpoint: Path | None = None
    members: tuple[Path, ...] = ()
    """The checkpoints of an ensemble (:func:`cloudpose.refine.select_refinements` by fitness:
    under a perturbation of the points the frame's depth is not what the segment shows)."""
    limit: int | None = None
    """Evenly spaced instances of the sweep's own it runs on (None: all)."""
    ends_only: bool = False
    """Only at the identity and at each perturbation's farthest level (a costly method)."""
    run_id: str | None = None
    """The MLflow run whose checkpoint it is, where the network was named by its run (kept in
    ``sweep.json``, so results stay traceable when the checkpoint was a downloaded copy)."""

    def runs_at(self, p: Perturbation, level: float) -> bool:
        """Whether this method is computed at ``level`` of ``p``."""
        ident = identity_level(p)
        return not self.ends_only or level in (ident, farthest_level(p))


def _kind(method: SweepMethod) -> str:
    return "net" if method.checkpoint is not None or method.members else method.name


def _networks(paths, cache: dict) -> list[LoadedNetwork]:
    """The network of each checkpoint, loaded once per sweep call."""
    out = []
    for p in paths:
        key = ("net", str(p))
        if key not in cache:
            cache[key] = LoadedNetwork.from_checkpoint(p, "cpu")
        out.append(cache[key])
    return out


def run_method(
    method: SweepMethod,
    segs: SegmentSet,
    dataset,
    seed: int,
    cache: dict,
    icp_radius: float = PAPER_RADIUS,
) -> pd.DataFrame:
    """The instance table (:func:`cloudpose.methods.score`, ``net_*`` and ``icp_*`` columns)
    of ``method`` on ``segs``; a segment a baseline cannot register is a miss. ICP starts at
    ``icp_radius`` (:func:`cloudpose.refine.schedule_for`) for every method."""
    models = cache.setdefault("models", dataset.models())
    segs = segs.subset(evenly_spaced(len(segs), method.limit))
    if method.checkpoint is not None or method.members:  # an ensemble keeps the best fit
        nets = _networks(method.members or [method.checkpoint], cache)
        table_cfg = nets[0].config
        icp_settings = ICPSettings.from_config(table_cfg.icp)
        if method.members:
            icp_settings = dataclasses.replace(icp_settings, select="fitness")
        estimated = Network(tuple(nets)).estimate(segs)
    else:
        key = ("estimator", method.name)
        if key not in cache:  # per-model state (features, PPF's hash tables) built once
            cache[key] = Baseline(method.name, models, seed)
        estimated = cache[key].estimate(segs)  # each condition's draws start afresh
        icp_settings = ICPSettings()
        table_cfg = cache.setdefault("cfg", resolve("shared-0", DEFAULT_PRESET, 1))
    icp_settings = dataclasses.replace(icp_settings, **schedule_for(icp_radius))
    scored = score(
        segs, estimated, dataset, icp_settings,
        symmetry_table=table_cfg.loss.symmetry_table, models=models, quiet=True,
    )  # fmt: skip
    drop = ["net_R", "net_t", "icp_R", "icp_t", "icp_fitness", "icp_inlier_rmse", "icp_fallback"]
    return scored.table.drop(columns=drop + (["ensemble_member"] if method.members else []))


# --------------------------------------------------------------------------- the sweep


def level_name(level: float) -> str:
    """A level as a folder name (``0.35``, ``10``)."""
    return f"{level:g}"


def result_path(out_dir: Path, source: str, pert: str, level: float, what: str) -> Path:
    """``OUT/results/{source}/{perturbation}/{level}/{what}.csv``; ``what`` is a method's
    name or ``stats`` (the segments' statistics)."""
    return out_dir / "results" / source / pert / level_name(level) / f"{what}.csv"


def level_result_path(out_dir: Path, source: str, pert: str, level: float, what: str) -> Path:
    """:func:`result_path` of ``pert`` at ``level``, where the identity of every perturbation
    is the one result computed under ``dilate`` at 0."""
    if level == identity_level(PERTURBATIONS[pert]):
        return result_path(out_dir, source, "dilate", 0.0, what)
    return result_path(out_dir, source, pert, float(level), what)


def conditions(perts: list[Perturbation]) -> list[tuple[Perturbation, float]]:
    """Every (perturbation, level) once; the identity of all of them is computed once, under
    the first."""
    out, seen_identity = [], False
    for p in perts:
        for lv in p.levels:
            if lv == identity_level(p):
                if seen_identity:
                    continue
                seen_identity = True
                out.append((PERTURBATIONS["dilate"], 0.0))
                continue
            out.append((p, float(lv)))
    return out


@dataclass(frozen=True)
class StressPlan:
    """What a sweep will compute: per (source, method), the conditions left and instances."""

    todo: dict[tuple[str, str], int]
    instances: dict[str, int]
    seconds: float

    def describe(self, methods: list[SweepMethod]) -> str:
        lines = []
        for (src, m), n in sorted(self.todo.items()):
            meth = next(x for x in methods if x.name == m)
            k = self.instances[src] if meth.limit is None else min(meth.limit, self.instances[src])
            lines.append(f"  {src:6s} {m:12s} {n:3d} conditions left x {k} instances")
        mins = self.seconds / 60
        lines.append(f"  estimated time: {mins:.0f} min (on one core; a busy machine is slower)")
        return "\n".join(lines)


def make_plan(
    out_dir: Path,
    sources: dict[str, int],
    perts: list[Perturbation],
    methods: list[SweepMethod],
    models: dict[str, int] | None = None,
) -> StressPlan:
    """The conditions left per (source, method) and the time they should take, a baseline's
    preparation of each of the source's ``models`` (a count per source; default none,
    :data:`SECONDS_PER_MODEL`) included once where it has a condition left there."""
    todo: dict[tuple[str, str], int] = {}
    secs = 0.0
    for src, n in sources.items():
        for m in methods:
            if _kind(m) in SECONDS_PER_MODEL and any(
                m.runs_at(p, lv) and not result_path(out_dir, src, p.name, lv, m.name).is_file()
                for p, lv in conditions(perts)
            ):
                k = (models or {}).get(src, 0)
                secs += (k if m.limit is None else min(m.limit, k)) * SECONDS_PER_MODEL[_kind(m)]
        seg_needed = 0
        for p, lv in conditions(perts):
            missing = [
                m
                for m in methods
                if m.runs_at(p, lv) and not result_path(out_dir, src, p.name, lv, m.name).is_file()
            ]
            if missing or not result_path(out_dir, src, p.name, lv, "stats").is_file():
                seg_needed += 1
            for m in missing:
                todo[(src, m.name)] = todo.get((src, m.name), 0) + 1
                k = n if m.limit is None else min(m.limit, n)
                secs += k * SECONDS_PER_INSTANCE[_kind(m)]
        secs += seg_needed * n * SECONDS_PER_INSTANCE["segment"]
    return StressPlan(todo, dict(sources), secs)


def model_trees(models: dict[int, np.ndarray]) -> dict[int, cKDTree]:
    """A k-d tree of each model's points (model frame)."""
    return {c: cKDTree(m) for c, m in models.items()}


def run_sweep(
    out_dir: Path,
    cfg,
    methods: list[SweepMethod],
    *,
    sources: tuple[str, ...] = SOURCES,
    only: tuple[str, ...] = (),
    instances: int | None = None,
    synth_frames: int = 60,
    seed: int = 1,
    progress: bool = True,
    echo: Callable[[str], None] = print,
    dry_run: bool = False,
    icp_radius: float = PAPER_RADIUS,
) -> StressPlan:
    """Compute every missing (source, perturbation, level, method) result into ``out_dir``
    (module doc); prints the plan first. ``only`` names perturbations (default all).
    ``icp_radius``: ICP's first radius for every method (:func:`cloudpose.refine.schedule_for`),
    kept in ``sweep.json``; results of another radius are another folder's."""
    unknown = sorted(set(only) - set(PERTURBATIONS))
    if unknown:
        raise ValueError(f"--only {unknown}: expected some of {', '.join(PERTURBATIONS)}")
    perts = [p for n, p in PERTURBATIONS.items() if not only or n in only]
    out_dir.mkdir(parents=True, exist_ok=True)
    opened = {
        s: open_source(
            s, cfg, out_dir, instances=instances, synth_frames=synth_frames, progress=progress
        )
        for s in sources
    }
    meta = {
        "preset": cfg.preset,
        "seed": seed,
        "sources": {s: src.described for s, src in opened.items()},
        "methods": {m.name: {"checkpoint": str(m.checkpoint or ""), "limit": m.limit,
                             **({"members": [str(p) for p in m.members]} if m.members else {}),
                             **({"ends_only": True} if m.ends_only else {}),
                             **({"run_id": m.run_id} if m.run_id else {})}
                    for m in methods},
        "perturbations": {p.name: list(p.levels) for p in perts},
        "icp_radius": icp_radius,
    }  # fmt: skip
    meta_path = out_dir / "sweep.json"
    if meta_path.is_file():  # another call's sources, methods and perturbations stay listed
        old = json.loads(meta_path.read_text())
        check_icp_radius(out_dir, old, icp_radius)
        for key, was in (("sources", old.get("sources", {})), ("methods", old.get("methods", {}))):
            changed = [k for k, v in meta[key].items() if k in was and _same(was[k]) != _same(v)]
            if changed or old.get("seed", seed) != seed:
                raise ValueError(
                    f"{out_dir} holds results of other {key} or seed ({changed or 'seed'}: "
                    f"{[was.get(k) for k in changed] or old.get('seed')}); choose another "
                    "--results folder"
                )
        for key in ("sources", "methods", "perturbations"):
            meta[key] = {**old.get(key, {}), **meta[key]}
    models = {
        s: len({int(src.frames[f].frame.cls_ids[i]) for f, i in src.instances})
        for s, src in opened.items()
    }
    plan = make_plan(
        out_dir, {s: len(src.instances) for s, src in opened.items()}, perts, methods, models
    )
    echo("stress plan:\n" + plan.describe(methods))
    if dry_run:  # the plan only: no sweep.json that a later call with other runs would meet
        return plan
    atomic_write(meta_path, lambda tmp: Path(tmp).write_text(json.dumps(meta, indent=1)))
    n_fps, radius = cfg.data.n_fps, cfg.data.outlier_radius
    for s, src in opened.items():
        cache: dict = {}
        trees = model_trees(src.dataset.models())
        for p, lv in conditions(perts):
            stats_path = result_path(out_dir, s, p.name, lv, "stats")
            missing = [
                m
                for m in methods
                if m.runs_at(p, lv) and not result_path(out_dir, s, p.name, lv, m.name).is_file()
            ]
            if not missing and stats_path.is_file():
                continue
            t0 = time.perf_counter()
            segs, px = condition_segments(src, p, lv, seed, n_fps, radius)
            if not stats_path.is_file():
                st = segment_stats(segs, px, trees, src.dataset.models())
                st.insert(0, "frame_id", segs.frame_id)
                st.insert(1, "instance", segs.instance)
                _write_csv(stats_path, st)
            for m in missing:
                t1 = time.perf_counter()
                table = run_method(m, segs, src.dataset, seed, cache, icp_radius)
                table["seconds"] = time.perf_counter() - t1
                _write_csv(result_path(out_dir, s, p.name, lv, m.name), table)
            echo(f"  {s} {p.name}={level_name(lv)}: {', '.join(m.name for m in missing)} "
                 f"({time.perf_counter() - t0:.0f} s)")  # fmt: skip
    return plan


def check_icp_radius(out_dir: Path, meta: dict, icp_radius: float) -> None:
    """``ValueError`` unless the results in ``out_dir`` (its ``sweep.json``, ``meta``; one
    written before the radius was recorded is the paper's) were refined from ``icp_radius``."""
    was = meta.get("icp_radius", PAPER_RADIUS)
    if was != icp_radius:
        raise ValueError(
            f"{out_dir} holds results refined by ICP from a first radius of {was} m, not "
            f"{icp_radius}; choose another --results folder"
        )


def _same(entry):
    """What of a sweep.json entry decides its result files: not where a method runs, nor where
    the checkpoint of a network named by its MLflow run was downloaded to (its run decides)."""
    if not isinstance(entry, dict):
        return entry
    drop = {"ends_only", "checkpoint"} if entry.get("run_id") else {"ends_only"}
    return {k: v for k, v in entry.items() if k not in drop}


def _write_csv(path: Path, df: pd.DataFrame) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda tmp: df.to_csv(tmp, index=False), suffix=".csv")


# --------------------------------------------------------------------------- results


SUMMARY_COLUMNS = ("ads_auc", "rot_sym_lt_10deg", "trans_lt_1cm", "trans_median_mm")
"""What each (source, perturbation, level, method, stage) is summed up by: ADS AUC, rotation
< 10 deg modulo symmetry, translation < 1 cm (fractions), median translation error (mm)."""


def summary_of(table: pd.DataFrame, stage: str) -> dict[str, float]:
    """:data:`SUMMARY_COLUMNS` of one method's result table at ``stage`` (``net``: its own
    estimate, ``icp``: after ICP), pooled over its instances, and their ``count``
    (:func:`cloudpose.metrics.stage_summary`)."""
    out = stage_summary(table, stage)
    return {k: out[k] for k in (*SUMMARY_COLUMNS, "count")}


def _learned(method: dict) -> bool:
    """Whether a method of ``sweep.json`` is a network (a checkpoint) or an ensemble of them
    (members), not a registration."""
    return bool(method["checkpoint"] or method.get("members"))


def collect(out_dir: Path) -> pd.DataFrame:
    """One row per (source, perturbation, level, method, stage) found under ``out_dir``:
    :data:`SUMMARY_COLUMNS` and the instance count; the identity (computed once) is repeated
    under every perturbation. Stage ``net`` is the method's own estimate, ``icp`` after ICP.
    Method ``NET@BASELINE``: network (or ensemble) NET on the instances the baseline ran on
    (its subsample), for paired comparisons."""
    meta = json.loads((out_dir / "sweep.json").read_text())
    learned = [m for m, v in meta["methods"].items() if _learned(v)]  # sweep order: stable rows
    rows = []
    for src in meta["sources"]:
        for pname, levels in meta["perturbations"].items():
            for lv in levels:
                tables = {}
                for m in meta["methods"]:
                    path = level_result_path(out_dir, src, pname, lv, m)
                    if path.is_file():
                        tables[m] = pd.read_csv(path)
                for m in learned:  # each network (or ensemble) on each baseline's rows
                    for b in meta["methods"]:
                        if b not in learned:
                            if m in tables and b in tables:
                                keys = tables[b][["frame_id", "instance"]]
                                tables[f"{m}@{b}"] = tables[m].merge(keys)
                for m, table in tables.items():
                    for stage in ("net", "icp"):
                        rows.append(
                            {
                                "source": src,
                                "perturbation": pname,
                                "level": float(lv),
                                "method": m,
                                "stage": stage,
                                **summary_of(table, stage),
                                "seconds_per_instance": float(table["seconds"].iloc[0])
                                / max(len(table), 1),
                            }
                        )
    return pd.DataFrame(rows)


def collect_stats(out_dir: Path) -> pd.DataFrame:
    """The segments' statistics (:data:`STATISTICS`) per (source, perturbation, level): the mean
    of the share-type ones (``off_model``, ``no_depth``, ``boundary``), the median of the
    others."""
    meta = json.loads((out_dir / "sweep.json").read_text())
    rows = []
    for src in meta["sources"]:
        for pname, levels in meta["perturbations"].items():
            for lv in levels:
                path = level_result_path(out_dir, src, pname, lv, "stats")
                if not path.is_file():
                    continue
                st = pd.read_csv(path)
                row = {"source": src, "perturbation": pname, "level": float(lv)}
                for k in STATISTICS:
                    if k not in st:  # a statistic added after this level was measured
                        row[k] = np.nan
                        continue
                    v = st[k].to_numpy(dtype=float)
                    v = v[np.isfinite(v)]
                    share = k in ("off_model", "no_depth", "boundary")
                    row[k] = float(v.mean() if share else np.median(v)) if len(v) else np.nan
                rows.append(row)
    return pd.DataFrame(rows)


def real_level(p: Perturbation, stats: pd.DataFrame) -> tuple[float, str]:
    """Where the real frames sit on ``p``'s axis, and how it was found, in words.

    The real segments' statistic ``p.stat`` (unperturbed) against the synthetic ones' at each
    level of ``p``, linearly interpolated; below the synthetic identity -> the identity (real
    frames show no more of it than synthetic ones); beyond the last level -> NaN. ``count``:
    the ratio of the medians; ``occlusion``: the extra share hidden,
    1 - (1 - O_real) / (1 - O_synth), of the median occlusion factors. A statistic that moves
    by less than a fifth of its identity value over the whole range places nothing (NaN).
    """
    ident = identity_level(p)
    real = stats[(stats.source == "real") & (stats.perturbation == p.name) & (stats.level == ident)]
    syn = stats[(stats.source == "synth") & (stats.perturbation == p.name)].sort_values("level")
    if real.empty or syn.empty:
        return np.nan, "needs both sources"
    r = float(real[p.stat].iloc[0])
    s0 = syn[syn.level == ident][p.stat]
    if not np.isfinite(r) or s0.empty or not np.isfinite(float(s0.iloc[0])):
        return np.nan, "statistic unknown"
    s0 = float(s0.iloc[0])
    if p.stat == "count":
        return r / s0, f"median points: real {r:.0f}, synthetic {s0:.0f}"
    if p.stat == "occlusion":
        extra = 1 - (1 - r) / (1 - s0) if s0 < 1 else np.nan
        return max(extra, 0.0), f"median occlusion factor: real {r:.2f}, synthetic {s0:.2f}"
    lv = syn.level.to_numpy(dtype=float)
    sv = syn[p.stat].to_numpy(dtype=float)
    order = np.argsort(lv)
    lv, sv = lv[order], sv[order]
    words = f"{STATISTICS[p.stat]}: real {r:.3g}, synthetic {s0:.3g} at level {ident:g}"
    ok = np.isfinite(sv)
    lv, sv = lv[ok], sv[ok]
    if len(sv) > 1 and np.ptp(sv) < 0.2 * max(abs(s0), 1e-9):
        return np.nan, words + " (the statistic does not move with this perturbation: not placed)"
    increasing = len(sv) < 2 or sv[1] >= sv[0]  # the direction of the first step
    if (r <= s0) if increasing else (r >= s0):
        return ident, words + " (real frames show no more of it)"
    for a, b, sa, sb in zip(lv[:-1], lv[1:], sv[:-1], sv[1:], strict=True):
        if min(sa, sb) <= r <= max(sa, sb) and sa != sb:
            return float(a + (r - sa) * (b - a) / (sb - sa)), words
    return np.nan, words + f" (beyond level {lv[-1]:g})"


# --------------------------------------------------------------------------- packed results

RESULT_PARTS = ("sweep.json", "results", "icp_select")
"""What a sweep's report is rendered from (:func:`pack_results` keeps these; the synthetic
frames' cache under ``synth/`` is rebuilt from the preset)."""


def result_files(run_dir: Path) -> list[Path]:
    """The sweep's result files (:data:`RESULT_PARTS`) in ``run_dir``, sorted."""
    run_dir = Path(run_dir)
    return sorted(
        f
        for part in RESULT_PARTS
        for f in ([run_dir / part] if part.endswith(".json") else (run_dir / part).rglob("*"))
        if f.is_file()
    )


def pack_results(run_dir: Path, archive: Path) -> int:
    """The sweep's result files (:data:`RESULT_PARTS`) in ``run_dir`` into the ``.tar.xz``
    ``archive``, written atomically and byte-identical for identical files (sorted members, no
    times or owners); ``--results`` reads it back (:func:`results_folder`). Returns the number
    of files; ``FileNotFoundError`` without a ``sweep.json``."""
    run_dir, archive = Path(run_dir), Path(archive)
    if not (run_dir / "sweep.json").is_file():
        raise FileNotFoundError(f"{run_dir}: no sweep.json (not the results of `cloudpose stress`)")
    files = result_files(run_dir)

    def plain(info: tarfile.TarInfo) -> tarfile.TarInfo:
        info.mtime, info.uid, info.gid, info.uname, info.gname = 0, 0, 0, "", ""
        return info

    def write(tmp: Path) -> None:
        with tarfile.open(tmp, "w:xz", preset=9) as tar:
            for f in files:
                tar.add(f, arcname=f.relative_to(run_dir).as_posix(), filter=plain)

    atomic_write(archive, write, suffix=".tar.xz")
    return len(files)


@contextlib.contextmanager
def results_folder(path: Path) -> Iterator[Path]:
    """A sweep's results as a folder: ``path`` itself, or an archive of :func:`pack_results`
    unpacked into a temporary folder removed afterwards. ``ValueError`` naming the archive and
    the member when one lies outside :data:`RESULT_PARTS` or outside the folder (nothing is
    unpacked then), or when the archive cannot be read."""
    path = Path(path)
    if path.is_dir():
        yield path
        return
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no stress results (a folder or a packed .tar.xz)")
    with tempfile.TemporaryDirectory(prefix="cloudpose-stress-") as tmp:
        try:
            with tarfile.open(path, "r:*") as tar:
                members = checked_members(
                    path,
                    tar,
                    tmp,
                    lambda name: name.split("/")[0] in RESULT_PARTS,
                    f"a stress result (one of {', '.join(RESULT_PARTS)})",
                )
                tar.extractall(tmp, members=members, filter="data")
        except (tarfile.TarError, EOFError, lzma.LZMAError) as exc:
            raise ValueError(
                f"{path}: not a readable archive of stress results ({type(exc).__name__}: "
                f"{exc}); pack it again (cloudpose stress --steps none --pack)"
            ) from exc
        yield Path(tmp)
