"""The report's figures (PNG, matplotlib Agg), drawn from MLflow runs.

- occlusion: ADS < 1 cm accuracy per 10%-wide occlusion bin, one bar group per method or variant,
  the bin's instance count in parentheses under it (the paper's Fig. 5).
- accuracy-threshold curves: share of instances with AD (ADS) below a threshold, 0-10 cm.
- training curves: training loss and validation ADS AUC per epoch, mean over seeds with a band.
- rotation-error histograms per variant.
- the test set's occlusion histogram (``cloudpose prepare --histogram``).

Every figure carries a footer naming the command, preset, data, seeds and code that made it.
"""

from __future__ import annotations

import hashlib
import io
import re
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
from matplotlib.ticker import MaxNLocator
from PIL import Image

from cloudpose.metrics import accuracy_curve, occlusion_bin_index, occlusion_bins
from cloudpose.report.formats import Provenance, write_png

OCCLUSION_EDGES = np.linspace(0.0, 1.0, 11)
"""Edges of the 10%-wide occlusion bins, as fractions."""

ADS_HIT_M = 0.01
"""ADS threshold of the occlusion plot, metres (the paper's "< 1 cm")."""


@dataclass(frozen=True)
class Series:
    """One bar group / curve: a label and the per-seed instance tables it is drawn from.

    Attributes:
        label: legend text.
        tables: one ``instances.csv`` table per seed.
        method: column prefix, "net" (network alone) or "icp" (after ICP).
    """

    label: str
    tables: Sequence[pd.DataFrame]
    method: str = "net"


FOOTER_RECT = (0, 0.04, 1, 1)
"""Where a figure's axes go (:func:`finish`): the bottom 4% left to its footer."""

_FOOTER = {"fontsize": 6, "color": "0.35", "ha": "left", "va": "bottom", "wrap": True}


def finish(fig, path: Path, footer: Provenance | str, rect=FOOTER_RECT) -> Path:
    """The last steps of every report figure: lay ``fig`` out in ``rect`` (figure fractions),
    put ``footer`` under it and write it (:func:`_save`, which closes it).

    Args:
        footer: the runs' provenance, shown without the commit that rendered it and compared
            without its command (:func:`_footer`); or a text, shown and compared as it is.
    """
    fig.tight_layout(rect=rect)
    if isinstance(footer, Provenance):
        _footer(fig, footer)
    else:
        fig.text(0.01, 0.005, footer, **_FOOTER)
    return _save(fig, path)


def _footer(fig, prov: Provenance) -> None:
    """The runs' provenance under a figure, without the commit that rendered it: a figure
    rendered again from the same runs is the same file, byte for byte, so a re-render adds
    nothing to the repository where only the renderer moved (the tables beside it say which
    code rendered them)."""
    line = replace(prov, renderer="").line().replace("`", "")
    fig._cloudpose_footer = fig.text(0.01, 0.005, line, **_FOOTER)  # read back by _save


def occlusion_accuracy(table: pd.DataFrame, method: str = "net") -> tuple[np.ndarray, np.ndarray]:
    """ADS < 1 cm accuracy and instance count per 10%-wide occlusion bin.

    Args:
        table: per-instance table with columns ``occlusion`` (fraction 0..1, NaN = unknown) and
            ``{method}_ads`` (metres, inf for misses).
        method: "net" or "icp".

    Returns:
        (10,) accuracy (fraction; NaN for an empty bin) and (10,) instance counts
        (:func:`cloudpose.metrics.occlusion_bins`: unknown occlusion left out, 1.0 in the last
        bin, misses count as failures).
    """
    col = f"{method}_ads"
    if col not in table or "occlusion" not in table:
        raise ValueError(f"instance table lacks column 'occlusion' or {col!r}; has {list(table)}")
    bins = occlusion_bins(
        table["occlusion"].to_numpy(float),
        table[col].to_numpy(float),
        width=OCCLUSION_EDGES[1],
        threshold=ADS_HIT_M,
    )
    return bins["ads_lt_1cm"].to_numpy(float), bins["count"].to_numpy(int)


def occlusion_frame(series: Sequence[Series]) -> pd.DataFrame:
    """Per bin and series: mean and std over seeds of the accuracy (%), and the count."""
    rows = []
    for s in series:
        accs, counts = zip(*(occlusion_accuracy(t, s.method) for t in s.tables), strict=True)
        accs = np.array(accs) * 100  # (S, 10)
        if any((c != counts[0]).any() for c in counts):
            warnings.warn(
                f"{s.label}: the seeds' test sets differ; bin counts are seed 1's", stacklevel=2
            )
        for i in range(len(OCCLUSION_EDGES) - 1):
            col = accs[:, i][np.isfinite(accs[:, i])]
            rows.append(
                {
                    "series": s.label,
                    "method": s.method,
                    "bin_low_pct": round(100 * OCCLUSION_EDGES[i]),
                    "bin_high_pct": round(100 * OCCLUSION_EDGES[i + 1]),
                    "count": int(counts[0][i]),
                    "accuracy_mean_pct": float(col.mean()) if col.size else np.nan,
                    "accuracy_std_pct": float(col.std(ddof=1)) if col.size > 1 else np.nan,
                    "seeds": len(s.tables),
                }
            )
    return pd.DataFrame(rows)


