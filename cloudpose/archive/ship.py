"""Shipping a trained network into the package (``cloudpose ship``): the weights and their
record beside them (``resources/pretrained/STEM.pt`` and ``STEM.json``; what they hold and how
``pretrained`` finds them: :mod:`cloudpose.store.pretrained`).

Half precision ships only where it keeps every pose of the check segments within
:data:`HALF_TOLERANCE_DEG`; a network a name answers to already is replaced only when asked
(:func:`check_replace`).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import torch

from cloudpose.data.keys import DataKey
from cloudpose.files import atomic_text, atomic_write
from cloudpose.store.pretrained import (
    HEADLINE,
    PRETRAINED,
    SHIPPED,
    SHIPPED_AS,
    describe_record,
    file_sha256,
    record_of,
)

HALF_TOLERANCE_DEG = 0.01
"""Half precision ships only if no pose it gives differs from the float32 network's by more
than this many degrees (and 0.01 mm)."""


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


def half_state(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """A network state with every floating tensor in float16 (integer buffers kept)."""
    return {k: v.half() if v.is_floating_point() else v for k, v in state.items()}


def pose_difference(a, b, valid: np.ndarray) -> tuple[float, float]:
    """Largest rotation (degrees) and translation (mm) difference between two
    :class:`~cloudpose.refine.Estimates` over the ``valid`` rows."""
    # lazy: geometry loads roma and with it sympy; store-pack and -unpack start without them
    from cloudpose.geometry.rigid import rotation_error_deg

    if not np.any(valid):
        return 0.0, 0.0
    rot = rotation_error_deg(a.R[valid], b.R[valid])
    dt = 1000 * np.linalg.norm(a.t[valid] - b.t[valid], axis=1)
    return float(rot.max()), float(dt.max())


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
    check_segments: list,
    half: bool = True,
    name: str = PRETRAINED,
    force: bool = False,
) -> Path:
    """Write ``stem.pt`` (weights and config) and ``stem.json`` (record, answering to ``name``)
    into ``out_dir``. With ``force``, the network ``name`` answered to there before is removed
    when its stem is another (:func:`check_replace`; without ``force`` one is refused).

    Half precision is kept only if, on every segment set of ``check_segments`` (pairs of a name
    and :class:`~cloudpose.data.segment_set.SegmentSet`), no pose differs from the float32
    network's by more than :data:`HALF_TOLERANCE_DEG` (and 0.01 mm); else float32 ships: the
    checkpoint's bytes as they are (one git blob with the run's stored checkpoint) when it
    holds only the network and its config. The record says which and by how much the poses
    differ.

    Returns:
        The weights file written.
    """
    # lazy: infer loads numba and scipy; store-pack and -unpack start without them
    from cloudpose.infer import estimate_poses, load_checkpoint

    if name not in SHIPPED:
        raise ValueError(f"unknown shipped network {name!r}; known: {', '.join(SHIPPED)}")
    replaced = check_replace(out_dir, stem, name, force=force, incoming=run_name)
    state = torch.load(checkpoint, map_location="cpu", weights_only=True)
    if not isinstance(state, dict) or "model" not in state or "config" not in state:
        raise ValueError(f"{checkpoint} is not a cloudpose checkpoint (keys 'model', 'config')")
    out_dir.mkdir(parents=True, exist_ok=True)
    full, cfg = load_checkpoint(checkpoint)
    dtype, worst = "float32", {}
    if half:
        trial = out_dir / f".{stem}.half.pt"
        torch.save({"model": half_state(state["model"]), "config": state["config"]}, trial)
        try:
            halved, _ = load_checkpoint(trial)
            for name, segs in check_segments:
                a = estimate_poses(full, segs, cfg.train.n_points)
                b = estimate_poses(halved, segs, cfg.train.n_points)
                worst[name] = pose_difference(a, b, np.asarray(segs.valid, dtype=bool))
        finally:
            trial.unlink(missing_ok=True)
        ok = all(r <= HALF_TOLERANCE_DEG and t <= 0.01 for r, t in worst.values())
        dtype = "float16" if ok else "float32"
    path = out_dir / f"{stem}.pt"
    if dtype == "float32" and set(state) == {"model", "config"}:
        # the checkpoint's own bytes: torch.save names the zip's root after the file, so a
        # save under another name would differ, and git would store the network twice
        atomic_write(path, lambda p: shutil.copyfile(checkpoint, p))
    else:
        weights = half_state(state["model"]) if dtype == "float16" else state["model"]
        atomic_write(path, lambda p: torch.save({"model": weights, "config": state["config"]}, p))
    record = {
        "run_name": run_name,
        "run_id": run_id,
        "data_key": data_key,
        "config_fingerprint": fingerprint,
        "dtype": dtype,
        "half_vs_float32": {
            k: {"max_rot_deg": r, "max_trans_mm": t} for k, (r, t) in worst.items()
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
