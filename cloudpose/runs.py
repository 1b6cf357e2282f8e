"""Run identity: what makes two runs the same run, where a run lives, and how a user's name for a
run is resolved to one.

A run is one config (:meth:`cloudpose.config.Config.fingerprint`, which covers the variant,
preset values, seed and every override) trained on one dataset
(:func:`cloudpose.data.dataset.data_fingerprint`, a content hash). Both fingerprints name:

- the run folder ``runs/{variant}/{preset}/seed{S}-{data[:10]}-{config[:8]}`` (:func:`run_dir`),
  holding ``last.pt``, ``model.pt`` and ``run.json`` (:func:`read_info` / :func:`write_info`:
  the MLflow run id, the group, the config, and once finished its final metrics);
- the MLflow run's tags ``config`` and ``data``; its name is ``variant/preset/seedS``
  (:func:`run_name`), plus ``+{config[:8]}`` for a config that is not its preset's own
  (:func:`display_name`), so runs of different configs never share a name.

A user names a run by its folder, its MLflow run id, or ``variant/preset/seedS``; the last means
the one finished run of the preset's own config (:func:`resolve_run_id`), and an error lists
the candidates when there are none or several. The ablation runner takes a run as done when a
finished run of exactly the config on exactly the data has test metrics (:func:`finished_run`).
"""

from __future__ import annotations

import datetime
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cloudpose import tracking
from cloudpose.files import atomic_text

if TYPE_CHECKING:
    from cloudpose.config import Config

__all__ = [
    "TEST_KEY",
    "describe_run",
    "display_name",
    "finished_run",
    "is_preset_config",
    "read_info",
    "resolve_run",
    "resolve_run_id",
    "run_dir",
    "run_has_config",
    "run_name",
    "write_info",
]

TEST_KEY = "test/ads_auc"
"""The metric a run has once its own test set is evaluated."""

INFO = "run.json"


def run_name(variant: str, preset: str, seed: int) -> str:
    """Deterministic run name, ``shared-3/cpu/seed1``."""
    return f"{variant}/{preset}/seed{seed}"


def display_name(cfg: Config) -> str:
    """The MLflow run name of ``cfg``: :func:`run_name`, plus ``+{config fingerprint}`` when
    ``cfg`` is not its preset's own config (overrides)."""
    name = run_name(cfg.variant, cfg.preset, cfg.seed)
    return (
        name
        if _is_own(cfg.variant, cfg.preset, cfg.seed, cfg.data.root, cfg.fingerprint())
        else f"{name}+{cfg.fingerprint()[:8]}"
    )


def _is_own(variant: str, preset: str, seed: int, root: str, fingerprint: str | None) -> bool:
    """Whether ``fingerprint`` is the config that variant/preset/seed (on ``root``) resolves to."""
    from cloudpose.config import resolve

    try:
        own = resolve(variant, preset, seed, {"data": {"root": root}} if root else None)
    except (KeyError, ValueError):
        return False
    return own.fingerprint() == fingerprint


def run_dir(cfg: Config, data_key: str, project_dir: Path) -> Path:
    """``runs/{variant}/{preset}/seed{S}-{data[:10]}-{config[:8]}`` under the project folder."""
    name = f"seed{cfg.seed}-{data_key[:10]}-{cfg.fingerprint()[:8]}"
    return project_dir / "runs" / cfg.variant / cfg.preset / name


def read_info(folder: Path) -> dict[str, Any]:
    """The run folder's ``run.json`` ({} when there is none yet)."""
    path = Path(folder) / INFO
    return json.loads(path.read_text()) if path.exists() else {}


def write_info(folder: Path, info: dict[str, Any]) -> None:
    """Write the run folder's ``run.json`` atomically."""
    atomic_text(Path(folder) / INFO, json.dumps(info, indent=2))


def is_run_folder(path: str | Path) -> bool:
    return (Path(path) / INFO).exists()


def run_has_config(run, cfg: Config) -> bool:
    """Whether an MLflow ``run`` was made with exactly the config ``cfg``.

    By the ``config`` tag; a run from before that tag existed is compared on its logged params
    (every ``section.field`` of ``cfg`` must be there with the same value).
    """
    tag = run.data.tags.get("config")
    if tag is not None:
        return tag == cfg.fingerprint()
    params = run.data.params
    return all(params.get(k) == v for k, v in tracking.flat_params(cfg.flat()).items())


