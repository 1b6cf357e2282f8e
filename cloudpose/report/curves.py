"""Per-epoch curves of any metrics of any runs, side by side: ``cloudpose curves``.

The group reports plot each group's training loss and validation ADS AUC over seeds. This is the
tool for a question across presets or variants, e.g. whether the rotation error falls with more
epochs or fewer frames: one panel per metric, one line per run, the run's name, data, config and
code in the footer.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import matplotlib.pyplot as plt
import pandas as pd
from matplotlib.ticker import MaxNLocator

from cloudpose.report.plots import finish  # also selects the Agg backend
from cloudpose.report.runs import metric_history
from cloudpose.store.runs import resolve_run_id

METRIC_LABELS = {
    "train/loss": "training loss (10·m + rad)",
    "train/loss_rot": "training rotation loss (geodesic: rad)",
    "train/loss_trans": "training translation loss (m)",
    "val/loss": "validation loss (10·m + rad)",
    "val/ads_auc": "validation ADS AUC (fraction)",
    "val/rot_err_median_deg": "validation median rotation error (°)",
    "val/trans_err_median_mm": "validation median translation error (mm)",
    "val/rot_lt_10deg": "validation rot. err. < 10° (fraction)",
    "val/trans_lt_1cm": "validation trans. err. < 1 cm (fraction)",
}
"""Axis labels with units of the metrics train.py logs per epoch (others: the key itself)."""


@dataclass(frozen=True)
class RunCurves:
    """One run's per-epoch series and what identifies it.

    Attributes:
        label: legend text (the run name).
        run_id: MLflow run id.
        series: metric key -> values indexed by epoch (empty if never logged).
        data, config, commit: the run's tags (data and config fingerprints, git commit).
        steps_per_epoch: Adam steps per epoch (training segments // batch size, from the run's
            params; the last partial batch is dropped), None if the params are missing.
    """

    label: str
    run_id: str
    series: dict[str, pd.Series]
    data: str
    config: str
    commit: str
    steps_per_epoch: int | None = None


def fetch_curves(client, runs: Sequence[str], metrics: Sequence[str]) -> list[RunCurves]:
    """The per-epoch histories of ``metrics`` for each of ``runs``.

    Args:
        client: an MLflow client bound to the store.
        runs: run names ``variant/preset/seedS``, MLflow run ids or run folders, each
            optionally ``LABEL=RUN`` to name its line (default: the run name).
        metrics: metric keys (``train/loss_rot``, ...).

    Raises:
        ValueError: a run that cannot be found, or a metric none of the runs logged.
    """
    out = []
    for spec in runs:
        label, sep, run = spec.rpartition("=")
        if not sep:
            label, run = "", spec
        run_id = resolve_run_id(client, run)
        r = client.get_run(run_id)
        series = {key: metric_history(client, run_id, key) for key in metrics}
        tags, params = r.data.tags, r.data.params
        try:
            steps = int(params["data.train_segments"]) // int(params["train.batch_size"])
        except (KeyError, ValueError):
            steps = None
        out.append(
            RunCurves(
                label or r.info.run_name or run_id,
                run_id,
                series,
                tags.get("data", "?"),
                tags.get("config", "?"),
                tags.get("git_commit", "?"),
                steps,
            )
        )
    for key in metrics:
        if not any(len(c.series[key]) for c in out):
            raise ValueError(
                f"metric {key!r} was not logged by any of the runs {list(runs)}; "
                f"per-epoch metrics: {sorted(METRIC_LABELS)}"
            )
    return out


def plot_curves(
    curves: Sequence[RunCurves],
    metrics: Sequence[str],
    path: Path,
    *,
    command: str,
    title: str = "",
    mark_epoch: int | None = None,
    mark_label: str = "",
    x: str = "epoch",
) -> Path:
    """One panel per metric, one line per run; footer: the command and every run's identity.

    Args:
        mark_epoch: draw a dashed vertical line at this epoch (e.g. where a shorter preset stops),
            labelled ``mark_label`` (with ``x="step"``: at that epoch of the first run).
        x: "epoch", or "step" (Adam steps: epochs x steps per epoch), to compare runs whose
            epochs differ in length.
    """
    if x not in ("epoch", "step"):
        raise ValueError(f"x must be 'epoch' or 'step', got {x!r}")
    if x == "step" and any(c.steps_per_epoch is None for c in curves):
        missing = [c.label for c in curves if c.steps_per_epoch is None]
        raise ValueError(
            f"x='step' needs params data.train_segments and train.batch_size; missing in {missing}"
        )
    fig, axes = plt.subplots(1, len(metrics), figsize=(5.5 * len(metrics), 4.4), squeeze=False)
    for ax, key in zip(axes[0], metrics, strict=True):
        for c in curves:
            s = c.series[key]
            if len(s):
                xs = s.index * (c.steps_per_epoch if x == "step" else 1)
                ax.plot(xs, s.to_numpy(), marker="." if len(s) <= 30 else None, label=c.label)
        if mark_epoch is not None:
            at = mark_epoch * (curves[0].steps_per_epoch if x == "step" else 1)
            ax.axvline(at, color="0.4", linestyle="--", linewidth=1)
            if mark_label:
                ax.annotate(
                    mark_label,
                    (at, 1.0),
                    xycoords=("data", "axes fraction"),
                    xytext=(3, -12),
                    textcoords="offset points",
                    fontsize=8,
                    color="0.3",
                )
        ax.set_xlabel("epoch" if x == "epoch" else "Adam steps")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_ylabel(METRIC_LABELS.get(key, key))
        ax.set_title(key)
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8)
    if title:
        fig.suptitle(title)
    ids = "; ".join(
        f"{c.label}: run {c.run_id[:8]}, data {c.data[:10]}, config {c.config[:8]}, code {c.commit}"
        for c in curves
    )
    # room for the footer: ~190 characters per line at this size and font
    width_chars = 190 * len(metrics) / 2
    lines = 1 + int(len(command) / width_chars) + 1 + int(len(ids) / width_chars)
    return finish(
        fig, path, f"made by {command}\n{ids}", (0, min(0.3, 0.025 * lines + 0.015), 1, 1)
    )


def curves_csv(
    curves: Sequence[RunCurves], metrics: Sequence[str], path: Path, command: str
) -> Path:
    """The plotted values as CSV (one row per run and epoch), with the command as a comment."""
    rows = []
    for c in curves:
        frame = pd.DataFrame({k: c.series[k] for k in metrics})
        frame.index.name = "epoch"
        frame = frame.reset_index()
        frame.insert(0, "run", c.label)
        frame.insert(1, "run_id", c.run_id)
        frame.insert(
            3, "step", frame["epoch"] * (c.steps_per_epoch or 0) if c.steps_per_epoch else None
        )
        rows.append(frame)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w") as f:
        f.write(f"# made by {command}\n")
        pd.concat(rows, ignore_index=True).to_csv(f, index=False, float_format="%.6g")
    return path
