"""Run identity (cloudpose.store.runs): names, folders, run.json, and resolving a user's name for a run."""

from __future__ import annotations

import types
from pathlib import Path

import pytest

from cloudpose.config import Config
from cloudpose.registry import resolve
from cloudpose.store import runs, tracking


def test_names_and_folders_follow_config_and_data():
    cfg = resolve("shared-3", "smoke", seed=2)
    assert runs.run_name("shared-3", "smoke", 2) == "shared-3/smoke/seed2"
    assert runs.display_name(cfg) == "shared-3/smoke/seed2"  # the preset's own config
    other = resolve("shared-3", "smoke", 2, {"train": {"lr": 3e-4}})
    assert runs.display_name(other) == f"shared-3/smoke/seed2+{other.fingerprint()[:8]}"
    d = runs.run_dir(cfg, "0123456789abcdef", Path("/p"))
    assert d == Path(f"/p/runs/shared-3/smoke/seed2-0123456789-{cfg.fingerprint()[:8]}")
    assert runs.run_dir(other, "0123456789abcdef", Path("/p")) != d
    assert runs.run_dir(cfg, "fedcba9876543210", Path("/p")) != d


def test_run_json_round_trip_is_atomic(tmp_path):
    assert runs.read_info(tmp_path) == {}
    assert not runs.is_run_folder(tmp_path)
    runs.write_info(tmp_path, {"run_id": "abc", "finished": False})
    runs.write_info(tmp_path, {"run_id": "abc", "finished": True})
    assert runs.read_info(tmp_path) == {"run_id": "abc", "finished": True}
    assert runs.is_run_folder(tmp_path)
    assert [p.name for p in tmp_path.iterdir()] == ["run.json"]  # no temporary file left


def _run(tags: dict, params: dict | None = None):
    data = types.SimpleNamespace(tags=tags, params=params or {}, metrics={})
    return types.SimpleNamespace(data=data)


def test_config_matching_by_tag_and_by_params():
    cfg = resolve("l2", "smoke", seed=1)
    own = {"variant": "l2", "preset": "smoke", "seed": "1", "config": cfg.fingerprint()}
    assert runs.run_has_config(_run(own), cfg) and runs.is_preset_config(_run(own))
    edited = {**own, "config": "0" * 16}
    assert not runs.run_has_config(_run(edited), cfg) and not runs.is_preset_config(_run(edited))
    untagged = {k: v for k, v in own.items() if k != "config"}  # a run from before the tag
    assert runs.run_has_config(_run(untagged, tracking.flat_params(cfg.flat())), cfg)
    assert not runs.run_has_config(_run(untagged, {"train.lr": "1"}), cfg)
    assert not runs.is_preset_config(_run({"variant": "nope", "preset": "smoke", "seed": "1"}))
    # the rule itself, as the committed store's run.json rows ask it (tags and params only)
    assert runs.is_preset_fingerprint("l2", "smoke", 1, "", cfg.fingerprint())
    assert not runs.is_preset_fingerprint("l2", "smoke", 1, "", "0" * 16)
    assert not runs.is_preset_fingerprint("l2", "smoke", 1, "", None)
    assert not runs.is_preset_fingerprint("nope", "smoke", 1, "", cfg.fingerprint())
    on_root = resolve("l2", "smoke", 1, {"data": {"root": "/ycb"}})
    assert runs.is_preset_fingerprint("l2", "smoke", 1, "/ycb", on_root.fingerprint())


def test_resolve_run_id_errors(tmp_path):
    client = tracking.setup(tmp_path)
    with pytest.raises(ValueError, match="expected variant/preset/seedN"):
        runs.resolve_run_id(client, "shared-0/smoke/first")
    with pytest.raises(ValueError, match="no finished run named 'shared-0/smoke/seed1'"):
        runs.resolve_run_id(client, "shared-0/smoke/seed1")
    with pytest.raises(ValueError, match="neither a run folder"):
        runs.resolve_run_id(client, "not-a-run")
    runs.write_info(tmp_path / "r", {"run_id": "from-the-folder"})
    assert runs.resolve_run_id(client, str(tmp_path / "r")) == "from-the-folder"


def _finished(client, exp: str, cfg, name: str, data: str = "d" * 16) -> str:
    tags = {
        "variant": cfg.variant,
        "preset": cfg.preset,
        "seed": str(cfg.seed),
        "data": data,
        "config": cfg.fingerprint(),
    }
    run = client.create_run(exp, tags=tags, run_name=name)
    client.set_terminated(run.info.run_id, "FINISHED")
    return run.info.run_id


def test_every_printed_run_name_resolves(tmp_path):
    """``variant/preset/seedS+CONFIG``, as display_name prints a run with overrides, names that
    run; the plain name keeps naming the preset's own config."""
    client = tracking.setup(tmp_path)
    exp = tracking.experiment_id(client, "shared", tmp_path)
    own = resolve("shared-0", "smoke", seed=1)
    other = resolve("shared-0", "smoke", 1, {"train": {"epochs": 1}})
    own_id = _finished(client, exp, own, runs.display_name(own))
    other_id = _finished(client, exp, other, runs.display_name(other))
    assert runs.display_name(other).startswith("shared-0/smoke/seed1+")
    assert runs.resolve_run_id(client, runs.display_name(own)) == own_id
    assert runs.resolve_run_id(client, runs.display_name(other)) == other_id
    assert runs.resolve_run_id(client, f"shared-0/smoke/seed1+{other.fingerprint()}") == other_id
    with pytest.raises(ValueError, match="no finished run named 'shared-0/smoke/seed1' has a"):
        runs.resolve_run_id(client, "shared-0/smoke/seed1+ffffffff")
    with pytest.raises(ValueError, match="a config fingerprint after"):
        runs.resolve_run_id(client, "shared-0/smoke/seed1+")
    # the same config on two datasets: both listed, neither guessed
    twin_id = _finished(client, exp, other, runs.display_name(other), data="e" * 16)
    with pytest.raises(ValueError, match="2 finished runs of config") as info:
        runs.resolve_run_id(client, runs.display_name(other))
    assert other_id in str(info.value) and twin_id in str(info.value)


