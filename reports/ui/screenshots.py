"""The MLflow UI on the committed cpu-online store, checked in headless Chromium, and its
screenshots (this folder's PNGs).

    python reports/ui/screenshots.py [--store reports/cpu-online/mlflow-store.tar.xz]

Unpacks the committed store into a temporary folder (``cloudpose store-unpack``), starts
``cloudpose mlflow-ui`` there (which prepares the store: docs/tracking.md, "The MLflow UI") and
drives Debian's Chromium (``/usr/bin/chromium``, headless) with the ``playwright`` package (its
driver only: ``pip install playwright``, no browser download). It

- opens every comparison view the command prints and checks its grid: one row per variant of
  the group, the reference shared-0 included, with as many seeds as the report counts and the
  report's mean and sd of every column, computed from the same store by the report's code
  (``load_runs``, ``mean_std``, ``format_mean_std``) and, where the committed tables print the
  figure, read from ``reports/cpu-online/table{1,3,4}*.md``; and a row linking the report run;
- checks that no run of the preset is left RUNNING (another preset's training may be in
  flight in a store packed mid-sweep; views of other presets are listed, not checked), that no run tagged ``superseded`` shows in a view, and
  that the description of each group's experiment holds the same table as its grid;
- times the chart view of the largest comparison (it draws only the statistics);
- saves screenshots (256-colour PNGs): each view, the experiments list, an experiment's
  description, a report run's artifacts, a chart view.

Exits 1 naming each mismatch.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PRESET = "cpu-online"
ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
VIEW_LINE = re.compile(r"^\s+(\S+)\s+\d+ variants\s+\d+ runs\s+(http\S+)$")
# the MLflow assistant's side panel starts closed; no telemetry
INIT = """
localStorage.setItem('mlflow.assistant.panelOpen_v1', 'false');
localStorage.setItem('mlflow.assistant.fab.autoOpenedOnFirstLoad_v1', 'true');
"""


def default_store() -> Path:
    """The committed store: the compact folder, else the archive."""
    folder = ROOT / "reports" / PRESET / "mlflow-store"
    return folder if folder.is_dir() else ROOT / "reports" / PRESET / "mlflow-store.tar.xz"


def cli(*args: str, cwd: Path | None = None, **kw) -> subprocess.Popen | str:
    cmd = [sys.executable, "-m", "cloudpose.cli", *args]
    if kw.pop("popen", False):
        return subprocess.Popen(cmd, cwd=cwd, **kw)
    return subprocess.run(cmd, cwd=cwd, check=True, capture_output=True, text=True).stdout


def start_ui(folder: Path, port: int) -> tuple[subprocess.Popen, dict[str, str], list[str]]:
    """``cloudpose mlflow-ui`` in ``folder``: its process, the comparison views it printed
    (key -> address) and its output lines, once the UI answers."""
    env = {**os.environ, "MLFLOW_DISABLE_TELEMETRY": "true", "DO_NOT_TRACK": "true"}
    proc = cli(
        "mlflow-ui",
        "--port",
        str(port),
        cwd=folder,
        popen=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
        start_new_session=True,
    )
    views, lines = {}, []
    for line in proc.stdout:
        lines.append(line.rstrip())
        if m := VIEW_LINE.match(line.rstrip()):
            views[m[1]] = m[2]
        if line.startswith("MLflow UI on"):
            break
    else:
        raise SystemExit("cloudpose mlflow-ui ended:\n" + "\n".join(lines))
    for _ in range(120):
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=2):
                return proc, views, lines
        except OSError:
            time.sleep(1)
    raise SystemExit("the MLflow UI did not answer in 120 s")


def stop(proc: subprocess.Popen) -> None:
    try:
        os.killpg(proc.pid, signal.SIGINT)
        proc.wait(timeout=30)
    except (ProcessLookupError, subprocess.TimeoutExpired):
        os.killpg(proc.pid, signal.SIGKILL)


# -- what the report says ----------------------------------------------------------------------


def expected(folder: Path) -> dict[str, dict[str, dict[str, str]]]:
    """Comparison key -> row name -> column -> the report's text (``"91.3 ± 0.2"``, seeds
    ``"8"``), from the store in ``folder`` by the report's own code."""
    from cloudpose.report import ui
    from cloudpose.report.runs import load_runs
    from cloudpose.report.stats import format_mean_std, mean_std
    from cloudpose.store import tracking

    runs = load_runs(PRESET, client=tracking.setup(folder))
    out = {}
    for group, members in ui.comparison_members(runs.variants):
        rows = {}
        for variant, label in members:
            if not runs.of(variant):
                continue
            cells = {"seeds": str(len(runs.of(variant)))}
            for key, name in ui.COLUMNS.items():
                values = list(runs.values(variant, ui.HEADLINE[key]).values())
                cells[name] = format_mean_std(mean_std(values))
            cells["run ids"] = sorted(r.run_id for r in runs.of(variant))
            rows[ui.Row(variant, label).value] = cells
        out[f"{group}.{PRESET}"] = rows
    return out


