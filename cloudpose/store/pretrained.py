"""The shipped network: a trained shared-0 inside the package, so a fresh clone predicts and
evaluates without training.

``pretrained`` names it wherever a checkpoint or run is asked for (``cloudpose predict
--checkpoint pretrained``, ``cloudpose evaluate --run pretrained --real``). The package holds
the weights (``resources/pretrained/STEM.pt``: the network's state and its resolved config, in
the fewest bytes that keep every pose of the real development frames where float32 puts it,
:mod:`cloudpose.models.stored`) and a record beside them (``STEM.json``: the MLflow run it was
taken from, so its preset and recipe, its data key and config fingerprint, the metrics that
run logged, the weights' form and SHA-256, the command that made both and the name it answers
to). STEM is what the file holds, ``variant_preset_seedS`` (:func:`file_stem`).
``cloudpose ship --run RUN`` writes the pair from a finished run
(:func:`cloudpose.archive.ship.ship`), and writes over the network a name answers to only when
asked (``--force``).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cloudpose.conventions import resource_path
from cloudpose.registry import DEFAULT_PRESET

PRETRAINED = "pretrained"
"""The name of the shipped network wherever a checkpoint or run is asked for."""

SHIPPED = {PRETRAINED: "shared-0_gpu_seed1"}
"""Name -> the stem of its files under ``resources/pretrained`` when no record there names
it (``shipped_as``): the network the package ships."""

SHIPPED_AS = "shipped_as"
"""Field of a record: the name (a key of :data:`SHIPPED`) its network answers to."""

SHOWN = ("test/ads_auc", "test_icp/ads_auc", "real/ads_auc", "real_icp/ads_auc")
"""The run's metrics :func:`describe_run` names: ADS AUC (0-1) on its synthetic test set and on
the real development frames, without and with ICP."""

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


def file_sha256(path: Path) -> str:
    """The SHA-256 of a file, read in 1 MiB blocks (hex)."""
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
    if file_sha256(path) != info.get("sha256"):
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
