"""The MLflow UI made ready to compare variants by their headline metrics
(:mod:`cloudpose.store.headline`): the report's runs, tables and links, as saved views.

A run logs dozens of split-prefixed summary metrics (``test/...``, ``test_icp/class_mean/...``;
a run logged before the per-class and per-video detail tables of
:mod:`cloudpose.store.metric_names` also ~2,000 detail keys), which the reports read and which
stay as they are. Four of them are what a comparison of variants
starts from; they are logged again as top-level keys (:data:`HEADLINE`, 0-1), short names that
a runs table can show without searching 2,000 columns.

:func:`prepare_ui` (``cloudpose mlflow-ui``) makes a store ready for the MLflow UI (3.x):

- **Which runs count.** Per preset, the runs the report's tables are made of, chosen by the
  report's own function (:func:`cloudpose.report.runs.load_runs`: the preset's own config, the
  data most seeds were trained on, the newest finished run per (variant, seed)). Every other
  evaluated run of the preset gets a tag ``superseded`` saying why it does not count (a newer
  run of its seed, another config, other data).
- **Comparisons.** One per ablation group and preset (the registry's groups, and ``baselines``:
  shared-0 beside the classical baselines, Table I), holding every member with counted runs,
  the reference shared-0 included wherever it was logged. A counted run carries the tag
  ``{group}.{preset}`` (e.g. ``rotation.cpu-online``) of each comparison it belongs to, its
  value the row's name (``shared-0, axis-angle``); the group's report run
  ``report/{group}/{preset}`` carries it too (``report: tables and plots``), so the view has a
  link to every table and plot.
- **Columns in percent.** The statistics of each variant over its counted seeds, computed as
  the report's tables compute them (mean and sample std, rounded to one decimal as the tables
  print them), are logged on each of its counted runs as :func:`stat_keys` (``ADS AUC mean``,
  ``ADS AUC sd``, ..., ``seeds``). A view groups the runs by the comparison's tag with the
  aggregate *maximum*, which of equal values is that value: the group's row shows the report's
  numbers exactly (MLflow's *average* of equal floats is not always that float). A run that no
  longer counts has them set to NaN.
- **Saved views.** MLflow keeps a shared view of the runs table as an experiment tag
  ``mlflow.sharedViewState.<key>`` (what its "Views" menu writes) and opens it from
  ``?viewStateShareKey=<key>``. A comparison's view (key ``{group}.{preset}``) filters on its
  tag; when its runs lie in several experiments (shared-0 is trained once, in one group's
  experiment) it opens in MLflow's multi-experiment runs table
  (``#/compare-experiments/s?experiments=[...]``), which reads the view from the first of its
  experiments, so the view is put on each of them (:func:`view_path`). Its chart view shows only
  the statistics (``chartsSearchFilter``): MLflow adds a chart for every metric key of the
  runs it loads and offers no way to stop that; the filter keeps it from drawing them.
- **Descriptions.** Each experiment's description (``mlflow.note.content``) starts with a line
  naming its comparison in words, then the comparison's table (the same numbers as the grid),
  links to its views and report run, and the report's own note.
- **Dead runs.** A run left RUNNING by a process that is gone (no lock on its run folder here,
  and a later run of its seed, or no metric logged for :data:`~cloudpose.store.liveness.STALE_AFTER_S`) is marked KILLED
  with the tag ``marked_killed`` saying why; resuming it works as for any unfinished run.
- **Paths.** A ``run_dir`` tag naming another machine's folder becomes the run folder's place
  in this project (``runs/{variant}/{preset}/{folder}``), one inside the project relative to it.

Every step writes only what differs, so a second call writes nothing.
"""

from __future__ import annotations

import json
import math
import sys
import time
import warnings
from collections import defaultdict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from urllib.parse import quote

from cloudpose.archive.pack import relative_run_dir
from cloudpose.baselines.base import is_current
from cloudpose.data.keys import same_data
from cloudpose.registry import groups
from cloudpose.report.runs import load_runs
from cloudpose.report.stats import mean_std
from cloudpose.report.tables import BASELINE_LABELS
from cloudpose.store import tracking
from cloudpose.store.headline import HEADLINE, headline
from cloudpose.store.liveness import KILLED_TAG, dead_runs, when
from cloudpose.store.runs import TRAINING_PREFIXES, folder_locked, is_preset_config

