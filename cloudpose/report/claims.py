"""Every difference the paper claims, measured over seeds, with a verdict.

The paper (Gao et al., ICRA 2020) claims: two separate networks beat every amount of sharing
(Table III); axis-angle beats the quaternion (Table IV); the geodesic loss beats L2 on axis-angle
(Table IV); ICP improves the network's estimate (Table I). Each claim is tested on the metrics of
its table, as ``favoured - other`` in percentage points.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import pandas as pd

from cloudpose.config import get_group
from cloudpose.report.formats import Provenance
from cloudpose.report.runs import RunSet
from cloudpose.report.stats import MIN_SEEDS, UNRESOLVED, Difference, difference
from cloudpose.report.tables import METRIC_LABELS, paper_table


@dataclass(frozen=True)
class Claim:
    """``favoured`` beats ``other`` on ``metric`` (a fraction, larger is better).

    Attributes:
        topic: the section of claims.md.
        statement: the claim in words.
        favoured, other: (variant, metric prefix) of each side, e.g. ("shared-0", "test_icp").
        metric: metric name without prefix (``ads_auc``).
        paper: the paper's difference in percentage points (NaN when it has none).
    """

    topic: str
    statement: str
    favoured: tuple[str, str]
    other: tuple[str, str]
    metric: str
    paper: float


@dataclass(frozen=True)
class ClaimResult:
    claim: Claim
    diff: Difference


def paper_claims() -> list[Claim]:
    """The claims, with the paper's own differences from its tables."""
    claims = []
    t3 = paper_table("table3_shared_layers").set_index("shared_layers")
    t3.index = t3.index.astype(str)
    shared = get_group("shared")
    # rot_sym_*: the rotation error modulo symmetry (no paper value; see table4_rotation)
    cols3 = {
        "ad_auc": "AD_auc",
        "ads_auc": "ADS_auc",
        "rot_lt_10deg": "rot_err_lt_10deg",
        "rot_sym_lt_10deg": None,
        "trans_lt_1cm": "trans_err_lt_1cm",
    }
    for v in shared.members[1:]:
        label = shared.labels.get(v, v)
        for m, col in cols3.items():
            known = col is not None and label in t3.index
            paper = (t3.loc["none", col] - t3.loc[label, col]) if known else math.nan
            claims.append(
                Claim(
                    "Separate networks vs shared layers (Table III, without ICP)",
                    f"separate (none) beats shared {label}",
                    ("shared-0", "test"),
                    (v, "test"),
                    m,
                    float(paper),
                )
            )
    t4 = paper_table("table4_rotation").set_index(["ablation", "variant"])
    cols4 = {
        "rot_lt_10deg": "rot_err_lt_10deg",
        "rot_lt_15deg": "rot_err_lt_15deg",
        "rot_lt_20deg": "rot_err_lt_20deg",
        "rot_sym_lt_10deg": None,
        "rot_sym_lt_20deg": None,
    }
    for topic, section, fav, oth, other_variant in (
        (
            "Axis-angle vs quaternion (Table IV, without ICP)",
            "representation",
            "axis-angle",
            "quaternion",
            "quaternion",
        ),
        ("Geodesic vs L2 rotation loss (Table IV, without ICP)", "loss", "geodesic", "L2", "l2"),
    ):
        for m, col in cols4.items():
            paper = (
                math.nan
                if col is None
                else t4.loc[(section, fav), col] - t4.loc[(section, oth), col]
            )
            claims.append(
                Claim(
                    topic,
                    f"{fav} beats {oth}",
                    ("shared-0", "test"),
                    (other_variant, "test"),
                    m,
                    float(paper),
                )
            )
    for m in ("rot_sym_lt_10deg", "rot_sym_lt_20deg", "ads_auc"):
        # ours, not the paper's: training modulo symmetry against the plain geodesic loss
        claims.append(
            Claim(
                "Loss modulo symmetry vs plain geodesic (ours, without ICP)",
                "modulo symmetry beats plain",
                ("shared-0", "test"),
                ("geodesic-plain", "test"),
                m,
                math.nan,
            )
        )
    t1 = paper_table("table1_overall").set_index("method")
    cols1 = {"ad_auc": "AD_auc", "ads_auc": "ADS_auc", "ads_lt_1cm": "ADS_lt_1cm"}
    for m, col in cols1.items():
        paper = t1.loc["Ours", col] - t1.loc["Ours w/o ICP", col]
        claims.append(
            Claim(
                "With vs without ICP (Table I, shared-0)",
                "ICP improves the estimate",
                ("shared-0", "test_icp"),
                ("shared-0", "test"),
                m,
                float(paper),
            )
        )
    return claims


