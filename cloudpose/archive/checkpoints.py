"""A run's checkpoint as a compact store keeps it: in fewer bytes where its poses do not move.

A float32 checkpoint of the default network is 6.5 MB, and zlib (git's) takes 8% off it. The
compact form (:mod:`cloudpose.archive.compact`) stores a kept checkpoint ``NAME.pt``:

- **as it is** when its bytes are a shipped network's (``resources/pretrained/*.pt``: git
  stores the two as one blob), or when it is not a cloudpose checkpoint;
- else in the first form of :data:`~cloudpose.models.stored.REDUCED` (``NAME.fp16.pt``, float16;
  ``NAME.f24.pt``, float24: :mod:`cloudpose.models.stored`) under which no pose of the check set
  (:class:`PoseCheck`: the 61 packaged real development frames' segments) moves by more than
  :data:`TOLERANCE_DEG` degrees (geodesic angle) or :data:`TOLERANCE_MM` millimetres from the
  float32 network's (:func:`choose_form`, the rule ``cloudpose ship`` follows too, so a shipped
  network and its run's packed checkpoint are the same bytes);
- else as it is (float32).

Beside a checkpoint that was checked goes its record, ``NAME.precision.json``: the form, the
largest pose change each form tried gave, the check set, the original's SHA-256 and the digest
of the float32 state that unpacking gives (:func:`state_digest`).

Unpacking (:func:`unpack_checkpoint`) writes ``NAME.pt`` back in float32, the same keys and
dtypes as the original, the values as rounded, so every reader (``evaluate --run``,
``stress``, ``mlflow-ui``) loads it as before; the record is an artifact beside it. Packing
such a store again finds the record, sees that the checkpoint is the one it describes (the
digest) and writes the same form and record without checking again: rounding is idempotent,
so the packed file holds the same tensors.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import tempfile
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from cloudpose.conventions import resource_path
from cloudpose.data.dataset import folder_segments
from cloudpose.data.layout import open_dataset, real_dev_root
from cloudpose.data.segments import SegmentWarning
from cloudpose.files import CorruptFileError, why
from cloudpose.geometry.rigid import rotation_error_deg
from cloudpose.infer import estimate_poses, load_checkpoint
from cloudpose.models.stored import (
    FLOAT32,
    FORM_KEY,
    REDUCED,
    decode,
    encode,
    round_trip,
    to_bytes,
)

RECORD_SUFFIX = ".precision.json"
"""Ending of a checkpoint's record (``model.pt`` -> ``model.precision.json``)."""

TOLERANCE_DEG = 0.01
"""Largest rotation change (degrees, geodesic) a form may give a pose of the check set."""

TOLERANCE_MM = 0.01
"""Largest translation change (millimetres) a form may give a pose of the check set."""

REAL_FRAMES = "real development frames"
"""Name of :class:`PoseCheck`'s default check set (the packaged real frames' segments)."""

_CHECKPOINT = ".pt"


def record_name(checkpoint: str) -> str:
    """``NAME.precision.json`` of the checkpoint ``NAME.pt``."""
    return checkpoint.removesuffix(_CHECKPOINT) + RECORD_SUFFIX


def packed_form(name: str) -> str | None:
    """The form of a packed checkpoint's file name (``model.f24.pt`` -> ``float24``), else None."""
    return next((form for form, end in REDUCED.items() if name.endswith(end)), None)


def unpacked_name(name: str) -> str:
    """``NAME.pt`` of a packed checkpoint's file name ``NAME.fp16.pt`` or ``NAME.f24.pt``."""
    form = packed_form(name)
    return name if form is None else name.removesuffix(REDUCED[form]) + _CHECKPOINT


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def shipped_digests(folder: Path | None = None) -> set[str]:
    """SHA-256 of every shipped network's weights (``resources/pretrained/*.pt``)."""
    folder = folder or resource_path("pretrained")
    return {_sha256(p.read_bytes()) for p in sorted(Path(folder).glob(f"*{_CHECKPOINT}"))}


# -- forms ---------------------------------------------------------------------------------


def state_digest(ckpt: Mapping[str, Any]) -> str:
    """SHA-256 of a checkpoint's values: every state tensor's key, dtype, shape and bytes, and
    the other entries as sorted JSON (the same for the same values, whatever file holds
    them)."""
    h = hashlib.sha256()
    for key, value in ckpt["model"].items():
        h.update(key.encode() + b"\0")
        if isinstance(value, torch.Tensor):
            t = value.detach().cpu().contiguous()
            h.update(f"{t.dtype}{tuple(t.shape)}".encode())
            h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
        else:
            h.update(repr(value).encode())
    rest = {k: v for k, v in ckpt.items() if k not in ("model", FORM_KEY)}
    h.update(json.dumps(rest, sort_keys=True, default=repr).encode())
    return h.hexdigest()


