"""What ship, predict and showcase say and write when the input is not what they expect.

``ship`` never writes over the network a name answers to unless asked, names the run it ships
(preset and metrics) first and the file after it; ``predict`` writes its overlay where
``--overlay`` says and names that file, says when no object is labelled, and names
``--checkpoint`` (and a packed checkpoint of a compact store) in its errors; ``showcase``
checks its options before any work. The package's shipped network is never touched: ship
writes into a copy of its folder (:func:`package_copy`).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from PIL import Image

from cloudpose.conventions import resource_path
from cloudpose.store.pretrained import PRETRAINED, SHIPPED, SHIPPED_AS, shipped
from tests.conftest import DATA, cli, one_line_error

DEMO = DATA / "demo_no_gt"
SMOKE = "shared-0/smoke/seed1"
DEFAULT_STEM = SHIPPED[PRETRAINED]


def _digests(folder: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir())}


@pytest.fixture(scope="module")
def package_before() -> dict[str, str]:
    """The package's shipped files as the module found them (checked again after each test)."""
    return _digests(resource_path("pretrained"))


@pytest.fixture
def package_copy(tmp_path, monkeypatch, package_before) -> Path:
    """A copy of the package's ``resources/pretrained`` that every ``resource_path("pretrained")``
    names for the test (ship's default --out and :func:`shipped`'s folder)."""
    import cloudpose.conventions
    import cloudpose.store.pretrained

    original = cloudpose.conventions.resource_path
    folder = tmp_path / "package" / "pretrained"
    shutil.copytree(original("pretrained"), folder)

    def resource(*parts):
        return folder if parts == ("pretrained",) else original(*parts)

    monkeypatch.setattr(cloudpose.conventions, "resource_path", resource)
    monkeypatch.setattr(cloudpose.store.pretrained, "resource_path", resource)
    yield folder
    assert _digests(original("pretrained")) == package_before


def _smoke_checkpoint(path: Path) -> Path:
    """A checkpoint as the smoke preset's training writes one: its config, untrained weights."""
    from cloudpose.models.pose import build_model
    from cloudpose.registry import resolve

    cfg = resolve("shared-0", "smoke", seed=1)
    torch.manual_seed(0)
    model = build_model(cfg.model)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"model": model.state_dict(), "config": cfg.to_dict()}, path)
    return path


@pytest.fixture
def smoke_store(tmp_path, monkeypatch) -> Path:
    """The MLflow store ship reads holds one finished run, shared-0/smoke/seed1, every metric
    0.0 (as the smoke preset's are): the store and its resolver replaced by stand-ins."""
    import cloudpose.store.runs
    import cloudpose.store.tracking

    ckpt = _smoke_checkpoint(tmp_path / "runs" / "smoke" / "model.pt")
    metrics = {
        f"{s}/{k}": 0.0
        for s in ("test", "test_icp", "real", "real_icp")
        for k in ("ads_auc", "ad_auc")
    }
    record = SimpleNamespace(
        info=SimpleNamespace(run_name=SMOKE, run_id="f" * 32),
        data=SimpleNamespace(tags={"data": "0" * 16}, metrics=metrics),
    )
    client = SimpleNamespace(get_run=lambda run_id: record)

    @contextlib.contextmanager
    def local_checkpoint(_client, run):
        assert run == SMOKE, run
        yield "f" * 32, ckpt

    monkeypatch.setattr(cloudpose.store.tracking, "setup", lambda *a, **k: client)
    monkeypatch.setattr(cloudpose.store.runs, "local_checkpoint", local_checkpoint)
    return ckpt


# --- ship ----------------------------------------------------------------------------------


def test_ship_refuses_to_replace_the_shipped_network_without_force(package_copy, smoke_store):
    before = _digests(package_copy)
    res = cli("ship", "--run", SMOKE, "--no-reduce")
    line = one_line_error(res, str(package_copy), "--force", "shared-0/gpu/seed1", SMOKE)
    assert "preset smoke" in line and "real_icp/ads_auc 0.000" in line
    assert _digests(package_copy) == before


def test_ship_with_force_names_the_run_then_replaces_the_network(package_copy, smoke_store):
    res = cli("ship", "--run", SMOKE, "--force", "--no-reduce")
    assert res.exit_code == 0, res.output
    lines = res.output.splitlines()
    assert lines[0].startswith(f"shipping {SMOKE} (preset smoke, not the default cpu-online)")
    assert "test/ads_auc 0.000" in lines[0] and "real_icp/ads_auc 0.000" in lines[0]
    assert lines[1] == f"as 'pretrained': {package_copy / 'shared-0_smoke_seed1.pt'}"
    assert lines[2].startswith("replacing shared-0/gpu/seed1 (preset gpu, not the default")
    assert f"removed {package_copy / DEFAULT_STEM}.pt" in res.output
    assert sorted(p.name for p in package_copy.iterdir()) == [
        "shared-0_smoke_seed1.json",
        "shared-0_smoke_seed1.pt",
    ]
    net = shipped(folder=package_copy)
    assert net.path.name == "shared-0_smoke_seed1.pt" and net.info["run_name"] == SMOKE
    assert net.info[SHIPPED_AS] == PRETRAINED
    assert net.path.read_bytes() == smoke_store.read_bytes()


