"""The shipped network at work (``cloudpose showcase``, the end of ``make setup``).

The shipped network (:mod:`cloudpose.store.pretrained`) and FPFH + RANSAC on the same segments,
each estimate as it is, after the paper's ICP and after the product's refinement
(:data:`cloudpose.config.PRODUCT_REFINEMENT`): one comparison
(:func:`cloudpose.studies.compare.run_compare`) on the 61 packaged real development frames and one on
the first ``synthetic_frames`` test frames of the network's preset (frame i of a synthetic split
depends on the scene seed, the split and i alone, so these are the preset's own first test
frames), in ``out_dir``. Plus an overlay picture of one real frame, posed as ``cloudpose
predict`` poses it. Nothing is logged to MLflow; the real-frame figures of the estimate and the
paper's ICP are those the network's run logged for the same frames (its record,
``resources/pretrained/*.json``), up to the last digits of another CPU.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from cloudpose.config import PRODUCT_REFINEMENT, describe_refinement, refinement
from cloudpose.data.layout import real_dev_root
from cloudpose.data.synth.write import synthesize
from cloudpose.infer import load_checkpoint
from cloudpose.predict import predict
from cloudpose.refine import settings_overrides
from cloudpose.registry import BASELINES_FILE
from cloudpose.store.pretrained import PRETRAINED, shipped
from cloudpose.studies.compare import NETWORK, run_compare
from cloudpose.studies.compare import rows as pooled_rows

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


def check_options(synthetic_frames: int, baseline: str) -> None:
    """``ValueError`` naming the option unless ``synthetic_frames`` is 0 or more and
    ``baseline`` is a method of ``baselines.toml`` or ''."""
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
    refine: str = PRODUCT_REFINEMENT,
) -> Showcase:
    """Compare the shipped network and ``baseline`` on the real development frames and the
    first ``synthetic_frames`` synthetic test frames of the network's preset, each estimate
    also after the paper's ICP and after ``refine``; draw one real frame.

    Args:
        out_dir: where the synthetic frames, segment caches, comparisons and the overlay go.
        synthetic_frames: test frames to render (0: real frames only).
        baseline: a registered baseline (``cloudpose baseline --help``), or "" for none.
        refine: the refinement beside the paper's (:data:`cloudpose.config.REFINEMENTS`);
            the overlay's too.

    Raises:
        ValueError: a negative ``synthetic_frames``, an unknown ``baseline`` or ``refine``
            (before any work; :func:`check_options`).
    """
    check_options(synthetic_frames, baseline)
    fields = refinement(refine)
    out_dir = Path(out_dir).resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    net = shipped()
    _, cfg = load_checkpoint(net.path)
    sets = [("real development frames", None, None)]
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
        done = run_compare(
            out_dir / "compare" / ("real" if root is None else "synthetic"),
            data=root,
            frames=frames,
            runs=[PRETRAINED],
            methods=[baseline] if baseline else [],
            seed=1,
            project_dir=out_dir,
            progress=progress,
            **fields,
        )
        counts.append(f"{label}: {len(done.tables[(NETWORK, done.refinements[0].name)])} instances")
        pooled = pooled_rows(done.tables, done.contenders, done.refinements)
        for r in pooled.to_dict("records"):
            method = r["label"].replace(NETWORK, f"{NETWORK} ({cfg.variant})", 1)
            rows.append(
                {"data": label, "method": method, **{c: 100 * r[k] for k, c in COLUMNS.items()}}
            )
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
        icp_overrides=settings_overrides(fields),
    )
    described = (
        f"{net.describe()}; refinement beside the paper's ICP: "
        f"{describe_refinement(**fields)}; " + "; ".join(counts)
    )
    return Showcase(pd.DataFrame(rows), overlay, described)


def format_table(table: pd.DataFrame) -> str:
    """The showcase table as Markdown, percent with one decimal."""
    cols = ["data", "method", *COLUMNS.values()]
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * 2 + "---:|" * len(COLUMNS)]
    for _, r in table.iterrows():
        cells = [r["data"], r["method"], *(f"{r[c]:.1f}" for c in COLUMNS.values())]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
