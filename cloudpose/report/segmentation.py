"""The segmentation-quality report: shared-0, trained on ground-truth masks, tested under each
mask source (``cloudpose ablate-masks`` makes the evaluations).

The paper tests with PoseCNN's segmentation; the default data has only ground truth, so
:mod:`cloudpose.data.masks` imitates a segmentation network's errors at three strengths. Each
run of shared-0 holds one evaluation of its own test set per source, each with the network's
estimate and the estimate after ICP: ``eval/test/instances.csv`` for ground truth,
``eval/test-degraded-medium/instances.csv`` and so on (:func:`cloudpose.store.metric_names.own_test_name`).
From those per-instance tables:

- ``table_masks`` (.md, .tex, .csv): per source, ADS AUC, AD AUC, ADS < 2 cm and rotation error
  modulo symmetry < 10° without and with ICP, and the misses; mean ± sample std over seeds,
  beside the paper's figures (tested with PoseCNN's masks on real YCB-Video);
- ``occlusion_masks`` (.png, .csv): ADS < 1 cm accuracy per occlusion bin, one series per source
  and method. A miss is a failure in its bin: its occlusion factor comes from the ground-truth
  labels whatever the masks.
"""

from __future__ import annotations

import math
from pathlib import Path

import pandas as pd

from cloudpose.data.masks import DEGRADATIONS
from cloudpose.metrics import fraction_below, voc_ap_auc
from cloudpose.report import plots
from cloudpose.report.formats import Provenance, Table
from cloudpose.report.runs import RunSet
from cloudpose.report.stats import format_mean_std, mean_std
from cloudpose.report.tables import METRIC_LABELS, paper_table
from cloudpose.store.metric_names import own_test_name

__all__ = [
    "GROUP",
    "SOURCES",
    "describe_source",
    "instance_figures",
    "mask_source_evaluation_name",
    "render",
    "source_tables",
    "table_masks",
]

GROUP = "masks"
"""The report's name: ``cloudpose report --group masks``, MLflow run ``report/masks/{preset}``."""

VARIANT = "shared-0"
"""The network every mask source is tested with (trained on ground-truth masks)."""

SOURCES = ("gt", *DEGRADATIONS)
"""The mask sources of the ablation, ground truth first, then the degradations mildest first."""

METRICS = {
    "ads_auc": ("ads", None),
    "ad_auc": ("ad", None),
    "ads_lt_2cm": ("ads", 0.02),
    "rot_sym_lt_10deg": ("rot_sym_err_deg", 10.0),
}
"""Table columns: key -> (instance-table error column without its method prefix, threshold;
None = the toolbox's AUC up to 10 cm). Thresholds in metres, or degrees for rotations."""

LABELS = METRIC_LABELS | {"ads_lt_2cm": "ADS < 2 cm"}

METHODS = {"net": "w/o ICP", "icp": "+ ICP"}
"""Instance-table method prefixes and their column labels."""


def mask_source_evaluation_name(source: str) -> str:
    """Metric prefix and artifact folder of shared-0's evaluation of its own test set under
    mask source ``source`` (one of :data:`SOURCES`)."""
    return own_test_name(None if source == "gt" else source)


def describe_source(source: str) -> str:
    """What a mask source is, in words (``boundary ±4 px, bleeding 4 px, 5% missed``)."""
    if source == "gt":
        return "ground-truth labels"
    how = DEGRADATIONS.get(source)
    if how is None:
        return ""
    return (
        f"boundary ±{how.boundary_px} px, bleeding {how.bleed_px} px, "
        f"{100 * how.miss_rate:g}% missed"
    )


def source_tables(runs: RunSet, source: str) -> dict[int, pd.DataFrame]:
    """seed -> shared-0's per-instance table under ``source`` (seeds without one left out)."""
    name = mask_source_evaluation_name(source)
    return {r.seed: t for r in runs.of(VARIANT) if (t := r.instances(name)) is not None}


def instance_figures(table: pd.DataFrame, method: str) -> dict[str, float]:
    """The table's figures of one method, as fractions (NaN where the table lacks a column).

    Args:
        table: per-instance table (:func:`cloudpose.methods.instance_table`); errors in
            metres and degrees, inf for misses.
        method: "net" or "icp".

    Returns:
        ``{key: value}`` for every key of :data:`METRICS`.
    """
    out = {}
    for key, (column, threshold) in METRICS.items():
        col = f"{method}_{column}"
        if col not in table:
            out[key] = math.nan
            continue
        values = table[col].to_numpy(float)
        out[key] = voc_ap_auc(values) if threshold is None else fraction_below(values, threshold)
    return out


def _misses(tables: dict[int, pd.DataFrame]) -> tuple[str, dict[str, float]]:
    counts = [int(t["miss"].astype(bool).sum()) for t in tables.values()]
    sizes = sorted({len(t) for t in tables.values()})
    ms = mean_std(counts)
    of = "/".join(map(str, sizes))
    same = ms.n == 1 or ms.std == 0
    text = f"{ms.mean:.0f} of {of}" if same else f"{ms.mean:.1f} ± {ms.std:.1f} of {of}"
    return text, {"misses_mean": ms.mean, "misses_std": ms.std, "instances": sizes[-1]}


