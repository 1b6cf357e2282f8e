"""The on-line chunk store: chunks read back to the bit, keyed by all they depend on, written
atomically, and runs that read them train the numbers of runs that synthesize."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from cloudpose.data.synth import chunks as chunks_module
from cloudpose.data.synth.chunks import ChunkStore, OnlineSettings, store_settings
from cloudpose.data.synth.online import (
    OnlineChunks,
    OnlineStream,
    OnlineSynth,
    store_chunks,
)
from cloudpose.registry import resolve
from cloudpose.store import tracking
from cloudpose.suite.pipeline import train_run
from cloudpose.train.loop import ONLINE_STORE_ENV, online_chunks, online_store_root
from tests.conftest import make_project

KW = OnlineSettings(2, n_points=32)


def test_a_stored_chunk_reads_back_to_the_bit(tmp_path):
    chunk = OnlineSynth(KW).batch(3, 5, 4).tensors()
    store = ChunkStore(tmp_path, KW, 4)
    assert store.load(3, 5) is None
    store.save(3, 5, chunk)
    got = store.load(3, 5)
    assert got is not None
    for a, b in zip(got, chunk, strict=True):
        assert a.dtype == b.dtype and torch.equal(a, b)
    assert (store.folder / "settings.json").is_file()
    assert not list(store.folder.rglob(".*"))  # written under a temporary name, then renamed
    assert store.stored(3, 8) == 1 and store.stored(4, 8) == 0


def test_the_key_covers_what_a_chunk_depends_on(tmp_path, monkeypatch):
    from dataclasses import replace

    base = ChunkStore(tmp_path, KW, 4).key
    assert ChunkStore(tmp_path, replace(KW, n_points=64), 4).key != base
    assert ChunkStore(tmp_path, replace(KW, online_version=2), 4).key != base
    assert ChunkStore(tmp_path, replace(KW, class_ids=(3, 1, 2)), 4).key == (
        ChunkStore(tmp_path, replace(KW, class_ids=(1, 2, 3)), 4).key
    )
    assert ChunkStore(tmp_path, replace(KW, class_ids=(1, 2, 3)), 4).key != base
    # every setting is a field of the key, by its name (the version-3 settings once they are
    # set)
    later = {"online_bleed", "online_bleed_branch", "online_smooth", "online_noise_corr"}
    assert set(store_settings(KW, 4)["synth"]) == set(KW.__dataclass_fields__) - later
    bled = replace(
        KW,
        online_version=3,
        online_bleed=0.5,
        online_bleed_branch="translation",
        online_smooth=1.0,
        online_noise_corr=2.0,
    )
    assert set(store_settings(bled, 4)["synth"]) == set(KW.__dataclass_fields__)
    assert ChunkStore(tmp_path, bled, 4).key != (
        ChunkStore(tmp_path, replace(bled, online_bleed_branch="both"), 4).key
    )
    for name in later - {"online_bleed_branch"}:  # the branch: above
        off = {name: 0.0} | ({"online_bleed_branch": "both"} if name == "online_bleed" else {})
        assert (
            ChunkStore(tmp_path, bled, 4).key != ChunkStore(tmp_path, replace(bled, **off), 4).key
        )
    assert ChunkStore(tmp_path, KW, 8).key != base
    # the synthesis code: another source digest is another folder
    monkeypatch.setattr(chunks_module, "code_digest", lambda: "0" * 32)
    assert ChunkStore(tmp_path, KW, 4).key != base
    assert store_settings(KW, 4)["code"] == "0" * 32


def test_code_digest_follows_the_code_not_its_prose(tmp_path):
    (tmp_path / "a").mkdir()
    f = tmp_path / "a" / "m.py"

    def digest(text: str) -> str:
        f.write_text(text)
        return chunks_module._digest_code([f])

    base = digest('"""Module."""\n\ndef g(x):\n    """Twice x."""\n    return 2 * x\n')
    # prose: docstrings, comments, blank lines, formatting
    assert (
        digest('"""Other words."""\ndef g(x):  # why\n    """Doubled."""\n    return 2*x\n') == base
    )
    assert digest("def g(x):\n    return 2 * x\n") == base
    assert digest("def g(x):\n    return 3 * x\n") != base  # code
    assert digest('def g(x):\n    return "2 * x"\n') != base  # a string that is not a docstring


def test_code_digest_keeps_its_key_when_code_moves(tmp_path):
    """A restructuring keeps the chunk stores: an import moved into or out of a function, a
    definition moved to another module, modules renamed or reordered; what the code does
    (an alias, another library's function, a changed body) changes the key."""

    def digest(**modules: str) -> str:
        paths = []
        for name, text in modules.items():
            p = tmp_path / name / "m.py"  # one folder a call: nothing left from the last
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_text(text)
            paths.append(p)
        for q in tmp_path.rglob("*.py"):
            if q not in paths:
                q.unlink()
        return chunks_module._digest_code(paths)

    g = "def g(x):\n    return sqrt(x)\n"
    h = "def h(x):\n    return 2 * x\n"
    top = "from numpy import sqrt\nfrom cloudpose.data import k\n\n"
    base = digest(a=top + g + "\n" + h)
    inner = 'def g(x):\n    """Root."""\n    from numpy import sqrt\n\n    return sqrt(x)\n'
    assert digest(a="from cloudpose.data import k\n" + inner + h) == base  # import moved in
    # g moved to its own module, which the other imports it from (relatively)
    assert digest(a=top + h + "from .b import g\n", b="from numpy import sqrt\n" + g) == base
    assert digest(z=top + h + "\n" + g) == base  # renamed, reordered
    assert digest(a="from numpy import sqrt as sqrt\nfrom cloudpose.x import k\n" + g + h) == base
    assert digest(a=top.replace("numpy", "math") + g + h) != base  # another library's sqrt
    assert digest(a=top.replace("sqrt\n", "sqrt as s\n") + g + h) != base  # an alias
    assert digest(a=top + g + h.replace("2 *", "3 *")) != base  # a body
    assert digest(a=top + g) != base  # a definition gone


def test_code_digest_of_the_package():
    assert len(chunks_module.code_digest()) == 32
    sources = chunks_module._synthesis_sources(Path(chunks_module.__file__).resolve().parents[2])
    names = {p.name for p in sources}
    assert {"online.py", "sensor.py", "render.py", "segments.py"} <= names
    assert "chunks.py" not in names


def test_an_unreadable_chunk_is_made_again(tmp_path):
    chunks = OnlineChunks(KW, 1, 4, 3, store=tmp_path)
    ref = chunks[2]
    path = chunks.store.path(1, 2)
    path.write_bytes(b"not a zip")
    with pytest.warns(UserWarning, match="stored chunk is unreadable"):
        again = OnlineChunks(KW, 1, 4, 3, store=tmp_path)[2]
    for a, b in zip(again, ref, strict=True):
        assert torch.equal(a, b)
    assert chunks.store.load(1, 2) is not None  # replaced by a whole file


def test_a_stream_reads_stored_chunks_and_yields_the_same_batches(tmp_path, monkeypatch):
    args = {"seed": 1, "batch_size": 8, "reuse": 2, "total_steps": 4, "spacing": 2}
    ref = OnlineStream(KW, workers=0, **args)
    want = [ref.next() for _ in range(4)]
    made = store_chunks(KW, 1, 4, 4 + 2, tmp_path, workers=0, progress=False)
    assert made == 6
    assert store_chunks(KW, 1, 4, 4 + 2, tmp_path, workers=0, progress=False) == 0

    def no_synthesis(*a, **k):
        raise AssertionError("a stored chunk was synthesized again")

    monkeypatch.setattr(OnlineSynth, "batch", no_synthesis)
    for workers in (0, 1):
        stream = OnlineStream(KW, workers=workers, store=tmp_path, **args)
        for w in want:
            for a, b in zip(stream.next(), w, strict=True):
                assert torch.equal(a, b)
        stream.close()


def test_training_keeps_the_threads_its_synthesis_workers_leave(tmp_path):
    """A stream with workers trains on threads - workers (the count is part of the numbers);
    without workers (chunks read in process: ``cpu-online-4x-2t``) on every thread."""
    args = {"seed": 1, "batch_size": 8, "reuse": 2, "total_steps": 2, "spacing": 2}
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        for workers, training in ((1, 1), (0, 2), (3, 1)):
            stream = OnlineStream(KW, workers=workers, store=tmp_path, **args)
            assert torch.get_num_threads() == training, workers
            stream.close()
            assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_the_in_process_preset_reads_the_4x_chunks_as_another_run():
    names = [f"c{i}" for i in range(21)]
    four, both = (resolve("shared-0", p, seed=4) for p in ("cpu-online-4x", "cpu-online-4x-2t"))
    assert online_chunks(four, names) == online_chunks(both, names)
    assert (four.data.online_workers, both.data.online_workers) == (1, 0)
    assert four.train.threads == both.train.threads == 2
    assert four.fingerprint() != both.fingerprint()


def test_store_root_follows_the_environment(tmp_path, monkeypatch):
    monkeypatch.delenv(ONLINE_STORE_ENV, raising=False)
    assert online_store_root(tmp_path) == tmp_path / "data" / "cache" / "online"
    monkeypatch.setenv(ONLINE_STORE_ENV, "0")
    assert online_store_root(tmp_path) is None
    monkeypatch.setenv(ONLINE_STORE_ENV, str(tmp_path / "elsewhere"))
    assert online_store_root(tmp_path) == tmp_path / "elsewhere"


def test_variants_of_a_preset_share_their_chunks():
    names = [f"c{i}" for i in range(21)]
    got = [online_chunks(resolve(v, "cpu-online"), names) for v in ("shared-0", "shared-all", "l2")]
    assert got[0] == got[1] == got[2]
    _, chunk_size, n_chunks = got[0]
    assert chunk_size == 8 and n_chunks > 4096  # the default: batch 32, each segment in 4 steps


@pytest.mark.slow
def test_a_run_that_reads_the_store_trains_the_same_numbers(tmp_path, smoke_data, monkeypatch):
    overrides = {
        "data": {"train_source": "online", "online_epoch_segments": 64, "online_reuse": 4},
        "train": {"augment_roll_deg": 15.0},
    }
    cfg = resolve("shared-0", "smoke", seed=2, overrides=overrides)
    monkeypatch.setenv(ONLINE_STORE_ENV, "0")
    plain = train_run(cfg, project_dir=make_project(tmp_path / "plain", smoke_data, monkeypatch))
    store = tmp_path / "store"
    monkeypatch.setenv(ONLINE_STORE_ENV, str(store))
    filling = train_run(cfg, project_dir=make_project(tmp_path / "a", smoke_data, monkeypatch))
    assert any(store.rglob("chunk-*.npz"))
    monkeypatch.setattr(OnlineSynth, "batch", lambda *a, **k: pytest.fail("synthesized again"))
    project_b = make_project(tmp_path / "b", smoke_data, monkeypatch)
    reading = train_run(cfg, project_dir=project_b)
    params = tracking.setup(project_b).get_run(reading.run_id).data.params
    assert params["data.online_code"] == chunks_module.code_digest()  # what made its segments
    assert filling.metrics == plain.metrics
    assert reading.metrics == plain.metrics
    w = [torch.load(r.checkpoint, weights_only=True)["model"] for r in (plain, reading)]
    for k in w[0]:
        assert torch.equal(w[0][k], w[1][k]), k
    assert np.isfinite(plain.metrics["train/loss"])


def test_prepare_fills_the_store_for_seeds(tmp_path, smoke_data, monkeypatch):
    from typer.testing import CliRunner

    from cloudpose.cli import app

    project = make_project(tmp_path / "p", smoke_data, monkeypatch)
    monkeypatch.chdir(project)
    monkeypatch.delenv(ONLINE_STORE_ENV, raising=False)
    base = ["prepare", "--preset", "smoke", "--no-progress", "--workers", "0"]
    online = [
        "--set", 'data.train_source="online"', "--set", "data.online_epoch_segments=16",
        "--set", "data.online_reuse=1", "--set", "train.epochs=1", "--set", "train.batch_size=8",
    ]  # fmt: skip
    res = CliRunner().invoke(app, [*base, *online, "--seeds", "2"])
    assert res.exit_code == 0, res.output
    cfg = resolve("shared-0", "smoke", seed=1, overrides={
        "data": {"train_source": "online", "online_epoch_segments": 16, "online_reuse": 1},
        "train": {"epochs": 1, "batch_size": 8},
    })  # fmt: skip
    from cloudpose.conventions import packaged_classes

    kw, size, n = online_chunks(cfg, packaged_classes())
    assert (size, n) == (8, 2)  # 2 steps, each segment used once
    store = ChunkStore(online_store_root(project), kw, size)
    assert store.stored(1, n) == n and store.stored(2, n) == n and store.stored(3, n) == 0
    assert f"seed 2: {n} chunks of {size} segments ({n} made)" in res.output
    res = CliRunner().invoke(app, [*base, "--seeds", "1"])
    assert res.exit_code != 0 and "only an on-line preset" in res.output


def test_a_chunk_that_cannot_be_written_warns_and_training_goes_on(tmp_path):
    blocked = tmp_path / "file"
    blocked.write_text("a file where the store's folder would go")
    chunks = OnlineChunks(KW, 1, 4, 2, store=blocked)
    with pytest.warns(UserWarning, match="chunk not stored"):
        got = chunks[0]
    for a, b in zip(got, OnlineSynth(KW).batch(1, 0, 4).tensors(), strict=True):
        assert torch.equal(a, b)
