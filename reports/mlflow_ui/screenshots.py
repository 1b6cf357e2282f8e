"""The screenshots in this folder: the MLflow UI of the committed cpu store in headless Chromium.

    mkdir -p /tmp/cpstore && tar -xJf reports/cpu/mlflow-store.tar.xz -C /tmp/cpstore
    (cd /tmp/cpstore && cloudpose mlflow-ui --port 5817 &)  # prepares the store, serves it
    python reports/mlflow_ui/screenshots.py http://127.0.0.1:5817 reports/mlflow_ui

Needs Debian's chromium (/usr/bin/chromium) and the ``playwright`` package (its driver only; it
downloads no browser). Experiment 4 is cloudpose-shared in that store; the report run's id is
looked up by name.
"""

from __future__ import annotations

import json
import sys
import urllib.request

from playwright.sync_api import sync_playwright

ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


def report_run(base: str, experiment_id: str, name: str) -> str:
    body = json.dumps(
        {"experiment_ids": [experiment_id], "filter": f"attributes.run_name = '{name}'"}
    ).encode()
    req = urllib.request.Request(
        f"{base}/api/2.0/mlflow/runs/search", body, {"Content-Type": "application/json"}
    )
    with urllib.request.urlopen(req) as r:
        return json.load(r)["runs"][0]["info"]["run_id"]


def close_assistant(page) -> None:
    close = page.get_by_role("button", name="Close")
    if close.count():
        close.first.click()
        page.wait_for_timeout(1000)


def main(base: str, out: str, exp: str = "4") -> None:
    view = (
        f"{base}/#/experiments/{exp}/runs?viewStateShareKey=variants&workflowType=machine_learning"
    )
    run = report_run(base, exp, "report/shared/cpu")
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path="/usr/bin/chromium", args=ARGS)
        page = browser.new_page(viewport={"width": 1500, "height": 860})
        page.goto(view)
        page.wait_for_timeout(7000)
        close_assistant(page)
        page.screenshot(path=f"{out}/runs_shared.png")
        page.goto(f"{base}/#/experiments?workflowType=machine_learning")
        page.wait_for_timeout(4000)
        page.screenshot(path=f"{out}/experiments.png")
        page.goto(view)
        page.wait_for_timeout(6000)
        box = page.get_by_test_id("experiment-metadata-editor-edit-button").bounding_box()
        page.mouse.click(box["x"] + 48, box["y"] + 16)  # the description's expand chevron
        page.wait_for_timeout(1500)
        page.screenshot(path=f"{out}/description_shared.png")
        page.goto(
            f"{base}/#/experiments/{exp}/runs/{run}/artifacts/table3_shared_layers.md"
            "?workflowType=machine_learning"
        )
        page.wait_for_timeout(6000)
        page.screenshot(path=f"{out}/report_artifacts_shared.png")
        browser.close()


if __name__ == "__main__":
    main(*sys.argv[1:])