def table_masks(runs: RunSet, tables: dict[str, dict[int, pd.DataFrame]]) -> Table:
    """The mask ablation's table: one row per mask source with evaluations, the paper's first.

    Args:
        runs: the shared-0 runs (for the data label).
        tables: source -> seed -> per-instance table (:func:`source_tables`).
    """
    header = [("", "mask source"), ("", "masks")]
    for key in METRICS:
        header += [(LABELS[key], label) for label in METHODS.values()]
    header += [("", "misses"), ("", "seeds")]
    paper = paper_table("table1_overall").set_index("method")
    paper_values = {
        ("ads_auc", "net"): paper.loc["Ours w/o ICP", "ADS_auc"],
        ("ads_auc", "icp"): paper.loc["Ours", "ADS_auc"],
        ("ad_auc", "net"): paper.loc["Ours w/o ICP", "AD_auc"],
        ("ad_auc", "icp"): paper.loc["Ours", "AD_auc"],
    }
    cells = ["PoseCNN (paper)", "PoseCNN's segmentation, real YCB-Video"]
    row: dict = {"source": "paper: PoseCNN", "masks": cells[1]}
    for key in METRICS:
        for method in METHODS:
            v = float(paper_values.get((key, method), math.nan))
            cells.append("–" if math.isnan(v) else f"{v:.1f}")
            row[f"{key}_{method}_mean"], row[f"{key}_{method}_std"] = v, math.nan
    rows: list[list[str] | None] = [[*cells, "–", "1"], None]
    data = [row | {"seeds": 1}]
    for source, by_seed in tables.items():
        if not by_seed:
            continue
        cells = [source, describe_source(source)]
        row = {"source": source, "masks": cells[1]}
        for key in METRICS:
            for method in METHODS:
                ms = mean_std([instance_figures(t, method)[key] for t in by_seed.values()])
                cells.append(format_mean_std(ms))
                row[f"{key}_{method}_mean"], row[f"{key}_{method}_std"] = (
                    ms.mean * 100,
                    ms.std * 100,
                )
        text, counts = _misses(by_seed)
        rows.append([*cells, text, str(len(by_seed))])
        data.append(row | counts | {"seeds": len(by_seed)})
    notes = [
        f"Rows: {VARIANT}, trained once per seed on ground-truth masks, tested on its own test "
        "set segmented by each source (`cloudpose/data/masks.py` imitates a segmentation "
        "network: boundary eroded or dilated, labels bleeding into touching objects, missed "
        f"detections); mean ± sample std over seeds on {runs.data_label()}; percent, computed "
        "from each run's per-instance table.",
        "misses: instances whose mask leaves no usable point; each is a failure in every "
        "column (infinite error), with and without ICP.",
        "Paper row: Gao et al. (ICRA 2020), Table I, 'Ours' without and with ICP, tested with "
        "PoseCNN's segmentation on real YCB-Video; the paper gives no ADS < 2 cm, rotation "
        "share or miss count (its ADS < 1 cm: "
        f"{paper.loc['Ours w/o ICP', 'ADS_lt_1cm']:.1f} without, "
        f"{paper.loc['Ours', 'ADS_lt_1cm']:.1f} with ICP).",
    ]
    return Table(
        "table_masks",
        f"Segmentation quality: {VARIANT} under each test-time mask source (%)",
        header,
        rows,
        pd.DataFrame(data),
        notes,
        text_cols=2,
    )


def occlusion_series(tables: dict[str, dict[int, pd.DataFrame]]) -> list[plots.Series]:
    """One series per source and method: every source's network alone, then each + ICP."""
    out = []
    for method in METHODS:
        for source, by_seed in tables.items():
            seeds = list(by_seed.values())
            if seeds and f"{method}_ads" in seeds[0]:
                suffix = ", network alone" if method == "net" else " + ICP"
                out.append(plots.Series(f"{source}{suffix}", seeds, method))
    return out


def render(runs: RunSet, out_dir: Path, command: str, renderer: str = "") -> list[Path]:
    """Write ``table_masks`` and ``occlusion_masks`` into ``out_dir``; nothing (an empty list)
    when no shared-0 run has an evaluation under a mask source other than ground truth."""
    base = runs.subset([VARIANT])
    tables = {s: source_tables(base, s) for s in SOURCES}
    if not any(tables[s] for s in SOURCES if s != "gt"):
        return []
    prov = Provenance.of(base, command, renderer)
    files = table_masks(base, tables).write(out_dir, prov)
    series = occlusion_series(tables)
    files.append(
        plots.plot_occlusion(
            series,
            out_dir / "occlusion_masks.png",
            prov,
            f"ADS < 1 cm accuracy vs occlusion, {VARIANT} under each mask source",
        )
    )
    csv = out_dir / "occlusion_masks.csv"
    frame = plots.occlusion_frame(series)
    csv.write_text(
        f"# {prov.line()}\n" + frame.to_csv(index=False, float_format="%.2f"), encoding="utf-8"
    )
    files.append(csv)
    return files