def load(path: Path) -> dict[str, Any] | None:
    """A checkpoint file's content (tensors and plain data only), or None when it is not a
    cloudpose checkpoint (keys ``model``, ``config``)."""
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception:  # a torn file, a foreign or unsafe pickle: not ours to reduce
        return None
    if not isinstance(obj, dict) or not {"model", "config"} <= set(obj):
        return None
    if not isinstance(obj["model"], Mapping):
        return None
    return obj


# -- the check ----------------------------------------------------------------------------


@dataclass
class PoseCheck:
    """The poses a checkpoint's network gives on a check set, to compare forms by.

    Args:
        project_dir: the project whose ``data/cache`` holds the check set's segments (as
            ``evaluate`` caches them).
        segments: a fixed :class:`~cloudpose.data.segment_set.SegmentSet` to check on
            instead of the real frames (tests).
        name: what the check set is, for the record.
    """

    project_dir: Path | None = None
    segments: Any = None
    name: str = REAL_FRAMES
    _sets: dict = field(default_factory=dict, repr=False)

    def segment_set(self, cfg):
        """The check set's segments under the data settings of ``cfg`` (a Config)."""
        if self.segments is not None:
            return self.segments
        if cfg.data not in self._sets:
            with warnings.catch_warnings():  # instances without points: misses, not checked
                warnings.simplefilter("ignore", SegmentWarning)
                self._sets[cfg.data] = folder_segments(
                    open_dataset(real_dev_root()), "all", cfg.data, self.project_dir, False
                )
        return self._sets[cfg.data]

    def poses(self, ckpt: Mapping[str, Any]) -> tuple[Any, np.ndarray]:
        """(:class:`~cloudpose.infer.Estimates`, valid rows) of ``ckpt``'s network on the set,
        loaded as every reader loads a checkpoint (:func:`cloudpose.infer.load_checkpoint`)."""
        with tempfile.TemporaryDirectory(prefix="cloudpose-check-") as tmp:
            path = Path(tmp) / "model.pt"
            path.write_bytes(to_bytes(ckpt))
            net, cfg = load_checkpoint(path)
        segs = self.segment_set(cfg)
        return estimate_poses(net, segs, cfg.train.n_points), np.asarray(segs.valid, bool)


def pose_difference(a, b, valid: np.ndarray) -> tuple[float, float]:
    """Largest rotation (degrees) and translation (mm) difference between two
    :class:`~cloudpose.refine.Estimates` over the ``valid`` rows."""
    if not np.any(valid):
        return 0.0, 0.0
    rot = rotation_error_deg(a.R[valid], b.R[valid])
    dt = 1000 * np.linalg.norm(a.t[valid] - b.t[valid], axis=1)
    return float(rot.max()), float(dt.max())


def within(change: tuple[float, float]) -> bool:
    """Whether a (degrees, millimetres) pose change is within the tolerances."""
    rot, trans = change
    return rot <= TOLERANCE_DEG and trans <= TOLERANCE_MM


def choose_form(
    ckpt: Mapping[str, Any], check: PoseCheck
) -> tuple[str, dict[str, tuple[float, float]], int]:
    """The first form of :data:`REDUCED` whose round trip keeps every pose of the check set
    within the tolerances, else :data:`FLOAT32`; with the largest change each form tried gave
    (degrees, millimetres) and the number of segments checked."""
    base, valid = check.poses(ckpt)
    changes = {}
    for form in REDUCED:
        est, _ = check.poses(round_trip(ckpt, form))
        changes[form] = pose_difference(base, est, valid)
        if within(changes[form]):
            return form, changes, int(valid.sum())
    return FLOAT32, changes, int(valid.sum())


# -- packing and unpacking ------------------------------------------------------------------


@dataclass(frozen=True)
class Packed:
    """What :func:`pack_checkpoint` wrote: the file and, for a checked checkpoint, its record."""

    file: str
    record: dict[str, Any] | None = None


def _reusable(record_path: Path, ckpt: Mapping[str, Any]) -> dict[str, Any] | None:
    """The record beside a checkpoint when it describes this checkpoint as unpacked (its
    digest), else None (no record, another checkpoint's, or unreadable)."""
    if not record_path.is_file():
        return None
    try:
        record = json.loads(record_path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError):
        return None
    if not isinstance(record, dict) or record.get("stored_as") not in (*REDUCED, FLOAT32):
        return None
    return record if record.get("unpacked_digest") == state_digest(ckpt) else None


