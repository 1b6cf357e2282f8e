"""The shipped network at work (``cloudpose showcase``, the end of ``make setup``).

The shipped network (:mod:`cloudpose.store.pretrained`) and FPFH + RANSAC, each without and with the
network's ICP, on the same instances: the 61 packaged real development frames and the first
``synthetic_frames`` test frames of the network's preset (frame i of a synthetic split depends
on the scene seed, the split and i alone, so these are the preset's own first test frames),
rendered into ``out_dir``. Plus an overlay picture of one real frame. Nothing is logged to
MLflow; the real-frame figures are those the network's run logged for the same frames (its
record, ``resources/pretrained/*.json``), up to the last digits of another CPU.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from cloudpose.store.pretrained import PRETRAINED, shipped

COLUMNS = {
    "ads_auc": "ADS AUC",
    "ad_auc": "AD AUC",
    "rot_sym_lt_10deg": "rot < 10 deg (mod sym)",
    "trans_lt_1cm": "trans < 1 cm",
}
"""Pooled metrics shown, as fractions -> their column headings (shown in percent)."""

OVERLAY_FRAME = ("0001", "000001")
"""The real frame drawn with the network's poses (video 0001: 6 objects on a table)."""


@dataclass(frozen=True)
class Showcase:
    """The showcase's table (one row per data x method, percent), its instance counts and the
    overlay picture written."""

    table: pd.DataFrame
    overlay: Path
    described: str


def _pooled(table: pd.DataFrame) -> dict[str, dict[str, float]]:
    """``{"": {metric: %}, " + ICP": {...}}`` of one instance table."""
    from cloudpose.evaluate import summary_metrics

    metrics = summary_metrics(table, "x")
    out = {}
    for prefix, suffix in (("x", ""), ("x_icp", " + ICP")):
        if f"{prefix}/ads_auc" in metrics:
            out[suffix] = {col: 100 * metrics[f"{prefix}/{key}"] for key, col in COLUMNS.items()}
    return out


def check_options(synthetic_frames: int, baseline: str) -> None:
    """``ValueError`` naming the option unless ``synthetic_frames`` is 0 or more and
    ``baseline`` is a method of ``baselines.toml`` or ''."""
    import tomllib

    from cloudpose.registry import BASELINES_FILE

    if synthetic_frames < 0:
        raise ValueError(
            f"--synthetic-frames {synthetic_frames}: expected 0 (real frames only) or more"
        )
    known = list(tomllib.loads(BASELINES_FILE.read_text()).get("baseline", {}))
    if baseline and baseline not in known:
        raise ValueError(f"--baseline {baseline!r}: expected one of {', '.join(known)}, or ''")


def run_showcase(
    out_dir: Path,
    synthetic_frames: int = 40,
    baseline: str = "fpfh",
    progress: bool = True,
) -> Showcase:
    """Evaluate the shipped network and ``baseline`` on the real development frames and the
    first ``synthetic_frames`` synthetic test frames of the network's preset; draw one real frame.

    Args:
        out_dir: where the synthetic frames, segment caches and the overlay go.
        synthetic_frames: test frames to render (0: real frames only).
        baseline: a registered baseline (``cloudpose baseline --help``), or "" for none.

    Raises:
        ValueError: a negative ``synthetic_frames`` or an unknown ``baseline`` (before any
            work; :func:`check_options`).
    """
    from cloudpose.baselines.run import run_baseline
    from cloudpose.data.layout import real_dev_root
    from cloudpose.data.synth.write import synthesize
    from cloudpose.evaluate import evaluate
    from cloudpose.infer import load_checkpoint
    from cloudpose.predict import predict

    check_options(synthetic_frames, baseline)
    out_dir = Path(out_dir).resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    net = shipped()
    _, cfg = load_checkpoint(net.path)
    sets = [("real development frames", real_dev_root(), "all")]
    if synthetic_frames > 0:
        root = out_dir / "data" / f"synth-seed{cfg.data.synth_seed}-v{cfg.data.synth_version}-test"
        synthesize(
            root,
            train_frames=0,
            test_frames=synthetic_frames,
            seed=cfg.data.synth_seed,
            version=cfg.data.synth_version,
            progress=progress,
        )
        sets.append((f"synthetic test frames of {cfg.preset}", root, "keyframe"))
    rows, counts = [], []
    for label, root, frames in sets:
        ours = evaluate(
            PRETRAINED,
            data=str(root),
            frames=frames,
            project_dir=out_dir,
            log=False,
            progress=progress,
        )
        results = [(f"network ({cfg.variant})", ours.table)]
        if baseline:
            theirs = run_baseline(
                baseline,
                cfg.preset,
                seed=1,
                project_dir=out_dir,
                data=root,
                frames=frames,
                log=False,
                progress=progress,
            )
            results.append((baseline, theirs.table))
        counts.append(f"{label}: {len(ours.table)} instances")
        for method, table in results:
            for suffix, values in _pooled(table).items():
                rows.append({"data": label, "method": method + suffix, **values})
    frame_dir = real_dev_root() / "data" / OVERLAY_FRAME[0]
    stem = frame_dir / OVERLAY_FRAME[1]
    overlay = out_dir / f"overlay_{OVERLAY_FRAME[0]}_{OVERLAY_FRAME[1]}.png"
    predict(
        Path(f"{stem}-depth.png"),
        Path(f"{stem}-label.png"),
        PRETRAINED,
        color=Path(f"{stem}-color.png"),
        meta=Path(f"{stem}-meta.mat"),
        overlay=overlay,
    )
    described = f"{net.describe()}; " + "; ".join(counts)
    return Showcase(pd.DataFrame(rows), overlay, described)


def format_table(table: pd.DataFrame) -> str:
    """The showcase table as Markdown, percent with one decimal."""
    cols = ["data", "method", *COLUMNS.values()]
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * 2 + "---:|" * len(COLUMNS)]
    for _, r in table.iterrows():
        cells = [r["data"], r["method"], *(f"{r[c]:.1f}" for c in COLUMNS.values())]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
