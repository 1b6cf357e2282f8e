"""Reading the finished, evaluated runs of a preset out of MLflow for the reports.

A report compares runs trained on the same data: of the preset's finished runs that carry test
metrics, it keeps those of one data key (the one most (variant, seed) pairs were trained
on, ties to the newest; or the one asked for) and, per (variant, seed), the newest run.
"""

from __future__ import annotations

import math
import warnings
from collections import Counter
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd

from cloudpose.baselines.base import is_current
from cloudpose.data.keys import DataKey, canonical_key, same_data
from cloudpose.store import instances, tracking
from cloudpose.store.metric_names import DetailReader, detail_kind
from cloudpose.store.runs import is_preset_config

TEST_KEY = "test/ads_auc"
"""A run counts as evaluated when it has this metric."""


@dataclass
class RunRecord:
    """One finished, evaluated training run as the reports need it."""

    run_id: str
    variant: str
    seed: int
    preset: str
    data_key: DataKey
    git_commit: str
    start_time: int
    params: dict[str, str]
    metrics: dict[str, float]
    artifact_uri: str = ""
    subsample: str = "all"  # a baseline run on an evenly spaced subsample: its size (tag)
    client: object = field(repr=False, default=None)
    _cache: dict = field(repr=False, default_factory=dict)

    @property
    def info(self) -> SimpleNamespace:
        """``run_id`` and ``artifact_uri``, as an MLflow run's ``info`` holds them: what the
        artifact readers (:func:`cloudpose.store.instances.artifact_file`) read of a run."""
        return SimpleNamespace(run_id=self.run_id, artifact_uri=self.artifact_uri)

    @property
    def parameters(self) -> int | None:
        """Parameter count of the network (param ``model.parameters``), if logged."""
        v = self.params.get("model.parameters")
        return int(v) if v not in (None, "") else None

    def metric(self, key: str) -> float:
        """Value of a metric; NaN when the run does not have it. A per-class or per-video key
        (``test_icp/class/025_mug/ads_auc``) is read from the run's detail table where its
        metrics lack it (:class:`cloudpose.store.metric_names.DetailReader`)."""
        if key in self.metrics or detail_kind(key) is None:
            return float(self.metrics.get(key, math.nan))
        if "detail" not in self._cache:
            self._cache["detail"] = DetailReader(
                self.client, self.run_id, self.artifact_uri, self.metrics
            )
        return self._cache["detail"].get(key)

    def instances(self, name: str = "test") -> pd.DataFrame | None:
        """The per-instance table ``eval/{name}/instances.parquet`` (or, logged before, its
        ``instances.csv``), or None if it is missing.

        Raises:
            CorruptFileError: the table is empty, truncated (its last row cut, or fewer rows
                than the run's metric ``{name}/count``) or lacks the columns an evaluation
                writes; the message names the file, the run and the command that writes it
                again.
        """
        key = ("instances", name)
        if key not in self._cache:
            rel = instances.artifact_names(name)[0]
            with instances.artifact_file(self.client, self, rel, missing_ok=True) as path:
                self._cache[key] = None if path is None else self._checked(path, name)
        return self._cache[key]

    def _checked(self, path: str | Path, name: str) -> pd.DataFrame:
        count = self.metrics.get(tracking.metric_key(name, "count"))
        return instances.read_instance_table(
            path, name, self.run_id, self.variant, self.seed, self.preset, count
        )

    def history(self, key: str) -> pd.Series:
        """Per-epoch values of ``key`` (index: epoch); empty if never logged."""
        return metric_history(self.client, self.run_id, key)


def metric_history(client, run_id: str, key: str) -> pd.Series:
    """Per-step values of metric ``key`` of a run (index: step; a step logged twice keeps the
    later value); empty if never logged."""
    hist = client.get_metric_history(run_id, key)
    s = pd.Series({m.step: m.value for m in sorted(hist, key=lambda m: m.timestamp)})
    return s.sort_index().astype(float)