def test_ship_into_a_new_folder_names_the_file_after_the_run(package_copy, smoke_store, tmp_path):
    out = tmp_path / "shipped"
    res = cli("ship", "--run", SMOKE, "--out", str(out), "--no-reduce")
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in out.iterdir()) == [
        "shared-0_smoke_seed1.json",
        "shared-0_smoke_seed1.pt",
    ]
    assert "replacing" not in res.output and shipped(folder=out).info["run_name"] == SMOKE
    again = cli("ship", "--run", SMOKE, "--out", str(out), "--no-reduce")
    one_line_error(again, str(out), "--force", SMOKE)


def test_the_shipped_name_follows_the_record_that_names_it(package_copy, tmp_path):
    """A record answering to ``pretrained`` wins over the package's default stem; two of them
    are one line naming both."""
    folder = tmp_path / "two"
    shutil.copytree(package_copy, folder)
    default = folder / f"{DEFAULT_STEM}.json"
    info = json.loads(default.read_text())
    info.pop(SHIPPED_AS, None)  # the package's stem answers to the name without a record's word
    default.write_text(json.dumps(info, indent=1) + "\n")
    for suffix in (".pt", ".json"):
        shutil.copy(folder / f"{DEFAULT_STEM}{suffix}", folder / f"other{suffix}")
    record = folder / "other.json"
    record.write_text(
        record.read_text().replace('"made_by"', f'"{SHIPPED_AS}": "pretrained", "made_by"')
    )
    assert shipped(folder=folder).path == folder / "other.pt"
    record.rename(folder / "third.json")
    (folder / "other.pt").rename(folder / "third.pt")
    shutil.copy(folder / "third.json", record)
    shutil.copy(folder / "third.pt", folder / "other.pt")
    with pytest.raises(ValueError, match=r"other\.json, third\.json all ship as 'pretrained'"):
        shipped(folder=folder)


# --- predict ---------------------------------------------------------------------------------


def _predict(*args: str):
    return cli(
        "predict",
        "--depth",
        str(DEMO / "depth.png"),
        "--checkpoint",
        PRETRAINED,
        *args,
    )


def test_predict_overlay_in_a_folder_is_a_file_inside_it(tmp_path):
    folder = tmp_path / "pictures"
    folder.mkdir()
    res = _predict("--label", str(DEMO / "label.png"), "--overlay", str(folder))
    assert res.exit_code == 0, res.output
    written = folder / "prediction.png"
    assert res.output.splitlines()[-1] == f"overlay: {written}"
    assert written.is_file() and not (tmp_path / "pictures.png").exists()
    assert Image.open(written).format == "PNG"


def test_predict_overlay_named_without_a_suffix_gets_png_and_is_named(tmp_path):
    res = _predict("--label", str(DEMO / "label.png"), "--overlay", str(tmp_path / "frame1"))
    assert res.exit_code == 0, res.output
    assert res.output.splitlines()[-1] == f"overlay: {tmp_path / 'frame1.png'}"
    assert (tmp_path / "frame1.png").is_file() and not (tmp_path / "frame1").exists()


def test_overlay_path_rules(tmp_path):
    from cloudpose.predict import overlay_path

    assert overlay_path(f"{tmp_path}/new/") == tmp_path / "new" / "prediction.png"
    assert overlay_path(tmp_path) == tmp_path / "prediction.png"
    assert overlay_path(tmp_path / "a.PNG") == tmp_path / "a.PNG"
    assert overlay_path("x") == Path("x.png")
    with pytest.raises(ValueError, match=r"--overlay .*a\.jpg: expected a \.png file"):
        overlay_path(tmp_path / "a.jpg")


def test_predict_overlay_with_another_suffix_is_refused_before_any_work(tmp_path):
    res = _predict("--label", str(DEMO / "label.png"), "--overlay", str(tmp_path / "o.jpg"))
    one_line_error(res, "--overlay", "o.jpg", ".png")
    assert list(tmp_path.iterdir()) == []


def test_predict_says_when_no_object_is_labelled(tmp_path):
    label = tmp_path / "empty-label.png"
    Image.fromarray(np.zeros((480, 640), np.uint8)).save(label)
    res = _predict("--label", str(label), "--overlay", str(tmp_path / "o.png"))
    assert res.exit_code == 0, res.output
    lines = res.output.splitlines()
    assert lines[0].startswith(f"no object found: --label {label} labels no pixel")
    assert lines[-1] == f"overlay: {tmp_path / 'o.png'}" and len(lines) == 2


