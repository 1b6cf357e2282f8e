"""What ``cloudpose compare`` keeps and reads back is checked before it is trusted, and what it
computes survives a stop: a cache that lacks an array or holds no pose and a table that lacks a
column or was edited are named and computed again; a baseline's estimates are kept on Ctrl-C and
SIGTERM and the rerun resumes them; the plan counts PPF's detector training. Beside them, the
``--run`` of ``same-data`` and the counts of ``stress`` are checked at the entry point."""

from __future__ import annotations

import os
import shutil
import signal
import threading
import time

import numpy as np
import pandas as pd
import pytest

from tests.conftest import DATA, cli, one_line_error

REAL = DATA / "ycb_real"  # one real annotated frame
QUICK = {"starts": 1, "select": "fitness", "radius": 0.05}


# --------------------------------------------------------------------------- fakes


class _Segments:
    """What a baseline's loop reads of a segment set: length, validity, classes, points."""

    def __init__(self, n: int, classes: list[int] | None = None):
        rng = np.random.default_rng(n)
        self.points = rng.normal(size=(n, 16, 3)) + np.array([0.0, 0.0, 1.0])
        self.valid = np.ones(n, dtype=bool)
        self.cls_id = np.array(classes if classes is not None else [1 + i % 3 for i in range(n)])

    def __len__(self) -> int:
        return len(self.points)

    def observed(self, i: int) -> np.ndarray:
        return self.points[i]


MODELS = {c: np.zeros((4, 3)) for c in (1, 2, 3, 4)}


class _Estimator:
    """A baseline whose pose of a segment depends on its points and on the draws so far
    (``calls``), as RANSAC's does; ``stop`` is called before the estimate numbered ``at``."""

    def __init__(self, at: int | None = None, stop=None):
        self.calls, self.at, self.stop = 0, at, stop
        self.seen: list[int] = []
        self.prepared: list[int] = []

    def prepare(self, cls_ids) -> None:
        self.prepared += [int(c) for c in cls_ids]

    def estimate(self, points, cls_id):
        from cloudpose.baselines.base import PoseEstimate

        if len(self.seen) == self.at:
            self.stop()
        self.calls += 1
        self.seen.append(int(cls_id))
        a = 0.1 * self.calls
        R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0, 0, 1.0]])
        return PoseEstimate(R, points.mean(axis=0), 1.0)


def _interrupt():
    raise KeyboardInterrupt


def _sigterm():
    """SIGTERM to this process, as ``kill PID`` sends it; refused (an AssertionError, not a
    dead test run) unless the code under test takes it as an interrupt."""
    if signal.getsignal(signal.SIGTERM) in (signal.SIG_DFL, signal.SIG_IGN, None):
        raise AssertionError("SIGTERM is not taken as an interrupt here: it would kill the run")
    os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(5)  # the handler raises before this returns
    raise AssertionError("SIGTERM raised nothing")


def _use(monkeypatch, estimator) -> None:
    import cloudpose.baselines as baselines

    monkeypatch.setattr(baselines, "make", lambda *a, **k: estimator)


# --------------------------------------------------------------------------- baseline estimates


def _saved(path, n, **change) -> None:
    arrays = dict(R=np.tile(np.eye(3), (n, 1, 1)), t=np.ones((n, 3)), done=np.ones(n, bool),
                  ok=np.ones(n, bool), seconds=1.0, calls=n)  # fmt: skip
    arrays.update(change)
    for k in [k for k, v in change.items() if v is None]:
        del arrays[k]
    np.savez(path, **arrays)