COLUMNS: dict[str, str] = {
    "ads_auc": "ADS AUC",
    "ads_auc_icp": "ADS AUC ICP",
    "rot_sym_lt_10deg": "rot lt 10deg sym",
    "trans_lt_1cm": "trans lt 1cm",
}
"""Headline key -> the name of its two columns in a comparison view, ``{name} mean`` and
``{name} sd`` (percent, over the variant's counted seeds)."""

SEEDS = "seeds"
"""Metric of a counted run: how many seeds its variant has in the comparison."""

REFERENCE = "shared-0"
"""The network every group is compared with (the paper's, Table I's row)."""

BASELINES = "baselines"
"""The comparison of the classical baselines with :data:`REFERENCE` (Table I)."""

TITLES: dict[str, str] = {
    "shared": "Shared layers: how many the rotation and translation networks share",
    "rotation": "Rotation representation: axis-angle, quaternion or 6D",
    "loss": "Rotation loss: geodesic or L2",
    "symmetry": "Symmetry in the loss: geodesic modulo symmetry or plain",
    "centre": "Translation centre: the segment's mean, median or trimmed mean",
    BASELINES: "Classical baselines beside the network: FPFH + RANSAC, PPF",
    "masks": "Test-time masks: shared-0 under ground-truth and degraded masks",
    "diagnostics": "Diagnostics: runs with overrides, outside the report's tables",
}
"""The first line of an experiment's description (the experiments list shows about its first
25 characters): what its group compares, in words."""

PRIMARY: dict[str, str] = dict.fromkeys(("rotation", "loss", "symmetry"), "rot_sym_lt_10deg")
"""Headline key a comparison's view sorts its rows by (best first); ``ads_auc`` otherwise."""

REPORT_ROW = "report: tables and plots"
"""The row of a comparison's report run (its run page lists every table and plot)."""

SUPERSEDED = "superseded"
"""Tag of an evaluated run the report does not count: why."""

RUNS_VIEW = "runs"
"""Share key of the view of an experiment that holds no comparison (finished runs, newest first)."""

LEGACY_VIEWS = ("variants",)
"""Share keys of views that earlier versions of :func:`prepare_ui` wrote; removed."""

_VIEW_PREFIX = "mlflow.sharedViewState."
_NOTE = "mlflow.note.content"
_KIND_TAG = "mlflow.experimentKind"
_KIND = "custom_model_development"  # the UI's "Model training" layout, not its GenAI one
_RUN_NAME_COLUMN = "attributes.`Run Name`"
_START_COLUMN = "runDateAndNestInfo"
_NOTE_LIMIT = 20000  # MLflow's longest experiment tag value


def stat_keys() -> list[str]:
    """The metric keys of a comparison view's columns: mean and sd of each headline, seeds."""
    keys = []
    for name in COLUMNS.values():
        keys += [f"{name} mean", f"{name} sd"]
    return [*keys, SEEDS]


def shown(fraction: float) -> float:
    """A 0-1 figure as the report's tables print it: percent with one decimal (the float of
    :func:`cloudpose.report.stats.format_mean_std`'s text)."""
    return float(f"{fraction * 100.0:.1f}")


def variant_stats(values: Mapping[str, Sequence[float]], seeds: int) -> dict[str, float]:
    """The statistics columns of a variant (:func:`stat_keys`).

    Args:
        values: headline key -> its per-seed values (0-1), as the report reads them.
        seeds: the variant's counted runs.

    Returns:
        ``{name} mean`` and, with two seeds or more, ``{name} sd`` (sample std) in percent
        rounded as the report prints them (:func:`shown`), for each headline with a finite
        value; ``seeds``.
    """
    out: dict[str, float] = {}
    for key, name in COLUMNS.items():
        ms = mean_std(list(values.get(key, ())))
        if ms.n:
            out[f"{name} mean"] = shown(ms.mean)
            if ms.n > 1 and math.isfinite(ms.std):
                out[f"{name} sd"] = shown(ms.std)
    out[SEEDS] = float(seeds)
    return out


