"""Files the suite writes and reads back, damaged: zero bytes, cut short, garbled, the wrong
shape (issue 40). A cache is made again with a one-line warning naming it; anything else stops
with one line naming the file and what to do; never a traceback or "Aborted."."""

from __future__ import annotations

import json
import pickle
import shutil
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
import typer
from typer.testing import CliRunner

from cloudpose.conventions import load_classes, resource_path
from cloudpose.files import CorruptFileError, read_json, read_npz
from tests.conftest import cli, one_line_error

# --------------------------------------------------------------------------- a tiny dataset


def _tiny_root(path: Path, train=("0000/000001",), test=("0000/000002",)) -> Path:
    """A YCB-Video-layout root of a few of the packaged real development frames."""
    src = resource_path("real_dev")
    (path / "image_sets").mkdir(parents=True)
    shutil.copyfile(src / "classes.txt", path / "classes.txt")
    for fid in {*train, *test}:
        seq, name = fid.split("/")
        (path / "data" / seq).mkdir(parents=True, exist_ok=True)
        for kind in ("depth.png", "label.png", "meta.mat"):
            shutil.copyfile(
                src / "data" / seq / f"{name}-{kind}", path / "data" / seq / f"{name}-{kind}"
            )
    (path / "image_sets" / "train.txt").write_text("".join(f + "\n" for f in train))
    (path / "keyframe.txt").write_text("".join(f + "\n" for f in test))
    return path


def _smoke_data():
    from cloudpose.registry import resolve

    return resolve("shared-0", "smoke").data


def _cut(path: Path, keep: float | int) -> None:
    """Leave the first ``keep`` bytes of ``path`` (a fraction of its size when a float)."""
    raw = path.read_bytes()
    path.write_bytes(raw[: int(len(raw) * keep) if isinstance(keep, float) else keep])


# --------------------------------------------------------------------------- 1: frame PNGs


@pytest.mark.parametrize("damage", ["zero", "truncated"])
def test_a_damaged_png_in_a_dataset_is_one_line_naming_it(tmp_path, damage):
    """Item 1: the cache key's digest opened the image first: Pillow's traceback, no file."""
    root = _tiny_root(tmp_path / "root")
    png = root / "data" / "0000" / "000002-depth.png"
    _cut(png, 0 if damage == "zero" else 0.5)
    res = cli("prepare", "--preset", "smoke", "--data", str(root), "--no-progress")
    line = one_line_error(res, str(png), "not a readable PNG")
    assert "replace it" in line


def test_a_zero_byte_synthetic_frame_is_rendered_again(tmp_path):
    """A synthetic frame file of zero bytes is not a frame: the synth renders it anew; a model
    file it copied, cut short, is copied again."""
    from cloudpose.data.synth import synthesize

    root = tmp_path / "synth"
    assert synthesize(root, 1, 0, workers=1, progress=False).frames_written == 1
    png = next((root / "data").glob("*/*-label.png"))
    model = root / "models" / "025_mug" / "points.xyz"
    before = png.read_bytes()
    png.write_bytes(b"")
    _cut(model, 0.5)
    again = synthesize(root, 1, 0, workers=1, progress=False)
    assert (again.frames_written, again.frames_skipped) == (1, 0)
    assert png.read_bytes() == before
    assert model.read_bytes() == resource_path("models", "025_mug", "points.xyz").read_bytes()


# --------------------------------------------------------------------------- 2: the CLI


def _reader_app():
    """An app with the cloudpose error handler and commands that read a file the way numpy,
    zipfile, pickle and json do."""
    from cloudpose.cli.app import _Commands

    app = typer.Typer(cls=_Commands)

    @app.command()
    def read(kind: str, path: Path) -> None:
        if kind == "npy":
            np.load(path)
        elif kind == "zip":
            zipfile.ZipFile(path)
        elif kind == "pickle":
            with open(path, "rb") as f:
                pickle.load(f)
        elif kind == "json":
            json.loads(path.read_text())
        elif kind == "pipe":  # a worker process gone: its pipe ends, no file is to blame
            import multiprocessing

            ours, theirs = multiprocessing.Pipe()
            theirs.close()
            ours.recv()

    @app.command()
    def other() -> None:  # two commands: typer makes a group, as cloudpose's app is
        pass

    return app


