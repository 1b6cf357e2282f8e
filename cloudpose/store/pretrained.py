"""The shipped network: a trained shared-0 of the default preset inside the package, so a fresh
clone predicts and evaluates without training.

``pretrained`` names it wherever a checkpoint or run is asked for (``cloudpose predict
--checkpoint pretrained``, ``cloudpose evaluate --run pretrained --real``). The package holds
the weights (``resources/pretrained/STEM.pt``: the network's state in half precision, when
that keeps every pose of the real development frames and of the synthetic test frames within
:data:`HALF_TOLERANCE_DEG`, and its resolved config) and a record beside them
(``STEM.json``: the MLflow run it was taken from, its data key and config fingerprint, the
metrics that run logged, the weights' SHA-256, the command that made both and the name it
answers to). STEM is what the file holds, ``variant_preset_seedS`` (:func:`file_stem`).
``cloudpose ship --run RUN`` writes the pair from a finished run (:func:`ship`), and writes
over the network a name answers to only when asked (``--force``).
"""

from __future__ import annotations

import hashlib
import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from cloudpose.conventions import resource_path
from cloudpose.data.keys import DataKey
from cloudpose.files import atomic_text, atomic_write
from cloudpose.registry import DEFAULT_PRESET

PRETRAINED = "pretrained"
"""The name of the shipped network wherever a checkpoint or run is asked for."""

SHIPPED = {PRETRAINED: "shared-0_cpu-online_seed1"}
"""Name -> the stem of its files under ``resources/pretrained`` when no record there names
it (``shipped_as``): the network the package ships."""

SHIPPED_AS = "shipped_as"
"""Field of a record: the name (a key of :data:`SHIPPED`) its network answers to."""

SHOWN = ("test/ads_auc", "test_icp/ads_auc", "real/ads_auc", "real_icp/ads_auc")
"""The run's metrics :func:`describe_run` names: ADS AUC (0-1) on its synthetic test set and on
the real development frames, without and with ICP."""

HALF_TOLERANCE_DEG = 0.01
"""Half precision ships only if no pose it gives differs from the float32 network's by more
than this many degrees (and 0.01 mm)."""

HEADLINE = tuple(
    f"{split}{icp}/{key}"
    for split in ("test", "real")
    for icp in ("", "_icp")
    for key in ("ads_auc", "ad_auc", "rot_sym_lt_10deg", "trans_lt_1cm", "count")
)
"""The run's metrics copied into the record (those it logged of these)."""


@dataclass(frozen=True)
class Shipped:
    """A shipped network: its weights file and the record written beside it."""

    name: str
    path: Path
    info: dict[str, Any]

    def describe(self) -> str:
        """One line: which run it is and where it came from."""
        i = self.info
        return (
            f"{self.name}: {i['run_name']} (MLflow run {i['run_id'][:8]}, data {i['data_key'][:10]}, "
            f"{i['dtype']} weights, {self.path.name})"
        )


def shipped_folder() -> Path:
    """The package's folder of shipped networks (``resources/pretrained``)."""
    return resource_path("pretrained")


def file_stem(run_name: str) -> str:
    """The file stem of a network trained as ``run_name`` (``shared-0/cpu-online/seed1`` ->
    ``shared-0_cpu-online_seed1``; a ``+CONFIG`` of a run with overrides is kept, ``_CONFIG``)."""
    return run_name.replace("/", "_").replace("+", "_")


def describe_run(run_name: str, preset: str, metrics: dict[str, float]) -> str:
    """One line: the run, its preset and its metrics of :data:`SHOWN` (0-1; those not logged
    are named so)."""
    shown = ", ".join(f"{k} {metrics[k]:.3f}" if k in metrics else f"{k} not logged" for k in SHOWN)
    other = "" if preset == DEFAULT_PRESET else f", not the default {DEFAULT_PRESET}"
    return f"{run_name} (preset {preset}{other}): {shown}"


def is_pretrained(name: str | Path | None) -> bool:
    """Whether ``name`` (a ``--run`` or ``--checkpoint`` value) names a shipped network."""
    return isinstance(name, str) and name in SHIPPED


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _shipped_as(record: Path) -> str | None:
    """The name a record says its network answers to, or None (no such field, not a record)."""
    try:
        info = json.loads(record.read_text())
    except (OSError, ValueError):  # ValueError: bad JSON or bytes; shipped() names such a file
        return None
    return info.get(SHIPPED_AS) if isinstance(info, dict) else None


def record_of(name: str, folder: Path) -> Path:
    """The record of the network that ``name`` answers to in ``folder``: the one record whose
    ``shipped_as`` is ``name``, else ``SHIPPED[name].json`` (which may not exist).

    Raises:
        ValueError: several records answer to ``name`` (naming them).
    """
    named = [p for p in sorted(folder.glob("*.json")) if _shipped_as(p) == name]
    if len(named) > 1:
        files = ", ".join(p.name for p in named)
        raise ValueError(f"{folder}: {files} all ship as {name!r}; remove all but one pair")
    return named[0] if named else folder / f"{SHIPPED[name]}.json"


def shipped(name: str = PRETRAINED, folder: Path | None = None) -> Shipped:
    """The shipped network ``name`` (:func:`record_of`), its weights checked against the
    record's checksum.

    Raises:
        ValueError: an unknown name (listing the known ones), a missing or unreadable record,
            or weights whose checksum is not the record's (naming the file and what to do).
    """
    if name not in SHIPPED:
        raise ValueError(f"unknown shipped network {name!r}; known: {', '.join(SHIPPED)}")
    folder = folder or shipped_folder()
    record = record_of(name, folder)
    stem = record.stem
    path = folder / f"{stem}.pt"
    if not record.is_file() or not path.is_file():
        raise ValueError(
            f"{folder}: the shipped network {stem} is missing ({path.name} and {record.name} "
            "expected); reinstall the package or use a trained run"
        )
    try:
        info = json.loads(record.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{record}: not a shipped-network record ({exc})") from exc
    if not isinstance(info, dict):
        raise ValueError(f"{record}: not a shipped-network record (a JSON object expected)")
    if _sha256(path) != info.get("sha256"):
        raise ValueError(
            f"{path}: its SHA-256 is not the one {record.name} records (a damaged or replaced "
            "file); restore it from the repository (git checkout -- PATH)"
        )
    return Shipped(name, path, info)


def describe_record(record: Path) -> str:
    """:func:`describe_run` of the run a shipped network's record names (its preset read from
    the run name), or what is wrong with the record."""
    try:
        info = json.loads(record.read_text())
        run_name, metrics = info["run_name"], info.get("metrics", {})
        preset = run_name.split("/")[1]
    except (OSError, ValueError, KeyError, TypeError, IndexError):
        return f"{record.name}, not a readable record"
    return describe_run(run_name, preset, metrics)


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
    :class:`~cloudpose.infer.Estimates` over the ``valid`` rows."""
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
        "sha256": _sha256(path),
        "made_by": command,
        SHIPPED_AS: name,
    }
    atomic_text(out_dir / f"{stem}.json", json.dumps(record, indent=1) + "\n")
    if replaced is not None and replaced.stem != stem:  # one pair answers to the name
        replaced.with_suffix(".pt").unlink(missing_ok=True)
        replaced.unlink(missing_ok=True)
    return path