def md_table(path: Path) -> list[dict[str, str]]:
    """The rows of the first Markdown table in ``path``, as header -> cell."""
    lines = [ln for ln in path.read_text(encoding="utf-8").splitlines() if ln.startswith("|")]
    head = [c.strip() for c in lines[0].strip("|").split("|")]
    cells = [[c.strip() for c in ln.strip("|").split("|")] for ln in lines[2:]]
    return [dict(zip(head, row, strict=True)) for row in cells]


def committed_figures() -> dict[tuple[str, str, str], str]:
    """(comparison key, variant, column) -> the figure the committed tables print."""
    reports = ROOT / "reports" / PRESET
    out = {}
    for row in md_table(reports / "table3_shared_layers.md"):
        v = row["variant"]
        out[(f"shared.{PRESET}", v, "ADS AUC")] = row["ADS AUC (ours)"]
        out[(f"shared.{PRESET}", v, "trans lt 1cm")] = row["trans. err. < 1 cm (ours)"]
        out[(f"shared.{PRESET}", v, "seeds")] = row["seeds"]
    sections = {"representation": "rotation", "loss": "loss", "symmetry": "symmetry"}
    for row in md_table(reports / "table4_rotation.md"):
        key = f"{sections[row['ablation']]}.{PRESET}"
        out[(key, row["variant"], "rot lt 10deg sym")] = row["rot. err. mod sym. < 10° (ours)"]
        out[(key, row["variant"], "seeds")] = row["seeds"]
    for row in md_table(reports / "table1_overall.md"):
        m = re.search(r"\((shared-0|baseline-\w+)( \+ ICP)?", row["method"])
        if row["source"].startswith("ours") and m:
            column = "ADS AUC ICP" if m[2] else "ADS AUC"
            out[(f"baselines.{PRESET}", m[1], column)] = row["ADS AUC"]
            out[(f"baselines.{PRESET}", m[1], "seeds")] = row["seeds"]
    return out


# -- what the UI shows ---------------------------------------------------------------------


def grid_rows(page) -> dict[str, dict[str, str]]:
    """Group rows of the runs table on screen: row name -> column -> text (``"91.3"`` for
    ``"91.3 (max)"``), ``seeds`` the group's run count."""
    rows = page.evaluate(
        """() => {
        const out = {};
        for (const r of document.querySelectorAll('.ag-row')) {
          const id = r.getAttribute('row-id');
          out[id] = out[id] || {};
          for (const c of r.querySelectorAll('[col-id]'))
            out[id][c.getAttribute('col-id')] = c.innerText;
        }
        return out;
      }"""
    )
    groups = {}
    for cells in rows.values():
        name = cells.get("attributes.`Run Name`", "")
        m = re.match(r"(?:#\w+\s*)?Group: (.*)\n(\d+)$", name.strip(), re.S)
        if not m:
            continue
        row = {"runs": m[2]}
        for col, text in cells.items():
            if col.startswith("metrics.`"):
                row[col[len("metrics.`") : -1]] = text.replace("(max)", "").strip()
        groups[m[1].strip()] = row
    return groups


def shown_cell(row: dict[str, str], name: str) -> str:
    """A grid row's ``name`` column as the report prints it (``"91.3 ± 0.2"``)."""
    mean, sd = row.get(f"{name} mean", "-"), row.get(f"{name} sd", "-")
    if mean in ("", "-"):
        return "–"
    mean = f"{float(mean):.1f}"
    return mean if sd in ("", "-") else f"{mean} ± {float(sd):.1f}"


def open_view(page, url: str, wide: bool = True) -> float:
    """Open a view and wait for its grouped rows; returns the seconds it took."""
    page.set_viewport_size({"width": 2600 if wide else 1920, "height": 900})
    t0 = time.monotonic()
    page.goto(url)
    page.wait_for_selector("text=Group:", timeout=120_000)
    page.wait_for_timeout(1500)
    return time.monotonic() - t0


