"""Pose error metrics and their summaries, as the YCB-Video toolbox computes them.

docs/design.md "Metrics":

- AD  = mean over model points x of |(R x + t) - (R^ x + t^)|                  (metres)
- ADS = mean over x1 of min over x2 of |(R x1 + t) - (R^ x2 + t^)|             (metres)
- rotation error = geodesic angle between R and R^ (degrees); translation error = |t - t^|.
- AUC = the toolbox's VOCap of the accuracy-threshold curve up to 0.1 m (``voc_ap_auc``).
- "<1cm" = share of instances with ADS < 0.01 m; rotation / translation shares likewise.

Arguments come in bop_toolkit's order, estimate first; AD, ADS and ``pose_errors`` take the
poses by keyword (``R_est=, t_est=, R_gt=, t_gt=``: ADS is not symmetric in them), see
``errors``.

A miss (an instance without a usable segment or estimate) is never dropped: its errors are
infinite and it counts in every denominator, as in the toolbox.

Fast and reference twins: ``add_distance`` / ``adds_distance`` evaluate many instances at once
(ADS maps the ground-truth-posed points into the estimate's model frame, q = R^T((R x + t) - t^),
and queries the model's ``kernels.model_index.ModelIndex``, built once per model and shared with ICP);
``add_distance_reference`` / ``adds_distance_reference`` loop over instances and, for ADS, build a KD-tree on every
estimate as bop_toolkit's ``adi`` does. Tests show they agree.

Where numba is installed, ``adds_distance`` runs the compiled kernel
``cloudpose.kernels.adds_mean`` (parallel over instances): each nearest neighbour is found by a
downhill walk over the model's Delaunay graph, starting at the point's own model point or the
previous point's neighbour; the walk ends in the query's Voronoi cell, so the neighbour is
exact. The pykdtree path stays as the fallback and as a test twin.

Modules: ``errors`` (per-instance errors) and ``summaries`` (AUC, shares, tables, occlusion
bins); everything is importable from ``cloudpose.metrics``.
"""

from cloudpose.metrics.errors import (
    add_distance,
    add_distance_reference,
    adds_distance,
    adds_distance_reference,
    pose_errors,
    rotation_error_deg,
    translation_error,
)
from cloudpose.metrics.summaries import (
    AUC_MAX_THRESHOLD,
    SUMMARY_KEYS,
    accuracy_curve,
    flatten_summary,
    fraction_below,
    occlusion_bin_index,
    occlusion_bins,
    per_class_table,
    stage_summary,
    summarize,
    voc_ap_auc,
)

__all__ = [
    "AUC_MAX_THRESHOLD",
    "SUMMARY_KEYS",
    "accuracy_curve",
    "add_distance",
    "add_distance_reference",
    "adds_distance",
    "adds_distance_reference",
    "flatten_summary",
    "fraction_below",
    "occlusion_bin_index",
    "occlusion_bins",
    "per_class_table",
    "pose_errors",
    "rotation_error_deg",
    "stage_summary",
    "summarize",
    "translation_error",
    "voc_ap_auc",
]