def pack_checkpoint(
    src: Path,
    dest: Path,
    check: PoseCheck | None,
    shipped: set[str] | None = None,
    made_by: str = "cloudpose store-pack",
) -> Packed:
    """Write the checkpoint ``src`` (``NAME.pt``) into the folder ``dest`` as the compact form
    keeps it (the module's docstring): its bytes, or a packed file and its record.

    Args:
        src: a run's checkpoint artifact.
        dest: the folder to write into (created).
        check: the pose check new forms are chosen by; None keeps every checkpoint float32
            (a record beside ``src`` that describes it is still followed).
        shipped: SHA-256 of the shipped networks' weights (default :func:`shipped_digests`).
        made_by: the command, for the record.
    """
    dest.mkdir(parents=True, exist_ok=True)
    data = src.read_bytes()
    shipped = shipped_digests() if shipped is None else shipped
    ckpt = None if _sha256(data) in shipped else load(src)
    if ckpt is None or FORM_KEY in ckpt:
        shutil.copyfile(src, dest / src.name)
        return Packed(src.name)
    record = _reusable(src.parent / record_name(src.name), ckpt)
    if record is None and check is None:
        shutil.copyfile(src, dest / src.name)
        return Packed(src.name)
    if record is None:
        try:
            form, changes, n = choose_form(ckpt, check)
        except ValueError as exc:  # a config this version cannot build: kept as it is
            warnings.warn(f"{src}: kept float32, its network was not checked ({exc})", stacklevel=2)
            shutil.copyfile(src, dest / src.name)
            return Packed(src.name)
        unpacked = ckpt if form == FLOAT32 else round_trip(ckpt, form)
        record = {
            "checkpoint": src.name,
            "stored_as": form,
            "file": src.name
            if form == FLOAT32
            else src.name.removesuffix(_CHECKPOINT) + REDUCED[form],
            "max_pose_change": {f: {"rot_deg": r, "trans_mm": t} for f, (r, t) in changes.items()},
            "tolerance": {"rot_deg": TOLERANCE_DEG, "trans_mm": TOLERANCE_MM},
            "check_set": {"frames": check.name, "segments": n},
            "float32_sha256": _sha256(data),
            "unpacked_digest": state_digest(unpacked),
            "made_by": made_by,
        }
    form = record["stored_as"]
    if form == FLOAT32:
        shutil.copyfile(src, dest / src.name)
    else:
        (dest / record["file"]).write_bytes(to_bytes(encode(ckpt, form)))
    text = json.dumps(record, indent=1, sort_keys=True) + "\n"
    (dest / record_name(src.name)).write_text(text, encoding="utf-8")
    return Packed(record["file"], record)


def unpack_checkpoint(packed: Path, target: Path) -> Path:
    """Write the float32 checkpoint of the packed file ``packed`` to ``target`` (a file).

    Raises:
        CorruptFileError: ``packed`` does not load, or is not a checkpoint in the form its
            name says (:func:`decode` cannot read it); nothing is written.
    """
    form = packed_form(Path(packed).name) or "packed"
    try:
        obj = torch.load(packed, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises RuntimeError, UnpicklingError, EOFError, ...
        raise CorruptFileError(
            packed, f"not a readable {form} checkpoint (torch.load: {_short(why(exc))})"
        ) from exc
    if not isinstance(obj, dict) or FORM_KEY not in obj or "model" not in obj:
        raise CorruptFileError(
            packed, f"not a {form} checkpoint: no {FORM_KEY!r} and 'model' entries"
        )
    try:
        ckpt = decode(obj)
    except (KeyError, TypeError, ValueError, IndexError, AttributeError, RuntimeError) as exc:
        raise CorruptFileError(packed, f"not a readable {form} checkpoint ({why(exc)})") from exc
    target.write_bytes(to_bytes(ckpt))
    return target


def _short(text: str, limit: int = 120) -> str:
    return text if len(text) <= limit else text[:limit] + "..."


def same_packed(new: Path, old: Path) -> bool:
    """Whether two packed checkpoint files hold the same form and values (another torch
    version may write other bytes for them)."""
    try:
        a, b = (torch.load(p, map_location="cpu", weights_only=True) for p in (new, old))
    except Exception:  # a damaged old file: written again
        return False
    if not all(isinstance(x, dict) and FORM_KEY in x for x in (a, b)):
        return False
    if a[FORM_KEY] != b[FORM_KEY]:
        return False
    return state_digest(a) == state_digest(b)