def save(page, path: Path) -> None:
    from PIL import Image

    page.screenshot(path=str(path))
    Image.open(path).convert("RGB").quantize(256).save(path, optimize=True)


def check(args) -> list[str]:
    from playwright.sync_api import sync_playwright

    from cloudpose.store import tracking

    problems: list[str] = []
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="cloudpose-ui-") as tmp:
        folder = Path(tmp) / "store"
        cli("store-unpack", str(args.store), "--into", str(folder))
        proc, views, lines = start_ui(folder, args.port)
        print("\n".join(lines))
        try:
            want = expected(folder)
            committed = committed_figures()
            client = tracking.setup(folder)
            exps = {e.experiment_id: e for e in client.search_experiments()}
            # the store may hold another preset's trainings in flight (packed mid-sweep, alive
            # by store/liveness.py's rule); this preset's runs are all finished or marked dead
            running = client.search_runs(
                list(exps), f"attributes.status = 'RUNNING' and tags.preset = '{PRESET}'"
            )
            if running:
                problems.append(f"{len(running)} {PRESET} runs still RUNNING after mlflow-ui")
            others = sorted(k for k in views if not k.endswith(f".{PRESET}"))
            print(f"views of other presets, not checked here: {', '.join(others) or 'none'}")
            views = {k: v for k, v in views.items() if k.endswith(f".{PRESET}")}
            if set(want) != set(views):
                problems.append(f"views printed {sorted(views)}, comparisons {sorted(want)}")
            with sync_playwright() as p:
                browser = p.chromium.launch(executable_path="/usr/bin/chromium", args=ARGS)
                page = browser.new_page(viewport={"width": 2600, "height": 900})
                page.add_init_script(INIT)
                timings = {}
                for key, url in sorted(views.items()):
                    timings[key] = open_view(page, url)
                    got = grid_rows(page)
                    problems += compare_view(key, got, want.get(key, {}), committed)
                    problems += compare_runs(client, list(exps), key, want.get(key, {}))
                    open_view(page, url, wide=False)
                    save(page, out / f"view_{key.split('.')[0]}.png")
                    print(f"{key}: {len(got)} rows, grid in {timings[key]:.1f} s")
                problems += check_descriptions(client, exps, want)
                problems += screenshots_elsewhere(
                    page, args.port, client, exps, views, out, timings
                )
                browser.close()
            print(
                "view load times (s): " + json.dumps({k: round(v, 1) for k, v in timings.items()})
            )
        finally:
            stop(proc)
    return problems


def compare_view(key, got, want, committed) -> list[str]:
    """Mismatches between a view's grid rows and the report's figures."""
    from cloudpose.report import ui

    problems = []
    report_rows = [k for k in got if k == ui.REPORT_ROW]
    if not report_rows:
        problems.append(f"{key}: no row linking the report run")
    names = set(got) - {ui.REPORT_ROW}
    if names != set(want):
        problems.append(f"{key}: rows {sorted(names)}, the group's variants {sorted(want)}")
    for name, cells in want.items():
        row = got.get(name, {})
        variant = name.split(",")[0]
        if row.get("runs") != cells["seeds"] or row.get("seeds") != cells["seeds"]:
            problems.append(f"{key} {name}: {row.get('runs')} runs, report {cells['seeds']} seeds")
        for col in ui.COLUMNS.values():
            shown = shown_cell(row, col)
            if shown != cells[col]:
                problems.append(f"{key} {name} {col}: grid {shown}, report {cells[col]}")
            figure = committed.get((key, variant, col))
            if figure is not None and figure != shown:
                problems.append(f"{key} {name} {col}: grid {shown}, committed table {figure}")
        figure = committed.get((key, variant, "seeds"))
        if figure is not None and figure != row.get("runs"):
            problems.append(f"{key} {name}: {row.get('runs')} seeds, committed table {figure}")
    return problems