def evaluate_claims(runs: RunSet, claims: list[Claim] | None = None) -> list[ClaimResult]:
    """Measure every claim on ``runs`` (values as fractions; differences in fractions)."""
    out = []
    for c in claims if claims is not None else paper_claims():
        a = runs.values(c.favoured[0], f"{c.favoured[1]}/{c.metric}")
        b = runs.values(c.other[0], f"{c.other[1]}/{c.metric}")
        out.append(ClaimResult(c, difference(a, b, expect=1)))
    return out


def _pp(x: float, signed: bool = True) -> str:
    if not math.isfinite(x):
        return "–"
    return f"{100 * x:+.1f}" if signed else f"{100 * x:.1f}"


def claims_frame(results: list[ClaimResult]) -> pd.DataFrame:
    """One row per claim and metric; differences in percentage points."""
    return pd.DataFrame(
        [
            {
                "topic": r.claim.topic,
                "claim": r.claim.statement,
                "favoured": "/".join(r.claim.favoured),
                "other": "/".join(r.claim.other),
                "metric": r.claim.metric,
                "paper_diff_pp": r.claim.paper,
                "diff_pp": 100 * r.diff.mean,
                "ci_low_pp": 100 * r.diff.low,
                "ci_high_pp": 100 * r.diff.high,
                "seeds": r.diff.n,
                "paired": r.diff.paired,
                "verdict": r.diff.verdict,
                "why_unresolved": r.diff.why,
            }
            for r in results
        ]
    )


def claims_markdown(results: list[ClaimResult], prov: Provenance) -> str:
    """claims.md: per topic, one row per metric with the paper's and our difference."""
    lines = [
        "# The paper's claims, measured over seeds",
        "",
        f"_{prov.line()}_",
        "",
        "Each row: the difference favoured − other in percentage points (pp), as the paper "
        "printed it (one run, real YCB-Video) and as we measure it (mean over seeds, paired by "
        "seed; 95% confidence interval from Student's t over seeds). Verdict: **supported** when "
        "the interval lies above 0, **contradicted** when it lies below 0, **not resolved at this "
        f"size** when it contains 0, when fewer than {MIN_SEEDS} seeds are available, or when "
        "it has zero width (every seed's difference the same: a spread below the test set's "
        "resolution, not certainty).",
        "",
    ]
    counts: dict[str, int] = {}
    for r in results:
        counts[r.diff.verdict] = counts.get(r.diff.verdict, 0) + 1
    lines.append("Summary: " + "; ".join(f"{v}: {n}" for v, n in sorted(counts.items())) + ".")
    why: dict[str, int] = {}
    for r in results:
        if r.diff.why:
            why[r.diff.why] = why.get(r.diff.why, 0) + 1
    if why:
        lines.append(
            "Not resolved because: " + "; ".join(f"{w} ({n})" for w, n in sorted(why.items())) + "."
        )
    n_ci = sum(math.isfinite(r.diff.low) for r in results)
    if n_ci:
        lines += [
            "",
            f"{n_ci} intervals at 95% each, not corrected for multiple comparisons: were "
            f"no claimed difference real, about {0.05 * n_ci:.1f} of them would still exclude "
            "0 by chance, so a lone verdict among many unresolved rows is weak evidence.",
        ]
    topic = None
    for r in results:
        c, d = r.claim, r.diff
        if c.topic != topic:
            topic = c.topic
            lines += [
                "",
                f"## {topic}",
                "",
                "| claim | metric | paper (pp) | ours (pp) | 95% CI (pp) | seeds | verdict |",
                "|---|---|---:|---:|---:|---:|---|",
            ]
        ci = f"[{_pp(d.low)}, {_pp(d.high)}]" if math.isfinite(d.low) else "–"
        seeds = f"{d.n}" + ("" if d.paired or d.n < 2 else " (unpaired)")
        verdict = f"**{d.verdict}**" if d.verdict != UNRESOLVED else f"{d.verdict} ({d.why})"
        lines.append(
            f"| {c.statement} | {METRIC_LABELS.get(c.metric, c.metric)} | "
            f"{_pp(c.paper / 100)} | {_pp(d.mean)} | {ci} | {seeds} | {verdict} |"
        )
    return "\n".join(lines) + "\n"