@pytest.mark.parametrize(
    ("change", "said"),
    [
        ({"t": None, "ok": None}, "lacks fields ['t', 'ok']"),
        ({"R": np.zeros((4, 3, 3))}, "4 registered pose(s) that are no pose"),
        ({"t": np.full((4, 3), np.nan)}, "no pose"),
        ({"done": np.ones(5, bool)}, "other shapes"),
    ],
    ids=["lacks-arrays", "all-zero", "not-finite", "other-count"],
)
def test_a_baseline_cache_that_cannot_serve_is_named_and_computed_again(change, said, tmp_path):
    from cloudpose.methods import EstimateProgress, estimate_all

    path = tmp_path / "fpfh.npz"
    _saved(path, 4, **change)
    with pytest.warns(UserWarning, match="computed again") as caught:
        state = EstimateProgress(path, 4)
    message = str(caught[0].message)
    assert message.startswith(str(path)) and said in message and "\n" not in message
    assert not state.done.any() and state.calls == 0
    fresh = _Estimator()
    estimate_all(fresh, MODELS, _Segments(4), state, "fpfh", False)
    assert len(fresh.seen) == 4 and state.ok.all()
    assert EstimateProgress(path, 4).done.all()  # the cache is whole again


# --------------------------------------------------------------------------- the plan


def test_the_plan_counts_ppfs_detector_training_and_shows_it_as_it_goes(tmp_path, capsys):
    """Each model PPF needs costs a detector's training before its first estimate: the plan
    counts it (and names it) for the models of the estimates left, and the training shows a
    bar of its own."""
    from cloudpose.methods import (
        SECONDS_PER_INSTANCE,
        SECONDS_PER_MODEL,
        EstimateProgress,
        estimate_all,
    )
    from cloudpose.studies.compare import plan

    segs = _Segments(10, classes=[1, 1, 2, 2, 3, 3, 4, 4, 4, 4])
    state = EstimateProgress(tmp_path / "ppf.npz", 10)
    text = plan(segs, {"ppf": state}, {})
    assert "ppf estimates: 10 of 10 to compute, training 4 detector(s) first" in text
    seconds = 10 * SECONDS_PER_INSTANCE["ppf"] + 4 * SECONDS_PER_MODEL["ppf"]
    assert f"about {seconds / 60:.0f} min" in text
    state.done[:6] = True  # those of classes 1-3 done: one detector left to train
    assert "4 of 10 to compute, training 1 detector(s) first" in plan(segs, {"ppf": state}, {})
    # two frames' six instances of four models: seconds of estimates, minutes of training
    six = _Segments(6, classes=[1, 2, 3, 4, 1, 2])
    assert "about 2 min" in plan(six, {"ppf": EstimateProgress(tmp_path / "b.npz", 6)}, {})
    estimator = _Estimator()
    capsys.readouterr()
    estimate_all(estimator, MODELS, segs, state, "ppf", progress=True)
    err = capsys.readouterr().err
    assert "ppf models" in err and "1/1" in err and estimator.prepared == [4]


def test_the_stress_plan_counts_a_baselines_models_once_per_source(tmp_path):
    from cloudpose.methods import SECONDS_PER_MODEL
    from cloudpose.studies import perturbations as pt
    from cloudpose.studies import stress as st

    perts = [pt.PERTURBATIONS["dilate"]]
    methods = [st.SweepMethod("ppf", limit=3)]
    bare = st.make_plan(tmp_path, {"real": 10}, perts, methods).seconds
    trained = st.make_plan(tmp_path, {"real": 10}, perts, methods, {"real": 5}).seconds
    assert trained - bare == pytest.approx(3 * SECONDS_PER_MODEL["ppf"])  # 3 of 5 at most


# --------------------------------------------------------------------------- a comparison's folder


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    """(project, comparison folder, its tables, the comparison) of the shipped network and the
    control on the one real frame, each after two refinements."""
    from cloudpose.studies.compare import run_compare

    proj = tmp_path_factory.mktemp("trust")
    done = run_compare(proj / "cmp", data=REAL, frames="all", methods=["none"], project_dir=proj,
                       progress=False, **QUICK)  # fmt: skip
    return proj, done.out_dir, done.tables, done