def compare_runs(client, exp_ids, key, want) -> list[str]:
    """The runs a view's filter finds are the report's runs of its rows (none tagged
    ``superseded``) and one report run."""
    found = client.search_runs(exp_ids, f"tags.`{key}` != ''", max_results=5000)
    problems = [
        f"{key}: superseded run {r.info.run_name} ({r.info.run_id}) in the view"
        for r in found
        if "superseded" in r.data.tags
    ]
    ids = sorted(r.info.run_id for r in found if r.data.tags.get("kind") != "report")
    if ids != sorted(i for cells in want.values() for i in cells["run ids"]):
        problems.append(f"{key}: the view's runs are not the report's runs of its variants")
    if sum(r.data.tags.get("kind") == "report" for r in found) != 1:
        problems.append(f"{key}: not one report run in the view")
    return problems


def check_descriptions(client, exps, want) -> list[str]:
    """Each group's experiment description holds its grid's table (the report's figures)."""
    problems = []
    for exp in exps.values():
        key = f"{exp.name.removeprefix('cloudpose-')}.{PRESET}"
        if key not in want:
            continue
        note = exp.tags.get("mlflow.note.content", "")
        for name, cells in want[key].items():
            variant = name.split(",")[0]
            line = next((ln for ln in note.splitlines() if ln.startswith(f"| {variant} |")), "")
            for col, text in cells.items():
                if col != "run ids" and f" {text} |" not in line:
                    problems.append(f"{exp.name} description, {variant} {col}: no {text!r}")
    return problems


def screenshots_elsewhere(page, port, client, exps, views, out, timings) -> list[str]:
    """The experiments list, an experiment's description (its links followed), a report
    run's artifacts and the chart view of the largest comparison (timed); returns the links
    that led elsewhere."""
    base = f"http://127.0.0.1:{port}"
    page.set_viewport_size({"width": 1600, "height": 900})
    page.goto(f"{base}/#/experiments?workflowType=machine_learning")
    page.wait_for_selector("text=cloudpose-rotation", timeout=60_000)
    page.wait_for_timeout(1000)
    save(page, out / "experiments.png")

    rotation = next(e for e in exps.values() if e.name == "cloudpose-rotation")

    def description() -> None:
        page.goto(
            f"{base}/#/experiments/{rotation.experiment_id}/runs?workflowType=machine_learning"
        )
        page.wait_for_selector("text=Rotation representation", timeout=60_000)
        box = page.get_by_test_id("experiment-metadata-editor-edit-button").bounding_box()
        page.mouse.click(box["x"] + 48, box["y"] + 16)  # the description's expand chevron
        page.wait_for_timeout(1500)

    description()
    save(page, out / "description_rotation.png")
    problems = []
    for link, expect, shows in (
        ("open the comparison", "viewStateShareKey=rotation.", "text=Group:"),
        ("the report's tables and plots", "/artifacts", "text=table4_rotation.md"),
    ):
        description()
        with page.context.expect_page() as opened:  # the UI opens description links in a tab
            page.get_by_role("link", name=link).first.click()
        tab = opened.value
        try:
            tab.wait_for_selector(shows, timeout=60_000)
        except Exception:
            problems.append(f"description link {link!r}: {tab.url} shows no {shows!r}")
        if expect not in tab.url:
            problems.append(f"description link {link!r} led to {tab.url}")
        tab.close()

    report = client.search_runs(
        [rotation.experiment_id], f"attributes.run_name = 'report/rotation/{PRESET}'"
    )[0]
    page.goto(
        f"{base}/#/experiments/{rotation.experiment_id}/runs/{report.info.run_id}/artifacts/"
        "table4_rotation.md?workflowType=machine_learning"
    )
    page.wait_for_selector("text=table4_rotation.md", timeout=60_000)
    page.wait_for_timeout(3000)
    save(page, out / "report_run_rotation.png")

    key = f"shared.{PRESET}" if f"shared.{PRESET}" in views else sorted(views)[0]
    t0 = time.monotonic()
    page.goto(views[key] + "&compareRunsMode=CHART")
    page.wait_for_selector(".js-plotly-plot, canvas", timeout=120_000)
    page.wait_for_timeout(1000)
    timings[f"{key} charts"] = time.monotonic() - t0
    page.wait_for_timeout(3000)
    save(page, out / f"charts_{key.split('.')[0]}.png")
    return problems


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--store", type=Path, default=default_store())
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent)
    parser.add_argument("--port", type=int, default=5817)
    problems = check(parser.parse_args())
    for p in problems:
        print("MISMATCH:", p)
    print("all checks passed" if not problems else f"{len(problems)} mismatches")
    sys.exit(1 if problems else 0)


if __name__ == "__main__":
    main()
