"""Runs of data keyed by an earlier definition are found again after :func:`rekey_runs` (the
one-off migration of the store to today's keys; no command of the CLI since)."""

from __future__ import annotations

import shutil

import pytest

from cloudpose.data.dataset import prepare_data
from cloudpose.registry import resolve
from cloudpose.store import tracking
from cloudpose.store.rekey import current_keys, rekey_runs
from cloudpose.store.runs import TEST_KEY, finished_run
from tests.conftest import make_project


def _run(client, exp, name, tags, metrics=()):
    run = client.create_run(exp, run_name=name, tags=tags)
    for key in metrics:
        client.log_metric(run.info.run_id, key, 0.9)
    client.set_terminated(run.info.run_id)
    return run.info.run_id


def test_rekeyed_runs_are_found_under_todays_keys(tmp_path, smoke_data, empty_store, monkeypatch):
    proj = make_project(tmp_path / "proj", smoke_data, monkeypatch)
    shutil.copy(empty_store, proj / tracking.STORE_DB)
    monkeypatch.chdir(proj)
    cfg = resolve("shared-0", "smoke", 1)
    keys = current_keys("smoke", proj)
    prepared = prepare_data(cfg.data, proj, progress=False)
    assert keys["data"] == prepared.data_key and keys["test"] == prepared.test.data_key

    client = tracking.setup(proj)
    exp = tracking.experiment_id(client, "shared", proj)
    base = {"variant": "shared-0", "preset": "smoke", "seed": "1", "config": cfg.fingerprint()}
    old = {
        **base,
        "data": "0123456789abcdef",
        "eval/test/data": "a" * 20,
        "eval/real/data": "b" * 20,
        "eval/test-degraded-mild/data": "c" * 20,  # other masks: another key, kept
    }
    moved = _run(client, exp, "shared-0/smoke/seed1", old, [TEST_KEY])
    other = _run(client, exp, "shared-0/smoke/seed1", {**base, "data": "fedcba9876543210"})
    assert finished_run(client, cfg, keys["data"]) is None

    would = rekey_runs("smoke", ["01234567"], proj, dry_run=True)
    assert len(would) == 3 and {c.run_id for c in would} == {moved}
    assert client.get_run(moved).data.tags["data"] == "0123456789abcdef"

    assert rekey_runs("smoke", ["01234567"], proj) == would
    tags = client.get_run(moved).data.tags
    assert tags["data"] == keys["data"] and tags["rekeyed/data"] == "0123456789abcdef"
    assert tags["eval/test/data"] == keys["test"] and tags["rekeyed/eval/test/data"] == "a" * 20
    assert tags["eval/real/data"] == keys["real"]
    assert tags["eval/test-degraded-mild/data"] == "c" * 20
    assert client.get_run(other).data.tags["data"] == "fedcba9876543210"
    assert finished_run(client, cfg, keys["data"]).info.run_id == moved
    # a run rekeyed while it ran logs its evaluations later, keyed by the old definition
    client.set_tag(moved, "eval/real/data", "d" * 20)
    assert [c.tag for c in rekey_runs("smoke", ["01234567"], proj)] == ["eval/real/data"]
    tags = client.get_run(moved).data.tags
    assert tags["eval/real/data"] == keys["real"] and tags["rekeyed/eval/real/data"] == "b" * 20
    # again: nothing left to change; today's key is refused as an old one
    assert rekey_runs("smoke", ["01234567"], proj) == []
    with pytest.raises(ValueError, match="today's key of the smoke data"):
        rekey_runs("smoke", [keys["data"][:8]], proj)
