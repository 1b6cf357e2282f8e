"""Plans: what a suite will do and how long it will take, printed before it starts.

``cloudpose ablate --dry-run``, ``ablate-masks --dry-run``, ``run --dry-run`` and the
occlusion report's check print a :class:`Plan`: for each (variant, seed) whether a finished,
evaluated run of its config on its data exists (skipped) or not (to train), the frames still to
render, and a time estimate from earlier runs of the preset in MLflow, else from the size of
the preset (:func:`estimate_run_s`). Nothing here trains, renders or writes.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from cloudpose import runtime
from cloudpose.config import Config
from cloudpose.conventions import packaged_classes
from cloudpose.data.dataset import data_fingerprint, dataset_root, synthetic_root
from cloudpose.data.keys import DataKey
from cloudpose.data.synth.chunks import ChunkStore
from cloudpose.data.synth.frames import frame_id
from cloudpose.data.synth.write import _frame_done
from cloudpose.registry import get_group, resolve
from cloudpose.report import segmentation
from cloudpose.report.build import default_out_dir
from cloudpose.store import tracking
from cloudpose.store.runs import TEST_KEY, finished_run, run_has_config, run_name
from cloudpose.train.loop import online_chunks, online_store_root


def seed_list(seeds: int | Iterable[int]) -> list[int]:
    """``3`` -> [1, 2, 3]; a list is taken as it is (sorted, duplicates dropped)."""
    if isinstance(seeds, int):
        if seeds < 1:
            raise ValueError(f"seeds must be >= 1, got {seeds}")
        return list(range(1, seeds + 1))
    out = sorted({int(s) for s in seeds})
    if not out:
        raise ValueError("seeds is empty")
    return out


def format_seconds(s: float | None) -> str:
    """``s`` seconds as ``1h05m`` or ``3m07s``; "unknown" for None or a non-finite value."""
    if s is None or not math.isfinite(s):
        return "unknown"
    s = round(s)
    return f"{s // 3600}h{s % 3600 // 60:02d}m" if s >= 3600 else f"{s // 60}m{s % 60:02d}s"


RENDER_S_PER_FRAME = 1 / 2.94 + 1 / 12.9
"""Seconds to render one synthetic frame and cache its segments on a 2-core CPU: synthesis at
2.9 and segment preparation at 12.9 frames/s (``make bench``, reports/benchmarks.md)."""

TRAIN_S_PER_POINT = 2.1e-5
"""Training seconds per (sample x input point), per-epoch validation included: shared-0 on the
cpu preset took ~19.5 s an epoch of 3,583 segments x 256 points on a 2-core CPU (the first
sweep's store, reports/cpu/mlflow-store.tar.xz in commit b200bde; 25 epochs, ~8 min)."""

EVAL_S_PER_TEST_FRAME = 1.0
"""Seconds of evaluation (network, ICP, metrics, with and without ICP) per test frame, from
the same runs: ~11 min a run, of which ~2.5 min after training for 150 test frames."""

RUN_OVERHEAD_S = 30.0
"""Seconds a run spends regardless of its size: start-up, BatchNorm re-estimation, the real
development frames' evaluation, MLflow logging."""

SEGMENTS_PER_FRAME = 4.5
"""Training segments per synthetic training frame (the cpu preset: 3,583 from 800 frames,
10% of them held out)."""


@dataclass(frozen=True)
class PlannedRun:
    """One (variant, seed) of a plan.

    Attributes:
        status: "finished" (a finished, evaluated run of this config on this data exists: it
            is skipped) or "to train".
        run_id: the finished run, if any.
    """

    variant: str
    seed: int
    preset: str
    status: str
    run_id: str | None = None

    @property
    def name(self) -> str:
        return run_name(self.variant, self.preset, self.seed)


@dataclass
class Plan:
    """What a command will do before it does it: frames, runs, evaluations, time.

    Attributes:
        title: what runs, e.g. ``ablation shared/cpu``.
        frames: dataset root -> (frames to render, frames it needs).
        runs: every (variant, seed), finished or to train.
        per_run_s: estimated seconds of one run (training + evaluation).
        per_run_source: where ``per_run_s`` comes from, in words.
        evaluations: extra evaluations of finished runs (name -> seconds each), e.g. the mask
            ablation's sources.
        notes: further lines (what follows the runs, caveats).
        data_ready: whether every dataset is rendered (the finished runs are found by the
            data's fingerprint, so before rendering a run of the same config on any data
            counts as finished).
        matched_elsewhere: with the data not rendered, runs counted finished that way.
        finished: what happens to a finished run, in words.
    """

    title: str
    frames: dict[str, tuple[int, int]] = field(default_factory=dict)
    runs: list[PlannedRun] = field(default_factory=list)
    per_run_s: float | None = None
    per_run_source: str = ""
    evaluations: list[tuple[str, float]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    data_ready: bool = True
    matched_elsewhere: int = 0
    finished: str = "finished before (skipped)"

    @property
    def to_train(self) -> list[PlannedRun]:
        return [r for r in self.runs if r.status != "finished"]

    @property
    def render_s(self) -> float:
        return sum(n for n, _ in self.frames.values()) * RENDER_S_PER_FRAME

    @property
    def total_s(self) -> float | None:
        if self.to_train and self.per_run_s is None:
            return None
        runs = len(self.to_train) * (self.per_run_s or 0.0)
        return self.render_s + runs + sum(s for _, s in self.evaluations)

    def lines(self) -> list[str]:
        """The plan as the commands print it."""
        out = [f"plan: {self.title}"]
        for root, (todo, wanted) in self.frames.items():
            if todo:
                out.append(
                    f"  data: render {todo:,} of {wanted:,} frames into {root} "
                    f"(~{format_seconds(todo * RENDER_S_PER_FRAME)} at {RENDER_S_PER_FRAME:.2f} s a frame "
                    "on 2 cores, reports/benchmarks.md)"
                )
            else:
                out.append(f"  data: {root}, all {wanted:,} frames rendered")
        if self.runs:
            variants = list(dict.fromkeys(r.variant for r in self.runs))
            seeds = sorted({r.seed for r in self.runs})
            done = len(self.runs) - len(self.to_train)
            out.append(
                f"  runs: {len(self.runs)} ({len(variants)} variant(s) x {len(seeds)} seed(s)): "
                f"{done} {self.finished}, {len(self.to_train)} to train + evaluate"
            )
            for v in variants:
                mine = [r for r in self.runs if r.variant == v]
                parts = []
                for status in ("finished", "to train"):
                    s = [str(r.seed) for r in mine if r.status == status]
                    if s:
                        parts.append(f"seed {','.join(s)} {status}")
                out.append(f"    {v:<18} {'; '.join(parts)}")
            if not self.data_ready and self.matched_elsewhere:
                out.append(
                    f"    (the data is not rendered yet: the {self.matched_elsewhere} finished "
                    "runs are of the same config, and are skipped once the data rendered here "
                    "has the key of theirs or of the same data rendered on another kind of CPU; "
                    "a key not known to be the same data stops the sweep before it trains, "
                    "naming the check to run)"
                )
        for name, seconds in self.evaluations:
            out.append(f"  evaluate: {name} (~{format_seconds(seconds)})")
        n = len(self.to_train)
        if n:
            out.append(
                f"  time: ~{format_seconds(self.per_run_s)} a run ({self.per_run_source}); "
                f"{n} run(s) x ~{format_seconds(self.per_run_s)} = ~{format_seconds(n * (self.per_run_s or 0))}"
            )
        total = self.total_s
        out.append(
            f"  total: ~{format_seconds(total)}" + (" (nothing to do)" if not total else "")
            if total is not None
            else "  total: unknown"
        )
        out += [f"  {line}" for line in self.notes]
        return out

    def text(self) -> str:
        return "\n".join(self.lines())


def estimate_run_s(cfg: Config) -> tuple[float, str]:
    """Seconds one run of ``cfg`` takes (training + evaluation), from its settings alone.

    The rates are the cpu preset's shared-0 runs on a 2-core CPU (:data:`TRAIN_S_PER_POINT`,
    :data:`EVAL_S_PER_TEST_FRAME`, :data:`RUN_OVERHEAD_S`); variants that share layers train
    faster, a GPU much faster.

    Returns:
        (seconds, where the figure comes from, in words).
    """
    t, d = cfg.train, cfg.data
    if d.train_source == "online":
        samples = d.online_epoch_segments
    else:
        samples = d.train_frames * SEGMENTS_PER_FRAME
    steps = t.epochs * max(1, math.ceil(samples / t.batch_size))
    train_s = steps * t.batch_size * t.n_points * TRAIN_S_PER_POINT
    seconds = RUN_OVERHEAD_S + train_s + d.test_frames * EVAL_S_PER_TEST_FRAME
    source = (
        f"from the preset: {steps:,} Adam steps of {t.batch_size} x {t.n_points} points and "
        f"{d.test_frames} test frames at the rate of shared-0 on the cpu preset, 2-core CPU"
    )
    return seconds, source


def _measured_run_s(
    client, preset: str, variants: list[str], device: str
) -> tuple[float, int] | None:
    """Median wall time of the finished runs of ``preset`` in the store that trained on
    ``device`` (``cpu`` or ``cuda``; of ``variants`` when they have any), and how many runs it is
    from. A run that trained some of its steps on another machine (``train.machine_steps``,
    ``benchmarks/gpu_run.py``) or on another device (its ``device`` param, ``cuda, then cpu``
    for a run resumed on a CPU) is left out: its wall time is not what a run here takes. A run
    that does not record its device counts."""
    found = [
        r
        for r in tracking.find_runs(client, preset=preset)
        if r.info.end_time
        and r.info.start_time
        and TEST_KEY in r.data.metrics
        and "train.machine_steps" not in r.data.params
        and r.data.params.get("device", device).split(":")[0] == device
    ]
    own = [r for r in found if r.data.tags.get("variant") in variants]
    runs = own or found
    if not runs:
        return None
    seconds = sorted((r.info.end_time - r.info.start_time) / 1000 for r in runs)
    return seconds[len(seconds) // 2], len(seconds)


def training_device(cfg: Config) -> str:
    """The kind of device (``cpu`` or ``cuda``) a run of ``cfg`` would train on here
    (:func:`cloudpose.runtime.pick_device`)."""
    try:
        return runtime.pick_device(cfg.train.device).type
    except ValueError:  # CUDA named where there is none: the run stops; its plan still shows
        return cfg.train.device.split(":")[0]


def _frames_to_render(cfg: Config, project_dir: Path) -> tuple[str, int, int, bool]:
    """(root, frames to render, frames needed, whether its image sets list what ``cfg``
    asks for) of ``cfg``'s synthetic data; a real root needs no rendering."""
    d = cfg.data
    if d.root:
        return str(dataset_root(d, project_dir)), 0, 0, True
    root = synthetic_root(d, project_dir)
    wanted = [("train", i) for i in range(d.train_frames)]
    wanted += [("test", i) for i in range(d.test_frames)]
    todo = sum(not _frame_done(root, frame_id(s, i)) for s, i in wanted)
    lists = True
    for name, n in (("train", d.train_frames), ("test", d.test_frames)):
        path = root / "image_sets" / f"{name}.txt"
        lines = path.read_text().split() if path.is_file() else []
        lists = lists and len(lines) == n
    try:
        shown = str(root.relative_to(project_dir))
    except ValueError:
        shown = str(root)
    return shown, todo, len(wanted), lists


def plan_runs(
    variants: list[str],
    preset: str,
    seeds: int | Iterable[int],
    *,
    title: str,
    project_dir: Path | None = None,
    overrides: dict | None = None,
) -> Plan:
    """The plan of :func:`ensure_runs` for ``variants`` x ``seeds`` (:func:`plan_configs`)."""
    todo = [resolve(v, preset, s, overrides) for v in variants for s in seed_list(seeds)]
    return plan_configs(todo, title=title, project_dir=project_dir)


def plan_configs(
    todo: list[Config],
    *,
    title: str,
    project_dir: Path | None = None,
    finished: str = "finished before (skipped)",
) -> Plan:
    """The plan of training and evaluating ``todo``, made without rendering or training.

    Frames are counted on disk; a run counts as finished when the store holds a finished,
    evaluated run of its config on its data (the data's fingerprint needs the rendered frames:
    before they exist, a finished run of the config on any data counts, as the runner then
    either skips it or stops, :func:`cloudpose.suite.ablate.ensure_runs`). The time of a run is the median of the
    preset's finished runs in the store when there are any, else :func:`estimate_run_s`.

    Args:
        todo: the runs' configs.
        title: what the plan is of.
        project_dir: folder of ``data/`` and the default MLflow store (cwd).
        finished: what happens to a finished run, in words.
    """
    project_dir = (project_dir or Path.cwd()).resolve()
    client = tracking.setup(project_dir)
    plan = Plan(title, finished=finished)
    preset = todo[0].preset if todo else ""
    variants = list(dict.fromkeys(c.variant for c in todo))
    data_keys: dict[str, DataKey | None] = {}
    for cfg in todo:
        k = repr(cfg.data)
        if k in data_keys:
            continue
        root, n, wanted, lists = _frames_to_render(cfg, project_dir)
        plan.frames[root] = (n, wanted)
        ready = n == 0 and lists
        data_keys[k] = data_fingerprint(cfg.data, project_dir) if ready else None
        plan.data_ready = plan.data_ready and ready
    for cfg in todo:
        data_key = data_keys[repr(cfg.data)]
        done = finished_run(client, cfg, data_key) if data_key is not None else None
        if data_key is None:
            done = finished_run_any_data(client, cfg)
            plan.matched_elsewhere += done is not None
        plan.runs.append(
            PlannedRun(
                cfg.variant,
                cfg.seed,
                preset,
                "finished" if done is not None else "to train",
                done.info.run_id if done is not None else None,
            )
        )
    plan.notes += chunk_lines(
        [c for c, r in zip(todo, plan.runs, strict=True) if r.status != "finished"], project_dir
    )
    device = training_device(todo[0]) if todo else "cpu"
    measured = _measured_run_s(client, preset, variants, device)
    if measured is not None:
        plan.per_run_s = measured[0]
        plan.per_run_source = (
            f"median wall time of {measured[1]} finished {preset} run(s) on {device} "
            "in this MLflow store"
        )
    elif todo:
        plan.per_run_s, plan.per_run_source = estimate_run_s(todo[0])
    return plan


def chunk_lines(todo: list[Config], project_dir: Path) -> list[str]:
    """What the chunk store holds for the on-line runs in ``todo``, a line per seed: a seed
    whose chunks are all stored trains without synthesis; the chunks it lacks are made by the
    run's synthesis workers, or between its steps with ``data.online_workers = 0``."""
    root = online_store_root(project_dir)
    online = [c for c in todo if c.data.train_source == "online" and not c.data.root]
    if root is None or not online:
        return []
    out: list[str] = []
    seen: set[tuple] = set()
    for cfg in online:
        settings, chunk_size, n_chunks = online_chunks(cfg, packaged_classes())
        store = ChunkStore(root, settings, chunk_size)
        key = (store.key, cfg.seed, n_chunks, cfg.data.online_workers)
        if key in seen:
            continue
        seen.add(key)
        stored = store.stored(cfg.seed, n_chunks)
        line = f"chunks: seed {cfg.seed}: {stored:,} of {n_chunks:,} stored"
        if stored >= n_chunks:
            line += " (read, none synthesized)"
        elif cfg.data.online_workers == 0:
            line += (
                " (the rest synthesized in the training process, between its steps: "
                f"cloudpose prepare --preset {cfg.preset} --seeds N fills seeds 1..N on every "
                "core first)"
            )
        else:
            n = cfg.data.online_workers
            line += f" (the rest synthesized by the run's {n} worker{'s' if n > 1 else ''})"
        out.append(line)
    return out


def finished_run_any_data(client, cfg: Config):
    """The newest finished, evaluated run of exactly ``cfg`` on any data, or None (what a
    report, which reads MLflow only, can use)."""
    for r in tracking.find_runs(client, variant=cfg.variant, preset=cfg.preset, seed=cfg.seed):
        if TEST_KEY in r.data.metrics and run_has_config(r, cfg):
            return r
    return None


def plan_group(
    group: str,
    preset: str,
    seeds: int | Iterable[int] = 3,
    project_dir: Path | None = None,
    *,
    overrides: dict | None = None,
    report: bool = True,
    out_dir: Path | None = None,
    only: Sequence[str] | None = None,
) -> Plan:
    """The plan of :func:`run_group`: the group's runs (its members, or those of ``only``),
    then its reports."""
    project_dir = (project_dir or Path.cwd()).resolve()
    plan = plan_runs(
        list(get_group(group).pick(only)),
        preset,
        seeds,
        title=f"ablation {group}/{preset}, seeds {_seed_text(seeds)}",
        project_dir=project_dir,
        overrides=overrides,
    )
    if report:
        out = out_dir or default_out_dir(project_dir, preset)
        note = f"then: the group's reports into {_shown(out, project_dir)}/"
        if out_dir is None:
            note += (
                f" (into runs/reports/{preset}/ instead if the store then lacks runs that "
                "the committed reports count: no committed result is replaced by fewer runs)"
            )
        plan.notes.append(note)
    return plan


def plan_masks(
    preset: str,
    seeds: int | Iterable[int] = 3,
    project_dir: Path | None = None,
    *,
    sources: Iterable[str] | None = None,
    out_dir: Path | None = None,
) -> Plan:
    """The plan of :func:`mask_ablation`: the shared-0 runs, then one evaluation per seed and
    mask source that is not logged yet (each ~ a run's evaluation)."""
    project_dir = (project_dir or Path.cwd()).resolve()
    sources = list(segmentation.SOURCES if sources is None else sources)
    plan = plan_runs(
        [segmentation.VARIANT],
        preset,
        seeds,
        title=f"mask ablation {preset}, seeds {_seed_text(seeds)}, sources {', '.join(sources)}",
        project_dir=project_dir,
    )
    client = tracking.setup(project_dir)
    cfg = resolve(segmentation.VARIANT, preset)
    each = cfg.data.test_frames * EVAL_S_PER_TEST_FRAME + RUN_OVERHEAD_S / 3
    logged = 0
    for r in plan.runs:
        metrics = client.get_run(r.run_id).data.metrics if r.run_id else {}
        todo = []
        for source in sources:
            name = segmentation.mask_source_evaluation_name(source)
            if f"{name}/ads_auc" in metrics and f"{name}_icp/ads_auc" in metrics:
                logged += 1
            elif r.run_id or name != TEST_KEY.split("/")[0]:  # a new run evaluates its own
                todo.append(source)
        if todo:
            label = f"{r.name} under {', '.join(todo)} masks, ~{format_seconds(each)} each"
            plan.evaluations.append((label, each * len(todo)))
    plan.notes.append(f"{logged} mask evaluation(s) logged before (skipped)")
    out = out_dir or default_out_dir(project_dir, preset)
    plan.notes.append(f"then: table_masks and occlusion_masks into {_shown(out, project_dir)}/")
    return plan


def missing_report_runs(
    variants: list[str], preset: str, seeds: int | Iterable[int], project_dir: Path | None = None
) -> list[str]:
    """Names of the runs a report of ``variants`` x ``seeds`` needs that the store lacks (a
    finished, evaluated run of the config on any data; the report reads MLflow only)."""
    client = tracking.setup((project_dir or Path.cwd()).resolve())
    return [
        run_name(v, preset, s)
        for v in variants
        for s in seed_list(seeds)
        if finished_run_any_data(client, resolve(v, preset, s)) is None
    ]


def _seed_text(seeds: int | Iterable[int]) -> str:
    s = seed_list(seeds)
    return (
        f"{s[0]}-{s[-1]}"
        if s == list(range(s[0], s[-1] + 1)) and len(s) > 1
        else ",".join(map(str, s))
    )


def _shown(path: Path, project_dir: Path) -> str:
    try:
        return str(Path(path).resolve().relative_to(project_dir))
    except ValueError:
        return str(path)