def _again(folder, tmp_path, monkeypatch):
    """A copy of the folder, and a call on it that counts what it refines and estimates."""
    import cloudpose.infer as infer
    import cloudpose.studies.compare as compare

    proj, out, *_ = folder
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    done = {"refined": [], "estimated": 0}
    refine, estimate = compare._refine, infer.estimate_poses

    def refine_spy(c, segs, dataset, models, ref, *args, **kwargs):
        done["refined"].append(f"{c.name}-{ref.name}")
        return refine(c, segs, dataset, models, ref, *args, **kwargs)

    def estimate_spy(*args, **kwargs):
        done["estimated"] += 1
        return estimate(*args, **kwargs)

    monkeypatch.setattr(compare, "_refine", refine_spy)
    monkeypatch.setattr(infer, "estimate_poses", estimate_spy)

    def call():
        return compare.run_compare(copy, data=REAL, frames="all", methods=["none"],
                                   project_dir=proj, progress=False, **QUICK)  # fmt: skip

    return copy, call, done


def _one_warning(caught, path, *needles) -> str:
    said = [str(w.message) for w in caught if str(path) in str(w.message)]
    assert len(said) == 1, [str(w.message) for w in caught]
    assert "\n" not in said[0] and said[0].endswith("computed again")
    for n in needles:
        assert n in said[0], said[0]
    return said[0]


def _compare(out, proj, method, progress=False):
    from cloudpose.studies.compare import run_compare

    return run_compare(out, data=REAL, frames="all", methods=[method], project_dir=proj,
                       progress=progress, **QUICK)  # fmt: skip


@pytest.mark.parametrize("stop", [_interrupt, _sigterm], ids=["ctrl-c", "sigterm"])
def test_a_stopped_comparison_keeps_its_baseline_estimates_and_the_rerun_resumes_them(
    stop, folder, tmp_path, monkeypatch, capsys
):
    """``compare --method fpfh`` stopped after 1 of the frame's 3 estimates (well within a
    minute), by Ctrl-C or by SIGTERM: the estimate is in the project's cache, and the same
    call estimates only the 2 left, with the poses of a call that went through (the draw count
    is kept with them)."""
    if threading.current_thread() is not threading.main_thread():
        pytest.skip("signals reach the main thread only")
    out = folder[1]
    _use(monkeypatch, _Estimator())
    straight = _compare(tmp_path / "a", tmp_path / "pa", "fpfh")
    shutil.copytree(out, tmp_path / "b")  # the network's estimates are kept there
    _use(monkeypatch, _Estimator(at=1, stop=stop))
    with pytest.raises(KeyboardInterrupt):
        _compare(tmp_path / "b", tmp_path / "pb", "fpfh")
    saved = list((tmp_path / "pb" / "runs" / "compare" / "estimates").glob("fpfh-*.npz"))
    assert len(saved) == 1, "no estimate kept"
    assert f"stopped at 1 of 3 estimates, kept in {saved[0]}" in capsys.readouterr().out
    with np.load(saved[0]) as f:
        assert f["done"].tolist() == [True, False, False] and int(f["calls"]) == 1
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # the handler is put back
    rest = _Estimator()
    _use(monkeypatch, rest)
    resumed = _compare(tmp_path / "b", tmp_path / "pb", "fpfh")
    assert len(rest.seen) == 2  # only the estimates left
    ours, theirs = (next(c for c in x.contenders if c.name == "fpfh") for x in (resumed, straight))
    np.testing.assert_array_equal(ours.estimates[0].R, theirs.estimates[0].R)
    np.testing.assert_array_equal(ours.estimates[0].t, theirs.estimates[0].t)
    pd.testing.assert_frame_equal(resumed.tables[("fpfh", "icp")], straight.tables[("fpfh", "icp")])