def test_a_second_process_of_one_run_waits_for_the_first(tmp_path):
    import threading

    folder = tmp_path / "runs" / "shared-0" / "smoke" / "seed1-abc-def"
    entered = threading.Event()

    def second() -> None:
        with runs.run_lock(folder):
            entered.set()

    with runs.run_lock(folder):
        assert runs.lock_path(folder).parent == folder.parent
        worker = threading.Thread(target=second, daemon=True)
        with pytest.warns(UserWarning, match="another process is training this run"):
            worker.start()
            assert not entered.wait(1.0)  # held: the second one waits
    assert entered.wait(10.0)  # released: it goes on
    worker.join(10.0)
    assert not folder.exists()  # the lock lives beside the folder, which it does not make


def test_the_run_record_names_and_tags_training_and_baseline_runs_in_one_place(tmp_path):
    from cloudpose.registry import resolve

    cfg = resolve("shared-0", "smoke", 2)
    tags = runs.training_tags(cfg, "shared", "d" * 20, tmp_path / "r")
    assert {k: tags[k] for k in ("variant", "group", "preset", "seed", "data", "config")} == {
        "variant": "shared-0",
        "group": "shared",
        "preset": "smoke",
        "seed": "2",
        "data": "d" * 20,
        "config": cfg.fingerprint(),
    }
    b = runs.baseline_tags("fpfh", "baselines", "cpu", 1, "k", "c" * 16, limit=None, split="test")
    assert b["variant"] == "baseline-fpfh" and b["kind"] == "baseline" and b["subsample"] == "all"
    own = "c" * 16
    assert runs.baseline_name("fpfh", "cpu", 1, "test", own, own) == "baseline-fpfh/cpu/seed1"
    other = runs.baseline_name("fpfh", "cpu", 1, "real", own, own)
    assert other == "baseline-fpfh/cpu/seed1+real-cccccccc"
    assert runs.baseline_name("ppf", "cpu", 1, "test", "e" * 16, own).endswith("+test-eeeeeeee")
    r = runs.report_tags("shared", "cpu", "cloudpose report", "k", (1, 2), ("abc",), "note")
    assert r["kind"] == "report" and r["seeds"] == "1,2" and "variant" not in r


def test_a_run_record_holds_its_params_and_config(tmp_path, monkeypatch):
    """Params beyond MLflow's 100 per request all arrive; the config is ``config.json``."""
    import json

    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    client = tracking.setup(tmp_path)
    exp = tracking.experiment_id(client, "shared", tmp_path)
    cfg = resolve("shared-0", "smoke", 1)
    params = {f"p.{i}": i for i in range(250)} | {"device": "cpu"}
    tags = runs.training_tags(cfg, "shared", "k" * 16, tmp_path / "r")
    run_id = runs.create_run_record(
        client, exp, "shared-0/smoke/seed1", tags, params, cfg.to_dict()
    )
    run = client.get_run(run_id)
    assert len(run.data.params) == 251 and run.data.params["p.249"] == "249"
    assert (
        run.info.run_name == "shared-0/smoke/seed1" and run.data.tags["config"] == cfg.fingerprint()
    )
    local = tracking.local_artifact(run.info.artifact_uri, "config.json")
    assert Config.from_dict(json.loads(Path(local).read_text())) == cfg


def test_a_run_folder_of_another_store_is_named_not_resumed(tmp_path, monkeypatch):
    """A run folder whose run.json names an MLflow run the current store lacks (it was started
    against another store) stops with the folder, the run and both ways on; a folder of this
    store resumes its own run."""
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    client = tracking.setup(tmp_path)
    cfg = resolve("shared-0", "smoke", 1)
    folder = tmp_path / "runs" / "r"
    kw = {"group": "shared", "params": {}, "project_dir": tmp_path}
    info = runs.open_training_run(client, cfg, "k" * 16, folder, **kw)
    assert runs.open_training_run(client, cfg, "k" * 16, folder, **kw)["run_id"] == info["run_id"]
    runs.write_info(folder, {**info, "run_id": "0" * 32})
    with pytest.raises(tracking.StoreError) as err:
        runs.open_training_run(client, cfg, "k" * 16, folder, **kw)
    message = str(err.value)
    assert str(folder / "run.json") in message and "0" * 32 in message
    assert "MLFLOW_TRACKING_URI" in message and "remove the folder" in message


def test_resolving_only_the_shipped_network_opens_no_store(tmp_path, monkeypatch):
    """A command given only the shipped network creates no mlflow.db; one that also names a
    run opens the project's store."""
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    assert runs.client_for(["pretrained", "pretrained"], tmp_path) is None
    assert list(tmp_path.iterdir()) == []
    with runs.local_checkpoint(None, "pretrained") as (run_id, path):
        assert run_id is None and path.is_file()
    assert runs.client_for(["pretrained", "shared-0/cpu/seed1"], tmp_path) is not None
    assert (tmp_path / tracking.STORE_DB).is_file()