def test_predict_says_when_no_labelled_object_has_depth(tmp_path):
    label = np.array(Image.open(DEMO / "label.png"))
    depth = np.array(Image.open(DEMO / "depth.png"))
    depth[label > 0] = 0
    holes = tmp_path / "depth-holes.png"
    Image.fromarray(depth).save(holes)
    res = cli(
        "predict",
        "--depth",
        str(holes),
        "--label",
        str(DEMO / "label.png"),
        "--checkpoint",
        PRETRAINED,
        "--overlay",
        str(tmp_path / "o.png"),
    )
    assert res.exit_code == 0, res.output
    note = next(line for line in res.output.splitlines() if line.startswith("no object posed"))
    assert "class ids 2, 4, 5, 10, 15" in note and str(holes) in note and "--depth-factor" in note


def test_predict_names_a_missing_checkpoint_file_as_checkpoint(tmp_path):
    res = _predict("--label", str(DEMO / "label.png"), "--checkpoint", "nothere.pt")
    line = one_line_error(res, "--checkpoint nothere.pt", "no such file")
    assert "--run" not in line
    assert not Path("mlflow.db").exists()  # no store opened for a file name


def test_predict_names_an_unknown_run_as_checkpoint(tmp_path):
    res = _predict("--label", str(DEMO / "label.png"), "--checkpoint", "a/b/seedX")
    line = one_line_error(res, "--checkpoint 'a/b/seedX'")
    assert "--run" not in line


@pytest.mark.parametrize("form", ["float24", "float16"])
def test_predict_reads_a_packed_checkpoint_by_name_and_content(form, tmp_path):
    """A compact store's ``model.f24.pt`` (or one renamed) is a checkpoint every reader loads:
    the poses are those of its unpacked float32 weights."""
    from cloudpose.models.stored import REDUCED, decode, encode

    ckpt = torch.load(_smoke_checkpoint(tmp_path / "model.pt"), weights_only=True)
    packed = tmp_path / f"model{REDUCED[form]}"
    torch.save(encode(ckpt, form), packed)
    unpacked = tmp_path / "unpacked.pt"
    torch.save(decode(torch.load(packed, weights_only=True)), unpacked)
    renamed = tmp_path / "renamed.pt"
    renamed.write_bytes(packed.read_bytes())
    outputs = []
    for path in (unpacked, packed, renamed):
        res = _predict(
            "--label",
            str(DEMO / "label.png"),
            "--checkpoint",
            str(path),
            "--overlay",
            str(tmp_path / f"{path.stem}.png"),
        )
        assert res.exit_code == 0, res.output
        outputs.append([line for line in res.output.splitlines() if "overlay" not in line])
    assert outputs[0] and outputs[0] == outputs[1] == outputs[2]


def test_a_same_size_shipped_file_with_another_checksum_names_the_checksum(package_copy):
    weights = package_copy / f"{DEFAULT_STEM}.pt"
    data = bytearray(weights.read_bytes())
    data[-100] ^= 0x01
    weights.write_bytes(bytes(data))
    line = one_line_error(_predict("--label", str(DEMO / "label.png")), str(weights), "SHA-256")
    assert "bytes, not the" not in line


# --- showcase --------------------------------------------------------------------------------


@pytest.fixture
def no_work(monkeypatch):
    """Rendering or evaluating anything fails the test: the options are checked first."""
    import cloudpose.studies.showcase

    def work(*args, **kwargs):
        raise AssertionError("work started before the options were checked")

    for name in ("synthesize", "run_compare", "predict", "shipped"):
        monkeypatch.setattr(cloudpose.studies.showcase, name, work)


def test_showcase_refuses_a_negative_frame_count_before_any_work(no_work, tmp_path):
    out = tmp_path / "show"
    res = cli("showcase", "--synthetic-frames", "-4", "--out", str(out), "--no-progress")
    one_line_error(res, "--synthetic-frames -4", "0")
    assert not out.exists()


def test_showcase_refuses_an_unknown_refinement_before_any_work(no_work, tmp_path):
    out = tmp_path / "show"
    res = cli("showcase", "--refine", "fast", "--out", str(out), "--no-progress")
    one_line_error(res, "--refine 'fast'", "paper", "wide")
    assert not out.exists()


def test_showcase_refuses_an_unknown_baseline_before_any_work(no_work, tmp_path):
    out = tmp_path / "show"
    res = cli("showcase", "--baseline", "foo", "--out", str(out), "--no-progress")
    one_line_error(res, "--baseline 'foo'", "fpfh", "ppf")
    assert not out.exists()