def test_compares_plan_counts_ppfs_detector_training_and_shows_it(
    folder, tmp_path, monkeypatch, capsys
):
    """``compare --method ppf`` on the frame's 3 instances of 3 objects: the plan names the
    detectors to train and counts their minutes, and their training shows a bar."""
    shutil.copytree(folder[1], tmp_path / "c")
    estimator = _Estimator()
    _use(monkeypatch, estimator)
    _compare(tmp_path / "c", tmp_path / "p", "ppf", progress=True)
    said = capsys.readouterr()
    plan = next(line for line in said.out.splitlines() if line.startswith("compare:"))
    assert "ppf estimates: 3 of 3 to compute, training 3 detector(s) first" in plan, plan
    assert "about 1 min on one core" in plan, plan  # 3 x 3.5 s, and 3 x 25 s of training
    assert "ppf models" in said.err and "3/3" in said.err and len(estimator.prepared) == 3


def test_a_table_without_a_column_is_named_by_its_column_and_computed_again(
    folder, tmp_path, monkeypatch
):
    copy, call, done = _again(folder, tmp_path, monkeypatch)
    path = copy / "tables" / "network-icp.csv"
    pd.read_csv(path).drop(columns=["icp_ads"]).to_csv(path, index=False)
    with pytest.warns(UserWarning) as caught:
        again = call()
    _one_warning(caught, path, "lacks column(s) icp_ads")
    assert done["refined"] == ["network-icp"] and done["estimated"] == 0  # from network.npz
    np.testing.assert_allclose(again.tables[("network", "icp")]["icp_ads"],
                               folder[2][("network", "icp")]["icp_ads"], atol=1e-9)  # fmt: skip


def test_the_report_names_the_file_and_column_a_table_lacks(folder, tmp_path):
    import dataclasses

    from cloudpose.report.compare import render

    _, out, tables, comparison = folder
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    broken = {**tables, ("none", "icp"): tables[("none", "icp")].drop(columns=["icp_ads"])}
    with pytest.raises(ValueError, match=r"tables/none-icp\.csv: lacks column\(s\) icp_ads"):
        render(dataclasses.replace(comparison, out_dir=copy, tables=broken), "cloudpose compare")
    assert not (copy / "compare.md").exists()


def test_a_hand_edited_table_is_computed_again(folder, tmp_path, monkeypatch):
    copy, call, done = _again(folder, tmp_path, monkeypatch)
    path = copy / "tables" / "none-icp-radius50mm.csv"
    table = pd.read_csv(path, dtype={"frame_id": str})
    table["icp_ads"] = 0.0  # a better (or worse) number than was computed
    table.to_csv(path, index=False)
    with pytest.warns(UserWarning) as caught:
        again = call()
    _one_warning(caught, path, "checksum")
    assert done["refined"] == ["none-icp-radius50mm"]
    np.testing.assert_allclose(again.tables[("none", "icp-radius50mm")]["icp_ads"],
                               folder[2][("none", "icp-radius50mm")]["icp_ads"], atol=1e-9)  # fmt: skip
    # the table written is trusted again: a further call computes nothing
    done["refined"].clear()
    call()
    assert done["refined"] == []


def test_a_table_of_other_instances_is_computed_again(folder, tmp_path, monkeypatch):
    copy, call, done = _again(folder, tmp_path, monkeypatch)
    path = copy / "tables" / "none-icp.csv"
    pd.read_csv(path).iloc[:-1].to_csv(path, index=False)
    with pytest.warns(UserWarning) as caught:
        call()
    _one_warning(caught, path, "not the 3 segments compared")
    assert done["refined"] == ["none-icp"]


