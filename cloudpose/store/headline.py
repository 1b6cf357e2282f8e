"""Headline metrics: the four figures a comparison of variants starts from.

A run logs dozens of split-prefixed summary metrics (``test/...``, ``test_icp/class_mean/...``;
its per-class and per-video detail are tables, :mod:`cloudpose.store.metric_names`, where runs
logged before keep ~2,000 keys), which the reports read. Four of them are logged again as top-level keys (:data:`HEADLINE`, 0-1), short
names that a runs table can show without searching 2,000 columns; the MLflow UI's comparison
views (:mod:`cloudpose.report.ui`) start from them.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

HEADLINE: dict[str, str] = {
    "ads_auc": "test/ads_auc",
    "ads_auc_icp": "test_icp/ads_auc",
    "rot_sym_lt_10deg": "test/rot_sym_lt_10deg",
    "trans_lt_1cm": "test/trans_lt_1cm",
}
"""Headline key -> the detailed key it copies: ADS AUC (0.1 m threshold) of the network and
after ICP, and the shares of test instances with rotation error under 10 degrees modulo the
object's symmetry and translation error under 1 cm, all on the run's own test set (0-1)."""


def headline(metrics: Mapping[str, float]) -> dict[str, float]:
    """The headline metrics found among ``metrics`` (detailed keys), finite ones only."""
    out = {}
    for key, source in HEADLINE.items():
        value = metrics.get(source)
        if value is not None and math.isfinite(value):
            out[key] = float(value)
    return out