def format_stat(stats: Mapping[str, float], name: str) -> str:
    """``"91.3 ± 0.2"`` (one seed: ``"91.3"``; none: ``"–"``) from :func:`variant_stats`."""
    mean, sd = stats.get(f"{name} mean"), stats.get(f"{name} sd")
    if mean is None or not math.isfinite(mean):
        return "–"
    return f"{mean:.1f}" if sd is None or not math.isfinite(sd) else f"{mean:.1f} ± {sd:.1f}"


@dataclass(frozen=True)
class Row:
    """One variant of a comparison."""

    variant: str
    label: str
    """Its name in the group (the registry's label, e.g. ``axis-angle``)."""
    run_ids: tuple[str, ...] = ()
    """Its counted runs (one per seed)."""
    stats: dict[str, float] = field(default_factory=dict)
    """:func:`variant_stats` of those runs ({} without runs)."""

    @property
    def value(self) -> str:
        """The row's name: the value of the comparison's tag on its runs."""
        return self.variant if self.label == self.variant else f"{self.variant}, {self.label}"


@dataclass(frozen=True)
class GroupComparison:
    """The variants of one group on one preset, as the report's table compares them."""

    group: str
    preset: str
    data: str
    """Data fingerprint of the counted runs."""
    rows: tuple[Row, ...]
    report_run: str | None = None
    """Run id of the group's report run ``report/{group}/{preset}``, if there is one."""
    report_experiment: str = ""
    """Id of the experiment holding :attr:`report_run`."""
    experiments: tuple[str, ...] = ()
    """Ids of the experiments holding its runs and its report run, sorted."""

    @property
    def key(self) -> str:
        """Tag key on its runs and share key of its view: ``{group}.{preset}``."""
        return f"{self.group}.{self.preset}"

    def primary(self) -> str:
        """The column its view sorts by."""
        return f"{COLUMNS[PRIMARY.get(self.group, 'ads_auc')]} mean"


def group_title(group: str, rows: Iterable[Row] = ()) -> str:
    """:data:`TITLES` of ``group``; else ``Group: label, label, ...``."""
    if group in TITLES:
        return TITLES[group]
    labels = ", ".join(r.label for r in rows)
    return f"{group[:1].upper()}{group[1:]}" + (f": {labels}" if labels else "")


def comparison_members(variants: Iterable[str]) -> list[tuple[str, list[tuple[str, str]]]]:
    """The comparisons that ``variants`` (those with counted runs) make, each as its name and
    ``(variant, label)`` members in the group's order: every registry group with a member
    among them (all its members listed, those without runs too), and :data:`BASELINES`
    (:data:`REFERENCE` and every ``baseline-*`` variant) when a baseline is among them."""
    present = set(variants)
    out = []
    for g in groups().values():
        if present & set(g.members):
            out.append((g.name, [(v, g.labels.get(v, v)) for v in g.members]))
    baselines = sorted(v for v in present if v.startswith("baseline-"))
    if baselines:
        members = [(REFERENCE, "network")]
        members += [(b, BASELINE_LABELS.get(b, b.removeprefix("baseline-"))) for b in baselines]
        out.append((BASELINES, members))
    return out


def _group_id(key: str, value: str) -> str:
    """The UI's id of the group of runs whose tag ``key`` is ``value``."""
    return f"tag.{key}.{value}"