@pytest.mark.parametrize(
    ("damage", "said"),
    [("zeros", "no pose"), ("lacks", "lacks fields ['t']"), ("garbled", "unreadable")],
)
def test_a_network_cache_that_cannot_serve_is_named_and_computed_again(
    damage, said, folder, tmp_path, monkeypatch
):
    """``estimates/network.npz`` all zeros (every rotation no rotation), without its
    translations, or not an archive: a warning naming it, the networks' estimates made again,
    and the tables the same as the first call's."""
    copy, call, done = _again(folder, tmp_path, monkeypatch)
    path = copy / "estimates" / "network.npz"
    with np.load(path) as f:
        arrays = {k: f[k] for k in f.files}
    if damage == "zeros":
        np.savez(path, **{k: np.zeros_like(v) for k, v in arrays.items()})
    elif damage == "lacks":
        np.savez(path, R=arrays["R"], ms=arrays["ms"])
    else:
        path.write_bytes(b"not an archive" * 10)
    for f in (copy / "tables").glob("network-*.csv"):
        f.unlink()
    with pytest.warns(UserWarning) as caught:
        again = call()
    _one_warning(caught, path, said)
    assert done["estimated"] == 1
    for ref in ("icp", "icp-radius50mm"):
        np.testing.assert_allclose(again.tables[("network", ref)]["icp_ads"],
                                   folder[2][("network", ref)]["icp_ads"], atol=1e-6)  # fmt: skip
    with np.load(path) as f:
        np.testing.assert_allclose(f["R"], arrays["R"], atol=1e-6)  # rewritten whole


# --------------------------------------------------------------------------- entry points


@pytest.fixture
def store(empty_store, tmp_path, monkeypatch):
    """An empty MLflow store in the current folder (``mlflow.db``)."""
    shutil.copy(empty_store, tmp_path / "mlflow.db")
    monkeypatch.chdir(tmp_path)
    return tmp_path


@pytest.mark.parametrize("run", ["deadbeef", "shared-0/cpu-online/seed1", "", "shared-0/x/y"])
def test_same_data_refuses_a_run_it_cannot_find_in_one_line(store, run):
    one_line_error(cli("same-data", "--run", run), f"--run {run!r}")


def test_same_data_takes_a_run_by_name_as_the_other_commands_do(store, monkeypatch):
    from cloudpose.registry import resolve
    from cloudpose.store import rekey, tracking

    client = tracking.setup(store)
    exp = client.create_experiment(f"{tracking.EXPERIMENT_PREFIX}shared")
    tags = {"variant": "shared-0", "preset": "smoke", "seed": "1",
            "config": resolve("shared-0", "smoke", 1).fingerprint()}  # fmt: skip
    run_id = client.create_run(exp, tags=tags).info.run_id
    client.set_terminated(run_id, "FINISHED")
    asked = []

    def compared(run, project_dir):
        asked.append(run)
        return rekey.SegmentComparison(run, {"data": ("a", "a"), "test": ("b", "b")}, (3, 3),
                                       0, 0, 0, 0.0)  # fmt: skip

    monkeypatch.setattr(rekey, "compare_test_segments", compared)
    for given in ("shared-0/smoke/seed1", run_id):
        res = cli("same-data", "--run", given)
        assert res.exit_code == 0, res.output
        assert "nothing to add" in res.output
    assert asked == [run_id, run_id]


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--sample", "instances=-5"], "--sample instances=-5: expected a positive number"),
        (["--sample", "instances=0"], "--sample instances=0"),
        (["--sample", "quick,fpfh-instances=-1"], "--sample fpfh-instances=-1"),
        (["--sample", "ppf-instances=-2"], "--sample ppf-instances=-2"),
        (["--sample", "synth-frames=0"], "--sample synth-frames=0"),
        (["--sample", "seed=x"], "--sample seed=x: expected a whole number"),
        (["--sample", "ppf-levels=some"], "--sample ppf-levels=some: expected all or ends"),
        (["--sample", "frames=3"], "--sample frames=3: expected a key of instances"),
        (["--only", "cut", "--only", "reel"], "--only reel: expected sources (real, synth)"),
        (["--steps", "render"], "--steps 'render': expected sweep, report"),
        (["--steps", "none"], "--steps none: nothing to do without --pack"),
    ],
)
def test_stress_names_the_setting_it_refuses(args, needle, tmp_path):
    res = cli("stress", "--run", "pretrained", *args, "--results", str(tmp_path / "r"),
              "--dry-run", "--no-progress")  # fmt: skip
    line = one_line_error(res, needle)
    assert "--limit" not in line and not (tmp_path / "r").exists()
