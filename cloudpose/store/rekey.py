"""A store's runs brought to today's keys of the data they were made on.

Runs are found by the key of their data: the ``data`` tag of a training or baseline run
(:func:`cloudpose.data.dataset.data_fingerprint`) and ``eval/NAME/data`` of each evaluation
(the key of the segments it scored). The runner skips a run finished on the same key, and the
reports pool the runs of one key. When the definition of a key changes, the runs made before
carry keys that today's data no longer has, and neither finds them. That happened once for
every synthetic dataset: a PNG was keyed by its bytes, and Pillow's encoder (zlib-ng) compresses
the same pixels to other bytes on a CPU with other instructions, so one frame rendered on two
machines had two keys; a PNG is now keyed by its decoded image
(:func:`cloudpose.data.cache.content_digests`).

:func:`rekey_runs` gives the runs of a preset whose ``data`` is one of the keys named the key
of the preset's data today, and their evaluations of the test set and of the real development
frames today's keys of those segments; each old key stays on the run as ``rekeyed/data``,
``rekeyed/eval/NAME/data``. Which old keys mean the same data is for the caller to say and to
check: a key cannot be recomputed from anything but the bytes it was made from. One check: a
stored checkpoint evaluated on today's data (``cloudpose evaluate --run ID --data ROOT
--frames test``) against the metrics it logged, per instance (``eval/test/instances.csv``).

Renders on two CPUs can also differ in their pixels, not only in their bytes: Open3D's ray
casting (Embree) picks its kernels by the CPU's instructions, and a ray that grazes an edge can
hit on one and miss on the other. The ``cpu-online`` test set rendered on an AMD EPYC differs
from the one rendered on an Intel Xeon in 9 of its 2,053 segments, each by one point (of
4,600-34,000); shared-0's stored checkpoint scores the two alike (ADS AUC 91.255 / 91.255, the
same 48.6% within 10 degrees modulo symmetry, one instance across the 15-degree threshold).
Rekeying such data says the runs on either are comparable, not that they are bit-identical: a
seed trained on the other machine draws on-line segments that differ as rarely.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from cloudpose.data.cache import cache_key
from cloudpose.data.dataset import data_fingerprint, dataset_root, prepare_data
from cloudpose.data.keys import DataKey, same_data, same_data_keys
from cloudpose.data.layout import open_dataset, real_dev_root
from cloudpose.registry import resolve
from cloudpose.store import tracking
from cloudpose.store.instances import run_instance_table

REKEYED_PREFIX = "rekeyed/"
"""Tag prefix that keeps a key a run had before :func:`rekey_runs` replaced it."""


@dataclass(frozen=True)
class Rekeyed:
    """One tag of one run given a new key."""

    run_id: str
    run_name: str
    tag: str
    old: str
    new: str


def current_keys(preset: str, project_dir: Path) -> dict[str, DataKey]:
    """Today's keys of ``preset``'s data (it must exist: ``cloudpose prepare``): ``data`` (the
    fingerprint of train and test), ``test`` (the test segments), ``real`` (the packaged real
    development frames)."""
    cfg = resolve(preset=preset).data
    return {
        "data": data_fingerprint(cfg, project_dir),
        "test": cache_key(open_dataset(dataset_root(cfg, project_dir)), "test", cfg),
        "real": cache_key(open_dataset(real_dev_root()), "all", cfg),
    }


def rekey_runs(
    preset: str, old: Iterable[str], project_dir: Path | None = None, *, dry_run: bool = False
) -> list[Rekeyed]:
    """Give the runs of ``preset`` whose ``data`` tag is (or was, before an earlier rekey) one of
    ``old`` today's keys.

    Args:
        preset: the preset whose runs to rekey (tag ``preset``).
        old: the earlier keys of the same data (``data`` tags, 16 hex digits or a prefix of at
            least 8).
        project_dir: the folder of the store and the data (cwd).
        dry_run: say what would change, change nothing.

    Returns:
        Every tag changed (or, with ``dry_run``, to change). An evaluation whose old key is
        neither the run's own test key nor its real-frames key (other masks, other data)
        keeps its tag.

    Raises:
        ValueError: an old key shorter than 8 digits, or today's key among them.
        FileNotFoundError: the preset's data is missing (today's keys are made from it).
    """
    project_dir = Path(project_dir or Path.cwd()).resolve()
    old = [k.strip() for k in old]
    if any(len(k) < 8 for k in old):
        raise ValueError(f"old keys {old}: give at least 8 hex digits of each")
    try:
        data_keys = current_keys(preset, project_dir)
    except FileNotFoundError as exc:
        raise FileNotFoundError(
            f"--preset {preset}: {' '.join(str(exc).split())}; store-rekey computes today's "
            "keys (those it gives the runs, and a --dry-run prints) from the preset's data "
            f"itself: prepare it first (cloudpose prepare --preset {preset})"
        ) from exc
    if any(data_keys["data"].startswith(k) for k in old):
        raise ValueError(f"{data_keys['data']} is today's key of the {preset} data, not an old one")
    client = tracking.setup(project_dir)
    changes: list[Rekeyed] = []
    for run in tracking.find_runs(client, preset=preset, status=None):
        tags = run.data.tags
        # a run rekeyed while it ran logs its evaluations' keys later, by the old definition
        was = (tags.get("data", ""), tags.get(REKEYED_PREFIX + "data", ""))
        if not any(w.startswith(k) for w in was for k in old):
            continue
        wanted = {"data": data_keys["data"]}
        own = {
            tags[f"eval/{s}/data"]: data_keys[s]
            for s in ("test", "real")
            if f"eval/{s}/data" in tags
        }
        for tag, value in tags.items():
            if tag.startswith("eval/") and tag.endswith("/data") and value in own:
                wanted[tag] = own[value]
        for tag, new in wanted.items():
            if tags.get(tag) == new:
                continue
            changes.append(Rekeyed(run.info.run_id, run.info.run_name, tag, tags[tag], new))
            if not dry_run:
                if REKEYED_PREFIX + tag not in tags:  # a second rekey keeps the first key
                    client.set_tag(run.info.run_id, REKEYED_PREFIX + tag, tags[tag])
                client.set_tag(run.info.run_id, tag, new)
    return changes


SAME_POINT_SHARE = 0.001
"""Largest change of a segment's point count (a share of its points) that still counts as the
same segment rendered on another CPU: a ray grazing an edge hits on one and misses on the other,
one point of thousands."""


@dataclass(frozen=True)
class SegmentComparison:
    """A run's test segments (its instance table) against the same preset's made here.

    Attributes:
        run_id: the run compared.
        keys: ``(run's, today's)`` for ``data`` (the run's data) and ``test`` (the test
            segments).
        instances: ``(run's, today's)`` instance counts.
        unmatched: instances in one and not the other, by (frame, instance).
        other_class: matched instances of another class.
        other_count: matched instances with another point count.
        largest_share: the largest change of a point count, a share of the run's count.
    """

    run_id: str
    keys: dict[str, tuple[str, str]]
    instances: tuple[int, int]
    unmatched: int
    other_class: int
    other_count: int
    largest_share: float

    @property
    def same(self) -> bool:
        """The same frames and instances, classes, and point counts within
        :data:`SAME_POINT_SHARE`."""
        return (
            self.unmatched == 0 and self.other_class == 0 and self.largest_share <= SAME_POINT_SHARE
        )

    def entry(self, what: str) -> str:
        """What ``same_data.toml`` needs to say so: a ``[[same]]`` entry per kind of key not
        yet listed as the same, or the key to add to the entry that lists the run's; empty when
        every key is already the same data."""
        out = []
        for kind, label in (("data", "data"), ("test", "segments")):
            old, new = self.keys[kind]
            if same_data(old, new):
                continue
            if len(same_data_keys(old)) > 1:  # a key has one entry: add the new key to it
                out.append(f'add "{new}" to the keys of the entry that lists "{old}"\n')
            else:
                out.append(
                    f'[[same]]\nkind = "{label}"\nwhat = "{what}"\nkeys = ["{old}", "{new}"]\n'
                )
        return "\n".join(out)


def compare_test_segments(run_id: str, project_dir: Path | None = None) -> SegmentComparison:
    """Compare the test segments a run was evaluated on with those of its preset made here
    (rendered first if they are not), instance by instance: whether a data key that differs
    names the same data (e.g. frames rendered on another CPU), before listing both in
    :data:`cloudpose.data.keys.SAME_DATA_FILE` or rekeying.

    Raises:
        ValueError: the run has no preset or no test evaluation.
    """
    project_dir = Path(project_dir or Path.cwd()).resolve()
    client = tracking.setup(project_dir)
    run = client.get_run(run_id)
    tags = run.data.tags
    if not tags.get("preset") or "eval/test/data" not in tags:
        raise ValueError(
            f"run {run_id}: expected a run of a preset with a test evaluation (tags preset and "
            "eval/test/data)"
        )
    cfg = resolve(preset=tags["preset"]).data
    here = prepare_data(cfg, project_dir, progress=False)
    seg = here.test
    today = pd.DataFrame(
        {
            "frame_id": seg.frame_id.astype(str),
            "instance": seg.instance.astype(np.int64),
            "cls_today": seg.cls_id.astype(np.int64),
            "points_today": seg.count.astype(np.int64),
        }
    )
    table = run_instance_table(client, run, "test")
    theirs = pd.DataFrame(
        {
            "frame_id": table["frame_id"].astype(str),
            "instance": table["instance"].astype(np.int64),
            "cls_run": table["cls_id"].astype(np.int64),
            "points_run": table["points"].astype(np.int64),
        }
    )
    both = today.merge(theirs, on=["frame_id", "instance"], how="outer", indicator=True)
    matched = both[both["_merge"] == "both"]
    change = (matched["points_today"] - matched["points_run"]).abs()
    share = change / matched["points_run"].clip(lower=1)
    return SegmentComparison(
        run_id=run_id,
        keys={
            "data": (tags.get("data", ""), here.data_key),
            "test": (tags["eval/test/data"], seg.data_key),
        },
        instances=(len(theirs), len(today)),
        unmatched=int((both["_merge"] != "both").sum()),
        other_class=int((matched["cls_today"] != matched["cls_run"]).sum()),
        other_count=int((change > 0).sum()),
        largest_share=float(share.max()) if len(share) else 0.0,
    )