def comparison_view(comp: GroupComparison) -> dict:
    """The runs table's state of a comparison's view: the search facets (filter, order) and
    the UI state (columns, grouping, charts) that the MLflow UI keeps in a saved view.

    The runs carrying the comparison's tag, grouped by it (one row per variant, the report run
    a row of its own, open so that its name links to it), the statistics columns aggregated
    by their maximum (:func:`stat_keys`: equal on every run of a row), best row first; the
    chart view draws only those columns.
    """
    keys = stat_keys()
    metrics = [f"metrics.`{k}`" for k in keys]
    expanded = {_group_id(comp.key, r.value): False for r in comp.rows if r.run_ids}
    if comp.report_run:
        expanded[_group_id(comp.key, REPORT_ROW)] = True
    return {
        "searchFilter": f"tags.`{comp.key}` != ''",
        "orderByKey": f"metrics.`{comp.primary()}`",
        "orderByAsc": False,
        "selectedColumns": metrics,
        "columnOrder": [_RUN_NAME_COLUMN, *metrics, _START_COLUMN],
        "columnWidths": {_RUN_NAME_COLUMN: 320, **{m: _width(m) for m in metrics}},
        "groupBy": {
            "aggregateFunction": "max",
            "groupByKeys": [{"mode": "tag", "groupByData": comp.key}],
        },
        "groupsExpanded": expanded,
        "runsHiddenMode": "SHOW_ALL",
        "useGroupedValuesInCharts": True,
        "hideEmptyCharts": True,
        "chartsSearchFilter": "^(" + "|".join(keys) + ")$",
    }


def _width(column: str) -> int:
    """Pixels that show a metric column's whole header (``metrics.`KEY```)."""
    return max(84, 7 * len(column.removeprefix("metrics.`").removesuffix("`")) + 24)


def runs_view() -> dict:
    """The state of :data:`RUNS_VIEW`: an experiment's finished runs, newest first, with the
    per-run headline metrics (0-1)."""
    metrics = [f"metrics.`{k}`" for k in HEADLINE]
    return {
        "searchFilter": "attributes.status = 'FINISHED'",
        "orderByKey": "attributes.start_time",
        "orderByAsc": False,
        "selectedColumns": metrics,
        "columnOrder": [_RUN_NAME_COLUMN, *metrics, _START_COLUMN],
        "columnWidths": {_RUN_NAME_COLUMN: 320, **{m: _width(m) for m in metrics}},
        "runsHiddenMode": "SHOW_ALL",
        "hideEmptyCharts": True,
        "chartsSearchFilter": "^(" + "|".join(HEADLINE) + ")$",
    }


def view_name(comp: GroupComparison) -> str:
    """A comparison view's name in the UI's "Views" menu."""
    return f"{comp.group} ({comp.preset}): percent, mean and sd over seeds"


def view_path(experiments: Sequence[str], key: str) -> str:
    """The UI's address (after ``http://HOST:PORT/``) of view ``key`` over ``experiments``: an
    experiment's runs table, or MLflow's runs table of several experiments."""
    query = f"viewStateShareKey={quote(key)}&workflowType=machine_learning"
    if len(experiments) == 1:
        return f"#/experiments/{experiments[0]}/runs?{query}"
    ids = quote(json.dumps(sorted(experiments), separators=(",", ":")))
    return f"#/compare-experiments/s?experiments={ids}&{query}"


def view_url(base: str, experiments: Sequence[str], key: str) -> str:
    """:func:`view_path` on the UI at ``base`` (``http://HOST:PORT``)."""
    return f"{base.rstrip('/')}/{view_path(experiments, key)}"


def run_path(experiment_id: str, run_id: str, tab: str = "artifacts") -> str:
    """The UI's address of a run's page (its artifacts: every table and plot of a report run)."""
    return f"#/experiments/{experiment_id}/runs/{run_id}/{tab}"


# -- which runs count ------------------------------------------------------------------------


def superseded_reason(run, counted: Mapping[tuple[str, int], object], data: str | None) -> str:
    """Why an evaluated run of a preset is not among the report's runs (``counted``:
    (variant, seed) -> the counted run, ``data``: their data fingerprint)."""
    tags = run.data.tags
    key = (tags.get("variant", ""), int(tags.get("seed", 0) or 0))
    chosen = counted.get(key)
    if not _current(run):
        return (
            f"another config than the {tags.get('preset')} preset's own (overrides or an "
            "older preset): not in the report's tables"
        )
    if data is not None and not same_data(tags.get("data", ""), data):
        return f"trained on data {tags.get('data', '?')[:10]}; the report's runs on {data[:10]}"
    if chosen is not None:
        return (
            f"a newer run of {key[0]} seed {key[1]} counts instead: "
            f"{chosen.run_id} (started {when(chosen.start_time)})"
        )
    return "not among the report's runs"