def plot_occlusion(series: Sequence[Series], path: Path, prov: Provenance, title: str) -> Path:
    """Bar chart of ADS < 1 cm accuracy per occlusion bin; one bar group per series."""
    df = occlusion_frame(series)
    n_bins = len(OCCLUSION_EDGES) - 1
    counts = df[df["series"] == series[0].label]["count"].to_numpy()
    many = len(series) > 3
    fig, ax = plt.subplots(figsize=(13.0 if many else 9.0, 5.0))
    width = 0.8 / len(series)
    x = np.arange(n_bins)
    for k, s in enumerate(series):
        sub = df[df["series"] == s.label]
        err = sub["accuracy_std_pct"].fillna(0).to_numpy() if len(s.tables) > 1 else None
        ax.bar(
            x + (k - (len(series) - 1) / 2) * width,
            sub["accuracy_mean_pct"].fillna(0),
            width,
            yerr=err,
            capsize=2,
            label=f"{s.label} ({len(s.tables)} seed{'s' if len(s.tables) != 1 else ''})",
        )
    ax.set_xticks(x)
    ax.set_xticklabels(
        [
            f"{round(100 * lo)}–{round(100 * hi)}%\n({c})"
            for lo, hi, c in zip(OCCLUSION_EDGES[:-1], OCCLUSION_EDGES[1:], counts, strict=True)
        ],
        fontsize=8,
    )
    ax.set_xlabel("occlusion factor (instances in parentheses)")
    ax.set_ylabel("ADS < 1 cm accuracy (%)")
    ax.set_ylim(0, 105)
    ax.set_title(title + " (bars: mean over seeds, whiskers: ± 1 std)")
    ax.grid(axis="y", alpha=0.3)
    if many:
        ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    else:
        ax.legend(fontsize=8, loc="upper right")
    return finish(fig, path, prov)


def accuracy_curves(tables: Sequence[pd.DataFrame], column: str, thresholds_m: np.ndarray):
    """Per-seed accuracy (fraction, misses count as failures) at each threshold; (S, T)."""
    return np.array([accuracy_curve(t[column].to_numpy(float), thresholds_m) for t in tables])


def plot_threshold_curves(
    series: Sequence[Series], path: Path, prov: Provenance, title: str
) -> Path:
    """AD and ADS accuracy-threshold curves (0-10 cm), mean over seeds, one line per series."""
    thresholds = np.linspace(0.0, 0.1, 201)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.6), sharey=True)
    for ax, metric, name in zip(axes, ("ad", "ads"), ("AD", "ADS"), strict=True):
        for s in series:
            acc = accuracy_curves(s.tables, f"{s.method}_{metric}", thresholds) * 100
            mean = acc.mean(axis=0)
            (line,) = ax.plot(thresholds * 100, mean, label=s.label)
            if len(acc) > 1:
                ax.fill_between(
                    thresholds * 100,
                    acc.min(axis=0),
                    acc.max(axis=0),
                    color=line.get_color(),
                    alpha=0.15,
                    linewidth=0,
                )
        ax.set_xlabel(f"{name} threshold (cm)")
        ax.set_title(f"{name}")
        ax.set_xlim(0, 10)
        ax.set_ylim(0, 100)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("accuracy (% of instances below threshold)")
    axes[1].legend(fontsize=8, loc="lower right")
    fig.suptitle(title + " (mean over seeds; band: min–max)")
    return finish(fig, path, prov)


def plot_training_curves(
    histories: dict[str, list[dict[str, pd.Series]]], path: Path, prov: Provenance, title: str
) -> Path:
    """Training loss and validation ADS AUC per epoch, mean over seeds, band = ± 1 std.

    Args:
        histories: label -> one dict per seed with ``train/loss`` and ``val/ads_auc`` series
            (index: epoch).
    """
    panels = (
        ("train/loss", "training loss (10·m + rad)", 1.0),
        ("val/ads_auc", "validation ADS AUC (%)", 100.0),
    )
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.4))
    for ax, (key, ylabel, scale) in zip(axes, panels, strict=True):
        for label, seeds in histories.items():
            curves = [h[key] for h in seeds if key in h and len(h[key])]
            if not curves:
                continue
            frame = pd.concat(curves, axis=1) * scale  # (epochs, seeds)
            mean = frame.mean(axis=1)
            (line,) = ax.plot(mean.index, mean.to_numpy(), marker=".", label=label)
            if frame.shape[1] > 1:
                std = frame.std(axis=1, ddof=1).fillna(0)
                ax.fill_between(
                    mean.index,
                    mean - std,
                    mean + std,
                    color=line.get_color(),
                    alpha=0.15,
                    linewidth=0,
                )
        ax.set_xlabel("epoch")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    axes[0].set_yscale("log")
    axes[0].set_title("training loss")
    axes[1].set_title("validation ADS AUC (without ICP)")
    axes[1].legend(fontsize=8, loc="lower right")
    fig.suptitle(title + " (mean over seeds; band: ± 1 std)")
    return finish(fig, path, prov)