@pytest.mark.parametrize(
    "kind, content",
    [("npy", b""), ("zip", b"PK\x03\x04garbage"), ("pickle", b"\x80\x04garbage"), ("json", b"{")],
)
def test_an_unreadable_file_is_one_line_naming_it_not_aborted(tmp_path, kind, content):
    """Item 2: EOFError (np.load, torch.load, lzma of a zero-byte file) became "Aborted." with
    exit 1; BadZipFile, UnpicklingError and JSONDecodeError a traceback or a line naming no
    file."""
    path = tmp_path / f"state.{kind}"
    path.write_bytes(content)
    res = CliRunner().invoke(_reader_app(), ["read", kind, str(path)])
    assert "Aborted" not in res.output
    one_line_error(res, str(path), "unreadable")


def test_an_eof_error_of_a_pipe_blames_no_file(tmp_path):
    path = tmp_path / "innocent.npz"
    path.write_bytes(b"")
    res = CliRunner().invoke(_reader_app(), ["read", "pipe", str(path)])
    line = one_line_error(res, "a worker process ended early (EOFError")
    assert str(path) not in line


def test_under_debug_an_eof_error_shows_its_traceback_not_aborted(tmp_path, monkeypatch):
    import importlib

    app_module = importlib.import_module("cloudpose.cli.app")  # the module, not the app
    monkeypatch.setattr(app_module, "_DEBUG", True)
    path = tmp_path / "empty.npz"
    path.write_bytes(b"")
    res = CliRunner().invoke(_reader_app(), ["read", "npy", str(path)])
    assert res.exit_code != 0 and "Aborted" not in res.output
    assert isinstance(res.exception, RuntimeError) and str(path) in str(res.exception)
    assert isinstance(res.exception.__cause__, EOFError)


@pytest.mark.parametrize("content", [b"", b"PK\x03\x04", b"garbage" * 20])
def test_read_npz_names_the_file(tmp_path, content):
    path = tmp_path / "a.npz"
    path.write_bytes(content)
    with pytest.raises(CorruptFileError, match=r"a\.npz: thing is unreadable") as e:
        read_npz(path, ["x"], "thing")
    assert e.value.path == path


def test_read_json_names_the_file_and_what_to_do(tmp_path):
    path = tmp_path / "run.json"
    path.write_text('{"a": ')
    with pytest.raises(
        CorruptFileError, match=r"run.json: run record is not readable JSON .*; redo"
    ):
        read_json(path, "run record", "redo")


# --------------------------------------------------------------------------- 3: segment caches