def _current(run) -> bool:
    """The report's test of a run's config (:func:`cloudpose.report.runs.load_runs`)."""
    if run.data.tags.get("kind") == "baseline":
        return is_current(run)
    return is_preset_config(run)


def counted_runs(client, presets: Iterable[str]) -> dict[str, object]:
    """preset -> the report's :class:`~cloudpose.report.runs.RunSet` of it (its own warnings
    about left-out runs silenced: :func:`superseded_reason` tags each of them)."""
    out = {}
    for preset in sorted(set(presets)):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out[preset] = load_runs(preset, client=client)
    return out


def build_comparisons(
    runset, report_runs: Mapping[tuple[str, str], object], experiment_of: Mapping[str, str]
) -> list[GroupComparison]:
    """The comparisons of one preset's counted runs.

    Args:
        runset: the report's runs of the preset (:func:`counted_runs`).
        report_runs: (group, preset) -> the group's report run (an MLflow run).
        experiment_of: run id -> experiment id, of every run.
    """
    out = []
    for group, members in comparison_members(runset.variants):
        rows = []
        for variant, label in members:
            records = runset.of(variant)
            values = {k: list(runset.values(variant, src).values()) for k, src in HEADLINE.items()}
            stats = variant_stats(values, len(records)) if records else {}
            rows.append(Row(variant, label, tuple(r.run_id for r in records), stats))
        report = report_runs.get((group, runset.preset))
        if report is None and group == BASELINES:  # every report run carries Table I
            report = report_runs.get(("shared", runset.preset))
        report_id = report.info.run_id if report is not None else None
        ids = [i for r in rows for i in r.run_ids] + ([report_id] if report_id else [])
        exps = tuple(sorted({experiment_of[i] for i in ids if i in experiment_of}))
        comp = GroupComparison(group, runset.preset, runset.data_key or "", tuple(rows), report_id)
        out.append(
            replace(comp, experiments=exps, report_experiment=experiment_of.get(report_id, ""))
        )
    return out


# -- dead runs ---------------------------------------------------------------------------


def _folder_locked(run_dir: str | None, store: str | None = None) -> bool:
    """Whether a process on this machine holds the lock of run folder ``run_dir`` (a relative
    one under the folder of the SQLite store ``store``: :func:`tracking.store_path`)."""
    return folder_locked(tracking.store_path(run_dir, store) if run_dir else None)


def _last_activity(client, run) -> int:
    """The run's start or the last time it logged a training metric, in ms."""
    last = run.info.start_time or 0
    for key in run.data.metrics:
        if key.split("/")[0] in TRAINING_PREFIXES:
            for m in client.get_metric_history(run.info.run_id, key)[-1:]:
                last = max(last, m.timestamp)
    return last


def mark_dead(client, runs: Sequence, now_ms: int | None = None) -> list[tuple[object, str]]:
    """Mark KILLED each RUNNING run among ``runs`` that :func:`~cloudpose.store.liveness.dead_reason` finds dead (end
    time: its last activity), with the tag :data:`KILLED_TAG`; returns (run, why) of each."""
    now_ms = now_ms if now_ms is not None else int(time.time() * 1000)
    store = getattr(client, "tracking_uri", None)
    dead = dead_runs(
        [(r, r.info.status, r.info.start_time, _config_key(r)) for r in runs],
        now_ms,
        lambda r: _last_activity(client, r),
        lambda r: _folder_locked(r.data.tags.get("run_dir"), store),
    )
    for d in dead:
        client.set_tag(d.run.info.run_id, KILLED_TAG, f"{d.why}; marked by cloudpose mlflow-ui")
        client.set_terminated(d.run.info.run_id, "KILLED", end_time=d.last_activity_ms)
    return [(d.run, d.why) for d in dead]


def _config_key(run) -> tuple:
    t = run.data.tags
    return (t.get("variant"), t.get("preset"), t.get("seed"), t.get("config"))


# -- paths ------------------------------------------------------------------------------------


# -- writing --------------------------------------------------------------------------------