@dataclass
class RunSet:
    """The runs one report is rendered from."""

    preset: str
    data_key: DataKey | None
    records: list[RunRecord]
    ignored: int = 0
    """Runs of the same preset left out because they were trained on other data."""

    def of(self, variant: str) -> list[RunRecord]:
        """Runs of ``variant``, sorted by seed."""
        return sorted((r for r in self.records if r.variant == variant), key=lambda r: r.seed)

    def values(self, variant: str, key: str) -> dict[int, float]:
        """seed -> metric ``key`` for ``variant`` (seeds where the metric is finite)."""
        out = {r.seed: r.metric(key) for r in self.of(variant)}
        return {s: v for s, v in out.items() if np.isfinite(v)}

    @cached_property
    def variants(self) -> list[str]:
        return sorted({r.variant for r in self.records})

    def subset(self, variants) -> RunSet:
        """The runs of the given variants only."""
        keep = set(variants)
        return RunSet(
            self.preset, self.data_key, [r for r in self.records if r.variant in keep], self.ignored
        )

    def lacking_instances(self) -> list[RunRecord]:
        """The runs without their test instance table (:meth:`RunRecord.instances`)."""
        return [r for r in self.records if r.instances() is None]

    def with_instances(self) -> RunSet:
        """The runs that have their test instance table: those a per-instance figure (the
        occlusion plots) is drawn from, and so its provenance."""
        lacking = {r.run_id for r in self.lacking_instances()}
        kept = [r for r in self.records if r.run_id not in lacking]
        return RunSet(self.preset, self.data_key, kept, self.ignored)

    @property
    def seeds(self) -> list[int]:
        return sorted({r.seed for r in self.records})

    @property
    def commits(self) -> list[str]:
        return sorted({r.git_commit for r in self.records})

    def data_label(self) -> str:
        """Where the runs' data came from, in words, with the data key."""
        if not self.records:
            return "no runs"
        roots = {r.params.get("data.root", "") for r in self.records}
        short = (self.data_key or "?")[:10]
        if roots <= {""}:
            seeds = {r.params.get("data.synth_seed", "?") for r in self.records}
            return (
                f"synthetic YCB-Video-layout scenes (synth seed {','.join(sorted(seeds))}, data "
                f"{short})" + self._borrowed()
            )
        names = ", ".join(sorted(Path(r).name or r for r in roots))
        return f"{names} (data {short})" + self._borrowed()

    def _borrowed(self) -> str:
        other = sorted({r.preset for r in self.records if r.preset != self.preset})
        return f"; baselines of preset {', '.join(other)} on the same data" if other else ""


def _current(run) -> bool:
    """A training run of its preset's own config, or a baseline run of today's settings."""
    if run.data.tags.get("kind") == "baseline":
        return is_current(run)
    return is_preset_config(run)


def _record(run, key: tuple[str, int], preset: str, data_key: DataKey, client) -> RunRecord:
    tags = run.data.tags
    return RunRecord(
        run_id=run.info.run_id,
        variant=key[0],
        seed=key[1],
        preset=preset,
        data_key=data_key,
        git_commit=tags.get("git_commit", "unknown"),
        start_time=run.info.start_time or 0,
        params=dict(run.data.params),
        metrics=dict(run.data.metrics),
        artifact_uri=run.info.artifact_uri or "",
        subsample=tags.get("subsample", "all"),
        client=client,
    )


def load_runs(
    preset: str,
    *,
    data_key: DataKey | None = None,
    client=None,
    project_dir: Path | None = None,
) -> RunSet:
    """Finished runs of ``preset`` with test metrics, one per (variant, seed), on one dataset;
    a classical baseline (variant ``baseline-*``) that ``preset`` has not run is taken from
    another preset's runs on the same data (its record names that preset).

    Args:
        preset: the training preset (tag ``preset``).
        data_key: the data key to keep (tag ``data``; with every key of the same data,
            :func:`cloudpose.data.keys.same_data`); default the one with the most (variant,
            seed) pairs.
        client: an ``MlflowClient``; default :func:`cloudpose.store.tracking.setup` of ``project_dir``.
        project_dir: folder of the default MLflow store (cwd).
    """
    client = client or tracking.setup(project_dir)
    runs = tracking.find_runs(client, preset=preset)
    runs = [
        r
        for r in runs
        if r.data.tags.get("variant") and r.data.tags.get("seed") and TEST_KEY in r.data.metrics
    ]
    # a run with overrides (--set, --epochs) or from an edited preset is another config
    other = [r for r in runs if not _current(r)]
    if other:
        warnings.warn(
            f"{len(other)} finished run(s) tagged preset {preset!r} were made with another "
            "config (overrides or an older preset) and are left out of the report",
            stacklevel=2,
        )
        runs = [r for r in runs if _current(r)]
    if not runs:
        return RunSet(preset, data_key, [])
    if data_key is None:
        pairs: Counter[DataKey] = Counter()
        newest: dict[DataKey, int] = {}
        for r in runs:
            run_key = canonical_key(r.data.tags.get("data", ""))
            pairs[run_key] += 1
            newest[run_key] = max(newest.get(run_key, 0), r.info.start_time or 0)
        data_key = max(pairs, key=lambda k: (pairs[k], newest[k]))
    data_key = canonical_key(data_key)  # runs on every key of the same data count
    chosen: dict[tuple[str, int], RunRecord] = {}
    ignored = 0
    for r in runs:  # newest first
        tags = r.data.tags
        if not same_data(tags.get("data", ""), data_key):
            ignored += 1
            continue
        key = (tags["variant"], int(tags["seed"]))
        if key in chosen:
            continue
        chosen[key] = _record(r, key, preset, data_key, client)
    # a classical baseline sees only the test segments: one run serves every preset of the
    # same data, so a preset without its own takes another's
    for r in tracking.find_runs(client, data=data_key, extra_filter="tags.kind = 'baseline'"):
        tags = r.data.tags
        if tags.get("preset") == preset or TEST_KEY not in r.data.metrics or not _current(r):
            continue
        key = (tags.get("variant", ""), int(tags.get("seed", 0) or 0))
        if key not in chosen:
            chosen[key] = _record(r, key, tags.get("preset", "?"), data_key, client)
    if ignored:
        warnings.warn(
            f"{ignored} finished run(s) of preset {preset!r} were trained on other data than "
            f"{data_key[:10]} and are left out of the report",
            stacklevel=2,
        )
    return RunSet(preset, data_key, list(chosen.values()), ignored)
