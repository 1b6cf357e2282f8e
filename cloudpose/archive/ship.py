"""Shipping a trained network into the package (``cloudpose ship``): the weights and their
record beside them (``resources/pretrained/STEM.pt`` and ``STEM.json``; what they hold and how
``pretrained`` finds them: :mod:`cloudpose.store.pretrained`).

The weights ship in the fewest bytes that keep every pose of the check set where float32 puts
it, by the rule a compact store keeps a run's checkpoint by
(:func:`cloudpose.archive.checkpoints.choose_form`): a shipped network and its run's packed
checkpoint are then the same bytes, one git blob. A network a name answers to already is
replaced only when asked (:func:`check_replace`).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import torch

from cloudpose.archive.checkpoints import PoseCheck, choose_form
from cloudpose.data.keys import DataKey
from cloudpose.files import atomic_text, atomic_write
from cloudpose.models.stored import FLOAT32, encode, to_bytes
from cloudpose.store.pretrained import (
    HEADLINE,
    PRETRAINED,
    SHIPPED,
    SHIPPED_AS,
    describe_record,
    file_sha256,
    record_of,
)


def check_replace(
    out_dir: Path, stem: str, name: str, *, force: bool, incoming: str = ""
) -> Path | None:
    """The record of the network that a ship of ``stem`` as ``name`` into ``out_dir`` replaces
    (the one ``name`` answers to there, or a pair of the same stem), or None.

    Raises:
        FileExistsError: there is one and not ``force``, naming it, ``incoming`` (what would
            replace it) and ``--force``.
    """
    if not out_dir.is_dir():
        return None
    answering = record_of(name, out_dir)
    same = out_dir / f"{stem}.json"
    present = next((p for p in (answering, same, same.with_suffix(".pt")) if p.is_file()), None)
    if present is None:
        return None
    record = present.with_suffix(".json")
    if not force:
        what = f"the network {name!r} answers to" if record == answering else "a network"
        held = describe_record(record) if record.is_file() else f"{present.name}, no record"
        instead = f" with {incoming}" if incoming else ""
        raise FileExistsError(
            f"{out_dir}: holds {what}, {held}; pass --force to replace it{instead}, or give "
            "--out another folder"
        )
    return record


def ship(
    checkpoint: Path,
    out_dir: Path,
    stem: str,
    *,
    run_name: str,
    run_id: str,
    data_key: DataKey,
    fingerprint: str,
    metrics: dict[str, float],
    command: str,
    check: PoseCheck | None,
    name: str = PRETRAINED,
    force: bool = False,
) -> Path:
    """Write ``stem.pt`` (weights and config) and ``stem.json`` (record, answering to ``name``)
    into ``out_dir``. With ``force``, the network ``name`` answered to there before is removed
    when its stem is another (:func:`check_replace`; without ``force`` one is refused).

    The weights take the first reduced form (float16, float24) under which no pose of
    ``check``'s set moves from the float32 network's by more than the archive's tolerances
    (:func:`~cloudpose.archive.checkpoints.choose_form`), else float32 (and float32 when
    ``check`` is None): the checkpoint's bytes as they are (one git blob with the run's stored
    checkpoint) when it holds only the network and its config. The record says which form
    and by how much each form tried moves the poses.

    Returns:
        The weights file written.
    """
    if name not in SHIPPED:
        raise ValueError(f"unknown shipped network {name!r}; known: {', '.join(SHIPPED)}")
    replaced = check_replace(out_dir, stem, name, force=force, incoming=run_name)
    state = torch.load(checkpoint, map_location="cpu", weights_only=True)
    if not isinstance(state, dict) or "model" not in state or "config" not in state:
        raise ValueError(f"{checkpoint} is not a cloudpose checkpoint (keys 'model', 'config')")
    form, changes, checked = FLOAT32, {}, 0
    if check is not None:
        form, changes, checked = choose_form(state, check)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"{stem}.pt"
    if form != FLOAT32:
        packed = to_bytes(encode(state, form))
        atomic_write(path, lambda p: p.write_bytes(packed))
    elif set(state) == {"model", "config"}:
        # the checkpoint's own bytes: torch.save names the zip's root after the file, so a
        # save under another name would differ, and git would store the network twice
        atomic_write(path, lambda p: shutil.copyfile(checkpoint, p))
    else:
        weights = {"model": state["model"], "config": state["config"]}
        atomic_write(path, lambda p: torch.save(weights, p))
    record = {
        "run_name": run_name,
        "run_id": run_id,
        "data_key": data_key,
        "config_fingerprint": fingerprint,
        "dtype": form,
        "pose_change": {
            "check_set": {"frames": check.name, "segments": checked} if check else None,
            **{k: {"max_rot_deg": r, "max_trans_mm": t} for k, (r, t) in changes.items()},
        },
        "metrics": {k: metrics[k] for k in HEADLINE if k in metrics},
        "sha256": file_sha256(path),
        "made_by": command,
        SHIPPED_AS: name,
    }
    atomic_text(out_dir / f"{stem}.json", json.dumps(record, indent=1) + "\n")
    if replaced is not None and replaced.stem != stem:  # one pair answers to the name
        replaced.with_suffix(".pt").unlink(missing_ok=True)
        replaced.unlink(missing_ok=True)
    return path