def _damage_npz(path: Path, damage: str) -> None:
    if damage == "zero":
        path.write_bytes(b"")
    elif damage == "truncated":
        _cut(path, 0.6)
    elif damage == "garbled":  # same size, bytes of an array overwritten: its CRC fails on read
        raw = bytearray(path.read_bytes())
        raw[len(raw) // 3 : len(raw) // 3 + 64] = bytes(64)
        path.write_bytes(bytes(raw))
    elif damage == "shape":  # readable, but its fields do not agree
        with np.load(path) as z:
            arrays = dict(z)
        arrays["R"] = arrays["R"][:-1]
        np.savez(path.with_suffix(""), **arrays)


@pytest.mark.parametrize("damage", ["zero", "truncated", "garbled", "shape"])
def test_a_damaged_segment_cache_is_made_again_with_a_warning(tmp_path, damage):
    """Item 3: a truncated segment cache (BadZipFile, traceback) was never rebuilt."""
    from cloudpose.data.cache import cache_path, segments_for

    root, cache, cfg = _tiny_root(tmp_path / "root"), tmp_path / "cache", _smoke_data()
    first = segments_for(root, "keyframe", cfg, cache_dir=cache, workers=1, progress=False)
    path = cache_path(root, "keyframe", cfg, cache)
    _damage_npz(path, damage)
    with pytest.warns(UserWarning, match=rf"{path.name}: segment cache .*; making it again"):
        again = segments_for(root, "keyframe", cfg, cache_dir=cache, workers=1, progress=False)
    np.testing.assert_array_equal(again.points, first.points)
    np.testing.assert_array_equal(again.frame_id, first.frame_id)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # made whole again: read without a word
        segments_for(root, "keyframe", cfg, cache_dir=cache, workers=1, progress=False)


def test_a_truncated_test_cache_is_rebuilt_by_the_command(tmp_path):
    """Item 3 through the CLI: ``prepare`` (as ``run`` and ``evaluate`` read it) warns in one
    line naming the cache, makes it again and goes on."""
    root = _tiny_root(tmp_path / "root")
    assert cli("prepare", "--preset", "smoke", "--data", str(root), "--no-progress").exit_code == 0
    (test_cache,) = Path("data/cache").glob("root-test-*.npz")
    _cut(test_cache, 0.5)
    with pytest.warns(UserWarning, match=rf"{test_cache.name}: segment cache is unreadable"):
        res = cli("prepare", "--preset", "smoke", "--data", str(root), "--no-progress")
    assert res.exit_code == 0, res.output
    assert "Traceback" not in res.output
    from cloudpose.data.segment_set import SegmentSet

    SegmentSet.load(test_cache)  # whole again


@pytest.mark.parametrize("content", ["{", "[]", '{"x": [1, 2]}'])
def test_a_damaged_digest_memo_is_made_again_with_a_warning(tmp_path, content):
    from cloudpose.data.cache import DIGEST_MEMO, content_digests

    f = tmp_path / "a.txt"
    f.write_text("a")
    (tmp_path / DIGEST_MEMO).write_text(content)
    with pytest.warns(UserWarning, match=rf"{DIGEST_MEMO}: digest memo .*making it again"):
        digests = content_digests([f], tmp_path)
    assert content_digests([f], tmp_path) == digests
    assert json.loads((tmp_path / DIGEST_MEMO).read_text())[str(f.resolve())][2] == digests[0]


# --------------------------------------------------------------------------- 2, 13: chunks

N, K = 4, 16


def _chunk(n=N, k=K, seed=0):
    g = torch.Generator().manual_seed(seed)
    return (
        torch.rand(n, k, 3, generator=g),
        torch.arange(1, n + 1, dtype=torch.int64),
        torch.eye(3).repeat(n, 1, 1),
        torch.rand(n, 3, generator=g),
    )


@pytest.fixture
def store(tmp_path):
    from cloudpose.data.synth.chunks import ChunkStore, OnlineSettings

    return ChunkStore(tmp_path / "online", OnlineSettings(n_points=K), N)


def test_a_stored_chunk_reads_back(store):
    chunk = _chunk()
    store.save(3, 7, chunk)
    for a, b in zip(store.load(3, 7), chunk, strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize("damage", ["zero", "truncated", "garbled", "size", "points", "other"])
def test_a_damaged_or_misplaced_chunk_is_synthesized_again(store, damage):
    """Items 2 and 13: a zero-byte chunk raised EOFError ("Aborted."); a chunk of another
    size, or another chunk's file, was trained on silently."""
    path = store.path(3, 7)
    if damage in ("zero", "truncated", "garbled"):
        store.save(3, 7, _chunk())
        {"zero": lambda: path.write_bytes(b""), "truncated": lambda: _cut(path, 0.5)}.get(
            damage, lambda: _damage_npz(path, "garbled")
        )()
    elif damage == "size":
        store.save(3, 7, _chunk(n=N + 2))
    elif damage == "points":
        store.save(3, 7, _chunk(k=K * 2))
    else:  # chunk 8's file copied over chunk 7's
        store.save(3, 8, _chunk())
        shutil.copyfile(store.path(3, 8), path)
    with pytest.warns(UserWarning, match=rf"{path.name}: stored chunk .*; synthesizing it again"):
        assert store.load(3, 7) is None


# --------------------------------------------------------------------------- 10: synth.json


@pytest.mark.parametrize(
    "content", ["", '{\n  "generator": "cloudpose.data.synth",\n  "vers', "[1]"]
)
def test_a_damaged_synth_json_is_one_line_naming_it(tmp_path, content):
    """Item 10: "error: Expecting value: line 16 column 1", no file named."""
    root = tmp_path / "synth"
    root.mkdir()
    (root / "synth.json").write_text(content)
    res = cli("synth", "--out", str(root), "--train-frames", "0", "--test-frames", "0")
    line = one_line_error(res, str(root / "synth.json"))
    assert "delete the folder" in line and "restore the file" in line


# --------------------------------------------------------------------------- 11, 12: image sets


def test_a_frame_listed_twice_is_refused_naming_both_lines(tmp_path):
    """Item 11: a repeated frame counted twice in every metric."""
    root = _tiny_root(tmp_path / "root")
    (root / "keyframe.txt").write_text("0000/000002\n0000/000001\n\n0000/000002\n")
    res = cli("prepare", "--preset", "smoke", "--data", str(root), "--no-progress")
    one_line_error(
        res, str(root / "keyframe.txt"), "line 4", "0000/000002", "first on line 1", "twice"
    )


def test_an_image_set_with_a_byte_order_mark_reads(tmp_path):
    """Item 12: the BOM was read into the first frame id ("depth file of frame 0000/000001 not
    found", naming a file that exists)."""
    from cloudpose.data.cache import cache_key
    from cloudpose.data.ycb import YCBVideo

    root = _tiny_root(tmp_path / "root", test=("0000/000001", "0000/000002"))
    key = cache_key(root, "keyframe", _smoke_data())
    (root / "keyframe.txt").write_bytes(b"\xef\xbb\xbf0000/000001\r\n0000/000002\r\n")
    assert YCBVideo(root).image_set("keyframe") == ["0000/000001", "0000/000002"]
    assert cache_key(root, "keyframe", _smoke_data()) == key


def test_an_image_set_not_in_utf8_is_one_line(tmp_path):
    root = _tiny_root(tmp_path / "root")
    (root / "keyframe.txt").write_bytes("0000/000002\n".encode("utf-16"))
    res = cli("prepare", "--preset", "smoke", "--data", str(root), "--no-progress")
    one_line_error(res, str(root / "keyframe.txt"), "not UTF-8")


def test_a_class_list_with_a_byte_order_mark_reads(tmp_path):
    path = tmp_path / "classes.txt"
    path.write_bytes(b"\xef\xbb\xbf" + resource_path("classes.txt").read_bytes())
    assert load_classes(path) == load_classes(resource_path("classes.txt"))


# --------------------------------------------------------------------------- 14: instances.csv


def _record(tmp_path, csv: str | None, count: float | None = 3.0):
    from cloudpose.report.runs import RunRecord

    art = tmp_path / "artifacts"
    table = art / "eval" / "test" / "instances.csv"
    table.parent.mkdir(parents=True)
    if csv is not None:
        table.write_text(csv)
    metrics = {} if count is None else {"test/count": count}
    record = RunRecord("abc123", "shared-0", 1, "smoke", "d", "c", 0, {}, metrics, art.as_uri())
    return record, table


GOOD = (
    "frame_id,instance,cls_id,miss,net_ads\n"
    "0000/000001,0,1,False,0.01\n"
    "0000/000001,1,2,False,0.02\n"
    "0000/000002,0,1,True,inf\n"
)


def test_a_whole_instance_table_reads(tmp_path):
    record, _ = _record(tmp_path, GOOD)
    assert len(record.instances()) == 3


@pytest.mark.parametrize(
    "csv, problem",
    [
        ("", "is empty"),
        (GOOD[: len(GOOD) - 9], "cut short in its last row"),
        (GOOD.rsplit("0000/000002", 1)[0], "has 2 rows, where the run's metric test/count has 3"),
        ("frame_id,instance\n0000/000001,0\n", "lacks the columns"),
    ],
)
def test_a_damaged_instance_table_is_one_line_naming_it_and_the_run(tmp_path, csv, problem):
    """Item 14: a truncated table changed the report's tables (exit 0); an empty one gave
    "No columns to parse from file"."""
    record, table = _record(tmp_path, csv)
    with pytest.raises(CorruptFileError) as e:
        record.instances()
    message = str(e.value)
    assert message.startswith(f"{table}: instance table of run abc123 (shared-0 seed 1)")
    assert problem in message and "cloudpose evaluate --run abc123" in message


def test_the_real_frame_report_checks_its_tables_too(tmp_path):
    """``real-report`` read ``eval/real/instances.csv`` unchecked: a cut table gave "distances:
    expected values >= 0 or inf", an empty one "No columns to parse from file"."""
    from types import SimpleNamespace

    from cloudpose.report.real import _load

    table = tmp_path / "artifacts" / "eval" / "real" / "instances.csv"
    table.parent.mkdir(parents=True)
    run = SimpleNamespace(
        info=SimpleNamespace(run_id="abc123", artifact_uri=(tmp_path / "artifacts").as_uri()),
        data=SimpleNamespace(
            tags={"variant": "baseline-fpfh", "seed": "1", "preset": "smoke"},
            metrics={"real/count": 3.0},
        ),
    )
    assert _load(None, run, "fpfh", "real") is None  # no such evaluation: listed as missing
    table.write_text(GOOD)
    assert len(_load(None, run, "fpfh", "real").table) == 3
    table.write_text(GOOD[:-5])
    with pytest.raises(CorruptFileError, match="cut short") as e:
        _load(None, run, "fpfh", "real")
    assert str(e.value).startswith(f"{table}: instance table of run abc123 (baseline-fpfh seed 1)")
    assert "cloudpose baseline --method fpfh --preset smoke --seed 1 --split real --rerun" in str(
        e.value
    )
