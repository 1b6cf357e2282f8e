"""The runs a report is made from (cloudpose.report.runs): finished, evaluated runs of a preset's
own config, one per (variant, seed), on one dataset."""

from __future__ import annotations

import math

import pytest

from cloudpose.registry import resolve
from cloudpose.report.runs import TEST_KEY, load_runs
from cloudpose.store import tracking


@pytest.fixture
def store(tmp_path):
    """An MLflow store with one cloudpose experiment; ``add`` logs a finished run into it."""
    client = tracking.setup(tmp_path)
    exp = client.create_experiment(f"{tracking.EXPERIMENT_PREFIX}shared")
    clock = iter(range(1_000, 100_000, 1_000))

    def add(variant, seed, data, ads=None, config=None, params=None, status="FINISHED"):
        fp = config or resolve(variant, "smoke", seed).fingerprint()
        tags = {"variant": variant, "seed": str(seed), "preset": "smoke", "data": data}
        tags.update(config=fp, git_commit="abc1234")
        run = client.create_run(exp, start_time=next(clock), tags=tags)
        for k, v in {
            "data.synth_seed": "0",
            "model.parameters": "1600000",
            **(params or {}),
        }.items():
            client.log_param(run.info.run_id, k, v)
        if ads is not None:
            client.log_metric(run.info.run_id, TEST_KEY, ads)
        client.set_terminated(run.info.run_id, status)
        return run.info.run_id

    return client, add


def test_one_dataset_and_the_newest_run_per_variant_and_seed(store):
    client, add = store
    add("shared-0", 1, "aaaa", ads=0.50)
    newest = add("shared-0", 1, "aaaa", ads=0.55)
    add("shared-0", 2, "aaaa", ads=0.60)
    add("l2", 1, "aaaa", ads=0.40)
    add("shared-0", 3, "bbbb", ads=0.90)  # other data: fewer (variant, seed) pairs
    add("l2", 2, "aaaa")  # not evaluated
    add("l2", 3, "aaaa", ads=0.1, status="FAILED")
    with pytest.warns(UserWarning, match="1 finished run.* other data than aaaa"):
        rs = load_runs("smoke", client=client)
    assert rs.data_key == "aaaa" and rs.ignored == 1
    assert rs.variants == ["l2", "shared-0"] and rs.seeds == [1, 2]
    assert [r.seed for r in rs.of("shared-0")] == [1, 2]
    assert rs.of("shared-0")[0].run_id == newest
    assert rs.values("shared-0", TEST_KEY) == {1: 0.55, 2: 0.60}
    assert rs.values("shared-0", "test/missing") == {}
    assert rs.subset(["l2"]).variants == ["l2"] and rs.commits == ["abc1234"]
    rec = rs.of("l2")[0]
    assert rec.parameters == 1_600_000 and math.isnan(rec.metric("test/missing"))
    assert rs.data_label() == "synthetic YCB-Video-layout scenes (synth seed 0, data aaaa)"


def test_data_asked_for_wins_over_the_most_common(store):
    client, add = store
    add("shared-0", 1, "aaaa", ads=0.5)
    add("shared-0", 2, "aaaa", ads=0.5)
    add("shared-0", 1, "bbbb", ads=0.7)
    with pytest.warns(UserWarning, match="2 finished run"):
        rs = load_runs("smoke", data_key="bbbb", client=client)
    assert [r.metric(TEST_KEY) for r in rs.records] == [0.7]


def test_runs_of_another_config_are_left_out(store):
    client, add = store
    add("shared-0", 1, "aaaa", ads=0.5)
    add("shared-0", 2, "aaaa", ads=0.9, config="0123456789")  # --set, or an edited preset
    with pytest.warns(UserWarning, match="1 finished run.* another config"):
        rs = load_runs("smoke", client=client)
    assert [r.seed for r in rs.records] == [1]


def test_no_runs_is_an_empty_set_and_a_real_root_is_named(store, tmp_path):
    client, add = store
    assert load_runs("smoke", client=client).records == []
    assert load_runs("smoke", client=client).data_label() == "no runs"
    root = str(tmp_path / "YCB_Video_Dataset")
    cfg = resolve("shared-0", "smoke", 1, {"data": {"root": root}})
    add("shared-0", 1, "cccc", ads=0.3, config=cfg.fingerprint(), params={"data.root": root})
    rs = load_runs("smoke", client=client)
    assert rs.data_label() == "YCB_Video_Dataset (data cccc)"


def test_runs_on_keys_of_the_same_data_are_pooled_and_found(store, tmp_path, monkeypatch):
    from cloudpose.data import keys

    same = tmp_path / "same_data.toml"
    same.write_text('[[same]]\nkind = "data"\nkeys = ["aaaa", "cccc"]\n')
    monkeypatch.setattr(keys, "SAME_DATA_FILE", same)
    client, add = store
    add("shared-0", 1, "aaaa", ads=0.50)
    newer = add("shared-0", 1, "cccc", ads=0.52)  # the same data rendered on another CPU
    add("shared-0", 2, "cccc", ads=0.60)
    add("l2", 1, "bbbb", ads=0.40)  # other data
    with pytest.warns(UserWarning, match="1 finished run.* other data than aaaa"):
        rs = load_runs("smoke", client=client)
    assert rs.data_key == "aaaa" and rs.seeds == [1, 2] and rs.variants == ["shared-0"]
    assert rs.of("shared-0")[0].run_id == newer
    with pytest.warns(UserWarning, match="1 finished run"):
        assert load_runs("smoke", data_key="cccc", client=client).data_key == "aaaa"
    found = tracking.find_runs(client, variant="shared-0", seed=1, data="aaaa")
    assert found[0].info.run_id == newer and len(found) == 2
    assert [r.data.tags["data"] for r in tracking.find_runs(client, data="bbbb")] == ["bbbb"]


def test_a_baseline_of_another_preset_on_the_same_data_serves_the_report(store):
    from cloudpose.baselines.base import load_settings, settings_fingerprint

    client, add = store
    exp = client.get_experiment_by_name(f"{tracking.EXPERIMENT_PREFIX}shared").experiment_id

    def baseline(preset, seed, data, ads, method="fpfh"):
        fp = settings_fingerprint(load_settings(method))
        tags = {"variant": f"baseline-{method}", "seed": str(seed), "preset": preset}
        tags.update(data=data, kind="baseline", config=fp, subsample="all")
        run = client.create_run(exp, tags=tags)
        client.log_metric(run.info.run_id, TEST_KEY, ads)
        client.set_terminated(run.info.run_id)
        return run.info.run_id

    add("shared-0", 1, "aaaa", ads=0.5)
    own = baseline("smoke", 1, "aaaa", 0.71)
    baseline("other", 1, "aaaa", 0.70)  # the preset has its own seed 1
    other = baseline("other", 2, "aaaa", 0.72)
    baseline("other", 3, "bbbb", 0.99)  # other data
    rs = load_runs("smoke", client=client)
    got = {r.seed: (r.run_id, r.preset) for r in rs.of("baseline-fpfh")}
    assert got == {1: (own, "smoke"), 2: (other, "other")}
    assert rs.data_label().endswith("; baselines of preset other on the same data")