def plot_rotation_histograms(
    series: Sequence[Series], path: Path, prov: Provenance, title: str
) -> Path:
    """Histogram of rotation errors (degrees), one panel per series, pooled over seeds."""
    bins = np.arange(0, 182.5, 2.5)
    ncols = 1 if len(series) <= 3 else 3
    nrows = -(-len(series) // ncols)
    fig, axes = plt.subplots(
        nrows,
        ncols,
        figsize=(8 if ncols == 1 else 15, 1.3 + 2.0 * nrows),
        sharex=True,
        sharey=True,
        squeeze=False,
    )
    for ax, s in zip(axes.flat, series, strict=False):
        err = np.concatenate([t[f"{s.method}_rot_err_deg"].to_numpy(float) for t in s.tables])
        finite = err[np.isfinite(err)]
        weights = np.full(finite.shape, 100.0 / max(err.size, 1))
        ax.hist(finite, bins=bins, weights=weights, color="C0")
        for thr, style in ((10, "-"), (15, "--"), (20, ":")):
            ax.axvline(thr, color="C3", linestyle=style, linewidth=0.8)
        median = np.median(err) if err.size else np.nan
        ax.set_title(s.label, fontsize=9)
        ax.text(
            0.98,
            0.92,
            f"median {median:.1f}°\n< 10°: {100 * np.mean(err < 10):.1f}%\n"
            f"n = {err.size} ({int(np.sum(~np.isfinite(err)))} misses)",
            transform=ax.transAxes,
            ha="right",
            va="top",
            fontsize=8,
        )
        ax.grid(alpha=0.3)
    for ax in axes.flat[len(series) :]:
        ax.set_visible(False)
    for ax in axes[:, 0]:
        ax.set_ylabel("% of instances")
    for ax in axes[-1, :]:
        ax.set_xlabel("rotation error (degrees)")
    axes[0, 0].set_xlim(0, 180)
    fig.suptitle(title + " (pooled over seeds; red lines at 10°, 15°, 20°)")
    return finish(fig, path, prov)


DPI = 120
"""Resolution of the report's figures (dots per inch)."""

CONTENT_KEY = "cloudpose-content"
"""PNG text chunk of a figure: the digest of what it shows, the command in its footer left out."""


def _content_digest(fig) -> str:
    """SHA-256 of the figure rendered as a PNG with the command left out of its footer."""
    footer = getattr(fig, "_cloudpose_footer", None)
    shown = footer.get_text() if footer is not None else None
    if footer is not None:
        footer.set_text(re.sub(r"^made by [^;]*;", "made by;", shown))
    buf = io.BytesIO()
    try:
        fig.savefig(buf, dpi=DPI, format="png", metadata={"Software": None})
    finally:
        if footer is not None:
            footer.set_text(shown)
    return hashlib.sha256(buf.getvalue()).hexdigest()


def _save(fig, path: Path) -> Path:
    """Write ``fig`` as a PNG (atomically), leaving a file that shows the same already but
    for the command in its footer (:func:`cloudpose.report.formats.write_text` for figures)."""
    path = Path(path)
    digest = _content_digest(fig)
    try:
        with Image.open(path) as old:
            if old.text.get(CONTENT_KEY) == digest:
                plt.close(fig)
                return path
    except (OSError, ValueError, AttributeError):
        pass  # none, or not a PNG of ours: written anew
    return write_png(fig, path, DPI, {CONTENT_KEY: digest})


def occlusion_histogram(segments, path: str | Path | None = None, title: str = "") -> np.ndarray:
    """Counts of instances per 10%-wide occlusion-factor bin; optionally a PNG bar chart.

    Args:
        segments: the instances, a ``SegmentSet``; binned as the occlusion plot
            (:func:`cloudpose.metrics.occlusion_bin_index`: NaN left out, below 0 in the
            first bin).
        path: where to write the PNG (None: no plot).
        title: the plot title (name the command and settings).

    Returns:
        (10,) int64 counts for [0, 10%), ..., [90%, 100%] (the last bin includes 100%).
    """
    index, n_bins = occlusion_bin_index(segments.occlusion, width=OCCLUSION_EDGES[1])
    counts = np.bincount(index[index >= 0], minlength=n_bins)
    edges = OCCLUSION_EDGES
    if path is not None:
        fig, ax = plt.subplots(figsize=(7, 4))
        centres = (edges[:-1] + edges[1:]) / 2 * 100
        ax.bar(centres, counts, width=9.0, color="tab:blue")
        for x, c in zip(centres, counts, strict=True):
            ax.text(x, c, str(c), ha="center", va="bottom", fontsize=8)
        ax.set_xticks(edges * 100)
        ax.set_xlabel("occlusion factor O = 1 - visible / alone pixels (%)")
        ax.set_ylabel("instances")
        ax.set_title(title or f"occlusion factors of {int(counts.sum())} instances", fontsize=9)
        fig.tight_layout()
        write_png(fig, path, DPI)
    return counts