@dataclass(frozen=True)
class PreparedUI:
    """What :func:`prepare_ui` found and wrote."""

    comparisons: list[GroupComparison]
    experiments: dict[str, str]
    """Experiment id -> name, of every cloudpose experiment."""
    backfilled: int = 0
    """Runs whose headline metrics were logged now (stored before they existed, or stale)."""
    superseded: int = 0
    """Evaluated runs the report does not count (tagged :data:`SUPERSEDED`)."""
    killed: list[tuple[str, str]] = field(default_factory=list)
    """(run name, why) of each run marked KILLED now."""
    written: int = 0
    """Tags and metrics written (0 on a store already prepared)."""


def backfill(client, runs: Sequence) -> int:
    """Log the headline metrics of every run among ``runs`` that lacks them or holds other
    values than its detailed keys; returns how many runs were given them (a second call: 0)."""
    changed = 0
    for run in runs:
        have = run.data.metrics
        want = {k: v for k, v in headline(have).items() if have.get(k) != v}
        if want:
            client.log_batch(run.info.run_id, metrics=tracking.metric_batch(want))
            changed += 1
    return changed


def _same(a: float | None, b: float | None) -> bool:
    if a is None or b is None:
        return a is b
    return a == b or (math.isnan(a) and math.isnan(b))


def write_run(client, run, tags: Mapping[str, str | None], metrics: Mapping[str, float]) -> int:
    """Set ``tags`` (None: delete) and log ``metrics`` on ``run`` where they differ from what
    it holds; returns how many were written."""
    from mlflow.entities import RunTag

    have_t, have_m = run.data.tags, run.data.metrics
    set_tags = [RunTag(k, v) for k, v in tags.items() if v is not None and have_t.get(k) != v]
    drop = [k for k, v in tags.items() if v is None and k in have_t]
    new = {k: v for k, v in metrics.items() if not _same(have_m.get(k), v)}
    if set_tags or new:
        client.log_batch(run.info.run_id, metrics=tracking.metric_batch(new), tags=set_tags)
    for k in drop:
        client.delete_tag(run.info.run_id, k)
    return len(set_tags) + len(drop) + len(new)


def install_view(client, experiment, key: str, name: str, state: dict) -> bool:
    """Put the saved view ``key`` (``state``, named ``name``) and the "Model training" kind on
    ``experiment`` (an MLflow ``Experiment``); True if a tag was written, False if current."""
    text = json.dumps(state, sort_keys=True)
    tags = experiment.tags
    old = tags.get(_VIEW_PREFIX + key)
    try:
        envelope = json.loads(old) if old else None
    except json.JSONDecodeError:
        envelope = None
    wrote = False
    current = isinstance(envelope, dict)
    if not current or envelope.get("state") != text or envelope.get("name") != name:
        now = int(time.time() * 1000)
        created = envelope.get("createdAt", now) if current else now
        value = {"name": name, "createdAt": created, "updatedAt": now, "state": text}
        client.set_experiment_tag(experiment.experiment_id, _VIEW_PREFIX + key, json.dumps(value))
        wrote = True
    if tags.get(_KIND_TAG) != _KIND:
        client.set_experiment_tag(experiment.experiment_id, _KIND_TAG, _KIND)
        wrote = True
    return wrote


def comparison_table(comp: GroupComparison) -> str:
    """A comparison as a Markdown table: the grid's numbers (:func:`format_stat`)."""
    head = ["variant", comp.group, *[f"{n} (%)" for n in COLUMNS.values()], "seeds"]
    lines = ["| " + " | ".join(head) + " |", "|---|---|" + "---:|" * (len(head) - 2)]
    for r in comp.rows:
        cells = [format_stat(r.stats, n) for n in COLUMNS.values()]
        seeds = str(len(r.run_ids)) if r.run_ids else "no run"
        lines.append(f"| {r.variant} | {r.label} | " + " | ".join(cells) + f" | {seeds} |")
    return "\n".join(lines)