def is_preset_config(run) -> bool:
    """Whether an MLflow ``run`` was trained with its preset's own config (no override).

    Its tags name variant, preset and seed; the config those resolve to today (with the run's
    dataset root) must have the run's ``config`` fingerprint. A run made with ``--set`` or
    ``--epochs``, or under an edited preset, is another config and answers False.
    """
    tags = run.data.tags
    try:
        seed = int(tags["seed"])
        variant, preset = tags["variant"], tags["preset"]
    except (KeyError, ValueError):
        return False
    root = run.data.params.get("data.root", "")
    return _is_own(variant, preset, seed, root, tags.get("config"))


def describe_run(run) -> str:
    """One line naming a run: id, name, config and data fingerprints, start time."""
    t = run.data.tags
    start = datetime.datetime.fromtimestamp((run.info.start_time or 0) / 1000)
    return (
        f"{run.info.run_id} ({run.info.run_name}, config {t.get('config', '?')}, "
        f"data {t.get('data', '?')[:10]}, started {start:%Y-%m-%d %H:%M})"
    )


def finished_run(client, cfg: Config, data: str):
    """The newest FINISHED run of exactly ``cfg`` on ``data`` with test metrics, or None.

    Matched on the tags (variant, preset, seed, data) and then on the whole config: after an
    edit of the preset or the variant, or a run with overrides, the runs of the old config are
    not taken for the new one.
    """
    for r in tracking.find_runs(
        client, variant=cfg.variant, preset=cfg.preset, seed=cfg.seed, data=data
    ):
        if TEST_KEY in r.data.metrics and run_has_config(r, cfg):
            return r
    return None


def resolve_run_id(client, run: str) -> str:
    """MLflow run id of ``run`` (a run folder, an MLflow run id or a run name; see resolve_run)."""
    if is_run_folder(run):
        return read_info(Path(run))["run_id"]
    if run.count("/") == 2:
        variant, preset, seed = run.split("/")
        try:
            seed_n = int(seed.removeprefix("seed"))
        except ValueError:
            raise ValueError(f"--run {run!r}: expected variant/preset/seedN") from None
        found = tracking.find_runs(client, variant=variant, preset=preset, seed=seed_n)
        own = [r for r in found if is_preset_config(r)]
        if not found:
            raise ValueError(f"no finished run named {run!r} in {tracking.tracking_uri()}")
        if len(own) != 1:
            listed = "; ".join(describe_run(r) for r in (own or found))
            why = (
                f"{len(own)} finished runs of preset {preset!r}'s own config are named {run!r}"
                if own
                else f"no finished run named {run!r} has preset {preset!r}'s own config "
                "(the ones there were made with overrides or an older preset)"
            )
            raise ValueError(f"{why}: {listed}. Pass the run id or run folder")
        return own[0].info.run_id
    try:
        return client.get_run(run).info.run_id
    except Exception as exc:
        raise ValueError(
            f"--run {run!r} is neither a run folder, a run name variant/preset/seedS, "
            f"nor an MLflow run id in {tracking.tracking_uri()}"
        ) from exc


def resolve_run(client, run: str) -> tuple[str, Path]:
    """MLflow run id and local checkpoint of ``run``.

    ``run`` is a run folder (``runs/shared-0/cpu/seed1-...``), an MLflow run id, or a run name
    ``variant/preset/seedS``: the one finished run of that name trained with the preset's own
    config (an error listing the candidates when there are none or several). A checkpoint that
    is not on this machine is downloaded from the run's artifacts.
    """
    run_id = resolve_run_id(client, run)
    if is_run_folder(run):
        return run_id, Path(run) / "model.pt"
    local = Path(client.get_run(run_id).data.tags.get("run_dir", "")) / "model.pt"
    if not local.exists():
        import mlflow

        local = Path(
            mlflow.artifacts.download_artifacts(
                run_id=run_id, artifact_path="model.pt", tracking_uri=client.tracking_uri
            )
        )
    return run_id, local
