"""An experiment log from MLflow: one row per run, what it changed and what it reached.

``cloudpose experiments --group diagnostics --out reports/diagnostics/rotation_experiments.md``
lists every finished run of a group's experiment (of several groups' with ``--group`` repeated;
of one preset's with ``--preset``) in start order: the settings in which its config differs
from its preset's own config (``--set`` overrides), the Adam steps, the last epoch's rotation
error on a fixed sample of training segments in train mode (batch statistics) and in eval mode
(running statistics), the validation and test rotation errors (plain geodesic, as the paper
reports them, and modulo symmetry), the test ADS AUC, the share under 10 degrees modulo
symmetry with ICP and on the real development frames (``real/``, logged by every run since
the real-frame check exists), and the minutes it took.
The runs are the evidence; this file is their index, rewritten from the store each time.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from cloudpose.config import Config
from cloudpose.registry import resolve
from cloudpose.store import tracking

COLUMNS = {
    "steps": "Adam steps",
    "fit/rot_err_median_deg_batchstats": "train segs, train mode (°)",
    "fit/rot_err_median_deg": "train segs, eval mode (°)",
    "fit/rot_sym_err_median_deg": "train segs, eval, mod sym (°)",
    "val/rot_err_median_deg": "val median (°)",
    "test/rot_err_median_deg": "test median (°)",
    "test/rot_lt_10deg": "test < 10° (%)",
    "test/rot_lt_20deg": "test < 20° (%)",
    "test/rot_sym_err_median_deg": "test median mod sym (°)",
    "test/rot_sym_lt_10deg": "test < 10° mod sym (%)",
    "test/rot_sym_lt_20deg": "test < 20° mod sym (%)",
    "test/ads_auc": "test ADS AUC",
    "test_icp/rot_sym_lt_10deg": "test + ICP < 10° mod sym (%)",
    "test_icp/ads_auc": "test + ICP ADS AUC",
    "real/rot_sym_lt_10deg": "real < 10° mod sym (%)",
    "real_icp/rot_sym_lt_10deg": "real + ICP < 10° mod sym (%)",
    "real/ads_auc": "real ADS AUC",
    "minutes": "minutes",
}
"""Log columns: MLflow metric key (or derived field) -> header."""


@dataclass(frozen=True)
class Experiment:
    """One run of the log."""

    name: str
    command: str
    changes: str
    values: dict[str, float]


def config_changes(cfg: Config, against: str | None = None) -> dict[str, object]:
    """``section.field -> value`` where ``cfg`` differs from its variant under ``against``
    (a preset name; default its own preset as registered now)."""
    base = resolve(cfg.variant, against or cfg.preset, cfg.seed).flat()
    base["preset"] = cfg.preset
    return {k: v for k, v in cfg.flat().items() if base.get(k) != v}


def steps_per_epoch(cfg: Config, params: dict[str, str]) -> int:
    """Adam steps of one epoch of a run: its fitted segments (MLflow param
    ``data.train_segments``) over the batch, or ``data.online_epoch_segments`` over the batch
    for an on-line run."""
    if cfg.data.train_source == "online":
        return cfg.data.online_epoch_segments // cfg.train.batch_size
    return int(params.get("data.train_segments", 0)) // cfg.train.batch_size


def _command(cfg: Config, changes: dict[str, object], group: str) -> str:
    own = config_changes(cfg)  # what --set must say under the run's own preset
    sets = " ".join(
        f"--set {k}={json.dumps(v) if not isinstance(v, str) else v}"
        for k, v in own.items()
        if k != "preset"
    )
    return (
        f"cloudpose run --variant {cfg.variant} --preset {cfg.preset} --seed {cfg.seed} "
        f"--group {group} {sets}"
    ).strip()


def _group_names(group: str | list[str]) -> list[str]:
    """One group name or several, as a list without repeats (in the order given)."""
    return list(dict.fromkeys([group] if isinstance(group, str) else group))


def collect(
    group: str | list[str],
    project_dir: Path | None = None,
    against: str | None = None,
    preset: str | None = None,
) -> list[Experiment]:
    """The finished runs of the experiments of ``group`` (one name or several), of ``preset``
    only when given, oldest first (changes: see :func:`config_changes`)."""
    client = tracking.setup(project_dir)
    groups = _group_names(group)
    ids = []
    for g in groups:
        exp = client.get_experiment_by_name(tracking.EXPERIMENT_PREFIX + g)
        if exp is None:
            raise ValueError(f"no MLflow experiment for group {g!r} in {tracking.tracking_uri()}")
        ids.append(exp.experiment_id)
    where = "attributes.status = 'FINISHED'"
    if preset is not None:
        tracking.check_name("preset", preset)
        where += f" and tags.preset = '{preset}'"
    runs = client.search_runs(ids, where, order_by=["attributes.start_time ASC"], max_results=1000)
    out = []
    for run in runs:
        try:
            cfg = Config.from_dict(json.loads(Path(_config_path(client, run)).read_text()))
        except (OSError, ValueError):
            continue
        changes = config_changes(cfg, against)
        m = dict(run.data.metrics)
        history = client.get_metric_history(run.info.run_id, "train/loss")
        m["steps"] = len(history) * steps_per_epoch(cfg, run.data.params)
        if run.info.end_time and run.info.start_time:
            m["minutes"] = (run.info.end_time - run.info.start_time) / 60_000
        for k in list(m):
            if k.split("/")[-1].startswith(("rot_lt", "rot_sym_lt")) or k.endswith("ads_auc"):
                m[k] = 100 * m[k]
        text = ", ".join(f"{k}={v}" for k, v in changes.items()) or "(none)"
        group_of = groups[ids.index(run.info.experiment_id)]
        out.append(Experiment(run.info.run_name, _command(cfg, changes, group_of), text, m))
    return out


def _config_path(client, run) -> str:
    return str(tracking.download_artifact(client, run, "config.json"))


def experiment_table(experiments: list[Experiment]) -> pd.DataFrame:
    """One row per run: name, changes and the :data:`COLUMNS` (NaN where not logged)."""
    rows = []
    for i, e in enumerate(experiments, start=1):
        row = {"#": i, "run": e.name, "changes": e.changes}
        row.update({h: e.values.get(k, float("nan")) for k, h in COLUMNS.items()})
        rows.append(row)
    return pd.DataFrame(rows)


def _markdown(df: pd.DataFrame) -> str:
    def cell(v) -> str:
        if isinstance(v, float):
            return "–" if v != v else f"{v:.1f}"
        return str(v).replace("|", "\\|")

    lines = ["| " + " | ".join(df.columns) + " |", "|" + "---|" * len(df.columns)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in df.itertuples(index=False)]
    return "\n".join(lines)


def write_log(
    group: str | list[str],
    out: Path,
    command: str,
    project_dir: Path | None = None,
    against: str | None = None,
    preset: str | None = None,
) -> Path:
    """Write the log of ``group`` (one name or several; runs of ``preset`` only when given) as
    Markdown to ``out`` (and the values as CSV beside it)."""
    groups = _group_names(group)
    experiments = collect(groups, project_dir, against, preset)
    if not experiments:
        raise ValueError(
            f"group(s) {', '.join(groups)} have no finished run"
            + (f" of preset {preset!r}" if preset else "")
            + " to list"
        )
    df = experiment_table(experiments)
    out.parent.mkdir(parents=True, exist_ok=True)
    df.to_csv(out.with_suffix(".csv"), index=False, float_format="%.2f")
    lines = [
        f"# Experiment log: {', '.join(groups)}" + (f" ({preset})" if preset else ""),
        "",
        f"Made by `{command}` from the MLflow runs of the experiment(s) "
        + ", ".join(f"`{tracking.EXPERIMENT_PREFIX + g}`" for g in groups)
        + (f" of preset `{preset}`" if preset else "")
        + "; every row is a run anyone can repeat with the "
        "command listed under the table. 'changes': the settings in which the run differs from "
        f"{'the preset ' + repr(against) if against else 'its own preset'} as registered now. 'train segs': a fixed sample of 512 training segments, "
        "the last epoch, in train mode (batch statistics) and in eval mode (running statistics). "
        "Rotation errors are the plain geodesic angle (as the paper reports them) and the angle "
        "modulo each class's symmetries (`cloudpose symmetries`). Minutes: wall clock of "
        "training + evaluation on the machine that ran it.",
        "",
        _markdown(df),
        "",
        "Commands:",
        "",
    ]
    lines += [f"{i}. `{e.command}`" for i, e in enumerate(experiments, start=1)]
    out.write_text("\n".join(lines) + "\n")
    return out