def description(
    title: str,
    own: Sequence[GroupComparison],
    others: Sequence[GroupComparison],
    report_note: str = "",
    runs_link: str = "",
) -> str:
    """An experiment's description: ``title`` on the first line (plain text: the experiments
    list shows it unrendered), the table and links of each comparison the experiment is named
    for (``own``), links to the other comparisons its runs appear in (``others``) or to its
    finished runs (``runs_link``), and the report's note."""
    parts = [title, ""]
    for comp in own:
        links = [f"[open the comparison]({view_path(comp.experiments, comp.key)})"]
        if comp.report_run:
            where = run_path(comp.report_experiment, comp.report_run)
            links.append(f"[the report's tables and plots]({where})")
        parts += [
            f"**{comp.preset}** (data {comp.data[:10]}): mean ± sample std over seeds, percent, "
            "of the runs the report counts (newest finished run per seed of the preset's own "
            "config); " + ", ".join(links) + ".",
            "",
            comparison_table(comp),
            "",
        ]
    if others:
        links = ", ".join(
            f"[{c.group} ({c.preset})]({view_path(c.experiments, c.key)})" for c in others
        )
        parts += [f"Runs of this experiment are also compared in: {links}.", ""]
    if runs_link:
        parts += [f"[Its finished runs]({runs_link}), newest first.", ""]
    text = "\n".join(parts)
    if report_note and len(text) + len(report_note) + 20 < _NOTE_LIMIT:
        text += "\n---\n\n" + report_note
    return text[:_NOTE_LIMIT]


def prepare_ui(client, now_ms: int | None = None) -> PreparedUI:
    """Make every cloudpose experiment of the store ready for the MLflow UI (see the module's
    docstring): dead runs marked KILLED, headline metrics back-filled, the runs of each
    comparison tagged and given their statistics, runs the report does not count tagged
    :data:`SUPERSEDED`, foreign ``run_dir`` paths made relative, views and descriptions put
    on the experiments. Writes only what differs: a second call writes nothing."""
    exps = {
        e.experiment_id: e
        for e in client.search_experiments()
        if e.name.startswith(tracking.EXPERIMENT_PREFIX)
    }
    runs = []
    for exp_id in sorted(exps, key=lambda i: exps[i].name):
        runs += client.search_runs([exp_id], "", max_results=50000)
    killed = mark_dead(client, runs, now_ms)
    if killed:  # their status and tags changed
        dead = {r.info.run_id for r, _ in killed}
        runs = [client.get_run(r.info.run_id) if r.info.run_id in dead else r for r in runs]
    evaluated = [r for r in runs if r.data.tags.get("variant") and headline(r.data.metrics)]
    backfilled = backfill(client, evaluated)
    presets = {
        r.data.tags["preset"]
        for r in evaluated
        if r.data.tags.get("preset") and r.info.status == "FINISHED"
    }
    runsets = counted_runs(client, presets)
    reports = _report_runs(runs)
    experiment_of = {r.info.run_id: r.info.experiment_id for r in runs}
    comps = [c for rs in runsets.values() for c in build_comparisons(rs, reports, experiment_of)]
    tags, metrics, superseded = run_updates(runs, evaluated, comps, runsets)
    project = _project_folder(client)
    written = 2 * len(killed) + backfilled
    for r in runs:
        i = r.info.run_id
        rel = relative_run_dir(r.data.tags.get("run_dir", ""), project) if project else None
        if rel:
            tags[i]["run_dir"] = rel
        if i in tags or i in metrics:
            written += write_run(client, r, tags.get(i, {}), metrics.get(i, {}))
    for exp in exps.values():
        written += _prepare_experiment(client, exp, comps, reports)
    return PreparedUI(
        comps,
        {i: e.name for i, e in exps.items()},
        backfilled,
        superseded,
        [(r.info.run_name, why) for r, why in killed],
        written,
    )


def _report_runs(runs: Iterable) -> dict[tuple[str, str], object]:
    """(group, preset) -> the newest finished report run ``report/{group}/{preset}``."""
    out = {}
    for r in runs:
        t = r.data.tags
        if t.get("kind") == "report" and r.info.status == "FINISHED":
            key = (t.get("report_group"), t.get("report_preset"))
            if key not in out or r.info.start_time > out[key].info.start_time:
                out[key] = r
    return out


