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

from cloudpose.data.keys import DataKey
from cloudpose.store import tracking

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
    from cloudpose.data.cache import cache_key
    from cloudpose.data.dataset import data_fingerprint, dataset_root
    from cloudpose.data.layout import open_dataset, real_dev_root
    from cloudpose.registry import resolve

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
    """
    project_dir = Path(project_dir or Path.cwd()).resolve()
    old = [k.strip() for k in old]
    if any(len(k) < 8 for k in old):
        raise ValueError(f"old keys {old}: give at least 8 hex digits of each")
    data_keys = current_keys(preset, project_dir)
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
