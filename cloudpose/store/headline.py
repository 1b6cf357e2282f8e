"""Headline metrics and the MLflow UI view that compares variants by them.

A run logs hundreds of split-prefixed metrics (``test/...``, ``test_icp/class/<c>/...``), which
the reports read and which stay as they are. Four of them are what a comparison of variants
starts from; they are logged again as top-level keys (:data:`HEADLINE`), short names that a
runs table can show without searching 400 columns.

MLflow 3's runs table shows no metric until columns are chosen; a *saved view* (an experiment
tag ``mlflow.sharedViewState.<key>`` holding the table's state as JSON, the same tag that the
UI's "Views" menu writes) chooses them. :func:`prepare_ui` puts the view :data:`VIEW_KEY` on
every cloudpose experiment: finished runs grouped by their ``variant`` and ``preset`` tags, the
headline metrics averaged over the seeds of each group. :func:`view_url` opens it.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass

from cloudpose.store import tracking

HEADLINE: dict[str, str] = {
    "ads_auc": "test/ads_auc",
    "ads_auc_icp": "test_icp/ads_auc",
    "rot_sym_lt_10deg": "test/rot_sym_lt_10deg",
    "trans_lt_1cm": "test/trans_lt_1cm",
}
"""Headline key -> the detailed key it copies: ADS AUC (0.1 m threshold) of the network and
after ICP, and the shares of test instances with rotation error under 10 degrees modulo the
object's symmetry and translation error under 1 cm, all on the run's own test set (0-1)."""

VIEW_KEY = "variants"
"""Share key of the saved view (``?viewStateShareKey=variants`` in the experiment's URL)."""

VIEW_NAME = "Variants: headline metrics, mean over seeds"
"""The view's name in the UI's "Views" menu."""

_VIEW_TAG = "mlflow.sharedViewState." + VIEW_KEY
_KIND_TAG = "mlflow.experimentKind"
_KIND = "custom_model_development"  # the UI's "Model training" layout, not its GenAI one
_RUN_NAME_COLUMN = "attributes.`Run Name`"
_START_COLUMN = "runDateAndNestInfo"
_GROUP_TAGS = ("variant", "preset")


def _group_id(values: tuple[str, ...]) -> str:
    """The UI's id of the group of runs whose :data:`_GROUP_TAGS` have ``values``."""
    return ",".join(f"tag.{tag}.{v or 'null'}" for tag, v in zip(_GROUP_TAGS, values, strict=True))


def headline(metrics: Mapping[str, float]) -> dict[str, float]:
    """The headline metrics found among ``metrics`` (detailed keys), finite ones only."""
    out = {}
    for key, source in HEADLINE.items():
        value = metrics.get(source)
        if value is not None and math.isfinite(value):
            out[key] = float(value)
    return out


def view_state(groups: list[tuple[str, str]] = ()) -> dict:
    """The runs table's state of :data:`VIEW_KEY`: the search facets (filter, order) and the UI
    state (columns, grouping) that the MLflow UI stores in a saved view.

    Finished runs with headline metrics, grouped by the tags ``variant`` and ``preset`` (runs
    of the smoke and the cpu preset share an experiment), the headline metrics averaged over
    each group's seeds. The ``groups`` given, ``(variant, preset)`` pairs, start collapsed (one
    row of means each); the UI opens a group it is not told about.
    """
    metrics = [f"metrics.`{k}`" for k in HEADLINE]
    return {
        "searchFilter": f"metrics.{next(iter(HEADLINE))} >= 0 and attributes.status = 'FINISHED'",
        "orderByKey": "tags.`mlflow.runName`",
        "orderByAsc": True,
        "selectedColumns": metrics,
        # ag-grid column ids: the metrics beside the run name (wide enough for a group's name
        # and 7 digits), then the start time
        "columnOrder": [_RUN_NAME_COLUMN, *metrics, _START_COLUMN, "duration"],
        "columnWidths": {_RUN_NAME_COLUMN: 360, _START_COLUMN: 120, **{m: 140 for m in metrics}},
        "groupBy": {
            "aggregateFunction": "average",
            "groupByKeys": [{"mode": "tag", "groupByData": tag} for tag in _GROUP_TAGS],
        },
        "groupsExpanded": {_group_id(g): False for g in sorted(groups)},
        "runsHiddenMode": "SHOW_ALL",
        "useGroupedValuesInCharts": True,
        "hideEmptyCharts": True,
    }


def view_url(base: str, experiment_id: str) -> str:
    """The address of an experiment's runs table in :data:`VIEW_KEY` (``base``: the UI's
    ``http://HOST:PORT``), in the UI's "Model training" mode."""
    return (
        f"{base.rstrip('/')}/#/experiments/{experiment_id}/runs"
        f"?viewStateShareKey={VIEW_KEY}&workflowType=machine_learning"
    )


@dataclass(frozen=True)
class Prepared:
    """One experiment made ready for the UI by :func:`prepare_ui`."""

    experiment_id: str
    name: str
    runs: int
    """Runs with headline metrics (the view shows the finished ones, grouped)."""
    backfilled: int
    """Runs whose headline metrics were logged now (stored before they existed, or stale)."""


def backfill(client, experiment_id: str) -> tuple[list, int]:
    """Log the headline metrics of every run of the experiment that lacks them or holds
    other values than its detailed keys; a second call logs nothing.

    Returns:
        (the runs with headline metrics, how many of them were given them now).
    """
    runs = client.search_runs([experiment_id], "tags.variant IS NOT NULL", max_results=50000)
    evaluated, changed = [], 0
    for run in runs:
        have = run.data.metrics
        want = headline(have)
        if want:
            evaluated.append(run)
        want = {k: v for k, v in want.items() if have.get(k) != v}
        if want:
            client.log_batch(run.info.run_id, metrics=tracking.metric_batch(want))
            changed += 1
    return evaluated, changed


def install_view(client, experiment, groups: list[tuple[str, str]] = ()) -> bool:
    """Put the saved view :data:`VIEW_KEY` (:func:`view_state` of ``groups``) and the
    "Model training" kind on ``experiment`` (an MLflow ``Experiment``); True if a tag was
    written, False if both were current."""
    state = json.dumps(view_state(groups), sort_keys=True)
    tags = experiment.tags
    old = tags.get(_VIEW_TAG)
    try:
        envelope = json.loads(old) if old else None
    except json.JSONDecodeError:
        envelope = None
    wrote = False
    if not isinstance(envelope, dict) or envelope.get("state") != state:
        now = int(time.time() * 1000)
        created = envelope.get("createdAt", now) if isinstance(envelope, dict) else now
        value = {"name": VIEW_NAME, "createdAt": created, "updatedAt": now, "state": state}
        client.set_experiment_tag(experiment.experiment_id, _VIEW_TAG, json.dumps(value))
        wrote = True
    if tags.get(_KIND_TAG) != _KIND:
        client.set_experiment_tag(experiment.experiment_id, _KIND_TAG, _KIND)
        wrote = True
    return wrote


def prepare_ui(client) -> list[Prepared]:
    """Every cloudpose experiment with its headline metrics back-filled and its saved view
    installed (:func:`backfill`, :func:`install_view`), by name."""
    out = []
    exps = client.search_experiments()
    for exp in sorted(exps, key=lambda e: e.name):
        if not exp.name.startswith(tracking.EXPERIMENT_PREFIX):
            continue
        runs, changed = backfill(client, exp.experiment_id)
        groups = {tuple(r.data.tags.get(t, "") for t in _GROUP_TAGS) for r in runs}
        install_view(client, exp, sorted(groups))
        out.append(Prepared(exp.experiment_id, exp.name, len(runs), changed))
    return out


def ui_command(backend: str, host: str = "127.0.0.1", port: int = 5000) -> list[str]:
    """argv of the MLflow UI on ``backend`` (this interpreter's MLflow, one worker)."""
    import sys

    return [
        sys.executable,
        "-m",
        "mlflow",
        "ui",
        "--backend-store-uri",
        backend,
        "--host",
        host,
        "--port",
        str(port),
        "--workers",
        "1",
    ]