def run_updates(
    runs: Sequence, evaluated: Sequence, comps: Sequence[GroupComparison], runsets: Mapping
) -> tuple[dict[str, dict[str, str | None]], dict[str, dict[str, float]], int]:
    """What :func:`write_run` is to make of each run (run id -> tags, None to delete; run id
    -> metrics) and how many evaluated runs do not count.

    A counted run gets the tag of each comparison it belongs to and its variant's statistics;
    a report run the tag of its comparisons; an evaluated, finished run of a reported preset
    that does not count the tag :data:`SUPERSEDED` (why), and NaN in place of statistics it
    holds; a comparison tag no longer wanted is deleted.
    """
    tags: dict[str, dict[str, str | None]] = defaultdict(dict)
    metrics: dict[str, dict[str, float]] = defaultdict(dict)
    names = {c.group for c in comps} | set(TITLES)
    for r in runs:
        t = r.data.tags
        preset = t.get("preset") or t.get("report_preset")
        for n in names:
            if f"{n}.{preset}" in t:
                tags[r.info.run_id][f"{n}.{preset}"] = None
    counted = set()
    for comp in comps:
        for row in comp.rows:
            for i in row.run_ids:
                tags[i][comp.key] = row.value
                metrics[i] = dict(row.stats)
                counted.add(i)
        if comp.report_run:
            tags[comp.report_run][comp.key] = REPORT_ROW
    chosen = {p: {(x.variant, x.seed): x for x in rs.records} for p, rs in runsets.items()}
    nan_stats = dict.fromkeys(stat_keys(), math.nan)
    superseded = 0
    for r in evaluated:
        i, preset = r.info.run_id, r.data.tags.get("preset")
        if i in counted:
            tags[i][SUPERSEDED] = None
        elif r.info.status == "FINISHED" and preset in runsets:
            why = superseded_reason(r, chosen[preset], runsets[preset].data_key)
            tags[i][SUPERSEDED] = why
            metrics[i] = {k: v for k, v in nan_stats.items() if k in r.data.metrics}
            superseded += 1
    return tags, metrics, superseded


def _prepare_experiment(client, exp, comps: Sequence[GroupComparison], reports: Mapping) -> int:
    """Views and description of one experiment: the views of the comparisons it is named for
    or holds runs of (else :data:`RUNS_VIEW`), its views of earlier versions removed; returns
    the tags written."""
    exp_id = exp.experiment_id
    group = exp.name.removeprefix(tracking.EXPERIMENT_PREFIX)
    own = [c for c in comps if c.group == group]
    others = [c for c in comps if c.group != group and exp_id in c.experiments]
    written = 0
    for comp in [*own, *others]:
        written += install_view(client, exp, comp.key, view_name(comp), comparison_view(comp))
    keys = {c.key for c in [*own, *others]}
    if not own:
        written += install_view(client, exp, RUNS_VIEW, "Finished runs", runs_view())
        keys.add(RUNS_VIEW)
    names = {c.group for c in comps} | set(TITLES)
    for tag in list(exp.tags):
        key = tag.removeprefix(_VIEW_PREFIX)
        ours = key in LEGACY_VIEWS or key == RUNS_VIEW or key.split(".")[0] in names
        if tag.startswith(_VIEW_PREFIX) and ours and key not in keys:
            client.delete_experiment_tag(exp_id, tag)
            written += 1
    mine = [r for (g, _), r in sorted(reports.items()) if g == group]
    note = mine[0].data.tags.get(_NOTE, "") if mine else ""
    runs_link = view_path([exp_id], RUNS_VIEW) if not own else ""
    text = description(group_title(group, own[0].rows if own else ()), own, others, note, runs_link)
    if exp.tags.get(_NOTE) != text:
        client.set_experiment_tag(exp_id, _NOTE, text)
        written += 1
    return written


def _project_folder(client) -> Path | None:
    """The folder of a local SQLite store (its run folders' project), else None."""
    db = tracking.sqlite_path(getattr(client, "tracking_uri", "") or "")
    return db.resolve().parent if db is not None else None


def ui_command(backend: str, host: str = "127.0.0.1", port: int = 5000) -> list[str]:
    """argv of the MLflow UI on ``backend`` (this interpreter's MLflow, one worker)."""
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
